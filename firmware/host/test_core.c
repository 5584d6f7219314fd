/* Host tests of the firmware core: CRC, COBS, frames (+ shared vectors), commands, safety, PI.
 * Usage: test_core [vectors.txt ...]. Prints a summary; exit status 1 on any failure. */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "cobs.h"
#include "core.h"
#include "crc16.h"
#include "frame.h"
#include "hal_fake.h"
#include "proto.h"

static int checks, failures;

#define CHECK(cond, ...) check_((cond) ? 1 : 0, __FILE__, __LINE__, #cond, __VA_ARGS__)
static void check_(int ok, const char *file, int line, const char *expr, const char *fmt, ...)
{
    checks++;
    if (ok) {
        return;
    }
    failures++;
    printf("FAIL %s:%d: %s: ", file, line, expr);
    va_list ap;
    va_start(ap, fmt);
    vprintf(fmt, ap);
    va_end(ap);
    printf("\n");
}

/* ------------------------------------------------------------------ harness */
typedef struct {
    uint8_t seq, type, len;
    uint8_t payload[FRAME_MAX_PAYLOAD];
} pkt_t;

#define MAX_PKTS 2048
static pkt_t rxp[MAX_PKTS]; /* frames the device sent, decoded */
static frame_rx_t host_rx;  /* host-side receiver of device frames */
static uint8_t host_seq;

static void reset(uint8_t wdt_reset)
{
    fake_reset();
    core_init(wdt_reset);
    frame_rx_init(&host_rx);
    host_seq = 0;
}

/* Decode all TX bytes so far, then clear them; returns the number of frames. */
static int take_tx(void)
{
    size_t n;
    const uint8_t *d = fake_tx_data(&n);
    int count = 0;
    frame_packet_t p;
    for (size_t i = 0; i < n; i++) {
        if (frame_rx_push(&host_rx, d[i], &p) && count < MAX_PKTS) {
            rxp[count].seq = p.seq;
            rxp[count].type = p.type;
            rxp[count].len = p.len;
            memcpy(rxp[count].payload, p.payload, p.len);
            count++;
        }
    }
    CHECK(host_rx.crc_errors == 0 && host_rx.frame_errors == 0, "device sent a bad frame");
    fake_tx_clear();
    return count;
}

static void push_frame(uint8_t seq, uint8_t type, const uint8_t *pl, uint8_t len)
{
    uint8_t out[FRAME_MAX_WIRE];
    uint8_t n = frame_encode(seq, type, pl, len, out, sizeof out);
    fake_rx_push(out, n);
}

/* Send a command, poll, return the ACK status (-1 if no single ACK). ACK data -> rxp[0]. */
static int cmd(uint8_t type, const uint8_t *pl, uint8_t len)
{
    uint8_t seq = host_seq++;
    push_frame(seq, type, pl, len);
    core_poll();
    int n = take_tx();
    if (n != 1 || rxp[0].type != MSG_ACK || rxp[0].len < 3 || rxp[0].payload[0] != seq ||
        rxp[0].payload[1] != type) {
        return -1;
    }
    return rxp[0].payload[2];
}

static int cmd_u8(uint8_t type, uint8_t v) { return cmd(type, &v, 1); }
static int cmd_u16(uint8_t type, uint16_t v)
{
    uint8_t b[2] = {(uint8_t)v, (uint8_t)(v >> 8)};
    return cmd(type, b, 2);
}
static int cmd_limits(uint16_t limit, uint16_t timeout)
{
    uint8_t b[4] = {(uint8_t)limit, (uint8_t)(limit >> 8), (uint8_t)timeout, (uint8_t)(timeout >> 8)};
    return cmd(MSG_SET_LIMITS, b, 4);
}

/* Advance 1 ms and run one control tick. */
static void tick(void)
{
    fake_advance_ms(1);
    core_poll();
    core_control_tick();
}

static void ticks(int n)
{
    for (int i = 0; i < n; i++) {
        tick();
    }
}

static const core_state_t *st(void) { return core_state(); }
static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

/* ------------------------------------------------------------------ CRC, COBS */
static void test_crc(void)
{
    const uint8_t s[] = "123456789";
    CHECK(crc16_ccitt(s, 9) == 0x29B1u, "check value 0x%04X", crc16_ccitt(s, 9));
    CHECK(crc16_ccitt(s, 0) == 0xFFFFu, "empty");
}

static void cobs_roundtrip(const uint8_t *src, uint16_t len, const char *what)
{
    static uint8_t enc[1200], dec[1200];
    uint16_t n = cobs_encode(src, len, enc, sizeof enc);
    CHECK(n >= 1 && n <= COBS_MAX_ENCODED(len), "%s: encoded length %u for %u", what, n, len);
    CHECK(memchr(enc, 0, n) == NULL, "%s: zero in encoding", what);
    uint16_t m = 0xFFFF;
    CHECK(cobs_decode(enc, n, dec, sizeof dec, &m) == 0, "%s: decode failed", what);
    CHECK(m == len && memcmp(src, dec, len) == 0, "%s: round trip len %u -> %u", what, len, m);
    /* in place */
    CHECK(cobs_decode(enc, n, enc, n, &m) == 0 && m == len && memcmp(src, enc, len) == 0,
          "%s: in-place decode", what);
    /* one byte too small */
    CHECK(cobs_encode(src, len, enc, (uint16_t)(n - 1u)) == 0, "%s: overflow not reported", what);
}

static void test_cobs(void)
{
    static uint8_t buf[1100], enc[1200], dec[1200];
    uint16_t n, m;
    /* Known encodings (Wikipedia examples). */
    const uint8_t z1[] = {0x00}, z2[] = {0x00, 0x00}, a[] = {0x11, 0x22, 0x00, 0x33};
    n = cobs_encode(z1, 1, enc, sizeof enc);
    CHECK(n == 2 && enc[0] == 1 && enc[1] == 1, "00 -> 01 01");
    n = cobs_encode(z2, 2, enc, sizeof enc);
    CHECK(n == 3 && enc[0] == 1 && enc[1] == 1 && enc[2] == 1, "00 00 -> 01 01 01");
    n = cobs_encode(a, 4, enc, sizeof enc);
    CHECK(n == 5 && enc[0] == 3 && enc[3] == 2 && enc[4] == 0x33, "11 22 00 33");
    n = cobs_encode(a, 0, enc, sizeof enc);
    CHECK(n == 1 && enc[0] == 1, "empty -> 01");
    /* 254 non-zero bytes: FF + data, no trailing code byte */
    for (int i = 0; i < 254; i++) buf[i] = (uint8_t)(i + 1);
    n = cobs_encode(buf, 254, enc, sizeof enc);
    CHECK(n == 255 && enc[0] == 0xFF && enc[254] == 0xFE, "254 run: n=%u", n);
    /* ... and the non-minimal form (extra 01) decodes to the same */
    enc[255] = 0x01;
    CHECK(cobs_decode(enc, 256, dec, sizeof dec, &m) == 0 && m == 254 && memcmp(dec, buf, 254) == 0,
          "254 run with trailing 01");
    /* 255 non-zero: FF 01..FE 02 FF */
    for (int i = 0; i < 255; i++) buf[i] = (uint8_t)(i + 1);
    n = cobs_encode(buf, 255, enc, sizeof enc);
    CHECK(n == 257 && enc[0] == 0xFF && enc[255] == 0x02 && enc[256] == 0xFF, "255 run: n=%u", n);
    /* 254 non-zero then 00: FF .. 01 01 */
    for (int i = 0; i < 254; i++) buf[i] = (uint8_t)(i + 2);
    buf[254] = 0;
    n = cobs_encode(buf, 255, enc, sizeof enc);
    CHECK(n == 257 && enc[0] == 0xFF && enc[255] == 0x01 && enc[256] == 0x01, "254 run + 00");
    /* Round trips around the 254-byte boundaries and random data. */
    static const uint16_t runs[] = {0, 1, 2, 253, 254, 255, 256, 507, 508, 509, 762, 1000};
    for (size_t r = 0; r < sizeof runs / sizeof runs[0]; r++) {
        memset(buf, 0x5A, runs[r]);
        cobs_roundtrip(buf, runs[r], "run");
        if (runs[r] > 0) {
            buf[runs[r] - 1] = 0; /* run ending in a zero */
            cobs_roundtrip(buf, runs[r], "run+0");
            memset(buf, 0, runs[r]);
            cobs_roundtrip(buf, runs[r], "zeros");
        }
    }
    srand(1234);
    for (int t = 0; t < 2000; t++) {
        uint16_t len = (uint16_t)(rand() % 1000);
        int zero_pct = rand() % 4 == 0 ? 0 : rand() % 50;
        for (uint16_t i = 0; i < len; i++) {
            buf[i] = (rand() % 100 < zero_pct) ? 0 : (uint8_t)(1 + rand() % 255);
        }
        cobs_roundtrip(buf, len, "random");
    }
    /* Invalid encodings */
    const uint8_t bad1[] = {0x03, 0x11}, bad2[] = {0x02, 0x00, 0x01}, bad3[] = {0x00};
    CHECK(cobs_decode(bad1, 2, dec, sizeof dec, &m) != 0, "block past end");
    CHECK(cobs_decode(bad2, 3, dec, sizeof dec, &m) != 0, "zero in data");
    CHECK(cobs_decode(bad3, 1, dec, sizeof dec, &m) != 0, "zero code");
    const uint8_t ok4[] = {0x03, 0x11, 0x22, 0x02, 0x33};
    CHECK(cobs_decode(ok4, 5, dec, 3, &m) != 0, "decode cap too small");
}

/* ------------------------------------------------------------------ frames, vectors */
static int hexbytes(const char *hex, uint8_t *out, int cap)
{
    if (strcmp(hex, "-") == 0) {
        return 0;
    }
    int n = 0;
    size_t len = strlen(hex);
    if (len % 2) {
        return -1;
    }
    for (size_t i = 0; i < len; i += 2) {
        unsigned v;
        if (n >= cap || sscanf(hex + i, "%2x", &v) != 1) {
            return -1;
        }
        out[n++] = (uint8_t)v;
    }
    return n;
}

static void vector_good(const char *name, const char *seq_s, const char *type_s, const char *pl_s,
                        const char *fr_s)
{
    static uint8_t pl[512], fr[512], out[FRAME_MAX_WIRE];
    int pl_n = hexbytes(pl_s, pl, sizeof pl), fr_n = hexbytes(fr_s, fr, sizeof fr);
    long seq = strtol(seq_s, NULL, strncmp(seq_s, "0x", 2) == 0 ? 16 : 10);
    long type = strtol(type_s, NULL, 16);
    CHECK(pl_n >= 0 && fr_n > 0 && seq >= 0 && seq < 256 && type >= 0 && type < 256,
          "%s: unparsable", name);
    if (pl_n < 0 || fr_n <= 0) {
        return;
    }
    int with_delim = fr[fr_n - 1] == 0;
    uint8_t n = frame_encode((uint8_t)seq, (uint8_t)type, pl, (uint8_t)pl_n, out, sizeof out);
    CHECK(n != 0 && (int)n - (with_delim ? 0 : 1) == fr_n && memcmp(out, fr, (size_t)fr_n) == 0,
          "%s: encode differs", name);
    frame_rx_t rx;
    frame_packet_t p;
    frame_rx_init(&rx);
    int got = 0;
    for (int i = 0; i < fr_n; i++) got += frame_rx_push(&rx, fr[i], &p);
    if (!with_delim) got += frame_rx_push(&rx, 0, &p);
    CHECK(got == 1 && p.seq == seq && p.type == type && p.len == pl_n &&
              memcmp(p.payload, pl, (size_t)pl_n) == 0,
          "%s: decode differs", name);
    CHECK(rx.crc_errors == 0 && rx.frame_errors == 0, "%s: error counted", name);
}

static void vector_bad(const char *name, const char *kind, const char *fr_s)
{
    static uint8_t fr[512];
    int fr_n = hexbytes(fr_s, fr, sizeof fr);
    CHECK(fr_n > 0 && (!strcmp(kind, "crc") || !strcmp(kind, "frame")), "%s: unparsable", name);
    if (fr_n <= 0) {
        return;
    }
    frame_rx_t rx;
    frame_packet_t p;
    frame_rx_init(&rx);
    int got = 0;
    for (int i = 0; i < fr_n; i++) got += frame_rx_push(&rx, fr[i], &p);
    if (fr[fr_n - 1] != 0) got += frame_rx_push(&rx, 0, &p);
    int is_crc = !strcmp(kind, "crc");
    CHECK(got == 0, "%s: invalid frame accepted", name);
    CHECK(rx.crc_errors == (is_crc ? 1 : 0) && rx.frame_errors == (is_crc ? 0 : 1),
          "%s: counters crc=%u frame=%u, want %s", name, rx.crc_errors, rx.frame_errors, kind);
    /* the next frame is received again */
    const uint8_t ping[] = {0x01, 0x04, 0x07, 0xE8, 0x6D, 0x00};
    for (size_t i = 0; i < sizeof ping; i++) got += frame_rx_push(&rx, ping[i], &p);
    CHECK(got == 1 && p.type == MSG_PING, "%s: no resync", name);
}

static void test_vectors(const char *path)
{
    FILE *f = fopen(path, "r");
    CHECK(f != NULL, "cannot open %s", path);
    if (!f) {
        return;
    }
    char line[2048];
    int good = 0, bad = 0;
    while (fgets(line, sizeof line, f)) {
        char *tok[6];
        int nt = 0;
        char *hash = strchr(line, '#');
        if (hash) *hash = '\0';
        for (char *t = strtok(line, " \t\r\n"); t && nt < 6; t = strtok(NULL, " \t\r\n")) {
            tok[nt++] = t;
        }
        if (nt == 0) continue;
        if (nt == 4 && strcmp(tok[1], "ERR") == 0) {
            vector_bad(tok[0], tok[2], tok[3]);
            bad++;
        } else if (nt == 5) {
            vector_good(tok[0], tok[1], tok[2], tok[3], tok[4]);
            good++;
        } else {
            CHECK(0, "%s: bad line starting with %s", path, tok[0]);
        }
    }
    fclose(f);
    CHECK(good > 0, "%s: no valid vectors", path);
    printf("vectors %s: %d valid, %d invalid\n", path, good, bad);
}

static void test_frame_rx(void)
{
    frame_rx_t rx;
    frame_packet_t p;
    uint8_t out[FRAME_MAX_WIRE], pl[FRAME_MAX_PAYLOAD + 1];
    memset(pl, 0xA5, sizeof pl);
    CHECK(frame_encode(1, 2, pl, FRAME_MAX_PAYLOAD + 1, out, sizeof out) == 0, "61-byte payload");
    CHECK(frame_encode(1, 2, pl, FRAME_MAX_PAYLOAD, out, 10) == 0, "small out buffer");
    uint8_t n = frame_encode(1, 2, pl, FRAME_MAX_PAYLOAD, out, sizeof out);
    CHECK(n == FRAME_MAX_WIRE, "max frame %u bytes", n);
    frame_rx_init(&rx);
    /* too long: 300 non-zero bytes, then the max frame */
    for (int i = 0; i < 300; i++) CHECK(frame_rx_push(&rx, 0x33, &p) == 0, "long");
    CHECK(frame_rx_push(&rx, 0, &p) == 0 && rx.frame_errors == 1, "overflow counted");
    int got = 0;
    for (uint8_t i = 0; i < n; i++) got += frame_rx_push(&rx, out[i], &p);
    CHECK(got == 1 && p.len == FRAME_MAX_PAYLOAD && p.seq == 1 && p.type == 2, "max frame decoded");
    /* empty frames ignored */
    frame_rx_push(&rx, 0, &p);
    frame_rx_push(&rx, 0, &p);
    CHECK(rx.frame_errors == 1 && rx.crc_errors == 0, "empty frames not counted");
    /* counters saturate */
    for (long i = 0; i < 70000; i++) {
        frame_rx_push(&rx, 0x42, &p);
        frame_rx_push(&rx, 0, &p);
    }
    CHECK(rx.frame_errors == 0xFFFF, "saturating frame_errors %u", rx.frame_errors);
}

/* ------------------------------------------------------------------ commands */
static void test_commands(void)
{
    reset(0);
    CHECK(fake_pwm_duty() == 0 && fake_pwm_set_count() >= 1 && !st()->enabled, "off at reset");
    CHECK(st()->limit_ma == 2500 && st()->host_timeout_ms == 250 && st()->telemetry_period_ms == 0,
          "defaults");
    /* IDENTIFY */
    CHECK(cmd_u8(MSG_IDENTIFY, 1) == ST_OK, "identify");
    const uint8_t want[] = {1, 1, 0, 0, 0xC4, 0x09, 'S', 'M', 'A', '-', 'C', 'D', '3', '2', '8'};
    CHECK(rxp[0].len == 3 + sizeof want && memcmp(rxp[0].payload + 3, want, sizeof want) == 0,
          "identify data");
    CHECK(cmd_u8(MSG_IDENTIFY, 2) == ST_VERSION_MISMATCH, "version mismatch");
    CHECK(rxp[0].len == 3 + sizeof want && memcmp(rxp[0].payload + 3, want, sizeof want) == 0,
          "mismatch still sends data");
    /* unknown types */
    const uint8_t unknown[] = {0x00, 0x08, 0x80, 0x90, 0xFF};
    for (size_t i = 0; i < sizeof unknown; i++) {
        CHECK(cmd(unknown[i], NULL, 0) == ST_UNKNOWN_COMMAND, "type 0x%02X", unknown[i]);
        CHECK(rxp[0].len == 3, "no data on error");
    }
    /* bad length, for every command */
    const uint8_t types[] = {1, 2, 3, 4, 5, 6, 7}, lens[] = {1, 1, 2, 4, 2, 0, 0};
    uint8_t junk[8] = {1, 0, 1, 0, 1, 0, 1, 0};
    for (size_t i = 0; i < sizeof types; i++) {
        CHECK(cmd(types[i], junk, (uint8_t)(lens[i] + 1)) == ST_BAD_LENGTH, "len+1 type %u", types[i]);
        if (lens[i]) CHECK(cmd(types[i], junk, (uint8_t)(lens[i] - 1)) == ST_BAD_LENGTH, "len-1 type %u", types[i]);
    }
    CHECK(!st()->enabled && st()->setpoint_ma == 0, "bad length changed nothing");
    /* ENABLE */
    CHECK(cmd_u8(MSG_ENABLE, 2) == ST_OUT_OF_RANGE && !st()->enabled, "enable 2");
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK && st()->enabled && (st()->flags & FLAG_ENABLED), "enable");
    /* SET_CURRENT */
    CHECK(cmd_u16(MSG_SET_CURRENT, 1000) == ST_OK && st()->setpoint_ma == 1000, "set 1000");
    CHECK(cmd_u16(MSG_SET_CURRENT, 3000) == ST_CLAMPED && st()->setpoint_ma == 2500, "clamp 2500");
    /* SET_LIMITS */
    CHECK(cmd_limits(2501, 250) == ST_OUT_OF_RANGE && st()->limit_ma == 2500, "limit 2501");
    CHECK(cmd_limits(1000, 19) == ST_OUT_OF_RANGE && st()->limit_ma == 2500, "timeout 19");
    CHECK(cmd_limits(1000, 5001) == ST_OUT_OF_RANGE && st()->host_timeout_ms == 250, "timeout 5001");
    CHECK(cmd_limits(1000, 20) == ST_OK && st()->limit_ma == 1000 && st()->host_timeout_ms == 20,
          "limits 1000/20");
    CHECK(st()->setpoint_ma == 1000, "setpoint clamped by new limit: %u", st()->setpoint_ma);
    CHECK(cmd_limits(2500, 5000) == ST_OK && st()->host_timeout_ms == 5000, "limits 2500/5000");
    CHECK(cmd_limits(1200, 250) == ST_OK, "limits 1200");
    CHECK(cmd_u16(MSG_SET_CURRENT, 1500) == ST_CLAMPED && st()->setpoint_ma == 1200, "clamp 1200");
    CHECK(cmd_u16(MSG_SET_CURRENT, 1200) == ST_OK, "at limit is OK");
    CHECK(cmd_u16(MSG_SET_CURRENT, 0) == ST_OK && st()->setpoint_ma == 0, "set 0");
    /* SET_TELEMETRY */
    const uint16_t bad_p[] = {1, 4, 1001, 65535}, good_p[] = {5, 1000, 0};
    for (size_t i = 0; i < 4; i++)
        CHECK(cmd_u16(MSG_SET_TELEMETRY, bad_p[i]) == ST_OUT_OF_RANGE && st()->telemetry_period_ms == 0,
              "period %u", bad_p[i]);
    for (size_t i = 0; i < 3; i++)
        CHECK(cmd_u16(MSG_SET_TELEMETRY, good_p[i]) == ST_OK && st()->telemetry_period_ms == good_p[i],
              "period %u", good_p[i]);
    CHECK(cmd(MSG_CLEAR_FAULTS, NULL, 0) == ST_OK, "clear faults");
    CHECK(cmd(MSG_PING, NULL, 0) == ST_OK, "ping");
    CHECK(cmd_u8(MSG_ENABLE, 0) == ST_OK && !st()->enabled && fake_pwm_duty() == 0 &&
              !(st()->flags & FLAG_ENABLED),
          "enable 0: output off at once");
    /* device sequence numbers count up, ACK echoes the host seq */
    reset(0);
    host_seq = 250;
    for (int i = 0; i < 10; i++) {
        CHECK(cmd(MSG_PING, NULL, 0) == ST_OK && rxp[0].seq == (uint8_t)i, "device seq %d", i);
    }
}

/* ------------------------------------------------------------------ safety */
static void test_host_timeout(void)
{
    reset(0);
    fake_set_millis(1000);
    CHECK(cmd_limits(2500, 100) == ST_OK, "limits");
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK, "enable"); /* last valid frame at t = 1000 */
    cmd_u16(MSG_SET_CURRENT, 500);
    fake_adc_set(HAL_ADC_CURRENT, 500);
    int off_at = -1;
    for (int t = 1; t <= 200 && off_at < 0; t++) {
        tick();
        if (!st()->enabled) off_at = t;
    }
    CHECK(off_at >= 99 && off_at <= 101, "off after %d ms, timeout 100", off_at);
    CHECK(fake_pwm_duty() == 0 && (st()->flags & FLAG_HOST_TIMEOUT) && !(st()->flags & FLAG_ENABLED),
          "timeout: off and flagged");
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK && !(st()->flags & FLAG_HOST_TIMEOUT), "ENABLE clears it");
    /* PING feeds it */
    for (int i = 0; i < 20; i++) {
        ticks(80);
        CHECK(cmd(MSG_PING, NULL, 0) == ST_OK, "ping");
    }
    CHECK(st()->enabled, "PING every 80 ms keeps it on");
    /* bad-CRC frames do not */
    int off2 = -1;
    for (int t = 1; t <= 300 && off2 < 0; t++) {
        if (t % 10 == 0) {
            uint8_t fr[] = {0x01, 0x04, 0x07, 0xE8, 0x6E, 0x00}; /* ping, CRC off by one */
            fake_rx_push(fr, sizeof fr);
        }
        tick();
        if (!st()->enabled) off2 = t;
    }
    CHECK(off2 >= 99 && off2 <= 101, "bad-CRC frames fed the watchdog: off after %d", off2);
    CHECK(st()->rx_crc_errors >= 9, "crc errors counted: %u", st()->rx_crc_errors);
    CHECK(take_tx() == 0, "bad frames never acknowledged");
    /* CLEAR_FAULTS also clears HOST_TIMEOUT */
    CHECK(cmd(MSG_CLEAR_FAULTS, NULL, 0) == ST_OK && !(st()->flags & FLAG_HOST_TIMEOUT), "clear");
}

static void expect_latched(uint16_t flag, const char *what)
{
    CHECK(!st()->enabled && fake_pwm_duty() == 0 && (st()->flags & flag), "%s latched", what);
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_FAULT_ACTIVE && !st()->enabled, "%s: ENABLE refused", what);
    ticks(10);
    CHECK(st()->flags & flag, "%s stays latched", what);
    CHECK(cmd(MSG_CLEAR_FAULTS, NULL, 0) == ST_OK && !(st()->flags & flag), "%s cleared", what);
    CHECK(!st()->enabled && fake_pwm_duty() == 0, "%s: still off after CLEAR_FAULTS", what);
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK && st()->enabled, "%s: ENABLE after clear", what);
}

static void test_overcurrent(void)
{
    reset(0);
    cmd_limits(2500, 5000);
    cmd_u8(MSG_ENABLE, 1);
    cmd_u16(MSG_SET_CURRENT, 1000);
    fake_adc_set(HAL_ADC_CURRENT, 3001); /* limit * 1.2 = 3000 */
    ticks(4);
    CHECK(st()->enabled, "4 ms over: not yet");
    fake_adc_set(HAL_ADC_CURRENT, 3000); /* not above */
    ticks(20);
    CHECK(st()->enabled && !(st()->flags & FLAG_OVERCURRENT), "at threshold, or blips < 5 ms");
    fake_adc_set(HAL_ADC_CURRENT, 3001);
    ticks(4);
    CHECK(st()->enabled, "4 ms");
    tick();
    CHECK(!st()->enabled, "5 ms over: latched");
    fake_adc_set(HAL_ADC_CURRENT, 0);
    expect_latched(FLAG_OVERCURRENT, "overcurrent");
    /* lower limit lowers the threshold */
    cmd_limits(1000, 5000);
    fake_adc_set(HAL_ADC_CURRENT, 1201);
    ticks(5);
    CHECK(st()->flags & FLAG_OVERCURRENT, "threshold follows the limit");
}

static void test_open_wire(void)
{
    reset(0);
    fake_load_t load = {12000, 4200, 1};
    fake_set_plant(fake_plant_resistive, &load);
    cmd_limits(2500, 5000);
    cmd_u16(MSG_SET_CURRENT, 1000);
    cmd_u8(MSG_ENABLE, 1);
    int over_half = -1, latched = -1;
    for (int t = 1; t <= 500 && latched < 0; t++) {
        tick();
        if (over_half < 0 && fake_pwm_duty() > HAL_PWM_TOP / 2) over_half = t;
        if (!st()->enabled) latched = t;
    }
    CHECK(over_half > 0 && latched - over_half >= 49 && latched - over_half <= 51,
          "open wire: duty > 50 %% at %d ms, latched at %d ms", over_half, latched);
    expect_latched(FLAG_OPEN_WIRE, "open wire");
    /* a connected wire at low current (duty < 50 %) is not an open wire */
    load.open = 0;
    cmd_u16(MSG_SET_CURRENT, 10);
    ticks(300);
    CHECK(st()->enabled && !(st()->flags & FLAG_OPEN_WIRE), "low current is fine");
}

/* ------------------------------------------------------------------ PI */
/* Run until settled; returns ms of the last sample outside +-5 % of target (n if never). */
static int settle_ms(uint16_t target, int n, uint16_t *peak)
{
    int last_out = 0;
    *peak = 0;
    for (int t = 1; t <= n; t++) {
        tick();
        uint16_t i = st()->current_ma;
        if (i > *peak) *peak = i;
        if (abs((int)i - (int)target) * 20 > target) last_out = t;
    }
    return last_out;
}

static void test_pi(void)
{
    fake_load_t load = {12000, 4200, 0}; /* reference load: 12 V, 4 + 0.2 Ohm */
    const uint16_t steps[][2] = {{0, 1000}, {0, 500}, {0, 2500}, {1000, 500}, {500, 2000}, {0, 100}};
    for (size_t k = 0; k < sizeof steps / sizeof steps[0]; k++) {
        reset(0);
        fake_set_plant(fake_plant_resistive, &load);
        cmd_limits(2500, 5000);
        cmd_u8(MSG_ENABLE, 1);
        uint16_t peak;
        if (steps[k][0]) {
            cmd_u16(MSG_SET_CURRENT, steps[k][0]);
            settle_ms(steps[k][0], 200, &peak);
        }
        cmd_u16(MSG_SET_CURRENT, steps[k][1]);
        int ms = settle_ms(steps[k][1], 300, &peak);
        printf("PI step %4u -> %4u mA: settled (5 %%) in %2d ms, peak %u mA, duty %u\n",
               steps[k][0], steps[k][1], ms, peak, st()->duty);
        CHECK(ms <= 50, "step %u -> %u settles in %d ms", steps[k][0], steps[k][1], ms);
        CHECK(st()->duty <= HAL_PWM_TOP * 95 / 100, "duty clamp");
    }
    /* anti-windup: a 20 Ohm wire cannot take 1000 mA (max 570 mA at 95 %) */
    reset(0);
    load.load_mohm = 20000;
    fake_set_plant(fake_plant_resistive, &load);
    cmd_limits(2500, 5000);
    cmd_u8(MSG_ENABLE, 1);
    cmd_u16(MSG_SET_CURRENT, 1000);
    ticks(1000);
    CHECK(st()->duty == 971 && fake_pwm_duty() == 971, "saturated at 95 %%: %u", st()->duty);
    CHECK(st()->flags & FLAG_LIMIT_ACTIVE, "LIMIT_ACTIVE at the duty limit");
    CHECK(st()->enabled, "no open-wire fault at 570 mA");
    /* recover: load back to the reference one, the integrator has not wound up */
    load.load_mohm = 4200;
    uint16_t peak;
    int ms = settle_ms(1000, 300, &peak);
    printf("PI recovery from saturation: settled in %d ms, peak %u mA\n", ms, peak);
    /* the first sample after the swap is still at 95 % duty (2.7 A): physics, not windup */
    CHECK(ms <= 50, "recovery after saturation: %d ms, peak %u", ms, peak);
    CHECK(!(st()->flags & FLAG_LIMIT_ACTIVE), "LIMIT_ACTIVE cleared");
    /* saturated again, then a lower setpoint reachable by the weak load */
    load.load_mohm = 20000;
    ticks(500);
    CHECK(st()->duty == 971, "saturated again");
    cmd_u16(MSG_SET_CURRENT, 300);
    ticks(2);
    CHECK(st()->duty < 971, "duty leaves the clamp at once (no wound-up integrator): %u", st()->duty);
    ms = settle_ms(300, 300, &peak);
    CHECK(ms <= 150, "down-step after saturation, weak 20 Ohm plant: %d ms", ms);
    /* LIMIT_ACTIVE at the current limit */
    cmd_u8(MSG_ENABLE, 0);
    load.load_mohm = 4200;
    cmd_limits(800, 5000);
    cmd_u8(MSG_ENABLE, 1);
    CHECK(cmd_u16(MSG_SET_CURRENT, 900) == ST_CLAMPED, "clamped");
    ticks(100);
    CHECK((st()->flags & FLAG_LIMIT_ACTIVE) && abs((int)st()->current_ma - 800) < 40,
          "at current limit: %u mA", st()->current_ma);
    /* disabled: duty 0 whatever the error */
    cmd_u8(MSG_ENABLE, 0);
    ticks(10);
    CHECK(fake_pwm_duty() == 0 && st()->duty == 0, "disabled: duty 0");
}

/* ------------------------------------------------------------------ telemetry */
static double ntc_expect_cdeg(double mv)
{
    double r = 10000.0 * (5000.0 - mv) / mv;
    return (1.0 / (1.0 / 298.15 + log(r / 10000.0) / 3950.0) - 273.15) * 100.0;
}

static void test_telemetry(void)
{
    reset(0);
    fake_set_millis(5000);
    cmd_limits(2500, 5000);
    CHECK(cmd_u16(MSG_SET_TELEMETRY, 10) == ST_OK, "telemetry 10 ms");
    fake_adc_set(HAL_ADC_CURRENT, 1234);
    fake_adc_set(HAL_ADC_VOLTAGE, 1000);
    fake_adc_set(HAL_ADC_AMBIENT, 2500);
    cmd_u16(MSG_SET_CURRENT, 1500);
    uint8_t junk[] = {0x05, 0x42, 0x00, 0x01, 0x04, 0x07, 0xE8, 0x6E, 0x00}; /* 1 frame + 1 crc err */
    fake_rx_push(junk, sizeof junk);
    int total = 0;
    uint32_t first_t = 0, last_t = 0;
    for (int t = 0; t < 1000; t++) {
        tick();
        int n = take_tx();
        CHECK(n <= 1, "one frame per tick");
        if (n == 1) {
            const uint8_t *p = rxp[0].payload;
            CHECK(rxp[0].type == MSG_TELEMETRY && rxp[0].len == 20, "telemetry frame");
            uint32_t tm = rd16(p) | ((uint32_t)rd16(p + 2) << 16);
            if (total == 0) first_t = tm;
            CHECK(tm == hal_millis(), "time %u", (unsigned)tm);
            CHECK(total == 0 || tm - last_t == 10, "period %u", (unsigned)(tm - last_t));
            last_t = tm;
            total++;
        }
    }
    CHECK(total == 100, "100 frames in 1 s at 10 ms: %d", total);
    CHECK(first_t == 5001, "first frame at the first tick: %u", (unsigned)first_t);
    /* layout, enabled at full duty */
    cmd_u8(MSG_ENABLE, 1);
    fake_adc_set(HAL_ADC_CURRENT, 100); /* 100 mA: saturates, but no open wire */
    ticks(200);
    take_tx();
    ticks(10);
    CHECK(take_tx() == 1, "frame");
    const uint8_t *p = rxp[0].payload;
    CHECK(rd16(p + 4) == 100, "current");
    CHECK(rd16(p + 6) == 3000, "voltage 3 x 1000 mV: %u", rd16(p + 6));
    CHECK(rd16(p + 8) == (uint16_t)(971u * 65535u / 1023u), "duty %u", rd16(p + 8));
    CHECK((int16_t)rd16(p + 10) == 2500, "ambient 25.00 C: %d", (int16_t)rd16(p + 10));
    CHECK(rd16(p + 12) == st()->flags && (rd16(p + 12) & (FLAG_ENABLED | FLAG_LIMIT_ACTIVE)) ==
                                             (FLAG_ENABLED | FLAG_LIMIT_ACTIVE),
          "flags 0x%04X", rd16(p + 12));
    CHECK(rd16(p + 14) == 1500, "setpoint");
    CHECK(rd16(p + 16) == 1 && rd16(p + 18) == 1, "crc/frame errors %u/%u", rd16(p + 16), rd16(p + 18));
    fake_adc_set(HAL_ADC_CURRENT, 1234);
    cmd_u8(MSG_ENABLE, 0);
    /* ambient conversion over the range */
    const uint16_t mvs[] = {300, 1000, 1700, 2500, 3300, 4000, 4700};
    for (size_t i = 0; i < sizeof mvs / sizeof mvs[0]; i++) {
        fake_adc_set(HAL_ADC_AMBIENT, mvs[i]);
        ticks(10);
        CHECK(take_tx() == 1, "frame");
        double want = ntc_expect_cdeg(mvs[i]);
        int16_t got = (int16_t)rd16(rxp[0].payload + 10);
        CHECK(fabs(got - want) <= 1.0, "ambient at %u mV: %d, want %.1f", mvs[i], got, want);
        CHECK(rd16(rxp[0].payload + 4) == 1234, "current");
    }
    fake_adc_set(HAL_ADC_AMBIENT, 0); /* open NTC: saturates, no crash */
    ticks(10);
    fake_adc_set(HAL_ADC_AMBIENT, 5000);
    ticks(10);
    CHECK(take_tx() == 2, "extreme ambient");
    /* off */
    CHECK(cmd_u16(MSG_SET_TELEMETRY, 0) == ST_OK, "off");
    ticks(2000);
    CHECK(take_tx() == 0, "no telemetry when off");
    /* slow rate */
    cmd_u16(MSG_SET_TELEMETRY, 1000);
    ticks(3000);
    int n1 = take_tx();
    CHECK(n1 == 3, "1 s period: %d", n1);
}

static void test_watchdog_flag(void)
{
    reset(1);
    CHECK(st()->flags & FLAG_WATCHDOG_RESET, "watchdog flag set");
    CHECK(!st()->enabled && fake_pwm_duty() == 0, "off after watchdog reset");
    cmd_u16(MSG_SET_TELEMETRY, 5);
    tick();
    CHECK(take_tx() == 1 && (rd16(rxp[0].payload + 12) & FLAG_WATCHDOG_RESET), "in telemetry");
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK, "not a latched fault");
    CHECK(st()->flags & FLAG_WATCHDOG_RESET, "ENABLE keeps it");
    CHECK(cmd(MSG_CLEAR_FAULTS, NULL, 0) == ST_OK && !(st()->flags & FLAG_WATCHDOG_RESET), "cleared");
    reset(0);
    CHECK(!(st()->flags & FLAG_WATCHDOG_RESET), "normal reset");
}

static void test_resync(void)
{
    reset(0);
    srand(99);
    uint8_t noise[500];
    for (size_t i = 0; i < sizeof noise; i++) noise[i] = (uint8_t)rand();
    fake_rx_push(noise, sizeof noise);
    uint8_t z = 0;
    fake_rx_push(&z, 1);
    CHECK(cmd(MSG_PING, NULL, 0) == ST_OK, "valid frame after noise + 00");
    CHECK(st()->rx_frame_errors + st()->rx_crc_errors > 0, "noise counted");
    /* noise without a delimiter costs the frame it hits, not the next one */
    uint8_t garbage[30];
    memset(garbage, 0x77, sizeof garbage);
    fake_rx_push(garbage, sizeof garbage);
    push_frame(200, MSG_PING, NULL, 0); /* lost */
    CHECK(cmd_u8(MSG_ENABLE, 1) == ST_OK, "next frame handled");
    /* byte-by-byte delivery, split across polls */
    uint8_t out[FRAME_MAX_WIRE];
    uint8_t pl[2] = {0x00, 0x01}; /* 256 mA: a zero byte inside */
    uint8_t n = frame_encode(77, MSG_SET_CURRENT, pl, 2, out, sizeof out);
    for (uint8_t i = 0; i < n; i++) {
        fake_rx_push(&out[i], 1);
        core_poll();
    }
    CHECK(take_tx() == 1 && rxp[0].payload[0] == 77 && st()->setpoint_ma == 256, "split frame");
    /* a full TX buffer drops the ACK, no crash, later frames fine */
    fake_tx_set_limit(5);
    push_frame(1, MSG_PING, NULL, 0);
    core_poll();
    fake_tx_clear();
    fake_tx_set_limit(FAKE_TX_CAP);
    frame_rx_init(&host_rx);
    CHECK(cmd(MSG_PING, NULL, 0) == ST_OK, "after TX overflow");
}

int main(int argc, char **argv)
{
    test_crc();
    test_cobs();
    test_frame_rx();
    for (int i = 1; i < argc; i++) test_vectors(argv[i]);
    if (argc < 2) printf("note: no vectors file given (usage: test_core vectors.txt ...)\n");
    test_commands();
    test_host_timeout();
    test_overcurrent();
    test_open_wire();
    test_pi();
    test_telemetry();
    test_watchdog_flag();
    test_resync();
    printf("%d checks, %d failures\n", checks, failures);
    return failures ? 1 : 0;
}
