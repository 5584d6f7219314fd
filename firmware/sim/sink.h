/* The reference linear current sink for the simavr harness (sink.c): a C port of
 * firmware/hardware/sink.py with the numbers of electrical.h. */
#ifndef SMA_SIM_SINK_H
#define SMA_SIM_SINK_H

typedef struct {
    double current_a;   /* wire current */
    double wire_v;      /* across the wire (open wire: the supply) */
    double supply_v;    /* at the driver's terminals (after the source resistance) */
    double adc0_mv;     /* shunt amplifier output at ADC0 */
    double adc1_mv;     /* supply monitor divider at ADC1 */
} sink_out_t;

/* Advance the sink to time t_s (AVR time, s) with the setpoint PWM at duty_counts (0 ... 1023)
 * held since the previous call, the enable line (1: released) and the wire; returns the outputs. */
sink_out_t sink_update(double t_s, double duty_counts, int enabled, double wire_ohm, int wire_open);
/* Wire supply at no load, V (default: the nominal supply of electrical.h). */
void sink_set_supply(double volts);
double sink_supply(void);
/* Forget the filter state (MCU reset: the pin went low). */
void sink_reset(void);
#endif
