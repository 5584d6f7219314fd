"""Register maps of real sensors (drivers/sensors/*.toml), the declared schema they are checked
against, and what makes a sample invalid: status errors and out-of-range codes, served by the
Modbus simulator over real TCP. The decoding is checked against the worked examples printed in
the sensors' own manuals (numbers we did not make)."""

from __future__ import annotations

import json
import math
import time

import jsonschema
import pytest

from smabench.drivers.displacement import (
    FLAG_OUT_OF_RANGE,
    FLAG_SENSOR_STATUS,
    FLAGS_INVALID,
    SCHEMA_PATH,
    DisplacementSensor,
    SensorMapError,
    available_maps,
    decode_registers,
    encode_registers,
    load_map,
    parse_map,
)
from smabench.drivers.modbus_sim import SensorServer

RIFTEK = "riftek-rf602-80-50"
BAUMER = "baumer-om20-om30-rs485"
REAL = (RIFTEK, BAUMER)
T = 0.5  # per-request timeout: generous, a loaded machine must not fail these

pytestmark = pytest.mark.timeout(60)


def test_every_shipped_map_follows_the_declared_schema():
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.validators.validator_for(schema).check_schema(schema)
    import tomllib

    for name in available_maps():
        path = load_map(name).source
        with open(path, "rb") as fh:
            jsonschema.validate(tomllib.load(fh), schema)  # the schema alone accepts it


def test_real_maps_name_their_document_and_the_examples_say_so():
    assert set(REAL) <= set(available_maps())
    for name in available_maps():
        m = load_map(name)
        if name in REAL:
            assert not m.example and m.document and m.section, name
        else:
            assert m.example and name.startswith("generic-"), name


def test_riftek_scaling_matches_the_manual_example():
    """RF602 manual §11.7.8 example 3: range 50 mm, D = 677 (02A5h) → X = 2.066 mm."""
    m = load_map(RIFTEK)
    assert m.position.decode([0x02A5]) == pytest.approx(2.066, abs=5e-4)
    assert m.position.decode([0x4000]) == pytest.approx(50.0)  # 4000h = the full range
    assert (m.function, m.line.baudrate, m.line.parity) == (4, 9600, "E")  # §11.3, §11.6.3
    assert [(w.address, w.values) for w in m.on_connect] == [(10, (1,)), (15, (1,))]
    assert m.position.invalid_reason(16385) and not m.position.invalid_reason(16384)


def test_baumer_float_word_order_matches_the_manual_example():
    """OM20/OM30 manual §7.2 (p. 23): 202 = 7C37h, 203 = 428Bh is 69.743 mm (low word first)."""
    m = load_map(BAUMER)
    assert m.position.decode([0x7C37, 0x428B]) == pytest.approx(69.743, abs=5e-4)
    assert m.blocks() == [(200, 13, [m.quantities["status"], m.position])]  # read whole
    assert m.position.invalid_reason(math.nan)
    assert m.quantities["status"].status_error(2) and not m.quantities["status"].status_error(1)


@pytest.mark.parametrize(
    ("word_order", "byte_order", "regs"),
    [
        ("big", "big", [0x1234, 0x5678]),  # ABCD
        ("little", "big", [0x5678, 0x1234]),  # CDAB
        ("big", "little", [0x3412, 0x7856]),  # BADC
        ("little", "little", [0x7856, 0x3412]),  # DCBA
    ],
)
def test_word_and_byte_order(word_order, byte_order, regs):
    assert encode_registers(0x12345678, "uint32", word_order, byte_order) == regs
    assert decode_registers(regs, "uint32", word_order, byte_order) == 0x12345678


@pytest.mark.parametrize("name", REAL)
def test_real_map_served_read_and_configured(name):
    """The simulator serves the map; connecting checks the identity registers and writes the
    configuration; a status error or an out-of-range code gives an invalid sample (NaN)."""
    m = load_map(name)
    with SensorServer(name, tcp_port=0) as srv:
        srv.set_position_mm(12.5)
        with DisplacementSensor(m, srv.tcp_spec, timeout_s=T) as s:
            assert srv.writes == [(w.address, list(w.values)) for w in m.on_connect]
            sample = s.read()
            assert sample.ok and sample.position_mm == pytest.approx(12.5, abs=m.position.scale)
            srv.serve_sentinel(count=1)
            bad = s.read()
            assert bad.flags & FLAG_OUT_OF_RANGE and not bad.ok and math.isnan(bad.position_mm)
            assert "position raw value" in bad.error
            assert s.read().ok  # the fault was for one request
            if "status" in m.quantities:
                srv.serve_status_error(count=2)
                for _ in range(2):
                    bad = s.read()
                    assert bad.flags & FLAG_SENSOR_STATUS and math.isnan(bad.position_mm)
                    assert bad.flags & FLAGS_INVALID
                assert s.read().ok
            assert s.stats["invalid"] == 1 + 2 * ("status" in m.quantities)
            assert srv.requests >= 4


def test_wrong_model_is_refused_at_connect():
    """A sensor whose range register says 25 mm is not the 50 mm sensor the scale is for."""
    with SensorServer(RIFTEK, tcp_port=0) as srv:
        srv.set_registers(5, [25])
        s = DisplacementSensor(RIFTEK, srv.tcp_spec, timeout_s=T)
        with pytest.raises(SensorMapError, match="register 5 reads 25.*expects 50"):
            s.connect()
        assert not s.connected
        assert srv.writes == []  # nothing written to a sensor the map does not fit


def test_on_connect_writes_are_redone_after_a_reconnect():
    with (
        SensorServer(BAUMER, tcp_port=0) as srv,
        DisplacementSensor(BAUMER, srv.tcp_spec, timeout_s=T, reconnect_interval_s=0) as s,
    ):
        assert s.read().ok
        srv.stop()
        assert not s.read_or_flag().ok
        srv.start()
        deadline = time.monotonic() + 10
        while not s.read_or_flag().ok:
            assert time.monotonic() < deadline, "no reconnect"
        assert srv.writes == [(800, [0]), (800, [0])]


def test_adapter_latency_delays_every_answer():
    """An FTDI adapter's latency timer holds each answer (here 30 ms): the read cannot be
    faster than that (a lower bound: true on any machine)."""
    with (
        SensorServer(BAUMER, tcp_port=0, adapter_latency_s=0.03) as srv,
        DisplacementSensor(BAUMER, srv.tcp_spec, timeout_s=T) as s,
    ):
        lat = [s.read().latency_s for _ in range(3)]
    assert min(lat) >= 0.03
    with pytest.raises(ValueError, match="adapter latency"):
        SensorServer(BAUMER, adapter_latency_s=2.0)


GOOD = {"registers": {"position": {"address": 0, "type": "int32", "scale": 0.001}}}


@pytest.mark.parametrize(
    ("patch", "where", "words"),
    [
        ({"position": {"address": 0, "type": "int32", "scale": math.nan}},
         "[registers.position].scale", "finite"),
        ({"position": {"address": 0, "type": "uint16", "valid_range": [9, 1]}},
         "[registers.position].valid_range", "low end above high end"),
        ({"position": {"address": 0, "type": "uint16", "byte_order": "middle"}},
         "[registers.position].byte_order", "bad value"),
        ({"position": {"address": 0, "type": "float32"},
          "status": {"address": 1, "type": "uint16", "error_values": [2]}},
         "[registers.status].address", "overlaps"),
        ({"position": {"address": 0, "type": "uint16", "scale": 0}},
         "[registers.position].scale", "must not be 0"),
    ],
)
def test_schema_errors_name_the_key(patch, where, words):
    with pytest.raises(SensorMapError) as info:
        parse_map({"registers": patch}, source="x.toml")
    assert "x.toml" in str(info.value) and where in str(info.value)
    assert words in str(info.value)


def test_blocks_and_writes_are_checked():
    with pytest.raises(SensorMapError, match=r"\[registers.position\].address: not inside"):
        parse_map({**GOOD, "block": [{"address": 10, "count": 2}]})
    with pytest.raises(SensorMapError, match=r"\[\[on_connect\]\] #1: missing.*|description"):
        parse_map({**GOOD, "on_connect": [{"address": 3, "values": [1]}]})
    with pytest.raises(SensorMapError, match=r"\[\[check\]\] #1.expect"):
        parse_map({**GOOD, "check": [{"address": 3, "expect": 70000, "description": "x"}]})


def test_latency_timer_of_the_adapter_is_read_and_warned_about(tmp_path, monkeypatch, caplog):
    """The driver reads the FTDI latency timer from sysfs (here a stand-in folder) and warns
    when it is above 1 ms; a port without one (a pty, another chip) gives None."""
    import smabench.drivers.displacement as d

    (tmp_path / "ttyUSB7").mkdir()
    (tmp_path / "ttyUSB7" / "latency_timer").write_text("16\n")
    monkeypatch.setattr(d, "LATENCY_TIMER_SYSFS", str(tmp_path / "{tty}" / "latency_timer"))
    link = tmp_path / "by-id-adapter"
    link.symlink_to(tmp_path / "ttyUSB7")  # /dev/serial/by-id/… style names are followed
    assert d.adapter_latency_ms(str(link)) == 16
    assert d.adapter_latency_ms("/dev/pts/0") is None
    s = DisplacementSensor(BAUMER, f"rtu:{tmp_path / 'ttyUSB7'}", timeout_s=T)
    with (
        caplog.at_level("WARNING", logger="smabench.drivers.displacement"),
        pytest.raises(d.SensorLinkLost),
    ):
        s.connect()  # not a serial port: the connect fails, after the check
    assert any("latency timer is 16 ms" in r.getMessage() for r in caplog.records)


def test_a_position_outside_the_sensor_range_is_served_as_out_of_range():
    """The plant can move the slider where a real sensor cannot measure (below 0 on the RF602):
    the simulator then serves the map's out-of-range code, not a failing device."""
    with SensorServer(RIFTEK, tcp_port=0) as srv:
        srv.set_source("position", lambda: -1.0)
        with DisplacementSensor(RIFTEK, srv.tcp_spec, timeout_s=T) as s:
            sample = s.read()
        assert sample.flags == FLAG_OUT_OF_RANGE and math.isnan(sample.position_mm)


@pytest.mark.slow  # a mock bench process: about 6 s on a loaded machine
def test_mock_bench_serves_the_chosen_map_behind_an_adapter_latency():
    """`smabench mock --sensor-map … --adapter-latency-ms …` end to end (its own process), with
    the fault injection of its control input."""
    from smabench.bench.headless import MockProcess

    with (
        MockProcess(["--sensor-map", BAUMER, "--adapter-latency-ms", "30"]) as mock,
        DisplacementSensor(BAUMER, mock.ports.sensor_tcp, timeout_s=T) as s,
    ):
        sample = s.read()
        assert sample.ok and sample.latency_s >= 0.03
        mock.send("sensor-status-error 1000")
        deadline = time.monotonic() + 10
        while not s.read().flags & FLAG_SENSOR_STATUS:
            assert time.monotonic() < deadline, "status error never served"
