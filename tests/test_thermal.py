"""Heat balance eq. (16): exact step, profiles, steady state, inverses, online estimator."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from smabench.physics.thermal import (
    TemperatureEstimator,
    current_for_steady_temperature,
    current_for_trajectory,
    simulate_temperature,
    steady_state_temperature,
    step_exact,
    thermal_constants,
    time_constant_s,
)
from smabench.physics.wire import PAPER_WIRE

W = PAPER_WIRE


def _ode_step(temp0: float, current: float, dt: float, ambient: float) -> float:
    c, g = thermal_constants(W)
    r = W.resistance_mean_ohm

    def rhs(_t, y):
        return [(-g * (y[0] - ambient) + current**2 * r) / c]

    sol = solve_ivp(rhs, (0.0, dt), [temp0], method="DOP853", rtol=1e-12, atol=1e-12)
    return float(sol.y[0, -1])


@pytest.mark.parametrize(
    ("temp0", "current", "dt", "ambient"),
    [
        (22.0, 1.2, 0.001, 22.0),
        (22.0, 1.5, 3.0, 22.0),
        (95.0, 0.0, 5.0, 18.0),
        (60.0, 0.8, 20.0, 30.0),
    ],
)
def test_exact_step_matches_fine_ode(temp0, current, dt, ambient):
    assert step_exact(temp0, current, dt, W, ambient) == pytest.approx(
        _ode_step(temp0, current, dt, ambient), abs=1e-8
    )


def test_exact_step_vectorises():
    temps = np.array([22.0, 50.0, 90.0])
    currents = np.array([1.5, 0.0, 1.0])
    out = step_exact(temps, currents, 0.5, W, 22.0)
    assert out.shape == (3,)
    for k in range(3):
        assert out[k] == pytest.approx(step_exact(temps[k], currents[k], 0.5, W, 22.0), abs=1e-12)


def test_time_constant_is_a_few_seconds():
    assert 2.0 < time_constant_s(W) < 8.0


def test_simulate_temperature_equals_repeated_steps_uniform_and_not():
    rng = np.random.default_rng(1)
    t = np.arange(2000) * 0.01
    cur = np.where((t % 8.0) < 4.0, 1.3, 0.0)
    temp = simulate_temperature(t, cur, W, 22.0, 25.0)
    ref = [25.0]
    for k in range(len(t) - 1):
        ref.append(step_exact(ref[-1], cur[k], t[k + 1] - t[k], W, 22.0))
    np.testing.assert_allclose(temp, ref, atol=1e-9)
    # jittered sample times (sequential path) give the same exact answer at those times
    tj = np.sort(t + rng.uniform(0, 0.004, len(t)))
    tj[0] = 0.0
    temp_j = simulate_temperature(tj, cur, W, 22.0, 25.0)
    ref_j = [25.0]
    for k in range(len(tj) - 1):
        ref_j.append(step_exact(ref_j[-1], cur[k], tj[k + 1] - tj[k], W, 22.0))
    np.testing.assert_allclose(temp_j, ref_j, atol=1e-9)


def test_steady_state_and_inverse_round_trip():
    currents = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    temps = steady_state_temperature(currents, W, 22.0)
    assert temps[0] == pytest.approx(22.0)
    assert 80.0 < steady_state_temperature(1.2, W, 22.0) < 130.0
    np.testing.assert_allclose(current_for_steady_temperature(temps, W, 22.0), currents, atol=1e-12)
    assert current_for_steady_temperature(10.0, W, 22.0) == 0.0
    # the simulation settles on it after many time constants
    t = np.arange(0, 12 * time_constant_s(W), 0.01)
    assert simulate_temperature(t, 1.2, W, 22.0)[-1] == pytest.approx(
        steady_state_temperature(1.2, W, 22.0), abs=1e-3
    )


def test_current_for_trajectory_drives_the_wire_onto_it():
    t = np.arange(0, 20, 0.002)
    # heat 22 → 90 °C smoothly, hold, then cool slowly (within natural cooling)
    target = 22.0 + 68.0 * np.clip(t / 5.0, 0, 1) ** 2 - 20.0 * np.clip((t - 10) / 10, 0, 1)
    cur, clipped = current_for_trajectory(t, target, W, 22.0)
    assert not clipped.any()
    assert cur.max() < 2.5
    np.testing.assert_allclose(simulate_temperature(t, cur, W, 22.0, 22.0), target, atol=1e-8)
    # a drop faster than natural cooling: zero current, flagged, the wire stays above
    fast = np.where(t < 10, 90.0, 30.0)
    cur2, clipped2 = current_for_trajectory(t, fast, W, 22.0)
    assert clipped2[t >= 9.99].any() and (cur2[clipped2] == 0).all()
    sim = simulate_temperature(t, cur2, W, 22.0, 90.0)
    assert (sim[t > 10.5] > 30.0).all()


def test_estimator_matches_the_model_and_voltage_beats_a_wrong_resistance():
    dt = 1e-3
    t = np.arange(0, 30, dt)
    cur = np.where((t % 10) < 5, 1.3, 0.0)
    r_true = 1.2 * W.resistance_mean_ohm  # the real wire is 20 % more resistive than assumed
    truth = simulate_temperature(t, cur, W, 22.0, 22.0, resistance_ohm=r_true)
    est_i, est_v = TemperatureEstimator(W, 22.0), TemperatureEstimator(W, 22.0)
    out_i = np.empty(len(t))
    out_v = np.empty(len(t))
    out_i[0] = out_v[0] = 22.0
    for k in range(len(t) - 1):
        i = float(cur[k])
        out_i[k + 1] = est_i.update(dt, i)
        out_v[k + 1] = est_v.update(dt, i, i * r_true, 22.0)
    err_i = np.max(np.abs(out_i - truth))
    err_v = np.max(np.abs(out_v - truth))
    print(f"\nestimator max error: current only {err_i:.2f} K, with voltage {err_v:.2e} K")
    assert err_v < 1e-6 < 5.0 < err_i
    assert est_v.measured_resistance_ohm == pytest.approx(r_true)
    assert est_i.measured_resistance_ohm is None
    # without voltage it is exactly the heat balance with the assumed resistance
    np.testing.assert_allclose(out_i, simulate_temperature(t, cur, W, 22.0, 22.0), atol=1e-8)


def test_estimator_ignores_nan_voltage_and_is_fast():
    est = TemperatureEstimator(W, 22.0)
    est.update(0.1, 1.0, float("nan"), float("nan"))
    ref = step_exact(22.0, 1.0, 0.1, W, 22.0)
    assert est.temperature_c == pytest.approx(ref)
    hot = TemperatureEstimator(replace(W, h_w_m2k=60.0), 22.0)
    n = 50000
    t0 = time.perf_counter()
    for _ in range(n):
        hot.update(1e-3, 1.2, 0.55, 22.0)
    us = (time.perf_counter() - t0) / n * 1e6
    print(f"\nTemperatureEstimator.update: {us:.2f} µs")
