/* The Arduino's bootloader and auto-reset for the simavr harness: see boot.h and
 * firmware/sim/README.md ("Bootloader and auto-reset"). */
#define _GNU_SOURCE
#include "boot.h"

#include <errno.h>
#include <poll.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/inotify.h>
#include <termios.h>
#include <unistd.h>

#include "avr_watchdog.h"
#include "sim_elf.h"

#define BOOT_F_CPU 16000000u
#define A_MCUSR 0x54    /* ATmega328P data-space address */
#define BIT_EXTRF 0x02  /* MCUSR: external (reset pin) reset */
#define A_WDTCSR 0x60
#define A_SPL 0x5D
#define A_SPH 0x5E
#define A_UCSR0A 0xC0
#define BIT_U2X0 0x02
#define A_UBRR0L 0xC4
#define A_UBRR0H 0xC5
#define BAUD_TOLERANCE 0.05 /* a UART frame survives a few per cent of mismatch */
#define WDT_WDP 0x27    /* WDP3 (bit 5), WDP2..0 */
#define WDT_ON 0x48     /* WDIE | WDE */

static const char *boot_hex;  /* --bootloader HEX */
static int blank;             /* --blank */
static uint32_t boot_base;    /* first address of the bootloader image, bytes */
static int port_was_open;
static int port_watch = -1; /* inotify on the slave device: every open and close, in order */
static long port_handles;   /* open handles on the slave, as counted from the inotify events */
static unsigned long port_opens;
static int reset_pending;
static void (*plain_run)(avr_t *); /* avr->run when nothing (watchdog, us) has swapped it */
static unsigned long host_baud;    /* what the client set on the port (the slave's termios) */
static unsigned polls;

static void refresh_host_baud(int pty_master);

static void boot_die(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    fputs("smabench-sim: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(2);
}

int boot_option(int argc, char **argv, int i)
{
    if (!strcmp(argv[i], "--bootloader") && i + 1 < argc) {
        boot_hex = argv[i + 1];
        return 2;
    }
    if (!strcmp(argv[i], "--blank")) {
        blank = 1;
        return 1;
    }
    return 0;
}

int boot_enabled(void) { return boot_hex != NULL; }

int boot_args_ok(const char *app)
{
    if (blank && !boot_hex)
        return 0;
    return blank ? app == NULL : app != NULL;
}

static int ends_with(const char *s, const char *tail)
{
    size_t n = strlen(s), m = strlen(tail);
    return n >= m && !strcasecmp(s + n - m, tail);
}

static int hex_byte(const char *s, unsigned *out)
{
    unsigned v = 0;
    for (int k = 0; k < 2; k++) {
        char c = s[k];
        v <<= 4;
        if (c >= '0' && c <= '9')
            v |= (unsigned)(c - '0');
        else if (c >= 'A' && c <= 'F')
            v |= (unsigned)(c - 'A' + 10);
        else if (c >= 'a' && c <= 'f')
            v |= (unsigned)(c - 'a' + 10);
        else
            return -1;
    }
    *out = v;
    return 0;
}

/* Copy an Intel hex image into flash; returns [lowest address, end) of what it wrote. Our own
 * reader: simavr 1.6's read_ihex_chunks rejects record type 03 (start segment address), which
 * Debian's optiboot_atmega328.hex ends with. Records 00 data, 01 end, 02/04 extended address;
 * 03/05 (start addresses) are ignored; every checksum is checked. */
static void load_hex(avr_t *avr, const char *path, uint32_t *lo, uint32_t *hi)
{
    FILE *f = fopen(path, "r");
    if (!f)
        boot_die("cannot open %s: %s", path, strerror(errno));
    char line[600];
    uint32_t base = 0;
    unsigned lineno = 0, bytes = 0;
    int done = 0;
    *lo = UINT32_MAX;
    *hi = 0;
    while (!done && fgets(line, sizeof line, f)) {
        lineno++;
        size_t len = strcspn(line, "\r\n");
        if (len == 0)
            continue;
        unsigned n, ah, al, type, b, sum = 0;
        if (line[0] != ':' || len < 11 || hex_byte(line + 1, &n) || len != 11 + 2 * n ||
            hex_byte(line + 3, &ah) || hex_byte(line + 5, &al) || hex_byte(line + 7, &type))
            boot_die("%s:%u: not an Intel hex record", path, lineno);
        uint8_t data[256];
        sum = n + ah + al + type;
        for (unsigned k = 0; k <= n; k++) {
            if (hex_byte(line + 9 + 2 * k, &b))
                boot_die("%s:%u: not an Intel hex record", path, lineno);
            sum += b;
            if (k < n)
                data[k] = (uint8_t)b;
        }
        if (sum & 0xff)
            boot_die("%s:%u: checksum error", path, lineno);
        uint32_t a = base + (ah << 8 | al);
        switch (type) {
        case 0:
            if ((uint64_t)a + n > (uint64_t)avr->flashend + 1)
                boot_die("%s:%u: data at 0x%05x is beyond the end of the flash (0x%05x): no chip "
                         "can hold this image", path, lineno, a + n - 1, avr->flashend + 1);
            memcpy(avr->flash + a, data, n);
            bytes += n;
            if (n && a < *lo)
                *lo = a;
            if (a + n > *hi)
                *hi = a + n;
            break;
        case 1:
            done = 1;
            break;
        case 2:
        case 4:
            if (n != 2)
                boot_die("%s:%u: bad extended address record", path, lineno);
            base = (uint32_t)(data[0] << 8 | data[1]) << (type == 2 ? 4 : 16);
            break;
        default: /* 03, 05: start address, meaningless for flash */
            break;
        }
    }
    fclose(f);
    if (!done || !bytes)
        boot_die("%s: %s", path, bytes ? "no end-of-file record" : "no data");
}

/* simavr 1.6 reads the old prescaler after storing the new one, so a timeout changed while the
 * watchdog runs takes effect only after the next WDR; optiboot shortens it to 16 ms to start the
 * application (after avrdude's last command, or on a byte that is no STK500 command) and then
 * waits for it without WDR, so the application would start 1 s late. Re-arm on a change, as a WDR
 * does (on the chip the counter runs on, so this is at most the chip's timeout). */
static avr_io_write_t wdt_write_simavr;
static void *wdt_write_param;

static void wdt_write(avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    uint8_t before = avr->data[A_WDTCSR];
    wdt_write_simavr(avr, addr, v, param);
    uint8_t after = avr->data[A_WDTCSR];
    if ((after & WDT_ON) && ((before ^ after) & WDT_WDP))
        avr_ioctl(avr, AVR_IOCTL_WATCHDOG_RESET, NULL);
}

static void wdt_fix(avr_t *avr)
{
    int io = AVR_DATA_TO_IO(A_WDTCSR);
    if (!avr->io[io].w.c)
        return;
    wdt_write_simavr = avr->io[io].w.c;
    wdt_write_param = avr->io[io].w.param;
    avr->io[io].w.c = wdt_write;
    avr->io[io].w.param = wdt_write_param;
}

void boot_setup(avr_t *avr, const char *app)
{
    uint32_t app_end = 0, lo, hi;
    if (app && ends_with(app, ".hex")) {
        load_hex(avr, app, &lo, &app_end);
    } else if (app) {
        elf_firmware_t fw;
        memset(&fw, 0, sizeof fw);
        if (elf_read_firmware(app, &fw) != 0)
            boot_die("cannot read %s", app);
        fw.frequency = BOOT_F_CPU;
        avr_load_firmware(avr, &fw);
        app_end = fw.flashbase + fw.flashsize;
    }
    load_hex(avr, boot_hex, &lo, &hi);
    if (app_end > lo)
        boot_die("the application (%u B) runs into the bootloader at 0x%04x", app_end, lo);
    boot_base = lo;
    wdt_fix(avr);
    /* BOOTRST: the reset vector is the start of the boot section */
    avr->reset_pc = avr->pc = boot_base;
    avr->codeend = avr->flashend;
    fprintf(stderr, "smabench-sim: bootloader %s at 0x%04x..0x%04x, application %s (%u B)\n",
            boot_hex, lo, hi, app ? app : "blank", app_end);
}

void boot_port_init(avr_t *avr, int *pty_slave)
{
    /* the termios set on the slave (raw, 115200) stay with the pty after the close */
    const char *name = *pty_slave >= 0 ? ttyname(*pty_slave) : NULL;
    char path[256] = "";
    if (name)
        snprintf(path, sizeof path, "%s", name);
    if (*pty_slave >= 0)
        close(*pty_slave);
    *pty_slave = -1;
    plain_run = avr->run;
    /* A client that closes and reopens the port within one poll of POLLHUP would go unseen;
     * inotify queues every open and close of the device node, however close together. */
    port_watch = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
    if (port_watch >= 0 &&
        (!path[0] || inotify_add_watch(port_watch, path, IN_OPEN | IN_CLOSE) < 0)) {
        close(port_watch);
        port_watch = -1;
    }
    if (port_watch < 0)
        fprintf(stderr, "smabench-sim: no inotify on %s: opens are seen by polling only\n", path);
}

/* Count opens and closes from the inotify queue; returns 1 if the handle count went from 0 up at
 * least once (a DTR rising edge: the board resets), even if it is back at 0 by now. */
static int port_watch_opened(void)
{
    char buf[4096] __attribute__((aligned(__alignof__(struct inotify_event))));
    int rising = 0;
    ssize_t n;
    while ((n = read(port_watch, buf, sizeof buf)) > 0) {
        for (char *q = buf; q < buf + n;) {
            const struct inotify_event *ev = (const struct inotify_event *)q;
            if (ev->mask & IN_OPEN) {
                if (port_handles++ == 0)
                    rising = 1;
            } else if ((ev->mask & IN_CLOSE) && port_handles > 0) {
                port_handles--;
            }
            q += sizeof *ev + ev->len;
        }
    }
    return rising;
}

/* One-shot avr->run: the external reset happens inside avr_run, as the watchdog's does, so the
 * harness accounts for it the same way (cycle counter restarted, reset hook called). */
static void run_external_reset(avr_t *avr)
{
    avr->run = plain_run;
    avr_reset(avr);
    avr->data[A_MCUSR] |= BIT_EXTRF;
}

static void request_reset(avr_t *avr)
{
    if (avr->run == plain_run) { /* not while simavr's watchdog reset is under way */
        avr->run = run_external_reset;
        reset_pending = 0;
    } else if (avr->run != run_external_reset) {
        reset_pending = 1;
    }
}

/* An erased application section (0xFFFF words) is run through like NOPs into the bootloader,
 * which optiboot then leaves again at once (no EXTRF) with an RCALL that pushes two bytes: on a
 * blank chip the stack walks down by 2 bytes per pass, into the I/O registers after about 1000
 * passes (1 s). What the chip does then is undefined; simavr stops on the write below address
 * 0. Every pass through erased flash starts with a fresh stack here, so a blank Nano keeps
 * cycling through its bootloader (as it visibly does: the LED keeps flashing) until it is
 * flashed. */
static void blank_slide_keeps_stack(avr_t *avr)
{
    avr_flashaddr_t pc = avr->pc;
    if (pc + 1 < boot_base && avr->flash[pc] == 0xff && avr->flash[pc + 1] == 0xff) {
        avr->data[A_SPL] = (uint8_t)(avr->ramend & 0xff);
        avr->data[A_SPH] = (uint8_t)(avr->ramend >> 8);
    }
}

enum boot_port_state boot_port_poll(avr_t *avr, int pty_master)
{
    blank_slide_keeps_stack(avr);
    struct pollfd pfd = {.fd = pty_master, .events = 0};
    if (reset_pending)
        request_reset(avr);
    if (++polls % 100 == 0)
        refresh_host_baud(pty_master);
    if (poll(&pfd, 1, 0) < 0)
        return port_was_open ? BOOT_PORT_OPEN : BOOT_PORT_CLOSED;
    int open = !(pfd.revents & POLLHUP);
    int rising = port_watch >= 0 ? port_watch_opened() : open && !port_was_open;
    port_was_open = open;
    if (!rising)
        return open ? BOOT_PORT_OPEN : BOOT_PORT_CLOSED;
    /* the DTR pulse: what the client wrote before the reset never reaches the bootloader */
    uint8_t junk[256];
    while (read(pty_master, junk, sizeof junk) > 0)
        ;
    port_opens++;
    refresh_host_baud(pty_master);
    fprintf(stderr, "smabench-sim: port opened (%lu): external reset into the bootloader\n",
            port_opens);
    request_reset(avr);
    return BOOT_PORT_OPENED;
}

/* ------------------------------------------------------------------ baud rate of the line */
static unsigned long speed_baud(speed_t s)
{
    static const struct { speed_t s; unsigned long baud; } table[] = {
        {B1200, 1200},     {B2400, 2400},     {B4800, 4800},     {B9600, 9600},
        {B19200, 19200},   {B38400, 38400},   {B57600, 57600},   {B115200, 115200},
        {B230400, 230400}, {B460800, 460800}, {B500000, 500000}, {B1000000, 1000000},
    };
    for (size_t k = 0; k < sizeof table / sizeof table[0]; k++)
        if (table[k].s == s)
            return table[k].baud;
    return 0; /* B0 or unknown: not checked */
}

/* On a pty master, tcgetattr reads the slave's termios: the speed the client asked for. */
static void refresh_host_baud(int pty_master)
{
    struct termios t;
    host_baud = tcgetattr(pty_master, &t) == 0 ? speed_baud(cfgetospeed(&t)) : 0;
}

static unsigned long avr_baud(avr_t *avr)
{
    const uint8_t *d = avr->data;
    unsigned ubrr = d[A_UBRR0L] | ((unsigned)(d[A_UBRR0H] & 0x0f) << 8);
    return BOOT_F_CPU / ((d[A_UCSR0A] & BIT_U2X0 ? 8ul : 16ul) * (ubrr + 1));
}

static int baud_mismatch(avr_t *avr)
{
    unsigned long avr_b = avr_baud(avr);
    if (!host_baud || !avr_b)
        return 0;
    double ratio = (double)host_baud / (double)avr_b;
    return ratio < 1.0 - BAUD_TOLERANCE || ratio > 1.0 + BAUD_TOLERANCE;
}

int boot_line_rx(avr_t *avr, int pty_master, uint8_t *buf, size_t n)
{
    refresh_host_baud(pty_master);
    if (!baud_mismatch(avr))
        return 0;
    for (size_t k = 0; k < n; k++)
        buf[k] = (uint8_t)~buf[k];
    return 1;
}

uint8_t boot_line_tx(avr_t *avr, uint8_t byte)
{
    return baud_mismatch(avr) ? (uint8_t)~byte : byte;
}
