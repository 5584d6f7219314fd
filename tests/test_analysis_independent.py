"""smabench analyze on sessions from ``tests/independent_sim.py``: a simulator written apart from
smabench.physics (Preisach hysteresis with erf-shaped branches and wiping-out memory, RK4 heat
balance, material values drawn per session, a Voigt modulus, the effects in textbook forms of
their own). Passing here means the analysis answers to the physics, not to the quirks of the
project's plant. Effect magnitudes are drawn at random within physical ranges (seeded)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from independent_sim import WireWorld, make, make_thermo

from smabench.analysis.cli import main
from smabench.analysis.core import EFFECT_PARAMETER

pytestmark = pytest.mark.slow

# effect: (low, high, relative tolerance of the headline parameter, loads kg, cycles)
CASES = {
    "phase_resistance": (15.0, 40.0, 0.25, [2.0], 9),
    "latent_heat": (15e3, 35e3, 0.25, [2.0], 9),
    "stress_shift": (5.0, 12.0, 0.15, [1.0, 3.0], 9),
    "convection_nonlinear": (0.005, 0.02, 0.25, [2.0], 9),
    "sensor_lag": (0.3, 1.0, 0.35, [2.0], 9),
    "ambient_drift": (4.0, 10.0, 0.30, [2.0], 30),
    "cycle_drift": (2e-4, 8e-4, 0.30, [2.0], 9),
}


def expected(effect: str, value: float) -> float:
    """The headline parameter the analysis should report for the simulator's effect value."""
    if effect == "stress_shift":
        # the simulator moves the austenite temperatures by Δσ/(1.15 s) and the martensite ones
        # by Δσ/(0.85 s); the loop's centre moves by the mean of the two
        return 1.0 / (0.5 * (1.0 / (1.15 * value) + 1.0 / (0.85 * value)))
    return value


def analyse(tmp_path, effects: dict[str, float], loads, seed: int, n_cycles: int = 9):
    rng = np.random.default_rng(seed)
    world = WireWorld.draw(rng, **effects)
    folders = []
    for j, load in enumerate(loads):
        folder = tmp_path / f"s{j}"
        make(folder, effects, load, seed + j, n_cycles=n_cycles, world=world)
        folders.append(str(folder))
    out = tmp_path / "a.json"
    assert main([*folders, "--json", str(out), "-q"]) == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize("effect", sorted(CASES))
def test_hidden_effect_is_named(tmp_path, effect):
    lo, hi, tol, loads, n_cycles = CASES[effect]
    k = sorted(CASES).index(effect)
    rng = np.random.default_rng(2000 + k)
    value = float(rng.uniform(lo, hi))
    if effect == "ambient_drift" and rng.random() < 0.5:
        value = -value
    doc = analyse(tmp_path, {effect: value}, loads, seed=300 + k, n_cycles=n_cycles)
    fitted = doc["parameters"].get(EFFECT_PARAMETER[effect], {}).get("value")
    print(effect, value, doc["cause"], doc["runner_up"], f"gain {doc['gain']:.2f}", fitted)
    if effect == "sensor_lag" and doc["cause"] == "unexplained":
        # named only when it beats equal kinetic lags and a dead time of ξ (a sensor also
        # delays the thermal expansion and the rests): an honest miss, never another name
        assert "kinetic" in doc["candidates"]["sensor_lag"].get("ruled_out", ""), doc["reason"]
        return
    assert doc["cause"] == effect, doc["reason"]
    assert fitted == pytest.approx(expected(effect, value), rel=tol)
    assert doc["gain"] >= 0.30
    if effect == "stress_shift":  # the model-free shift of the two loops agrees
        own = doc["loop_shift_check"]["stress_rate_mpa_per_k"]
        assert fitted == pytest.approx(own, rel=0.15)


def test_no_effect_gives_none(tmp_path):
    doc = analyse(tmp_path, {}, [2.0], seed=400)
    assert doc["cause"] == "none", doc["reason"]


def test_friction_outside_the_list_is_unexplained(tmp_path):
    # 10–20 N: a deadband of 0.35–0.7 mm. Weaker friction on mostly complete cycles is absorbed
    # into the loop's width (a known detection limit, see docs/analysis.md)
    value = float(np.random.default_rng(2100).uniform(10.0, 20.0))
    doc = analyse(tmp_path, {"pulley_friction": value}, [2.0], seed=401)
    # never a candidate's name; `none` only where the baseline's held-out error is within its
    # floor (this draw, 13 N: the Tanaka/logistic branch shapes absorb it to 0.022 mm against
    # 0.026 mm, a detection limit stated in docs/analysis.md)
    assert doc["cause"] in ("unexplained", "none"), doc["reason"]
    if doc["cause"] == "none":
        assert doc["baseline_heldout_rmse_mm"] <= doc["test"]["floor_mm"]


@pytest.mark.parametrize("loads", [[1.2, 2.0], [1.0, 2.0, 3.0]], ids=["2 loads", "3 loads"])
def test_chamber_loops_give_the_stress_rate(tmp_path, loads):
    """Thermometer loops (one per load, as a tensile tester in a chamber records them); with
    three loads each is held out whole and predicted from the other two."""
    rng = np.random.default_rng(2200 + len(loads))
    value = float(rng.uniform(5.0, 12.0))
    world = WireWorld.draw(rng, stress_shift=value)
    folders = [str(make_thermo(tmp_path / f"l{j}", world, load, 500 + j))
               for j, load in enumerate(loads)]  # fmt: skip
    out = tmp_path / "a.json"
    assert main([*folders, "--json", str(out), "-q"]) == 0
    doc = json.loads(out.read_text())
    fitted = doc["parameters"]["stress_rate_mpa_per_k"]["value"]
    print(loads, value, expected("stress_shift", value), fitted)
    assert doc["cause"] == "stress_shift", doc["reason"]
    assert fitted == pytest.approx(expected("stress_shift", value), rel=0.15)
    assert fitted == pytest.approx(doc["loop_shift_check"]["stress_rate_mpa_per_k"], rel=0.10)
