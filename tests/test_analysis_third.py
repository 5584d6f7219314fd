"""smabench analyze on sessions from ``tests/third_sim.py``: a third simulator written apart from
the project's plant and from ``independent_sim`` (Tanaka exponential kinetics with rate-dependent
nucleation, Heun integration, latent heat as an effective heat capacity, a temperature
coefficient of resistance, Q ∝ ΔT^1.25, per-phase thermal expansion, logarithmic residual strain,
a first-order sensor lag, a pulley dead band, 50 Hz with jitter). Its parameters were fixed from
the physics before the analysis was run on it.

Also: two effects hidden at once (stress shift with latent heat, stress shift with cycle
drift) must both be named, in ``causes``. Slow: each case runs the whole analysis."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import third_sim as ts

from smabench.analysis.candidates import REGISTRY
from smabench.analysis.cli import main
from smabench.analysis.core import DRIFT_CYCLES

pytestmark = pytest.mark.slow

# effect: (low, high, relative tolerance of the headline (None: a law of another form),
# stresses MPa, cycles)
CASES = {
    "phase_resistance": (15.0, 40.0, 0.30, [170.0], 12),
    "latent_heat": (15e3, 35e3, 0.30, [170.0], 12),
    "stress_shift": (5.0, 12.0, 0.20, [90.0, 250.0], 12),
    "convection_nonlinear": (0.2, 0.33, None, [170.0], 12),
    "sensor_lag": (0.3, 1.0, 0.35, [170.0], 12),
    "ambient_drift": (4.0, 10.0, 0.35, [170.0], 30),
    "cycle_drift": (3e-4, 1.5e-3, 0.35, [170.0], 12),
}
OUTSIDE = {"pulley_deadband": (0.04, 0.1, [170.0], 12)}
"""Effects outside the analysis' list: the right verdict is ``unexplained``."""


def expected(effect: str, value: float) -> float | None:
    """The headline the analysis should report for the simulator's effect value."""
    if effect == "stress_shift":  # C_A = 1.1 C, C_M = 0.9 C: the loop's centre moves by the mean
        return 1.0 / (0.5 * (1.0 / (1.1 * value) + 1.0 / (0.9 * value)))
    if effect == "cycle_drift":  # a·ln(1 + N): the mean residual strain per cycle over 10
        return value * math.log(1.0 + DRIFT_CYCLES) / DRIFT_CYCLES
    if CASES[effect][2] is None:
        return None
    return value


def sessions(tmp_path, effects: dict[str, float], stresses, seed: int, n_cycles: int):
    rng = np.random.default_rng(seed)
    world = ts.World.draw(rng, **effects)
    folders = []
    for j, load in enumerate(ts.loads_for(world, stresses)):
        folder = tmp_path / f"s{j}"
        ts.make(folder, effects, load, seed + j, n_cycles=n_cycles, world=world)
        folders.append(str(folder))
    return folders


def analyse(tmp_path, effects, stresses, seed, n_cycles=12):
    folders = sessions(tmp_path, effects, stresses, seed, n_cycles)
    out = tmp_path / "a.json"
    assert main([*folders, "--json", str(out), "-q"]) == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize("effect", ["latent_heat", "phase_resistance", "cycle_drift"])
def test_hidden_effect_is_named(tmp_path, effect):
    lo, hi, tol, stresses, n_cycles = CASES[effect]
    k = sorted(CASES).index(effect)
    value = float(np.random.default_rng(3000 + k).uniform(lo, hi))
    doc = analyse(tmp_path, {effect: value}, stresses, seed=600 + k, n_cycles=n_cycles)
    key = REGISTRY[effect].headline
    fitted = doc["parameters"].get(key, {}).get("value")
    print(effect, value, doc["cause"], doc["runner_up"], f"gain {doc['gain']:.2f}", fitted)
    assert doc["cause"] == effect, doc["reason"]
    assert fitted == pytest.approx(expected(effect, value), rel=tol)


def test_flat_resistance_rules_out_phase_resistance(tmp_path):
    """Latent heat and a flat V/I: phase_resistance may fit the position, but the voltage says
    the resistance does not follow ξ, so it can never be named or block the verdict."""
    doc = analyse(tmp_path, {"latent_heat": 30e3}, [170.0], seed=610)
    assert doc["cause"] == "latent_heat", doc["reason"]
    pr = doc["candidates"]["phase_resistance"]
    assert not pr["significant"]


@pytest.mark.parametrize(("second", "value"), [("latent_heat", 25e3), ("cycle_drift", 1e-3)],
                         ids=["stress+latent", "stress+drift"])  # fmt: skip
def test_two_effects_are_both_named(tmp_path, second, value):
    """Two effects hidden at once in the third team's sessions: both named in ``causes``, each
    with its incremental gain and p over the causes before it; ``cause`` stays the first. (The
    same claim on smabench's own plant was in test_analysis.py: it proved nothing this one does
    not, on a simulator we did not write, for 50 s of CI.)"""
    doc = analyse(tmp_path, {"stress_shift": 7.0, second: value}, [90.0, 250.0], seed=620)
    named = [c["cause"] for c in doc["causes"]]
    print(named, [round(c["incremental_gain"], 3) for c in doc["causes"]], doc["flags"])
    assert set(named) == {"stress_shift", second}, doc["reason"]
    assert doc["cause"] == named[0]
    assert all(c["incremental_gain"] >= 0.15 and c["p_value"] < 0.01 for c in doc["causes"])


def test_no_effect_is_none_when_the_wires_rate_dependent_kinetics_explain_it(tmp_path):
    """No hidden effect. The baseline misses the third team's nucleation, which waits
    κ·√|dT/dt| (its heating rates vary from pulse to pulse) and leaves structure no candidate
    removes; with transformation temperatures that move with the rate the held-out error is
    within the floor, so the verdict is ``none``, and κ is recovered."""
    doc = analyse(tmp_path, {}, [170.0], seed=5)
    kin = doc["kinetics"]
    print(doc["reason"], kin)
    assert doc["cause"] == "none", doc["reason"]
    assert doc["test"]["structured_baseline"] and kin["within_floor"]
    kappa = ts.World.draw(np.random.default_rng(5)).kappa
    assert kin["rate_shift_k"] == pytest.approx(kappa, rel=0.25)


def test_a_cause_hidden_under_the_wires_kinetics_is_named_on_top_of_them(tmp_path):
    """Convection ∝ ΔT^1.25 where the baseline's miss of the nucleation delay dilutes every
    candidate's gain (sweep draw 8539: `unexplained` before): no candidate passes over the
    baseline, the rate-dependent kinetics leave structure, and on top of them convection
    passes the same test, so it is named, over ``rate_kinetics``."""
    lo, hi = CASES["convection_nonlinear"][:2]
    value = float(np.random.default_rng(8539).uniform(lo, hi))
    doc = analyse(tmp_path, {"convection_nonlinear": value}, [170.0], seed=8539)
    print(doc["reason"])
    assert doc["cause"] == "convection_nonlinear", doc["reason"]
    assert [c["cause"] for c in doc["causes"]] == ["convection_nonlinear"]
    assert doc["causes"][0]["over"] == "rate_kinetics"
    assert not doc["kinetics"]["within_floor"]
    assert not doc["candidates"]["convection_nonlinear"]["significant"]  # not over the baseline


@pytest.mark.parametrize(("effect", "seed", "want"),
                         [("phase_resistance", 8416, ["phase_resistance"]),
                          ("none", 47639, [])], ids=["drift-on-top", "lag-on-none"])  # fmt: skip
def test_no_cause_is_added_that_is_not_there(tmp_path, effect, seed, want):
    """Two wrong names a second sweep (seed 1) found: a room drift of −4 … −11 K/h added on top
    of a large phase resistance at p = 0.006 (a cause on top is now tested at α / the number
    tried there), and a sensor lag named on a no-effect session where the kinetic rival's fit
    had stalled in one fold (it now also starts from the sensor fit's solution). The drift on
    top came back with TAU_STARTS and went with TRAINING_ONLY (the first cycle trains every
    fold)."""
    effects = {}
    if effect != "none":
        lo, hi = CASES[effect][:2]
        effects = {effect: float(np.random.default_rng(seed).uniform(lo, hi))}
    doc = analyse(tmp_path, effects, [170.0], seed=seed)
    print(doc["reason"])
    assert [c["cause"] for c in doc["causes"]] == want, doc["reason"]
    assert doc["cause"] == (want[0] if want else doc["cause"])
    assert doc["cause"] not in ("sensor_lag", "ambient_drift")
