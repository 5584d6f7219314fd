/* Fake HAL for host tests and fuzzing (implements core/hal.h). */
#ifndef SMA_HAL_FAKE_H
#define SMA_HAL_FAKE_H
#include <stddef.h>
#include <stdint.h>
#include "hal.h"

#define FAKE_RX_CAP 4096u
#define FAKE_TX_CAP 8192u

/* Current model: returns the shunt amplifier output in mV (= mA) for the duty applied. */
typedef uint16_t (*fake_plant_fn)(uint16_t duty, void *ctx);

/* Resistive reference load: I = duty / HAL_PWM_TOP * supply / (wire + series). */
typedef struct {
    uint32_t supply_mv;   /* 12000 for the reference load */
    uint32_t load_mohm;   /* wire + shunt + switch, 4200 for the reference load */
    uint8_t open;         /* 1: wire broken, no current */
} fake_load_t;
uint16_t fake_plant_resistive(uint16_t duty, void *ctx); /* ctx: fake_load_t* */

void fake_reset(void);                 /* everything to zero, no plant, unlimited TX */
void fake_set_millis(uint32_t ms);
void fake_advance_ms(uint32_t ms);

void fake_rx_push(const uint8_t *data, size_t len);
size_t fake_rx_pending(void);

const uint8_t *fake_tx_data(size_t *len); /* bytes written by the core since the last clear */
void fake_tx_clear(void);
void fake_tx_set_limit(size_t max_bytes);  /* simulate a full TX ring: accept at most this many */

uint16_t fake_pwm_duty(void);        /* last duty set */
uint32_t fake_pwm_set_count(void);   /* number of hal_pwm_set calls */
uint32_t fake_watchdog_feeds(void);

void fake_adc_set(uint8_t channel, uint16_t mv);
/* With a plant, HAL_ADC_CURRENT returns plant(last duty) instead of the set value. NULL: off. */
void fake_set_plant(fake_plant_fn fn, void *ctx);
#endif
