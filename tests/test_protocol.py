"""Current-driver protocol codec (drivers/protocol.py) vs PROTOCOL.md and the shared vectors."""

from __future__ import annotations

import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from smabench.drivers import protocol as p

REPO = Path(__file__).resolve().parent.parent
VECTOR_DIR = REPO / "firmware" / "test-vectors"


def load_vectors(path: Path):
    good, bad = [], []
    for line in path.read_text().splitlines():
        tok = line.split("#", 1)[0].split()
        if not tok:
            continue
        if len(tok) == 4 and tok[1] == "ERR":
            bad.append((tok[0], tok[2], bytes.fromhex(tok[3])))
        else:
            assert len(tok) == 5, line
            name, seq, type_hex, payload_hex, frame_hex = tok
            payload = b"" if payload_hex == "-" else bytes.fromhex(payload_hex)
            good.append((name, int(seq), int(type_hex, 16), payload, bytes.fromhex(frame_hex)))
    return good, bad


VECTOR_FILES = sorted(VECTOR_DIR.glob("*.txt"))
GOOD = [(f.name, *v) for f in VECTOR_FILES for v in load_vectors(f)[0]]
BAD = [(f.name, *v) for f in VECTOR_FILES for v in load_vectors(f)[1]]


# ------------------------------------------------------------------ independent references
def crc_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE, bit by bit (independent of the table-driven codec)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_crc_check_value():
    assert p.crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc_bitwise(b"123456789") == 0x29B1


def test_crc_matches_bitwise_reference():
    rng = random.Random(1)
    for n in range(0, 70):
        data = bytes(rng.randrange(256) for _ in range(n))
        assert p.crc16_ccitt_false(data) == crc_bitwise(data)


# Examples from the COBS paper / Wikipedia "Consistent Overhead Byte Stuffing" (without the 00).
COBS_EXAMPLES = [
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize("raw,encoded", COBS_EXAMPLES)
def test_cobs_examples(raw, encoded):
    assert p.cobs_encode(raw) == encoded
    assert p.cobs_decode(encoded) == raw


def test_hand_computed_ping_frame():
    # packet 00 07 + CRC(00 07) = 0x6DE8 little-endian; no zero after seq: COBS 01 | 04 07 e8 6d
    assert crc_bitwise(b"\x00\x07") == 0x6DE8
    assert p.encode_frame(0, p.MsgType.PING) == bytes.fromhex("010407e86d00")


def test_hand_computed_set_current_frame():
    # seq 5, SET_CURRENT 256 mA: packet 05 03 00 01 crc; zero at index 2 splits the COBS blocks
    crc = crc_bitwise(b"\x05\x03\x00\x01")
    raw = b"\x05\x03\x00\x01" + struct.pack("<H", crc)
    assert 0 not in raw[3:]
    expected = b"\x03\x05\x03" + bytes((len(raw) - 3 + 1,)) + raw[3:] + b"\x00"
    assert p.encode_frame(5, p.MsgType.SET_CURRENT, *p.set_current(0.256)[1:]) == expected


def test_cobs_roundtrip_random():
    rng = random.Random(2)
    for _ in range(500):
        n = rng.randrange(0, 600)
        data = bytes(rng.choice((0, 0, rng.randrange(256))) for _ in range(n))
        enc = p.cobs_encode(data)
        assert 0 not in enc
        assert len(enc) <= n + n // 254 + 1
        assert p.cobs_decode(enc) == data


@pytest.mark.parametrize("bad", [b"\x00", b"\x03\x11", b"\x02\x00\x01", b"\x05\x11\x22"])
def test_cobs_decode_rejects(bad):
    with pytest.raises(p.FrameError):
        p.cobs_decode(bad)


# ------------------------------------------------------------------ shared vectors
def test_vector_files_present():
    names = {f.name for f in VECTOR_FILES}
    assert "frames.txt" in names
    good, bad = load_vectors(VECTOR_DIR / "frames.txt")
    assert len(bad) >= 6
    types = {t for _, _, t, _, _ in good}
    assert set(p.COMMANDS) <= types and p.MsgType.ACK in types and p.MsgType.TELEMETRY in types
    assert any(seq == 255 for _, seq, _, _, _ in good)
    assert any(len(pl) == 60 for _, _, _, pl, _ in good)
    assert any(0 in pl for _, _, _, pl, _ in good)


def test_frames_txt_up_to_date():
    gen = VECTOR_DIR / "generate.py"
    proc = subprocess.run([sys.executable, str(gen), "--check"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("file,name,seq,type_,payload,frame", GOOD, ids=[v[1] for v in GOOD])
def test_valid_vector(file, name, seq, type_, payload, frame):
    assert frame.endswith(b"\x00") and frame.count(0) == 1
    assert p.encode_frame(seq, type_, payload) == frame
    rx = p.FrameReceiver()
    assert rx.feed(frame) == [p.Packet(seq, type_, payload)]
    assert (rx.crc_errors, rx.frame_errors) == (0, 0)
    assert p.decode_frame(frame) == p.Packet(seq, type_, payload)


@pytest.mark.parametrize("file,name,kind,frame", BAD, ids=[v[1] for v in BAD])
def test_invalid_vector(file, name, kind, frame):
    assert kind in ("crc", "frame")
    rx = p.FrameReceiver()
    assert rx.feed(frame) == []
    assert (rx.crc_errors, rx.frame_errors) == ((1, 0) if kind == "crc" else (0, 1))
    with pytest.raises(p.CrcError if kind == "crc" else p.FrameError):
        p.decode_frame(frame)
    # resync: the next frame is received
    assert rx.feed(p.encode_frame(1, p.MsgType.PING)) == [p.Packet(1, p.MsgType.PING)]


def test_identify_reply_vector():
    good, _ = load_vectors(VECTOR_DIR / "frames.txt")
    (_, _, _, payload, _) = next(v for v in good if v[0] == "ack_identify_ok")
    ack = p.Ack.from_payload(payload)
    assert (ack.type, ack.status) == (p.MsgType.IDENTIFY, p.Status.OK)
    info = p.DeviceInfo.from_data(ack.data)
    assert info == p.DeviceInfo(1, (1, 0, 0), 2.5, "SMA-CD328")
    assert info.firmware == "1.0.0"
    assert info.to_data() == ack.data


# ------------------------------------------------------------------ receiver robustness
def test_receiver_split_byte_by_byte_and_multiple_frames():
    frames = [p.encode_frame(i, p.MsgType.SET_CURRENT, struct.pack("<H", i * 7)) for i in range(20)]
    stream = b"".join(frames)
    rx = p.FrameReceiver()
    got = []
    for b in stream:
        got += rx.feed(bytes((b,)))
    assert [g.seq for g in got] == list(range(20))
    rx2 = p.FrameReceiver()
    assert len(rx2.feed(stream)) == 20


def test_empty_frames_ignored():
    rx = p.FrameReceiver()
    assert rx.feed(b"\x00\x00\x00" + p.encode_frame(3, 7) + b"\x00") == [p.Packet(3, 7)]
    assert (rx.crc_errors, rx.frame_errors) == (0, 0)


def test_random_garbage_never_raises_and_resyncs():
    rng = random.Random(3)
    rx = p.FrameReceiver()
    valid = 0
    for _ in range(300):
        garbage = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 200)))
        rx.feed(garbage)  # never raises; may even decode a packet by chance
        frame = p.encode_frame(rng.randrange(256), p.MsgType.PING, b"\x01\x00\x02")
        # a delimiter first: whatever the garbage left in the buffer is dropped
        got = rx.feed(b"\x00" + frame)
        assert got and got[-1].payload == b"\x01\x00\x02"
        valid += 1
    assert valid == 300
    assert rx.crc_errors + rx.frame_errors > 100


def test_noise_costs_at_most_the_frame_it_hits():
    rng = random.Random(4)
    frames = [p.encode_frame(i, p.MsgType.PING, bytes((i,))) for i in range(200)]
    hit = set()
    stream = bytearray()
    for i, f in enumerate(frames):
        f = bytearray(f)
        if i % 3 == 0:
            pos = rng.randrange(len(f) - 1)  # never the delimiter
            f[pos] ^= 1 << rng.randrange(8) or 1
            if f[pos] == 0:
                f[pos] = 0x55
            hit.add(i)
        stream += f
    rx = p.FrameReceiver()
    got = rx.feed(bytes(stream))
    seqs = {g.seq for g in got}
    assert seqs >= set(range(200)) - hit
    assert rx.crc_errors + rx.frame_errors == 200 - len(got)


def test_overflow_counts_one_frame_error():
    rx = p.FrameReceiver()
    assert rx.feed(b"\x11" * 1000) == []
    assert rx.feed(b"\x00") == []
    assert (rx.crc_errors, rx.frame_errors) == (0, 1)
    assert rx.feed(p.encode_frame(0, 7)) == [p.Packet(0, 7)]


def test_build_packet_limits():
    assert len(p.build_packet(0, 7, bytes(60))) == 64
    with pytest.raises(ValueError):
        p.build_packet(0, 7, bytes(61))
    with pytest.raises(ValueError):
        p.build_packet(256, 7)
    assert len(p.encode_frame(255, 7, b"\xff" * 60)) <= p.MAX_WIRE


# ------------------------------------------------------------------ commands and payloads
def test_command_table_matches_spec():
    sizes = {
        p.MsgType.IDENTIFY: 1,
        p.MsgType.ENABLE: 1,
        p.MsgType.SET_CURRENT: 2,
        p.MsgType.SET_LIMITS: 4,
        p.MsgType.SET_TELEMETRY: 2,
        p.MsgType.CLEAR_FAULTS: 0,
        p.MsgType.PING: 0,
    }
    assert {t: c.size for t, c in p.COMMANDS.items()} == sizes


def test_unit_builders():
    M = p.MsgType
    assert p.identify() == (M.IDENTIFY, b"\x01")
    assert p.enable(True) == (M.ENABLE, b"\x01")
    assert p.enable(False) == (M.ENABLE, b"\x00")
    assert p.set_current(1.0) == (M.SET_CURRENT, b"\xe8\x03")
    assert p.set_current(0.0004) == (M.SET_CURRENT, b"\x00\x00")
    assert p.set_limits(2.5, 0.25) == (M.SET_LIMITS, b"\xc4\x09\xfa\x00")
    assert p.set_telemetry(0.01) == (M.SET_TELEMETRY, b"\x0a\x00")
    assert p.set_telemetry(0) == (M.SET_TELEMETRY, b"\x00\x00")
    assert p.clear_faults() == (M.CLEAR_FAULTS, b"")
    assert p.ping() == (M.PING, b"")
    for bad in (
        lambda: p.set_current(-0.1),
        lambda: p.set_limits(3.0, 0.25),
        lambda: p.set_limits(1.0, 0.01),
        lambda: p.set_telemetry(0.001),
        lambda: p.set_telemetry(2.0),
    ):
        with pytest.raises(ValueError):
            bad()
    with pytest.raises(TypeError):
        p.command_payload(M.SET_LIMITS, 1)


def test_telemetry_parse():
    payload = struct.pack("<IHHHhHHHH", 123456, 1000, 4000, 32768, -525, 0x21, 1200, 3, 65535)
    t = p.Telemetry.from_payload(payload, host_time=5.0)
    assert t.t_ms == 123456
    assert t.current_a == pytest.approx(1.0)
    assert t.voltage_v == pytest.approx(4.0)
    assert t.duty == pytest.approx(0.5, abs=1e-4)
    assert t.ambient_c == pytest.approx(-5.25)
    assert t.flags == p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE
    assert t.enabled and not t.latched_faults
    assert t.setpoint_a == pytest.approx(1.2)
    assert (t.crc_errors, t.frame_errors) == (3, 65535)
    assert t.to_payload() == payload
    with pytest.raises(p.ProtocolError):
        p.Telemetry.from_payload(payload[:-1])


def test_fault_text():
    assert p.fault_text(p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE) == ""
    text = p.fault_text(p.Flag.OPEN_WIRE | p.Flag.HOST_TIMEOUT)
    assert "open wire" in text and "host timeout" in text


def test_ack_parse():
    ack = p.Ack.from_payload(b"\x05\x03\x06")
    assert (ack.seq, ack.type, ack.status, ack.status_name) == (5, 3, 6, "CLAMPED")
    with pytest.raises(p.ProtocolError):
        p.Ack.from_payload(b"\x05\x03")
