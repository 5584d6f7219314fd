/* The hardware cut for the simavr harness (cut.h). Numbers from electrical.h and the netlist
 * (firmware/hardware/bench.cir, README.md "The cut"):
 *   comparators U7A/U7B (LM339): response time 1.3 us typ (TI LM339 datasheet, 100 mV step, 5 mV
 *     overdrive) behind 1 us input RC filters; U10 (TPS25940L) EN turn-off ~2 us (the netlist
 *     model's figure): both far below the harness's model step (<= 100 us), so a fault that
 *     crosses a threshold opens the switch within the step that sees it;
 *   watchdog pump: each D7 edge moves CW2 halfway to its pumped level (3.6 V at 500 Hz), which
 *     decays with (RW1 + RW2) * CW2 = 22 ms; U7D trips below 2 x 0.816 V = 1.63 V: 17.4 ms after
 *     the last edge (ngspice: 17.6 ms stuck low, 28.2 ms stuck high, 31.7 ms slow corner);
 *   a MOSFET short: the current is V_supply / (loop + wire), no longer the setpoint's; the wire's
 *     low end to ground: the same through the supply, none through the shunt.
 * A hang: the main loop is sent to an endless `rjmp .` written into unused flash below the
 * bootloader, interrupts enabled; they (the 1 ms tick, the UART, the AVR's own watchdog) go on. */
#include <math.h>
#include <string.h>

#include "avr_ioport.h"
#include "cut.h"
#include "electrical.h"
#include "sim_core.h"
#include "sim_irq.h"

#define PUMP_V 3.6
#define PUMP_TRIP_V (2.0 * ELEC_REFERENCE_MV * 1e-3 * 10.0 / 50.2) /* R54/R55 from VREF, RW1/RW2 */
#define PUMP_TAU_S (99.8e3 * 220e-9)                                  /* (RW1 + RW2) * CW2 */
#define HANG_ADDR 0x7DFCu /* byte address of `rjmp .` (0xCFFF): free flash below optiboot */
#define A_PIND 0x29 /* ATmega328P data-space addresses */
#define A_DDRD 0x2A

static avr_t *avr;
static double (*now_s)(void);
static int latch = 1; /* power-on: the pump is empty, U7D holds the latch set */
static double pump_v, pump_t;
static int fault;
static int cause;
static int closed, d8_last, estop_last;
static double fault_ms = -1.0, trip_ms = -1.0, off_ms = -1.0;
static int d8_at_trip = -1;
static unsigned feeds, clears;
static avr_irq_t *pin_irq[8];
static int en_driven = -1, latch_driven = -1, estop_driven = -1; /* what D2/D5/D6 show */
static uint8_t pins_driven;

static void pump_decay(double t)
{
    if (t > pump_t) {
        pump_v *= exp(-(t - pump_t) / PUMP_TAU_S);
        pump_t = t;
    }
}

static void set_latch(double t_s, int why)
{
    if (!latch) {
        latch = 1;
        cause = why;
        trip_ms = t_s * 1e3;
        d8_at_trip = d8_last; /* 1: the MCU still enabled: the cut, not the MCU, opened it */
    }
}

void cut_drive_pins(int estop)
{
    int en = d8_last && !latch;
    uint8_t value = (uint8_t)((estop ? 1u << 2 : 0u) | (en ? 1u << 5 : 0u) | (latch ? 1u << 6 : 0u));
    avr_ioport_external_t ext = {.name = 'D', .mask = (1u << 2) | (1u << 5) | (1u << 6), .value = value};
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('D'), &ext);
    en_driven = en;
    latch_driven = latch;
    estop_driven = estop;
    pins_driven = value & 0x64u;
    avr_raise_irq(pin_irq[2], (uint32_t)(estop ? 1 : 0));
    avr_raise_irq(pin_irq[5], (uint32_t)en);
    avr_raise_irq(pin_irq[6], (uint32_t)latch);
    /* simavr filters a raise that repeats the IRQ's last value, and a reset clears PIND behind
     * the IRQs' back: set the input bits themselves too */
    uint8_t inputs = (uint8_t)(~avr->data[A_DDRD] & 0x64u);
    avr->data[A_PIND] = (uint8_t)((avr->data[A_PIND] & ~inputs) | (value & inputs));
}

static void d7_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    double t = now_s();
    pump_decay(t);
    pump_v += (PUMP_V - pump_v) * 0.5;
    feeds++;
}

/* D4 LOW: /CLR. /PRE (any comparator) dominates: the latch clears only when none holds it. */
static void d4_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    /* only a driven LOW: at reset D4 is an input and R49 pulls it up (simavr may report 0) */
    if (value || !(avr->data[A_DDRD] & (1u << 4)))
        return;
    clears++;
    double t = now_s();
    pump_decay(t);
    if (latch && !estop_last && pump_v >= PUMP_TRIP_V && !closed) {
        latch = 0;
        cause = CUT_CAUSE_NONE;
    }
    cut_drive_pins(estop_last);
}

void cut_attach(avr_t *a, double (*t_now)(void))
{
    avr = a;
    now_s = t_now;
    for (int i = 0; i < 8; i++)
        pin_irq[i] = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), i);
    avr_irq_register_notify(pin_irq[7], d7_cb, NULL);
    avr_irq_register_notify(pin_irq[4], d4_cb, NULL);
    cause = CUT_CAUSE_POWER_ON;
}

double cut_step(double t_s, double sink_a, int d8_enable, int estop, double supply_v, double wire_ohm,
                double *shunt_a, int *closed_out)
{
    pump_decay(t_s);
    d8_last = d8_enable;
    estop_last = estop;
    double loop = (ELEC_SOURCE_MOHM + ELEC_SHUNT_MOHM) * 1e-3; /* source incl. U10, shunt */
    double wire_a = 0.0, through_shunt = 0.0;
    int on = d8_enable && !latch;
    if (on) {
        if (fault == CUT_FAULT_MOSFET) {
            wire_a = through_shunt = supply_v / (loop + wire_ohm);
        } else if (fault == CUT_FAULT_GROUND) {
            wire_a = supply_v / (loop - ELEC_SHUNT_MOHM * 1e-3 + wire_ohm);
        } else {
            wire_a = through_shunt = sink_a;
        }
    }
    /* the comparators (wired-OR on /PRE) */
    if (on && through_shunt * 1e3 > ELEC_TRIP_SINK_MA)
        set_latch(t_s, CUT_CAUSE_SINK);
    else if (on && wire_a * 1e3 > ELEC_TRIP_SUPPLY_MA)
        set_latch(t_s, CUT_CAUSE_SUPPLY);
    else if (estop)
        set_latch(t_s, CUT_CAUSE_ESTOP);
    else if (pump_v < PUMP_TRIP_V)
        set_latch(t_s, CUT_CAUSE_WATCHDOG);
    if (latch)
        on = 0;
    if (!on)
        wire_a = through_shunt = 0.0;
    if (fault_ms >= 0.0 && off_ms < 0.0 && wire_a < 0.02 && t_s * 1e3 >= fault_ms)
        off_ms = t_s * 1e3;
    closed = on;
    int en = d8_enable && !latch;
    if (en != en_driven || latch != latch_driven || estop != estop_driven ||
        (avr->data[A_PIND] & ~avr->data[A_DDRD] & 0x64u) != (pins_driven & ~avr->data[A_DDRD]))
        cut_drive_pins(estop); /* also when the port lost them (its writes at the MCU's init) */
    *shunt_a = through_shunt;
    *closed_out = on;
    return wire_a;
}

int cut_fault(void) { return fault; }

static void hang(void)
{
    avr->flash[HANG_ADDR] = 0xFF; /* rjmp . = 0xCFFF, little-endian */
    avr->flash[HANG_ADDR + 1] = 0xCF;
    avr->pc = HANG_ADDR;
    if (avr->state == cpu_Sleeping)
        avr->state = cpu_Running;
    /* the main loop hangs with interrupts on (the tick, the UART and the AVR's own watchdog go
     * on), wherever it was sent from (inside cli/sei or an ISR). With interrupts off the AVR's
     * watchdog in interrupt-then-reset mode would never reach its reset stage (its interrupt
     * must run first: ATmega328P datasheet, WDTCSR), and only the external watchdog would act */
    avr_sreg_set(avr, S_I, 1);
}

int cut_command(const char *cmd, const char *arg, double t_s)
{
    if (strcmp(cmd, "FAULT"))
        return 0;
    int f = !arg ? -1
            : !strcmp(arg, "NONE") ? CUT_FAULT_NONE
            : !strcmp(arg, "MOSFET") ? CUT_FAULT_MOSFET
            : !strcmp(arg, "GROUND") ? CUT_FAULT_GROUND
            : !strcmp(arg, "HANG") ? CUT_FAULT_HANG : -1;
    if (f < 0) {
        fprintf(stderr, "smabench-sim: FAULT takes NONE, MOSFET, GROUND or HANG\n");
        return 1;
    }
    if (f == CUT_FAULT_HANG && fault == CUT_FAULT_HANG)
        return 1;
    fault = f;
    if (f != CUT_FAULT_NONE) {
        fault_ms = t_s * 1e3;
        trip_ms = off_ms = -1.0;
        d8_at_trip = -1;
    }
    if (f == CUT_FAULT_HANG)
        hang();
    return 1;
}

void cut_mcu_reset(void)
{
    if (fault == CUT_FAULT_HANG)
        fault = CUT_FAULT_NONE; /* the reset restarts the program: the hang is over */
    d8_last = 0;
    cut_drive_pins(estop_last); /* the reset cleared the port's external state: D2, D5, D6 again */
}

void cut_state(FILE *f)
{
    fprintf(f, " cut_closed=%d cut_trip=%d cut_cause=%d pump_v=%.3f fault=%d fault_ms=%.3f"
               " trip_ms=%.3f off_ms=%.3f d8_at_trip=%d cut_feeds=%u cut_clears=%u pind=%u ddrd=%u portd=%u",
            closed, latch, cause, pump_v, fault, fault_ms, trip_ms, off_ms, d8_at_trip, feeds,
            clears, avr->data[A_PIND], avr->data[A_DDRD], avr->data[A_PIND + 2]);
}
