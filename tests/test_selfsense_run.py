"""The wire as its own sensor in a running session (issue 26, items 2, 4, 5).

A probe current while the wire cools (``probe_current_a``), the position estimated from the
wire's resistance every tick (``selfsense``: columns ``resistance_ohm``, ``position_est_mm``),
that estimate as the controller's measured position (``feedback resistance``) or as its stand-in
while the laser's reading is invalid (``fallback resistance``), and the mock whose wire voltage
is I·R(ξ, T, ε) (``smabench mock --resistivity``).

The unit tier runs the bench runtime on simulated time (:mod:`smabench.drivers.sim`, the plant
with the Flexinol resistivity model, the firmware's own core): seconds each, the same figures on
a busy machine. The slow tier runs ``smabench run --mock`` and the mock bench in its own process
over the real transports, and prints the figures the issue asks for.
"""

from __future__ import annotations

import json
import logging
import math
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from smabench.bench.runtime import BenchRuntime
from smabench.bench.session_run import RunSettings
from smabench.bench.tick import FEEDBACK_BLEND_TAU_S, RuntimeConfig
from smabench.commands import CommandStep
from smabench.drivers.sim import SimBench
from smabench.physics.resistance import FLEXINOL_RESISTIVITY
from smabench.protocols import Protocol, ProtocolSettings
from smabench.selfsense import (
    SelfSenseCalibration,
    SessionArrays,
    calibrate,
    estimate_session,
)
from smabench.sessions import (
    COLUMNS,
    FLAG_AFTER_END,
    FLAG_FEEDBACK_RESISTANCE,
    FLAG_SENSOR_INVALID,
    SELFSENSE_COLUMNS,
    SessionWriter,
    load_session,
    session_columns,
)
from smabench.settings import SettingError

PERIOD_S = 0.005  # 200 Hz, the bench's loop
PROBE_A = 0.1
CYCLES = dict(name="cycles", heat_s=3.0, current_a=1.2)


# ----------------------------------------------------------------------------- helpers
class Recording:
    """A command source around another (a protocol): keeps every position it was given."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.positions: list[float] = []

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        self.positions.append(position_mm)
        return self.inner.update(t_s, position_mm)


class Constant:
    def __init__(self, current_a: float) -> None:
        self.current_a = current_a

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        return CommandStep(self.current_a, 0, "hold")


def offline(command, seed: int = 1, at=None, max_duration_s: float = 60.0, **cfg):
    """One session of the bench runtime on simulated time against the plant with the Flexinol
    resistivity; ``at = {tick: fn(runtime, bench)}`` before those ticks. Returns (result, rows
    of the session itself)."""
    bench = SimBench(2.0, seed=seed, resistivity=FLEXINOL_RESISTIVITY)
    rows: list[dict] = []
    box: list[BenchRuntime] = []

    def on_tick(k: int, t_s: float) -> None:
        if at and k in at:
            at[k](box[0], bench)

    config = RuntimeConfig(rate_hz=1.0 / PERIOD_S, max_duration_s=max_duration_s, **cfg)
    rt = BenchRuntime(bench.source, bench.sensor, command, rows.append, config,
                      on_tick=on_tick, clock=bench.clock.now, sleep=bench.clock.sleep)  # fmt: skip
    box.append(rt)
    result = rt.run()
    return result, [r for r in rows if not int(r["flags"]) & FLAG_AFTER_END]


def col(rows, name) -> np.ndarray:
    return np.array([np.nan if r[name] is None else r[name] for r in rows], dtype=float)


def arrays(rows) -> SessionArrays:
    return SessionArrays(col(rows, "t_s"), col(rows, "current_A"), col(rows, "voltage_V"),
                         col(rows, "position_mm"), col(rows, "cycle").astype(int), "offline",
                         2.0)  # fmt: skip


@pytest.fixture(scope="module")
def cal() -> SelfSenseCalibration:
    """Learnt from four heating cycles recorded offline with the 0.1 A probe (≈ 8 s)."""
    result, rows = offline(Protocol(ProtocolSettings(cycles=4, **CYCLES)),
                           probe_current_a=PROBE_A)  # fmt: skip
    assert result.status == "completed", result.reason
    return calibrate([arrays(rows)])


@pytest.fixture(scope="module")
def cal_file(cal, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("selfsense") / "cal.json"
    path.write_text(cal.to_json())
    return path


def fed_and_estimate(rows, src: Recording):
    return np.asarray(src.positions, dtype=float), col(rows, "position_est_mm")


# ----------------------------------------------------------------------------- settings
def test_the_settings_are_declared_once_and_off_by_default():
    r = RunSettings(load_kg=2.0)
    assert (r.probe_current_a, r.selfsense, r.feedback, r.fallback) == (0.0, None, "laser", None)
    cfg = r.runtime_config()
    assert (cfg.probe_current_a, cfg.selfsense, cfg.feedback, cfg.fallback) == \
        (0.0, None, "laser", None)  # fmt: skip
    with pytest.raises(SettingError, match="probe current must be in 0 … 0.1 A"):
        RunSettings(load_kg=2.0, probe_current_a=0.15).validate()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--selfsense", "{missing}"], "self-sense calibration cannot read"),
        (["--selfsense", "{bad}"], "not JSON"),
        (["--feedback", "resistance"], "--feedback resistance needs a self-sense calibration"),
        (["--fallback", "resistance", "--selfsense", "{cal}"],
         "needs a probe current of at least 0.02 A"),
        (["--feedback", "sonar"], "unknown position feedback 'sonar'"),
    ],
)  # fmt: skip
def test_a_bad_calibration_or_sensing_setting_is_one_line_before_any_device(
    args, message, cli, tmp_path, cal_file
):
    bad = tmp_path / "bad.json"
    bad.write_text("{nope")
    names = {"missing": tmp_path / "missing.json", "bad": bad, "cal": cal_file}
    args = [a.format(**names) for a in args]
    out = tmp_path / "sessions"
    proc = cli("run", "--port", "/nonexistent/tty", "--sensor", "tcp:127.0.0.1:1",
               "--load-kg", "2", "--out", out, *args)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "nonexistent" not in proc.stderr and not out.exists()


def test_the_session_records_the_probe_the_calibration_and_the_new_columns(cal_file, tmp_path):
    from smabench.bench.session_run import session_meta

    s = RunSettings(load_kg=2.0, probe_current_a=PROBE_A, selfsense=str(cal_file),
                    fallback="resistance", out_dir=tmp_path)  # fmt: skip
    s.validate()
    meta = json.loads(json.dumps(session_meta(s, {}), allow_nan=False))
    assert meta["settings"]["probe_current_a"] == PROBE_A
    assert meta["settings"]["fallback"] == "resistance"
    sensing = meta["sensing"]
    assert sensing["probe_current_a"] == PROBE_A and sensing["fallback_max_s"] == 120.0
    assert sensing["selfsense"]["path"] == str(cal_file.resolve())
    again = SelfSenseCalibration.from_dict(sensing["selfsense"]["calibration"])
    assert again.heating == s.selfsense_calibration().heating
    assert session_columns(True) == COLUMNS + SELFSENSE_COLUMNS
    plain = session_meta(RunSettings(load_kg=2.0), {})["sensing"]
    assert plain == {"probe_current_a": 0.0, "feedback": "laser", "fallback": None,
                     "fallback_max_s": 120.0, "selfsense": None}  # fmt: skip


# ----------------------------------------------------------------------------- the estimate
def test_without_the_new_options_the_rows_are_as_before_and_the_estimate_is_passive(cal):
    """The estimate (feedback from the laser, no fallback) changes nothing the session does:
    the contract columns are the same floats as without it; without the options the rows carry
    the contract columns only."""
    proto = ProtocolSettings(cycles=1, **CYCLES)
    _, plain = offline(Protocol(proto), seed=4, max_duration_s=8.0)
    assert all(list(r) == list(COLUMNS) for r in plain)
    _, probed = offline(Protocol(proto), seed=4, max_duration_s=8.0, probe_current_a=PROBE_A)
    _, sensed = offline(Protocol(proto), seed=4, max_duration_s=8.0, probe_current_a=PROBE_A,
                        selfsense=cal)  # fmt: skip
    assert len(probed) == len(sensed) > 1000
    assert all(list(r) == list(COLUMNS + SELFSENSE_COLUMNS) for r in sensed)
    for c in COLUMNS:
        a, b = [r[c] for r in probed], [r[c] for r in sensed]
        assert a == b or np.array_equal(np.asarray(a, float), np.asarray(b, float), equal_nan=True)
    assert not any(int(r["flags"]) & FLAG_FEEDBACK_RESISTANCE for r in sensed)
    # the probe is what the driver drives while the protocol cools (the plain session: 0 A)
    cool = col(probed, "current_set_A") == 0
    assert np.nanmedian(col(probed, "current_A")[cool & (col(probed, "t_s") > 4)]) == \
        pytest.approx(PROBE_A, abs=0.005)  # fmt: skip
    assert np.nanmax(col(plain, "current_A")[cool & (col(plain, "t_s") > 4)]) < 0.01


def test_the_online_estimate_is_the_offline_one_within_a_few_percent_of_stroke(cal, tmp_path):
    """Every tick's estimate, written and read back, is the very float ``smabench selfsense
    estimate`` gives on the recorded session; against the laser: a few % of the stroke."""
    result, rows = offline(Protocol(ProtocolSettings(cycles=2, **CYCLES)), seed=2,
                           probe_current_a=PROBE_A, selfsense=cal)  # fmt: skip
    assert result.status == "completed", result.reason
    folder = tmp_path / "est"
    with SessionWriter(folder, {"load_kg": 2.0}, columns=session_columns(True)) as w:
        for r in rows:
            w.append(r)
    s = load_session(folder)
    assert s.columns == list(COLUMNS + SELFSENSE_COLUMNS)
    d = s.data
    off = estimate_session(cal, s)
    assert np.array_equal(d["position_est_mm"], off.position_est_mm, equal_nan=True)
    r_expected = np.where(d["current_A"] >= cal.min_current_a, d["voltage_V"] / d["current_A"],
                          np.nan)  # fmt: skip
    assert np.allclose(d["resistance_ohm"], r_expected, equal_nan=True, rtol=1e-12)
    cooling = (d["current_A"] > 0.05) & (d["current_A"] < 0.2)
    assert np.isfinite(d["resistance_ohm"][cooling]).mean() > 0.95  # R while the wire cools
    pct = cal.percent_of_stroke(off.rms_mm)
    print(
        f"\noffline, 2 cycles: estimate against the laser {off.rms_mm:.4f} mm RMS = "
        f"{pct:.2f} % of the {cal.stroke_mm:.2f} mm stroke"
    )
    assert pct < 5.0


# ----------------------------------------------------------------------------- feedback
def test_feedback_resistance_gives_the_controller_the_estimate_and_flags_every_row(cal):
    src = Recording(Protocol(ProtocolSettings(cycles=1, **CYCLES)))
    _, rows = offline(src, max_duration_s=6.0, probe_current_a=PROBE_A, selfsense=cal,
                      feedback="resistance")  # fmt: skip
    fed, est = fed_and_estimate(rows, src)
    assert np.array_equal(fed, est, equal_nan=True)  # from the start: no offset to blend
    assert np.isfinite(est[20:]).all()
    assert all(int(r["flags"]) & FLAG_FEEDBACK_RESISTANCE for r in rows)


def test_a_live_switch_of_the_feedback_is_bumpless(cal):
    src = Recording(Protocol(ProtocolSettings(cycles=2, **CYCLES)))
    k = 900  # 4.5 s: the wire cooling, the estimate and the laser apart
    _, rows = offline(src, max_duration_s=12.0, probe_current_a=PROBE_A, selfsense=cal,
                      at={k: lambda rt, b: rt.set_feedback("resistance")})  # fmt: skip
    fed, est = fed_and_estimate(rows, src)
    laser = col(rows, "position_mm")
    assert np.array_equal(fed[:k], laser[:k])
    jump = abs(laser[k - 1] - est[k])
    step = abs(fed[k] - fed[k - 1])
    print(
        f"\nlive switch at {k * PERIOD_S:.1f} s: laser − estimate {jump:.4f} mm; the fed "
        f"position moved {step:.4f} mm in that tick"
    )
    assert step < 0.02 < jump  # the difference is carried over, not stepped into the loop
    later = k + int(5 * FEEDBACK_BLEND_TAU_S / PERIOD_S)
    assert abs(fed[later] - est[later]) < 0.01 * jump + 1e-6  # … and has decayed away
    flags = col(rows, "flags").astype(int)
    assert not np.any(flags[:k] & FLAG_FEEDBACK_RESISTANCE)
    assert np.all(flags[k:] & FLAG_FEEDBACK_RESISTANCE)
    with pytest.raises(ValueError, match="needs a self-sense calibration"):
        BenchRuntime(None, None, Constant(0.0), print).set_feedback("resistance")


# ----------------------------------------------------------------------------- fallback
def test_the_fallback_carries_the_control_while_the_laser_is_invalid_and_hands_it_back(cal, caplog):
    from smabench.bench.runtime import SENSOR_PROBE_WHILE_SILENT_S

    src = Recording(Protocol(ProtocolSettings(cycles=2, **CYCLES)))
    k0, n = 800, 600  # at 4 s, for 3 s: the wire cooling and stretching back
    caplog.set_level(logging.WARNING, logger="smabench.bench.tick")
    result, rows = offline(src, probe_current_a=PROBE_A, selfsense=cal, fallback="resistance",
                           at={k0: lambda rt, b: b.sensor.fail_for(n * PERIOD_S)})  # fmt: skip
    assert result.status == "completed", result.reason  # the 1 s sensor timeout did not end it
    flags = col(rows, "flags").astype(int)
    fb = (flags & FLAG_FEEDBACK_RESISTANCE) != 0
    invalid = (flags & FLAG_SENSOR_INVALID) != 0
    gap = np.flatnonzero(invalid)
    # from its first failed reading until the background request that finds it back (≤ one
    # SENSOR_PROBE_WHILE_SILENT_S after it is)
    assert gap[0] == k0 and gap.tolist() == list(range(k0, gap[-1] + 1))
    assert n <= len(gap) <= n + SENSOR_PROBE_WHILE_SILENT_S / PERIOD_S + 1
    end = int(gap[-1]) + 1
    assert np.array_equal(fb, invalid)  # exactly the rows without a valid laser reading
    fed, est = fed_and_estimate(rows, src)
    laser = col(rows, "position_mm")
    assert np.isfinite(fed).all() and np.isfinite(est[gap]).all()
    # bumpless both ways: the fed position continues from the last one
    assert abs(fed[k0] - laser[k0 - 1]) < 0.02 and abs(fed[end] - fed[end - 1]) < 0.02
    truth = np.interp(col(rows, "t_s")[gap], col(rows, "t_s")[~invalid], laser[~invalid])
    err = fed[gap] - truth
    rms, worst = float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err)))
    print(
        f"\nfallback 3 s while cooling: fed position against the laser's (interpolated "
        f"across the gap) {rms:.4f} mm RMS, {worst:.4f} mm at worst, stroke "
        f"{cal.stroke_mm:.2f} mm; {len(gap)} rows"
    )
    assert rms < 0.1 * cal.stroke_mm
    said = [r.getMessage() for r in caplog.records]
    assert sum("control goes on with the position from the wire's resistance" in m
               for m in said) == 1, said  # fmt: skip
    assert sum(re.search(r"displacement sensor back after 3\.[01]", m) is not None
               for m in said) == 1, said  # fmt: skip


def test_the_fallback_ends_after_its_bound_or_without_a_valid_estimate(cal):
    result, rows = offline(Constant(0.5), probe_current_a=PROBE_A, selfsense=cal,
                           fallback="resistance", fallback_max_s=2.0,
                           at={200: lambda rt, b: b.sensor.fail()})  # fmt: skip
    assert result.status == "aborted" and result.cause == "device"
    assert "longer than the 2 s the position from the wire's resistance" in result.reason
    t = col(rows, "t_s")
    assert t[-1] - t[199] == pytest.approx(2.0, abs=2 * PERIOD_S)

    def no_current(rt, b):  # the laser goes, and so does every current that would give an R
        b.sensor.fail()
        b.source.set_probe_current(0.0)

    result, rows = offline(Constant(0.0), probe_current_a=PROBE_A, selfsense=cal,
                           fallback="resistance", at={200: no_current})  # fmt: skip
    assert result.status == "aborted" and "no valid position from the wire's resistance" in \
        result.reason  # fmt: skip
    t = col(rows, "t_s")
    assert t[-1] - t[199] == pytest.approx(1.0, abs=2 * PERIOD_S)  # the sensor's own timeout
    # without a fallback the estimate changes nothing: lost after the sensor timeout, as before
    result, rows = offline(Constant(0.5), probe_current_a=PROBE_A, selfsense=cal,
                           at={200: lambda rt, b: b.sensor.fail()})  # fmt: skip
    assert result.reason.startswith("displacement sensor lost for 1.0")


def test_a_fallback_or_feedback_without_calibration_or_probe_is_refused():
    with pytest.raises(SettingError, match="fallback resistance needs a self-sense"):
        RuntimeConfig(fallback="resistance").validate()
    with pytest.raises(SettingError, match="feedback resistance needs a self-sense"):
        RuntimeConfig(feedback="resistance").validate()


# ----------------------------------------------------------------------------- slow: mock bench
MOCK_SPEED = "2"
RATE_HZ = "100"


def _run(tmp_path: Path, sid: str, *args: str, timeout: float = 300.0):
    proc = subprocess.run(
        [sys.executable, "-m", "smabench.cli", "run", "--mock", "--mock-resistivity", "flexinol",
         "--mock-speed", MOCK_SPEED, "--rate-hz", RATE_HZ, "--load-kg", "2",
         "--probe-current-a", str(PROBE_A), "--out", str(tmp_path), "--session-id", sid,
         "--quiet", *args],
        capture_output=True, text=True, timeout=timeout,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc, load_session(tmp_path / sid)


@pytest.fixture(scope="module")
def mock_cal(tmp_path_factory):
    """A calibration session over the real transports (3 cycles, 0.1 A probe) and the
    calibration `smabench selfsense calibrate` makes of it."""
    out = tmp_path_factory.mktemp("mock-selfsense")
    _, s = _run(out, "cal", "--cycles", "3", "--heat-s", "3", "--current-a", "1.2")
    cal_path = out / "cal.json"
    proc = subprocess.run([sys.executable, "-m", "smabench.cli", "selfsense", "calibrate",
                           str(out / "cal"), "--out", str(cal_path)],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    print("\n" + proc.stdout.strip())
    return out, s, cal_path


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_mock_resistivity_run_measures_r_while_the_wire_cools(mock_cal):
    _, s, _ = mock_cal
    d = s.data
    assert s.columns == list(COLUMNS)  # no --selfsense: the columns are the contract's
    assert "--resistivity" in s.meta["devices"]["mock"]
    assert s.meta["sensing"]["probe_current_a"] == PROBE_A
    cooling = (d["current_set_A"] == 0) & (d["t_s"] > 1.0)
    assert np.nanmedian(d["current_A"][cooling]) == pytest.approx(PROBE_A, abs=0.005)
    r = d["voltage_V"] / d["current_A"]
    assert np.isfinite(r[cooling]).mean() > 0.95
    r_cool = r[cooling & np.isfinite(r)]
    print(
        f"\nmock, flexinol: R while cooling at {PROBE_A} A: {r_cool.min():.4f} … "
        f"{r_cool.max():.4f} Ω ({np.isfinite(r[cooling]).mean():.1%} of the cooling rows)"
    )
    assert 0.45 < r_cool.min() < r_cool.max() < 0.55 and np.ptp(r_cool) > 0.02


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_mock_run_with_selfsense_records_the_estimate_within_a_few_percent(mock_cal):
    out, _, cal_path = mock_cal
    cal = SelfSenseCalibration.from_json(cal_path.read_text())
    _, s = _run(out, "est", "--cycles", "2", "--heat-s", "3", "--current-a", "1.2",
                "--mock-seed", "3", "--selfsense", str(cal_path))  # fmt: skip
    assert s.columns == list(COLUMNS + SELFSENSE_COLUMNS)
    assert s.meta["sensing"]["selfsense"]["calibration"]["stroke_mm"] == \
        pytest.approx(cal.stroke_mm)  # fmt: skip
    off = estimate_session(cal, s)
    assert np.array_equal(s.data["position_est_mm"], off.position_est_mm, equal_nan=True)
    pct = cal.percent_of_stroke(off.rms_mm)
    print(
        f"\nmock: online estimate against the laser {off.rms_mm:.4f} mm RMS = {pct:.2f} % of "
        f"the {cal.stroke_mm:.2f} mm stroke ({off.rows_compared} rows)"
    )
    assert pct < 6.0


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_mock_fallback_when_the_sensor_stops_answering(mock_cal, caplog):
    """The mock's sensor answers nothing for 1.5 s (wall) mid-session: the session goes on on
    the estimate (flagged rows, one warning each way) and returns to the laser."""
    from smabench.bench.headless import MockProcess, open_devices
    from smabench.bench.session_run import run_session

    out, _, cal_path = mock_cal
    settings = RunSettings(
        load_kg=2.0, protocol=ProtocolSettings(cycles=2, **CYCLES), rate_hz=float(RATE_HZ),
        out_dir=out, session_id="fallback", probe_current_a=PROBE_A, selfsense=str(cal_path),
        fallback="resistance", time_scale=float(MOCK_SPEED),
    )  # fmt: skip
    settings.validate()
    caplog.set_level(logging.WARNING, logger="smabench.bench.tick")
    seen: dict = {}
    rows = [0]
    started = threading.Event()

    def on_sample(row: dict) -> None:
        rows[0] += 1
        if rows[0] == 250:  # 2.5 s wall, 5 s device: the wire cooling at the probe current
            started.set()

    with MockProcess(["--load-kg", "2", "--resistivity", "flexinol", "--speed", MOCK_SPEED]) \
            as mock:  # fmt: skip
        source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
        box: dict = {}
        th = threading.Thread(
            target=lambda: box.update(
                out=run_session(settings, source, sensor, on_sample=on_sample)
            )
        )
        th.start()
        assert started.wait(60.0)
        tel = source.latest()  # the firmware's own R at the probe current (precise path)
        seen["tel"] = (tel.current_a, tel.precise_current_a, tel.resistance_ohm)
        mock.send("sensor-drop 1.5")
        th.join(120.0)
        assert not th.is_alive()
        source.close()
        sensor.close()
    folder, result = box["out"]
    assert result.status == "completed", result.reason
    i, ip, r = seen["tel"]
    print(f"\ntelemetry at the probe: {i:.3f} A (precise {ip:.4f} A), R {r:.4f} Ω")
    assert math.isfinite(r) and ip > 0.05
    s = load_session(folder)
    flags = s.data["flags"].astype(int)
    fb = (flags & FLAG_FEEDBACK_RESISTANCE) != 0
    invalid = (flags & FLAG_SENSOR_INVALID) != 0
    assert fb.sum() >= 5 and np.all(invalid[fb])  # control on the estimate only without laser
    last_fb = np.flatnonzero(fb)[-1]
    assert np.isfinite(s.data["position_mm"][last_fb + 1 :]).mean() > 0.9  # the laser is back
    gap_t = s.data["t_s"][fb]
    said = [x.getMessage() for x in caplog.records]
    print(
        f"mock sensor dropped: {fb.sum()} rows on the estimate over "
        f"{gap_t[-1] - gap_t[0]:.2f} s device time; " + " / ".join(said)
    )
    assert sum("control goes on with the position" in m for m in said) == 1, said
    assert sum("displacement sensor back after" in m for m in said) == 1, said


@pytest.mark.realtime_bench  # a mock bench: see tests/conftest.py
@pytest.mark.slow
def test_mock_run_closes_the_loop_on_the_estimate(mock_cal):
    """`smabench run --mock … --controller pid --feedback resistance`: every row controlled on
    the estimate, the session completes; its tracking error against the laser is printed."""
    out, _, cal_path = mock_cal
    proc, s = _run(out, "fb", "--protocol", "step", "--controller", "pid", "--cycles", "1",
                   "--period-s", "12", "--lead-in-s", "4", "--selfsense", str(cal_path),
                   "--feedback", "resistance")  # fmt: skip
    assert "completed" in proc.stdout
    d = s.data
    flags = d["flags"].astype(int)
    assert np.all(flags & FLAG_FEEDBACK_RESISTANCE)
    m = d["t_s"] > 4.0
    track = np.sqrt(np.nanmean((d["position_mm"][m] - d["setpoint_mm"][m]) ** 2))
    on_est = np.sqrt(np.nanmean((d["position_est_mm"][m] - d["setpoint_mm"][m]) ** 2))
    print(
        f"\nmock, PID step on the estimate: position − setpoint {track:.3f} mm RMS against "
        f"the laser, {on_est:.3f} mm against the estimate it controls on"
    )
    assert s.meta["sensing"]["feedback"] == "resistance"
