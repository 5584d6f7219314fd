/* Portable firmware core (core.h, PROTOCOL.md v4): commands, current control of the linear sink,
 * measurements, safety. The electrical numbers come from electrical.h, generated from
 * firmware/hardware/electrical.toml. */
#include <math.h>
#include <stddef.h>
#include "core.h"
#include "crc16.h"
#include "electrical.h"
#include "frame.h"
#include "hal.h"
#include "proto.h"

#define DUTY_MAX HAL_PWM_TOP
/* Setpoint PWM counts per mA: 1000 * 256 / ELEC_SETPOINT_UA_PER_COUNT_Q8 (feed-forward). */
#define FF_Q16_PER_MA ((uint32_t)((65536.0 * 256000.0) / ELEC_SETPOINT_UA_PER_COUNT_Q8 + 0.5))

/* Current loop: feed-forward duty = setpoint / (sink mA per count), plus a PI trim on the
 * measured current that only corrects the setpoint path's tolerances (divider, op-amp offset,
 * PWM level). Plant seen by the trim (linear region): K = 2.60 mA per count, two RC poles of
 * 1 ms, anti-alias 0.1 ms, 1 ms averaging + 1 tick delay; independent of the wire resistance and
 * the supply until the sink runs out of headroom (compliance), where the trim is frozen.
 * Ki*K = 0.05 per ms, Kp*K = 0.2: the loop's frequency response (poles, zero-order hold, the
 * mean over a tick, anti-alias RC, one tick of computation) crosses over at 51 rad/s (8 Hz) with
 * 92 deg of phase margin and 7.9x (18 dB) of gain margin. Setpoint steps do not go through it:
 * the trim compares with a reference model of the poles. Host tests: steps across 0.3 ... 1 Ohm
 * and 4.75 ... 5.5 V settle within 7 ms. */
#define PI_KP_Q16 5041 /* 0.077 counts/mA */
#define PI_KI_Q16 1260 /* 0.0192 counts/mA per ms */
#define TRIM_LEARN_MIN_MA 200 /* below, offsets dominate the path error: the trim holds */
#define TRIM_MAX_Q16 (65536 / 8) /* the trim corrects the setpoint path by at most 12.5 % */

/* The longest ACK: seq, type, status + IDENTIFY's data (6 bytes + name; the other data is
 * at most 8 bytes). A command is taken from the RX buffer only when an ACK this long fits in the
 * TX buffer, so every command gets its ACK, whole. */
#define ACK_MAX_DATA (6u + sizeof DEVICE_NAME - 1u > 8u ? 6u + sizeof DEVICE_NAME - 1u : 8u)
#define ACK_MAX_PAYLOAD (3u + ACK_MAX_DATA)
#define ACK_MAX_WIRE (COBS_MAX_ENCODED(ACK_MAX_PAYLOAD + 4u) + 1u)
/* telemetry leaves this much room for an ACK, so it never delays one */
#define TELEMETRY_MAX_WIRE (COBS_MAX_ENCODED(TELEMETRY_LEN + 4u) + 1u)

#define XADC_PERIOD_MS 2u  /* ADS1115 at 860 SPS: a conversion takes <= 1.3 ms */
#define XADC_AVERAGE 4u    /* conversions averaged per published value */
#define XADC_FAULT_AFTER 3u
#define WIRE_R_MIN_MA 20u  /* a wire window's mean current below this gives no resistance */
#define SLOW_PERIOD_MS 100u /* NTC, thermocouple (MAX31855 converts in <= 100 ms) */
#define NTC_T_MIN_C (-40.0f) /* NTC rated range: outside it the reading is implausible */
#define NTC_T_MAX_C 125.0f

static core_state_t s;
static frame_rx_t rx;
static int32_t integ_q16;        /* trim: relative gain correction of the setpoint path, Q16 */
static int32_t ref1_q8, ref2_q8, ref2_prev_q8; /* reference model of the setpoint path (mA * 256) */
static int32_t ref_alpha_q8;     /* 1 - exp(-1 ms / tau) of the setpoint filter's poles, Q8 */
static uint32_t last_rx_ms;      /* time of the last valid frame */
static uint32_t lease_start_ms;  /* last SET_CURRENT or ENABLE 1 */
static uint32_t next_telem_ms;
static uint8_t telem_restart;
static uint8_t overcurrent_ms;
static uint8_t open_wire_ms;
static uint8_t tx_seq;
static uint8_t compliance;       /* the sink is out of headroom: the trim is frozen */
static uint16_t dissipation_cap_ma;
static float measured_r_ohm;     /* V/I from the external ADC, 0 when unknown */
static float ambient_c;          /* last plausible ambient, or the fallback */
/* external ADC */
static uint8_t xadc_channel, xadc_pending, xadc_fails, xadc_n;
static int32_t xadc_sum;
/* fast-path current over the running window (mA) and the mean it had over each channel's last
 * published window; 0xFFFF: that window saw the current change (a step), no R from it */
static uint16_t xadc_i_min, xadc_i_max, xadc_i_at[2];
/* the wire channel's window paired conversion by conversion: the fast-path current over each
 * conversion (its first ms, xadc_conv_ma, and the next), summed over the window; the window's
 * V / I in mOhm (0: unknown) */
static uint16_t xadc_conv_ma;
static uint32_t xadc_isum;
static float wire_mohm;
static uint16_t xadc_timer;
static uint16_t slow_timer;
/* heat model, precomputed from s.heat */
static float heat_r_ohm, heat_g_w_k, heat_dt_over_c;
static uint16_t probe_cap_ma = PROBE_MAX_MA; /* the probe within PROBE_MAX_MW on heat_r_ohm */
static uint32_t heat_i2_sum; /* sum of I^2 over the current model step, mA^2 */
static uint8_t heat_ticks;
#define HEAT_STEP_MS 10u
/* hardware cut */
static uint8_t cut_startup_ms;   /* ticks since reset until the power-on clear */
static uint8_t cut_wdt_reset;    /* reset by the watchdog: the cut's trip is reported, not cleared */
static uint8_t cut_supply_low_ms;
static uint8_t cut_en_low_ms;
static uint32_t avcc_q4;         /* running mean of the measured AVcc, mV * 16; 0: none yet */

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

static int16_t cdeg(float c)
{
    float x = c * 100.0f;
    if (!(x > -32768.0f)) { /* also NaN */
        return -32768;
    }
    if (x > 32766.0f) {
        return 32766; /* 32767 is TEMP_NONE */
    }
    return (int16_t)(x >= 0.0f ? x + 0.5f : x - 0.5f);
}

/* Frames go out whole or not at all (PROTOCOL.md "Flow control"): a frame is queued only when
 * the TX ring has room for all of it; returns 1 when queued, 0 when it did not fit. */
static uint8_t send(uint8_t type, const uint8_t *payload, uint8_t len)
{
    uint8_t out[FRAME_MAX_WIRE];
    uint8_t n = frame_encode(tx_seq, type, payload, len, out, sizeof out);
    if (n == 0u || hal_uart_tx_free() < n) {
        return 0;
    }
    (void)hal_uart_write(out, n); /* fits: all n bytes are taken */
    tx_seq++;
    return 1;
}

static void set_flag(uint16_t flag, uint8_t on)
{
    s.flags = on ? (uint16_t)(s.flags | flag) : (uint16_t)(s.flags & ~flag);
}

/* Everything that turns the output off goes through here (ENABLE 0, the host timeout, the lease,
 * every latched fault: e-stop, cut, over-temperature, ...; reset): the probe current goes off with
 * it and stays off until the next SET_PROBE (PROTOCOL.md "Safety"). */
static void output_off(void)
{
    s.enabled = 0;
    s.duty = 0;
    s.probe_ma = 0;
    ref1_q8 = ref2_q8 = ref2_prev_q8 = 0;
    overcurrent_ms = 0;
    open_wire_ms = 0;
    hal_pwm_set(0);
    hal_output_enable(0);
    set_flag(FLAG_ENABLED | FLAG_LIMIT_ACTIVE | FLAG_DISSIPATION, 0);
}

static void latch(uint16_t fault)
{
    s.flags |= fault;
    output_off();
}

/* ------------------------------------------------------------------ EEPROM blocks */
/* A block: magic, version, data, CRC-16 of magic..data (little-endian). */
static uint8_t ee_load(uint16_t addr, uint8_t magic, uint8_t *data, uint8_t len)
{
    uint8_t buf[16];
    hal_eeprom_read(addr, buf, (uint8_t)(len + 4u));
    uint16_t crc = crc16_ccitt(buf, (uint8_t)(len + 2u));
    if (buf[0] != magic || buf[1] != 1u || get_u16(&buf[len + 2u]) != crc) {
        return 0;
    }
    for (uint8_t i = 0; i < len; i++) {
        data[i] = buf[2u + i];
    }
    return 1;
}

static void ee_store(uint16_t addr, uint8_t magic, const uint8_t *data, uint8_t len)
{
    uint8_t buf[16];
    buf[0] = magic;
    buf[1] = 1u;
    for (uint8_t i = 0; i < len; i++) {
        buf[2u + i] = data[i];
    }
    put_u16(&buf[len + 2u], crc16_ccitt(buf, (uint8_t)(len + 2u)));
    hal_eeprom_write(addr, buf, (uint8_t)(len + 4u));
}

static void cal_pack(uint8_t *d)
{
    put_u16(d, (uint16_t)s.cal.offset_ua);
    put_u16(d + 2, s.cal.current_gain);
    put_u16(d + 4, s.cal.voltage_gain);
    put_u16(d + 6, (uint16_t)s.cal.voltage_offset_uv);
}

static void heat_pack(uint8_t *d)
{
    put_u16(d, s.heat.r_mohm);
    put_u16(d + 2, s.heat.c);
    put_u16(d + 4, s.heat.g);
    put_u16(d + 6, s.heat.tmax_dc);
}

static uint8_t cal_valid(int16_t off, uint16_t ig, uint16_t vg)
{
    (void)off; /* every i16 offset (current uA, wire voltage uV) is in range */
    return ig >= CAL_GAIN_MIN && ig <= CAL_GAIN_MAX && vg >= CAL_GAIN_MIN && vg <= CAL_GAIN_MAX;
}

static uint8_t heat_valid(uint16_t r, uint16_t c, uint16_t g, uint16_t tmax)
{
    return r >= HEAT_R_MIN_MOHM && r <= HEAT_R_MAX_MOHM && c >= HEAT_C_MIN && g >= HEAT_G_MIN &&
           tmax >= HEAT_TMAX_MIN_DC && tmax <= HEAT_TMAX_MAX_DC;
}

static void heat_apply(void)
{
    heat_r_ohm = (float)s.heat.r_mohm * 1e-3f;
    heat_g_w_k = (float)s.heat.g * 1e-5f;
    heat_dt_over_c = (float)HEAT_STEP_MS * 1e-3f / ((float)s.heat.c * 1e-4f); /* step / (J/K) */
    float cap_ma = 1e3f * sqrtf((float)PROBE_MAX_MW * 1e-3f / heat_r_ohm);
    probe_cap_ma = cap_ma < (float)PROBE_MAX_MA ? (uint16_t)cap_ma : PROBE_MAX_MA;
}

static void load_eeprom(void)
{
    uint8_t d[8];
    uint8_t ok = 1;
    s.cal = (core_cal_t){0, CAL_GAIN_ONE, CAL_GAIN_ONE, 0};
    /* a protocol-2 block (magic 'C', 6 bytes, no voltage offset) is not read: defaults */
    if (ee_load(EE_CAL_ADDR, EE_CAL_MAGIC, d, CAL_LEN) &&
        cal_valid((int16_t)get_u16(d), get_u16(d + 2), get_u16(d + 4))) {
        s.cal = (core_cal_t){(int16_t)get_u16(d), get_u16(d + 2), get_u16(d + 4),
                             (int16_t)get_u16(d + 6)};
    } else {
        ok = 0;
    }
    s.heat = (core_heat_t){HEAT_DEFAULT_R_MOHM, HEAT_DEFAULT_C, HEAT_DEFAULT_G,
                           HEAT_DEFAULT_TMAX_DC};
    if (ee_load(EE_HEAT_ADDR, 'H', d, 8) &&
        heat_valid(get_u16(d), get_u16(d + 2), get_u16(d + 4), get_u16(d + 6))) {
        s.heat = (core_heat_t){get_u16(d), get_u16(d + 2), get_u16(d + 4), get_u16(d + 6)};
    } else {
        ok = 0;
    }
    set_flag(FLAG_CAL_DEFAULT, !ok);
    heat_apply();
}

/* ------------------------------------------------------------------ commands */
/* Expected payload length of a command, 0xFF for an unknown type. */
static uint8_t expected_len(uint8_t type)
{
    switch (type) {
    case MSG_IDENTIFY:
    case MSG_ENABLE: return 1;
    case MSG_SET_CURRENT:
    case MSG_SET_TELEMETRY:
    case MSG_SET_LEASE:
    case MSG_SET_PROBE: return 2;
    case MSG_SET_LIMITS: return 4;
    case MSG_SET_CALIBRATION: return CAL_LEN;
    case MSG_SET_HEAT_MODEL: return 8;
    case MSG_CLEAR_FAULTS:
    case MSG_PING:
    case MSG_GET_CALIBRATION:
    case MSG_GET_HEAT_MODEL: return 0;
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
        overcurrent_ms = 0;
        open_wire_ms = 0;
    }
    s.enabled = 1;
    lease_start_ms = hal_millis();
    hal_output_enable(1);
    s.flags = (uint16_t)((s.flags | FLAG_ENABLED) & ~(FLAG_HOST_TIMEOUT | FLAG_LEASE_EXPIRED));
    return ST_OK;
}

static uint8_t cmd_set_current(uint16_t ma)
{
    lease_start_ms = hal_millis(); /* every SET_CURRENT renews the lease */
    if (ma > s.limit_ma) {
        s.setpoint_ma = s.limit_ma;
        return ST_CLAMPED;
    }
    s.setpoint_ma = ma;
    return ST_OK;
}

/* SET_PROBE: a small current held while the output is enabled, so the wire's resistance is
 * measured while it cools. Not leased (it is not heating: <= 100 mA) and not a setpoint: the
 * setpoint, its lease and its telemetry field are untouched. Accepted enabled or disabled. */
static uint8_t cmd_set_probe(uint16_t ma)
{
    if (ma > PROBE_MAX_MA) {
        return ST_OUT_OF_RANGE;
    }
    s.probe_ma = ma;
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

static uint8_t cmd_set_lease(uint16_t ms)
{
    if (ms < LEASE_MIN_MS || ms > LEASE_MAX_MS) {
        return ST_OUT_OF_RANGE;
    }
    s.lease_ms = ms;
    return ST_OK;
}

static uint8_t cmd_set_calibration(const uint8_t *a)
{
    int16_t off = (int16_t)get_u16(a);
    uint16_t ig = get_u16(a + 2), vg = get_u16(a + 4);
    if (!cal_valid(off, ig, vg)) {
        return ST_OUT_OF_RANGE;
    }
    if (s.enabled) {
        return ST_OUTPUT_ON;
    }
    s.cal = (core_cal_t){off, ig, vg, (int16_t)get_u16(a + 6)};
    uint8_t d[CAL_LEN];
    cal_pack(d);
    ee_store(EE_CAL_ADDR, EE_CAL_MAGIC, d, CAL_LEN);
    load_eeprom(); /* read back: the flag says whether it stuck */
    return ST_OK;
}

static uint8_t cmd_set_heat_model(const uint8_t *a)
{
    uint16_t r = get_u16(a), c = get_u16(a + 2), g = get_u16(a + 4), tmax = get_u16(a + 6);
    if (!heat_valid(r, c, g, tmax)) {
        return ST_OUT_OF_RANGE;
    }
    if (s.enabled) {
        return ST_OUTPUT_ON;
    }
    s.heat = (core_heat_t){r, c, g, tmax};
    uint8_t d[8];
    heat_pack(d);
    ee_store(EE_HEAT_ADDR, 'H', d, 8);
    load_eeprom();
    return ST_OK;
}

/* Clears events and the latched faults whose cause is gone; FAULT_ACTIVE if one stays. */
static uint8_t cmd_clear_faults(void)
{
    uint16_t keep = 0;
    if (hal_estop_tripped()) {
        keep |= FLAG_ESTOP;
    }
    if ((s.flags & FLAG_OVERTEMP) &&
        (s.model_c > (float)s.heat.tmax_dc * 0.1f - (float)HEAT_REARM_K ||
         (s.tc_cdeg != TEMP_NONE && s.tc_cdeg >= (int16_t)(s.heat.tmax_dc * 10u)))) {
        keep |= FLAG_OVERTEMP;
    }
    if (s.cut_armed && (hal_cut_read() & HAL_CUT_TRIPPED)) {
        /* the latch is pulsed clear only when no cause the firmware knows of remains; the
         * hardware refuses too while a comparator holds it (read back) */
        if (!keep) {
            hal_cut_clear();
        }
        if (keep || (hal_cut_read() & HAL_CUT_TRIPPED)) {
            keep |= FLAG_CUT_TRIP;
        }
    }
    s.flags &= (uint16_t)~((FLAGS_LATCHED | FLAGS_EVENTS) & ~keep);
    cut_supply_low_ms = 0;
    cut_en_low_ms = 0;
    overcurrent_ms = 0;
    open_wire_ms = 0;
    return keep ? ST_FAULT_ACTIVE : ST_OK;
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
    case MSG_CLEAR_FAULTS: return cmd_clear_faults();
    case MSG_SET_LEASE: return cmd_set_lease(get_u16(a));
    case MSG_SET_CALIBRATION: return cmd_set_calibration(a);
    case MSG_GET_CALIBRATION: cal_pack(data); *data_len = CAL_LEN; return ST_OK;
    case MSG_SET_HEAT_MODEL: return cmd_set_heat_model(a);
    case MSG_GET_HEAT_MODEL: heat_pack(data); *data_len = 8; return ST_OK;
    case MSG_SET_PROBE: return cmd_set_probe(get_u16(a));
    default: return ST_OK; /* PING: only feeds the host watchdog, never the lease */
    }
}

static void handle(const frame_packet_t *p)
{
    uint8_t ack[ACK_MAX_PAYLOAD];
    uint8_t data_len = 0;
    ack[0] = p->seq;
    ack[1] = p->type;
    ack[2] = run_command(p, &ack[3], &data_len);
    send(MSG_ACK, ack, (uint8_t)(3u + data_len));
}

/* ------------------------------------------------------------------ measurements */
/* Fast-path current, calibrated, uA. */
static uint32_t measure_current_ua(void)
{
    /* + half a count: an ADC code k stands for inputs in [k, k+1) LSB */
    uint32_t raw = ((uint32_t)(hal_adc_q4(HAL_ADC_CURRENT) + 8u) *
                    ((uint32_t)ELEC_CURRENT_ADC_UA_PER_COUNT_Q8 >> 4)) >> 8;
    /* the counts are of AVcc, not of the nominal reference: scale by AVcc / nominal (Q15;
     * raw >> 6 <= 68 750 and the factor <= 36 700: the product fits in 32 bits; the low 6 bits
     * of raw scaled apart, so nothing is truncated away) */
    uint32_t k_q15 = avcc_q4 ? (avcc_q4 << 11) / ELEC_ADC_REF_MV : 32768u;
    raw = (((raw >> 6) * k_q15) >> 9) + (((raw & 63u) * k_q15) >> 15); /* to 1 uA */
    int32_t x = (int32_t)raw - s.cal.offset_ua;
    if (x <= 0) {
        return 0;
    }
    return (((uint32_t)x >> 6) * s.cal.current_gain) >> 9;
}

static uint16_t adc_mv(uint8_t channel)
{
    return (uint16_t)(((uint32_t)hal_adc_q4(channel) * s.avcc_mv) >> 14);
}

/* AVcc (the USB rail through the Nano's diode, 4.65 ... 5.0 V) from the REF3040 on A3:
 * counts = VREF / AVcc * 1024, so AVcc = VREF * 1024 * 16 / q4. Implausible: the nominal. */
static void measure_avcc(void)
{
    uint16_t q4 = hal_adc_q4(HAL_ADC_REFERENCE);
    /* + half a count, as for the current: a code k stands for inputs in [k, k+1) LSB */
    uint32_t den = (uint32_t)q4 + 8u;
    uint32_t mv = q4 ? ((uint32_t)ELEC_REFERENCE_MV * 16384u + den / 2u) / den : 0u;
    if (mv < AVCC_MIN_MV || mv > AVCC_MAX_MV) {
        avcc_q4 = 0;
        s.avcc_mv = ELEC_ADC_REF_MV;
        return;
    }
    /* the rail moves slowly: a 64 ms running mean keeps the reading's noise out of every
     * measurement scaled by it */
    if (avcc_q4 == 0u) {
        avcc_q4 = mv << 4;
    } else {
        avcc_q4 = avcc_q4 - (avcc_q4 >> 6) + (mv >> 2); /* 64 ms, mV * 16 */
    }
    s.avcc_mv = (uint16_t)((avcc_q4 + 8u) >> 4);
}

/* NTC: plausible ambient or TEMP_NONE (open: ADC near 0 V, shorted: near the reference). */
static void measure_ambient(void)
{
    uint16_t mv = adc_mv(HAL_ADC_AMBIENT);
    int16_t out = TEMP_NONE;
    /* ratiometric (the divider hangs from AVcc): thresholds scale with the measured AVcc */
    uint32_t short_mv = (uint32_t)ELEC_NTC_SHORT_ABOVE_MV * s.avcc_mv / ELEC_ADC_REF_MV;
    if (mv >= ELEC_NTC_OPEN_BELOW_MV && mv <= short_mv && mv < s.avcc_mv) {
        /* NTC on top: R_ntc = R_fixed * (AVcc - v) / v */
        float r_rel = (float)ELEC_NTC_FIXED_OHM / (float)ELEC_NTC_R25_OHM *
                      ((float)s.avcc_mv - (float)mv) / (float)mv;
        float t_c = 1.0f / (1.0f / 298.15f + logf(r_rel) / (float)ELEC_NTC_BETA_K) - 273.15f;
        if (t_c >= NTC_T_MIN_C && t_c <= NTC_T_MAX_C) {
            out = cdeg(t_c);
            ambient_c = t_c;
        }
    }
    s.ambient_cdeg = out;
    set_flag(FLAG_NTC_FAULT, out == TEMP_NONE);
    if (out == TEMP_NONE) {
        ambient_c = HEAT_AMBIENT_FALLBACK_C;
    }
}

/* MAX31855 word: D31..18 thermocouple (0.25 degC, signed), D17 reserved 0, D16 fault,
 * D3 reserved 0, D2 SCV, D1 SCG, D0 OC (Maxim MAX31855 datasheet, Table 2/3). */
static void measure_thermocouple(void)
{
    uint32_t w = 0;
    int8_t rc = hal_tc_read(&w);
    if (rc != 0 || w == 0u || w == 0xFFFFFFFFu || (w & 0x00020008u)) {
        s.tc_status = TC_ABSENT;
        s.tc_cdeg = TEMP_NONE;
        set_flag(FLAG_TC_FAULT, 0);
        return;
    }
    if (w & 0x00010000u) {
        s.tc_status = (uint8_t)(w & (TC_OC | TC_SCG | TC_SCV));
        s.tc_cdeg = TEMP_NONE;
        set_flag(FLAG_TC_FAULT, 1);
        return;
    }
    int32_t q = (int32_t)w >> 18; /* arithmetic: sign-extends the 14-bit field */
    int32_t c = q * 25;           /* 0.25 degC -> 0.01 degC */
    s.tc_status = 0;
    s.tc_cdeg = (int16_t)(c > 32766 ? 32766 : c);
    set_flag(FLAG_TC_FAULT, 0);
}

/* V and I are converted 8 ms apart: R = V/I only from a pair taken at one current (the fast
 * path held within 3 % + 10 mA over both windows), else a current step gives V at the new current
 * over I at the old one: R several times too high, and the heat budget trips early. */
static uint8_t xadc_same_current(void)
{
    uint16_t a = xadc_i_at[0], b = xadc_i_at[1];
    if (a == 0xFFFFu || b == 0xFFFFu) {
        return 0;
    }
    uint16_t hi = a > b ? a : b, lo = a > b ? b : a;
    return (uint16_t)(hi - lo) <= (uint16_t)(hi / 32u + 10u);
}

static void xadc_publish(int32_t mean_code)
{
    uint16_t span = (uint16_t)(xadc_i_max - xadc_i_min);
    xadc_i_at[xadc_channel & 1u] =
        span <= (uint16_t)(xadc_i_max / 32u + 10u)
            ? (uint16_t)(((uint32_t)xadc_i_min + xadc_i_max) / 2u) : 0xFFFFu;
    if (xadc_channel == HAL_XADC_WIRE) {
        uint32_t i_ma = (xadc_isum + XADC_AVERAGE / 2u) / XADC_AVERAGE;
        float uv = ((float)mean_code * ((float)ELEC_ADS1115_WIRE_UV_PER_LSB_Q8 / 256.0f) -
                    (float)s.cal.voltage_offset_uv) *
                   ((float)s.cal.voltage_gain / 32768.0f);
        float dmv = uv * 0.01f;
        s.voltage_dmv = dmv <= 0.0f ? 0u : dmv >= 65534.0f ? 65534u : (uint16_t)(dmv + 0.5f);
        /* each conversion with the current it saw: V/I holds while the current moves */
        wire_mohm = i_ma >= WIRE_R_MIN_MA
                        ? (dmv <= 0.0f ? 0.0f : dmv * 100.0f * (float)XADC_AVERAGE / (float)xadc_isum)
                        : 0.0f;
    } else {
        float na = (float)mean_code * (float)ELEC_ADS1115_SHUNT_NA_PER_LSB *
                   ((float)s.cal.current_gain / 32768.0f);
        float dma = na * 1e-5f;
        s.precise_dma = dma <= 0.0f ? 0u : dma >= 65534.0f ? 65534u : (uint16_t)(dma + 0.5f);
    }
    if (s.voltage_dmv != U16_NONE && s.precise_dma != U16_NONE && s.precise_dma > 500u) {
        if (xadc_same_current()) {
            measured_r_ohm = (float)s.voltage_dmv / (float)s.precise_dma;
        } /* else: keep the last consistent R while the current moves */
    } else {
        measured_r_ohm = 0.0f;
    }
}

/* ADS1115 state machine: every 2 ms read the pending conversion and start the other channel. */
static void xadc_tick(void)
{
    if (++xadc_timer == 1u) { /* the current over the pending conversion's first ms (of 1.16) */
        xadc_conv_ma = s.current_ma;
    }
    if (xadc_timer < XADC_PERIOD_MS) {
        return;
    }
    xadc_timer = 0;
    uint8_t ok = 1;
    if (xadc_pending) {
        int16_t code;
        if (hal_xadc_read(&code) == 0) {
            xadc_sum += code;
            /* 860 SPS: 1.16 ms of conversion, the first ms and 0.16 of the second */
            xadc_isum += ((uint32_t)xadc_conv_ma * 7u + s.current_ma + 4u) / 8u;
            if (xadc_n == 0u || s.current_ma < xadc_i_min) {
                xadc_i_min = s.current_ma;
            }
            if (xadc_n == 0u || s.current_ma > xadc_i_max) {
                xadc_i_max = s.current_ma;
            }
            if (++xadc_n >= XADC_AVERAGE) {
                xadc_publish(xadc_sum / (int32_t)XADC_AVERAGE);
                xadc_sum = 0;
                xadc_isum = 0;
                xadc_n = 0;
                xadc_channel ^= 1u;
            }
        } else {
            ok = 0;
        }
    }
    xadc_pending = hal_xadc_start(xadc_channel) == 0;
    if (!xadc_pending) {
        ok = 0;
    }
    if (ok) {
        xadc_fails = 0;
        set_flag(FLAG_VSENSE_FAULT, 0);
    } else if (++xadc_fails >= XADC_FAULT_AFTER) {
        xadc_fails = XADC_FAULT_AFTER;
        xadc_sum = 0;
        xadc_isum = 0;
        xadc_n = 0;
        wire_mohm = 0.0f;
        s.voltage_dmv = U16_NONE;
        s.precise_dma = U16_NONE;
        measured_r_ohm = 0.0f;
        set_flag(FLAG_VSENSE_FAULT, 1);
    }
}

/* Sink headroom and dissipation from the supply, the wire voltage and the current. */
static void sink_limits(void)
{
    compliance = 0;
    dissipation_cap_ma = 0xFFFFu;
    if (s.voltage_dmv == U16_NONE || s.supply_mv < 500u) {
        return;
    }
    int32_t v_fet_mv = (int32_t)s.supply_mv - (int32_t)(s.voltage_dmv / 10u) -
                       (int32_t)((uint32_t)s.current_ma * ELEC_SHUNT_MOHM / 1000u);
    compliance = v_fet_mv < (int32_t)ELEC_MOSFET_VDS_MIN_MV + 100;
    if (v_fet_mv > 0) {
        uint32_t cap = (uint32_t)ELEC_DISSIPATION_MAX_MW * 1000u / (uint32_t)v_fet_mv;
        dissipation_cap_ma = cap > 0xFFFFu ? 0xFFFFu : (uint16_t)cap;
    }
}

/* ------------------------------------------------------------------ safety */
static void check_faults(uint16_t sp_ma)
{
    uint32_t oc_ma = (uint32_t)s.limit_ma * 6u / 5u; /* limit + 20 % ... */
    if (oc_ma < (uint32_t)s.limit_ma + 50u) {
        oc_ma = (uint32_t)s.limit_ma + 50u; /* ... and at least 50 mA above */
    }
    overcurrent_ms = s.current_ma > oc_ma ? (uint8_t)(overcurrent_ms + 1u) : 0u;
    uint8_t open = sp_ma >= OPEN_WIRE_SET_MA && s.current_ma < OPEN_WIRE_MA;
    open_wire_ms = open ? (uint8_t)(open_wire_ms + 1u) : 0u;
    if (overcurrent_ms >= OVERCURRENT_MS) {
        latch(FLAG_OVERCURRENT);
    } else if (open_wire_ms >= OPEN_WIRE_MS) {
        latch(FLAG_OPEN_WIRE);
    }
}

/* The current the sink is asked for: while enabled the larger of the setpoint and the probe,
 * within the active limit; 0 while off. */
static uint16_t regulated_ma(void)
{
    if (!s.enabled) {
        return 0;
    }
    uint16_t probe = s.probe_ma < probe_cap_ma ? s.probe_ma : probe_cap_ma;
    uint16_t sp = s.setpoint_ma > probe ? s.setpoint_ma : probe;
    return sp < s.limit_ma ? sp : s.limit_ma;
}

/* Energy budget: C dT/dt = I^2 R - G (T - Ta), with the larger of the set and the measured
 * resistance and the larger of the measured and the commanded current (setpoint or probe). Runs
 * always (the wire cools while the output is off). I^2 is summed every tick, the model steps
 * every 10 ms. */
static void heat_tick(void)
{
    uint16_t i_ma = s.current_ma;
    uint16_t sp_ma = regulated_ma();
    if (sp_ma > i_ma) {
        i_ma = sp_ma;
    }
    heat_i2_sum += (uint32_t)i_ma * i_ma; /* 10 ticks of (2.8 A)^2 in mA^2: 7.8e7, fits */
    if (++heat_ticks >= HEAT_STEP_MS) {
        float r = measured_r_ohm > heat_r_ohm ? measured_r_ohm : heat_r_ohm;
        float p_w = (float)heat_i2_sum * (1e-6f / (float)HEAT_STEP_MS) * r; /* mean I^2 R */
        heat_i2_sum = 0;
        heat_ticks = 0;
        s.model_c += (p_w - heat_g_w_k * (s.model_c - ambient_c)) * heat_dt_over_c;
    }
    float tmax = (float)s.heat.tmax_dc * 0.1f;
    uint8_t tc_hot = s.tc_cdeg != TEMP_NONE && s.tc_cdeg >= (int16_t)(s.heat.tmax_dc * 10u);
    if ((s.model_c >= tmax || tc_hot) && !(s.flags & FLAG_OVERTEMP)) {
        latch(FLAG_OVERTEMP);
    }
}

/* The hardware cut: toggle its watchdog (D7) every tick, clear its latch once after power-on
 * (the pump starts empty: the cut starts tripped), then read it back every tick. A trip that
 * nobody asked for latches CUT_TRIP: the latch set (comparator, external watchdog, e-stop), EN
 * low while the firmware enables (D5), or the switched supply (A1) gone while enabled. */
static void cut_tick(void)
{
    hal_cut_feed();
    uint8_t c = hal_cut_read();
    if (!s.cut_armed) {
        if (++cut_startup_ms < CUT_STARTUP_MS) {
            return;
        }
        s.cut_armed = 1;
        uint8_t estop = hal_estop_tripped();
        if (estop) {
            latch(FLAG_ESTOP);
        }
        if (!cut_wdt_reset && !estop) {
            hal_cut_clear(); /* power-on: the pump is charged now */
            c = hal_cut_read();
        }
    }
    s.cut = c;
    set_flag(FLAG_CUT_OPEN, !(c & HAL_CUT_CLOSED));
    /* EN follows D8 within nanoseconds; two ticks of EN low while enabled leave room for a
     * read-back taken in the same loop pass as the ENABLE */
    cut_en_low_ms = (s.enabled && !(c & HAL_CUT_CLOSED)) ? (uint8_t)(cut_en_low_ms + 1u) : 0u;
    uint8_t unasked = (c & HAL_CUT_TRIPPED) || cut_en_low_ms >= 2u;
    if (s.enabled && s.supply_mv < CUT_SUPPLY_MIN_MV) {
        if (++cut_supply_low_ms >= CUT_SUPPLY_MS) {
            unasked = 1;
        }
    } else {
        cut_supply_low_ms = 0;
    }
    if (unasked && !(s.flags & FLAG_CUT_TRIP)) {
        latch(FLAG_CUT_TRIP);
    }
}

/* ------------------------------------------------------------------ control */
/* One control step: feed-forward plus the PI trim; returns the new duty. The trim's integral is
 * a relative correction of the setpoint path (its divider and PWM level tolerances scale with
 * the setpoint), learned while the output runs and kept across setpoints. */
static uint16_t control_step(uint16_t sp_ma)
{
    if (sp_ma == 0u) {
        ref1_q8 = ref2_q8 = ref2_prev_q8 = 0;
        return 0;
    }
    /* the trim compares the measurement with what the setpoint path should deliver by now (its
     * two RC poles), so it corrects the path's errors and not its known lag */
    /* the measurement is the mean over the last tick (plus the anti-alias lag): compare it with
     * the mean of the reference over that tick */
    int32_t expect = ((ref2_q8 + ref2_prev_q8) / 2 + 128) >> 8;
    ref2_prev_q8 = ref2_q8;
    ref1_q8 += (((int32_t)sp_ma << 8) - ref1_q8) * ref_alpha_q8 / 256;
    ref2_q8 += (ref1_q8 - ref2_q8) * ref_alpha_q8 / 256;
    int32_t err = expect - (int32_t)s.current_ma;
    /* an error beyond any tolerance of the setpoint path is not the path's: the sink is out of
     * headroom (compliance), or a fault is developing. Neither integrate nor amplify it. */
    int32_t err_max = (int32_t)(sp_ma >> 3) + 20;
    uint8_t beyond = err > err_max || err < -err_max;
    if (err > err_max) {
        err = err_max;
    } else if (err < -err_max) {
        err = -err_max;
    }
    int32_t ff = (int32_t)(((uint32_t)sp_ma * FF_Q16_PER_MA) >> 16);
    /* relative trim: d(duty) = ff * d(gain) = Ki * err counts per tick, whatever the setpoint */
    if (!beyond && !(compliance && err > 0) && sp_ma >= TRIM_LEARN_MIN_MA) {
        integ_q16 += (int32_t)PI_KI_Q16 * err / (ff > 0 ? ff : 1);
    }
    if (integ_q16 > TRIM_MAX_Q16) {
        integ_q16 = TRIM_MAX_Q16;
    } else if (integ_q16 < -TRIM_MAX_Q16) {
        integ_q16 = -TRIM_MAX_Q16;
    }
    /* |ff * integ| <= 1023 * 8192, |Kp * err| <= 5041 * 333: int32 is enough */
    int32_t out = ff + ((ff * integ_q16 + (int32_t)PI_KP_Q16 * err + 32768) >> 16);
    if (out < 0) {
        return 0;
    }
    return out > (int32_t)DUTY_MAX ? DUTY_MAX : (uint16_t)out;
}

/* The wire voltage at the frame's current: the wire's resistance over the last voltage window
 * (each conversion paired with the current it saw, so it holds while the current moves) times
 * the frame's current. A window below WIRE_R_MIN_MA (off, an open wire) gives no resistance: its
 * voltage goes out only with a frame current within 3 % + 10 mA of the window's, else "not
 * available", never V at one current over I at another. */
static uint16_t paired_voltage_dmv(void)
{
    uint16_t at = xadc_i_at[HAL_XADC_WIRE], now = s.current_ma;
    if (s.voltage_dmv == U16_NONE) {
        return U16_NONE;
    }
    if (wire_mohm > 0.0f) {
        float dmv = wire_mohm * (float)now * 0.01f; /* mOhm x mA = uV; 0.1 mV */
        return dmv >= 65534.0f ? 65534u : (uint16_t)(dmv + 0.5f);
    }
    if (at == 0xFFFFu) {
        return U16_NONE;
    }
    uint16_t hi = at > now ? at : now, lo = at > now ? now : at;
    return (uint16_t)(hi - lo) <= (uint16_t)(hi / 32u + 10u) ? s.voltage_dmv : U16_NONE;
}

uint8_t core_telemetry(uint8_t *t)
{
    put_u32(&t[0], hal_millis());
    put_u16(&t[4], s.current_ma);
    put_u16(&t[6], paired_voltage_dmv());
    put_u16(&t[8], (uint16_t)((uint32_t)s.duty * 65535u / HAL_PWM_TOP));
    put_u16(&t[10], (uint16_t)s.ambient_cdeg);
    put_u16(&t[12], s.flags);
    put_u16(&t[14], s.setpoint_ma);
    put_u16(&t[16], s.rx_crc_errors);
    put_u16(&t[18], s.rx_frame_errors);
    put_u16(&t[20], (uint16_t)cdeg(s.model_c));
    put_u16(&t[22], (uint16_t)s.tc_cdeg);
    put_u16(&t[24], s.precise_dma);
    put_u16(&t[26], s.supply_mv);
    t[28] = s.tc_status;
    return TELEMETRY_LEN;
}

/* A telemetry frame that falls due is sent when it fits whole with room left for an ACK;
 * otherwise it waits for the next tick (counted in telemetry_deferred), and one that falls a whole
 * period behind is skipped: telemetry never bursts and never cuts or delays an ACK. */
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
    uint8_t t[TELEMETRY_LEN];
    if (hal_uart_tx_free() < TELEMETRY_MAX_WIRE + ACK_MAX_WIRE ||
        !send(MSG_TELEMETRY, t, core_telemetry(t))) {
        if (s.telemetry_deferred != 0xFFFFu) {
            s.telemetry_deferred++;
        }
        if ((int32_t)(now - next_telem_ms) < (int32_t)s.telemetry_period_ms) {
            return; /* try again at the next tick */
        }
    }
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
    s.lease_ms = LEASE_DEFAULT_MS;
    s.flags = was_watchdog_reset ? FLAG_WATCHDOG_RESET : 0u;
    s.voltage_dmv = U16_NONE;
    s.precise_dma = U16_NONE;
    s.tc_cdeg = TEMP_NONE;
    s.tc_status = TC_ABSENT;
    frame_rx_init(&rx);
    tx_seq = 0;
    xadc_channel = HAL_XADC_WIRE;
    xadc_pending = xadc_fails = xadc_n = 0;
    xadc_sum = 0;
    xadc_isum = 0;
    wire_mohm = 0.0f;
    xadc_i_at[0] = xadc_i_at[1] = 0xFFFFu;
    xadc_timer = 0;
    integ_q16 = 0;
    heat_i2_sum = 0;
    heat_ticks = 0;
    slow_timer = 0; /* NTC and thermocouple after 100 ms, when the ADC has conversions */
    s.avcc_mv = ELEC_ADC_REF_MV;
    avcc_q4 = 0;
    cut_startup_ms = 0;
    cut_wdt_reset = was_watchdog_reset ? 1u : 0u;
    cut_supply_low_ms = 0;
    cut_en_low_ms = 0;
    measured_r_ohm = 0.0f;
    ref_alpha_q8 = (int32_t)(256.0f * (1.0f - expf(-1000.0f / (float)ELEC_SETPOINT_FILTER_TAU_US)) + 0.5f);
    compliance = 0;
    dissipation_cap_ma = 0xFFFFu;
    load_eeprom();
    s.ambient_cdeg = TEMP_NONE; /* not read yet (no fault either) */
    ambient_c = HEAT_AMBIENT_FALLBACK_C;
    /* the wire may still be hot after a watchdog reset: start the budget near its maximum */
    s.model_c = was_watchdog_reset ? (float)s.heat.tmax_dc * 0.1f - (float)HEAT_REARM_K
                                   : ambient_c;
    last_rx_ms = hal_millis();
    s.last_rx_ms = last_rx_ms;
    lease_start_ms = last_rx_ms;
    next_telem_ms = last_rx_ms;
    telem_restart = 0;
    output_off();
}

void core_poll(void)
{
    int16_t c;
    frame_packet_t pkt;
    /* a command is read only when its ACK fits whole: otherwise it waits in the RX buffer */
    while (hal_uart_tx_free() >= ACK_MAX_WIRE && (c = hal_uart_read()) >= 0) {
        if (frame_rx_push(&rx, (uint8_t)c, &pkt)) {
            last_rx_ms = hal_millis(); /* every valid frame feeds the host watchdog */
            s.last_rx_ms = last_rx_ms;
            handle(&pkt);
        }
    }
    s.rx_crc_errors = rx.crc_errors;
    s.rx_frame_errors = rx.frame_errors;
}

void core_control_tick(void)
{
    uint32_t now = hal_millis();
    measure_avcc();
    uint32_t ua = measure_current_ua();
    s.current_ma = (uint16_t)((ua + 500u) / 1000u > 0xFFFFu ? 0xFFFFu : (ua + 500u) / 1000u);
    s.supply_mv = (uint16_t)(((uint32_t)adc_mv(HAL_ADC_SUPPLY) << 16) /
                             ELEC_SUPPLY_MONITOR_DIV_Q16);
    xadc_tick();
    if (++slow_timer >= SLOW_PERIOD_MS) {
        slow_timer = 0;
        measure_ambient();
        measure_thermocouple();
    }
    sink_limits();
    cut_tick();

    if (hal_estop_tripped() && !(s.flags & FLAG_ESTOP)) {
        latch(FLAG_ESTOP);
    }
    if (s.enabled && (uint32_t)(now - last_rx_ms) >= s.host_timeout_ms) {
        output_off();
        s.flags |= FLAG_HOST_TIMEOUT;
    }
    if (s.enabled && s.setpoint_ma != 0u && (uint32_t)(now - lease_start_ms) >= s.lease_ms) {
        output_off();
        s.setpoint_ma = 0;
        s.flags |= FLAG_LEASE_EXPIRED;
    }
    heat_tick();
    uint16_t sp = regulated_ma(); /* max(setpoint, probe) within the limit; 0 while off */
    uint8_t dissipating = sp > dissipation_cap_ma;
    if (dissipating) {
        sp = dissipation_cap_ma;
    }
    if (s.enabled) {
        check_faults(sp);
    }
    if (s.enabled) {
        s.duty = control_step(sp);
        hal_pwm_set(s.duty);
        uint8_t at_limit = (sp != 0u && sp >= s.limit_ma) || s.duty >= DUTY_MAX ||
                           dissipating || (compliance && s.current_ma + 20u < sp);
        set_flag(FLAG_LIMIT_ACTIVE, at_limit);
        set_flag(FLAG_DISSIPATION, dissipating);
    }
    telemetry_tick(now);
}

void core_latch_fault(uint16_t fault)
{
    latch((uint16_t)(fault & FLAGS_LATCHED));
}

const core_state_t *core_state(void)
{
    return &s;
}
