"""``smabench firmware flash``: put the current-driver firmware on an Arduino Nano (ATmega328P)
through its bootloader with avrdude, then identify the new firmware over the protocol.

The board's bootloader decides the baud rate: optiboot (Nano "ATmega328P", Uno) talks at 115200,
the old Nano bootloader (ATmegaBOOT, "ATmega328P (Old Bootloader)") at 57600; both are tried in
that order, each first with one STK500 GET_SYNC probe of about a second (a wrong baud rate costs
avrdude its fixed 5 s serial timeout per try). avrdude opens the port, which resets the board
through DTR into the bootloader; it writes and verifies the flash page by page (STK500v1,
``-c arduino``) and leaves, and the bootloader starts the new application. Opening the port again
for the handshake resets the board once more; the driver's handshake waits for the bootloader to
hand over (``CurrentSource``).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from smabench.argtypes import port_syntax

if TYPE_CHECKING:
    from smabench.drivers.protocol import DeviceInfo

log = logging.getLogger(__name__)

FIRMWARE_DIR = Path(__file__).resolve().parents[1] / "firmware"  # present in a checkout only
DEFAULT_HEX = FIRMWARE_DIR / "build" / "avr" / "smabench-cd.hex"
AVRDUDE_PART = "m328p"
AVRDUDE_PROGRAMMER = "arduino"  # STK500v1 as the Arduino bootloaders speak it
BOOTLOADERS = ((115200, "optiboot"), (57600, "old Nano bootloader"))
AVRDUDE_TIMEOUT_S = 60.0  # a full 30 KB flash with verify takes about 10 s at 57600 baud
# avrdude run once more when it gives no result in AVRDUDE_TIMEOUT_S: on the emulated Nano under
# load it was seen to hang right after "AVR device initialized" (1 run in 5 beside four CPU
# burners, with and without the probe); writing the whole image again is what a user would do
AVRDUDE_RUNS = 2
# avrdude tries to sync 10 times by default. Each try resets the board, sends GET_SYNC three
# times and then waits avrdude's fixed 5 s serial timeout when the bootloader stays silent (or
# garbles at another baud rate): measured 6.4 s per failed try with avrdude 7.1 (-vvvv), which
# has no option for that timeout with -c arduino. One try before the next baud rate (a board
# that answers does so within its bootloader's ~1 s window after the reset), 3 on the last
SYNC_ATTEMPTS, SYNC_ATTEMPTS_LAST = 1, 3
# Before avrdude, each baud rate is probed: open the port (the board resets into its bootloader),
# send STK500 GET_SYNC every PROBE_PERIOD_S and wait for INSYNC OK, PROBE_S at most (both
# bootloaders wait about 1 s after a reset; in the emulator optiboot answered after 0.66 s, the
# old Nano bootloader after 0.3 s). avrdude then runs only at the baud rate that answered; when
# none does (or the port is no serial port), every baud rate goes to avrdude as before.
STK_GET_SYNC, STK_INSYNC_OK = b"\x30\x20", b"\x14\x10"
PROBE_S, PROBE_PERIOD_S = 1.2, 0.2
EXIT_USAGE = 2
EXIT_FAILED = 1


class FlashError(Exception):
    """Flashing or identifying failed; ``code`` is the exit code (2: bad input or setup)."""

    def __init__(self, message: str, code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.code = code


def find_avrdude() -> str:
    """Path of avrdude, or FlashError naming the Debian package."""
    path = shutil.which("avrdude")
    if path is None:
        raise FlashError("avrdude not found: apt-get install avrdude", EXIT_USAGE)
    return path


def build_hex() -> Path:
    """``make -C firmware hex`` in a checkout (make rebuilds only what changed); the hex path."""
    if not (FIRMWARE_DIR / "Makefile").is_file():
        raise FlashError(
            "no firmware sources in this installation: in a smabench checkout run "
            "`make -C firmware hex`, then pass --hex firmware/build/avr/smabench-cd.hex",
            EXIT_USAGE,
        )
    if shutil.which("make") is None:
        raise FlashError("make not found: apt-get install make gcc-avr avr-libc", EXIT_USAGE)
    proc = subprocess.run(
        ["make", "-C", str(FIRMWARE_DIR), "hex"], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0 or not DEFAULT_HEX.is_file():
        lines = proc.stderr.strip().splitlines() or ["(no output)"]
        last = next((ln for ln in lines if "error" in ln.lower()), lines[-1]).strip()
        raise FlashError(
            f"`make -C firmware hex` failed ({last}): run it to see why "
            "(it needs gcc-avr avr-libc binutils-avr)",
            EXIT_USAGE,
        )
    return DEFAULT_HEX


def hex_size_bytes(path: Path) -> int:
    """Data bytes in an Intel hex file; FlashError when it is not one."""
    total = 0
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise FlashError(f"cannot read {path}: {exc}", EXIT_USAGE) from exc
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line:
            continue
        if not re.fullmatch(r":[0-9A-Fa-f]{10,}", line):
            raise FlashError(f"{path}:{number}: not an Intel hex record", EXIT_USAGE)
        if line[7:9] == "00":
            total += int(line[1:3], 16)
    if total == 0:
        raise FlashError(f"{path}: no data records (not a firmware image)", EXIT_USAGE)
    return total


def avrdude_command(
    avrdude: str, port: str, baud: int, hex_path: Path, attempts: int = SYNC_ATTEMPTS_LAST
) -> list[str]:
    """The avrdude call for the Arduino bootloader (``-D``: the bootloader erases page by page;
    ``attempts``: tries to get in sync)."""
    return [
        avrdude, "-p", AVRDUDE_PART, "-c", AVRDUDE_PROGRAMMER, "-P", port, "-b", str(baud),
        "-x", f"attempts={attempts}", "-D", "-U", f"flash:w:{hex_path}:i",
    ]  # fmt: skip


def _avrdude_reason(output: str) -> str:
    """The line of avrdude's output that says why it failed."""
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if "error" in ln.lower() or "not in sync" in ln or "not respond" in ln:
            return ln
    return lines[-1] if lines else "no output"


def bootloader_answers(port: str, baud: int, window_s: float = PROBE_S) -> bool | None:
    """Whether a bootloader answers STK500 GET_SYNC at ``baud`` within ``window_s`` of opening
    the port (which resets the board into it); None when the port cannot be opened as a serial
    port (then nothing is known)."""
    import serial

    try:
        ser = serial.Serial(port, baud, timeout=PROBE_PERIOD_S)
    except (serial.SerialException, OSError, ValueError) as exc:
        log.info("cannot probe %s at %d baud: %s", port, baud, exc)
        return None
    got = b""
    try:
        deadline = time.monotonic() + window_s
        while time.monotonic() < deadline:
            ser.write(STK_GET_SYNC)
            got += ser.read(len(STK_INSYNC_OK))  # returns after PROBE_PERIOD_S at most
            if STK_INSYNC_OK in got:
                return True
    except (serial.SerialException, OSError) as exc:
        log.info("probe of %s at %d baud failed: %s", port, baud, exc)
        return None
    finally:
        ser.close()
    log.info("no bootloader at %d baud within %.1f s (%d bytes back)", baud, window_s, len(got))
    return False


def flash(port: str, hex_path: Path, bauds: tuple[tuple[int, str], ...] = BOOTLOADERS) -> int:
    """Write and verify ``hex_path`` through the bootloader; returns the baud rate that worked."""
    avrdude = find_avrdude()
    reasons = []
    if len(bauds) > 1:  # probe: avrdude then skips the baud rates that cannot be right
        for baud, name in bauds:
            answered = bootloader_answers(port, baud)
            if answered is None:
                break
            if answered:
                bauds = ((baud, name),)
                break
            print(f"  {baud} baud ({name}): no answer to GET_SYNC within {PROBE_S:g} s",
                  flush=True)  # fmt: skip
    for k, (baud, name) in enumerate(bauds):
        last = k == len(bauds) - 1
        attempts = SYNC_ATTEMPTS_LAST if last else SYNC_ATTEMPTS
        cmd = avrdude_command(avrdude, port, baud, hex_path, attempts)
        log.info("%s", " ".join(cmd))
        print(f"  {baud} baud ({name}) …", flush=True)
        proc = None
        for run in range(AVRDUDE_RUNS):
            try:
                proc = subprocess.run(
                    cmd, capture_output=True, text=True, timeout=AVRDUDE_TIMEOUT_S, check=False
                )
                break
            except subprocess.TimeoutExpired:
                again = run + 1 < AVRDUDE_RUNS
                print(f"  avrdude gave no result in {AVRDUDE_TIMEOUT_S:g} s"
                      + ("; running it again" if again else ""), flush=True)  # fmt: skip
        if proc is None:
            reasons.append(f"{baud} baud: avrdude gave no result in {AVRDUDE_TIMEOUT_S:g} s "
                           f"({AVRDUDE_RUNS} runs)")  # fmt: skip
            continue
        if proc.returncode == 0:
            verified = re.search(r"(\d+) bytes of flash verified", proc.stderr)
            if verified is None:
                raise FlashError(f"avrdude reported success but no verify: {proc.stderr[-200:]}")
            return baud
        if "device initialized" in proc.stderr:  # the bootloader answered: no other baud rate
            raise FlashError(f"avrdude at {baud} baud ({name}): {_avrdude_reason(proc.stderr)}")
        reasons.append(f"{baud} baud: {_avrdude_reason(proc.stderr)}")
    raise FlashError(
        "no bootloader answered on " + port + " (" + "; ".join(reasons) + "): check the port, "
        "that the board is an ATmega328P Nano/Uno and that nothing else has the port open"
    )


def identify(port: str) -> DeviceInfo:
    """Open the port (the board resets), do the handshake; returns the DeviceInfo."""
    from smabench.drivers.current_source import CurrentSource, CurrentSourceError

    source = CurrentSource(port)
    try:
        return source.connect()
    except (CurrentSourceError, OSError) as exc:
        raise FlashError(f"flashed, but the new firmware does not answer on {port}: {exc}") from exc
    finally:
        source.close()


def cmd_flash(args: argparse.Namespace) -> int:
    try:
        if not os.path.exists(args.port):
            raise FlashError(f"no such port: {args.port}", EXIT_USAGE)
        find_avrdude()
        if args.hex:
            hex_path = Path(args.hex)
            if not hex_path.is_file():
                raise FlashError(f"no such file: {hex_path}", EXIT_USAGE)
        else:
            hex_path = build_hex()
        size = hex_size_bytes(hex_path)
        print(f"flashing {hex_path} ({size} B) on {args.port} through the Arduino bootloader")
        bauds = tuple(b for b in BOOTLOADERS if args.baud in (None, b[0]))
        baud = flash(args.port, hex_path, bauds)
        print(f"written and verified at {baud} baud; identifying …", flush=True)
        info = identify(args.port)
    except FlashError as exc:
        print(f"smabench firmware flash: {exc}", file=sys.stderr)
        return exc.code
    major, minor, patch = info.firmware_version
    print(
        f"firmware: {info.name} {major}.{minor}.{patch} (protocol {info.protocol_version}, "
        f"hard current limit {info.hard_limit_a:g} A)"
    )
    return 0


def add_commands(sub) -> None:
    """Register ``firmware flash`` on the CLI's subparsers."""
    s = sub.add_parser("firmware", help="the current driver's firmware on an Arduino Nano")
    fsub = s.add_subparsers(dest="firmware_command", required=True, metavar="WHAT")
    f = fsub.add_parser(
        "flash",
        help="flash through the Arduino bootloader with avrdude, then identify the firmware",
    )
    f.add_argument("--port", type=port_syntax, required=True, metavar="DEV",
                   help="the Nano's serial port, e.g. /dev/ttyUSB0")
    f.add_argument(
        "--hex",
        help="Intel hex image (default: build firmware/build/avr/smabench-cd.hex with make)",
    )
    f.add_argument(
        "--baud",
        type=int,
        choices=[b for b, _ in BOOTLOADERS],
        help="only this bootloader baud rate (default: 115200 optiboot, then 57600 old Nano)",
    )
    f.set_defaults(func=cmd_flash)
