/* Fake HAL (see hal_fake.h). */
#include <string.h>
#include "hal_fake.h"

static uint32_t now_ms;
static uint8_t rx_buf[FAKE_RX_CAP];
static size_t rx_head, rx_tail;
static uint8_t tx_buf[FAKE_TX_CAP];
static size_t tx_len, tx_limit;
static uint16_t pwm_duty;
static uint32_t pwm_sets, wdt_feeds;
static uint16_t adc_mv[3];
static fake_plant_fn plant;
static void *plant_ctx;

uint16_t fake_plant_resistive(uint16_t duty, void *ctx)
{
    const fake_load_t *l = ctx;
    if (l->open || l->load_mohm == 0u) {
        return 0;
    }
    /* mA = duty/TOP * mV / mOhm * 1000 */
    uint64_t ma = (uint64_t)duty * l->supply_mv * 1000u / ((uint64_t)HAL_PWM_TOP * l->load_mohm);
    return ma > 5000u ? 5000u : (uint16_t)ma; /* ADC full scale 5 V */
}

void fake_reset(void)
{
    now_ms = 0;
    rx_head = rx_tail = 0;
    tx_len = 0;
    tx_limit = FAKE_TX_CAP;
    pwm_duty = 0;
    pwm_sets = wdt_feeds = 0;
    memset(adc_mv, 0, sizeof adc_mv);
    plant = NULL;
    plant_ctx = NULL;
}

void fake_set_millis(uint32_t ms) { now_ms = ms; }
void fake_advance_ms(uint32_t ms) { now_ms += ms; }

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
    *len = tx_len;
    return tx_buf;
}

void fake_tx_clear(void) { tx_len = 0; }
void fake_tx_set_limit(size_t max_bytes) { tx_limit = max_bytes < FAKE_TX_CAP ? max_bytes : FAKE_TX_CAP; }
uint16_t fake_pwm_duty(void) { return pwm_duty; }
uint32_t fake_pwm_set_count(void) { return pwm_sets; }
uint32_t fake_watchdog_feeds(void) { return wdt_feeds; }

void fake_adc_set(uint8_t channel, uint16_t mv)
{
    if (channel < 3u) {
        adc_mv[channel] = mv;
    }
}

void fake_set_plant(fake_plant_fn fn, void *ctx)
{
    plant = fn;
    plant_ctx = ctx;
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
    while (n < len && tx_len < tx_limit) {
        tx_buf[tx_len++] = data[n++];
    }
    return n;
}

void hal_pwm_set(uint16_t duty)
{
    pwm_duty = duty;
    pwm_sets++;
}

uint16_t hal_adc_mv(uint8_t channel)
{
    if (channel == HAL_ADC_CURRENT && plant != NULL) {
        return plant(pwm_duty, plant_ctx);
    }
    return channel < 3u ? adc_mv[channel] : 0u;
}

void hal_watchdog_feed(void) { wdt_feeds++; }
