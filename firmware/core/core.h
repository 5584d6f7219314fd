/* Portable firmware core: frame codec, commands, current control of the linear sink, safety
 * (firmware/PROTOCOL.md, protocol version 4). No AVR headers here; all I/O goes through hal.h. */
#ifndef SMA_CORE_H
#define SMA_CORE_H
#include <stdint.h>
#include "proto.h"

#define CORE_PROTOCOL_VERSION PROTOCOL_VERSION
#define CORE_HARD_LIMIT_MA HARD_LIMIT_MA
#define CORE_CONTROL_PERIOD_MS 1u /* core_control_tick() is called every 1 ms */

/* EEPROM layout (byte addresses) */
#define EE_CAL_ADDR 0u   /* calibration block, 12 bytes (CAL_LEN + magic, version, CRC) */
#define EE_CAL_MAGIC 'c' /* with the wire-voltage offset (protocol 3); 'C' was protocol 2's */
#define EE_HEAT_ADDR 16u /* heat model block, 12 bytes */

/* Heat model defaults: the bench's 55 mm of 0.38 mm Flexinol, chosen so the model runs hotter than
 * the wire (PROTOCOL.md "Energy budget"): R above the austenite resistance (0.485 Ohm), heat
 * capacity without latent heat (m cp = 33.6 mJ/K), convection h = 90 W/(m2 K) on 65.7 mm2. */
#define HEAT_DEFAULT_R_MOHM 550u
#define HEAT_DEFAULT_C 336u    /* 0.1 mJ/K */
#define HEAT_DEFAULT_G 590u    /* 0.01 mW/K */
#define HEAT_DEFAULT_TMAX_DC 1800u /* 0.1 degC */
#define HEAT_REARM_K 10        /* OVERTEMP clears only this far below the maximum */
#define HEAT_AMBIENT_FALLBACK_C 40.0f /* ambient used while the NTC is faulty */

typedef struct {
    int16_t offset_ua;     /* fast-path current offset, uA (subtracted) */
    uint16_t current_gain; /* Q15 */
    uint16_t voltage_gain; /* Q15 */
    int16_t voltage_offset_uv; /* wire-voltage offset at the ADC's input scale, uV (subtracted) */
} core_cal_t;

typedef struct {
    uint16_t r_mohm;  /* wire resistance used for I^2 R (the hottest), mOhm */
    uint16_t c;       /* heat capacity, 0.1 mJ/K */
    uint16_t g;       /* heat loss to ambient, 0.01 mW/K */
    uint16_t tmax_dc; /* maximum wire temperature, 0.1 degC */
} core_heat_t;

/* Call once after reset; was_watchdog_reset = 1 when the reset cause was the hardware watchdog
 * (sets the WATCHDOG_RESET flag). Loads calibration and heat model from EEPROM. Output off. */
void core_init(uint8_t was_watchdog_reset);
/* Drain received bytes (hal_uart_read), decode frames, run commands, queue ACKs. Call from the
 * main loop as often as possible. */
void core_poll(void);
/* 1 kHz tick: measurements, safety (host timeout, lease, e-stop, energy budget, over-current,
 * open wire), current control, telemetry. Call from the main loop when the 1 ms timer elapsed. */
void core_control_tick(void);

/* Latch faults (FLAGS_LATCHED bits; others ignored) from outside the core: output off at once,
 * cleared by CLEAR_FAULTS as any latched fault. For an external protection reporting a trip and
 * for the host stand-ins' fault injection. */
void core_latch_fault(uint16_t fault);
/* The TELEMETRY payload (PROTOCOL.md) of the present state into out (TELEMETRY_LEN bytes);
 * returns TELEMETRY_LEN. */
uint8_t core_telemetry(uint8_t *out);

/* Read-only view of the state, for tests. */
typedef struct {
    uint8_t enabled;
    uint16_t flags;          /* PROTOCOL.md flags */
    uint16_t setpoint_ma;    /* after clamping; 0 after a lease expiry */
    uint16_t probe_ma;       /* SET_PROBE: held while enabled (max with the setpoint); 0 = off,
                              * and 0 again whenever the output goes off */
    uint16_t limit_ma;
    uint16_t host_timeout_ms;
    uint16_t lease_ms;
    uint16_t telemetry_period_ms;
    uint16_t duty;           /* 0 ... HAL_PWM_TOP */
    uint16_t current_ma;     /* fast path, calibrated */
    uint16_t voltage_dmv;    /* wire voltage, 0.1 mV; U16_NONE when not available */
    uint16_t precise_dma;    /* precise (external ADC) current, 0.1 mA; U16_NONE */
    uint16_t supply_mv;      /* wire supply */
    int16_t ambient_cdeg;    /* 0.01 degC; TEMP_NONE on an NTC fault */
    int16_t tc_cdeg;         /* thermocouple, 0.01 degC; TEMP_NONE when absent or faulty */
    uint8_t tc_status;       /* TC_* bits */
    float model_c;           /* energy budget: conservative wire temperature, degC */
    uint16_t rx_crc_errors;
    uint16_t rx_frame_errors;
    uint16_t telemetry_deferred; /* telemetry frames that waited for TX room (saturating) */
    uint32_t last_rx_ms;     /* hal_millis() of the last valid frame (feeds the host timeout) */
    core_cal_t cal;
    core_heat_t heat;
    uint16_t avcc_mv;        /* AVcc measured with the REF3040 on A3 (nominal when implausible) */
    uint8_t cut;             /* last read-back of the hardware cut (HAL_CUT_* bits) */
    uint8_t cut_armed;       /* the power-on clear of the cut is done: its trips are faults */
} core_state_t;
const core_state_t *core_state(void);
#endif
