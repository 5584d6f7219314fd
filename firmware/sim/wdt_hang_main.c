/* Test-only replacement for firmware/avr/main.c (make sim-test builds build/sim/wdt-hang.elf from it
 * with avr/hal_avr.c and the core): the same main loop, except that 300 ms after a power-on reset
 * the loop hangs (interrupts still on, watchdog no longer fed). The 60 ms hardware watchdog must
 * then reset the MCU; after that watchdog reset it runs normally and reports WATCHDOG_RESET. */
#include <avr/interrupt.h>
#include <stdint.h>

#include "core.h"
#include "hal.h"
#include "hal_avr.h"

int main(void)
{
    uint8_t wdt_reset = hal_avr_was_watchdog_reset();
    hal_avr_init();
    core_init(wdt_reset);
    hal_avr_watchdog_enable();
    hal_avr_start();
    sei();

    for (;;) {
        if (!wdt_reset && hal_millis() >= 300u)
            for (;;) { /* hung main loop */
            }
        core_poll();
        if (hal_avr_take_tick()) {
            core_control_tick();
            hal_watchdog_feed();
        }
        hal_avr_idle();
    }
}
