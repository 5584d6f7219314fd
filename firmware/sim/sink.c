/* The reference linear current sink for the simavr harness (sink.h; firmware/hardware/sink.py).
 * The analog loop (op-amp, MOSFET, shunt) is far faster than the firmware, so the wire current is
 * the setpoint PWM after the two RC poles of its filter (exact zero-order-hold steps), clamped to
 * zero while the enable line holds the setpoint down, and limited by the compliance
 * (V_supply - V_DS,min) / (R_source + R_wire + R_shunt). */
#include <math.h>

#include "electrical.h"
#include "sink.h"

static double supply_v = ELEC_SUPPLY_NOMINAL_MV / 1000.0;
static double pole1_a, pole2_a, last_t = -1.0;

void sink_set_supply(double volts) { supply_v = volts; }
double sink_supply(void) { return supply_v; }

void sink_reset(void)
{
    pole1_a = pole2_a = 0.0;
}

sink_out_t sink_update(double t_s, double duty_counts, int enabled, double wire_ohm, int wire_open)
{
    const double tau = ELEC_SETPOINT_FILTER_TAU_US * 1e-6;
    const double rsh = ELEC_SHUNT_MOHM * 1e-3, rsrc = ELEC_SOURCE_MOHM * 1e-3;
    double dt = last_t < 0.0 ? 0.0 : t_s - last_t;
    if (dt < 0.0)
        dt = 0.0; /* the harness restarted its clock */
    last_t = t_s;
    double target = (duty_counts > 0.0 ? duty_counts : 0.0) * ELEC_SETPOINT_UA_PER_COUNT_Q8 / 256.0 * 1e-6;
    double k = exp(-dt / tau), p1 = pole1_a;
    pole1_a = target + (p1 - target) * k;
    pole2_a = target + (pole2_a - target) * k + (p1 - target) * (dt / tau) * k;
    sink_out_t o;
    double i = enabled ? (pole2_a > 0.0 ? pole2_a : 0.0) : 0.0;
    double compliance = wire_open ? 0.0
                                  : (supply_v - ELEC_MOSFET_VDS_MIN_MV * 1e-3) / (rsrc + wire_ohm + rsh);
    if (compliance < 0.0)
        compliance = 0.0;
    if (i > compliance)
        i = compliance;
    o.current_a = i;
    o.supply_v = supply_v - i * rsrc;
    o.wire_v = wire_open ? o.supply_v : i * wire_ohm;
    double a_per_count = ELEC_CURRENT_ADC_UA_PER_COUNT_Q8 / 256.0 * 1e-6;
    o.adc0_mv = i / a_per_count / 1024.0 * ELEC_ADC_REF_MV;
    o.adc1_mv = o.supply_v * 1000.0 * ELEC_SUPPLY_MONITOR_DIV_Q16 / 65536.0;
    return o;
}
