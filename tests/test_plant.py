"""Plant simulation: consistency, speed, paper Fig. 11 trends, one test per effect."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from smabench.physics.effects import CYCLE_DRIFT_TAU_CYCLES, EFFECT_DOCS, Effects
from smabench.physics.plant import (
    Plant,
    heating_cycles_profile,
    loop_mean_length_mm,
    loop_width_k,
    simulate_plant,
    transformation_temperatures_c,
)
from smabench.physics.thermal import steady_state_temperature
from smabench.physics.wire import PAPER_WIRE, stress_mpa

W = PAPER_WIRE
DT = 1e-3


def _profile(n=2, current=1.3, heat=5.0, cool=8.0, kind="complete", dt=DT):
    return heating_cycles_profile(n, current, heat, cool, dt, kind)


def _run_steps(t, cur, load_kg, effects, noise_mm=0.002, seed=0):
    plant = Plant(load_kg, W, effects, noise_mm=noise_mm, seed=seed)
    states = [plant.state] + [plant.step(t[k + 1] - t[k], cur[k]) for k in range(len(t) - 1)]
    return {
        name: np.array([getattr(s, name) for s in states])
        for name in ("temperature_c", "martensite_fraction", "length_mm", "position_mm")
    }


@pytest.mark.parametrize(
    "effects",
    [
        Effects(),
        Effects(
            stress_shift=7.5,
            sensor_lag=0.1,
            ambient_drift=3.0,
            ambient_sine=1.0,
            cycle_drift=2e-4,
            pulley_friction=3.0,
        ),
        Effects(latent_heat=24e3, phase_resistance=20.0, convection_nonlinear=0.005),
    ],
    ids=["default", "vectorised-effects", "coupled-effects"],
)
def test_simulate_plant_and_plant_step_agree(effects):
    t, cur = _profile(n=2)
    trace = simulate_plant(t, cur, load_kg=2.0, effects=effects, noise_mm=0.002, seed=3)
    steps = _run_steps(t, cur, 2.0, effects, noise_mm=0.002, seed=3)
    for name, values in steps.items():
        np.testing.assert_allclose(getattr(trace, name), values, atol=1e-8, err_msg=name)


def test_complete_cycle_transforms_fully_with_a_realistic_stroke():
    t, cur = _profile(n=1, current=1.3, heat=5.0, cool=10.0)
    tr = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
    assert tr.martensite_fraction.min() < 0.01 and tr.martensite_fraction[-1] > 0.99
    stroke = tr.length_mm.max() - tr.length_mm.min()
    assert 0.035 * W.length_mm < stroke < 0.06 * W.length_mm
    # position grows with length; heating lowers it
    k_hot = int(np.argmax(tr.temperature_c))
    assert tr.position_mm[k_hot] < tr.position_mm[0] - 2.0
    np.testing.assert_allclose(tr.position_mm, tr.length_mm - W.length_mm, atol=1e-12)


def test_profiles_make_incomplete_cycles_and_inner_loops():
    for kind in ("incomplete", "inner"):
        t, cur = _profile(n=4, kind=kind)
        tr = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
        switch = np.flatnonzero(np.diff(cur) > 0)[1:] + 1  # reheating starts after the first
        xi_at_reheat = tr.martensite_fraction[switch]
        assert ((xi_at_reheat > 0.05) & (xi_at_reheat < 0.95)).all(), (kind, xi_at_reheat)
        assert tr.martensite_fraction[-1] > 0.99
    t, cur = _profile(n=4, kind="inner")
    tr = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
    switch = np.flatnonzero(np.diff(cur) < 0)[1:-1] + 1  # heating stops of the short cycles
    assert (tr.martensite_fraction[switch] > 0.05).all()
    with pytest.raises(ValueError):
        heating_cycles_profile(1, 1.0, 1.0, 1.0, DT, kind="bogus")


# ---------------------------------------------------------------- paper Fig. 11 trends


def _loop(load_kg=2.0, wire=W, current=1.7, effects=None):
    t, cur = heating_cycles_profile(1, current, 5.0, 15.0, DT)
    tr = simulate_plant(t, cur, load_kg=load_kg, wire=wire, effects=effects, noise_mm=0.0)
    assert tr.martensite_fraction.min() < 0.01 and tr.martensite_fraction[-1] > 0.99
    return loop_width_k(tr.temperature_c, tr.length_mm), loop_mean_length_mm(tr.length_mm)


@pytest.mark.parametrize("effects", [None, Effects(stress_shift=7.5)], ids=["fixed-T", "shift"])
def test_more_load_shifts_the_loop_up_and_narrows_it(effects):
    w1, y1 = _loop(1.0, effects=effects)
    w4, y4 = _loop(4.0, effects=effects)
    print(f"\n1 kg: width {w1:.1f} K, mean {y1:.3f} mm; 4 kg: width {w4:.1f} K, mean {y4:.3f} mm")
    assert y4 - y1 > 0.2  # elastic strain: Δσ·(1/E) · L0 ≈ 0.3 mm
    # width shrinks by ≈ hysteresis_shrink·Δσ ≈ 7.8 K; with stress_shift the 4 kg loop sits
    # ≈ 35 K hotter, where cooling is faster and the kinetic lag gives back ≈ 2.5 K
    expected = W.hysteresis_shrink_k_per_mpa * (stress_mpa(4.0, W) - stress_mpa(1.0, W))
    assert w1 - w4 > 0.5 * expected
    if effects is None:
        assert w1 - w4 == pytest.approx(expected, abs=1.5)


def test_larger_h_widens_and_larger_cp_thins_the_loop():
    w0, _ = _loop(wire=W)
    w_h, _ = _loop(wire=replace(W, h_w_m2k=2 * W.h_w_m2k))
    w_cp, _ = _loop(wire=replace(W, cp_j_kgk=1.5 * W.cp_j_kgk))
    print(f"\nwidth: nominal {w0:.2f} K, 2×h {w_h:.2f} K, 1.5×cp {w_cp:.2f} K")
    assert w_h > w0 + 0.5
    assert w_cp < w0 - 0.5


# ---------------------------------------------------------------- effects one by one


def test_sensor_lag_delays_position_by_tau():
    tau = 0.2
    t, cur = _profile(n=2)
    tr = simulate_plant(t, cur, load_kg=2.0, effects=Effects(sensor_lag=tau), noise_mm=0.0)
    x = np.diff(tr.length_mm - W.length_mm)
    y = np.diff(tr.position_mm)
    lags = np.arange(0, 1000)
    corr = [np.dot(x[: len(x) - k], y[k:]) for k in lags]
    delay = lags[int(np.argmax(corr))] * DT
    print(f"\nsensor_lag {tau} s → measured delay {delay:.3f} s")
    assert delay == pytest.approx(tau, rel=0.35)


def test_latent_heat_slows_heating_through_as_af():
    t, cur = _profile(n=1, current=1.5, heat=8.0, cool=12.0)
    tt = transformation_temperatures_c(2.0, W)

    def crossing_time(tr):
        k_as = np.argmax(tr.temperature_c > tt["as_c"])
        k_af = np.argmax(tr.temperature_c > tt["af_c"])
        return (k_af - k_as) * DT

    base = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
    latent = simulate_plant(t, cur, load_kg=2.0, effects=Effects(latent_heat=24e3), noise_mm=0.0)
    print(f"\nAs→Af heating time: {crossing_time(base):.2f} s → {crossing_time(latent):.2f} s")
    assert crossing_time(latent) > 1.5 * crossing_time(base)
    assert latent.martensite_fraction.min() < 0.01  # still completes


def test_phase_resistance_changes_v_over_i_by_the_resistivity_ratio():
    t, cur = _profile(n=1, current=1.3)
    on = simulate_plant(t, cur, load_kg=2.0, effects=Effects(phase_resistance=20.0))
    off = simulate_plant(t, cur, load_kg=2.0)
    heating = np.flatnonzero(cur > 0)
    cold, hot = heating[0], heating[-1]
    ratio_on = (on.voltage_v[hot] / cur[hot]) / (on.voltage_v[cold] / cur[cold])
    ratio_off = (off.voltage_v[hot] / cur[hot]) / (off.voltage_v[cold] / cur[cold])
    # ρ_A/ρ_M = (90 + 10)/(90 - 10) µΩ·cm
    assert ratio_on == pytest.approx(100.0 / 80.0, rel=0.01)
    assert ratio_off == pytest.approx(1.0)


def test_stress_shift_moves_mid_transformation_temperature():
    rate = 7.5

    def mid_temperature(load, effects):
        t, cur = _profile(n=1, current=1.8, heat=6.0, cool=15.0)
        tr = simulate_plant(t, cur, load_kg=load, effects=effects, noise_mm=0.0)
        k = int(np.argmax(tr.martensite_fraction < 0.5))
        return tr.temperature_c[k]

    d_on = mid_temperature(4.0, Effects(stress_shift=rate)) - mid_temperature(
        1.0, Effects(stress_shift=rate)
    )
    d_off = mid_temperature(4.0, None) - mid_temperature(1.0, None)
    expected = (stress_mpa(4.0, W) - stress_mpa(1.0, W)) / rate
    print(f"\nmid-transformation shift 1→4 kg: on {d_on:.1f} K, off {d_off:.1f} K,", end=" ")
    print(f"Δσ/rate {expected:.1f} K")
    assert d_on - d_off == pytest.approx(expected, abs=3.0)


def test_convection_nonlinear_lowers_the_steady_temperature():
    k = 0.005
    t = np.arange(0, 40, 0.01)
    tr = simulate_plant(
        t, np.full(len(t), 1.5), load_kg=2.0, effects=Effects(convection_nonlinear=k), noise_mm=0.0
    )
    lin = steady_state_temperature(1.5, W, 22.0)
    dt_lin = lin - 22.0  # solve k·ΔT² + ΔT - ΔT_lin = 0
    expected = 22.0 + (-1.0 + np.sqrt(1.0 + 4.0 * k * dt_lin)) / (2.0 * k)
    assert tr.temperature_c[-1] == pytest.approx(expected, abs=0.5)
    assert tr.temperature_c[-1] < lin - 20.0


def test_ambient_drift_moves_the_cold_position():
    rate = 5.0  # K/h
    t = np.arange(0, 3600.0, 0.05)
    tr = simulate_plant(
        t, np.zeros(len(t)), load_kg=2.0, effects=Effects(ambient_drift=rate), noise_mm=0.0
    )
    assert tr.ambient_c[-1] - tr.ambient_c[0] == pytest.approx(rate, rel=1e-3)
    shift = tr.position_mm[-1] - tr.position_mm[0]
    assert shift == pytest.approx(W.length_mm * W.alpha_per_k * rate, rel=0.05)
    sine = simulate_plant(
        t,
        np.zeros(len(t)),
        load_kg=2.0,
        effects=Effects(ambient_sine=2.0, ambient_sine_period=600),
        noise_mm=0.0,
    )
    assert np.ptp(sine.ambient_c) == pytest.approx(4.0, rel=1e-3)
    assert np.ptp(sine.position_mm) > 0.5 * W.length_mm * W.alpha_per_k * 4.0


def test_cycle_drift_raises_the_cold_position_cycle_over_cycle():
    rate = 2e-4
    t, cur = _profile(n=5, current=1.3, heat=5.0, cool=10.0)
    tr = simulate_plant(t, cur, load_kg=2.0, effects=Effects(cycle_drift=rate), noise_mm=0.0)
    base = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
    ends = np.flatnonzero(np.diff(cur) > 0)  # end of each cooling (last sample before heating)
    ends = np.append(ends, len(t) - 1)
    extra = tr.position_mm[ends] - base.position_mm[ends]
    steps = np.diff(np.concatenate(([0.0], extra)))
    assert (steps > 0).all() and (np.diff(steps) < 0).all()  # grows and saturates
    assert steps[0] == pytest.approx(
        rate * W.length_mm * CYCLE_DRIFT_TAU_CYCLES * (1 - np.exp(-1 / CYCLE_DRIFT_TAU_CYCLES)),
        rel=0.05,
    )


def test_pulley_friction_makes_a_deadband_on_reversals():
    force = 5.0
    t, cur = _profile(n=2, current=1.3, heat=5.0, cool=10.0)
    on = simulate_plant(t, cur, load_kg=2.0, effects=Effects(pulley_friction=force), noise_mm=0.0)
    off = simulate_plant(t, cur, load_kg=2.0, noise_mm=0.0)
    second = t >= 15.0  # second cycle: the play already settled on a branch
    on, off = on.length_mm[second], off.length_mm[second]
    e_eff = 2.0 / (1 / W.e_austenite_pa + 1 / W.e_martensite_pa)
    play_mm = force * W.length_m / (e_eff * W.area_m2) * 1e3
    assert np.ptp(off) - np.ptp(on) == pytest.approx(2 * play_mm, rel=0.02)
    # after the heating stops the wire keeps its length until the free length moved by 2·play
    k = int(np.argmin(on))
    stuck = np.flatnonzero(on[k:] > on[k] + 1e-9)[0]
    moved = off[k + stuck] - off[k]
    assert stuck > 10 and moved == pytest.approx(2 * play_mm, rel=0.05)


def test_effects_parsing_and_docs():
    e = Effects.from_strings(["latent_heat=24000", "sensor_lag=0.1", "pulley_friction"])
    assert e.latent_heat == 24000 and e.sensor_lag == 0.1 and e.pulley_friction > 0
    assert set(e.active()) == {"latent_heat", "sensor_lag", "pulley_friction"}
    assert Effects.from_strings([]) == Effects()
    with pytest.raises(ValueError, match="unknown effect"):
        Effects.from_strings(["warp_drive=1"])
    with pytest.raises(ValueError, match="out of range"):
        Effects.from_strings(["sensor_lag=50"])
    with pytest.raises(ValueError, match="not a number"):
        Effects.from_strings(["sensor_lag=fast"])
    from dataclasses import fields

    assert {f.name for f in fields(Effects)} == set(EFFECT_DOCS)
    assert all("range" in doc for doc in EFFECT_DOCS.values())
