"""Calibration from the app (``smabench calibrate current|wire``, ``smabench sensor tare|read``,
the ``calibration`` block of session.json), against the mock bench's Python firmware and the real
firmware in simavr.

The "meter" is the wire current the device cannot see: the mock's sink current
(``MockFirmware.current_ma``) or the simavr harness's ``STATE current_a``. A known error is put
into the device's measurement by writing a wrong calibration first (the firmware then believes
``(I − offset)·gain``); after ``calibrate current`` the device must report what the meter reads.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import re
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from smabench import calibrate as cal
from smabench import calibration_store
from smabench.cli import main
from smabench.drivers import protocol as p
from smabench.drivers.current_source import CommandRejected, CurrentSource
from smabench.drivers.mock.bench import DEVICE_RT_PRIORITY, MockBench, realtime_child
from smabench.drivers.mock.firmware import Electrical
from smabench.drivers.mock.serial_device import SerialDevice
from smabench.physics.thermal import step_exact
from smabench.physics.wire import PAPER_WIRE

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

REPO = Path(__file__).resolve().parent.parent
SIM = Path(os.environ.get("SMABENCH_SIM", REPO / "firmware/build/sim/smabench-sim"))
ELF = Path(os.environ.get("SMABENCH_ELF", REPO / "firmware/build/avr/smabench-cd.elf"))
WRONG = p.Calibration(current_offset_a=0.006, current_gain=1.04)  # the device reads 4 % high
FAST = ["--settle-s", "0.15", "--average-s", "0.25"]
STEPS_A = (0.2, 1.0, 2.0)
CHECK_A = (0.5, 1.5)


@pytest.fixture(autouse=True)
def store(tmp_path, monkeypatch) -> Path:
    """Every test keeps its calibration file in its own folder (never the user's)."""
    path = tmp_path / "cfg" / "calibration.json"
    monkeypatch.setenv(cal.ENV_STORE, str(path))
    return path


# ----------------------------------------------------------------------------- no device
def test_fit_recovers_a_known_offset_and_gain():
    """Raw readings from a sensor with a known error, under an old calibration: the fit gives
    the calibration that maps raw onto the meter, with zero residuals on a line."""
    meter = np.array([0.2, 0.7, 1.3, 2.0])
    raw = meter / 1.031 + 0.0042  # what the fast path measures: gain and offset error
    old = p.Calibration(0.001, 0.98)
    device = (raw - old.current_offset_a) * old.current_gain  # what the device reported
    fit = cal.fit_current(device, meter, old)
    assert fit.gain == pytest.approx(1.031, rel=1e-9)
    assert fit.offset_a == pytest.approx(0.0042, abs=1e-9)
    assert max(map(abs, fit.residuals_a)) < 1e-9
    noisy = meter + np.array([1e-3, -1e-3, 1e-3, -1e-3])
    fit = cal.fit_current(device, noisy, old)  # least squares: residuals of the noise's size
    assert 0.5e-3 < max(map(abs, fit.residuals_a)) < 1.5e-3
    assert sum(fit.residuals_a) == pytest.approx(0.0, abs=1e-12)


def test_fit_refuses_what_the_device_cannot_take():
    with pytest.raises(cal.CalibrationError, match="gain"):
        cal.fit_current([0.2, 1.0], [0.1, 1.8], p.Calibration())
    with pytest.raises(cal.CalibrationError, match="offset"):
        cal.fit_current([0.2, 1.0], [0.16, 0.96], p.Calibration())


@pytest.mark.parametrize(
    "readings, match",
    [
        ([0.2, 1.0], "2 meter reading"),
        ([0.25, 1.0, 2.0], "more than 20%"),
        ([0.2, 1.0, 1.5], "more than 20%"),
        ([0.2, 1.1, 1.05], r"more than 20%|not rising"),
        ([0.2, 1.0, float("nan")], "more than 20%"),
    ],
)
def test_nonsense_readings_are_refused(readings, match):
    with pytest.raises(cal.CalibrationError, match=match):
        cal.check_readings(STEPS_A, readings)
    cal.check_readings(STEPS_A, [0.21, 0.97, 2.04])


def test_non_monotonic_readings_within_tolerance_are_refused():
    with pytest.raises(cal.CalibrationError, match="not rising"):
        cal.check_readings([1.0, 1.1], [1.08, 1.02])


def test_reading_text():
    assert cal.parse_reading("1.003") == pytest.approx(1.003)
    assert cal.parse_reading(" 1003 mA") == pytest.approx(1.003)
    assert cal.parse_reading("1,003 A") == pytest.approx(1.003)
    with pytest.raises(ValueError):
        cal.parse_reading("one amp")


def test_time_to_trip_is_the_device_heat_model():
    """The closed form against the firmware's heat model integrated in 1 ms steps."""
    model = p.HeatModel()
    t_trip = cal.time_to_trip_s(model, 2.0, 22.0, 22.0)
    temp, t = 22.0, 0.0
    while temp < model.max_temperature_c:
        temp += (4.0 * model.resistance_ohm - model.conductance_w_per_k * (temp - 22.0)) * \
            1e-3 / model.heat_capacity_j_per_k  # fmt: skip
        t += 1e-3
    assert t_trip == pytest.approx(t, abs=2e-3)
    assert 2.5 < t_trip < 4.0  # 2 A on the default model: about 3 s
    assert cal.time_to_trip_s(model, 0.5, 22.0, 22.0) == math.inf
    assert cal.time_to_trip_s(model, 2.0, 200.0, 22.0) == 0.0


def test_store_path_order(tmp_path, monkeypatch):
    monkeypatch.setenv(cal.ENV_STORE, str(tmp_path / "env.json"))
    assert cal.store_path(tmp_path / "arg.json") == tmp_path / "arg.json"
    assert cal.store_path() == tmp_path / "env.json"
    monkeypatch.delenv(cal.ENV_STORE)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    assert cal.store_path() == tmp_path / "xdg" / "smabench" / "calibration.json"


def test_broken_store_is_one_line_and_exit_2(store, capsys):
    store.parent.mkdir(parents=True)
    store.write_text("{not json")
    assert main(["calibrate", "show"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not valid JSON" in err[0]
    assert main(["calibrate", "current", "--port", "/dev/null", "--readings", "0.2,1.0"]) == 2


# ----------------------------------------------------------------------------- mock helpers
@pytest.fixture
def bench():
    # the device thread real-time where allowed, as in `smabench mock`: it stands in for a
    # microcontroller, which a busy host does not slow (its lease and host timeout run on)
    with MockBench(load_kg=1.0, rtu=False, realtime=True) as b:
        yield b


def _physical_a(bench: MockBench) -> float:
    return float(bench.device.call(lambda fw: fw.current_ma)) / 1000.0


def _write(port: str, calibration: p.Calibration) -> None:
    with CurrentSource(port) as cs:
        cs.set_calibration(calibration)
        assert cs.get_calibration() == p.Calibration.from_data(calibration.to_data())


def _read_back(port: str) -> p.Calibration:
    with CurrentSource(port) as cs:
        return cs.get_calibration()


def _held(port: str, currents, truth) -> list[tuple[float, float]]:
    """(device reading, wire current) at each setpoint once settled (200 ms device time), the
    setpoint renewed meanwhile (:class:`~smabench.calibrate.HeldCurrent`)."""
    out = []
    # (a host timeout of 1 s: this measures readings, and a busy machine can hold the driver's
    # keepalive thread past the default 0.25 s; the link's owner thread runs at the priority
    # calibrate gives it, or a busy machine holds the lease's renewals past LEASE_S)
    from smabench.bench.priority import LINK_RT_PRIORITY

    with CurrentSource(port, lease_s=cal.LEASE_S, host_timeout_s=1.0,
                       owner_priority=LINK_RT_PRIORITY) as cs:  # fmt: skip
        for i in currents:
            with cal.HeldCurrent(cs, i, settle_s=0.2) as held:
                assert held.wait_span(0.1, timeout_s=10.0), held.measurement()
                wire_a = truth()
                m = held.measurement()
            assert not m.faults and not m.timed_out, m
            out.append((m.current_a, wire_a))
    return out


# ----------------------------------------------------------------------------- mock: current
@pytest.mark.slow
def test_calibrate_current_scripted_on_the_mock(bench, store, capsys):
    """A device reading 4 % high with a 6 mA offset; the meter's readings given with
    --readings: afterwards the device reports the wire current within 5 mA."""
    port = bench.ports.driver
    _write(port, WRONG)
    before = _held(port, CHECK_A, lambda: _physical_a(bench))
    assert max(abs(d - w) for d, w in before) > 0.04  # the error the calibration must remove
    meter = [w for _, w in _held(port, STEPS_A, lambda: _physical_a(bench))]
    rc = main(["calibrate", "current", "--port", port, "--readings",
               ",".join(f"{m:.4f}" for m in meter), *FAST])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "residual" in out and "read back" in out
    back = _read_back(port)
    assert back.current_gain == pytest.approx(1.0, abs=2e-3)
    # the frames carry whole mA and the "meter" samples the wire current once (±0.5 mA of
    # ripple at 1–2 A, the sink under its PWM): the offset is known to about two frame LSBs
    assert back.current_offset_a == pytest.approx(0.0, abs=2e-3)
    after = _held(port, CHECK_A, lambda: _physical_a(bench))
    print(f"\nmock, device − wire: before {[f'{(d - w) * 1e3:+.1f}' for d, w in before]} mA, "
          f"after {[f'{(d - w) * 1e3:+.1f}' for d, w in after]} mA")  # fmt: skip
    assert all(abs(d - w) < 0.005 for d, w in after)
    rec = json.loads(store.read_text())["current"]
    assert rec["gain"] == back.current_gain and rec["offset_a"] == back.current_offset_a
    assert rec["written_at"] and len(rec["points"]) == 3


@pytest.mark.slow
def test_calibrate_current_asks_the_operator(bench, capsys):
    """The prompt path: each current is on while the "operator" types what the meter shows
    (the wire current at that moment, in mA); one typo is asked again."""
    port = bench.ports.driver
    _write(port, WRONG)
    typed: list[str] = []

    def operator(prompt: str) -> str:
        assert " A is on" in prompt  # asked while the current flows
        if not typed:
            typed.append("oops")
            return "oops"
        typed.append(f"{_physical_a(bench) * 1e3:.1f} mA")
        return typed[-1]

    args = _parse(["calibrate", "current", "--port", port, *FAST])
    assert cal.cmd_calibrate_current(args, input_fn=operator) == 0
    assert "not a reading" in capsys.readouterr().out
    assert len(typed) == 4
    after = _held(port, CHECK_A, lambda: _physical_a(bench))
    assert all(abs(d - w) < 0.005 for d, w in after)


def _parse(argv: list[str]):
    from smabench.cli import build_parser

    return build_parser().parse_args(argv)


def test_write_refused_while_the_output_is_on(bench):
    port = bench.ports.driver
    with CurrentSource(port, lease_s=1.0) as cs:
        cs.set_current(0.3, wait=True)
        cs.enable(True)
        cs.wait_telemetry(lambda t: t.enabled, 1.0)
        with pytest.raises(CommandRejected) as exc:
            cs.set_calibration(WRONG)
        assert exc.value.status == p.Status.OUTPUT_ON
        cs.enable(False)
        assert cs.get_calibration() == p.Calibration()
        cs.wait_telemetry(lambda t: not t.enabled, 1.0)
        cs.set_calibration(WRONG)  # off: taken
        assert cs.get_calibration() == p.Calibration.from_data(WRONG.to_data())


@pytest.mark.parametrize(
    "readings, match",
    [
        ("0.2,1.0,2.6", "more than 20%"),
        ("0.2,1.0", "2 meter reading"),
        ("0.2,0.95,0.9", "more than 20%"),
        ("0.2,abc,2", "give numbers"),
    ],
)
def test_bad_readings_exit_2_and_nothing_is_written(bench, store, capsys, readings, match):
    port = bench.ports.driver
    _write(port, WRONG)
    rc = main(["calibrate", "current", "--port", port, "--readings", readings, *FAST])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("smabench calibrate: error:")
    assert re.search(match, err[0]), err[0]
    assert _read_back(port) == p.Calibration.from_data(WRONG.to_data())
    assert not store.exists()
    assert bench.device.call(lambda fw: fw.enabled) is False


def test_a_reading_off_by_more_than_20_percent_stops_the_steps(bench, store, capsys):
    """Typed at the prompt: refused at once, output off, nothing written."""
    port = bench.ports.driver
    answers = iter(["0.2", "1.3"])
    args = _parse(["calibrate", "current", "--port", port, *FAST])
    with pytest.raises(cal.CalibrationError, match="more than 20%"):
        cal.cmd_calibrate_current(args, input_fn=lambda _prompt: next(answers))
    assert bench.device.call(lambda fw: fw.enabled) is False
    assert _read_back(port) == p.Calibration()
    assert not store.exists()


def test_a_hold_that_ends_before_the_readings_are_in_is_said_not_blamed_on_the_meter(
    bench, store
):
    """--max-hold-s shorter than settling + averaging: the output goes off before the meter is
    asked for; a meter read then shows no current. Said as the hold limit (it used to ask the
    meter anyway and refuse its 0 A as "more than 20 % off"), nothing written."""
    port = bench.ports.driver
    asked: list[float] = []

    def operator(prompt: str) -> str:
        asked.append(_physical_a(bench))
        return f"{asked[-1]:.4f}"

    args = _parse(["calibrate", "current", "--port", port, "--max-hold-s", "0.1",
                   "--settle-s", "0.3", "--average-s", "0.3"])  # fmt: skip
    said = r"hold limit \(0\.1 s at 0\.2 A.*nothing written"
    with pytest.raises(cal.CalibrationError, match=said):
        cal.cmd_calibrate_current(args, input_fn=operator)
    assert asked == []  # the meter was never asked for while nothing flowed
    assert bench.device.call(lambda fw: fw.enabled) is False
    assert not store.exists()


def test_a_current_the_heat_budget_cannot_hold_is_refused(bench, store, capsys):
    """A heat model that trips 2 A within 0.5 s: refused before 2 A is switched on."""
    port = bench.ports.driver
    tight = p.HeatModel(0.55, 0.002, 0.0059, 300.0)
    with CurrentSource(port) as cs:
        cs.set_heat_model(tight)
    rc = main(["calibrate", "current", "--port", port, "--readings", "0.2,1.0,2.0", *FAST])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "heat model" in err[0], err
    assert bench.device.call(lambda fw: fw.setpoint_ma) <= 1000  # 2 A was never set
    assert _read_back(port) == p.Calibration()
    assert not store.exists()


@pytest.mark.slow
def test_a_slow_operator_gets_the_output_turned_off(bench, store):
    """The hold ends by itself at --max-hold-s while the operator still reads; the reading
    typed afterwards (what the meter showed while on) still calibrates."""
    port = bench.ports.driver
    off_before_answer = []

    def operator(prompt: str) -> str:
        seen_a = _physical_a(bench)  # the meter while the current flows
        deadline = time.monotonic() + 10.0
        while bench.device.call(lambda fw: fw.enabled) and time.monotonic() < deadline:
            time.sleep(0.01)  # the operator still reading: wait for the output to go off
        off_before_answer.append(not bench.device.call(lambda fw: fw.enabled))
        return f"{seen_a:.4f}"

    # the hold limit counts wall time, the settling and averaging (0.4 s) device time: 1.5 s
    # leaves an in-process mock slowed by a busy machine time to finish them
    args = _parse(["calibrate", "current", "--port", port, "--max-hold-s", "1.5", *FAST])
    assert cal.cmd_calibrate_current(args, input_fn=operator) == 0
    assert off_before_answer == [True, True, True]
    back = _read_back(port)
    assert back.current_gain == pytest.approx(1.0, abs=2e-3)


# ----------------------------------------------------------------------------- mock: wire
def test_calibrate_wire_on_the_mock(bench, store, capsys):
    """The mock's wire (the plant's cold resistance) within 2 %; the heating printed is the
    heat balance's for the paper wire at 0.2 A."""
    port = bench.ports.driver
    r_true = bench.link.resistance_ohm()
    rc = main(["calibrate", "wire", "--port", port, "--wire-length-mm", "55",
               "--wire-diameter-mm", "0.38", "--average-s", "0.5"])  # fmt: skip
    out = capsys.readouterr().out
    assert rc == 0, out
    rec = json.loads(store.read_text())["wire"]
    print(f"\nmock wire: {rec['resistance_ohm']:.4f} Ω measured, {r_true:.4f} Ω in the plant")
    assert rec["resistance_ohm"] == pytest.approx(r_true, rel=0.02)
    assert rec["ohm_per_m"] == pytest.approx(r_true / 0.055, rel=0.02)
    assert rec["expected_ohm"] == pytest.approx(PAPER_WIRE.resistance_ohm(1.0), rel=1e-9)
    assert rec["deviation"] == pytest.approx(r_true / rec["expected_ohm"] - 1.0, abs=0.02)
    # the heating is the heat balance's over the time the current was on, device time: at
    # least the 0.3 s settling + 0.5 s averaged (longer when the host was slow to switch off)
    on_s = float(re.search(r"by the end of the ([\d.]+) s at", out)[1])
    assert on_s >= 0.8 - 0.05, out  # printed to 0.1 s

    def heat_k(t_s: float) -> float:
        return step_exact(rec["ambient_c"], rec["current_a"], t_s, PAPER_WIRE, rec["ambient_c"],
                          resistance_ohm=rec["resistance_ohm"]) - rec["ambient_c"]  # fmt: skip

    assert heat_k(on_s - 0.05) <= rec["heating_k"] <= heat_k(on_s + 0.05), (on_s, rec)
    assert 0.0 < rec["heating_k"] < 2.0
    assert "stays martensite" in out


@pytest.mark.parametrize("offset_mv", [3.0, -2.0])
def test_calibrate_wire_takes_out_the_amplifier_offset(store, capsys, offset_mv):
    """A difference amplifier reading ``offset_mv`` off at the wire (issue 25: ≈ 10 mV possible,
    11 % of R at 0.2 A): before, R at 0.2 A is that far off; ``calibrate wire`` fits the offset
    from two holds, writes it to the EEPROM (protocol 3) and the wire then reads within 0.25 %
    of its resistance: on this mock nothing dithers the ADS1115's codes, whose LSB (125 µV at
    the wire, 78 µA) is 0.15 % of R at 0.2 A (``electrical.resistance_resolution``); measured
    +0.21 % for both offsets, the offset recovered within 0.06 mV."""
    r_true, offset_v = 0.44, offset_mv * 1e-3
    wire = Electrical(resistance_ohm=r_true, wire_offset_v=offset_v)
    with SerialDevice(electrical=wire, thread_priority=DEVICE_RT_PRIORITY) as dev:
        with CurrentSource(dev.port_name, lease_s=1.0) as cs:
            raw = cal.measure_wire(cs, 0.2, average_s=0.3)
        r_raw = raw.voltage_v / raw.shunt_current_a
        assert abs(r_raw / r_true - 1.0) > 0.02, r_raw  # the offset shows before
        rc = main(["calibrate", "wire", "--port", dev.port_name, "--wire-length-mm", "55",
                   "--wire-diameter-mm", "0.38", "--average-s", "0.5"])  # fmt: skip
        out = capsys.readouterr().out
        assert rc == 0, out
        back = _read_back(dev.port_name)
    rec = json.loads(store.read_text())["wire"]
    print(f"\namplifier offset {offset_mv:+.1f} mV: R {r_raw:.4f} Ω before, "
          f"{rec['resistance_ohm']:.5f} Ω after ({rec['resistance_ohm'] / r_true - 1:+.3%}); "
          f"offset written {back.voltage_offset_v * 1e3:+.3f} mV")  # fmt: skip
    assert back.voltage_offset_v == pytest.approx(offset_v, abs=0.1e-3)
    assert rec["voltage_offset_v"] == back.voltage_offset_v
    assert rec["resistance_ohm"] == pytest.approx(r_true, rel=0.0025)
    assert "wire-voltage offset written to EEPROM and read back" in out


@pytest.mark.parametrize(
    "electrical, match",
    [
        (Electrical(resistance_ohm=0.44, open_wire=True), "open circuit"),
        (Electrical(resistance_ohm=0.002), "shorted Kelvin sense"),
        (Electrical(resistance_ohm=0.60), r"\+55% off"),
        (Electrical(resistance_ohm=0.22), r"-43% off"),
        (Electrical(resistance_ohm=0.44, vsense=False), "no Kelvin wire voltage"),
    ],
)
def test_wire_problems_are_named_and_exit_2(store, capsys, electrical, match):
    # the device thread real-time where allowed, as the bench fixture's: a microcontroller is not
    # slowed by host load (beside CPU burners its host timeout ended a run before the check)
    with SerialDevice(electrical=electrical, thread_priority=DEVICE_RT_PRIORITY) as dev:
        rc = main(["calibrate", "wire", "--port", dev.port_name, "--wire-length-mm", "55",
                   "--wire-diameter-mm", "0.38", "--average-s", "0.1"])  # fmt: skip
        assert dev.call(lambda fw: fw.enabled) is False
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and re.search(match, err[0]), err
    assert not store.exists()


# ----------------------------------------------------------------------------- mock: sensor
def test_tare_then_read_gives_zero(bench, store, capsys):
    spec = bench.ports.sensor_tcp
    absolute = bench.link.position_mm()
    assert main(["sensor", "tare", "--sensor", spec, "--duration-s", "0.3"]) == 0
    tare = json.loads(store.read_text())["sensor_tare"]
    assert tare["zero_mm"] == pytest.approx(absolute, abs=0.005)  # 2 µm noise, ≥ 5 readings
    assert tare["samples"] >= 5 and tare["invalid"] == 0
    capsys.readouterr()
    assert main(["sensor", "read", "--sensor", spec, "--duration-s", "0.3"]) == 0
    out = capsys.readouterr().out
    rel = float(out.split()[1])
    assert abs(rel) < 0.005, out
    assert main(["sensor", "read", "--sensor", spec, "--duration-s", "0.3", "--absolute"]) == 0
    assert "absolute" in capsys.readouterr().out


def test_tare_of_a_dead_sensor_is_refused(store, capsys):
    assert main(["sensor", "tare", "--sensor", "tcp:127.0.0.1:1", "--duration-s", "0.2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sensor" in err[0]
    assert not store.exists()


# ----------------------------------------------------------------------------- session.json
@pytest.mark.slow
def test_session_json_carries_the_calibration(bench, store, tmp_path, capsys):
    from smabench.bench.headless import open_devices
    from smabench.bench.session_run import RunSettings, run_session
    from smabench.protocols import ProtocolSettings

    port = bench.ports.driver
    with CurrentSource(port) as cs:  # a blank EEPROM's heat model is invalid too (CAL_DEFAULT)
        cs.set_heat_model(p.HeatModel())
        assert cs.get_heat_model() == p.HeatModel()
    meter = [w for _, w in _held(port, STEPS_A, lambda: _physical_a(bench))]
    assert main(["sensor", "tare", "--sensor", bench.ports.sensor_tcp, "--duration-s", "0.3"]) == 0
    assert main(["calibrate", "wire", "--port", port, "--wire-length-mm", "55",
                 "--wire-diameter-mm", "0.38", "--average-s", "0.3"]) == 0  # fmt: skip
    assert main(["calibrate", "current", "--port", port, "--readings",
                 ",".join(f"{m * 1.01:.4f}" for m in meter), *FAST]) == 0  # fmt: skip
    stored = json.loads(store.read_text())
    settings = RunSettings(
        load_kg=1.0,
        protocol=ProtocolSettings(name="cycles", cycles=1, current_a=0.5, heat_s=0.2,
                                  min_cool_s=0.1, cool_timeout_s=0.3),  # fmt: skip
        out_dir=tmp_path / "sessions",
        session_id="with-cal",
    )
    source, sensor = open_devices(port, bench.ports.sensor_tcp, settings)
    try:
        folder, result = run_session(settings, source, sensor)
    finally:
        source.close()
        sensor.close()
    block = json.loads((folder / "session.json").read_text())["calibration"]
    dev = block["current_driver"]
    assert dev["current_gain"] == pytest.approx(stored["current"]["gain"], abs=1 / 32768)
    assert dev["current_gain"] == pytest.approx(1.01, abs=3e-3)  # the meter read 1 % more
    assert dev["current_offset_a"] == pytest.approx(stored["current"]["offset_a"], abs=1e-6)
    assert dev["written_at"] == stored["current"]["written_at"]
    assert dev["eeprom_defaults"] is False
    assert block["wire"]["resistance_ohm"] == stored["wire"]["resistance_ohm"]
    assert block["wire"]["measured_at"]
    assert block["sensor_tare"]["zero_mm"] == stored["sensor_tare"]["zero_mm"]
    assert block["store"] == str(store)


def test_session_block_without_a_store_or_a_calibration(store):
    """A source that never read its calibration (a simulated driver) and no store yet."""
    block = calibration_store.session_block(object())
    assert block == {
        "store": str(store), "current_driver": None, "wire": None, "sensor_tare": None,
    }  # fmt: skip


def test_session_block_written_at_only_when_the_device_holds_what_was_written(store):
    cal.save_record("current", {"offset_a": 0.001, "gain": 1.01, "voltage_gain": 1.0,
                                "written_at": "2026-01-01T00:00:00+0000"})  # fmt: skip

    class Source:
        calibration = p.Calibration(0.001, 1.01)

        def latest(self):
            return None

    block = calibration_store.session_block(Source())
    assert block["current_driver"]["written_at"] == "2026-01-01T00:00:00+0000"
    Source.calibration = p.Calibration(0.002, 1.01)  # changed by something else since
    assert calibration_store.session_block(Source())["current_driver"]["written_at"] is None


# ----------------------------------------------------------------------------- emulated firmware
class Harness:
    """The simavr harness (real firmware), wire resistance fixed; ``current_a()`` is the wire
    current on the harness's side (its STATE line). Real-time where allowed, as the mock bench
    runs it: it stands in for a microcontroller, which host load does not slow (beside CPU
    burners, at normal scheduling, the firmware's 0.25 s host timeout once turned the output
    off in the middle of `calibrate wire`)."""

    def __init__(self, r_ohm: float = 0.44) -> None:
        self.proc = subprocess.Popen(
            [str(SIM), str(ELF)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL, text=True, bufsize=1, preexec_fn=realtime_child,
        )  # fmt: skip
        self.lines: queue.Queue[str] = queue.Queue()
        first = self.proc.stdout.readline().strip()
        assert first.startswith("PTY "), first
        self.port_name = first[4:]
        threading.Thread(target=self._read, daemon=True).start()
        self.send(f"R {r_ohm}")

    def _read(self) -> None:
        for line in self.proc.stdout:
            if line.startswith("STATE"):
                self.lines.put(line)

    def send(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def current_a(self, n: int = 5) -> float:
        values = []
        for _ in range(n):
            self.send("Q")
            line = self.lines.get(timeout=5.0)
            values.append(float(line.split("current_a=")[1].split()[0]))
        return float(np.mean(values))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        try:
            self.proc.wait(3.0)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


# under CI a missing build is a failure, never a skip (as test_firmware_emulated.py)
needs_build = pytest.mark.skipif(
    not (SIM.is_file() and ELF.is_file()) and not os.environ.get("CI"),
    reason="firmware build missing (make -C firmware elf sim)",
)


@pytest.fixture
def harness():
    h = Harness()
    yield h
    h.close()


@pytest.mark.emulator
@pytest.mark.slow
@needs_build
def test_calibrate_current_on_the_emulated_firmware(harness, store, capsys):
    """The real firmware reads 5 % high with a 5 mA offset; the operator types the harness's
    wire current; afterwards the firmware reports (and regulates) the wire current within
    5 mA. A write while the output is on is refused by the firmware."""
    port = harness.port_name
    wrong = p.Calibration(current_offset_a=0.005, current_gain=1.05)
    with CurrentSource(port, lease_s=1.0) as cs:
        cs.set_calibration(wrong)
        cs.set_current(0.3, wait=True)
        cs.enable(True)
        with pytest.raises(CommandRejected) as exc:
            cs.set_calibration(p.Calibration())
        assert exc.value.status == p.Status.OUTPUT_ON
        cs.enable(False)
        assert cs.get_calibration() == p.Calibration.from_data(wrong.to_data())
    before = _held(port, CHECK_A, harness.current_a)
    assert max(abs(d - w) for d, w in before) > 0.03

    def operator(prompt: str) -> str:
        return f"{harness.current_a():.4f}"

    args = _parse(["calibrate", "current", "--port", port, "--settle-s", "0.3",
                   "--average-s", "0.3"])  # fmt: skip
    assert cal.cmd_calibrate_current(args, input_fn=operator) == 0
    after = _held(port, CHECK_A, harness.current_a)
    print(f"\nemulated, device − wire: before {[f'{(d - w) * 1e3:+.1f}' for d, w in before]} mA, "
          f"after {[f'{(d - w) * 1e3:+.1f}' for d, w in after]} mA")  # fmt: skip
    assert all(abs(d - w) < 0.005 for d, w in after)
    assert all(abs(w - i) < 0.01 for (_, w), i in zip(after, CHECK_A, strict=True))
    back = _read_back(port)
    rec = json.loads(store.read_text())["current"]
    assert rec["gain"] == back.current_gain and rec["offset_a"] == back.current_offset_a


@pytest.mark.emulator
@pytest.mark.slow
@needs_build
def test_calibrate_wire_on_the_emulated_firmware(harness, store, capsys):
    """0.44 Ω in the harness, read through the emulated ADS1115 (Kelvin leads, shunt); then
    the wire opened: exit 2 naming the open circuit."""
    port = harness.port_name
    argv = ["calibrate", "wire", "--port", port, "--wire-length-mm", "55",
            "--wire-diameter-mm", "0.38", "--average-s", "0.5"]  # fmt: skip
    assert main(argv) == 0, capsys.readouterr()
    rec = json.loads(store.read_text())["wire"]
    print(f"\nemulated wire: {rec['resistance_ohm']:.4f} Ω measured, 0.44 Ω in the harness")
    assert rec["resistance_ohm"] == pytest.approx(0.44, rel=0.03)
    store.unlink()
    harness.send("OPEN")
    harness.current_a(1)  # answered after OPEN: the harness has taken it
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "open circuit" in err
    assert not store.exists()
