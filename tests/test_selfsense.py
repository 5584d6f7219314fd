"""The wire as its own sensor (issue 26): the plant's resistivity option and smabench.selfsense.

Sessions come from the plant with the resistivity model (Flexinol, 0.38 mm, 70 °C grade, 55 mm)
under 2 kg, heated at 1.4 A and cooled with a 0.1 A probe current, at 200 Hz, the wire voltage
through the bench's ADS1115 chain (its noise, or 3× it), written with the repo's session writer.
Figures are RMS errors of the estimate against the laser in % of the calibration's stroke.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import math
import re

import numpy as np
import pytest

from smabench import selfsense as ss
from smabench import selfsense_bench as sb
from smabench.physics.plant import Plant, simulate_plant, transformation_temperatures_c
from smabench.physics.resistance import (
    FLEXINOL_RESISTIVITY,
    FLEXINOL_WITH_RPHASE,
    resistance_ohm,
    rphase_fraction,
)
from smabench.sessions import FLAG_SENSOR_INVALID, load_session, write_session

# the runs of `smabench bench selfsense` (one source for its figures and these tests)
WIRE, LOAD_KG, DT_S, HEAT_A, PROBE_A = sb.WIRE, sb.LOAD_KG, sb.DT_S, sb.HEAT_A, sb.PROBE_A
MAJOR, PARTIAL = sb.MAJOR, sb.PARTIAL


# --------------------------------------------------------------------------- helpers
_profile = sb.profile


def _plant(phases, load_kg=LOAD_KG, model=FLEXINOL_RESISTIVITY, seed=0):
    run = sb.plant_run(phases, load_kg, model, seed)
    return run.t_s, run.current_a, run.cycle, run.trace


def _measured_v(trace, cur, noise_factor, seed):
    return sb.measured_voltage_v(cur, trace.voltage_v, noise_factor, seed)


def _write(folder, sim, noise_factor, seed, load_kg, flag_rows=None):
    t, cur, cyc, trace = sim
    pos = trace.position_mm.copy()
    flags = np.zeros(len(t), dtype=int)
    if flag_rows is not None:  # sensor-invalid rows: the recorded position is garbage
        flags[flag_rows] = FLAG_SENSOR_INVALID
        pos[flag_rows] = 40.0
    data = {
        "t_s": t, "current_set_A": cur, "current_A": cur,
        "voltage_V": _measured_v(trace, cur, noise_factor, seed),
        "ambient_C": np.full(len(t), 22.0), "position_mm": pos,
        "mode": np.array(["open_loop"] * len(t), dtype=object), "cycle": cyc, "flags": flags,
    }  # fmt: skip
    meta = {
        "kind": "simulated", "load_kg": load_kg,
        "wire": {"preset": "flexinol-0.38-70c", "length_mm": WIRE.length_mm,
                 "diameter_mm": WIRE.diameter_mm},
        "status": "completed", "end_reason": "protocol completed",
    }  # fmt: skip
    return write_session(folder, meta, data)


def _pct(cal, session):
    return cal.percent_of_stroke(ss.estimate_session(cal, session).rms_mm)


@pytest.fixture(scope="module")
def plants():
    """The benchmark's plant runs (one per profile and load), shared by both noise levels."""
    return {name: (r.t_s, r.current_a, r.cycle, r.trace) for name, r in sb.plant_runs().items()}


@pytest.fixture(scope="module", params=[1.0, 3.0], ids=["chain-noise", "3x-noise"])
def bench(request, plants, tmp_path_factory):
    """Session folders at one noise level, and the calibration from the 'cal' session."""
    noise = request.param
    base = tmp_path_factory.mktemp(f"selfsense-{noise:g}x")
    rows = len(plants["cal"][0])
    flagged = np.r_[1000:1040, rows // 2 : rows // 2 + 25]
    folders = {}
    for k, (name, sim) in enumerate(plants.items()):
        load = {"light": 0.5 * LOAD_KG, "heavy": 1.5 * LOAD_KG}.get(name, LOAD_KG)
        folders[name] = _write(base / name, sim, noise, 100 + k, load,
                               flagged if name == "cal" else None)  # fmt: skip
    sessions = {name: ss.session_arrays(f) for name, f in folders.items()}
    cal = ss.calibrate([folders["cal"]])
    return noise, folders, sessions, cal


# --------------------------------------------------------------------------- plant option
def test_plant_resistivity_option_falls_on_heating_and_bumps_on_cooling():
    t, cur, _ = _profile(MAJOR)
    default = simulate_plant(t, cur, load_kg=LOAD_KG, wire=WIRE)
    assert np.ptp(default.resistance_ohm) == 0.0  # default unchanged: R_mean, no effect on
    plain = simulate_plant(t, cur, load_kg=LOAD_KG, wire=WIRE, resistivity=FLEXINOL_RESISTIVITY)
    rp = simulate_plant(t, cur, load_kg=LOAD_KG, wire=WIRE, resistivity=FLEXINOL_WITH_RPHASE)
    heat = cur > 1.0
    k0, k1 = np.flatnonzero(heat)[[0, -1]]
    # heating stroke: from the cold loaded martensite to the hot austenite R falls a few %
    assert plain.martensite_fraction[k0] == 1.0 and plain.martensite_fraction[k1] < 1e-3
    fall = plain.resistance_ohm[k1] / plain.resistance_ohm[k0] - 1.0
    assert -0.08 < fall < -0.02, fall
    # cooling: with the R-phase, R rises ≈ 15 % between Rs and Rf while the wire is still short
    cool = ~heat & (t > t[k1])
    tt = transformation_temperatures_c(LOAD_KG, WIRE)
    before_ms = cool & (rp.temperature_c > tt["ms_c"] + 0.5)
    at_rs = before_ms & (rp.temperature_c > FLEXINOL_WITH_RPHASE.rs_c + 1.0)
    below_rs = before_ms & ~at_rs
    bump = rp.resistance_ohm[below_rs].max() / rp.resistance_ohm[at_rs][-1] - 1.0
    assert 0.10 < bump < 0.20, bump
    assert np.ptp(rp.position_mm[before_ms]) < 0.05  # no motion: the bump is no stroke
    no_bump = plain.resistance_ohm[below_rs].max() / plain.resistance_ohm[at_rs][-1] - 1.0
    assert no_bump < 0.0  # without the R-phase R only falls with the temperature there
    # the plant's R is resistance_ohm(ξ, T, strain = L/L0 - 1, wire, model, rphase(T, cooling))
    cooling = np.r_[False, np.diff(rp.temperature_c) < 0]
    ref = resistance_ohm(
        rp.martensite_fraction, rp.temperature_c, rp.length_mm / WIRE.length_mm - 1.0, WIRE,
        FLEXINOL_WITH_RPHASE, rphase_fraction(rp.temperature_c, cooling, FLEXINOL_WITH_RPHASE),
    )  # fmt: skip
    np.testing.assert_allclose(rp.resistance_ohm, ref, rtol=1e-12)
    np.testing.assert_allclose(rp.voltage_v, cur * rp.resistance_ohm, rtol=1e-15)
    # the Joule heat uses it: a higher R (R-phase) heats the next cycle's start differently,
    # and Plant.step gives the same trace as simulate_plant
    plant = Plant(LOAD_KG, WIRE, resistivity=FLEXINOL_WITH_RPHASE, seed=0)
    steps = [plant.step(DT_S, i).resistance_ohm for i in cur[:-1].tolist()]
    np.testing.assert_allclose(rp.resistance_ohm[1:], steps, rtol=1e-12)
    assert not np.allclose(plain.temperature_c, default.temperature_c, atol=0.5)


def test_plant_refuses_resistivity_with_phase_resistance_effect():
    from smabench.physics.plant import Effects

    with pytest.raises(ValueError, match="not both"):
        Plant(LOAD_KG, WIRE, Effects(phase_resistance=20.0), resistivity=FLEXINOL_RESISTIVITY)


# --------------------------------------------------------------------------- self-sensing
def test_resistance_threshold_and_branches():
    r = ss.resistance_from(np.array([0.0, 0.019, 0.02, 0.1, 1.4, np.nan]),
                           np.array([0.0, 0.01, 0.01, 0.05, 0.7, 0.1]))  # fmt: skip
    np.testing.assert_array_equal(np.isnan(r), [True, True, False, False, False, True])
    np.testing.assert_allclose(r[2:5], [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(ss.branch_of(np.array([0.05, 0.2, 0.21, 1.4])), [1, 1, 0, 0])


def test_major_cycles_held_out(bench):
    noise, _, sessions, cal = bench
    major = _pct(cal, sessions["major"])
    heat, cool = (cal.percent_of_stroke(cal.branch(b).rms_mm) for b in (0, 1))
    print(
        f"\n{noise:g}× chain noise: held-out major cycles {major:.2f} % of stroke "
        f"(calibration's own held-out RMS: heating {heat:.2f} %, cooling {cool:.2f} %)"
    )
    assert 2.4 < cal.stroke_mm < 2.9  # 4.5 % of 55 mm, less the elastic part
    assert major <= 3.0
    assert cal.heating.heldout and cal.cooling.heldout
    assert heat <= 3.0 and cool <= 3.0  # the stored uncertainty, held out by cycle


def test_partial_loops_need_the_reversal_rule(bench):
    noise, folders, sessions, cal = bench
    with_rule = _pct(cal, sessions["partial"])
    plain = _pct(ss.calibrate([folders["cal"]], reversal=False), sessions["partial"])
    print(
        f"\n{noise:g}× chain noise: partial loops {with_rule:.2f} % of stroke with the "
        f"reversal rule, {plain:.2f} % with the plain per-branch map"
    )
    assert with_rule <= (4.0 if noise == 1.0 else 5.0)
    assert plain > 2.0 * with_rule


def test_load_off_calibration(bench):
    noise, _, sessions, cal = bench
    light, heavy = _pct(cal, sessions["light"]), _pct(cal, sessions["heavy"])
    print(
        f"\n{noise:g}× chain noise: map taken at {LOAD_KG:g} kg, used at "
        f"{0.5 * LOAD_KG:g} kg: {light:.2f} %, at {1.5 * LOAD_KG:g} kg: {heavy:.2f} % of stroke"
    )
    assert light <= 6.0 and heavy <= 6.0


def test_chosen_fit_not_worse_than_the_other_on_held_out_cycles(bench):
    noise, folders, sessions, cal = bench
    pchip = ss.calibrate([folders["cal"]], fit="pchip")
    poly, spline = _pct(cal, sessions["major"]), _pct(pchip, sessions["major"])
    print(
        f"\n{noise:g}× chain noise: held-out major, polynomial {poly:.2f} %, "
        f"monotone spline {spline:.2f} %"
    )
    assert cal.heating.kind == "poly"
    assert poly <= spline * (1.05 if noise == 1.0 else 1.3)
    assert spline <= 3.0  # both are good maps; the difference is small


def test_flagged_rows_are_not_learned_and_calibration_round_trips(bench):
    _, folders, sessions, cal = bench
    assert cal.x_range_mm[1] < 3.5  # the flagged rows' 40 mm never entered
    assert np.isnan(sessions["cal"].position_mm[1000:1040]).all()
    assert cal.sessions[0]["rows_used"] == cal.sessions[0]["rows"] - 65
    assert cal.load_kg == LOAD_KG and cal.wire["preset"] == "flexinol-0.38-70c"
    r_lo, r_hi = cal.r_range_ohm
    assert 0.46 < r_lo < r_hi < 0.53
    back = ss.SelfSenseCalibration.from_json(cal.to_json())
    assert back == cal
    d = json.loads(cal.to_json())
    assert d["schema_version"] == ss.SCHEMA_VERSION and d["filter_tau_s"] == ss.FILTER_TAU_S
    assert d["rms_mm"]["heating"] == cal.heating.rms_mm and d["sessions"][0]["path"].endswith("cal")
    s = sessions["major"]
    a = ss.SelfSenseEstimator(cal).estimate(s.t_s[:3000], s.current_a[:3000], s.voltage_v[:3000])
    b = ss.SelfSenseEstimator(back).estimate(s.t_s[:3000], s.current_a[:3000], s.voltage_v[:3000])
    np.testing.assert_array_equal(a, b)
    assert d["map"] == "branches" and cal.thermal is None  # no heat-balance temperature here
    with pytest.raises(ss.SelfSenseError, match="temperature_est_C"):
        ss.calibrate([folders["cal"]], map="thermal")


def test_update_and_estimate_are_identical(bench):
    _, _, sessions, cal = bench
    s = sessions["partial"]
    n = 6000
    t, i, v = s.t_s[:n].copy(), s.current_a[:n].copy(), s.voltage_v[:n].copy()
    i[:10] = 0.0  # no R yet: NaN
    i[2000:2050] = 0.0  # current off: the last estimate is held
    v[3000] = np.nan
    est = ss.SelfSenseEstimator(cal)
    one = np.array([est.update(a, b, c) for a, b, c in zip(t, i, v, strict=True)])
    arr = ss.SelfSenseEstimator(cal).estimate(t, i, v)
    np.testing.assert_array_equal(one, arr)
    assert np.isnan(arr[:10]).all() and np.isfinite(arr[10:]).all()
    assert np.all(arr[2000:2050] == arr[1999])
    # causal: the first samples do not change when later ones do
    v2 = v.copy()
    v2[4000:] *= 1.05
    np.testing.assert_array_equal(ss.SelfSenseEstimator(cal).estimate(t, i, v2)[:4000], arr[:4000])


def test_rphase_wire(plants):
    """With the R-phase bump (R +15 % on cooling before Ms): the maps still read major cycles;
    a reversal to heating inside the R-phase drops R at once (the model's memoryless R-phase),
    which the estimate reads as motion on partial loops."""
    sims = {k: _plant(MAJOR * n, model=FLEXINOL_WITH_RPHASE, seed=s)
            for k, n, s in (("cal", 6, 1), ("major", 3, 2))}  # fmt: skip
    sims["partial"] = _plant(PARTIAL, model=FLEXINOL_WITH_RPHASE, seed=3)
    arrays = {
        k: ss.SessionArrays(t, cur, _measured_v(tr, cur, 1.0, 7), tr.position_mm, cyc, k, LOAD_KG)
        for k, (t, cur, cyc, tr) in sims.items()
    }
    cal = ss.calibrate([arrays["cal"]])
    major, partial = _pct(cal, arrays["major"]), _pct(cal, arrays["partial"])
    print(f"\nR-phase wire, chain noise: major {major:.2f} %, partial {partial:.2f} % of stroke")
    assert cal.cooling.forward == -1  # on cooling R falls as the wire lengthens (after the bump)
    assert cal.heating.forward == -1
    assert major <= 3.0
    assert partial <= 8.0


# --------------------------------------------------------------------------- CLI
def test_cli_calibrate_and_estimate(plants, cli, tmp_path):
    rows = len(plants["cal"][0])
    folders = {
        "cal": _write(tmp_path / "cal", plants["cal"], 1.0, 100, LOAD_KG, np.r_[1000:1040]),
        "partial": _write(tmp_path / "partial", plants["partial"], 1.0, 102, LOAD_KG),
    }
    assert rows > 1040
    cal_json = tmp_path / "cal.json"
    proc = cli("selfsense", "calibrate", folders["cal"], "--out", cal_json)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert any(ln.strip().startswith("heating:") and "% of stroke" in ln for ln in lines)
    assert any(ln.strip().startswith("cooling:") and " mm = " in ln for ln in lines)
    cal = ss.SelfSenseCalibration.from_json(cal_json.read_text())
    out = tmp_path / "est.csv"
    proc = cli("selfsense", "estimate", "--calibration", cal_json, folders["partial"], "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "RMS error against the laser" in proc.stdout
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t_s", "position_mm", "position_est_mm"]
    n = len(load_session(folders["partial"]))
    assert len(rows) == n + 1
    est = np.array([float(r[2]) for r in rows[1:]])
    pos = np.array([float(r[1]) for r in rows[1:]])
    rms = np.sqrt(np.mean((est - pos) ** 2))
    assert cal.percent_of_stroke(rms) <= 4.0
    printed = re.search(r"= ([0-9.]+) % of stroke", proc.stdout)
    assert float(printed.group(1)) == pytest.approx(cal.percent_of_stroke(rms), abs=0.011)
    # the laser's blank rows stay blank
    proc = cli("selfsense", "estimate", "--calibration", cal_json, folders["cal"], "--out", out)
    assert proc.returncode == 0, proc.stderr
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[1001][1] == "" and rows[1001][2] != ""


def test_cli_refuses_bad_input_with_one_line(cli, tmp_path):
    t, cur, cyc = _profile(MAJOR)
    pos = np.linspace(0.0, 1.0, len(t))
    base = {"t_s": t, "current_A": cur, "position_mm": pos, "cycle": cyc}
    write_session(tmp_path / "novolt", {"load_kg": 2.0}, base)
    write_session(tmp_path / "short", {"load_kg": 2.0},
                  {k: v[:150] for k, v in {**base, "voltage_V": cur * 0.5}.items()})  # fmt: skip
    (tmp_path / "bad.json").write_text('{"schema_version": 99}')
    cases = [
        (["calibrate", tmp_path / "novolt", "--out", tmp_path / "c.json"], "voltage_V"),
        (["calibrate", tmp_path / "short", "--out", tmp_path / "c.json"], "at least 200"),
        (["calibrate", tmp_path / "missing", "--out", tmp_path / "c.json"], "no such session"),
        (["estimate", "--calibration", tmp_path / "bad.json", tmp_path / "short", "--out",
          tmp_path / "e.csv"], "schema 99"),
    ]  # fmt: skip
    for argv, needle in cases:
        proc = cli("selfsense", *argv)
        assert proc.returncode == 2, (argv, proc.stdout, proc.stderr)
        err = proc.stderr.strip()
        assert len(err.splitlines()) == 1 and needle in err, err
        assert err.startswith("smabench selfsense: error:")
    assert not (tmp_path / "c.json").exists() and not (tmp_path / "e.csv").exists()


# --------------------------------------------------------------------------- the benchmark
@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    """`smabench bench selfsense --noise 1` once (about 45 s of simulated sessions)."""
    from smabench.cli import main

    out = tmp_path_factory.mktemp("bench-selfsense") / "figures.json"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["bench", "selfsense", "--noise", "1", "--json", str(out)])
    return rc, buf.getvalue(), json.loads(out.read_text())


@pytest.mark.slow
def test_bench_selfsense_prints_every_figure_against_its_target(bench_run):
    rc, stdout, res = bench_run
    assert rc == 0
    figs = res["noise"]["1x"]
    assert res["targets"] == sb.TARGETS and set(sb.TARGETS) <= set(figs)
    lines = stdout.splitlines()
    for key in sb.TARGETS:
        assert any(ln.startswith(key) for ln in lines), stdout
    assert f"{sum(figs['met'].values())} of {len(sb.TARGETS)} targets met" in stdout
    # the estimation figures are the ones the tests above measure, and meet their targets
    for key in ("major_pct", "load_minus50_pct", "load_plus50_pct", "partial_pct"):
        assert figs[key] <= sb.TARGETS[key] and figs["met"][key], (key, figs[key])
    assert set(figs["tracking"]) == set(sb.SINES)
    assert all(s["laser_mm"] > 0 and s["resistance_mm"] > 0 for s in figs["tracking"].values())
    assert figs["hold_on_laser_mm"] < 0.05 and figs["fallback_hold_mm"] > 0


@pytest.mark.slow
def test_bench_selfsense_fallback_holds_the_position(bench_run):
    """The laser gone 60 s in a hold at mid-stroke: the wire stays within 5 % of the stroke on
    the thermal map (the heat balance's temperature taken out of R, readings weighted by their
    current); on the branch maps it walked 38 % (the resistivity's temperature read as motion)."""
    figs = bench_run[2]["noise"]["1x"]
    assert figs["met"]["fallback_hold_pct"], figs
    assert figs["fallback_hold_mm"] < 0.15 and figs["hold_on_laser_mm"] < 0.05, figs


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="open (issue 26): PID on the estimate tracks the control "
                   "table's 20 s sine 1.69× worse than on the laser (target 1.5×; the 10 s sine "
                   "1.17×): the thermal map's error follows the heat balance's temperature, "
                   "whose dynamics are not the plant's (0.05-0.1 mm behind the wire after each "
                   "current swing); the filter that weights the probe's readings trades it "
                   "against the hold (THERMAL_FILTER_REF_A); on the mock bench (--mock) 2.41×")
def test_bench_selfsense_tracking_target(bench_run):
    figs = bench_run[2]["noise"]["1x"]
    assert figs["met"]["tracking_ratio"], figs


# --------------------------------------------------------------------------- the thermal map
def test_thermal_map_recovers_the_temperature_coefficient_and_round_trips():
    """R = (0.50 − 0.012·x)(1 + 4e-4·(T − 20)) with T uncorrelated to x: the fit finds 4e-4 /K
    (on its 2.5e-5 grid) and x within 1 µm; the calibration file keeps the map, and a file
    without one (written before it existed) still loads."""
    from smabench.physics.selfsense import SelfSenseCalibration, ThermalMap, fit_thermal_map

    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 2.5, 2000)
    t = rng.uniform(20.0, 90.0, 2000)
    r = (0.50 - 0.012 * x) * (1.0 + 4e-4 * (t - 20.0))
    m = fit_thermal_map(r, t, x)
    assert m.tcr_per_k == pytest.approx(4e-4, abs=1e-9)
    assert m.rms_mm < 1e-3
    np.testing.assert_allclose(m(r, t), x, atol=1e-3)
    assert m.at(float(r[7]), float(t[7])) == pytest.approx(x[7], abs=1e-3)
    assert ThermalMap.from_dict(json.loads(json.dumps(m.to_dict()))) == m
    with pytest.raises(ss.SelfSenseError, match="at least"):
        fit_thermal_map(r[:50], t[:50], x[:50])
    d = json.loads(json.dumps(SelfSenseCalibration(
        ss.BranchMap("poly", 0.4, 0.5, 1, 1, coeffs=(0.0,)),
        ss.BranchMap("poly", 0.4, 0.5, 1, 1, coeffs=(0.0,)), x_range_mm=(0.0, 2.5),
        thermal=m).to_dict()))  # fmt: skip
    assert SelfSenseCalibration.from_dict(d).thermal == m
    del d["thermal"]
    assert SelfSenseCalibration.from_dict(d).thermal is None


def test_the_estimator_takes_the_thermal_map_only_with_a_temperature():
    """A wire held still while its temperature falls 20 K: R falls by the temperature
    coefficient alone. With the temperature the thermal map (the calibration's choice) holds
    the position; the same calibration set to the branch maps reads them."""
    from smabench.physics.selfsense import SelfSenseCalibration, SelfSenseEstimator, ThermalMap

    x_true = 1.0
    m = ThermalMap(4e-4, 0.5 - 0.012 * 1.25, 0.012, (1.25, -1.0), 0.0)  # x = 1.25 − u
    branch = ss.BranchMap("poly", 0.46, 0.50, -1, -1, coeffs=(0.0,))
    cal = SelfSenseCalibration(branch, branch, x_range_mm=(0.0, 2.5), thermal=m, map="thermal")
    est = SelfSenseEstimator(cal)
    x = math.nan
    for k in range(400):
        temp = 60.0 - 20.0 * k / 400
        r = (0.5 - 0.012 * x_true) * (1.0 + 4e-4 * (temp - 20.0))
        x = est.update(k * 0.005, 0.8, 0.8 * r, temp)
    # R filtered (20 ms), the temperature not: R lags the falling temperature by 20 ms here
    assert x == pytest.approx(x_true, abs=4e-3)
    assert math.isnan(SelfSenseEstimator(cal).update(0.0, 0.01, 0.005, 40.0))  # below 20 mA
    on_branches = SelfSenseEstimator(dataclasses.replace(cal, map="branches"))
    assert on_branches.update(0.0, 0.8, 0.8 * 0.488, 40.0) == branch.at(branch.r_end_ohm)
