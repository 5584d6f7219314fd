/* Portable firmware core: frame codec, commands, PI current control, safety (firmware/PROTOCOL.md).
 * No AVR headers here; all I/O goes through hal.h. */
#ifndef SMA_CORE_H
#define SMA_CORE_H
#include <stdint.h>

#define CORE_PROTOCOL_VERSION 1u
#define CORE_HARD_LIMIT_MA 2500u
#define CORE_CONTROL_PERIOD_MS 1u /* core_control_tick() is called every 1 ms */

/* Call once after reset; was_watchdog_reset = 1 when the reset cause was the hardware watchdog
 * (sets the WATCHDOG_RESET flag). Leaves the output off. */
void core_init(uint8_t was_watchdog_reset);
/* Drain received bytes (hal_uart_read), decode frames, run commands, queue ACKs. Call from the
 * main loop as often as possible. */
void core_poll(void);
/* 1 kHz tick: read ADCs, run safety checks (host timeout, over-current, open wire), PI current
 * control, set the PWM, send telemetry when due. Call from the main loop when the 1 ms timer
 * elapsed (not from an interrupt). */
void core_control_tick(void);

/* Read-only view of the state, for tests. */
typedef struct {
    uint8_t enabled;
    uint16_t flags;          /* PROTOCOL.md flags */
    uint16_t setpoint_ma;    /* after clamping */
    uint16_t limit_ma;
    uint16_t host_timeout_ms;
    uint16_t telemetry_period_ms;
    uint16_t duty;           /* 0 ... HAL_PWM_TOP */
    uint16_t current_ma;     /* last measured */
    uint16_t rx_crc_errors;
    uint16_t rx_frame_errors;
} core_state_t;
const core_state_t *core_state(void);
#endif
