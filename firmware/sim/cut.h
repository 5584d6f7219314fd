/* The hardware cut for the simavr harness (cut.c; firmware/hardware/README.md "The cut"):
 * U10 eFuse in the wire supply, EN = NOR(D8, TRIP); the latch U8 set by the LM339 comparators
 * (shunt > ELEC_TRIP_SINK_MA, supply > ELEC_TRIP_SUPPLY_MA, e-stop, watchdog pump low) and
 * cleared by a D4 LOW pulse while no cause holds it; D5 = EN and D6 = TRIP read back. Faults:
 * a shorted MOSFET, the wire's low end shorted to ground, a hung main loop. */
#ifndef SMA_SIM_CUT_H
#define SMA_SIM_CUT_H
#include <stdio.h>

#include "sim_avr.h"

enum cut_fault { CUT_FAULT_NONE = 0, CUT_FAULT_MOSFET = 1, CUT_FAULT_GROUND = 2, CUT_FAULT_HANG = 3 };
enum cut_cause { CUT_CAUSE_NONE = 0, CUT_CAUSE_SINK = 1, CUT_CAUSE_SUPPLY = 2, CUT_CAUSE_ESTOP = 3,
                 CUT_CAUSE_WATCHDOG = 4, CUT_CAUSE_POWER_ON = 5 };

/* Hook D4 and D7 (port D IRQs); t_now returns the harness's AVR time in seconds. */
void cut_attach(avr_t *avr, double (*t_now)(void));
/* The wire current for this model step, given the sink's (setpoint-following) current and the
 * MCU's enable line (D8 driven low); applies the comparators and the latch. Returns the current
 * through the wire (the supply current) and sets *shunt_a (what the shunt, ADC0 and the
 * ADS1115 see) and *closed (the switch conducts). */
double cut_step(double t_s, double sink_a, int d8_enable, int estop, double supply_v, double wire_ohm,
                double *shunt_a, int *closed);
/* Drive D5/D6 (and D2, the e-stop) from the present state. */
void cut_drive_pins(int estop);
int cut_fault(void);
/* FAULT NONE|MOSFET|GROUND|HANG; returns 1 when the command was ours. */
int cut_command(const char *cmd, const char *arg, double t_s);
/* The MCU was reset: its pins are inputs again, a hang ends. */
void cut_mcu_reset(void);
/* Extra STATE fields, numbers only. */
void cut_state(FILE *f);
#endif
