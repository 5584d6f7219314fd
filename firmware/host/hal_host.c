/* Host HAL for the Python stand-ins (see hal_host.h). */
#include <string.h>
#include "hal_host.h"

static host_io_t io;
static uint8_t eeprom[1024];
static uint8_t eeprom_init;
static uint8_t rx_buf[HOST_RX_CAP];
static uint32_t rx_head, rx_len;
static uint8_t tx_buf[HOST_TX_SIZE];
static uint32_t tx_head, tx_len;

host_io_t *host_io(void) { return &io; }
uint8_t *host_eeprom(void)
{
    if (!eeprom_init) {
        memset(eeprom, 0xFF, sizeof eeprom); /* a blank chip */
        eeprom_init = 1;
    }
    return eeprom;
}
uint32_t host_state_size(void) { return (uint32_t)sizeof(core_state_t); }
uint32_t host_io_size(void) { return (uint32_t)sizeof(host_io_t); }

void host_init(uint8_t was_watchdog_reset)
{
    (void)host_eeprom();
    rx_head = rx_len = 0;
    tx_head = tx_len = 0;
    io.pwm_duty = 0;
    io.output_enabled = 0;
    io.cut_latch = 1; /* power-on: the watchdog pump is empty */
    core_init(was_watchdog_reset);
}

uint32_t host_rx_push(const uint8_t *data, uint32_t len)
{
    uint32_t n = 0;
    while (n < len && rx_len < HOST_RX_CAP) {
        rx_buf[(rx_head + rx_len) % HOST_RX_CAP] = data[n++];
        rx_len++;
    }
    return n;
}

uint32_t host_rx_pending(void) { return rx_len; }

uint32_t host_tx_take(uint8_t *out, uint32_t cap)
{
    uint32_t n = 0;
    while (n < cap && tx_len > 0u) {
        out[n++] = tx_buf[tx_head];
        tx_head = (tx_head + 1u) % HOST_TX_SIZE;
        tx_len--;
    }
    return n;
}

uint8_t host_telemetry(uint8_t *out) { return core_telemetry(out); }

/* ------------------------------------------------------------------ hal.h */
uint32_t hal_millis(void) { return io.millis; }

int16_t hal_uart_read(void)
{
    if (rx_len == 0u) {
        return -1;
    }
    uint8_t c = rx_buf[rx_head];
    rx_head = (rx_head + 1u) % HOST_RX_CAP;
    rx_len--;
    return c;
}

uint8_t hal_uart_write(const uint8_t *data, uint8_t len)
{
    uint8_t n = 0;
    while (n < len && tx_len < HOST_TX_SIZE) {
        tx_buf[(tx_head + tx_len) % HOST_TX_SIZE] = data[n++];
        tx_len++;
    }
    return n;
}

uint8_t hal_uart_tx_free(void) { return (uint8_t)(HOST_TX_SIZE - tx_len); }

void hal_pwm_set(uint16_t duty) { io.pwm_duty = duty; }
void hal_output_enable(uint8_t on) { io.output_enabled = on ? 1u : 0u; }

/* The ADS1115 converts over the 1.16 ms after its start (860 SPS). Python sets the inputs of
 * each ms before the tick that ends it: a conversion takes 7/8 of the first ms after its start and
 * 1/8 of the next, taken as those ticks come (the core reads the fast path first thing every
 * tick) and at its read. */
static uint8_t xadc_ch, xadc_ms_taken;
static uint32_t xadc_start_ms;
static int32_t xadc_acc; /* the code's eighths so far */

static void xadc_convert(void)
{
    uint32_t ms = io.millis - xadc_start_ms;
    if (xadc_ms_taken == 0u && ms >= 1u) {
        xadc_acc = 7 * (int32_t)io.xadc_code[xadc_ch];
        xadc_ms_taken = 1u;
    } else if (xadc_ms_taken == 1u && ms >= 2u) {
        xadc_acc += io.xadc_code[xadc_ch];
        xadc_ms_taken = 2u;
    }
}

uint16_t hal_adc_q4(uint8_t channel)
{
    xadc_convert();
    return channel < HAL_ADC_CHANNELS ? io.adc_q4[channel] : 0u;
}

uint8_t hal_estop_tripped(void) { return io.estop ? 1u : 0u; } /* Python sets the level per tick */

int8_t hal_xadc_start(uint8_t channel)
{
    if (!io.xadc_present) {
        return -1;
    }
    xadc_ch = channel & 1u;
    xadc_start_ms = io.millis;
    xadc_ms_taken = 0u;
    return 0;
}

int8_t hal_xadc_read(int16_t *code)
{
    if (!io.xadc_present) {
        return -1;
    }
    xadc_convert();
    if (xadc_ms_taken == 0u) { /* read in the ms it started: the inputs now */
        *code = io.xadc_code[xadc_ch];
    } else if (xadc_ms_taken == 1u) { /* read before its end: the first ms */
        *code = (int16_t)(xadc_acc / 7);
    } else {
        *code = (int16_t)((xadc_acc + (xadc_acc >= 0 ? 4 : -4)) / 8);
    }
    return 0;
}

int8_t hal_tc_read(uint32_t *word)
{
    if (!io.tc_bus_ok) {
        return -1;
    }
    *word = io.tc_word;
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
        io.watchdog_feeds++;
    }
}

void hal_watchdog_feed(void) { io.watchdog_feeds++; }

/* The cut's logic is combinational (EN = NOR(D8, TRIP)) and the clear acts at once, so both live
 * here; what sets the latch (comparators, the watchdog pump, the e-stop) is modelled in Python. */
uint8_t hal_cut_read(void)
{
    return (uint8_t)((io.output_enabled && !io.cut_latch ? HAL_CUT_CLOSED : 0u) |
                     (io.cut_latch ? HAL_CUT_TRIPPED : 0u));
}

void hal_cut_clear(void)
{
    io.cut_clears++;
    if (!io.cut_hold) {
        io.cut_latch = 0;
    }
}

void hal_cut_feed(void) { io.cut_feeds++; }
