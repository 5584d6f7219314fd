/* smabench-sim: runs the current-driver firmware (.elf, ATmega328P at 16 MHz) in simavr, in real
 * time, with UART0 bridged to a pseudo-terminal and a simple electrical model of the SMA wire
 * feeding the ADC. See firmware/sim/README.md.
 *
 *   smabench-sim [--report] [--r-ohm R] [--ambient C] [--trace-io FILE] [-v] firmware.elf
 *
 * stdout: first line "PTY <slave path>", then STATE lines (command Q, or every 100 ms with
 * --report). stdin: control commands, one per line (R <ohms>, A <celsius>, OPEN, CLOSE, Q).
 * Ends on SIGTERM/SIGINT/SIGHUP or when stdin reaches EOF. simavr's own messages go to stderr.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_timer.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_cycle_timers.h"
#include "sim_elf.h"
#include "sim_irq.h"

#include "boot.h" /* --bootloader: the Arduino bootloader and auto-reset */
#include "periph.h" /* ADS1115, MAX31855, e-stop, NTC faults (periph.c) */
#include "cut.h"    /* the hardware cut: eFuse, comparators, latch, watchdog pump (cut.c) */
#include "electrical.h"
#include "sink.h"     /* the reference linear current sink (sink.c) */

/* static inline helpers for the UART input FIFO declared in avr_uart.h (read-only use here) */
DEFINE_FIFO(uint16_t, uart_fifo);

#define F_CPU 16000000u
/* ATmega328P data-space addresses */
#define A_MCUSR 0x54
#define A_DDRB 0x24
#define A_PORTB 0x25
#define A_TCCR1A 0x80
#define A_OCR1AL 0x88
#define A_OCR1AH 0x89
#define BIT_PB1 0x02
#define BIT_COM1A1 0x80
#define PWM_TOP 1023.0

/* Electrical model (README.md) */
#define ADC_VREF_MV 5000.0

static avr_t *avr;
static volatile sig_atomic_t stop_signal;
static int verbose;
static FILE *ctl; /* the real stdout; fd 1 itself is redirected to stderr */

/* model state */
static double r_ohm = 0.44; /* the bench wire: 55 mm of 0.38 mm Flexinol */
static double ambient_c = 22.0;
static int wire_open;
static double duty_now = -1.0;
static double current_now;
static int model_dirty = 1;
static avr_irq_t *adc_irq;

/* PWM IRQ (timer '1', TIMER_IRQ_OUT_PWM0 carries OCR1A) */
static uint32_t pwm_irq_value, pwm_irq_count;

/* UART bridge */
static avr_uart_t *uart0;
static avr_irq_t *uart_irq;
static int xoff;
static uint8_t rxq[4096];
static size_t rxq_head, rxq_tail; /* bytes from the pty waiting to enter the AVR */
static uint8_t txq[65536];
static size_t txq_len;            /* bytes from the AVR waiting to be written to the pty */
static unsigned long tx_dropped, rx_bytes, tx_bytes;
static int pty_master = -1, pty_slave = -1;
static FILE *trace_io; /* --trace-io: pty bytes, stalls and slips with wall and AVR times */

/* time */
static uint64_t total_cycles, last_cycle;
static unsigned resets, resets_seen, resets_reported;
static uint8_t reset_mcusr;

static uint64_t now_ns(void);

/* One --trace-io line: event, CLOCK_MONOTONIC µs (the host's time.monotonic() × 1e6), AVR µs,
 * value (bytes, or the stall / slip in µs). */
static void trace_event(const char *what, double value)
{
    if (trace_io)
        fprintf(trace_io, "%s %.0f %.0f %.0f\n", what, now_ns() / 1e3,
                total_cycles / (F_CPU / 1e6), value);
}

/* ------------------------------------------------------------------ logging */
static void log_to_stderr(avr_t *a, const int level, const char *fmt, va_list ap)
{
    (void)a;
    if (level <= LOG_ERROR || verbose)
        vfprintf(stderr, fmt, ap);
}

static void die(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fputs("smabench-sim: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(2);
}

/* ------------------------------------------------------------------ electrical model */
static double read_duty(void)
{
    const uint8_t *d = avr->data;
    if (!(d[A_DDRB] & BIT_PB1))
        return 0.0; /* PB1 is an input: gate pulled down */
    if (d[A_TCCR1A] & BIT_COM1A1) {
        unsigned ocr = (unsigned)d[A_OCR1AL] | ((unsigned)d[A_OCR1AH] << 8);
        if (ocr > 1023u)
            ocr = 1023u;
        return ocr / PWM_TOP;
    }
    return (d[A_PORTB] & BIT_PB1) ? 1.0 : 0.0; /* OC1A disconnected: the port bit drives the pin */
}

static uint32_t clamp_mv(double mv)
{
    if (mv < 0.0)
        return 0;
    if (mv > avr->avcc)
        return avr->avcc;
    return (uint32_t)lround(mv);
}

static double ntc_mv(double celsius)
{
    double t = celsius + 273.15;
    double r_ntc = ELEC_NTC_R25_OHM * exp(ELEC_NTC_BETA_K * (1.0 / t - 1.0 / 298.15));
    return avr->avcc * ELEC_NTC_FIXED_OHM / (r_ntc + ELEC_NTC_FIXED_OHM); /* from AVcc */
}

/* AVR time now, s (the harness's clock: it keeps counting across resets) */
static double avr_now_s(void)
{
    uint64_t now = total_cycles + (avr->cycle >= last_cycle ? avr->cycle - last_cycle : avr->cycle);
    return (double)now / F_CPU;
}

/* Recompute the ADC inputs when the duty or the model changed (force: always). */
static void model_update(int force)
{
    double duty = read_duty();
    (void)force; /* the sink's filter moves with time: always recomputed */
    if (verbose && duty != duty_now)
        fprintf(stderr, "smabench-sim: t=%.3f ms duty %.4f (PWM0 irq %u x%u)\n",
                total_cycles / (F_CPU / 1000.0), duty, pwm_irq_value, pwm_irq_count);
    duty_now = duty;
    model_dirty = 0;
    /* the reference linear sink (sink.c): D8 driven low releases the setpoint */
    const uint8_t *d = avr->data;
    int enabled = (d[A_DDRB] & 0x01) && !(d[A_PORTB] & 0x01);
    double t_s = avr_now_s();
    sink_out_t o = sink_update(t_s, duty * PWM_TOP, enabled, r_ohm, wire_open);
    /* the cut (cut.c) decides what flows: the sink's current, a fault's, or nothing */
    double shunt_a;
    int closed;
    double wire_a = cut_step(t_s, o.current_a, enabled, periph_estop(), sink_supply(), r_ohm,
                             &shunt_a, &closed);
    if (!closed)
        sink_reset(); /* CLAMP (Q2) holds the setpoint at 0 while the cut is open */
    current_now = wire_a;
    double supply_v = sink_supply() - wire_a * ELEC_SOURCE_MOHM * 1e-3;
    periph_set_wire(shunt_a, wire_open && closed ? supply_v : wire_a * r_ohm);
    double a_per_count = ELEC_CURRENT_ADC_UA_PER_COUNT_Q8 / 256.0 * 1e-6;
    avr_raise_irq(adc_irq + ADC_IRQ_ADC0, clamp_mv(shunt_a / a_per_count / 1024.0 * ELEC_ADC_REF_MV));
    /* A1: the switched supply after U10 */
    avr_raise_irq(adc_irq + ADC_IRQ_ADC1,
                  clamp_mv(closed ? supply_v * 1000.0 * ELEC_SUPPLY_MONITOR_DIV_Q16 / 65536.0 : 0.0));
    avr_raise_irq(adc_irq + ADC_IRQ_ADC2, clamp_mv(periph_ntc_mv(ntc_mv(ambient_c))));
    avr_raise_irq(adc_irq + ADC_IRQ_ADC3, clamp_mv(ELEC_REFERENCE_MV)); /* REF3040 */
    (void)o;
}

static void pwm_irq_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    pwm_irq_value = value;
    pwm_irq_count++;
    model_dirty = 1;
}

/* Each ADC conversion start: make the inputs reflect the pin state right now. */
static void adc_trigger_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    model_update(0);
}

/* ------------------------------------------------------------------ UART bridge */
static void uart_out_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (txq_len < sizeof txq)
        txq[txq_len++] = boot_enabled() ? boot_line_tx(avr, (uint8_t)value) : (uint8_t)value;
    else
        tx_dropped++;
    tx_bytes++;
}

static void uart_xon_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    xoff = 0;
}

static void uart_xoff_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    xoff = value ? 1 : 0;
}

static avr_cycle_count_t uart_cycles_per_byte(void)
{
    /* simavr sets this from UBRR (it counts start + 8 data + parity + stop = 11 bits); fall back to
     * 10 bits at 115200 baud before the firmware configured the UART. */
    if (uart0 && uart0->cycles_per_byte > 100)
        return uart0->cycles_per_byte;
    return F_CPU / 11520u;
}

/* Cycle-timer pump: one byte from the pty into UART0 per byte time, never into a full FIFO. */
static avr_cycle_count_t rx_pump(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a;
    (void)param;
    if (rxq_head == rxq_tail)
        return 0; /* queue empty: stop; restarted when bytes arrive */
    int full = xoff || (uart0 && uart_fifo_isfull(&uart0->input));
    if (!full) {
        uint8_t b = rxq[rxq_tail];
        rxq_tail = (rxq_tail + 1) % sizeof rxq;
        avr_raise_irq(uart_irq + UART_IRQ_INPUT, b);
        rx_bytes++;
    }
    return when + uart_cycles_per_byte();
}

static void rx_pump_kick(void)
{
    if (rxq_head != rxq_tail && avr_cycle_timer_status(avr, rx_pump, NULL) == 0)
        avr_cycle_timer_register(avr, 1, rx_pump, NULL);
}

static size_t rxq_free(void) { return sizeof rxq - 1 - (rxq_head + sizeof rxq - rxq_tail) % sizeof rxq; }

static void pty_read(void)
{
    uint8_t buf[512];
    size_t room = rxq_free();
    if (room == 0)
        return;
    if (room > sizeof buf)
        room = sizeof buf;
    ssize_t n = read(pty_master, buf, room);
    if (n > 0 && boot_enabled())
        boot_line_rx(avr, pty_master, buf, (size_t)n); /* wrong baud rate: corrupted */
    for (ssize_t k = 0; k < n; k++) {
        rxq[rxq_head] = buf[k];
        rxq_head = (rxq_head + 1) % sizeof rxq;
    }
    if (n > 0) {
        trace_event("rx", (double)n);
        rx_pump_kick();
    }
}

static void pty_flush(void)
{
    if (!txq_len)
        return;
    ssize_t n = write(pty_master, txq, txq_len);
    if (n > 0) {
        trace_event("tx", (double)n);
        memmove(txq, txq + n, txq_len - (size_t)n);
        txq_len -= (size_t)n;
    } else if (n < 0 && errno != EAGAIN && errno != EINTR) {
        tx_dropped += txq_len; /* nobody can read it */
        txq_len = 0;
    }
}

/* ------------------------------------------------------------------ control channel */
static void print_state(void)
{
    fprintf(ctl, "STATE t_ms=%.3f duty=%.4f current_a=%.4f r_ohm=%.4f supply_v=%.3f",
            total_cycles / (F_CPU / 1000.0), duty_now < 0 ? 0.0 : duty_now, current_now, r_ohm,
            sink_supply());
    periph_state(ctl);
    cut_state(ctl);
    fprintf(ctl, " avcc_v=%.3f", avr->avcc / 1000.0);
    fputc('\n', ctl);
    fflush(ctl);
}

static void control_line(char *line)
{
    char *cmd = strtok(line, " \t\r\n");
    char *arg = strtok(NULL, " \t\r\n");
    char *end;
    if (!cmd)
        return;
    if (!strcmp(cmd, "Q")) {
        model_update(0);
        print_state();
    } else if (!strcmp(cmd, "R") && arg) {
        double v = strtod(arg, &end);
        if (*end || !(v > 0.0) || !isfinite(v)) {
            fprintf(stderr, "smabench-sim: bad resistance '%s'\n", arg);
            return;
        }
        r_ohm = v;
        wire_open = 0;
        model_update(1);
    } else if (!strcmp(cmd, "A") && arg) {
        double v = strtod(arg, &end);
        if (*end || !isfinite(v) || v < -50.0 || v > 150.0) {
            fprintf(stderr, "smabench-sim: bad ambient '%s'\n", arg);
            return;
        }
        ambient_c = v;
        model_update(1);
    } else if (!strcmp(cmd, "OPEN")) {
        wire_open = 1;
        model_update(1);
    } else if (!strcmp(cmd, "CLOSE")) {
        wire_open = 0;
        model_update(1);
    } else if (!strcmp(cmd, "V") && arg) {
        double v = strtod(arg, &end);
        if (*end || !isfinite(v) || v < 0.0 || v > 30.0) {
            fprintf(stderr, "smabench-sim: bad supply '%s'\n", arg);
            return;
        }
        sink_set_supply(v);
        model_update(1);
    } else if (!strcmp(cmd, "AVCC") && arg) {
        double v = strtod(arg, &end);
        if (*end || !isfinite(v) || v < 4.0 || v > 5.5) {
            fprintf(stderr, "smabench-sim: bad AVcc '%s' (4.0 ... 5.5 V)\n", arg);
            return;
        }
        avr->avcc = avr->aref = (uint32_t)lround(v * 1000.0);
        model_update(1);
    } else if (cut_command(cmd, arg, avr_now_s())) {
        model_update(1);
    } else if (periph_command(cmd, arg)) {
        model_update(1);
    } else {
        fprintf(stderr, "smabench-sim: unknown command '%s'\n", cmd);
    }
}

static char ctl_buf[1024];
static size_t ctl_len;

/* returns 0 on EOF */
static int stdin_read(void)
{
    ssize_t n = read(0, ctl_buf + ctl_len, sizeof ctl_buf - 1 - ctl_len);
    if (n == 0)
        return 0;
    if (n < 0)
        return (errno == EAGAIN || errno == EINTR) ? 1 : 0;
    ctl_len += (size_t)n;
    char *nl;
    while ((nl = memchr(ctl_buf, '\n', ctl_len)) != NULL) {
        *nl = 0;
        control_line(ctl_buf);
        size_t used = (size_t)(nl - ctl_buf) + 1;
        memmove(ctl_buf, ctl_buf + used, ctl_len - used);
        ctl_len -= used;
    }
    if (ctl_len == sizeof ctl_buf - 1)
        ctl_len = 0; /* overlong line: drop */
    return 1;
}

/* ------------------------------------------------------------------ setup */
static void on_signal(int sig) { stop_signal = sig; }

static void no_sleep(avr_t *a, avr_cycle_count_t how_long)
{
    /* SLEEP just fast-forwards the cycle counter; the main loop paces against the wall clock. */
    (void)a;
    (void)how_long;
}

static void (*mcu_reset_hook)(avr_t *);
static void on_avr_reset(avr_t *a)
{
    if (mcu_reset_hook)
        mcu_reset_hook(a);
    resets++;
}

static avr_uart_t *find_uart0(void)
{
    for (avr_io_t *io = avr->io_port; io; io = io->next)
        if (io->kind && !strcmp(io->kind, "uart") && ((avr_uart_t *)io)->name == '0')
            return (avr_uart_t *)io;
    return NULL;
}

static uint64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static void usage(void)
{
    fprintf(stderr, "usage: smabench-sim [--report] [--r-ohm R] [--ambient C] [--trace-io FILE] [-v]"
                    " firmware.elf\n"
                    "       smabench-sim --bootloader BOOT.hex [options] (app.elf | app.hex | --blank)\n");
    exit(2);
}

int main(int argc, char **argv)
{
    const char *elf = NULL;
    int report = 0, k;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--report"))
            report = 1;
        else if (!strcmp(argv[i], "-v"))
            verbose = 1;
        else if (!strcmp(argv[i], "--r-ohm") && i + 1 < argc)
            r_ohm = atof(argv[++i]);
        else if (!strcmp(argv[i], "--ambient") && i + 1 < argc)
            ambient_c = atof(argv[++i]);
        else if (!strcmp(argv[i], "--trace-io") && i + 1 < argc) {
            trace_io = fopen(argv[++i], "w");
            if (!trace_io)
                die("--trace-io %s: %s", argv[i], strerror(errno));
        }
        else if ((k = boot_option(argc, argv, i)) > 0)
            i += k - 1;
        else if (argv[i][0] == '-')
            usage();
        else if (!elf)
            elf = argv[i];
        else
            usage();
    }
    if (!boot_args_ok(elf) || !(r_ohm > 0.0))
        usage();

    /* Our control output keeps the real stdout; anything libsimavr prints goes to stderr. */
    int out_fd = dup(1);
    if (out_fd < 0 || dup2(2, 1) < 0)
        die("dup: %s", strerror(errno));
    ctl = fdopen(out_fd, "w");
    if (!ctl)
        die("fdopen: %s", strerror(errno));

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    avr_global_logger_set(log_to_stderr);

    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (!boot_enabled() && elf_read_firmware(elf, &fw) != 0)
        die("cannot read %s", elf);
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr)
        die("simavr has no atmega328p");
    avr_init(avr);
    fw.frequency = F_CPU;
    if (boot_enabled())
        boot_setup(avr, elf); /* boot.c: bootloader + application (or none) */
    else
        avr_load_firmware(avr, &fw);
    avr->frequency = F_CPU;
    avr->vcc = avr->avcc = avr->aref = 5000;
    avr->log = verbose ? LOG_TRACE : LOG_ERROR;
    avr->sleep = no_sleep;
    mcu_reset_hook = avr->reset;
    avr->reset = on_avr_reset;

    /* UART0: no stdio echo, no poll-sleep; IRQs to and from the pty */
    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    uart_irq = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    if (!uart_irq)
        die("no UART0 IRQs");
    avr_irq_register_notify(uart_irq + UART_IRQ_OUTPUT, uart_out_cb, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XON, uart_xon_cb, NULL);
    avr_irq_register_notify(uart_irq + UART_IRQ_OUT_XOFF, uart_xoff_cb, NULL);
    uart0 = find_uart0();
    if (!uart0)
        fprintf(stderr, "smabench-sim: UART0 struct not found, pacing at 115200 8N1\n");

    adc_irq = avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0);
    if (!adc_irq)
        die("no ADC IRQs");
    avr_irq_register_notify(adc_irq + ADC_IRQ_OUT_TRIGGER, adc_trigger_cb, NULL);
    cut_attach(avr, avr_now_s);
    periph_attach(avr);
    avr_irq_t *pwm = avr_io_getirq(avr, AVR_IOCTL_TIMER_GETIRQ('1'), TIMER_IRQ_OUT_PWM0);
    if (pwm)
        avr_irq_register_notify(pwm, pwm_irq_cb, NULL);

    /* pty: raw, the master non-blocking; we keep the slave open so the master never hangs up
     * while no client is connected */
    char name[256];
    struct termios tio;
    if (openpty(&pty_master, &pty_slave, name, NULL, NULL) < 0)
        die("openpty: %s", strerror(errno));
    tcgetattr(pty_slave, &tio);
    cfmakeraw(&tio);
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    tcsetattr(pty_slave, TCSANOW, &tio);
    fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
    fcntl(pty_master, F_SETFD, FD_CLOEXEC);
    fcntl(pty_slave, F_SETFD, FD_CLOEXEC);
    if (boot_enabled())
        boot_port_init(avr, &pty_slave); /* auto-reset: opens of the port must be seen */

    model_update(1);
    fprintf(ctl, "PTY %s\n", name);
    fflush(ctl);

    /* run in real time: slices of 100 us of AVR time, then I/O, then wait for the wall clock */
    const avr_cycle_count_t slice = F_CPU / 10000u;
    const uint64_t report_cycles = F_CPU / 10u; /* 100 ms */
    uint64_t next_report = report_cycles, next_refresh = 0;
    uint64_t wall0 = now_ns(), sim0 = 0;
    unsigned long slips = 0;
    uint64_t last_wake_ns = 0;
    int stdin_open = 1, exit_code = 0;
    last_cycle = avr->cycle;

    while (!stop_signal && stdin_open) {
        avr_cycle_count_t end = avr->cycle + slice;
        while (avr->cycle < end) {
            int st = avr_run(avr);
            if (resets != resets_seen) { /* right after the reset, before .init3 clears MCUSR */
                resets_seen = resets;
                reset_mcusr = avr->data[A_MCUSR];
            }
            if (avr->cycle < last_cycle) { /* reset (watchdog): simavr restarts the count */
                last_cycle = 0;
                end = slice;
            }
            if (st == cpu_Done || st == cpu_Crashed) {
                fprintf(stderr, "smabench-sim: AVR %s at pc 0x%04x, t=%.3f ms\n",
                        st == cpu_Done ? "stopped" : "crashed", (unsigned)avr->pc,
                        total_cycles / (F_CPU / 1000.0));
                exit_code = 3;
                goto out;
            }
        }
        total_cycles += avr->cycle - last_cycle;
        last_cycle = avr->cycle;
        enum boot_port_state port = boot_enabled() ? boot_port_poll(avr, pty_master) : BOOT_PORT_OPEN;
        if (port != BOOT_PORT_OPEN) { /* closed: nobody reads; opened: the MCU is being reset */
            txq_len = 0;
            rxq_tail = rxq_head;
        }
        if (resets != resets_reported) {
            fprintf(stderr, "smabench-sim: AVR reset at t=%.3f ms (MCUSR=0x%02x%s)\n",
                    total_cycles / (F_CPU / 1000.0), reset_mcusr,
                    (reset_mcusr & 0x08) ? ": watchdog" : "");
            resets_reported = resets;
            cut_mcu_reset();
            model_dirty = 1;
            rx_pump_kick(); /* reset cancelled the cycle timers */
        }
        model_update(total_cycles >= next_refresh);
        if (total_cycles >= next_refresh)
            next_refresh = total_cycles + F_CPU / 1000u;
        pty_flush();
        if (report && total_cycles >= next_report) {
            print_state();
            next_report += report_cycles;
        }

        /* pace: wait (for I/O or the wall clock) while the AVR is ahead */
        uint64_t sim_ns = (total_cycles - sim0) * 1000000000ull / F_CPU;
        uint64_t wall_ns = now_ns() - wall0;
        int64_t ahead = (int64_t)sim_ns - (int64_t)wall_ns;
        if (trace_io) { /* a slice that took more than 10 ms of wall time: the harness stalled */
            uint64_t w = now_ns();
            if (last_wake_ns && w - last_wake_ns > 10000000ull)
                trace_event("stall", (w - last_wake_ns) / 1e3);
        }
        if (ahead < -50000000) { /* more than 50 ms behind: slip instead of racing */
            trace_event("slip", -ahead / 1e3);
            wall0 = now_ns();
            sim0 = total_cycles;
            ahead = 0;
            slips++;
            if (verbose)
                fprintf(stderr, "smabench-sim: behind real time, slip %lu\n", slips);
        }
        for (;;) {
            struct pollfd pfd[2] = {
                {.fd = 0, .events = POLLIN},
                {.fd = port == BOOT_PORT_CLOSED ? -1 : pty_master,
                 .events = POLLIN | (txq_len ? POLLOUT : 0)},
            };
            struct timespec to = {0, 0};
            if (ahead > 0) {
                to.tv_sec = ahead / 1000000000;
                to.tv_nsec = ahead % 1000000000;
            }
            int n = ppoll(pfd, 2, &to, NULL);
            if (n < 0 && errno != EINTR)
                die("poll: %s", strerror(errno));
            if (n > 0) {
                if (pfd[0].revents & (POLLIN | POLLHUP | POLLERR))
                    stdin_open = stdin_read();
                if (pfd[1].revents & POLLIN)
                    pty_read();
                if (pfd[1].revents & POLLOUT)
                    pty_flush();
            }
            if (stop_signal || !stdin_open)
                break;
            ahead = (int64_t)((total_cycles - sim0) * 1000000000ull / F_CPU) - (int64_t)(now_ns() - wall0);
            if (ahead <= 0)
                break; /* caught up: run the next slice (input is injected at the AVR's time) */
        }
        last_wake_ns = now_ns();
    }
out:
    pty_flush();
    if (verbose || exit_code)
        fprintf(stderr, "smabench-sim: exit after %.3f ms AVR time; rx %lu B, tx %lu B, tx dropped %lu, slips %lu\n",
                total_cycles / (F_CPU / 1000.0), rx_bytes, tx_bytes, tx_dropped, slips);
    if (trace_io)
        fclose(trace_io);
    avr_terminate(avr);
    return exit_code;
}
