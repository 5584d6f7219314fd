/* Fake HAL for host tests and fuzzing (implements core/hal.h) with a model of the reference
 * linear current sink (firmware/hardware): setpoint PWM -> two RC poles -> op-amp + MOSFET ->
 * wire + shunt, limited by the supply's headroom; anti-aliased shunt amplifier -> 10-bit ADC
 * sampled 4 times per ms; an ADS1115 on the Kelvin leads and the shunt; a MAX31855; an NTC;
 * the e-stop input; 1 KiB of EEPROM. Numbers from electrical.h. */
#ifndef SMA_HAL_FAKE_H
#define SMA_HAL_FAKE_H
#include <stddef.h>
#include <stdint.h>
#include "hal.h"

#define FAKE_RX_CAP 4096u
#define FAKE_TX_CAP 16384u

/* The load and the conditions the sink works in. */
typedef struct {
    double wire_ohm;      /* wire between the Kelvin taps (0.3 ... 1 Ohm) */
    double supply_v;      /* wire supply at no load (4.75 ... 5.5 V) */
    double source_ohm;    /* supply + leads + fuse */
    uint8_t open;         /* wire broken: no current */
    double setpoint_gain; /* real / nominal setpoint path (divider, PWM level tolerance) */
    double adc_gain;      /* real / nominal fast-path gain */
    double adc_offset_ma; /* fast-path offset, mA */
    double ripple_a_pp;   /* PWM ripple on the wire current (15.625 kHz), peak to peak, A */
    double async_period_us; /* 0: conversions at every 2nd PWM period (the HAL); else this period */
    double wire_offset_v; /* wire-voltage amplifier offset referred to the wire, V */
} fake_sink_t;

void fake_reset(void);                 /* everything but the EEPROM to defaults; sink on 0.44 Ohm */
void fake_eeprom_erase(void);          /* EEPROM to 0xFF */
void fake_set_millis(uint32_t ms);
/* Advance time: the sink model runs in 50 us steps, the ADC samples 4 times per ms. */
void fake_advance_ms(uint32_t ms);
fake_sink_t *fake_sink(void);          /* change the load at any time */
double fake_current_a(void);           /* true wire current now */

void fake_rx_push(const uint8_t *data, size_t len);
size_t fake_rx_pending(void);
const uint8_t *fake_tx_data(size_t *len); /* bytes written by the core since the last clear */
void fake_tx_clear(void);
void fake_tx_set_limit(size_t max_bytes);  /* simulate a full TX ring: accept at most this many */
/* Model the AVR's TX ring: at most capacity bytes queued, sent at bytes_per_ms (117647 baud, 10
 * bits a byte: 11.76); fake_tx_data() then returns only what went out. capacity 0: off. */
void fake_tx_ring(size_t capacity, double bytes_per_ms);

uint16_t fake_pwm_duty(void);        /* last duty set */
uint8_t fake_output_enabled(void);   /* enable line */
uint32_t fake_pwm_set_count(void);
uint32_t fake_watchdog_feeds(void);

void fake_ntc_celsius(double c);     /* ambient seen by the NTC divider */
void fake_ntc_mv(uint16_t mv);       /* raw ADC2 voltage (open: ~0, shorted: ~5000) */
void fake_estop(uint8_t tripped);    /* e-stop input level (latched until read by the core) */
void fake_xadc_present(uint8_t on);  /* ADS1115 answers (default 1) */
/* MAX31855: absent (0), or present with a wire temperature (1), or a fault word's bits. */
void fake_tc_absent(void);
void fake_tc_celsius(double c);
void fake_tc_fault(uint8_t bits);    /* TC_OC / TC_SCG / TC_SCV */
uint8_t fake_eeprom_byte(uint16_t addr);
/* AVcc (the ADC's reference; default 5000 mV): ADC0/1 read against it, A3 reads the 4.096 V
 * REF3040, the NTC divider hangs from it. */
void fake_avcc_mv(double mv);
/* The hardware cut: latch U8 (starts set: the watchdog pump is empty at power-on), set by a
 * comparator (fake_cut_trip), the e-stop level or the pump (D7 edges: charged to 3.6 V, decays
 * with 22 ms below 1.63 V); cleared by a D4 pulse unless a cause holds it (fake_cut_hold).
 * The switch conducts while the enable line is on and the latch is clear. */
void fake_cut_trip(void);
void fake_cut_hold(uint8_t on);
uint8_t fake_cut_tripped(void);
uint8_t fake_cut_closed(void);
uint32_t fake_cut_feeds(void);  /* D7 toggles */
uint32_t fake_cut_clears(void); /* D4 pulses */
#endif
