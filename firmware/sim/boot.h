/* The Arduino's bootloader and auto-reset for the simavr harness (firmware/sim/README.md,
 * "Bootloader and auto-reset").
 *
 * With --bootloader HEX the harness loads a real bootloader image (Debian's optiboot, or the old
 * Nano's ATmegaBOOT) at the address its hex file gives, starts there as BOOTRST does, and puts
 * the application (ELF or Intel hex, or nothing with --blank) in the application section. The
 * harness then no longer holds the pty's slave open: every time a client opens the port, the MCU
 * is reset with EXTRF set, as the DTR pulse through the 100 nF capacitor does on a Nano.
 */
#ifndef SMABENCH_SIM_BOOT_H
#define SMABENCH_SIM_BOOT_H

#include <stddef.h>
#include <stdint.h>

#include "sim_avr.h"

/* Harness options --bootloader HEX and --blank. Returns how many argv entries starting at
 * argv[i] it consumed (0: not one of ours). */
int boot_option(int argc, char **argv, int i);

/* 1 when --bootloader was given. */
int boot_enabled(void);

/* The positional firmware argument is consistent with the options: required without --blank,
 * absent with it; --blank only with --bootloader. */
int boot_args_ok(const char *app);

/* After avr_init: load the application (ELF or .hex; NULL with --blank) and the bootloader, and
 * reset into the bootloader. Exits with code 2 and one line on stderr on a bad image. */
void boot_setup(avr_t *avr, const char *app);

/* Take over the pty for the auto-reset: closes the harness's own slave fd (*pty_slave = -1), so
 * the master reports POLLHUP whenever no client has the port open, and watches the slave device
 * with inotify, so a close and reopen between two polls still counts as a new open. */
void boot_port_init(avr_t *avr, int *pty_slave);

enum boot_port_state {
    BOOT_PORT_OPEN = 0,   /* a client has the port open */
    BOOT_PORT_CLOSED = 1, /* nobody has it open: bytes from the AVR are lost, as on a closed port */
    BOOT_PORT_OPENED = 2, /* a client has just opened it: the MCU resets into the bootloader, and
                           * what the client sent before the reset is gone */
};

/* Once per slice, between avr_run calls: watch the port (a poll for POLLHUP on the master). */
enum boot_port_state boot_port_poll(avr_t *avr, int pty_master);

/* The line's baud rate: the speed the client set on the port (the slave's termios, read on the
 * master) against UART0's (UBRR0, U2X0). Off by more than 5 %, every byte arrives corrupted (its
 * complement), as on a real line at the wrong speed; so avrdude at 115200 cannot talk to the old
 * 57600 bootloader. boot_line_rx: bytes from the pty (in place; 1 if corrupted); boot_line_tx: one
 * byte from UART0. */
int boot_line_rx(avr_t *avr, int pty_master, uint8_t *buf, size_t n);
uint8_t boot_line_tx(avr_t *avr, uint8_t byte);

#endif
