/* Fake HAL (see hal_fake.h). */
#define _DEFAULT_SOURCE /* M_PI */
#include <math.h>
#include <string.h>
#include "electrical.h"
#include "hal_fake.h"
#include "proto.h"

#define SUB_US 50.0          /* model step */
#define ANTIALIAS_TAU_US 100.0 /* shunt amplifier RC (electrical.toml: 1 kOhm, 100 nF) */
#define SINK_TAU_US 20.0     /* op-amp + MOSFET loop */
#define VDS_MIN_V 0.15       /* sink headroom at full current */
#define ADC_REF_MV 5000.0

static uint32_t now_ms;
static uint8_t rx_buf[FAKE_RX_CAP];
static size_t rx_head, rx_tail;
static uint8_t tx_buf[FAKE_TX_CAP];
static size_t tx_len, tx_limit;
static size_t tx_ring, tx_sent; /* ring mode: capacity (0: off), bytes already on the line */
static double tx_per_ms, tx_credit; /* ring mode: bytes the UART sends per ms */
static uint16_t pwm_duty;
static uint8_t out_enabled;
static uint32_t pwm_sets, wdt_feeds;
static fake_sink_t sink;
static double v1, v2;        /* the two setpoint RC poles, in "duty counts" */
static double i_a, i_meas_a; /* wire current, anti-aliased amplifier output (as A) */
static uint32_t adc_sum[HAL_ADC_CHANNELS], adc_n[HAL_ADC_CHANNELS];
static uint16_t adc_last[HAL_ADC_CHANNELS];
static double ntc_mv;
static uint8_t estop_level, estop_latched;
static uint8_t xadc_on, xadc_ch;
static int16_t xadc_code;
/* the ADS1115 converts over 1/860 s after its start (TI SBAS444, 860 SPS): the code is the mean
 * of the input over that window, taken in the sink model's 50 us steps */
#define XADC_CONV_US (1e6 / 860.0)
static double xadc_left_us, xadc_acc;
static int xadc_acc_n;
static uint32_t tc_word;
static uint8_t eeprom[1024];
static uint32_t dither;
static double avcc_mv = ADC_REF_MV;
static uint8_t cut_latch, cut_held;
static double cut_pump_v;
static uint32_t cut_feeds, cut_clears, cut_feeds_seen;
#define PUMP_V 3.6        /* watchdog hold capacitor pumped by 500 Hz of edges (README "The cut") */
#define PUMP_TRIP_V 1.63  /* U7D threshold (2 x 0.816 V) */
#define PUMP_TAU_MS 21.96 /* (RW1 + RW2) * CW2 */
static double t_us, next_sample_us; /* model time; when the next ADC conversion samples */
#define PWM_PERIOD_US 64.0          /* 16 MHz / 1024 */
#define ANTIALIAS_FC_HZ 1592.0      /* 1 kOhm, 100 nF */

void fake_eeprom_erase(void) { memset(eeprom, 0xFF, sizeof eeprom); }
uint8_t fake_eeprom_byte(uint16_t addr) { return eeprom[addr & 1023u]; }

static double ntc_divider_mv(double c)
{
    double r = ELEC_NTC_R25_OHM * exp(ELEC_NTC_BETA_K * (1.0 / (c + 273.15) - 1.0 / 298.15));
    return ADC_REF_MV * ELEC_NTC_FIXED_OHM / (r + ELEC_NTC_FIXED_OHM);
}

void fake_reset(void)
{
    static uint8_t eeprom_init;
    if (!eeprom_init) {
        fake_eeprom_erase();
        eeprom_init = 1;
    }
    now_ms = 0;
    rx_head = rx_tail = 0;
    tx_len = 0;
    tx_limit = FAKE_TX_CAP;
    tx_ring = tx_sent = 0;
    tx_per_ms = tx_credit = 0.0;
    pwm_duty = 0;
    out_enabled = 0;
    pwm_sets = wdt_feeds = 0;
    sink = (fake_sink_t){0.44, 5.0, 0.06, 0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0};
    t_us = 0.0;
    next_sample_us = 0.0;
    v1 = v2 = i_a = i_meas_a = 0.0;
    memset(adc_sum, 0, sizeof adc_sum);
    memset(adc_n, 0, sizeof adc_n);
    memset(adc_last, 0, sizeof adc_last);
    ntc_mv = ntc_divider_mv(22.0);
    estop_level = estop_latched = 0;
    xadc_on = 1;
    xadc_ch = 0;
    xadc_code = 0;
    xadc_left_us = xadc_acc = 0.0;
    xadc_acc_n = 0;
    tc_word = 0xFFFFFFFFu;
    dither = 12345u;
    avcc_mv = ADC_REF_MV;
    cut_latch = 1; /* power-on: the pump is empty */
    cut_held = 0;
    cut_pump_v = 0.0;
    cut_feeds = cut_clears = cut_feeds_seen = 0;
}

void fake_set_millis(uint32_t ms) { now_ms = ms; }
fake_sink_t *fake_sink(void) { return &sink; }
double fake_current_a(void) { return i_a; }

/* deterministic +-0.5 count noise, so oversampling has something to average */
static double noise(void)
{
    dither = dither * 1103515245u + 12345u;
    return ((double)((dither >> 16) & 0x7FFFu) / 32768.0) - 0.5;
}

static uint16_t adc_counts(double mv)
{
    double c = floor(mv / avcc_mv * 1024.0 + noise());
    return (uint16_t)(c < 0.0 ? 0.0 : c > 1023.0 ? 1023.0 : c);
}

static void sample_adcs(void)
{
    double a_per_count = ELEC_CURRENT_ADC_UA_PER_COUNT_Q8 / 256.0 * 1e-6;
    /* the PWM ripple at the sampling instant, after the anti-alias RC (gain and phase of one
     * pole at 15.625 kHz); with synchronous sampling the instant is always the same phase */
    double ripple = 0.0;
    if (sink.ripple_a_pp != 0.0) {
        double f_ratio = 1e6 / PWM_PERIOD_US / ANTIALIAS_FC_HZ;
        ripple = sink.ripple_a_pp / 2.0 / sqrt(1.0 + f_ratio * f_ratio) *
                 sin(2.0 * M_PI * t_us / PWM_PERIOD_US - atan(f_ratio));
    }
    double amp_a = (i_meas_a + ripple) * sink.adc_gain + sink.adc_offset_ma * 1e-3;
    uint16_t c0 = adc_counts(amp_a / a_per_count / 1024.0 * ADC_REF_MV);
    double vs = fake_cut_closed() ? sink.supply_v - i_a * sink.source_ohm : 0.0; /* switched */
    uint16_t c1 = adc_counts(vs * 1000.0 * ELEC_SUPPLY_MONITOR_DIV_Q16 / 65536.0);
    uint16_t c2 = adc_counts(ntc_mv * avcc_mv / ADC_REF_MV); /* ratiometric */
    /* A3 with its own noise source: the other channels' sequence stays as it was */
    static uint32_t dither3 = 777u;
    dither3 = dither3 * 1103515245u + 12345u;
    double n3 = ((double)((dither3 >> 16) & 0x7FFFu) / 32768.0) - 0.5;
    double r3 = floor(ELEC_REFERENCE_MV / avcc_mv * 1024.0 + n3);
    uint16_t c3 = (uint16_t)(r3 < 0.0 ? 0.0 : r3 > 1023.0 ? 1023.0 : r3);
    adc_sum[0] += c0;
    adc_sum[1] += c1;
    adc_sum[2] += c2;
    adc_sum[3] += c3;
    adc_n[0]++;
    adc_n[1]++;
    adc_n[2]++;
    adc_n[3]++;
}

static void model_step(double dt_us)
{
    double duty = pwm_duty;
    double a = dt_us / ELEC_SETPOINT_FILTER_TAU_US;
    v1 += (duty - v1) * a;
    v2 += (v1 - v2) * a;
    /* the enable line clamps the op-amp's input: off at once, whatever the RC filter holds */
    double target = fake_cut_closed() ? v2 * ELEC_SETPOINT_UA_PER_COUNT_Q8 / 256.0 * 1e-6 * sink.setpoint_gain
                                : 0.0;
    double rsh = ELEC_SHUNT_MOHM * 1e-3;
    double i_max = sink.open ? 0.0
                             : (sink.supply_v - VDS_MIN_V) / (sink.wire_ohm + rsh + sink.source_ohm);
    if (i_max < 0.0) {
        i_max = 0.0;
    }
    if (target > i_max) {
        target = i_max; /* compliance: the op-amp rails, the MOSFET is fully on */
    }
    i_a += (target - i_a) * (dt_us / SINK_TAU_US > 1.0 ? 1.0 : dt_us / SINK_TAU_US);
    i_meas_a += (i_a - i_meas_a) * (dt_us / ANTIALIAS_TAU_US);
}

/* The selected ADS1115 input now, in LSB (not rounded). */
static double xadc_input_code(void)
{
    if (xadc_ch == HAL_XADC_WIRE) {
        double v = (sink.open ? sink.supply_v : i_a * sink.wire_ohm) + sink.wire_offset_v;
        return v * 1e6 / (ELEC_ADS1115_WIRE_UV_PER_LSB_Q8 / 256.0);
    }
    return i_a * 1e9 / ELEC_ADS1115_SHUNT_NA_PER_LSB;
}

void fake_advance_ms(uint32_t ms)
{
    for (uint32_t k = 0; k < ms; k++) {
        /* the watchdog pump: each D7 edge of the last ms charges it, else it decays */
        for (; cut_feeds_seen < cut_feeds; cut_feeds_seen++) {
            cut_pump_v += (PUMP_V - cut_pump_v) * 0.5;
        }
        cut_pump_v *= exp(-1.0 / PUMP_TAU_MS);
        if (cut_pump_v < PUMP_TRIP_V || estop_level || cut_held) {
            cut_latch = 1;
        }
        for (int j = 0; j < 20; j++) {
            model_step(SUB_US);
            t_us += SUB_US;
            if (xadc_left_us > 0.0) {
                xadc_acc += xadc_input_code();
                xadc_acc_n++;
                xadc_left_us -= SUB_US;
            }
            /* conversions as the AVR HAL starts them: at every second PWM BOTTOM (synchronous),
             * or back to back in free-running mode */
            while (next_sample_us <= t_us) {
                sample_adcs();
                next_sample_us += sink.async_period_us > 0.0 ? sink.async_period_us
                                                             : 2.0 * PWM_PERIOD_US;
            }
        }
        now_ms++;
        if (tx_ring != 0u) { /* the UART empties the ring at the baud rate */
            tx_credit += tx_per_ms;
            while (tx_credit >= 1.0 && tx_sent < tx_len) {
                tx_sent++;
                tx_credit -= 1.0;
            }
            if (tx_sent == tx_len && tx_credit > 1.0) {
                tx_credit = 1.0; /* an idle line saves no bytes */
            }
        }
    }
}

void fake_tx_ring(size_t capacity, double bytes_per_ms)
{
    tx_ring = capacity;
    tx_per_ms = bytes_per_ms;
    tx_sent = tx_len;
    tx_credit = 0.0;
}

void fake_rx_push(const uint8_t *data, size_t len)
{
    if (rx_head == rx_tail) {
        rx_head = rx_tail = 0;
    }
    for (size_t i = 0; i < len && rx_tail < FAKE_RX_CAP; i++) {
        rx_buf[rx_tail++] = data[i];
    }
}

size_t fake_rx_pending(void) { return rx_tail - rx_head; }

const uint8_t *fake_tx_data(size_t *len)
{
    *len = tx_ring != 0u ? tx_sent : tx_len;
    return tx_buf;
}

void fake_tx_clear(void)
{
    if (tx_ring != 0u) { /* keep what is still queued in the ring */
        memmove(tx_buf, tx_buf + tx_sent, tx_len - tx_sent);
        tx_len -= tx_sent;
        tx_sent = 0;
        return;
    }
    tx_len = 0;
}
void fake_tx_set_limit(size_t max_bytes) { tx_limit = max_bytes < FAKE_TX_CAP ? max_bytes : FAKE_TX_CAP; }
uint16_t fake_pwm_duty(void) { return pwm_duty; }
uint8_t fake_output_enabled(void) { return out_enabled; }
uint32_t fake_pwm_set_count(void) { return pwm_sets; }
uint32_t fake_watchdog_feeds(void) { return wdt_feeds; }
void fake_ntc_celsius(double c) { ntc_mv = ntc_divider_mv(c); }
void fake_ntc_mv(uint16_t mv) { ntc_mv = mv; }

void fake_estop(uint8_t tripped)
{
    estop_level = tripped ? 1u : 0u;
    estop_latched |= estop_level;
}

void fake_xadc_present(uint8_t on) { xadc_on = on; }
void fake_tc_absent(void) { tc_word = 0xFFFFFFFFu; }

void fake_tc_celsius(double c)
{
    int32_t q = (int32_t)lround(c * 4.0);           /* 0.25 degC */
    uint32_t internal = (uint32_t)(25 * 16) & 0xFFFu; /* cold junction 25 degC, 0.0625 degC */
    tc_word = ((uint32_t)q << 18) | (internal << 4);
}

void fake_tc_fault(uint8_t bits)
{
    tc_word = 0x00010000u | (bits & 7u) | ((uint32_t)(25 * 16) << 4);
}

/* ------------------------------------------------------------------ hal.h */
uint32_t hal_millis(void) { return now_ms; }

int16_t hal_uart_read(void)
{
    return rx_head < rx_tail ? (int16_t)rx_buf[rx_head++] : -1;
}

uint8_t hal_uart_write(const uint8_t *data, uint8_t len)
{
    uint8_t n = 0;
    while (n < len && tx_len < tx_limit && (tx_ring == 0u || tx_len - tx_sent < tx_ring)) {
        tx_buf[tx_len++] = data[n++];
    }
    return n;
}

uint8_t hal_uart_tx_free(void)
{
    size_t free_bytes = tx_limit > tx_len ? tx_limit - tx_len : 0u;
    if (tx_ring != 0u && tx_ring - (tx_len - tx_sent) < free_bytes) {
        free_bytes = tx_ring - (tx_len - tx_sent);
    }
    return (uint8_t)(free_bytes > 255u ? 255u : free_bytes);
}

void hal_pwm_set(uint16_t duty)
{
    pwm_duty = duty;
    pwm_sets++;
}

void hal_output_enable(uint8_t on) { out_enabled = on ? 1u : 0u; }

uint16_t hal_adc_q4(uint8_t channel)
{
    if (channel >= HAL_ADC_CHANNELS) {
        return 0;
    }
    if (adc_n[channel] == 0u) {
        sample_adcs(); /* before the first advance: one conversion of the present state */
    }
    adc_last[channel] = (uint16_t)((adc_sum[channel] * 16u + adc_n[channel] / 2u) / adc_n[channel]);
    adc_sum[channel] = 0;
    adc_n[channel] = 0;
    return adc_last[channel];
}

uint8_t hal_estop_tripped(void)
{
    uint8_t t = estop_level | estop_latched;
    estop_latched = 0;
    return t;
}

int8_t hal_xadc_start(uint8_t channel)
{
    if (!xadc_on) {
        return -1;
    }
    xadc_ch = channel;
    xadc_left_us = XADC_CONV_US;
    xadc_acc = 0.0;
    xadc_acc_n = 0;
    return 0;
}

int8_t hal_xadc_read(int16_t *code)
{
    if (!xadc_on) {
        return -1;
    }
    /* read before the conversion ended: what it had so far (the whole window in the core's use) */
    double c = xadc_acc_n > 0 ? xadc_acc / xadc_acc_n : xadc_input_code();
    c = floor(c + noise() + 0.5);
    xadc_code = (int16_t)(c > 32767.0 ? 32767.0 : c < -32768.0 ? -32768.0 : c);
    *code = xadc_code;
    return 0;
}

int8_t hal_tc_read(uint32_t *word)
{
    *word = tc_word;
    return 0;
}

void hal_eeprom_read(uint16_t addr, uint8_t *data, uint8_t len)
{
    for (uint8_t i = 0; i < len; i++) {
        data[i] = eeprom[(addr + i) & 1023u];
    }
}

void hal_eeprom_write(uint16_t addr, const uint8_t *data, uint8_t len)
{
    for (uint8_t i = 0; i < len; i++) {
        eeprom[(addr + i) & 1023u] = data[i];
        wdt_feeds++;
    }
}

void hal_watchdog_feed(void) { wdt_feeds++; }

void fake_avcc_mv(double mv) { avcc_mv = mv; }
void fake_cut_trip(void) { cut_latch = 1; }
void fake_cut_hold(uint8_t on)
{
    cut_held = on;
    if (on) {
        cut_latch = 1;
    }
}
uint8_t fake_cut_tripped(void) { return cut_latch; }
uint8_t fake_cut_closed(void) { return out_enabled && !cut_latch; }
uint32_t fake_cut_feeds(void) { return cut_feeds; }
uint32_t fake_cut_clears(void) { return cut_clears; }

uint8_t hal_cut_read(void)
{
    return (uint8_t)((fake_cut_closed() ? HAL_CUT_CLOSED : 0u) | (cut_latch ? HAL_CUT_TRIPPED : 0u));
}

void hal_cut_clear(void)
{
    cut_clears++;
    for (; cut_feeds_seen < cut_feeds; cut_feeds_seen++) { /* edges up to now */
        cut_pump_v += (PUMP_V - cut_pump_v) * 0.5;
    }
    /* /PRE dominates /CLR: a comparator (or the e-stop, or an empty pump) still holding it wins */
    if (!cut_held && !estop_level && cut_pump_v >= PUMP_TRIP_V) {
        cut_latch = 0;
    }
}

void hal_cut_feed(void) { cut_feeds++; }
