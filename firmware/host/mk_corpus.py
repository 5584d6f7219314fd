#!/usr/bin/env python3
"""Seed corpus for fuzz_frame from the test vectors (firmware/test-vectors/*.txt).

Usage: mk_corpus.py OUT_DIR VECTORS.txt ...  Writes one seed per valid/invalid frame (raw mode:
first byte 0x00), the whole vector stream in one seed, and a few structured command scripts
(first byte odd, see fuzz_frame.c)."""
import hashlib
import pathlib
import struct
import sys


def frames(path):
    for line in pathlib.Path(path).read_text().splitlines():
        tok = line.split("#", 1)[0].split()
        if len(tok) == 5:
            yield bytes.fromhex(tok[4])
        elif len(tok) == 4 and tok[1] == "ERR":
            yield bytes.fromhex(tok[3])


def cmd(type_, payload=b""):
    return bytes((0, type_, len(payload))) + payload  # op 0: framed command


def ticks(n):
    return bytes((1, n, 0))


def main():
    out = pathlib.Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    seeds = []
    stream = b""
    for path in sys.argv[2:]:
        for fr in frames(path):
            seeds.append(b"\x00" + fr)
            seeds.append(b"\x10" + fr)  # tick every 2 bytes
            stream += fr
    seeds.append(b"\x00" + stream)
    on = cmd(2, b"\x01")
    seeds += [
        b"\x01" + cmd(1, b"\x01") + on + cmd(3, struct.pack("<H", 1000)) + ticks(100) + cmd(7),
        b"\x01" + cmd(4, struct.pack("<HH", 1000, 20)) + on + cmd(3, struct.pack("<H", 900))
        + ticks(30) + ticks(30),
        b"\x01" + on + cmd(3, struct.pack("<H", 2000)) + bytes((2, 1, 0)) + ticks(20)
        + cmd(6) + on + ticks(10),
        b"\x03" + on + cmd(3, struct.pack("<H", 1500)) + bytes((2, 42, 1)) + ticks(80) + cmd(6)
        + cmd(5, struct.pack("<H", 5)) + ticks(50),
        b"\x05" + cmd(5, struct.pack("<H", 5)) + cmd(9) + cmd(2, b"\x02") + ticks(20),
        # protocol v2: lease, calibration, heat model, e-stop, sensor faults
        b"\x01" + cmd(8, struct.pack("<H", 50)) + on + cmd(3, struct.pack("<H", 800)) + ticks(80)
        + cmd(7) + ticks(80),
        b"\x01" + cmd(9, struct.pack("<hHHh", 1500, 32000, 33000, -2500)) + cmd(10)
        + cmd(11, struct.pack("<HHHH", 1000, 200, 300, 1000)) + cmd(12) + on
        + cmd(3, struct.pack("<H", 2500)) + ticks(250) + ticks(250) + cmd(6),
        b"\x01" + on + cmd(3, struct.pack("<H", 1000)) + ticks(20) + bytes((2, 44, 2)) + ticks(5)
        + cmd(6) + bytes((2, 44, 0)) + cmd(6) + on + ticks(5),
        b"\x01" + cmd(5, struct.pack("<H", 5)) + bytes((2, 44, 4 | 8 | 32)) + ticks(200)
        + bytes((2, 44, 16)) + ticks(200),
        # protocol v4: the probe current, held at setpoint 0, off with the output
        b"\x01" + cmd(13, struct.pack("<H", 80)) + on + ticks(100) + cmd(3, struct.pack("<H", 500))
        + ticks(50) + cmd(3, struct.pack("<H", 0)) + ticks(50) + cmd(13, struct.pack("<H", 101))
        + cmd(2, b"\x00") + ticks(20) + on + cmd(13, struct.pack("<H", 100)) + ticks(250),
    ]
    for s in seeds:
        (out / hashlib.sha1(s).hexdigest()).write_bytes(s)
    print(f"{len(seeds)} seeds in {out}")


if __name__ == "__main__":
    main()
