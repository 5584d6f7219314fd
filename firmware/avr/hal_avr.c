/* AVR implementation of hal.h for the current driver: ATmega328P at 16 MHz (firmware/PROTOCOL.md,
 * "Hardware").
 *   UART0    115200 8N1 (U2X, UBRR0 = 16: 117647 baud, +2.1 %), RX and UDRE interrupts, ring
 *            buffers RX 64 / TX 128 bytes.
 *   Timer0   CTC, /64, OCR0A = 249: 1 kHz tick -> hal_millis() and the control tick flag.
 *   Timer1   fast PWM 10-bit (WGM1 = 7), no prescaler: 15.625 kHz on OC1A (PB1). Duty 0 disconnects
 *            OC1A and drives PB1 low, so "off" is a clean low pin, not a 1-clock spike.
 *   ADC      AVcc reference, /128 (125 kHz), single conversions restarted from the ADC interrupt,
 *            cycling channels 0, 1, 2 (each channel refreshed every ~0.3 ms).
 *   Watchdog 60 ms (WDTO_60MS); MCUSR saved and cleared, watchdog disabled in .init3.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <util/atomic.h>

#include "hal.h"
#include "hal_avr.h"

#ifndef F_CPU
#error "F_CPU must be defined (16000000UL)"
#endif

/* ------------------------------------------------------------------ reset cause (.init3) */
/* Read before main() and before the C runtime clears .bss; .noinit keeps it from being zeroed.
 * After a watchdog reset WDRF forces WDE on with the shortest timeout: it must be cleared and the
 * watchdog disabled at once (avr-libc <avr/wdt.h> documentation). */
static uint8_t mcusr_at_reset __attribute__((section(".noinit")));

void hal_avr_early_init(void) __attribute__((naked, used, section(".init3")));
void hal_avr_early_init(void)
{
    mcusr_at_reset = MCUSR;
    MCUSR = 0;
    wdt_disable();
}

uint8_t hal_avr_reset_cause(void) { return mcusr_at_reset; }

uint8_t hal_avr_was_watchdog_reset(void) { return (mcusr_at_reset & _BV(WDRF)) ? 1u : 0u; }

/* ------------------------------------------------------------------ UART0 */
#define RX_SIZE 64u  /* powers of two: indices wrap with a mask */
#define TX_SIZE 128u
#define RX_MASK (RX_SIZE - 1u)
#define TX_MASK (TX_SIZE - 1u)

static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail; /* head: written by the ISR; tail: by hal_uart_read */
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail; /* head: written by hal_uart_write; tail: by the ISR */
static volatile uint8_t rx_overruns;      /* bytes lost (ring full or hardware DOR) */

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A;
    uint8_t c = UDR0;
    uint8_t next = (uint8_t)((rx_head + 1u) & RX_MASK);
    if (status & _BV(DOR0))
        rx_overruns++;
    if (next == rx_tail) { /* full: drop the byte; the frame it belonged to fails its CRC */
        rx_overruns++;
        return;
    }
    rx_buf[rx_head] = c;
    rx_head = next;
}

ISR(USART_UDRE_vect)
{
    if (tx_tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0); /* nothing left: stop the interrupt */
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) & TX_MASK);
}

int16_t hal_uart_read(void)
{
    uint8_t tail = rx_tail;
    if (tail == rx_head) /* single-byte reads are atomic */
        return -1;
    uint8_t c = rx_buf[tail];
    rx_tail = (uint8_t)((tail + 1u) & RX_MASK);
    return c;
}

uint8_t hal_uart_write(const uint8_t *data, uint8_t len)
{
    uint8_t n = 0;
    uint8_t head = tx_head;
    while (n < len) {
        uint8_t next = (uint8_t)((head + 1u) & TX_MASK);
        if (next == tx_tail)
            break; /* full: drop the rest */
        tx_buf[head] = data[n++];
        head = next;
    }
    if (n) {
        tx_head = head;
        UCSR0B |= _BV(UDRIE0); /* read-modify-write of UCSR0B: the UDRE ISR also clears UDRIE0 */
    }
    return n;
}

uint8_t hal_avr_uart_overruns(void) { return rx_overruns; }

static void uart_init(void)
{
    /* U2X and the frame format before UBRR0L: simavr derives its byte time from the UBRR0L write
     * (the order does not matter on the chip). */
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00); /* 8N1 */
    UBRR0H = 0;
    UBRR0L = 16; /* U2X: 16 MHz / (8 * 17) = 117647 baud, +2.1 % from 115200 */
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

/* ------------------------------------------------------------------ 1 ms tick (Timer0) */
static volatile uint32_t millis_count;
static volatile uint8_t tick_pending;

ISR(TIMER0_COMPA_vect)
{
    millis_count++;
    tick_pending = 1;
}

uint32_t hal_millis(void)
{
    uint32_t m;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { m = millis_count; }
    return m;
}

uint8_t hal_avr_take_tick(void)
{
    uint8_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        t = tick_pending;
        tick_pending = 0;
    }
    return t;
}

static void tick_init(void)
{
    TCCR0A = _BV(WGM01);             /* CTC, TOP = OCR0A */
    OCR0A = (F_CPU / 64u / 1000u) - 1u; /* 249 */
    TCNT0 = 0;
    TIFR0 = _BV(OCF0A);
    TIMSK0 = _BV(OCIE0A);
    TCCR0B = _BV(CS01) | _BV(CS00); /* clk / 64 */
}

/* ------------------------------------------------------------------ PWM (Timer1, OC1A = PB1) */
void hal_pwm_set(uint16_t duty)
{
    if (duty == 0u) {
        TCCR1A &= (uint8_t)~(_BV(COM1A1) | _BV(COM1A0)); /* disconnect OC1A: PB1 = PORTB1 = 0 */
        PORTB &= (uint8_t)~_BV(PB1);
        OCR1A = 0;
        return;
    }
    if (duty > HAL_PWM_TOP)
        duty = HAL_PWM_TOP;
    OCR1A = duty; /* double-buffered in fast PWM: takes effect at the next BOTTOM */
    TCCR1A |= _BV(COM1A1); /* non-inverting: set at BOTTOM, clear on compare match */
}

static void pwm_init(void)
{
    PORTB &= (uint8_t)~_BV(PB1); /* pin low before it becomes an output */
    DDRB |= _BV(DDB1);
    TCCR1A = _BV(WGM11) | _BV(WGM10); /* fast PWM 10-bit (mode 7), OC1A disconnected */
    OCR1A = 0;
    TCNT1 = 0;
    TCCR1B = _BV(WGM12) | _BV(CS10); /* no prescaler: 16 MHz / 1024 = 15.625 kHz */
}

/* ------------------------------------------------------------------ ADC */
#define ADC_CHANNELS 3u
static volatile uint16_t adc_mv[ADC_CHANNELS];
static volatile uint8_t adc_channel;

#define ADMUX_BASE (_BV(REFS0)) /* AVcc reference, right-adjusted */

ISR(ADC_vect)
{
    uint16_t raw = ADC;
    adc_mv[adc_channel] = (uint16_t)(((uint32_t)raw * 5000u + 511u) / 1023u);
    uint8_t next = (uint8_t)(adc_channel + 1u);
    if (next >= ADC_CHANNELS)
        next = 0;
    adc_channel = next;
    ADMUX = (uint8_t)(ADMUX_BASE | next);
    ADCSRA |= _BV(ADSC); /* next single conversion */
}

uint16_t hal_adc_mv(uint8_t channel)
{
    uint16_t v;
    if (channel >= ADC_CHANNELS)
        return 0;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE) { v = adc_mv[channel]; }
    return v;
}

static void adc_init(void)
{
    DIDR0 = _BV(ADC0D) | _BV(ADC1D) | _BV(ADC2D); /* no digital input buffers on the analog pins */
    adc_channel = 0;
    ADMUX = ADMUX_BASE | 0u;
    /* enable, interrupt, /128; the first conversion starts in hal_avr_start() */
    ADCSRA = _BV(ADEN) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0);
}

/* ------------------------------------------------------------------ watchdog */
void hal_watchdog_feed(void) { wdt_reset(); }

void hal_avr_watchdog_enable(void) { wdt_enable(WDTO_60MS); }

/* ------------------------------------------------------------------ init */
void hal_avr_init(void)
{
    pwm_init(); /* first: the output pin is driven low as early as possible */
    uart_init();
    tick_init();
    adc_init();
    set_sleep_mode(SLEEP_MODE_IDLE);
}

void hal_avr_idle(void)
{
    /* Sleep (idle mode: timers, UART and ADC keep running) until the next interrupt, unless a
     * received byte or a tick is already waiting. Interrupts are off while checking; SEI executes
     * the next instruction (SLEEP) before any interrupt, so a wake-up cannot be lost. Every
     * interrupt ends the sleep, the 1 ms tick at the latest. */
    cli();
    if (rx_head == rx_tail && !tick_pending) {
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
}

void hal_avr_start(void)
{
    ADCSRA |= _BV(ADSC); /* start the ADC conversion chain (runs from its interrupt) */
}
