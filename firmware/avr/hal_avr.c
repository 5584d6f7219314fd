/* AVR implementation of hal.h for the reference current driver (firmware/hardware): ATmega328P at
 * 16 MHz on an Arduino Nano. Pins (electrical.toml [pins]): D9 OC1A setpoint PWM, D8 driver
 * enable (driven low = setpoint released; high-Z = clamped, also the reset state), D2 e-stop
 * (INT0, pull-up, the NC contact holds it low), A0 current, A1 switched supply, A2 NTC, A3 REF3040, A4/A5 I2C to the
 * ADS1115, D10/D12/D13 SPI to the MAX31855.
 *   UART0    115200 8N1 (U2X, UBRR0 = 16: 117647 baud, +2.1 %), RX and UDRE interrupts, ring
 *            buffers RX 64 / TX 128 bytes.
 *   Timer0   CTC, /64, OCR0A = 249: 1 kHz tick -> hal_millis() and the control tick flag.
 *   Timer1   fast PWM 10-bit (WGM1 = 7), no prescaler: 15.625 kHz on OC1A. Its overflow interrupt
 *            starts the ADC conversions, so every sample sits at the same phase of the PWM period
 *            (synchronous sampling: what is left of the PWM ripple after the setpoint filter
 *            aliases to a constant, never to a beat).
 *   ADC      AVcc reference, /128 (104 us per conversion: every second PWM period), a fixed
 *            sequence of 8 slots: current x6, supply, NTC; sums and counts per channel.
 *   TWI      400 kHz master, polled with bounded waits (ADS1115).
 *   SPI      master, mode 0, 4 MHz, polled with bounded waits (MAX31855).
 *   Cut      D7 toggled every control tick (external watchdog), D4 LOW pulse clears its latch, D5
 *            (EN) and D6 (TRIP) read back; ADC3 reads the REF3040 (AVcc measured).
 *   Watchdog interrupt-then-reset, 32 ms + 32 ms: the interrupt turns the output off and leaves
 *            a marker in .noinit, so a watchdog reset is recognised after the reset even when a
 *            bootloader (optiboot) has cleared MCUSR; MCUSR is read and cleared in .init3.
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <stdint.h>
#include <util/atomic.h>
#include <util/delay.h>

#include "hal.h"
#include "hal_avr.h"

#ifndef F_CPU
#error "F_CPU must be defined (16000000UL)"
#endif

/* ------------------------------------------------------------------ reset cause (.init3) */
#define WDT_MARK 0x5AC3u
static uint8_t mcusr_at_reset __attribute__((section(".noinit")));
static uint16_t wdt_mark __attribute__((section(".noinit")));
static uint16_t wdt_mark_inv __attribute__((section(".noinit")));
static uint8_t wdt_marked __attribute__((section(".noinit")));

void hal_avr_early_init(void) __attribute__((naked, used, section(".init3")));
void hal_avr_early_init(void)
{
    mcusr_at_reset = MCUSR;
    MCUSR = 0;
    wdt_disable(); /* after a watchdog reset WDRF forces WDE on at the shortest timeout */
    wdt_marked = (wdt_mark == WDT_MARK && wdt_mark_inv == (uint16_t)~WDT_MARK) ? 1u : 0u;
    wdt_mark = 0;
    wdt_mark_inv = 0;
}

uint8_t hal_avr_reset_cause(void) { return mcusr_at_reset; }

uint8_t hal_avr_was_watchdog_reset(void)
{
    return ((mcusr_at_reset & _BV(WDRF)) || wdt_marked) ? 1u : 0u;
}

/* ------------------------------------------------------------------ output (PWM, enable) */
#define ENABLE_DDR DDRB
#define ENABLE_PORT PORTB
#define ENABLE_BIT PB0 /* D8 */

static inline void output_hard_off(void)
{
    ENABLE_DDR &= (uint8_t)~_BV(ENABLE_BIT);  /* high-Z: the pull-up clamps the setpoint */
    ENABLE_PORT &= (uint8_t)~_BV(ENABLE_BIT);
    TCCR1A &= (uint8_t)~(_BV(COM1A1) | _BV(COM1A0)); /* PWM pin low */
    PORTB &= (uint8_t)~_BV(PB1);
}

/* Stage 1 of the watchdog: the main loop has not fed it for 32 ms. Output off, leave the marker,
 * wait for stage 2 (the reset, 32 ms later). */
ISR(WDT_vect)
{
    output_hard_off();
    wdt_mark = WDT_MARK;
    wdt_mark_inv = (uint16_t)~WDT_MARK;
    for (;;) {
    }
}

void hal_output_enable(uint8_t on)
{
    if (on) {
        ENABLE_PORT &= (uint8_t)~_BV(ENABLE_BIT);
        ENABLE_DDR |= _BV(ENABLE_BIT); /* driven low: setpoint released */
    } else {
        ENABLE_DDR &= (uint8_t)~_BV(ENABLE_BIT);
    }
}

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
    TCCR1A |= _BV(COM1A1);
}

static void pwm_init(void)
{
    ENABLE_DDR &= (uint8_t)~_BV(ENABLE_BIT);
    ENABLE_PORT &= (uint8_t)~_BV(ENABLE_BIT);
    PORTB &= (uint8_t)~_BV(PB1); /* pin low before it becomes an output */
    DDRB |= _BV(DDB1);
    TCCR1A = _BV(WGM11) | _BV(WGM10); /* fast PWM 10-bit (mode 7), OC1A disconnected */
    OCR1A = 0;
    TCNT1 = 0;
    TCCR1B = _BV(WGM12) | _BV(CS10); /* no prescaler: 16 MHz / 1024 = 15.625 kHz */
}

/* ------------------------------------------------------------------ e-stop (D2, INT0) */
static volatile uint8_t estop_latched;

ISR(INT0_vect)
{
    output_hard_off(); /* at once, before the core's next tick */
    estop_latched = 1;
}

uint8_t hal_estop_tripped(void)
{
    uint8_t t;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        t = (uint8_t)((PIND & _BV(PD2)) ? 1u : 0u) | estop_latched;
        estop_latched = 0;
    }
    return t;
}

static void estop_init(void)
{
    DDRD &= (uint8_t)~_BV(PD2);
    PORTD |= _BV(PD2);                   /* pull-up: an open contact (or cable) reads high */
    EICRA = _BV(ISC01) | _BV(ISC00);     /* INT0 on the rising edge */
    EIFR = _BV(INTF0);
    EIMSK = _BV(INT0);
}

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

/* The ring holds TX_SIZE - 1 bytes; tx_tail moves on in the ISR (a single-byte read is atomic),
 * so the space only grows between this call and the write that follows it. */
uint8_t hal_uart_tx_free(void)
{
    return (uint8_t)(TX_MASK - ((uint8_t)(tx_head - tx_tail) & TX_MASK));
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

/* ------------------------------------------------------------------ ADC, synchronous */
#define ADMUX_BASE (_BV(REFS0)) /* AVcc reference, right-adjusted */
static const uint8_t adc_slots[8] = {HAL_ADC_CURRENT, HAL_ADC_CURRENT, HAL_ADC_CURRENT,
                                     HAL_ADC_SUPPLY,  HAL_ADC_CURRENT, HAL_ADC_CURRENT,
                                     HAL_ADC_REFERENCE, HAL_ADC_AMBIENT};
static volatile uint32_t adc_sum[HAL_ADC_CHANNELS]; /* NTC: ~100 conversions per read */
static volatile uint8_t adc_n[HAL_ADC_CHANNELS];
static uint16_t adc_last[HAL_ADC_CHANNELS];
static volatile uint8_t adc_slot;
static volatile uint8_t adc_busy; /* a conversion started whose result the ADC ISR has not taken */

/* Every PWM period (64 us) at BOTTOM: start a conversion unless the last one is still running or
 * its result not yet taken (the overflow vector outranks the ADC's: without the flag a new
 * conversion could start on the old channel before the ADC ISR moved the multiplexer on). */
ISR(TIMER1_OVF_vect)
{
    if (!adc_busy) {
        adc_busy = 1;
        ADCSRA |= _BV(ADSC);
    }
}

ISR(ADC_vect)
{
    adc_busy = 0;
    uint8_t ch = adc_slots[adc_slot];
    if (adc_n[ch] < 255u) {
        adc_sum[ch] += ADC;
        adc_n[ch]++;
    }
    adc_slot = (uint8_t)((adc_slot + 1u) & 7u);
    ADMUX = (uint8_t)(ADMUX_BASE | adc_slots[adc_slot]);
}

uint16_t hal_adc_q4(uint8_t channel)
{
    uint32_t sum;
    uint8_t n;
    if (channel >= HAL_ADC_CHANNELS)
        return 0;
    ATOMIC_BLOCK(ATOMIC_RESTORESTATE)
    {
        sum = adc_sum[channel];
        n = adc_n[channel];
        adc_sum[channel] = 0;
        adc_n[channel] = 0;
    }
    if (n)
        adc_last[channel] = (uint16_t)(((sum << 4) + n / 2u) / n);
    return adc_last[channel];
}

static void adc_init(void)
{
    DIDR0 = _BV(ADC0D) | _BV(ADC1D) | _BV(ADC2D) | _BV(ADC3D); /* no digital input buffers on the analog pins */
    adc_slot = 0;
    ADMUX = ADMUX_BASE | adc_slots[0];
    ADCSRA = _BV(ADEN) | _BV(ADIE) | _BV(ADPS2) | _BV(ADPS1) | _BV(ADPS0); /* /128 */
}

/* ------------------------------------------------------------------ TWI (ADS1115) */
#define ADS1115_SLA (0x48u << 1) /* ADDR to GND (electrical.toml precise_adc.i2c_address) */
#define TWI_WAIT 1500u           /* polls: ~0.5 ms, > 9 bit times at 400 kHz */

/* Wait for TWINT with one of the expected status codes. Waiting for the status, not TWINT
 * alone: simavr 1.6 leaves TWINT set after a write of 1 and posts the status later; on the chip
 * TWINT clears at once, so both ways end on the right status or on the timeout (an unexpected
 * status, e.g. a NACK because no ADS1115 answers, also ends here, after the timeout). */
static int8_t twi_wait_for(uint8_t st1, uint8_t st2)
{
    for (uint16_t i = 0; i < TWI_WAIT; i++) {
        if (TWCR & _BV(TWINT)) {
            uint8_t st = TWSR & 0xF8u;
            if (st == st1 || st == st2)
                return 0;
            if (st == 0x20u || st == 0x30u || st == 0x48u || st == 0x38u)
                return -1; /* NACK or arbitration lost: fail at once */
        }
    }
    return -1;
}

static void twi_stop(void)
{
    TWCR = _BV(TWINT) | _BV(TWSTO) | _BV(TWEN);
}

static int8_t twi_start(uint8_t sla_rw)
{
    TWCR = _BV(TWINT) | _BV(TWSTA) | _BV(TWEN);
    if (twi_wait_for(0x08u, 0x10u)) /* START, repeated START */
        return -1;
    TWDR = sla_rw;
    TWCR = _BV(TWINT) | _BV(TWEN);
    /* SLA+W (0x18) / SLA+R (0x40) acknowledged; simavr 1.6 posts an acknowledged SLA+W as 0x28
     * (data acknowledged), which the chip never does after an address */
    return (sla_rw & 1u) ? twi_wait_for(0x40u, 0x40u) : twi_wait_for(0x18u, 0x28u);
}

static int8_t twi_write(uint8_t b)
{
    TWDR = b;
    TWCR = _BV(TWINT) | _BV(TWEN);
    return twi_wait_for(0x28u, 0x28u);
}

static int8_t twi_read(uint8_t *b, uint8_t ack)
{
    TWCR = (uint8_t)(_BV(TWINT) | _BV(TWEN) | (ack ? _BV(TWEA) : 0));
    if (twi_wait_for(ack ? 0x50u : 0x58u, ack ? 0x50u : 0x58u))
        return -1;
    *b = TWDR;
    return 0;
}

/* ADS1115 config (TI SBAS444, Config register): OS = 1 (start), MUX, PGA, MODE = 1 (single
 * shot), DR = 111 (860 SPS), comparator off (COMP_QUE = 11).
 *   wire:  MUX 000 (AIN0-AIN1), PGA 010 (+-2.048 V) -> 0x85E3
 *   shunt: MUX 011 (AIN2-AIN3), PGA 101 (+-0.256 V) -> 0xBBE3 */
int8_t hal_xadc_start(uint8_t channel)
{
    uint16_t cfg = channel == HAL_XADC_WIRE ? 0x85E3u : 0xBBE3u;
    int8_t rc = twi_start(ADS1115_SLA);
    if (!rc)
        rc = twi_write(0x01u);
    if (!rc)
        rc = twi_write((uint8_t)(cfg >> 8));
    if (!rc)
        rc = twi_write((uint8_t)cfg);
    twi_stop();
    return rc;
}

int8_t hal_xadc_read(int16_t *code)
{
    uint8_t hi = 0, lo = 0;
    int8_t rc = twi_start(ADS1115_SLA);
    if (!rc)
        rc = twi_write(0x00u); /* pointer: conversion register */
    twi_stop();
    if (!rc)
        rc = twi_start(ADS1115_SLA | 1u);
    if (!rc)
        rc = twi_read(&hi, 1);
    if (!rc)
        rc = twi_read(&lo, 0);
    twi_stop();
    if (!rc)
        *code = (int16_t)(((uint16_t)hi << 8) | lo);
    return rc;
}

static void twi_init(void)
{
    TWSR = 0;  /* prescaler 1 */
    TWBR = 12; /* 16 MHz / (16 + 2 * 12) = 400 kHz */
    TWCR = _BV(TWEN);
}

/* ------------------------------------------------------------------ SPI (MAX31855) */
#define TC_CS PB2 /* D10 = SS: an output, so the SPI stays master */
#define SPI_WAIT 400u

int8_t hal_tc_read(uint32_t *word)
{
    uint32_t w = 0;
    int8_t rc = 0;
    PORTB &= (uint8_t)~_BV(TC_CS);
    for (uint8_t k = 0; k < 4u && !rc; k++) {
        SPDR = 0;
        uint16_t i = 0;
        while (!(SPSR & _BV(SPIF)) && ++i < SPI_WAIT) {
        }
        if (i >= SPI_WAIT)
            rc = -1;
        w = (w << 8) | SPDR;
    }
    PORTB |= _BV(TC_CS);
    *word = w;
    return rc;
}

static void spi_init(void)
{
    PORTB |= _BV(TC_CS);
    DDRB |= _BV(TC_CS) | _BV(PB3) | _BV(PB5); /* CS, MOSI, SCK out; MISO in */
    DDRB &= (uint8_t)~_BV(PB4);
    PORTB |= _BV(PB4); /* pull-up: no chip reads all ones (absent) */
    SPCR = _BV(SPE) | _BV(MSTR); /* mode 0, fosc/4 = 4 MHz (MAX31855: <= 5 MHz) */
}

/* ------------------------------------------------------------------ EEPROM */
void hal_eeprom_read(uint16_t addr, uint8_t *data, uint8_t len)
{
    eeprom_read_block(data, (const void *)(uintptr_t)addr, len);
}

void hal_eeprom_write(uint16_t addr, const uint8_t *data, uint8_t len)
{
    for (uint8_t i = 0; i < len; i++) {
        wdt_reset(); /* one byte takes 3.4 ms; the watchdog's first stage is 32 ms */
        eeprom_update_byte((uint8_t *)(uintptr_t)(addr + i), data[i]);
    }
    eeprom_busy_wait();
    wdt_reset();
}

/* ------------------------------------------------------------------ watchdog */
void hal_watchdog_feed(void) { wdt_reset(); }

void hal_avr_watchdog_enable(void)
{
    /* interrupt + reset mode, 32 ms per stage (WDP = 001); timed sequence as in avr-libc */
    uint8_t on = _BV(WDCE) | _BV(WDE);
    uint8_t mode = _BV(WDIE) | _BV(WDE) | _BV(WDP0);
    __asm__ __volatile__("in __tmp_reg__, __SREG__\n\t"
                         "cli\n\t"
                         "wdr\n\t"
                         "sts %0, %1\n\t"
                         "sts %0, %2\n\t"
                         "out __SREG__, __tmp_reg__\n\t"
                         :
                         : "n"(_SFR_MEM_ADDR(WDTCSR)), "r"(on), "r"(mode)
                         : "r0");
}

/* ------------------------------------------------------------------ hardware cut (D4-D7) */
/* D7 feeds the external watchdog (a charge pump: each edge counts), D4 LOW clears the latch U8,
 * D5 reads U10's EN, D6 the latch. PORTD is written from the main loop only. */
#define CUT_FEED PD7
#define CUT_CLEAR PD4
#define CUT_EN PD5
#define CUT_TRIP PD6

uint8_t hal_cut_read(void)
{
    uint8_t pins = PIND;
    return (uint8_t)(((pins & _BV(CUT_EN)) ? HAL_CUT_CLOSED : 0u) |
                     ((pins & _BV(CUT_TRIP)) ? HAL_CUT_TRIPPED : 0u));
}

void hal_cut_clear(void)
{
    PORTD &= (uint8_t)~_BV(CUT_CLEAR);
    _delay_us(2); /* 74LVC1G74 /CLR pulse width: ns; the pull-up and wiring: 2 us */
    PORTD |= _BV(CUT_CLEAR);
    _delay_us(1); /* the latch and the NOR settle before the caller reads D5/D6 back */
}

void hal_cut_feed(void) { PORTD ^= _BV(CUT_FEED); }

static void cut_init(void)
{
    PORTD |= _BV(CUT_CLEAR);                     /* D4 high: no clear */
    PORTD &= (uint8_t)~_BV(CUT_FEED);
    DDRD |= _BV(CUT_CLEAR) | _BV(CUT_FEED);
    DDRD &= (uint8_t)~(_BV(CUT_EN) | _BV(CUT_TRIP)); /* readbacks: driven by the logic, no pull-up */
    PORTD &= (uint8_t)~(_BV(CUT_EN) | _BV(CUT_TRIP));
}

/* ------------------------------------------------------------------ init */
void hal_avr_init(void)
{
    pwm_init(); /* first: the output pin is driven low and the driver disabled at once */
    estop_init();
    cut_init();
    uart_init();
    tick_init();
    adc_init();
    twi_init();
    spi_init();
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
    TIFR1 = _BV(TOV1);
    TIMSK1 = _BV(TOIE1); /* synchronous ADC starts from here on */
}
