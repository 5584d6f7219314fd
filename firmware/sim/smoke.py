#!/usr/bin/env python3
"""Smoke test of the AVR firmware in the simavr harness (make -C firmware sim-test).

Starts smabench-sim on the .elf, opens the pty it prints, sends IDENTIFY and checks the ACK
(status OK, protocol 4, device name), checks the control channel (Q, R), measures frame round
trips through the pty, and runs every safety path from the device side: a current step into
0.3 and 1 Ohm at the ends of the supply range, the setpoint lease expiring while PINGs go on,
the probe current held at setpoint 0 past the lease and off with ENABLE 0, the e-stop input, the energy budget tripping under 2.5 A demanded for ever (a shortened budget),
the NTC open and shorted, the thermocouple and its faults, and calibration in EEPROM.
Python 3 standard library only; COBS and CRC-16/CCITT-FALSE are implemented here so the test
does not depend on drivers/protocol.py.

usage: smoke.py SIM_BINARY FIRMWARE_ELF [--rounds N] [--wdt-elf ELF]
"""
from __future__ import annotations

import argparse
import contextlib
import os
import select
import statistics
import struct
import subprocess
import sys
import termios
import time
import tty

IDENTIFY, ENABLE, SET_CURRENT, SET_LIMITS, SET_TELEMETRY, CLEAR_FAULTS, PING = range(1, 8)
SET_LEASE, SET_CALIBRATION, GET_CALIBRATION, SET_HEAT_MODEL, GET_HEAT_MODEL = range(8, 13)
SET_PROBE = 0x0D  # protocol 4
ACK, TELEMETRY = 0x80, 0x90
PROTOCOL_VERSION = 4
FLAG_ENABLED, FLAG_WATCHDOG_RESET, FLAG_LEASE_EXPIRED = 1 << 0, 1 << 4, 1 << 6
FLAG_OVERTEMP, FLAG_ESTOP, FLAG_NTC_FAULT, FLAG_TC_FAULT = 1 << 7, 1 << 8, 1 << 9, 1 << 10
ST_OK, ST_OUT_OF_RANGE, ST_FAULT_ACTIVE = 0, 3, 4
TEMP_NONE = 0x7FFF
TELEMETRY_FMT = "<IHHHhHHHHhhHHB"  # PROTOCOL.md, TELEMETRY: 29 bytes


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def cobs_encode(data: bytes) -> bytes:
    out = bytearray([0])
    code_at, code = 0, 1
    for b in data:
        if b == 0:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
        else:
            out.append(b)
            code += 1
            if code == 0xFF:
                out[code_at] = code
                code_at, code = len(out), 1
                out.append(0)
    out[code_at] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(data):
        code = data[i]
        if code == 0 or i + code > len(data):
            raise ValueError("bad COBS")
        out += data[i + 1:i + code]
        i += code
        if code != 0xFF and i < len(data):
            out.append(0)
    return bytes(out)


def encode_frame(seq: int, type_: int, payload: bytes = b"") -> bytes:
    body = bytes([seq & 0xFF, type_]) + payload
    return cobs_encode(body + struct.pack("<H", crc16(body))) + b"\x00"


def decode_packet(frame: bytes) -> tuple[int, int, bytes]:
    raw = cobs_decode(frame)
    if len(raw) < 4 or len(raw) > 64:
        raise ValueError(f"bad length {len(raw)}")
    body, crc = raw[:-2], struct.unpack("<H", raw[-2:])[0]
    if crc16(body) != crc:
        raise ValueError("CRC mismatch")
    return body[0], body[1], body[2:]


class Link:
    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)
        termios.tcflush(self.fd, termios.TCIOFLUSH)
        self.buf = bytearray()
        self.seq = 0

    def send(self, type_: int, payload: bytes = b"") -> tuple[int, bytes]:
        seq = self.seq
        self.seq = (self.seq + 1) & 0xFF
        frame = encode_frame(seq, type_, payload)
        os.write(self.fd, frame)
        return seq, frame

    def recv(self, timeout: float) -> tuple[int, int, bytes] | None:
        """Next valid packet within timeout (bad frames are skipped)."""
        end = time.monotonic() + timeout
        while True:
            while b"\x00" in self.buf:
                i = self.buf.index(b"\x00")
                frame, self.buf = bytes(self.buf[:i]), self.buf[i + 1:]
                if frame:
                    try:
                        return decode_packet(frame)
                    except ValueError:
                        continue
            left = end - time.monotonic()
            if left <= 0:
                return None
            r, _, _ = select.select([self.fd], [], [], left)
            if r:
                self.buf += os.read(self.fd, 4096)

    def ack(self, seq: int, type_: int, timeout: float = 1.0) -> tuple[int, bytes]:
        """Wait for the ACK of (seq, type_); returns (status, data). Telemetry is skipped."""
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            pkt = self.recv(left)
            if pkt is None:
                break
            _, t, payload = pkt
            if t == ACK and len(payload) >= 3 and payload[0] == seq and payload[1] == type_:
                return payload[2], payload[3:]
        raise TimeoutError(f"no ACK for seq {seq} type {type_:#04x}")

    def close(self) -> None:
        os.close(self.fd)


SIM_NICE = -10  # the mock bench's (drivers/mock/bench.py HARNESS_NICE, which says why not FIFO)


def realtime_child() -> None:
    """preexec_fn: the harness stands in for a microcontroller, which host load does not slow:
    CPU-favoured (nice) where allowed (root or CAP_SYS_NICE), as the mock bench runs it; else
    unchanged."""
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, SIM_NICE)


class Sim:
    def __init__(self, binary: str, elf: str, *extra: str) -> None:
        self.p = subprocess.Popen([binary, *extra, elf], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, bufsize=1,
                                  preexec_fn=realtime_child)
        line = self.p.stdout.readline()
        if not line.startswith("PTY "):
            self.p.kill()
            raise RuntimeError(f"harness did not print PTY: {line!r} {self.p.stderr.read()}")
        self.pty = line.split(None, 1)[1].strip()

    def cmd(self, text: str) -> None:
        self.p.stdin.write(text + "\n")
        self.p.stdin.flush()

    def state(self) -> dict[str, float]:
        self.cmd("Q")
        r, _, _ = select.select([self.p.stdout], [], [], 2.0)
        if not r:
            raise TimeoutError("no STATE line")
        line = self.p.stdout.readline().split()
        assert line[0] == "STATE", line
        return {k: float(v) for k, v in (kv.split("=") for kv in line[1:])}

    def close(self) -> tuple[int, str]:
        """Close stdin (the harness must exit on EOF); returns (exit code, stderr)."""
        self.p.stdin.close()
        try:
            rc = self.p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.p.kill()
            raise RuntimeError("harness did not exit on stdin EOF") from None
        return rc, self.p.stderr.read()


def check(cond: bool, what: str) -> None:
    print(("ok   " if cond else "FAIL ") + what)
    if not cond:
        raise SystemExit(1)


def round_trips(
    link: Link, type_: int, payload: bytes, rounds: int
) -> tuple[list[float], int, int]:
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        seq, frame = link.send(type_, payload)
        status, data = link.ack(seq, type_)
        times.append((time.perf_counter() - t0) * 1000.0)
    n_ack = len(encode_frame(0, ACK, bytes([0, type_, status]) + data))
    return times, len(frame), n_ack


TELEMETRY_NAMES = ("t_ms", "ma", "dmv", "duty", "amb", "flags", "sp", "crc", "fr", "model", "tc",
                   "dma", "supply_mv", "tc_status")


def cmd(link: Link, type_: int, payload: bytes = b"") -> int:
    seq, _ = link.send(type_, payload)
    return link.ack(seq, type_)[0]


def telemetry(link: Link, pred=lambda t: True, timeout: float = 2.0) -> dict[str, int]:
    """The first TELEMETRY frame (as a dict) for which pred holds."""
    end = time.monotonic() + timeout
    while (left := end - time.monotonic()) > 0:
        pkt = link.recv(left)
        if pkt and pkt[1] == TELEMETRY and len(pkt[2]) == struct.calcsize(TELEMETRY_FMT):
            t = dict(zip(TELEMETRY_NAMES, struct.unpack(TELEMETRY_FMT, pkt[2]), strict=True))
            if pred(t):
                return t
    raise TimeoutError("no matching telemetry")


def frames_for(link: Link, seconds: float) -> list[dict[str, int]]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        pkt = link.recv(left)
        if pkt and pkt[1] == TELEMETRY:
            values = struct.unpack(TELEMETRY_FMT, pkt[2])
            out.append(dict(zip(TELEMETRY_NAMES, values, strict=True)))
    return out


def off(link: Link) -> None:
    cmd(link, ENABLE, b"\x00")
    cmd(link, SET_CURRENT, struct.pack("<H", 0))


def safety_paths(sim: Sim, link: Link) -> None:
    """Every safety path of PROTOCOL.md, checked in device time (telemetry t_ms)."""
    u16 = lambda v: struct.pack("<H", v)  # noqa: E731
    check(cmd(link, SET_LIMITS, struct.pack("<HH", 2500, 1000)) == ST_OK, "limits 2.5 A, 1 s")
    check(cmd(link, SET_TELEMETRY, u16(5)) == ST_OK, "telemetry every 5 ms")

    # current steps across the wire range and the supply range
    for r_ohm, supply_v in ((0.3, 4.75), (1.0, 4.75), (0.3, 5.5), (1.0, 5.5)):
        sim.cmd(f"R {r_ohm}")
        sim.cmd(f"V {supply_v}")
        cmd(link, SET_LEASE, u16(5000))
        cmd(link, SET_CURRENT, u16(0))
        cmd(link, ENABLE, b"\x01")
        cmd(link, SET_CURRENT, u16(1000))
        rows = frames_for(link, 0.25)
        rows = [r for r in rows if r["sp"] == 1000]
        t0 = rows[0]["t_ms"] - 5  # the setpoint arrived within the 5 ms before this frame
        last_out = max((r["t_ms"] - t0 for r in rows if abs(r["ma"] - 1000) > 50), default=0)
        settled = min(r["t_ms"] - t0 for r in rows if r["t_ms"] - t0 > last_out)
        peak = max(r["ma"] for r in rows)
        st = sim.state()
        trace = " ".join(f"{r['t_ms'] - t0}:{r['ma']}" for r in rows[:4])
        check(settled <= 50 and peak <= 1070 and abs(st["current_a"] - 1.0) < 0.01,
              f"step 0 -> 1000 mA into {r_ohm} Ohm at {supply_v} V: within 5 % by {settled} ms "
              f"(device time; ms:mA {trace}), peak {peak} mA, wire {st['current_a'] * 1000:.1f} mA")
        off(link)
    sim.cmd("V 5.0")
    sim.cmd("R 0.44")

    # setpoint lease: PINGs keep the link, not the heating
    check(cmd(link, SET_LEASE, u16(250)) == ST_OK, "lease 250 ms")
    cmd(link, SET_CURRENT, u16(800))
    cmd(link, ENABLE, b"\x01")
    first = telemetry(link, lambda t: t["flags"] & FLAG_ENABLED and t["sp"] == 800)
    last_ping, end = 0.0, time.monotonic() + 2.0
    expired = None
    while time.monotonic() < end and expired is None:
        if time.monotonic() - last_ping > 0.02:
            link.send(PING)
            last_ping = time.monotonic()
        pkt = link.recv(0.01)
        if pkt and pkt[1] == TELEMETRY:
            t = dict(zip(TELEMETRY_NAMES, struct.unpack(TELEMETRY_FMT, pkt[2]), strict=True))
            if t["flags"] & FLAG_LEASE_EXPIRED:
                expired = t
    check(expired is not None and not expired["flags"] & (FLAG_ENABLED | 8) and expired["sp"] == 0,
          "lease expired while PINGs went on (output off, setpoint 0, no host timeout)")
    dt = expired["t_ms"] - first["t_ms"]
    check(240 <= dt <= 265,
          f"lease: off {dt} ms after the last SET_CURRENT (device time, lease 250)")
    time.sleep(0.02)
    check(sim.state()["current_a"] == 0.0, "no wire current after the lease expired")
    cmd(link, SET_LEASE, u16(5000))

    # probe current (protocol 4): held at setpoint 0 past the 250 ms lease while only PINGs go
    # on (it is not leased), the wire voltage measured at it; ENABLE 0 turns it off
    check(cmd(link, SET_LEASE, u16(250)) == ST_OK, "lease 250 ms")
    check(cmd(link, SET_PROBE, u16(101)) == ST_OUT_OF_RANGE, "probe 101 mA refused")
    check(cmd(link, SET_CURRENT, u16(0)) == ST_OK and cmd(link, SET_PROBE, u16(100)) == ST_OK
          and cmd(link, ENABLE, b"\x01") == ST_OK, "probe 100 mA, setpoint 0, enabled")
    first = telemetry(link, lambda t: t["flags"] & FLAG_ENABLED and abs(t["ma"] - 100) <= 5)
    last_ping, held = 0.0, None
    end = time.monotonic() + 3.0
    while time.monotonic() < end and held is None:
        if time.monotonic() - last_ping > 0.05:
            link.send(PING)
            last_ping = time.monotonic()
        pkt = link.recv(0.01)
        if pkt and pkt[1] == TELEMETRY:
            t = dict(zip(TELEMETRY_NAMES, struct.unpack(TELEMETRY_FMT, pkt[2]), strict=True))
            if not t["flags"] & FLAG_ENABLED or t["t_ms"] - first["t_ms"] >= 600:
                held = t
    st = sim.state()
    check(held is not None and held["flags"] & FLAG_ENABLED
          and not held["flags"] & FLAG_LEASE_EXPIRED and held["sp"] == 0
          and abs(held["ma"] - 100) <= 5 and abs(st["current_a"] - 0.1) < 0.005,
          f"probe held {held and held['t_ms'] - first['t_ms']} ms at setpoint 0 with PINGs only: "
          f"read {held and held['ma']} mA, wire {st['current_a'] * 1000:.1f} mA")
    check(held["dmv"] != 0xFFFF and abs(held["dmv"] / 1e4 - st["current_a"] * 0.44) < 0.001,
          f"wire voltage at the probe: {held['dmv'] / 10:.1f} mV (0.44 Ohm)")
    check(cmd(link, ENABLE, b"\x00") == ST_OK, "ENABLE 0")
    time.sleep(0.02)
    check(sim.state()["current_a"] == 0.0, "ENABLE 0: no probe current")
    check(cmd(link, ENABLE, b"\x01") == ST_OK, "enable again, no SET_PROBE")
    time.sleep(0.05)
    check(sim.state()["current_a"] == 0.0, "the probe stays off until the next SET_PROBE")
    off(link)
    cmd(link, SET_LEASE, u16(5000))

    # e-stop input, latched until cleared
    cmd(link, SET_CURRENT, u16(1000))
    check(cmd(link, ENABLE, b"\x01") == ST_OK, "enable after the lease (ENABLE clears the event)")
    on = telemetry(link, lambda t: t["ma"] > 950)
    sim.cmd("ESTOP 1")
    tripped = telemetry(link, lambda t: t["flags"] & FLAG_ESTOP)
    check(not tripped["flags"] & FLAG_ENABLED and sim.state()["current_a"] == 0.0,
          f"e-stop: output off ({tripped['t_ms'] - on['t_ms']} ms after a frame at 1 A)")
    check(cmd(link, ENABLE, b"\x01") == ST_FAULT_ACTIVE, "e-stop: ENABLE refused")
    check(cmd(link, CLEAR_FAULTS) == ST_FAULT_ACTIVE, "e-stop: CLEAR_FAULTS refused while tripped")
    sim.cmd("ESTOP 0")
    time.sleep(0.02)
    check(telemetry(link)["flags"] & FLAG_ESTOP, "e-stop released: still latched")
    check(cmd(link, CLEAR_FAULTS) == ST_OK and cmd(link, ENABLE, b"\x01") == ST_OK,
          "e-stop cleared, output on again")
    off(link)

    # energy budget: 2.5 A demanded for ever. Shortened budget: 2 mJ/K instead of 33.6 mJ/K
    # (16.8 x faster), so 3.6 s here stand for the 60 s of the real wire.
    heat = struct.pack("<HHHH", 550, 20, 590, 1800)
    check(cmd(link, SET_HEAT_MODEL, heat) == ST_OK, "shortened heat model stored")
    seq, _ = link.send(GET_HEAT_MODEL)
    check(link.ack(seq, GET_HEAT_MODEL) == (ST_OK, heat), "GET_HEAT_MODEL reads it back")
    c_wire, g_wire, r_wire = 2e-3 * 1.2, 5.9e-3 * 120 / 90, 0.44  # the "real" wire: kinder
    # the shortened model cools with tau = C/G = 0.34 s: start from ambient, as the wire
    telemetry(link, lambda t: t["model"] < 2300, 5.0)
    cmd(link, SET_CURRENT, u16(2500))
    cmd(link, ENABLE, b"\x01")
    t_wire, peak, first_trip, start, last_t = 22.0, 22.0, None, None, None
    end, last_cmd = time.monotonic() + 3.6, 0.0
    while time.monotonic() < end:
        if time.monotonic() - last_cmd > 0.05:  # the host insists
            link.send(SET_CURRENT, u16(2500))
            link.send(CLEAR_FAULTS)
            link.send(ENABLE, b"\x01")
            last_cmd = time.monotonic()
        pkt = link.recv(0.01)
        if not (pkt and pkt[1] == TELEMETRY):
            continue
        t = dict(zip(TELEMETRY_NAMES, struct.unpack(TELEMETRY_FMT, pkt[2]), strict=True))
        if last_t is not None:
            i = t["ma"] / 1000.0
            dt_s = (t["t_ms"] - last_t) / 1e3
            t_wire += (i * i * r_wire - g_wire * (t_wire - 22.0)) * dt_s / c_wire
            peak = max(peak, t_wire)
        if start is None and not t["flags"] & FLAG_ENABLED:
            continue  # frames from before the output came on
        start = t["t_ms"] if start is None else start
        last_t = t["t_ms"]
        if first_trip is None and t["flags"] & FLAG_OVERTEMP:
            first_trip = t["t_ms"] - start
    check(first_trip is not None and 50 <= first_trip <= 200,
          f"energy budget tripped {first_trip} ms into 2.5 A from 22 C (the model: 2 mJ/K x "
          f"158 K / (2.5 A)^2 x 0.55 Ohm = 92 ms)")
    check(peak < 180.0, f"the wire never passed 180 C in {(last_t - start) / 1000:.1f} s of "
          f"2.5 A demanded: peak {peak:.1f} C")
    off(link)
    cmd(link, CLEAR_FAULTS)
    cmd(link, SET_HEAT_MODEL, struct.pack("<HHHH", 550, 336, 590, 1800))

    # NTC open and shorted read as a fault, never as a temperature
    for state, what in (("OPEN", "open"), ("SHORT", "shorted")):
        sim.cmd(f"NTC {state}")
        t = telemetry(link, lambda t: t["flags"] & FLAG_NTC_FAULT, 1.0)
        check(t["amb"] == TEMP_NONE, f"NTC {what}: fault flag, no temperature")
    sim.cmd("NTC OK")
    t = telemetry(link, lambda t: not t["flags"] & FLAG_NTC_FAULT, 1.0)
    # the first plausible 100 ms mean may still hold conversions of the fault; the next is clean
    t = telemetry(link, lambda t, t0=t["t_ms"]: t["t_ms"] >= t0 + 100, 1.0)
    check(abs(t["amb"] / 100 - 22.0) < 0.3, f"NTC back: {t['amb'] / 100:.2f} C (harness 22 C)")

    # thermocouple: a temperature, its three faults, absent
    sim.cmd("TC 123.5")
    t = telemetry(link, lambda t: t["tc"] == 12350, 1.0)
    check(t["tc_status"] == 0, "thermocouple 123.50 C")
    for name, bit in (("OC", 1), ("SCG", 2), ("SCV", 4)):
        sim.cmd(f"TC {name}")
        t = telemetry(link, lambda t, b=bit: t["tc_status"] == b, 1.0)
        check(t["tc"] == TEMP_NONE and t["flags"] & FLAG_TC_FAULT, f"thermocouple fault {name}")
    sim.cmd("TC NONE")
    t = telemetry(link, lambda t: t["tc_status"] == 0x80, 1.0)
    check(t["tc"] == TEMP_NONE and not t["flags"] & FLAG_TC_FAULT, "no thermocouple: absent")

    # calibration in EEPROM
    cal = struct.pack("<hHHh", 1500, 32000, 33000, -2500)
    check(cmd(link, SET_CALIBRATION, cal) == ST_OK, "calibration stored")
    seq, _ = link.send(GET_CALIBRATION)
    check(link.ack(seq, GET_CALIBRATION) == (ST_OK, cal), "GET_CALIBRATION reads it back")
    cmd(link, SET_CALIBRATION, struct.pack("<hHHh", 0, 32768, 32768, 0))
    cmd(link, SET_TELEMETRY, u16(0))


def watchdog_test(sim_bin: str, elf: str) -> None:
    """The hang build stops feeding the watchdog at 300 ms: simavr must reset it (WDRF), and the
    firmware must come back with the WATCHDOG_RESET flag."""
    sim = Sim(sim_bin, elf)
    link = Link(sim.pty)
    try:
        time.sleep(0.05)
        seq, _ = link.send(IDENTIFY, bytes([PROTOCOL_VERSION]))
        check(link.ack(seq, IDENTIFY)[0] == 0, "watchdog build answers before the hang")
        # hang at 300 ms AVR time; the watchdog's interrupt at ~332 ms turns the output off and
        # leaves the .noinit marker, its reset follows at ~364 ms. Wait on the AVR's clock (the
        # harness may run behind the wall clock on a busy machine), then ask until it answers:
        # a frame sent during the hang is lost with the reset.
        end = time.monotonic() + 10.0
        while sim.state()["t_ms"] < 450 and time.monotonic() < end:
            time.sleep(0.02)
        answered = False
        while not answered and time.monotonic() < end:
            seq, _ = link.send(SET_TELEMETRY, struct.pack("<H", 10))
            with contextlib.suppress(TimeoutError):
                answered = link.ack(seq, SET_TELEMETRY, timeout=0.3)[0] == 0
        check(answered, "answers again after the watchdog reset")
        pkt = None
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            pkt = link.recv(end - time.monotonic())
            if pkt and pkt[1] == TELEMETRY:
                break
        check(pkt is not None and pkt[1] == TELEMETRY and len(pkt[2]) >= 14,
              "telemetry after the reset")
        t_ms, flags = struct.unpack("<I", pkt[2][0:4])[0], struct.unpack("<H", pkt[2][12:14])[0]
        check(bool(flags & FLAG_WATCHDOG_RESET) and t_ms < 1000,
              f"WATCHDOG_RESET flag set, device time restarted ({t_ms} ms, flags {flags:#06x})")
    finally:
        link.close()
        rc, err = sim.close()
    check(rc == 0 and "watchdog" in err, f"harness saw the watchdog reset: {err.strip()!r}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("sim")
    ap.add_argument("elf")
    ap.add_argument("--rounds", type=int, default=50)
    ap.add_argument("--wdt-elf",
                    help="build of sim/wdt_hang_main.c: main loop hangs 300 ms after power-on")
    args = ap.parse_args()

    t_start = time.monotonic()
    sim = Sim(args.sim, args.elf)
    link = Link(sim.pty)
    try:
        time.sleep(0.05)  # firmware boot
        seq, frame = link.send(IDENTIFY, bytes([PROTOCOL_VERSION]))
        status, data = link.ack(seq, IDENTIFY)
        check(status == 0, f"IDENTIFY ACK status OK (got {status})")
        check(len(data) >= 6 and data[0] == PROTOCOL_VERSION, f"protocol version {PROTOCOL_VERSION} in IDENTIFY data")
        fw, limit = data[1:4], struct.unpack("<H", data[4:6])[0]
        name = data[6:].decode("ascii", "replace")
        check(name == "SMA-CD328",
              f"device name {name!r}, firmware {'.'.join(map(str, fw))}, hard limit {limit} mA")

        st = sim.state()
        check(st["duty"] == 0.0 and st["current_a"] == 0.0, f"output off after reset: {st}")
        sim.cmd("R 5.5")
        st = sim.state()
        check(abs(st["r_ohm"] - 5.5) < 1e-9, "R command sets the wire resistance")
        t1 = st["t_ms"]
        time.sleep(0.2)
        t2 = sim.state()["t_ms"]
        # a figure, not a pass mark: a busy machine makes the harness slip behind the wall clock
        check(t2 > t1, f"AVR time runs: {t2 - t1:.1f} ms AVR time in ~200 ms of wall time")

        # round trips: PING, IDENTIFY, and a 16-byte frame (unknown type, 10-byte payload)
        results = []
        for label, type_, payload in (("PING", PING, b""), ("IDENTIFY", IDENTIFY, bytes([PROTOCOL_VERSION])),
                                      ("16-byte frame", 0x7F, bytes(range(1, 11)))):
            times, n_out, n_back = round_trips(link, type_, payload, args.rounds)
            results.append((label, n_out, n_back, times))
        for label, n_out, n_back, times in results:
            print(f"     round trip {label:14s} {n_out:2d} B out, {n_back:2d} B back: median "
                  f"{statistics.median(times):.2f} ms, min {min(times):.2f}, max {max(times):.2f} "
                  f"(n={len(times)})")
        seq, _ = link.send(0x7F, bytes(range(1, 11)))
        status, _ = link.ack(seq, 0x7F)
        check(status == 1, "unknown command answered UNKNOWN_COMMAND")

        # a little closed loop: enable 1 A into the bench wire and watch the harness current
        sim.cmd("R 0.44")
        for type_, payload in ((SET_LIMITS, struct.pack("<HH", 2000, 1000)),
                               (SET_LEASE, struct.pack("<H", 5000)),
                               (SET_CURRENT, struct.pack("<H", 1000)), (ENABLE, b"\x01")):
            seq, _ = link.send(type_, payload)
            status, _ = link.ack(seq, type_)
            check(status == 0, f"command {type_:#04x} ACK OK")
        time.sleep(0.15)
        st = sim.state()
        check(0.9 <= st["current_a"] <= 1.1, f"closed loop at 1 A: {st}")
        seq, _ = link.send(ENABLE, b"\x00")
        link.ack(seq, ENABLE)
        time.sleep(0.02)
        st = sim.state()
        check(st["duty"] == 0.0, f"ENABLE 0 turns the output off: {st}")
        safety_paths(sim, link)
    finally:
        link.close()
        rc, err = sim.close()
    check(rc == 0, f"harness exits 0 on stdin EOF (stderr: {err.strip()[-300:]!r})")

    sim = Sim(args.sim, args.elf)
    sim.p.terminate()
    try:
        rc = sim.p.wait(timeout=5)
    except subprocess.TimeoutExpired:
        sim.p.kill()
        rc = None
    check(rc == 0, "harness exits 0 on SIGTERM")

    if args.wdt_elf:
        watchdog_test(args.sim, args.wdt_elf)
    print(f"sim-test: passed in {time.monotonic() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
