/* AVR-only additions to hal.h, used by firmware/avr/main.c. */
#ifndef SMA_HAL_AVR_H
#define SMA_HAL_AVR_H
#include <stdint.h>

/* Configure UART0, the 1 ms tick (Timer0), the PWM (Timer1, output low) and the ADC. Interrupts
 * stay off. */
void hal_avr_init(void);
/* Start the interrupt-driven parts that need a kick (the ADC conversion chain). Call before sei. */
void hal_avr_start(void);
/* MCUSR as read in .init3, before it was cleared. */
uint8_t hal_avr_reset_cause(void);
/* 1 when the last reset was caused by the watchdog: WDRF in MCUSR, or the marker its interrupt
 * left in .noinit (a bootloader may have cleared MCUSR). */
uint8_t hal_avr_was_watchdog_reset(void);
/* 1 (and clears it) when at least one 1 ms tick elapsed since the last call. */
uint8_t hal_avr_take_tick(void);
/* Sleep until the next interrupt unless a received byte or a tick is pending; returns with
 * interrupts on. */
void hal_avr_idle(void);
/* Enable the hardware watchdog: interrupt (output off, marker) after 32 ms without a feed, reset
 * 32 ms later. */
void hal_avr_watchdog_enable(void);
/* Received bytes lost to a full RX ring or a hardware overrun (wraps). */
uint8_t hal_avr_uart_overruns(void);
#endif
