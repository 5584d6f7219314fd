/* The current driver's peripherals besides the wire model, for the simavr harness (periph.c):
 * the ADS1115 on TWI (Kelvin wire voltage and shunt), the MAX31855 on SPI (thermocouple on the
 * wire), the e-stop input on D2, and NTC faults. harness.c calls these hooks. */
#ifndef SMA_SIM_PERIPH_H
#define SMA_SIM_PERIPH_H
#include <stdio.h>

#include "sim_avr.h"

/* Connect to the AVR's TWI, SPI and port IRQs; call once after avr_init. */
void periph_attach(avr_t *avr);
/* Control commands (stdin): ESTOP 0|1, TC <celsius>|NONE|OC|SCG|SCV, ADS 0|1,
 * NTC OK|OPEN|SHORT. Returns 1 when the command was ours (handled or refused with a message). */
int periph_command(const char *cmd, const char *arg);
/* The electrical model's present state: wire current (A) and Kelvin wire voltage (V). */
void periph_set_wire(double current_a, double wire_v);
/* The NTC divider voltage the model computed, overridden by an NTC fault. */
double periph_ntc_mv(double model_mv);
/* The e-stop input: 1 = tripped (drives D2 and the cut's comparator U7C). */
int periph_estop(void);
/* Extra STATE fields, numbers only: " estop=0 tc=1 tc_c=55.00 ads=1 ntc=0". */
void periph_state(FILE *f);
#endif
