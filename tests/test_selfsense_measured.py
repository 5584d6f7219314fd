"""Self-sensing checked on what we did not make (issue 26, item 8).

1. The resistance physics (``smabench.physics.resistance``) against a measured series of a real
   wire: run 5 of the Mecanon/morphing_wing ``experimental/TECA`` recordings (MIT; files, source
   and columns in tests/data/mecanon-teca-run5/README.md): a 0.381 mm (0.015") NiTi wire, 0.19 m,
   heated by 36 steps of the supply's set voltage (1.0 … 4.5 V, 32 s each) while an Arduino logs
   the current and a FLIR A320 the hottest pixel's temperature. Heating only: no cooling, so no
   R-phase bump and no cooling branch can be checked; no position either, so the estimator
   cannot be run on it.
2. The estimator (``smabench.selfsense``) on a second simulator written apart
   (tests/selfsense_sim_apart.py: tanh branches with a reversal stack, its own R law, 1/f noise,
   spikes, another ADC and probe current): calibrated on major cycles, estimating held-out major
   cycles, partial loops and ±50 % load against the issue's targets (3, 4 and 6 % of stroke).

Every figure is printed (``pytest -s`` shows them): how far we are.
"""

from __future__ import annotations

import ast
import datetime as dt
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import selfsense_sim_apart as apart

from smabench import selfsense as ss
from smabench.physics.resistance import FLEXINOL_RESISTIVITY, resistance_ohm
from smabench.physics.wire import FLEXINOL_038_70C

DATA = Path(__file__).parent / "data" / "mecanon-teca-run5"

# --------------------------------------------------------------------------- measured series
# From the authors' own analysis script, experimental/TECA/read_data.py at commit
# 56e7f4ace40fa0936379507fc9662fe5a8d3582a (the version that reads run 5):
WIRE_LENGTH_M = 0.19  # "L = 0.19"
WIRE_DIAMETER_M = 0.000381  # "r = 0.000381/2."
AS_C, AF_C = 66.87, 89.68  # "A_s = 66.87", "A_f = 89.68"
SETTLE_ROWS = 20  # "N = 20": readings ignored at the start of each voltage step
# "There is a voltage offset": the set voltage minus this is the wire's voltage, mV
AUTHORS_OFFSET_MV = 1210.07069871 + 474.710578241 - 949.421156482 - 504.768862708
# The same repository's isobaric test at 50 MPa (experimental/TECA/filtered_data_50MPa.txt,
# columns temperature °C, strain, stress MPa), which that script uses for this run's length:
# strain 0.041256 at 30.2 °C (first row), 0 from 138.5 °C on: the transformation strain.
TRANSFORMATION_STRAIN = 0.041256
# Steps 1.1 and 1.2 V: at 18:55:13, mid-step, the current jumps from 553.85 to 629.65 mA (+14 %)
# at a constant set voltage while the temperature moves by 0.1 K (and back down in the 1.3 V
# step): an event of the supply or the contacts, not of the wire. Left out of the fits.
EVENT_STEPS_MV = (1100.0, 1200.0)


def _clock_s(hms: str) -> int:
    t = dt.datetime.strptime(hms, "%H:%M:%S")
    return t.hour * 3600 + t.minute * 60 + t.second


def _read_electric() -> np.ndarray:
    """(clock s, set voltage mV, current mA) per reading, as the Arduino logged them."""
    rows = []
    for line in (DATA / "untrained_wire_voltage_current_run5.txt").read_text().splitlines():
        stamp, _, rest = line.partition("\t")
        if not rest or "Calibrating" in rest:
            continue
        v_mv, i_ma = rest.split()
        rows.append((_clock_s(stamp.split()[1]), float(v_mv), float(i_ma)))
    return np.array(rows)


def _read_ir() -> np.ndarray:
    """(clock s with ms, temperature °C) of the IR camera's hottest pixel (decimal commas)."""
    lines = (DATA / "untrained_wire_temperature_run5_subset.txt").read_text().splitlines()
    start = lines.index("Date\tTime\tMilliseconds\tRelative time\tImage.Max.") + 1
    rows = []
    for line in lines[start:]:
        _, hms, ms, _, temp = line.split("\t")
        rows.append((_clock_s(hms) + int(ms) / 1000.0, float(temp.replace(",", "."))))
    return np.array(rows)


def _steps() -> dict[str, np.ndarray]:
    """Per voltage step, as the authors reduce it: the readings after the first 20, their mean
    current (mA, and its standard error) and the mean IR temperature over the same seconds."""
    elec, ir = _read_electric(), _read_ir()
    out: dict[str, list[float]] = {k: [] for k in ("v_mv", "i_ma", "i_se_ma", "t_c", "n_ir")}
    for v in np.unique(elec[:, 1]):
        keep = elec[elec[:, 1] == v][SETTLE_ROWS:]
        t0, t1 = keep[0, 0], keep[-1, 0] + 1.0
        temps = ir[(ir[:, 0] >= t0) & (ir[:, 0] < t1), 1]
        out["v_mv"].append(v)
        out["i_ma"].append(keep[:, 2].mean())
        out["i_se_ma"].append(keep[:, 2].std(ddof=1) / math.sqrt(len(keep)))
        out["t_c"].append(temps.mean())
        out["n_ir"].append(len(temps))
    return {k: np.array(v) for k, v in out.items()}


def _offsets_mv(s: dict[str, np.ndarray]) -> dict[str, float]:
    """Candidate offsets between the set voltage and the wire's voltage, mV: the authors', and
    the intercepts of V = V0 + R·I fitted over the martensite steps (below As) and over the
    austenite steps (above Af), the event steps left out. The spread of what follows over these
    offsets is the measurement's own uncertainty. (One line through all steps is no candidate:
    R falls by ≈ 10 % between the two phases, so its intercept is biased, 361 mV.)"""
    ok = ~np.isin(s["v_mv"], EVENT_STEPS_MV)
    sets = {"martensite fit": ok & (s["t_c"] < AS_C), "austenite fit": ok & (s["t_c"] > AF_C)}
    out = {"authors": AUTHORS_OFFSET_MV}
    for name, m in sets.items():
        out[name] = float(np.polyfit(s["i_ma"][m], s["v_mv"][m], 1)[1])
    return out


@pytest.fixture(scope="module")
def measured():
    s = _steps()
    offsets = _offsets_mv(s)
    r = {name: (s["v_mv"] - v0) / s["i_ma"] for name, v0 in offsets.items()}  # Ω (mV/mA)
    # the steps within 15 K below As (martensite, loaded) and within 15 K above Af (austenite):
    # 5 and 4 steps, whose means smooth the step-to-step scatter of R (≈ 2 %, printed)
    pre = np.flatnonzero((s["t_c"] > AS_C - 15.0) & (s["t_c"] < AS_C))
    post = np.flatnonzero((s["t_c"] > AF_C) & (s["t_c"] < AF_C + 15.0))
    return s, offsets, r, pre, post


def test_measured_series_is_what_the_readme_says(measured):
    s, offsets, _, pre, post = measured
    assert len(s["v_mv"]) == 36 and s["v_mv"][0] == 1000.0 and s["v_mv"][-1] == 4500.0
    assert np.all(s["n_ir"] >= 4)  # each step's settled part has IR rows (every 2 s)
    assert np.all(np.diff(s["t_c"][2:]) > -2.0)  # heating only (IR noise ±1-2 K)
    assert len(pre) >= 4 and len(post) >= 3
    print("\nmeasured steps (set mV, I mA, T_IR °C, R Ω with the authors' offset "
          f"{AUTHORS_OFFSET_MV:.1f} mV):")  # fmt: skip
    for v, i, t in zip(s["v_mv"], s["i_ma"], s["t_c"], strict=True):
        print(f"  {v:6.0f} {i:8.1f} {t:6.1f} {(v - AUTHORS_OFFSET_MV) / i:.4f}")
    print("offsets V0 (mV): " + ", ".join(f"{k} {v:.1f}" for k, v in offsets.items()))


def _model_wire(strain: float):
    """smabench's 0.38 mm Flexinol wire whose loaded length is the measured 0.19 m."""
    return replace(FLEXINOL_038_70C, radius_m=0.5 * WIRE_DIAMETER_M,
                   length_m=WIRE_LENGTH_M / (1.0 + strain))  # fmt: skip


@pytest.mark.xfail(
    strict=True,
    reason="measured 8.10 … 8.47 Ω/m (offsets) at 58.7 °C, loaded (ε 4.1 %); smabench 8.75 Ω/m, "
    "3 … 8 % high, just outside the ±3 % for the length: FLEXINOL_RESISTIVITY's ρ_M (94 µΩ·cm, "
    "from Dynalloy's 8.3 Ω/m table) is above this wire's (≈ 87 … 91 µΩ·cm)",
)
def test_measured_resistance_per_metre_of_cold_loaded_wire(measured):
    """The level: R per metre over the steps within 15 K below As (martensite, loaded).

    Tolerance: the spread over the offsets (the set voltage is not the wire's voltage) widened by
    3 % for the length, given to two digits (0.19 m ± 0.005 m)."""
    s, _, r, pre, _ = measured
    per_m = {k: float(np.mean(v[pre])) / WIRE_LENGTH_M for k, v in r.items()}
    lo, hi = min(per_m.values()) * 0.97, max(per_m.values()) * 1.03
    t_pre = float(np.mean(s["t_c"][pre]))
    wire = _model_wire(TRANSFORMATION_STRAIN)
    r_model = resistance_ohm(1.0, t_pre, TRANSFORMATION_STRAIN, wire, FLEXINOL_RESISTIVITY)
    model = r_model / WIRE_LENGTH_M
    print(
        f"\nR per metre at {t_pre:.1f} °C (martensite, loaded): measured "
        + ", ".join(f"{k} {v:.2f}" for k, v in per_m.items())
        + f" Ω/m; smabench (FLEXINOL_RESISTIVITY, ε {TRANSFORMATION_STRAIN:.3f}) {model:.2f} Ω/m "
        f"({100 * (model / per_m['authors'] - 1):+.1f} % against the authors' offset)"
    )
    assert lo <= model <= hi


def _measured_drop(r: dict[str, np.ndarray], pre: np.ndarray, post: np.ndarray) -> dict[str, float]:
    """ΔR/R, %, from the mean of the steps within 15 K below As to those within 15 K above Af."""
    return {k: 100.0 * (float(np.mean(v[post])) / float(np.mean(v[pre])) - 1.0)
            for k, v in r.items()}  # fmt: skip


def _model_drop(t_pre: float, t_post: float, strain: float) -> float:
    """smabench's ΔR/R, %, over the same temperatures: cold loaded martensite (ξ 1, ε = the
    transformation strain) to austenite (ξ 0, ε 0; the elastic strain at 50 MPa, 0.1-0.2 %, is
    left out on both sides)."""
    w = _model_wire(strain)
    r_pre = resistance_ohm(1.0, t_pre, strain, w, FLEXINOL_RESISTIVITY)
    r_post = resistance_ohm(0.0, t_post, 0.0, w, FLEXINOL_RESISTIVITY)
    return 100.0 * (r_post / r_pre - 1.0)


@pytest.mark.xfail(
    strict=True,
    reason="measured ΔR/R over the transformation -9.1 … -10.7 % (offsets), smabench's R law "
    "with the measured 4.1 % strain -5.0 % (-3.9 … -5.7 % for 3.5 … 4.5 %): FLEXINOL_RESISTIVITY's "
    "ρ_A/ρ_M = 95/94 (assumed, calibrated on a hobby figure of -3 %) is too high for this wire; "
    "its drop implies ρ_A/ρ_M ≈ 0.95 … 0.97 at the same temperature",
)
def test_measured_drop_over_the_transformation(measured):
    """The size: ΔR/R from below As to above Af on heating (means over 15 K each side).

    Tolerance ±1.5 points around the measured spread over the offsets: the current's standard
    error per step is 0.1-0.6 % (±0.5 point on the ratio), the IR temperature's ±1-2 K moves the
    model's TCR term by < 0.1 point, and the strain of this run is the 50 MPa test's (the model's
    figure moves by ±0.9 point for ±0.5 % strain, printed)."""
    s, _, r, pre, post = measured
    meas = _measured_drop(r, pre, post)
    t_pre, t_post = float(np.mean(s["t_c"][pre])), float(np.mean(s["t_c"][post]))
    model = _model_drop(t_pre, t_post, TRANSFORMATION_STRAIN)
    band = [_model_drop(t_pre, t_post, e) for e in (0.035, 0.045)]
    print(
        f"\nΔR/R {t_pre:.1f} → {t_post:.1f} °C (As {AS_C}, Af {AF_C}): measured "
        + ", ".join(f"{k} {v:+.1f} %" for k, v in meas.items())
        + f"; smabench {model:+.1f} % (strain 3.5 … 4.5 %: {band[0]:+.1f} … {band[1]:+.1f} %)"
    )
    assert min(meas.values()) - 1.5 <= model <= max(meas.values()) + 1.5


def test_measured_drop_lies_between_as_and_af(measured):
    """Where: R keeps the martensite level up to As and has the austenite level from Af on, as in
    the model (ξ moves between As and Af only). For every offset: each step more than 3 K below
    As (the IR scatter, ±1-2 K, and 2-4 K between steps) lies above the half-way level between the
    two means, each step above Af below it.

    Not asserted, printed: how the drop is spread. On the IR temperature it is 90 % done a few K
    above As, well before Af, whereas the model's drop (and the 50 MPa strain of the same wire,
    chamber thermocouple) spans As … Af; a Joule-heated 0.38 mm wire seen by a 320 × 240 camera
    at 1 m is not a thermometer to trust during the transformation (sub-pixel wire, emissivity
    set to 0.95, the latent-heat plateau at 66-68 °C), so this is no evidence for or against the
    model's shape."""
    s, _, r, pre, post = measured
    ok = ~np.isin(s["v_mv"], EVENT_STEPS_MV)
    below, above = ok & (s["t_c"] < AS_C - 3.0), s["t_c"] > AF_C
    for name, rv in r.items():
        half = 0.5 * (np.mean(rv[pre]) + np.mean(rv[post]))
        assert np.all(rv[below] > half) and np.all(rv[above] < half), name
    rv = r["authors"]
    level = (np.mean(rv[pre]) - rv) / (np.mean(rv[pre]) - np.mean(rv[post]))
    first = np.flatnonzero(ok & (s["t_c"] > AS_C - 3.0) & (level >= 0.9))[0]
    t90 = float(s["t_c"][first])
    x90 = math.acos(1.0 - 2.0 * 0.9) / math.pi  # the plant's cosine ξ(T): 90 % at As + x90·ΔT
    scatter = 100.0 * np.std(rv[below], ddof=1) / np.mean(rv[below])
    print(
        f"\n90 % of the drop reached at T_IR {t90:.1f} °C, the model's at "
        f"{AS_C + x90 * (AF_C - AS_C):.1f} °C (As {AS_C}, Af {AF_C}); R's step-to-step scatter "
        f"below As {scatter:.1f} % (authors' offset)"
    )


def test_measured_series_has_no_cooling_and_no_position():
    """What the series cannot check, said by a test so that it is not forgotten: the R-phase
    bump on cooling and the estimator need a cooling branch and a position; run 5 has neither
    (the set voltage only rises; no length sensor)."""
    s = _steps()
    assert np.all(np.diff(s["v_mv"]) > 0)
    cols = (DATA / "untrained_wire_voltage_current_run5.txt").read_text().splitlines()[1]
    assert len(cols.split("\t")[1].split()) == 2  # set voltage, current: nothing else


# --------------------------------------------------------------------------- simulator apart
W = apart.ApartWire()
LOAD_KG = 1.2  # 156 MPa on 0.31 mm
MAJOR = [(6.0, "heat"), (14.0, "probe")]
# heating cut short inside the transformation (2.2-2.8 s at 1 A from ~37 °C), cooling cut short
# inside it (6.0-7.2 s at the probe current from ~110 °C), between full cycles
PARTIAL = [
    *MAJOR, (2.5, "heat"), (14.0, "probe"), (6.0, "heat"), (6.6, "probe"), (6.0, "heat"),
    (14.0, "probe"), (2.2, "heat"), (14.0, "probe"), (6.0, "heat"), (7.2, "probe"),
    (2.8, "heat"), (14.0, "probe"), (6.0, "heat"), (6.0, "probe"), (2.4, "heat"), (9.0, "probe"),
    *MAJOR,
]  # fmt: skip


def _session(base: Path, name: str, w: apart.ApartWire, phases, load_kg: float, seed: int):
    t, cur = apart.profile(phases, w)
    sim = apart.simulate(w, load_kg, t, cur, apart.Noise(), seed)
    return apart.write(base / name, w, load_kg, t, cur, sim)


def _bench(tmp_path_factory, w: apart.ApartWire, tag: str):
    """Sessions written to disk in smabench's format; the map calibrated from the 'cal' folder
    (six major cycles at 1.2 kg); the others estimated with it."""
    base = tmp_path_factory.mktemp(tag)
    specs = {"cal": (MAJOR * 6, LOAD_KG, 11), "major": (MAJOR * 3, LOAD_KG, 12),
             "partial": (PARTIAL, LOAD_KG, 13), "light": (MAJOR * 3, 0.5 * LOAD_KG, 14),
             "heavy": (MAJOR * 3, 1.5 * LOAD_KG, 15)}  # fmt: skip
    folders = {name: _session(base, name, w, phases, load, seed)
               for name, (phases, load, seed) in specs.items()}  # fmt: skip
    cal = ss.calibrate([folders["cal"]])
    pct = {k: cal.percent_of_stroke(ss.estimate_session(cal, folders[k]).rms_mm)
           for k in ("major", "partial", "light", "heavy")}  # fmt: skip
    heat, cool = (cal.percent_of_stroke(cal.branch(b).rms_mm) for b in (0, 1))
    print(
        f"\nsimulator apart ({tag}): stroke {cal.stroke_mm:.3f} mm; held-out major cycles "
        f"{pct['major']:.2f} %, partial loops {pct['partial']:.2f} %, map at {LOAD_KG:g} kg "
        f"used at {0.5 * LOAD_KG:g} kg {pct['light']:.2f} %, at {1.5 * LOAD_KG:g} kg "
        f"{pct['heavy']:.2f} % of stroke (calibration's held-out RMS: heating {heat:.2f} %, "
        f"cooling {cool:.2f} %)"
    )
    return pct


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """The simulator apart as built (with its R-phase bump)."""
    return _bench(tmp_path_factory, W, "as built")


@pytest.fixture(scope="module")
def bench_no_rphase(tmp_path_factory):
    """The same without the R-phase bump: what the bump costs."""
    return _bench(tmp_path_factory, apart.replace(W, rphase_bump=0.0), "no R-phase")


def test_simulator_apart_imports_nothing_of_the_plant():
    tree = ast.parse(Path(apart.__file__).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if m.startswith("smabench") and m != "smabench.sessions"], names


def test_simulator_apart_has_return_point_memory_and_its_own_r_law():
    """An inner loop closes on the outer branch (Madelung's rules), and R over a full heating
    stroke falls by its own law's ≈ 11 % (the project's preset: ≈ 3 %)."""
    h = apart._Hysteresis(W, 0.0)
    path = np.r_[np.linspace(25, 80, 300), np.linspace(80, 66, 100), np.linspace(66, 74, 100),
                 np.linspace(74, 66, 100), np.linspace(66, 95, 300)]  # fmt: skip
    xi = np.array([h.update(float(t)) for t in path])
    # the inner loop 66 → 74 → 66 returns to where it started, and heating on past 80 °C rejoins
    # the curve that reached 80 °C the first time: ξ(80) on the way out = ξ(80) on the way in
    assert abs(xi[599] - xi[399]) < 1e-3, (xi[399], xi[599])
    k_in = 299
    k_out = 600 + int(np.argmin(np.abs(path[600:] - 80.0)))
    assert abs(xi[k_out] - xi[k_in]) < 0.01, (xi[k_in], xi[k_out])
    assert xi[-1] < 0.05 and xi[0] == 1.0
    t, cur = apart.profile(MAJOR, W)
    sim = apart.simulate(W, LOAD_KG, t, cur, None, 0)
    heat = cur > 0.5
    r = sim["resistance_ohm"]
    before = r[heat & (sim["xi"] > 0.999)].max()
    after = r[heat & (sim["xi"] < 0.001)].min()
    stroke = np.ptp(sim["position_mm"])
    print(
        f"\nsimulator apart at {LOAD_KG:g} kg: stroke {stroke:.2f} mm, R {before:.4f} → "
        f"{after:.4f} Ω on heating ({100 * (after / before - 1):+.1f} %)"
    )
    assert -0.14 < after / before - 1.0 < -0.09
    assert 3.0 < stroke < 3.6


TARGETS = {"major": 3.0, "partial": 4.0, "light": 6.0, "heavy": 6.0}
RPHASE = (
    "the R-phase bump (6 %, 9 K above the cooling branch's middle, moving with stress at "
    "0.05 K/MPa) overlaps the start of the martensite under load: at 1.2 kg R rises 4.8 % "
    "while the position has moved 7 % of the stroke, and the cooling map reads that as "
    "motion (cooling branch 5.9 %); without the bump 1.01 % / 1.17 %; the noise (white, 1/f, "
    "spikes, 14-bit ADC) costs 0.3 point (0.01 of it the spikes)"
)
LOAD = (
    "the transformation strain grows with stress here (3.1, 3.9, 4.1 % at 78, 156, 234 MPa, "
    "as in the Mecanon isobaric tests) and the loop moves 11 K: a map taken at one load reads "
    "another's stroke wrong; the plant keeps ε_L constant (2.6-2.8 % there)"
)


@pytest.mark.xfail(strict=True, reason="held-out major cycles 4.68 % of stroke > 3 %: " + RPHASE)
def test_apart_major_cycles_held_out(bench):
    assert bench["major"] <= TARGETS["major"]


@pytest.mark.xfail(strict=True, reason="partial loops 4.75 % of stroke > 4 %: " + RPHASE)
def test_apart_partial_loops(bench):
    assert bench["partial"] <= TARGETS["partial"]


@pytest.mark.xfail(
    strict=True,
    reason="±50 % load 8.38 % (0.6 kg) and 11.83 % (1.8 kg) of stroke "
    "> 6 %: " + LOAD + "; the R-phase adds to it (6.56 / 7.66 % without)",
)
def test_apart_load_off_calibration(bench):
    assert bench["light"] <= TARGETS["light"] and bench["heavy"] <= TARGETS["heavy"]


def test_apart_without_rphase_major_and_partial(bench_no_rphase):
    assert bench_no_rphase["major"] <= TARGETS["major"]
    assert bench_no_rphase["partial"] <= TARGETS["partial"]


@pytest.mark.xfail(
    strict=True,
    reason="±50 % load without the R-phase 6.56 % (0.6 kg) and 7.66 % "
    "(1.8 kg) of stroke > 6 %: " + LOAD,
)
def test_apart_without_rphase_load_off_calibration(bench_no_rphase):
    assert bench_no_rphase["light"] <= TARGETS["light"]
    assert bench_no_rphase["heavy"] <= TARGETS["heavy"]
