/* Current-driver firmware entry point, ATmega328P at 16 MHz (firmware/PROTOCOL.md).
 * Main loop: core_poll() for received bytes; core_control_tick() once per elapsed 1 ms tick; the
 * hardware watchdog (60 ms) is fed only after a control tick ran, so a hung core or a dead tick
 * resets the MCU (output off at reset). Between events the CPU sleeps in idle mode. */
#include <avr/interrupt.h>
#include <stdint.h>

#include "core.h"
#include "hal.h"
#include "hal_avr.h"

int main(void)
{
    hal_avr_init(); /* PWM pin low first; interrupts still off */
    core_init(hal_avr_was_watchdog_reset());
    hal_avr_watchdog_enable();
    hal_avr_start();
    sei();

    for (;;) {
        core_poll();
        if (hal_avr_take_tick()) {
            core_control_tick();
            hal_watchdog_feed();
        }
        hal_avr_idle();
    }
}
