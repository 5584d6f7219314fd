/* Hardware abstraction used by the portable core (firmware/core). Implemented by the AVR HAL
 * (firmware/avr/hal_avr.c) and by the host test HAL (firmware/host/hal_fake.c). */
#ifndef SMA_HAL_H
#define SMA_HAL_H
#include <stdint.h>

#define HAL_PWM_TOP 1023u /* Timer1 10-bit fast PWM: duty 0 ... HAL_PWM_TOP */

enum hal_adc_channel {
    HAL_ADC_CURRENT = 0, /* shunt amplifier, 1 V per A */
    HAL_ADC_VOLTAGE = 1, /* wire voltage divider, 1/3 */
    HAL_ADC_AMBIENT = 2, /* NTC 10 kOhm B=3950 (top) to 10 kOhm (bottom), AVcc = 5 V */
};

/* Milliseconds since reset (wraps after 49 days). */
uint32_t hal_millis(void);
/* Next received UART byte (0 ... 255) or -1 when the RX ring buffer is empty. Non-blocking. */
int16_t hal_uart_read(void);
/* Queue bytes for transmission; returns how many were queued (drops the rest if the TX ring
 * buffer is full). Non-blocking. */
uint8_t hal_uart_write(const uint8_t *data, uint8_t len);
/* Set the PWM duty, 0 ... HAL_PWM_TOP. 0 means the MOSFET is off. */
void hal_pwm_set(uint16_t duty);
/* Latest conversion of an ADC channel, in millivolts at the pin (0 ... 5000). */
uint16_t hal_adc_mv(uint8_t channel);
/* Feed the hardware watchdog. */
void hal_watchdog_feed(void);
#endif
