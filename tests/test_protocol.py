"""Current-driver protocol codec (drivers/protocol.py) vs PROTOCOL.md and the shared vectors."""

from __future__ import annotations

import contextlib
import math
import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from smabench.drivers import protocol as p
from smabench.hardware import ELECTRICAL

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
    assert info == p.DeviceInfo(4, (4, 0, 0), 2.5, "SMA-CD328")
    assert info.firmware == "4.0.0"
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
        p.MsgType.SET_LEASE: 2,
        p.MsgType.SET_CALIBRATION: 8,
        p.MsgType.GET_CALIBRATION: 0,
        p.MsgType.SET_HEAT_MODEL: 8,
        p.MsgType.GET_HEAT_MODEL: 0,
        p.MsgType.SET_PROBE: 2,
    }
    assert {t: c.size for t, c in p.COMMANDS.items()} == sizes


def test_command_table_matches_firmware_header():
    """proto.h and the codec name the same types, status codes, flags and sizes."""
    text = (REPO / "firmware/core/proto.h").read_text()
    defs = {}
    for line in text.splitlines():
        tok = line.split()
        if len(tok) >= 3 and tok[0] == "#define" and tok[2].rstrip("u").isalnum():
            with contextlib.suppress(ValueError):
                defs[tok[1]] = int(tok[2].rstrip("u"), 0)
    assert defs["PROTOCOL_VERSION"] == p.PROTOCOL_VERSION
    assert defs["TELEMETRY_LEN"] == p.TELEMETRY_LEN
    for t in p.MsgType:
        assert defs[f"MSG_{t.name}"] == t.value, t
    for st in p.Status:
        assert defs[f"ST_{st.name}"] == st.value, st
    for f in p.Flag:
        assert defs[f"FLAG_{f.name}"] == f.value, f
    for b in p.TcStatus:
        assert defs[f"TC_{b.name}"] == b.value, b
    assert defs["LEASE_DEFAULT_MS"] == round(p.LEASE_DEFAULT_S * 1000)
    assert defs["CUT_STARTUP_MS"] == round(p.CUT_STARTUP_S * 1000)
    assert defs["CAL_LEN"] == p.COMMANDS[p.MsgType.SET_CALIBRATION].size
    assert defs["PROBE_MAX_MA"] == round(p.PROBE_MAX_A * 1000)


def test_unit_builders():
    M = p.MsgType
    assert p.identify() == (M.IDENTIFY, b"\x04")
    assert p.enable(True) == (M.ENABLE, b"\x01")
    assert p.enable(False) == (M.ENABLE, b"\x00")
    assert p.set_current(1.0) == (M.SET_CURRENT, b"\xe8\x03")
    assert p.set_current(0.0004) == (M.SET_CURRENT, b"\x00\x00")
    assert p.set_limits(2.5, 0.25) == (M.SET_LIMITS, b"\xc4\x09\xfa\x00")
    assert p.set_telemetry(0.01) == (M.SET_TELEMETRY, b"\x0a\x00")
    assert p.set_telemetry(0) == (M.SET_TELEMETRY, b"\x00\x00")
    assert p.clear_faults() == (M.CLEAR_FAULTS, b"")
    assert p.ping() == (M.PING, b"")
    assert p.set_lease(0.25) == (M.SET_LEASE, b"\xfa\x00")
    assert p.get_calibration() == (M.GET_CALIBRATION, b"")
    assert p.get_heat_model() == (M.GET_HEAT_MODEL, b"")
    assert p.set_probe(0.05) == (M.SET_PROBE, b"\x32\x00")
    assert p.set_probe(0.1) == (M.SET_PROBE, b"\x64\x00")
    assert p.set_probe(0) == (M.SET_PROBE, b"\x00\x00")
    for bad in (
        lambda: p.set_lease(0.019),
        lambda: p.set_lease(5.001),
        lambda: p.set_current(-0.1),
        lambda: p.set_limits(3.0, 0.25),
        lambda: p.set_limits(1.0, 0.01),
        lambda: p.set_telemetry(0.001),
        lambda: p.set_telemetry(2.0),
        lambda: p.set_probe(0.101),
        lambda: p.set_probe(-0.001),
        lambda: p.set_probe(math.nan),
    ):
        with pytest.raises(ValueError):
            bad()
    with pytest.raises(TypeError):
        p.command_payload(M.SET_LIMITS, 1)


def test_set_probe_frame_bytes():
    """SET_PROBE (protocol 4) byte for byte: seq 31, type 0x0D, u16 probe current in mA."""
    packet = bytes((31, 0x0D, 50, 0))  # 50 mA
    crc = crc_bitwise(packet)
    assert crc == 0x6A2F
    assert p.build_packet(31, p.MsgType.SET_PROBE, p.set_probe(0.05)[1]) == packet + b"\x2f\x6a"
    # COBS: 1f 0d 32 | 00 | 2f 6a -> 04 1f 0d 32 03 2f 6a, then the delimiter
    frame = bytes.fromhex("041f0d32032f6a00")
    assert p.encode_frame(31, p.MsgType.SET_PROBE, p.set_probe(0.05)[1]) == frame
    assert p.decode_frame(frame) == p.Packet(31, p.MsgType.SET_PROBE, b"\x32\x00")
    good = {v[1]: v for v in GOOD if v[0] == "frames.txt"}
    assert good["set_probe_50ma"][2:] == (31, 0x0D, b"\x32\x00", frame)
    # the device's answers: OK, and OUT_OF_RANGE above 100 mA
    assert p.encode_frame(21, p.MsgType.ACK, p.Ack(31, p.MsgType.SET_PROBE, p.Status.OK)
                          .to_payload()) == good["ack_set_probe_ok"][5]  # fmt: skip
    assert p.Ack.from_payload(good["ack_set_probe_out_of_range"][4]).status == p.Status.OUT_OF_RANGE


def test_telemetry_parse():
    payload = struct.pack(
        "<IHHHhHHHHhhHHB",
        123456, 1000, 4400, 32768, -525, 0x21, 1200, 3, 65535, 6350, 7125, 10003, 4940, 0,
    )  # fmt: skip
    t = p.Telemetry.from_payload(payload, host_time=5.0)
    assert t.t_ms == 123456
    assert t.current_a == pytest.approx(1.0)
    assert t.voltage_v == pytest.approx(0.44)  # 0.1 mV units
    assert t.duty == pytest.approx(0.5, abs=1e-4)
    assert t.ambient_c == pytest.approx(-5.25)
    assert t.flags == p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE
    assert t.enabled and not t.latched_faults
    assert t.setpoint_a == pytest.approx(1.2)
    assert (t.crc_errors, t.frame_errors) == (3, 65535)
    assert t.wire_model_c == pytest.approx(63.5)
    assert t.thermocouple_c == pytest.approx(71.25) and t.temperature_c == t.thermocouple_c
    assert t.precise_current_a == pytest.approx(1.0003)
    assert t.supply_v == pytest.approx(4.94)
    assert t.thermocouple_status == p.TcStatus(0)
    assert t.resistance_ohm == pytest.approx(0.44 / 1.0003)
    assert t.to_payload() == payload
    with pytest.raises(p.ProtocolError):
        p.Telemetry.from_payload(payload[:-1])


def test_telemetry_missing_values_are_nan_not_numbers():
    """An open NTC, no thermocouple and no external ADC decode as nan (never −92 °C or 0 V)."""
    good, _ = load_vectors(VECTOR_DIR / "frames.txt")
    (_, _, _, payload, _) = next(v for v in good if v[0] == "telemetry_sensors_missing")
    raw = struct.unpack("<IHHHhHHHHhhHHB", payload)
    assert raw[2] == p.U16_NONE and raw[4] == p.TEMP_NONE and raw[10] == p.TEMP_NONE
    t = p.Telemetry.from_payload(payload)
    for name in ("voltage_v", "ambient_c", "thermocouple_c", "precise_current_a", "resistance_ohm"):
        assert math.isnan(getattr(t, name)), name
    assert t.flags & p.Flag.NTC_FAULT and t.flags & p.Flag.TC_FAULT
    assert t.thermocouple_status == p.TcStatus.OC
    assert t.wire_model_c == pytest.approx(40.0)
    assert t == p.Telemetry.from_payload(t.to_payload())  # equal by payload, nan and all
    assert t.to_payload() == payload


def test_telemetry_defaults_for_devices_without_the_new_fields():
    t = p.Telemetry(0, 1.0, 0.5, 0.5, 22.0, p.Flag.ENABLED, 1.0, 0, 0)
    back = p.Telemetry.from_payload(t.to_payload())
    assert math.isnan(back.thermocouple_c) and math.isnan(back.wire_model_c)
    assert back.thermocouple_status == p.TcStatus.ABSENT
    assert back == t


def test_calibration_and_heat_model_roundtrip_and_ranges():
    cal = p.Calibration(current_offset_a=-0.0025, current_gain=1 / 1.03, voltage_gain=1.01,
                        voltage_offset_v=-0.004321)
    data = cal.to_data()
    assert struct.unpack("<hHHh", data) == (-2500, round(32768 / 1.03), round(32768 * 1.01),
                                            -4321)  # fmt: skip
    back = p.Calibration.from_data(data)
    assert back.current_offset_a == pytest.approx(-0.0025)
    assert back.voltage_offset_v == pytest.approx(-0.004321)
    assert back.current_gain == pytest.approx(1 / 1.03, abs=1 / 32768)
    assert p.set_calibration(cal) == (p.MsgType.SET_CALIBRATION, data)
    for bad in (
        p.Calibration(current_gain=0.49),
        p.Calibration(voltage_gain=1.51),
        p.Calibration(current_offset_a=0.04),
        p.Calibration(voltage_offset_v=-0.033),
    ):
        with pytest.raises(ValueError):
            bad.to_data()
    heat = p.HeatModel()
    assert struct.unpack("<HHHH", heat.to_data()) == (550, 336, 590, 1800)  # = core.h defaults
    assert p.HeatModel.from_data(heat.to_data()) == heat
    for bad in (
        p.HeatModel(max_temperature_c=29.0),
        p.HeatModel(resistance_ohm=0.01),
        p.HeatModel(heat_capacity_j_per_k=7.0),
        p.HeatModel(conductance_w_per_k=0.0),
    ):
        with pytest.raises(ValueError):
            bad.to_data()


def test_heat_model_defaults_match_firmware():
    text = (REPO / "firmware/core/core.h").read_text()
    want = {"HEAT_DEFAULT_R_MOHM": 550, "HEAT_DEFAULT_C": 336, "HEAT_DEFAULT_G": 590,
            "HEAT_DEFAULT_TMAX_DC": 1800}  # fmt: skip
    for name, value in want.items():
        assert f"#define {name} {value}u" in text, name


def test_fault_text():
    assert p.fault_text(p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE) == ""
    text = p.fault_text(p.Flag.OPEN_WIRE | p.Flag.HOST_TIMEOUT)
    assert "open wire" in text and "host timeout" in text
    text = p.fault_text(p.Flag.LEASE_EXPIRED | p.Flag.OVERTEMP | p.Flag.ESTOP | p.Flag.NTC_FAULT)
    assert all(w in text for w in ("lease", "over-temperature", "e-stop", "NTC"))
    assert p.LATCHED_FAULTS & p.Flag.ESTOP and p.LATCHED_FAULTS & p.Flag.OVERTEMP


def test_ack_parse():
    ack = p.Ack.from_payload(b"\x05\x03\x06")
    assert (ack.seq, ack.type, ack.status, ack.status_name) == (5, 3, 6, "CLAMPED")
    with pytest.raises(p.ProtocolError):
        p.Ack.from_payload(b"\x05\x03")


# ------------------------------------------------------------------ the Python firmware model
class Model:
    """The stand-in firmware (the C core behind drivers/mock/firmware.py) in simulated time."""

    def __init__(self, eeprom: bytearray | None = None, **wire) -> None:
        from smabench.drivers.mock.firmware import Electrical, MockFirmware

        self.fw = MockFirmware(0.0, eeprom=eeprom)
        self.wire = Electrical(**wire)
        self.now = 0.0
        self.seq = 0
        self.fw.tick(0.0, self.wire)

    def cmd(self, type_: int, payload: bytes = b"") -> p.Ack:
        out = self.fw.receive(p.encode_frame(self.seq, type_, payload), self.now)
        self.seq = (self.seq + 1) & 0xFF
        return p.Ack.from_payload(p.decode_frame(out).payload)

    def status(self, *cmd) -> p.Status:
        return p.Status(self.cmd(*cmd).status)

    def run(self, ms: float, step_ms: float = 1.0, every=None) -> None:
        end = self.now + ms
        while self.now < end - 1e-9:
            self.now += step_ms
            if every is not None:
                every(self)
            self.fw.tick(self.now, self.wire)

    @property
    def t(self) -> p.Telemetry:
        return self.fw.telemetry(self.now, self.wire)


def test_model_lease_expires_while_pings_go_on():
    m = Model()
    m.status(*p.set_current(1.0))
    assert m.status(*p.enable(True)) == p.Status.OK
    t_off = None

    def ping(mm: Model) -> None:
        if round(mm.now) % 20 == 0:
            mm.status(*p.ping())

    for _ in range(600):
        m.run(1.0, every=ping)
        if t_off is None and not m.fw.enabled:
            t_off = m.now
    assert t_off == pytest.approx(250, abs=1)
    t = m.t
    assert t.flags & p.Flag.LEASE_EXPIRED and not t.flags & p.Flag.HOST_TIMEOUT
    # ADC code 0 reads as half a count (1.4 mA): the core's rounding of a code k to [k, k+1)
    # off: the fast path reads ADC code 0 as half a count
    assert t.setpoint_a == 0.0 and t.current_a < ELECTRICAL.current_adc_a_per_count
    assert m.fw.current_ma == 0.0
    assert m.status(*p.enable(True)) == p.Status.OK and not m.t.flags & p.Flag.LEASE_EXPIRED
    assert m.status(p.MsgType.SET_LEASE, b"\x13\x00") == p.Status.OUT_OF_RANGE  # 19 ms


def test_model_energy_budget_under_2_5_a_for_60_s():
    """The model trips as the C core does (host tests: first trip at 1.62 s), and a wire kinder
    than the model (the bench plant's h = 120, R 0.485 Ω) stays below T_max for 60 s."""
    m = Model(resistance_ohm=0.485)
    m.status(*p.set_limits(2.5, 5.0))
    m.status(*p.set_lease(5.0))
    m.status(*p.set_current(2.5))
    m.status(*p.enable(True))
    c, g = 0.0336, 120 * 2 * math.pi * 0.19e-3 * 0.055
    wire_c, peak, first = 22.0, 22.0, None

    def insist(mm: Model) -> None:
        if round(mm.now) % 100 == 0:
            mm.cmd(*p.set_current(2.5))
            if mm.fw.flags & p.Flag.OVERTEMP:
                mm.cmd(*p.clear_faults())
                mm.cmd(*p.enable(True))

    for _ in range(60000 // 10):
        m.run(10.0, step_ms=10.0, every=insist)
        i = m.fw.current_ma / 1000.0
        wire_c += (i * i * 0.485 - g * (wire_c - 22.0)) * 0.01 / c
        peak = max(peak, wire_c)
        if first is None and m.fw.flags & p.Flag.OVERTEMP:
            first = m.now
    assert first is not None and 1000 < first < 2500
    assert 120.0 < peak < 180.0


def test_model_estop_ntc_thermocouple():
    m = Model()
    m.status(*p.set_lease(5.0))
    m.status(*p.set_current(1.0))
    m.status(*p.enable(True))
    m.run(20)
    m.wire.estop = True
    m.run(1)
    assert not m.fw.enabled and m.t.flags & p.Flag.ESTOP
    assert m.status(*p.clear_faults()) == p.Status.FAULT_ACTIVE
    m.wire.estop = False
    m.run(5)
    assert m.t.flags & p.Flag.ESTOP
    assert m.status(*p.clear_faults()) == p.Status.OK and m.status(*p.enable(True)) == p.Status.OK
    for ntc in ("open", "short"):
        m.wire.ntc = ntc
        m.run(150)
        assert math.isnan(m.t.ambient_c) and m.t.flags & p.Flag.NTC_FAULT
    m.wire.ntc = "ok"
    m.run(150)
    assert m.t.ambient_c == pytest.approx(22.0, abs=0.1)  # through the 10-bit NTC divider
    # the thermocouple reports the wire temperature it is given (the plant's), in 0.25 °C
    assert m.t.thermocouple_status == p.TcStatus.ABSENT and math.isnan(m.t.temperature_c)
    m.wire.wire_temperature_c = 61.3
    m.run(150)
    assert m.t.temperature_c == 61.25 and m.t.thermocouple_status == 0
    m.wire.thermocouple_fault = p.TcStatus.SCG
    m.run(150)
    assert math.isnan(m.t.temperature_c) and m.t.flags & p.Flag.TC_FAULT
    m.wire.thermocouple_fault = 0
    m.wire.wire_temperature_c = 181.0  # hotter than T_max: OVERTEMP even with a cool model
    m.run(150)
    assert m.t.flags & p.Flag.OVERTEMP and not m.fw.enabled


def test_model_calibration_and_heat_model_in_eeprom():
    m = Model()
    assert m.t.flags & p.Flag.CAL_DEFAULT
    cal = p.Calibration(current_offset_a=0.002, current_gain=1.02, voltage_gain=0.99)
    assert m.status(*p.set_calibration(cal)) == p.Status.OK
    heat = p.HeatModel(max_temperature_c=120.0)
    assert m.status(*p.set_heat_model(heat)) == p.Status.OK
    assert not m.t.flags & p.Flag.CAL_DEFAULT
    m.status(*p.enable(True))
    assert m.status(*p.set_heat_model(heat)) == p.Status.OUTPUT_ON
    assert m.status(*p.set_calibration(cal)) == p.Status.OUTPUT_ON
    bad = p.COMMANDS[p.MsgType.SET_HEAT_MODEL].pack(550, 336, 590, 299)
    assert m.status(p.MsgType.SET_HEAT_MODEL, bad) == p.Status.OUT_OF_RANGE
    # a reset keeps the EEPROM image
    m2 = Model(eeprom=m.fw.eeprom)
    back = p.Calibration.from_data(m2.cmd(*p.get_calibration()).data)
    assert back.current_gain == pytest.approx(1.02, abs=1 / 32768)
    assert p.HeatModel.from_data(m2.cmd(*p.get_heat_model()).data) == heat
    # a corrupted block reads as defaults, flagged
    m.fw.eeprom[3] ^= 0x10
    m3 = Model(eeprom=m.fw.eeprom)
    assert m3.t.flags & p.Flag.CAL_DEFAULT
    assert p.Calibration.from_data(m3.cmd(*p.get_calibration()).data) == p.Calibration()


def test_model_open_wire_rule():
    m = Model(open_wire=True)
    m.status(*p.set_lease(5.0))
    m.status(*p.set_current(1.0))
    m.status(*p.enable(True))
    m.run(60)
    assert m.t.flags & p.Flag.OPEN_WIRE and not m.fw.enabled
    m2 = Model()
    m2.status(*p.set_lease(5.0))
    m2.status(*p.set_current(0.05))  # below 100 mA: never an open wire
    m2.status(*p.enable(True))
    m2.run(200)
    assert m2.fw.enabled and not m2.t.flags & p.Flag.OPEN_WIRE


def test_model_dissipation_limit_as_the_c_core():
    """2.5 A asked into 0.1 Ω at 5.5 V would put 12 W into the sink's MOSFET: capped at 10 W and
    flagged, as the C core does (host tests: 2.011 A, 10.01 W)."""
    m = Model(resistance_ohm=0.1, supply_v=5.5)
    m.status(*p.set_limits(2.5, 5.0))
    m.status(*p.set_lease(5.0))
    m.status(*p.set_heat_model(p.HeatModel(heat_capacity_j_per_k=6.0)))  # no energy trip here
    m.status(*p.set_current(2.5))
    m.status(*p.enable(True))
    m.run(300)
    i = m.fw.current_ma / 1000.0
    assert m.t.flags & p.Flag.DISSIPATION and m.t.flags & p.Flag.LIMIT_ACTIVE
    assert (5.5 - i * (0.06 + 0.1 + 0.1)) * i == pytest.approx(10.0, abs=0.3)
    m.wire.resistance_ohm = 0.6  # 2.5 A: 5.35 V - 1.5 V - 0.25 V across the MOSFET, 9.6 W
    m.run(300)
    assert not m.t.flags & p.Flag.DISSIPATION and m.fw.current_ma == pytest.approx(2500, abs=10)


# ------------------------------------------------------------------ PROTOCOL.md answers as bytes
ANSWER_FLAGS = p.Flag.ENABLED | p.EVENTS | p.LATCHED_FAULTS | p.Flag.VSENSE_FAULT


def _vector(name: str) -> tuple[int, int, bytes, bytes]:
    good, _ = load_vectors(VECTOR_DIR / "frames.txt")
    return next((seq, type_, payload, frame) for n, seq, type_, payload, frame in good if n == name)


def _answer(name: str, t: p.Telemetry, voltage: bool = False) -> None:
    want = p.Telemetry.from_payload(_vector(name)[2])
    assert t.flags & ANSWER_FLAGS == want.flags & ANSWER_FLAGS, (name, t)
    assert t.setpoint_a == want.setpoint_a, (name, t)
    if voltage:
        assert math.isnan(t.voltage_v) == math.isnan(want.voltage_v), (name, t)


def test_version_mismatch_answer_is_the_vector_byte_for_byte():
    """A version-1 host's IDENTIFY: the core (through the stand-in) answers exactly the vector."""
    from smabench.drivers.mock.firmware import MockFirmware

    out = MockFirmware(0.0).receive(_vector("answer_identify_v1")[3])
    assert out == _vector("answer_ack_identify_v1_mismatch_mock")[3]


def test_lease_answers_are_the_vectors():
    """After LEASE_EXPIRED: off, setpoint 0; ENABLE 1 is accepted at once, at 0 mA."""
    m = Model()
    m.status(*p.set_telemetry(0.01))
    m.status(*p.set_current(1.0))
    m.status(*p.enable(True))
    m.run(260, every=lambda mm: round(mm.now) % 20 == 0 and mm.status(*p.ping()))
    _answer("answer_telemetry_lease_expired", m.t)
    assert m.status(*p.enable(True)) == p.Status.OK
    m.run(20)
    _answer("answer_telemetry_enabled_after_lease", m.t)
    assert m.fw.current_ma == 0.0


def test_the_voltage_goes_out_at_every_frames_current_after_a_step():
    """A 1 A → 0.5 A step into 0.44 Ω: every frame carries the wire voltage at its own current
    (the window's V/I, each conversion paired with the current it saw, times the frame's
    current), the 8-16 ms after the step too: V/I of every frame is the wire's."""
    m = Model(resistance_ohm=0.44)
    m.status(*p.set_lease(5.0))
    m.status(*p.set_current(1.0))
    m.status(*p.enable(True))
    m.run(100)
    m.status(*p.set_current(0.5))
    frames = []
    for _ in range(60):
        m.run(1)
        frames.append(m.t)
    assert not any(math.isnan(t.voltage_v) or t.flags & p.Flag.VSENSE_FAULT for t in frames)
    _answer("answer_telemetry_voltage_after_step", frames[0], voltage=True)
    for t in frames:
        assert t.voltage_v == pytest.approx(0.44 * t.current_a, rel=0.01, abs=0.0002), t


def test_every_command_fits_the_window_and_the_longest_is_the_vector():
    good, _ = load_vectors(VECTOR_DIR / "frames.txt")
    skip = ("unknown", "payload", "seq0")  # frame-layer vectors, not commands
    sizes = {n: len(f) for n, _, t, _, f in good if t < p.MsgType.ACK and not n.startswith(skip)}
    longest = max(sizes, key=sizes.get)
    assert sizes[longest] == len(_vector("answer_longest_command_set_heat_model")[3]) == 14
    assert sizes[longest] <= p.COMMAND_WINDOW_BYTES
    assert len(_vector("answer_ack_identify_v1_mismatch")[3]) == 24  # PROTOCOL.md's longest ACK
