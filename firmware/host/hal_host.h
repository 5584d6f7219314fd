/* Host HAL for the Python stand-ins (drivers/mock/corelib.py loads core + this HAL as a shared
 * library, one private copy per device instance). The electrical side is NOT modelled here:
 * Python writes the inputs (ADC means, external-ADC codes, thermocouple word, e-stop level,
 * time) into host_io before each tick and reads the outputs (PWM duty, enable line) after it.
 * The UART is two byte queues: host -> device (large: the transport delivers at once) and
 * device -> host (HOST_TX_SIZE, the AVR's TX ring, so the core sees the same free space). */
#ifndef SMA_HAL_HOST_H
#define SMA_HAL_HOST_H
#include <stdint.h>
#include "core.h"
#include "hal.h"

#define HOST_RX_CAP 4096u
#define HOST_TX_SIZE 128u /* as TX_SIZE in avr/hal_avr.c */

typedef struct {
    /* inputs, written by Python */
    uint32_t millis;
    uint16_t adc_q4[HAL_ADC_CHANNELS]; /* mean of the last tick's conversions, 1/16 counts */
    uint8_t estop;                     /* e-stop input level, 1 = tripped */
    uint8_t xadc_present;              /* ADS1115 answers */
    int16_t xadc_code[2];              /* HAL_XADC_WIRE, HAL_XADC_SHUNT codes */
    uint8_t tc_bus_ok;                 /* the MAX31855 read completes */
    uint32_t tc_word;                  /* its 32-bit word (absent chip: 0xFFFFFFFF) */
    /* outputs, written by the core through the HAL */
    uint16_t pwm_duty;
    uint8_t output_enabled;
    uint32_t watchdog_feeds;
    /* the hardware cut (Python models its comparators and watchdog pump every tick): */
    uint8_t cut_latch;   /* in/out: the latch U8 (set by Python, cleared by a D4 pulse) */
    uint8_t cut_hold;    /* in: a cause holds the latch set (a clear pulse does nothing) */
    uint32_t cut_feeds;  /* out: D7 toggles */
    uint32_t cut_clears; /* out: D4 pulses */
} host_io_t;

host_io_t *host_io(void);
uint8_t *host_eeprom(void);        /* 1024 bytes */
uint32_t host_state_size(void);    /* sizeof(core_state_t): the Python mirror checks it */
uint32_t host_io_size(void);       /* sizeof(host_io_t) */
void host_init(uint8_t was_watchdog_reset); /* queues emptied, core_init */
/* Queue bytes from the host; returns how many were taken (all unless HOST_RX_CAP is full). */
uint32_t host_rx_push(const uint8_t *data, uint32_t len);
uint32_t host_rx_pending(void);
/* Take up to cap bytes the device queued for the host; returns how many. */
uint32_t host_tx_take(uint8_t *out, uint32_t cap);
/* The telemetry payload the core would send now (TELEMETRY_LEN bytes). */
uint8_t host_telemetry(uint8_t *out);
#endif
