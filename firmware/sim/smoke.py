#!/usr/bin/env python3
"""Smoke test of the AVR firmware in the simavr harness (make -C firmware sim-test).

Starts smabench-sim on the .elf, opens the pty it prints, sends IDENTIFY and checks the ACK
(status OK, protocol 1, device name), checks the control channel (Q, R), and measures frame round
trips through the pty. Python 3 standard library only; COBS and CRC-16/CCITT-FALSE are implemented
here so the test does not depend on drivers/protocol.py.

usage: smoke.py SIM_BINARY FIRMWARE_ELF [--rounds N] [--wdt-elf ELF]
"""
from __future__ import annotations

import argparse
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
ACK, TELEMETRY = 0x80, 0x90
FLAG_WATCHDOG_RESET = 1 << 4


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


class Sim:
    def __init__(self, binary: str, elf: str, *extra: str) -> None:
        self.p = subprocess.Popen([binary, *extra, elf], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, bufsize=1)
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
            raise RuntimeError("harness did not exit on stdin EOF")
        return rc, self.p.stderr.read()


def check(cond: bool, what: str) -> None:
    print(("ok   " if cond else "FAIL ") + what)
    if not cond:
        raise SystemExit(1)


def round_trips(link: Link, type_: int, payload: bytes, rounds: int) -> tuple[list[float], int, int]:
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        seq, frame = link.send(type_, payload)
        status, data = link.ack(seq, type_)
        times.append((time.perf_counter() - t0) * 1000.0)
    n_ack = len(encode_frame(0, ACK, bytes([0, type_, status]) + data))
    return times, len(frame), n_ack


def watchdog_test(sim_bin: str, elf: str) -> None:
    """The hang build stops feeding the watchdog at 300 ms: simavr must reset it (WDRF), and the
    firmware must come back with the WATCHDOG_RESET flag."""
    sim = Sim(sim_bin, elf)
    link = Link(sim.pty)
    try:
        time.sleep(0.05)
        seq, _ = link.send(IDENTIFY, bytes([1]))
        check(link.ack(seq, IDENTIFY)[0] == 0, "watchdog build answers before the hang")
        time.sleep(0.5)  # hang at 300 ms, watchdog at ~364 ms
        seq, _ = link.send(SET_TELEMETRY, struct.pack("<H", 10))
        check(link.ack(seq, SET_TELEMETRY)[0] == 0, "answers again after the watchdog reset")
        pkt = None
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            pkt = link.recv(end - time.monotonic())
            if pkt and pkt[1] == TELEMETRY:
                break
        check(pkt is not None and pkt[1] == TELEMETRY and len(pkt[2]) >= 14, "telemetry after the reset")
        t_ms, flags = struct.unpack("<I", pkt[2][0:4])[0], struct.unpack("<H", pkt[2][12:14])[0]
        check(bool(flags & FLAG_WATCHDOG_RESET) and t_ms < 400,
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
    ap.add_argument("--wdt-elf", help="build of sim/wdt_hang_main.c: main loop hangs 300 ms after power-on")
    args = ap.parse_args()

    t_start = time.monotonic()
    sim = Sim(args.sim, args.elf)
    link = Link(sim.pty)
    try:
        time.sleep(0.05)  # firmware boot
        seq, frame = link.send(IDENTIFY, bytes([1]))
        status, data = link.ack(seq, IDENTIFY)
        check(status == 0, f"IDENTIFY ACK status OK (got {status})")
        check(len(data) >= 6 and data[0] == 1, "protocol version 1 in IDENTIFY data")
        fw, limit, name = data[1:4], struct.unpack("<H", data[4:6])[0], data[6:].decode("ascii", "replace")
        check(name == "SMA-CD328", f"device name {name!r}, firmware {'.'.join(map(str, fw))}, hard limit {limit} mA")

        st = sim.state()
        check(st["duty"] == 0.0 and st["current_a"] == 0.0, f"output off after reset: {st}")
        sim.cmd("R 5.5")
        st = sim.state()
        check(abs(st["r_ohm"] - 5.5) < 1e-9, "R command sets the wire resistance")
        t1 = st["t_ms"]
        time.sleep(0.2)
        t2 = sim.state()["t_ms"]
        check(150 <= t2 - t1 <= 260, f"AVR time runs at real time: {t2 - t1:.1f} ms AVR time in ~200 ms")

        # round trips: PING, IDENTIFY, and a 16-byte frame (unknown type, 10-byte payload)
        results = []
        for label, type_, payload in (("PING", PING, b""), ("IDENTIFY", IDENTIFY, bytes([1])),
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

        # a little closed loop: enable 1 A into 4 ohm and watch the harness current
        sim.cmd("R 4.0")
        for type_, payload in ((SET_LIMITS, struct.pack("<HH", 2000, 1000)),
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
