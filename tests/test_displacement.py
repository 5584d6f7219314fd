"""Modbus displacement sensor driver against a real pymodbus server (TCP and RTU over socat)."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from smabench.drivers.base import (
    FLAG_EXCEPTION,
    FLAG_FRAMING,
    FLAG_LINK_LOST,
    FLAG_RETRIED,
    FLAG_SENSOR_STATUS,
    FLAG_TIMEOUT,
    Sample,
    SensorException,
    SensorFrameError,
    SensorLinkLost,
    SensorTimeout,
    describe_flags,
)
from smabench.drivers.displacement import (
    DATA_TYPES,
    DisplacementSensor,
    SensorMapError,
    available_maps,
    decode_registers,
    encode_registers,
    load_map,
    parse_map,
    parse_sensor_spec,
)
from smabench.drivers.modbus_sim import SensorServer

pytestmark = pytest.mark.timeout(60)

RS485 = "generic-rs485-laser"
FLOAT32 = "generic-float32-laser"
T = 0.25  # request timeout used in the tests (s): a loaded machine must not make answers late
SLACK_S = 1.5  # `bounded` proves a call does not hang, not how fast it is: room for a busy machine


def poll(fn, deadline_s: float = 10.0):
    """Call ``fn`` until it returns something truthy; fail after ``deadline_s``."""
    end = time.monotonic() + deadline_s
    while True:
        result = fn()
        if result:
            return result
        if time.monotonic() > end:
            raise AssertionError(f"condition not met within {deadline_s} s")
        time.sleep(0.01)


def bounded(fn, limit_s: float):
    """Run ``fn`` and assert it returned or raised within ``limit_s``; returns (result, exc)."""
    t0 = time.monotonic()
    try:
        result, exc = fn(), None
    except Exception as e:  # noqa: BLE001 - returned to the caller to check
        result, exc = None, e
    elapsed = time.monotonic() - t0
    assert elapsed < limit_s + SLACK_S, f"call took {elapsed:.3f} s (limit {limit_s} s + slack)"
    return result, exc


# --------------------------------------------------------------------------------------------
# pure unit tests: encoding, maps, specs
# --------------------------------------------------------------------------------------------

VALUES = {
    "int16": [0, 1, -1, 32767, -32768, 1234],
    "uint16": [0, 1, 65535, 0x1234],
    "int32": [0, 1, -1, 2**31 - 1, -(2**31), 12345678, -987654],
    "uint32": [0, 1, 2**32 - 1, 0x12345678],
    "float32": [0.0, 1.0, -1.5, 12.345, -3.25e-3, 1e30],
}


@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize("dtype", list(DATA_TYPES))
def test_encode_decode_round_trip(dtype, word_order):
    for value in VALUES[dtype]:
        regs = encode_registers(value, dtype, word_order)
        assert len(regs) == DATA_TYPES[dtype][0]
        assert all(0 <= r <= 0xFFFF for r in regs)
        back = decode_registers(regs, dtype, word_order)
        if dtype == "float32":
            assert back == pytest.approx(value, rel=1e-6)
        else:
            assert back == value


def test_register_layout_and_word_order():
    assert encode_registers(0x12345678, "uint32", "big") == [0x1234, 0x5678]
    assert encode_registers(0x12345678, "uint32", "little") == [0x5678, 0x1234]
    assert encode_registers(-2, "int32", "big") == [0xFFFF, 0xFFFE]
    assert encode_registers(1.0, "float32", "big") == [0x3F80, 0x0000]
    assert encode_registers(1.0, "float32", "little") == [0x0000, 0x3F80]
    assert encode_registers(-1, "int16") == [0xFFFF]
    assert decode_registers([0xFFFF], "int16") == -1
    assert decode_registers([0xFFFF], "uint16") == 0xFFFF
    # word order is irrelevant for one-register types
    assert encode_registers(0x1234, "uint16", "little") == [0x1234]


def test_encoding_errors():
    with pytest.raises(ValueError, match="does not fit int16"):
        encode_registers(40000, "int16")
    with pytest.raises(ValueError, match="does not fit uint32"):
        encode_registers(-1, "uint32")
    with pytest.raises(ValueError, match="unknown data type"):
        encode_registers(1, "int64")
    with pytest.raises(ValueError, match="word order"):
        encode_registers(1, "int32", "middle")
    with pytest.raises(ValueError, match="needs 2 register"):
        decode_registers([1], "float32")


def test_shipped_maps_load_and_scale():
    names = available_maps()
    assert RS485 in names and FLOAT32 in names
    for name in names:
        m = load_map(name)
        assert m.position.units == "mm"
        assert len(m.blocks()) == 1  # every shipped map reads in one request
    m = load_map(RS485)
    assert (m.unit_id, m.function, m.position.dtype) == (1, 3, "int32")
    assert m.encode("position", 12.345) == {0: 0, 1: 12345}
    assert m.position.decode([0xFFFF, 0xFFFF]) == pytest.approx(-0.001)
    f = load_map(FLOAT32)
    assert f.function == 4 and f.position.word_order == "little"
    assert f.quantities["temperature"].decode(f.quantities["temperature"].encode(23.4)) == (
        pytest.approx(23.4)
    )
    # a path works as well as a name
    assert load_map(Path(m.source)).name == m.name


def test_blocks_split_where_not_contiguous():
    m = parse_map({"registers": {
        "position": {"address": 10, "type": "float32"},
        "temperature": {"address": 12, "type": "int16"},
        "status": {"address": 20, "type": "uint16"},
    }})
    assert [(s, c, [q.name for q in qs]) for s, c, qs in m.blocks()] == [
        (10, 3, ["position", "temperature"]), (20, 1, ["status"])]


GOOD = """
[sensor]
unit_id = 1
[registers.position]
address = 0
type = "int32"
scale = 0.001
"""


@pytest.mark.parametrize(
    ("text", "key", "words"),
    [
        (GOOD.replace('"int32"', '"int64"'), "[registers.position].type", "unknown data type"),
        (GOOD + 'word_order = "middle"\n', "[registers.position].word_order", "bad value 'middle'"),
        (GOOD.replace("address = 0\n", ""), "[registers.position].address", "missing"),
        (GOOD.replace('type = "int32"\n', ""), "[registers.position].type", "missing"),
        ("[sensor]\nunit_id = 1\n", "[registers]", "missing"),
        ("[registers.status]\naddress = 0\ntype = \"uint16\"\n", "[registers.position]",
         "missing"),
        (GOOD + "colour = 3\n", "[registers.position].colour", "unknown key"),
        (GOOD + "[registers.speed]\naddress = 9\ntype = \"int16\"\n", "[registers.speed]",
         "unknown quantity"),
        (GOOD + "[registers.status]\naddress = 1\ntype = \"uint16\"\n",
         "[registers.status].address", "overlaps"),
        (GOOD.replace("unit_id = 1", "function = 6"), "[sensor].function", "expected one of 3, 4"),
        (GOOD + 'units = "um"\n', "[registers.position].units", "'mm'"),
        (GOOD + "[line]\ntimeout_s = 0\n", "[line].timeout_s", "must be in"),
        (GOOD.replace("unit_id = 1", "unit_id = true"), "[sensor].unit_id", "integer"),
        ("registers = [", "not valid TOML", ""),
    ],
)
def test_map_validation_errors_name_file_and_key(tmp_path, text, key, words):
    path = tmp_path / "broken.toml"
    path.write_text(text)
    with pytest.raises(SensorMapError) as info:
        load_map(path)
    msg = str(info.value)
    assert str(path) in msg and key in msg and words in msg


def test_missing_map_lists_shipped_maps():
    with pytest.raises(SensorMapError, match=RS485):
        load_map("no-such-sensor")


def test_parse_sensor_spec():
    s = parse_sensor_spec("tcp:192.168.0.7:1502")
    assert (s.kind, s.host, s.port) == ("tcp", "192.168.0.7", 1502)
    assert parse_sensor_spec("tcp:sensor.local").port == 502
    assert parse_sensor_spec("tcp:[::1]:5020").host == "::1"
    assert str(parse_sensor_spec("tcp:[::1]:5020")) == "tcp:[::1]:5020"
    r = parse_sensor_spec("rtu:/dev/ttyUSB0")
    assert (r.kind, r.device, r.baudrate) == ("rtu", "/dev/ttyUSB0", None)
    r = parse_sensor_spec("rtu:/dev/ttyUSB0:9600:8E1")
    assert (r.device, r.baudrate, r.bytesize, r.parity, r.stopbits) == (
        "/dev/ttyUSB0", 9600, 8, "E", 1)
    assert parse_sensor_spec("RTU:/tmp/x/B:115200").baudrate == 115200
    for bad in ["", "tcp", "udp:host:1", "tcp::502", "tcp:host:0", "tcp:host:http",
                "tcp:::1:502", "rtu:", "rtu::9600"]:
        with pytest.raises(ValueError, match="sensor spec"):
            parse_sensor_spec(bad)


def test_flags_and_sample():
    assert describe_flags(0) == ""
    assert describe_flags(FLAG_TIMEOUT | FLAG_RETRIED) == "timeout|retried"
    assert not Sample(math.nan, 0.0, FLAG_SENSOR_STATUS).ok  # a status error is no position
    assert Sample(1.0, 0.0, FLAG_RETRIED).ok
    assert not Sample(math.nan, 0.0, FLAG_LINK_LOST).ok
    assert len({FLAG_TIMEOUT, FLAG_EXCEPTION, FLAG_LINK_LOST, FLAG_FRAMING, FLAG_SENSOR_STATUS,
                FLAG_RETRIED}) == 6


# --------------------------------------------------------------------------------------------
# TCP against a real pymodbus server
# --------------------------------------------------------------------------------------------


@pytest.fixture
def tcp_server():
    srv = SensorServer(RS485, tcp_port=0).start()
    yield srv
    srv.stop()
    assert not srv.running


def sensor_for(srv: SensorServer, **kw) -> DisplacementSensor:
    kw.setdefault("timeout_s", T)
    kw.setdefault("reconnect_interval_s", 0.0)
    return DisplacementSensor(srv.sensor_map, srv.tcp_spec, **kw)


def test_tcp_read_position_and_status(tcp_server):
    tcp_server.set_position_mm(12.345)
    with sensor_for(tcp_server) as s:
        assert s.connected
        t0 = time.monotonic()
        sample = s.read()
        assert sample.position_mm == pytest.approx(12.345, abs=1e-9)
        assert sample.flags == 0 and sample.ok and sample.status == 0
        assert t0 <= sample.t_s <= time.monotonic()
        assert 0 < sample.latency_s < T
        tcp_server.set_position_mm(-0.5)
        assert s.read().position_mm == pytest.approx(-0.5)
        # a status word with an error bit makes the sample invalid: no position at all
        tcp_server.set_status(0x0001)
        sample = s.read()
        assert sample.flags == FLAG_SENSOR_STATUS and not sample.ok and sample.status == 1
        assert math.isnan(sample.position_mm) and "status 0x0001" in sample.error
        tcp_server.set_status(0x0100)  # not in error_mask
        assert s.read().flags == 0
        assert tcp_server.requests == 4  # one request per read: the map is contiguous
    assert not s.connected


def test_tcp_float32_input_registers():
    with SensorServer(FLOAT32, tcp_port=0) as srv:
        srv.set_position_mm(7.125)
        srv.set_value("temperature", 31.7)
        with sensor_for(srv) as s:
            before = srv.requests
            sample = s.read()
            assert sample.position_mm == pytest.approx(7.125)
            assert sample.temperature_c == pytest.approx(31.7)
            assert srv.requests - before == 1  # position+temperature+status in one request


def test_tcp_value_source_is_asked_at_every_request(tcp_server):
    calls = []

    def source():
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("plant crashed")
        return 0.5 * len(calls)

    tcp_server.set_source("position", source)
    with sensor_for(tcp_server) as s:
        assert s.read().position_mm == pytest.approx(0.5)
        assert s.read().position_mm == pytest.approx(1.0)
        with pytest.raises(SensorException) as info:
            s.read()
        assert info.value.code == 4
        tcp_server.set_source("position", None)
        assert s.read().position_mm == pytest.approx(1.0)  # last value stays
    with pytest.raises(KeyError):
        tcp_server.set_source("temperature", source)  # not in this map


@pytest.mark.slow  # real request timeouts: about a second or more on a busy machine
def test_tcp_timeout_is_bounded_and_flagged(tcp_server):
    tcp_server.set_position_mm(3.0)
    with sensor_for(tcp_server, retries=1) as s:
        assert s.read().position_mm == pytest.approx(3.0)
        tcp_server.delay_responses(1.0)  # every answer late
        _, exc = bounded(s.read, limit_s=2 * T + 0.2)
        assert isinstance(exc, SensorTimeout)
        sample, _ = bounded(s.read_or_flag, limit_s=2 * T + 0.2)
        assert math.isnan(sample.position_mm) and sample.flags == FLAG_TIMEOUT
        assert not sample.ok and "no response" in sample.error
        tcp_server.clear_faults()
        assert poll(lambda: s.read_or_flag().ok)
        assert s.read().position_mm == pytest.approx(3.0)
        assert s.stats["timeouts"] >= 2


def test_tcp_one_late_answer_is_retried(tcp_server):
    tcp_server.set_position_mm(4.0)
    with sensor_for(tcp_server, retries=1) as s:
        tcp_server.delay_responses(1.0, count=1)
        sample = s.read()
        assert sample.position_mm == pytest.approx(4.0)
        assert sample.flags == FLAG_RETRIED and sample.ok
        assert s.read().flags == 0


def test_tcp_no_retries_means_one_attempt(tcp_server):
    with sensor_for(tcp_server, retries=0) as s:
        tcp_server.delay_responses(1.0, count=1)
        _, exc = bounded(s.read, limit_s=T + 0.15)
        assert isinstance(exc, SensorTimeout)
        assert s.read().ok


def test_tcp_exception_response(tcp_server):
    with sensor_for(tcp_server) as s:
        tcp_server.fail_with_exception(code=6, count=1)
        with pytest.raises(SensorException) as info:
            s.read()
        assert info.value.code == 6 and "device busy" in str(info.value)
        tcp_server.fail_with_exception(code=4, count=1)
        sample = s.read_or_flag()
        assert math.isnan(sample.position_mm) and sample.flags == FLAG_EXCEPTION
        assert s.read().ok  # the link survives exception responses
        # an address the sensor does not have
        with pytest.raises(SensorException) as info:
            s.read_registers(50, 2)
        assert info.value.code == 2
        assert s.read_registers(0, 3) == [0, 0, 0]


def test_tcp_map_mismatches_surface_as_exceptions(tcp_server):
    wrong_address = parse_map({"registers": {"position": {"address": 40, "type": "int32"}}})
    with DisplacementSensor(wrong_address, tcp_server.tcp_spec, timeout_s=T) as s:
        with pytest.raises(SensorException) as info:
            s.read()
        assert info.value.code == 2
    wrong_function = parse_map({"sensor": {"function": 4},
                                "registers": {"position": {"address": 0, "type": "int32"}}})
    with DisplacementSensor(wrong_function, tcp_server.tcp_spec, timeout_s=T) as s:
        with pytest.raises(SensorException) as info:
            s.read()
        assert info.value.code == 1


@pytest.mark.slow  # real request timeouts: about a second or more on a busy machine
def test_tcp_garbled_answer_is_a_frame_error(tcp_server):
    tcp_server.set_position_mm(1.5)
    with sensor_for(tcp_server, retries=1) as s:
        tcp_server.corrupt_responses(count=2)
        _, exc = bounded(s.read, limit_s=2 * T + 0.2)
        assert isinstance(exc, SensorFrameError)
        tcp_server.corrupt_responses(count=1)
        sample = s.read_or_flag()
        assert sample.flags == FLAG_RETRIED and sample.position_mm == pytest.approx(1.5)
        tcp_server.corrupt_responses(count=2)
        sample = s.read_or_flag()
        assert sample.flags == FLAG_FRAMING and math.isnan(sample.position_mm)
        assert s.read().ok


def test_tcp_server_dies_and_comes_back(tcp_server):
    tcp_server.set_position_mm(2.5)
    s = sensor_for(tcp_server, reconnect_interval_s=0.05)
    s.connect()
    assert s.read().ok
    tcp_server.stop()
    _, exc = bounded(s.read, limit_s=2 * T + 0.5)
    assert isinstance(exc, SensorLinkLost)
    samples = [bounded(s.read_or_flag, limit_s=2 * T + 0.5)[0] for _ in range(5)]
    assert all(math.isnan(x.position_mm) and x.flags == FLAG_LINK_LOST for x in samples)
    assert not s.connected
    tcp_server.start()  # same port
    tcp_server.set_position_mm(2.75)
    sample = poll(lambda: (x := s.read_or_flag()).ok and x)
    assert sample.position_mm == pytest.approx(2.75)
    assert s.connected and s.stats["connects"] >= 2
    s.make_safe()
    assert not s.connected


def test_unreachable_sensor_and_make_safe():
    with SensorServer(RS485, tcp_port=0) as srv:
        spec = srv.tcp_spec  # a port that is certainly closed once the server stops
    s = DisplacementSensor(RS485, spec, timeout_s=T, reconnect_interval_s=10.0)
    _, exc = bounded(s.connect, limit_s=T + 0.5)
    assert isinstance(exc, SensorLinkLost) and "cannot connect" in str(exc)
    # within reconnect_interval_s reads fail at once without touching the network
    sample, _ = bounded(s.read_or_flag, limit_s=0.05)
    assert sample.flags == FLAG_LINK_LOST and "down" in sample.error
    s.make_safe()
    s.make_safe()
    s.close()


def test_server_stop_leaves_no_thread():
    srv = SensorServer(RS485, tcp_port=0)
    for _ in range(2):
        srv.start()
        with sensor_for(srv) as s:
            assert s.read().ok
        srv.stop()
    assert not any(t.name == "modbus-sim" and t.is_alive() for t in threading.enumerate())


# --------------------------------------------------------------------------------------------
# RTU over a socat pty pair
# --------------------------------------------------------------------------------------------


@pytest.fixture
def pty_pair(tmp_path):
    if not shutil.which("socat"):
        pytest.skip("socat not installed")
    a, b = tmp_path / "A", tmp_path / "B"
    proc = subprocess.Popen(
        ["socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        poll(lambda: a.exists() and b.exists())
        yield proc, str(a), str(b)
    finally:
        proc.terminate()
        proc.wait(5)


@pytest.fixture
def rtu_server(pty_pair):
    _, a, b = pty_pair
    srv = SensorServer(RS485, tcp_port=None, serial_port=a, baudrate=115200).start()
    srv.client_port = b
    yield srv
    srv.stop()


def rtu_sensor(srv, sensor_map=RS485, **kw) -> DisplacementSensor:
    kw.setdefault("timeout_s", T)
    kw.setdefault("reconnect_interval_s", 0.0)
    return DisplacementSensor(sensor_map, f"rtu:{srv.client_port}:115200", **kw)


def test_rtu_read(rtu_server):
    rtu_server.set_position_mm(-12.5)
    with rtu_sensor(rtu_server) as s:
        sample = s.read()
        assert sample.position_mm == pytest.approx(-12.5) and sample.ok
        assert 0 < sample.latency_s < T
        rtu_server.set_position_mm(48.001)
        assert s.read().position_mm == pytest.approx(48.001)


def test_rtu_float32(pty_pair):
    _, a, b = pty_pair
    with SensorServer(FLOAT32, tcp_port=None, serial_port=a) as srv:
        srv.set_position_mm(-3.25)
        srv.set_value("temperature", -5.5)
        srv.set_status(1)
        with DisplacementSensor(FLOAT32, f"rtu:{b}", timeout_s=T) as s:
            sample = s.read()
            assert math.isnan(sample.position_mm)  # status bit 0: measurement invalid
            assert sample.temperature_c == pytest.approx(-5.5)
            assert sample.flags == FLAG_SENSOR_STATUS
            srv.set_status(0)
            sample = s.read()
            assert sample.position_mm == pytest.approx(-3.25) and sample.ok


@pytest.mark.slow  # real request timeouts: about a second or more on a busy machine
def test_rtu_bad_crc_timeout_and_exception(rtu_server):
    t = 0.5  # a generous timeout: a loaded machine must not turn a good answer into a late one
    rtu_server.set_position_mm(1.0)
    with rtu_sensor(rtu_server, retries=1, timeout_s=t) as s:
        rtu_server.corrupt_responses(count=2)
        _, exc = bounded(s.read, limit_s=2 * t + 1.0)
        assert isinstance(exc, SensorFrameError)
        assert s.read().ok
        rtu_server.corrupt_responses(count=1)
        assert s.read().flags == FLAG_RETRIED
        rtu_server.delay_responses(3 * t, count=2)
        sample, _ = bounded(s.read_or_flag, limit_s=2 * t + 1.0)
        assert sample.flags == FLAG_TIMEOUT and math.isnan(sample.position_mm)
        # the late answers must not be mistaken for the next one
        rtu_server.set_position_mm(2.0)
        assert poll(lambda: (x := s.read_or_flag()).ok and x).position_mm == pytest.approx(2.0)
        rtu_server.fail_with_exception(code=4, count=1)
        with pytest.raises(SensorException) as info:
            s.read()
        assert info.value.code == 4
        with pytest.raises(SensorException) as info:
            s.read_registers(7, 1)
        assert info.value.code == 2
        assert s.read().position_mm == pytest.approx(2.0)


@pytest.mark.slow  # a server process restarted: about a second or more on a busy machine
def test_rtu_server_dies_and_comes_back(rtu_server):
    rtu_server.set_position_mm(5.0)
    t = 0.5  # pty, socat and a server thread between: room for a loaded machine
    with rtu_sensor(rtu_server, retries=1, timeout_s=t) as s:
        assert s.read().ok
        rtu_server.stop()  # the line stays, nobody answers
        samples = [bounded(s.read_or_flag, limit_s=2 * t + 0.3)[0] for _ in range(3)]
        assert all(x.flags == FLAG_TIMEOUT for x in samples), [x.flags for x in samples]
        rtu_server.start()
        assert poll(lambda: (x := s.read_or_flag()).ok and x).position_mm == pytest.approx(5.0)


def test_rtu_port_vanishes_and_comes_back(tmp_path):
    if not shutil.which("socat"):
        pytest.skip("socat not installed")
    a, b = tmp_path / "A", tmp_path / "B"

    def socat():
        proc = subprocess.Popen(
            ["socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        poll(lambda: a.exists() and b.exists())
        return proc

    proc = socat()
    srv = SensorServer(RS485, tcp_port=None, serial_port=str(a)).start()
    srv.set_position_mm(9.0)
    s = DisplacementSensor(RS485, f"rtu:{b}:115200", timeout_s=T, reconnect_interval_s=0.0)
    try:
        assert s.read().ok
        srv.stop()
        proc.terminate()
        proc.wait(5)
        poll(lambda: not os.path.exists(b))
        flagged = [bounded(s.read_or_flag, limit_s=2 * T + 0.5)[0] for _ in range(3)]
        assert all(math.isnan(x.position_mm) for x in flagged)
        assert flagged[-1].flags == FLAG_LINK_LOST  # the port is gone: cannot reopen
        proc = socat()
        srv.start()
        assert poll(lambda: (x := s.read_or_flag()).ok and x).position_mm == pytest.approx(9.0)
    finally:
        s.make_safe()
        srv.stop()
        proc.terminate()
        proc.wait(5)
