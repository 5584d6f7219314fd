/* Portable firmware core (core.h, PROTOCOL.md): commands, PI current control, safety. */
#include <math.h>
#include <stddef.h>
#include "core.h"
#include "frame.h"
#include "hal.h"
#include "proto.h"

/* Duty clamp: 95 % of the PWM range (971 of 1023). */
#define DUTY_MAX ((uint16_t)((uint32_t)HAL_PWM_TOP * 95u / 100u))
#define DUTY_OPEN_WIRE (HAL_PWM_TOP / 2u) /* "duty above 50 %" */

/* PI gains in Q16 duty counts per mA (per tick for Ki). Tuned for the reference load, 12 V
 * through 4.2 Ohm: ~2.8 mA per count, i.e. loop gains Kp*K ~ 0.06, Ki*K ~ 0.14 per tick: a step
 * settles to 5 % in ~22 ms; stable up to ~5x the reference plant gain. */
#define PI_KP_Q16 1311 /* 0.020 counts/mA */
#define PI_KI_Q16 3277 /* 0.050 counts/mA per ms */
#define PI_INTEG_MAX ((int32_t)DUTY_MAX << 16)
#define PI_ERR_MAX_MA 8000 /* |error| clamp, mA */

/* NTC divider: NTC (R25 = 10 kOhm, B = 3950 K) on top, 10 kOhm bottom, AVcc = 5000 mV. */
#define NTC_VCC_MV 5000.0f
#define NTC_B_K 3950.0f
#define NTC_T25_K 298.15f

static core_state_t s;
static frame_rx_t rx;
static int32_t integ_q16;        /* PI integrator, duty counts in Q16, clamped 0 ... DUTY_MAX */
static uint32_t last_rx_ms;      /* time of the last valid frame */
static uint32_t next_telem_ms;   /* when the next telemetry frame is due */
static uint8_t telem_restart;    /* period changed: send at the next tick, then every period */
static uint8_t overcurrent_ms;   /* consecutive ticks above limit * 1.2 */
static uint8_t open_wire_ms;     /* consecutive ticks at duty > 50 % and current < 20 mA */
static uint8_t tx_seq;
static uint16_t voltage_mv;      /* last wire voltage */

/* ------------------------------------------------------------------ helpers */
static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    put_u16(p, (uint16_t)(v & 0xFFFFu));
    put_u16(p + 2, (uint16_t)(v >> 16));
}

static void send(uint8_t type, const uint8_t *payload, uint8_t len)
{
    uint8_t out[FRAME_MAX_WIRE];
    uint8_t n = frame_encode(tx_seq, type, payload, len, out, sizeof out);
    if (n != 0u) {
        (void)hal_uart_write(out, n); /* a full TX buffer drops bytes; the host resyncs */
        tx_seq++;
    }
}

static void set_flag(uint16_t flag, uint8_t on)
{
    s.flags = on ? (uint16_t)(s.flags | flag) : (uint16_t)(s.flags & ~flag);
}

static void output_off(void)
{
    s.enabled = 0;
    s.duty = 0;
    integ_q16 = 0;
    overcurrent_ms = 0;
    open_wire_ms = 0;
    hal_pwm_set(0);
    set_flag(FLAG_ENABLED | FLAG_LIMIT_ACTIVE, 0);
}

static void latch(uint16_t fault)
{
    s.flags |= fault;
    output_off();
}

/* NTC divider voltage (mV) to temperature, 0.01 degC (B equation). */
static int16_t ntc_cdeg(uint16_t mv)
{
    if (mv < 1u) {
        mv = 1u;
    } else if (mv > 4999u) {
        mv = 4999u;
    }
    float r_rel = (NTC_VCC_MV - (float)mv) / (float)mv; /* R_ntc / R25 */
    float t_c = 1.0f / (1.0f / NTC_T25_K + logf(r_rel) / NTC_B_K) - 273.15f;
    float cdeg = t_c * 100.0f;
    if (cdeg > 32767.0f) {
        return 32767;
    }
    if (cdeg < -32768.0f) {
        return -32768;
    }
    return (int16_t)(cdeg >= 0.0f ? cdeg + 0.5f : cdeg - 0.5f);
}

/* ------------------------------------------------------------------ commands */
/* Expected payload length of a command, 0xFF for an unknown type. */
static uint8_t expected_len(uint8_t type)
{
    switch (type) {
    case MSG_IDENTIFY:
    case MSG_ENABLE: return 1;
    case MSG_SET_CURRENT:
    case MSG_SET_TELEMETRY: return 2;
    case MSG_SET_LIMITS: return 4;
    case MSG_CLEAR_FAULTS:
    case MSG_PING: return 0;
    default: return 0xFFu;
    }
}

static uint8_t cmd_enable(uint8_t on)
{
    if (on > 1u) {
        return ST_OUT_OF_RANGE;
    }
    if (!on) {
        output_off();
        return ST_OK;
    }
    if (s.flags & FLAGS_LATCHED) {
        return ST_FAULT_ACTIVE;
    }
    if (!s.enabled) {
        integ_q16 = 0;
        overcurrent_ms = 0;
        open_wire_ms = 0;
    }
    s.enabled = 1;
    s.flags = (uint16_t)((s.flags | FLAG_ENABLED) & ~FLAG_HOST_TIMEOUT);
    return ST_OK;
}

static uint8_t cmd_set_current(uint16_t ma)
{
    if (ma > s.limit_ma) {
        s.setpoint_ma = s.limit_ma;
        return ST_CLAMPED;
    }
    s.setpoint_ma = ma;
    return ST_OK;
}

static uint8_t cmd_set_limits(uint16_t limit_ma, uint16_t timeout_ms)
{
    if (limit_ma > CORE_HARD_LIMIT_MA || timeout_ms < HOST_TIMEOUT_MIN_MS ||
        timeout_ms > HOST_TIMEOUT_MAX_MS) {
        return ST_OUT_OF_RANGE;
    }
    s.limit_ma = limit_ma;
    s.host_timeout_ms = timeout_ms;
    if (s.setpoint_ma > limit_ma) {
        s.setpoint_ma = limit_ma;
    }
    return ST_OK;
}

static uint8_t cmd_set_telemetry(uint16_t period_ms)
{
    if (period_ms != 0u && (period_ms < TELEMETRY_MIN_MS || period_ms > TELEMETRY_MAX_MS)) {
        return ST_OUT_OF_RANGE;
    }
    s.telemetry_period_ms = period_ms;
    telem_restart = 1; /* first frame at the next tick */
    return ST_OK;
}

static void cmd_clear_faults(void)
{
    s.flags &= (uint16_t)~(FLAGS_LATCHED | FLAG_HOST_TIMEOUT | FLAG_WATCHDOG_RESET);
    overcurrent_ms = 0;
    open_wire_ms = 0;
}

/* IDENTIFY: ACK data = proto ver, fw major/minor/patch, u16 hard limit, name. */
static uint8_t identify_data(uint8_t *d)
{
    static const char name[] = DEVICE_NAME;
    d[0] = CORE_PROTOCOL_VERSION;
    d[1] = FW_VERSION_MAJOR;
    d[2] = FW_VERSION_MINOR;
    d[3] = FW_VERSION_PATCH;
    put_u16(&d[4], CORE_HARD_LIMIT_MA);
    for (uint8_t i = 0; i < sizeof name - 1u; i++) {
        d[6u + i] = (uint8_t)name[i];
    }
    return (uint8_t)(6u + sizeof name - 1u);
}

static uint8_t run_command(const frame_packet_t *p, uint8_t *data, uint8_t *data_len)
{
    uint8_t want = expected_len(p->type);
    if (want == 0xFFu) {
        return ST_UNKNOWN_COMMAND;
    }
    if (p->len != want) {
        return ST_BAD_LENGTH;
    }
    const uint8_t *a = p->payload;
    switch (p->type) {
    case MSG_IDENTIFY:
        *data_len = identify_data(data);
        return a[0] == CORE_PROTOCOL_VERSION ? ST_OK : ST_VERSION_MISMATCH;
    case MSG_ENABLE: return cmd_enable(a[0]);
    case MSG_SET_CURRENT: return cmd_set_current(get_u16(a));
    case MSG_SET_LIMITS: return cmd_set_limits(get_u16(a), get_u16(a + 2));
    case MSG_SET_TELEMETRY: return cmd_set_telemetry(get_u16(a));
    case MSG_CLEAR_FAULTS: cmd_clear_faults(); return ST_OK;
    default: return ST_OK; /* PING: only feeds the host watchdog */
    }
}

static void handle(const frame_packet_t *p)
{
    uint8_t ack[3u + 6u + sizeof DEVICE_NAME - 1u];
    uint8_t data_len = 0;
    ack[0] = p->seq;
    ack[1] = p->type;
    ack[2] = run_command(p, &ack[3], &data_len);
    send(MSG_ACK, ack, (uint8_t)(3u + data_len));
}

/* ------------------------------------------------------------------ control */
static void check_faults(void)
{
    uint32_t oc_ma = (uint32_t)s.limit_ma * 6u / 5u; /* limit + 20 % */
    overcurrent_ms = s.current_ma > oc_ma ? (uint8_t)(overcurrent_ms + 1u) : 0u;
    /* s.duty is the duty that produced this measurement */
    uint8_t open = s.duty > DUTY_OPEN_WIRE && s.current_ma < OPEN_WIRE_MA;
    open_wire_ms = open ? (uint8_t)(open_wire_ms + 1u) : 0u;
    if (overcurrent_ms >= OVERCURRENT_MS) {
        latch(FLAG_OVERCURRENT);
    } else if (open_wire_ms >= OPEN_WIRE_MS) {
        latch(FLAG_OPEN_WIRE);
    }
}

/* One PI step; returns the new duty, 0 ... DUTY_MAX. */
static uint16_t pi_step(int16_t err_ma)
{
    integ_q16 += (int32_t)PI_KI_Q16 * err_ma;
    if (integ_q16 < 0) {
        integ_q16 = 0; /* anti-windup: clamp the integrator to the duty range */
    } else if (integ_q16 > PI_INTEG_MAX) {
        integ_q16 = PI_INTEG_MAX;
    }
    int32_t out = (integ_q16 + (int32_t)PI_KP_Q16 * err_ma) >> 16;
    if (out < 0) {
        return 0;
    }
    return out > (int32_t)DUTY_MAX ? DUTY_MAX : (uint16_t)out;
}

static void send_telemetry(uint32_t now)
{
    uint8_t t[TELEMETRY_LEN];
    put_u32(&t[0], now);
    put_u16(&t[4], s.current_ma);
    put_u16(&t[6], voltage_mv);
    put_u16(&t[8], (uint16_t)((uint32_t)s.duty * 65535u / HAL_PWM_TOP));
    put_u16(&t[10], (uint16_t)ntc_cdeg(hal_adc_mv(HAL_ADC_AMBIENT)));
    put_u16(&t[12], s.flags);
    put_u16(&t[14], s.setpoint_ma);
    put_u16(&t[16], s.rx_crc_errors);
    put_u16(&t[18], s.rx_frame_errors);
    send(MSG_TELEMETRY, t, sizeof t);
}

static void telemetry_tick(uint32_t now)
{
    if (s.telemetry_period_ms == 0u) {
        return;
    }
    if (telem_restart) {
        telem_restart = 0;
        next_telem_ms = now;
    }
    if ((int32_t)(now - next_telem_ms) < 0) {
        return;
    }
    send_telemetry(now);
    next_telem_ms += s.telemetry_period_ms;
    if ((int32_t)(now - next_telem_ms) >= 0) {
        next_telem_ms = now + s.telemetry_period_ms; /* fell behind: skip, do not burst */
    }
}

/* ------------------------------------------------------------------ API */
void core_init(uint8_t was_watchdog_reset)
{
    s = (core_state_t){0};
    s.limit_ma = CORE_HARD_LIMIT_MA;
    s.host_timeout_ms = HOST_TIMEOUT_DEFAULT_MS;
    s.flags = was_watchdog_reset ? FLAG_WATCHDOG_RESET : 0u;
    frame_rx_init(&rx);
    tx_seq = 0;
    voltage_mv = 0;
    last_rx_ms = hal_millis();
    next_telem_ms = last_rx_ms;
    telem_restart = 0;
    output_off();
}

void core_poll(void)
{
    int16_t c;
    frame_packet_t pkt;
    while ((c = hal_uart_read()) >= 0) {
        if (frame_rx_push(&rx, (uint8_t)c, &pkt)) {
            last_rx_ms = hal_millis(); /* every valid frame feeds the host watchdog */
            handle(&pkt);
        }
    }
    s.rx_crc_errors = rx.crc_errors;
    s.rx_frame_errors = rx.frame_errors;
}

void core_control_tick(void)
{
    uint32_t now = hal_millis();
    s.current_ma = hal_adc_mv(HAL_ADC_CURRENT); /* 1 V per A: mA = mV */
    uint32_t v_mv = 3u * (uint32_t)hal_adc_mv(HAL_ADC_VOLTAGE); /* 1/3 divider */
    voltage_mv = v_mv > 0xFFFFu ? 0xFFFFu : (uint16_t)v_mv;
    if (s.enabled && (uint32_t)(now - last_rx_ms) >= s.host_timeout_ms) {
        output_off();
        s.flags |= FLAG_HOST_TIMEOUT;
    }
    if (s.enabled) {
        check_faults();
    }
    if (s.enabled) {
        int32_t err = (int32_t)s.setpoint_ma - (int32_t)s.current_ma;
        if (err < -PI_ERR_MAX_MA) {
            err = -PI_ERR_MAX_MA; /* keeps the Q16 products inside int32 */
        }
        s.duty = pi_step((int16_t)err);
        hal_pwm_set(s.duty);
        uint8_t at_limit = (s.setpoint_ma != 0u && s.setpoint_ma >= s.limit_ma) ||
                           s.duty >= DUTY_MAX;
        set_flag(FLAG_LIMIT_ACTIVE, at_limit);
    }
    telemetry_tick(now);
}

const core_state_t *core_state(void)
{
    return &s;
}
