/* Hardware abstraction used by the portable core (firmware/core). Implemented by the AVR HAL
 * (firmware/avr/hal_avr.c) and by the host test HAL (firmware/host/hal_fake.c). The circuit is
 * the reference linear current sink of firmware/hardware (electrical.h holds its numbers). */
#ifndef SMA_HAL_H
#define SMA_HAL_H
#include <stdint.h>

#define HAL_PWM_TOP 1023u /* Timer1 10-bit fast PWM: setpoint duty 0 ... HAL_PWM_TOP */

enum hal_adc_channel {
    HAL_ADC_CURRENT = 0, /* ADC0: shunt amplifier (fast current path), anti-alias filtered */
    HAL_ADC_SUPPLY = 1,  /* ADC1: wire supply through its divider */
    HAL_ADC_AMBIENT = 2, /* ADC2: ambient NTC divider (NTC on top, fixed resistor to ground) */
    HAL_ADC_REFERENCE = 3, /* ADC3: the REF3040 (ELEC_REFERENCE_MV): measures AVcc */
    HAL_ADC_CHANNELS = 4
};

enum hal_xadc_channel {
    HAL_XADC_WIRE = 0,  /* external ADC (ADS1115) AIN0-AIN1: Kelvin-sensed wire voltage */
    HAL_XADC_SHUNT = 1, /* AIN2-AIN3: shunt voltage (precise current) */
};

/* Milliseconds since reset (wraps after 49 days). */
uint32_t hal_millis(void);
/* Next received UART byte (0 ... 255) or -1 when the RX ring buffer is empty. Non-blocking. */
int16_t hal_uart_read(void);
/* Queue bytes for transmission; returns how many were queued (drops the rest if the TX ring
 * buffer is full). Non-blocking. The core writes a frame only when hal_uart_tx_free() says it
 * fits whole (PROTOCOL.md "Flow control"), so nothing is ever dropped here. */
uint8_t hal_uart_write(const uint8_t *data, uint8_t len);
/* Bytes hal_uart_write() would take now (free space of the TX ring buffer). */
uint8_t hal_uart_tx_free(void);
/* Setpoint PWM duty, 0 ... HAL_PWM_TOP (filtered to the sink's op-amp). 0 = pin low. */
void hal_pwm_set(uint16_t duty);
/* Driver enable line: 0 clamps the sink's setpoint to zero in hardware (also the reset state). */
void hal_output_enable(uint8_t on);
/* Mean of the conversions of an ADC channel since the previous call, in 1/16 ADC counts
 * (0 ... 1023*16). Conversions are started in step with the PWM period (synchronous sampling).
 * Without a new conversion since the previous call the last mean is returned again. */
uint16_t hal_adc_q4(uint8_t channel);
/* Hardware e-stop input: 1 when tripped now or at any moment since the previous call. */
uint8_t hal_estop_tripped(void);
/* External ADC: start a single conversion of a channel (HAL_XADC_*); 0 on success, -1 when the
 * device does not answer. */
int8_t hal_xadc_start(uint8_t channel);
/* External ADC: read the last conversion (signed code); 0 on success, -1 on a bus error. */
int8_t hal_xadc_read(int16_t *code);
/* Thermocouple amplifier (MAX31855): read its 32-bit word; 0 on success, -1 when the bus does not
 * complete. An absent chip reads as all ones or all zeros (the core decides). */
int8_t hal_tc_read(uint32_t *word);
/* EEPROM (byte addresses 0 ... 1023). Writes feed the hardware watchdog between bytes. */
void hal_eeprom_read(uint16_t addr, uint8_t *data, uint8_t len);
void hal_eeprom_write(uint16_t addr, const uint8_t *data, uint8_t len);
/* Feed the hardware watchdog. */
void hal_watchdog_feed(void);

/* The hardware cut (firmware/hardware/README.md "The cut"): U10 eFuse in the wire supply, EN =
 * NOR(D8, TRIP); the latch U8 (TRIP) is set by the LM339 comparators (shunt, supply current,
 * e-stop, external watchdog) and cleared only by a LOW pulse on D4 while no cause holds it. */
#define HAL_CUT_CLOSED 0x01u  /* D5: U10's EN is high (the switch conducts) */
#define HAL_CUT_TRIPPED 0x02u /* D6: the latch U8 is set */
/* Read back D5 and D6 (HAL_CUT_* bits). */
uint8_t hal_cut_read(void);
/* Pulse D4 LOW (>= 1 us): clears the latch unless a comparator still holds it set. */
void hal_cut_clear(void);
/* Toggle D7, the external watchdog's feed (a charge pump: it needs >= ~100 Hz of edges). Called
 * from the main loop only (core_control_tick), never from an interrupt: a hung loop stops it. */
void hal_cut_feed(void);
#endif
