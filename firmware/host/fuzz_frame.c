/* libFuzzer target: arbitrary bytes into the frame receiver and into core_poll (fake HAL), with
 * control ticks interleaved. Never crashes; invariants are checked after every step.
 * Build: clang -fsanitize=fuzzer,address,undefined (see firmware/Makefile `fuzz`).
 * With -DFUZZ_STANDALONE it builds a plain main() that replays the files given as arguments.
 *
 * Input: byte 0 selects the mode and start conditions, the rest is
 *   mode raw (bit 0 = 0): bytes straight into the UART, a tick every 1 + (b0 >> 4) bytes;
 *   mode structured (bit 0 = 1): records [op, a, b, ...]:
 *     op % 4 == 0: command type a, payload length b % 12, payload bytes (framed with good CRC)
 *     op % 4 == 1: a ticks (1 ms each)
 *     op % 4 == 2: change the conditions: a = wire resistance (x 10 mOhm), b bits: 1 open wire,
 *                  2 e-stop tripped, 4 NTC open, 8 external ADC absent, 16 thermocouple present
 *                  at 20 + a degC, 32 thermocouple open-circuit fault
 *     op % 4 == 3: a % 32 raw bytes into the UART */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "core.h"
#include "frame.h"
#include "hal_fake.h"
#include "proto.h"

#define DUTY_MAX HAL_PWM_TOP
#define REQUIRE(c)                                                                    \
    do {                                                                              \
        if (!(c)) {                                                                   \
            fprintf(stderr, "invariant failed: %s (%s:%d)\n", #c, __FILE__, __LINE__); \
            abort();                                                                  \
        }                                                                             \
    } while (0)

static frame_rx_t host_rx;     /* decodes what the device sends */
static uint32_t last_ack_ms;   /* harness view of the last valid command (= last ACK) */
static uint32_t last_lease_ms; /* last SET_CURRENT or ENABLE acknowledged */

/* Raw receiver alone: packets and counters stay within bounds. */
static void fuzz_receiver(const uint8_t *data, size_t size)
{
    frame_rx_t rx;
    frame_packet_t p;
    frame_rx_init(&rx);
    for (size_t i = 0; i < size; i++) {
        uint16_t crc = rx.crc_errors, fr = rx.frame_errors;
        if (frame_rx_push(&rx, data[i], &p)) {
            REQUIRE(p.len <= FRAME_MAX_PAYLOAD);
            REQUIRE(p.payload >= rx.buf && p.payload + p.len + 2 <= rx.buf + sizeof rx.buf);
            /* re-encoding a received packet gives a valid frame of the same content */
            uint8_t out[FRAME_MAX_WIRE];
            REQUIRE(frame_encode(p.seq, p.type, p.payload, p.len, out, sizeof out) != 0);
        }
        REQUIRE(rx.len <= sizeof rx.buf);
        REQUIRE(rx.crc_errors >= crc && rx.frame_errors >= fr);
        REQUIRE(rx.crc_errors + rx.frame_errors <= crc + fr + 1);
    }
}

/* Decode the device output: only valid frames, note ACKs. */
static void drain_tx(void)
{
    size_t n;
    const uint8_t *d = fake_tx_data(&n);
    frame_packet_t p;
    for (size_t i = 0; i < n; i++) {
        if (frame_rx_push(&host_rx, d[i], &p)) {
            REQUIRE(p.type == MSG_ACK || p.type == MSG_TELEMETRY);
            REQUIRE(p.type != MSG_TELEMETRY || p.len == TELEMETRY_LEN);
            if (p.type == MSG_ACK) {
                REQUIRE(p.len >= 3);
                last_ack_ms = hal_millis();
                if (p.payload[1] == MSG_SET_CURRENT ||
                    (p.payload[1] == MSG_ENABLE && p.payload[2] == ST_OK)) {
                    last_lease_ms = hal_millis();
                }
            }
        }
    }
    REQUIRE(host_rx.crc_errors == 0 && host_rx.frame_errors == 0);
    fake_tx_clear();
}

static void check_state(void)
{
    const core_state_t *s = core_state();
    REQUIRE(s->duty <= DUTY_MAX && fake_pwm_duty() <= DUTY_MAX);
    REQUIRE(s->limit_ma <= CORE_HARD_LIMIT_MA && s->setpoint_ma <= s->limit_ma);
    REQUIRE(s->host_timeout_ms >= HOST_TIMEOUT_MIN_MS && s->host_timeout_ms <= HOST_TIMEOUT_MAX_MS);
    REQUIRE(s->telemetry_period_ms == 0 ||
            (s->telemetry_period_ms >= TELEMETRY_MIN_MS && s->telemetry_period_ms <= TELEMETRY_MAX_MS));
    REQUIRE(!!(s->flags & FLAG_ENABLED) == !!s->enabled);
    REQUIRE(!s->enabled || !(s->flags & FLAGS_LATCHED));
    REQUIRE(s->lease_ms >= LEASE_MIN_MS && s->lease_ms <= LEASE_MAX_MS);
    REQUIRE(!!s->enabled == !!fake_output_enabled());
    REQUIRE(s->ambient_cdeg == TEMP_NONE || (s->ambient_cdeg >= -4000 && s->ambient_cdeg <= 12500));
    REQUIRE(s->enabled || (s->duty == 0 && fake_pwm_duty() == 0));
    REQUIRE(s->probe_ma <= PROBE_MAX_MA);
}

static void poll(void)
{
    core_poll();
    drain_tx();
    check_state();
}

static void tick(void)
{
    fake_advance_ms(1);
    core_poll();
    uint8_t was_on = core_state()->enabled;
    core_control_tick();
    /* whatever turned the output off in this tick turned the probe current off with it */
    REQUIRE(!was_on || core_state()->enabled || core_state()->probe_ma == 0);
    drain_tx();
    check_state();
    /* host timeout: off within the timeout of the last valid frame */
    if (core_state()->enabled) {
        REQUIRE(hal_millis() - last_ack_ms < core_state()->host_timeout_ms);
        /* lease: a non-zero setpoint lives at most the lease after its last renewal */
        REQUIRE(core_state()->setpoint_ma == 0 ||
                hal_millis() - last_lease_ms < core_state()->lease_ms);
    }
}

static void run_raw(const uint8_t *data, size_t size, unsigned every)
{
    for (size_t i = 0; i < size; i++) {
        fake_rx_push(&data[i], 1);
        if ((i + 1) % every == 0) {
            tick();
        } else {
            poll();
        }
    }
    tick();
}

static void run_structured(const uint8_t *d, size_t size)
{
    size_t i = 0;
    while (i + 3 <= size) {
        uint8_t op = d[i], a = d[i + 1], b = d[i + 2];
        i += 3;
        switch (op % 4u) {
        case 0: {
            uint8_t len = (uint8_t)(b % 12u);
            if (i + len > size) {
                len = (uint8_t)(size - i);
            }
            uint8_t out[FRAME_MAX_WIRE];
            uint8_t n = frame_encode(op, a, &d[i], len, out, sizeof out);
            fake_rx_push(out, n);
            i += len;
            poll();
            break;
        }
        case 1:
            for (unsigned t = 0; t <= a; t++) {
                tick();
            }
            break;
        case 2:
            fake_sink()->wire_ohm = 0.01 * (a ? a : 1);
            fake_sink()->open = (uint8_t)(b & 1u);
            fake_estop((uint8_t)(b & 2u));
            if (b & 4u) {
                fake_ntc_mv(0);
            } else {
                fake_ntc_celsius(22.0);
            }
            fake_xadc_present(!(b & 8u));
            if (b & 32u) {
                fake_tc_fault(TC_OC);
            } else if (b & 16u) {
                fake_tc_celsius(20.0 + a);
            } else {
                fake_tc_absent();
            }
            break;
        default: {
            size_t len = a % 32u;
            if (i + len > size) {
                len = size - i;
            }
            fake_rx_push(&d[i], len);
            i += len;
            poll();
            break;
        }
        }
    }
    tick();
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    fuzz_receiver(data, size);
    if (size == 0) {
        return 0;
    }
    uint8_t mode = data[0];
    fake_reset();
    fake_set_millis((mode & 2u) ? 0xFFFFFF00u : 0u); /* also run across the 32-bit wrap */
    fake_eeprom_erase(); /* every input starts from a blank EEPROM */
    fake_ntc_mv((uint16_t)(mode * 19u));
    core_init((uint8_t)((mode >> 2) & 1u));
    frame_rx_init(&host_rx);
    last_ack_ms = hal_millis();
    last_lease_ms = last_ack_ms;
    check_state();
    if (mode & 1u) {
        run_structured(data + 1, size - 1);
    } else {
        run_raw(data + 1, size - 1, 1u + (mode >> 4));
    }
    return 0;
}

#ifdef FUZZ_STANDALONE
int main(int argc, char **argv)
{
    static uint8_t buf[1 << 16];
    for (int i = 1; i < argc; i++) {
        FILE *f = fopen(argv[i], "rb");
        if (!f) {
            perror(argv[i]);
            return 1;
        }
        size_t n = fread(buf, 1, sizeof buf, f);
        fclose(f);
        LLVMFuzzerTestOneInput(buf, n);
    }
    printf("replayed %d inputs\n", argc - 1);
    return 0;
}
#endif
