/* Peripherals of the reference current driver for the simavr harness (periph.h).
 *
 * ADS1115 (TI SBAS444) at 0x48 on TWI: writes set the pointer register and, for the config
 * register (pointer 1), start a single-shot conversion of AIN0-AIN1 (wire, through the 1:2
 * Kelvin dividers) or AIN2-AIN3 (shunt) at the full-scale range the config's PGA bits select;
 * reads return the register the pointer selects, MSB first. The conversion uses the electrical
 * model's state when the config is written.
 * MAX31855 (Maxim) on SPI, chip select D10 (PB2): while CS is low, each byte the AVR clocks out
 * returns the next byte of the 32-bit word D31..D0: 14-bit thermocouple temperature (0.25 degC),
 * D16 fault, 12-bit cold junction (0.0625 degC, 25 degC here), D2 SCV, D1 SCG, D0 OC. No chip:
 * MISO floats high (all ones).
 * E-stop on D2 (PD2): the NC contact holds it low; ESTOP 1 drives it high (tripped).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "avr_ioport.h"
#include "avr_spi.h"
#include "avr_twi.h"
#include "electrical.h"
#include "cut.h"
#include "periph.h"
#include "sim_irq.h"

static avr_t *avr;
static double wire_a, wire_v;

/* ------------------------------------------------------------------ ADS1115 */
#define ADS_SLA (ELEC_ADS1115_ADDRESS << 1)
static avr_irq_t *twi_in;
static int ads_present = 1;
static uint8_t ads_selected, ads_index, ads_pointer;
static uint8_t ads_wbuf[3];
static uint16_t ads_config = 0x8583u, ads_conversion;
/* the wire channel's noise, V RMS at the wire (VNOISE), one Gaussian draw per conversion from a
 * seeded generator (the runs repeat) */
static double ads_noise_v;
static uint64_t ads_rng = 0x9E3779B97F4A7C15ull;

static double ads_uniform(void) /* (0, 1): splitmix64 */
{
    uint64_t z = (ads_rng += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return ((double)(z >> 11) + 0.5) / 9007199254740992.0;
}

static double ads_gauss(void) /* Box-Muller */
{
    return sqrt(-2.0 * log(ads_uniform())) * cos(6.283185307179586 * ads_uniform());
}

static double ads_fsr_v(uint16_t cfg)
{
    static const double fsr[8] = {6.144, 4.096, 2.048, 1.024, 0.512, 0.256, 0.256, 0.256};
    return fsr[(cfg >> 9) & 7u];
}

static void ads_convert(void)
{
    unsigned mux = (ads_config >> 12) & 7u;
    double v = 0.0;
    if (mux == 0u) /* AIN0-AIN1: the wire through the two 1:2 dividers */
        v = (wire_v + (ads_noise_v > 0.0 ? ads_noise_v * ads_gauss() : 0.0)) * 0.5;
    else if (mux == 3u) /* AIN2-AIN3: the shunt */
        v = wire_a * ELEC_SHUNT_MOHM * 1e-3;
    double code = floor(v / ads_fsr_v(ads_config) * 32768.0 + 0.5);
    if (code > 32767.0)
        code = 32767.0;
    if (code < -32768.0)
        code = -32768.0;
    ads_conversion = (uint16_t)(int16_t)code;
}

static void twi_out_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    avr_twi_msg_irq_t m;
    m.u.v = value;
    if (m.u.twi.msg & TWI_COND_STOP) {
        if (ads_selected && !(ads_selected & 1u) && ads_index == 3u && ads_pointer == 1u) {
            ads_config = (uint16_t)((ads_wbuf[1] << 8) | ads_wbuf[2]);
            if (ads_config & 0x8000u)
                ads_convert(); /* OS = 1: a single conversion */
        }
        ads_selected = 0;
    }
    if (m.u.twi.msg & TWI_COND_START) {
        ads_selected = 0;
        ads_index = 0;
        if (ads_present && (m.u.twi.addr & 0xFEu) == ADS_SLA) {
            ads_selected = m.u.twi.addr;
            avr_raise_irq(twi_in, avr_twi_irq_msg(TWI_COND_ACK, ads_selected, 1));
        }
    }
    if (!ads_selected)
        return;
    if (m.u.twi.msg & TWI_COND_WRITE) {
        avr_raise_irq(twi_in, avr_twi_irq_msg(TWI_COND_ACK, ads_selected, 1));
        if (ads_index < 3u)
            ads_wbuf[ads_index] = m.u.twi.data;
        if (ads_index == 0u)
            ads_pointer = m.u.twi.data & 3u;
        ads_index++;
    }
    if (m.u.twi.msg & TWI_COND_READ) {
        uint16_t reg = ads_pointer == 1u ? ads_config : ads_conversion;
        uint8_t b = ads_index == 0u ? (uint8_t)(reg >> 8) : (uint8_t)reg;
        ads_index++;
        avr_raise_irq(twi_in, avr_twi_irq_msg(TWI_COND_READ, ads_selected, b));
    }
}

/* ------------------------------------------------------------------ MAX31855 */
static avr_irq_t *spi_in;
static int tc_present, tc_fault; /* tc_fault: TC_* bits */
static double tc_celsius = 22.0;
static int cs_low, spi_index;

static uint32_t tc_word(void)
{
    uint32_t internal = (uint32_t)(25 * 16) << 4; /* cold junction 25 degC */
    if (tc_fault)
        return 0x00010000u | internal | (uint32_t)(tc_fault & 7);
    long q = lround(tc_celsius * 4.0);
    if (q > 8191)
        q = 8191;
    if (q < -8192)
        q = -8192;
    return ((uint32_t)(q & 0x3FFF) << 18) | internal;
}

static void spi_out_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    uint8_t b = 0xFFu; /* MISO pulled up: no chip, or not selected */
    if (cs_low && tc_present) {
        uint32_t w = tc_word();
        b = spi_index < 4 ? (uint8_t)(w >> (8 * (3 - spi_index))) : 0u;
    }
    spi_index++;
    avr_raise_irq(spi_in, b);
}

static void cs_cb(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    int low = value ? 0 : 1;
    if (low && !cs_low)
        spi_index = 0; /* falling edge: a new read */
    cs_low = low;
}

/* ------------------------------------------------------------------ e-stop, NTC */
static int estop_tripped;

/* The contact drives D2 whatever the port's pull-up says: simavr's "external" pin state. */
static void estop_drive(void)
{
    cut_drive_pins(estop_tripped); /* port D's external state: D2 with the cut's D5/D6 */
}

int periph_estop(void) { return estop_tripped; }
static int ntc_fault; /* 0 ok, 1 open, 2 short */

double periph_ntc_mv(double model_mv)
{
    if (ntc_fault == 1)
        return 0.0; /* NTC open: the fixed resistor pulls ADC2 to ground */
    if (ntc_fault == 2)
        return 4998.0; /* NTC shorted: ADC2 at AVcc (code 1023; simavr wraps 5000 mV to 0) */
    return model_mv;
}

void periph_set_wire(double current_a, double wire_volts)
{
    wire_a = current_a;
    wire_v = wire_volts;
}

void periph_state(FILE *f)
{
    /* numbers only: tc 0 = no chip, 1 = ok, 2 = fault; ntc 0 = ok, 1 = open, 2 = short */
    fprintf(f, " estop=%d tc=%d tc_c=%.2f ads=%d ntc=%d", estop_tripped,
            !tc_present ? 0 : tc_fault ? 2 : 1, tc_celsius, ads_present, ntc_fault);
}

int periph_command(const char *cmd, const char *arg)
{
    char *end;
    if (!strcmp(cmd, "VNOISE")) { /* VNOISE <V RMS at the wire> [seed] */
        double v = arg ? strtod(arg, &end) : -1.0;
        if (!arg || *end || !isfinite(v) || v < 0.0 || v > 0.01) {
            fprintf(stderr, "smabench-sim: VNOISE takes 0 ... 0.01 V RMS\n");
            return 1;
        }
        ads_noise_v = v;
        return 1;
    }
    if (!strcmp(cmd, "ESTOP")) {
        if (!arg || (strcmp(arg, "0") && strcmp(arg, "1"))) {
            fprintf(stderr, "smabench-sim: ESTOP takes 0 or 1\n");
            return 1;
        }
        estop_tripped = arg[0] == '1';
        estop_drive();
        return 1;
    }
    if (!strcmp(cmd, "TC")) {
        if (!arg) {
            fprintf(stderr, "smabench-sim: TC takes <celsius>, NONE, OC, SCG or SCV\n");
        } else if (!strcmp(arg, "NONE")) {
            tc_present = 0;
        } else if (!strcmp(arg, "OC") || !strcmp(arg, "SCG") || !strcmp(arg, "SCV")) {
            tc_present = 1;
            tc_fault = arg[0] == 'O' ? 1 : arg[2] == 'G' ? 2 : 4;
        } else {
            double v = strtod(arg, &end);
            if (*end || !isfinite(v) || v < -270.0 || v > 1372.0) {
                fprintf(stderr, "smabench-sim: bad thermocouple temperature '%s'\n", arg);
                return 1;
            }
            tc_present = 1;
            tc_fault = 0;
            tc_celsius = v;
        }
        return 1;
    }
    if (!strcmp(cmd, "ADS")) {
        if (!arg || (strcmp(arg, "0") && strcmp(arg, "1")))
            fprintf(stderr, "smabench-sim: ADS takes 0 or 1\n");
        else
            ads_present = arg[0] == '1';
        return 1;
    }
    if (!strcmp(cmd, "NTC")) {
        if (arg && !strcmp(arg, "OK"))
            ntc_fault = 0;
        else if (arg && !strcmp(arg, "OPEN"))
            ntc_fault = 1;
        else if (arg && !strcmp(arg, "SHORT"))
            ntc_fault = 2;
        else
            fprintf(stderr, "smabench-sim: NTC takes OK, OPEN or SHORT\n");
        return 1;
    }
    return 0;
}

void periph_attach(avr_t *a)
{
    avr = a;
    twi_in = avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_INPUT);
    avr_irq_t *twi_out = avr_io_getirq(avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_OUTPUT);
    if (twi_in && twi_out)
        avr_irq_register_notify(twi_out, twi_out_cb, NULL);
    else
        fprintf(stderr, "smabench-sim: no TWI IRQs: no ADS1115\n");
    spi_in = avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_INPUT);
    avr_irq_t *spi_out = avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_OUTPUT);
    if (spi_in && spi_out)
        avr_irq_register_notify(spi_out, spi_out_cb, NULL);
    else
        fprintf(stderr, "smabench-sim: no SPI IRQs: no MAX31855\n");
    avr_irq_t *cs = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 2);
    if (cs)
        avr_irq_register_notify(cs, cs_cb, NULL);
    cs_low = 0;
    estop_drive(); /* the NC contact holds D2 low */
}
