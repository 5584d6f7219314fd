"""An SMA wire simulator written apart from ``smabench.physics``, to check that ``smabench
analyze`` works on physics and not on the quirks of the project's own plant.

It imports nothing from smabench and differs from ``smabench.physics.plant`` on purpose:

- hysteresis: a Preisach model, hysterons with Gaussian switching temperatures (erf-shaped major
  branches with tails, congruent minor loops, wiping-out memory), no kinetic lag; the project's
  plant uses compact cosine branches, scaled return-point memory and first-order kinetics;
- heat balance: classical RK4 on a 5 ms step; material values (cp, h, resistivity, ε_L, moduli,
  transformation temperatures) drawn per session within physical ranges;
- length: Voigt modulus mixture ``E = ξ·E_M + (1-ξ)·E_A``; wire length and diameter of its own;
  sensor zero offset, noise and a 0.5 µm quantisation;
- the effects in textbook forms of their own: resistivities ρ_M / ρ_A, latent heat
  ``m·L·dξ/dt``, Clausius–Clapeyron slopes that differ for the austenite and martensite
  temperatures, convection ``h = h0·(1 + k·ΔT)``, the sensor reading a dead time late (a delay,
  not a first-order lag), an unmeasured room drift, residual strain growing by a fixed amount per
  completed cycle, and (outside the analysis' list) Coulomb friction at the pulley.

``write_session`` writes the session contract by hand (csv module), not with smabench's writer.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

G = 9.80665


@dataclass
class WireWorld:
    """One simulated bench: wire, material, room, sensor. Defaults are drawn by ``draw``."""

    length_mm: float = 100.0
    diameter_mm: float = 0.38
    density: float = 6450.0
    cp: float = 840.0
    h0: float = 50.0  # W/(m²·K)
    rho_m_uohm_cm: float = 85.0  # martensite; austenite adds the phase_resistance effect
    eps_l: float = 0.04
    e_a_gpa: float = 70.0
    e_m_gpa: float = 30.0
    alpha_per_k: float = 1.1e-5
    # Preisach: switching temperatures of the hysterons at the reference stress, °C
    heat_mid_c: float = 78.0  # mean M→A (austenite) switching temperature
    cool_mid_c: float = 52.0  # mean A→M switching temperature
    spread_c: float = 5.0  # std of the hysterons' centre
    width_spread_c: float = 2.0  # std of their half-width
    ambient_c: float = 22.0
    noise_mm: float = 0.002
    offset_mm: float = 0.3
    effects: dict[str, float] = field(default_factory=dict)

    @classmethod
    def draw(cls, rng: np.random.Generator, **effects: float) -> WireWorld:
        """A bench with material values drawn within physical ranges."""
        return cls(
            length_mm=float(rng.uniform(80.0, 140.0)),
            cp=float(rng.uniform(800.0, 880.0)),
            h0=float(rng.uniform(40.0, 60.0)),
            rho_m_uohm_cm=float(rng.uniform(80.0, 95.0)),
            eps_l=float(rng.uniform(0.035, 0.045)),
            e_a_gpa=float(rng.uniform(60.0, 80.0)),
            e_m_gpa=float(rng.uniform(25.0, 35.0)),
            heat_mid_c=float(rng.uniform(72.0, 82.0)),
            cool_mid_c=float(rng.uniform(48.0, 56.0)),
            spread_c=float(rng.uniform(3.5, 6.0)),
            width_spread_c=float(rng.uniform(1.0, 2.5)),
            ambient_c=float(rng.uniform(20.0, 25.0)),
            noise_mm=float(rng.uniform(0.001, 0.003)),
            offset_mm=float(rng.uniform(-1.0, 1.0)),
            effects=dict(effects),
        )


def current_profile(rng: np.random.Generator, n_cycles: int, dt: float = 5e-3):
    """Heating pulses of varied current and length, each followed by a long cooling; every
    third cooling is cut short, so that the wire is reheated half-transformed (an incomplete
    cycle)."""
    phases = []
    for k in range(n_cycles):
        phases.append((float(rng.uniform(4.0, 6.0)), float(rng.uniform(1.2, 1.6))))
        cool = rng.uniform(7.0, 10.0) if k % 3 == 1 else rng.uniform(22.0, 26.0)
        phases.append((float(cool), 0.0))
    counts = [int(round(d / dt)) for d, _ in phases]
    cur = np.repeat([c for _, c in phases], counts).astype(float)
    return np.arange(len(cur)) * dt, cur


def simulate(world: WireWorld, load_kg: float, t: np.ndarray, current: np.ndarray, seed: int,
             temperature_c: np.ndarray | None = None):  # fmt: skip
    """Simulate on the uniform grid ``t`` (5 ms); returns a dict of arrays (true, measured).
    ``temperature_c``: a prescribed wire temperature (a chamber loop) instead of the heat
    balance."""
    w, fx = world, world.effects
    rng = np.random.default_rng(seed)
    r_m = w.diameter_mm * 0.5e-3
    area = math.pi * r_m**2
    l0 = w.length_mm * 1e-3
    mass = w.density * area * l0
    surface = 2.0 * math.pi * r_m * l0
    sigma = load_kg * G / area  # Pa
    sigma_mpa = sigma * 1e-6
    # Clausius–Clapeyron: C_A for the austenite (heating) switch, C_M for the martensite one;
    # the effect's value is the mean slope, MPa/K; reference stress 100 MPa
    slope = fx.get("stress_shift", 0.0)
    if slope:
        shift_a = (sigma_mpa - 100.0) / (slope * 1.15)
        shift_m = (sigma_mpa - 100.0) / (slope * 0.85)
    else:
        shift_a = shift_m = 0.0
    # hysterons: centre c, half-width hw; switch to austenite at c + hw, back at c - hw
    n_h = 1500
    hrng = np.random.default_rng(12345)
    c0 = 0.5 * (w.heat_mid_c + w.cool_mid_c)
    hw0 = 0.5 * (w.heat_mid_c - w.cool_mid_c)
    centre = c0 + w.spread_c * hrng.standard_normal(n_h)
    hw = np.abs(hw0 + w.width_spread_c * hrng.standard_normal(n_h))
    up = centre + hw + shift_a
    down = centre - hw + shift_m
    aus = np.zeros(n_h, dtype=bool)  # all martensite at the start
    rho_m = w.rho_m_uohm_cm * 1e-8
    d_rho = fx.get("phase_resistance", 0.0) * 1e-8  # ρ_A - ρ_M
    rho_a = rho_m + d_rho
    latent = fx.get("latent_heat", 0.0)  # J/kg
    conv_k = fx.get("convection_nonlinear", 0.0)  # 1/K
    drift = fx.get("ambient_drift", 0.0) / 3600.0  # K/s
    friction_n = fx.get("pulley_friction", 0.0)  # N
    cyc_strain = fx.get("cycle_drift", 0.0)  # strain per completed cycle
    dt = float(t[1] - t[0])
    n = len(t)
    temp = np.empty(n)
    xi = np.empty(n)
    res = np.empty(n)
    amb = w.ambient_c + drift * (t - t[0])
    temp_k = w.ambient_c if temperature_c is None else float(temperature_c[0])
    xi_k = 1.0
    cycles = 0.0
    heated = False

    def rhs(tk, xk, i_a, ta):
        rho = xk * rho_m + (1.0 - xk) * rho_a
        r_ohm = rho * l0 / area
        h = w.h0 * (1.0 + conv_k * (tk - ta))
        return (i_a * i_a * r_ohm - h * surface * (tk - ta)) / (mass * w.cp)

    for k in range(n):
        temp[k] = temp_k
        xi[k] = xi_k
        rho = xi_k * rho_m + (1.0 - xi_k) * rho_a
        res[k] = rho * l0 / area
        if k == n - 1:
            break
        i_a, ta = current[k], amb[k]
        k1 = rhs(temp_k, xi_k, i_a, ta)
        k2 = rhs(temp_k + 0.5 * dt * k1, xi_k, i_a, ta)
        k3 = rhs(temp_k + 0.5 * dt * k2, xi_k, i_a, ta)
        k4 = rhs(temp_k + dt * k3, xi_k, i_a, ta)
        new = temp_k + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        if temperature_c is not None:
            new = float(temperature_c[k + 1])
        aus |= up <= new
        aus &= ~(down >= new)
        xi_new = 1.0 - float(np.count_nonzero(aus)) / n_h
        if latent:
            new -= latent * (xi_k - xi_new) / w.cp  # heating (ξ falls) absorbs heat
        # a cycle completes when the wire went mostly austenite and came back mostly martensite
        if xi_new < 0.2:
            heated = True
        elif heated and xi_new > 0.8:
            heated = False
            cycles += 1.0
        temp_k, xi_k = new, xi_new
        xi[k + 1] = xi_k
    # length: Voigt mixture of the moduli, thermal expansion, residual strain per cycle
    e_pa = (xi * w.e_m_gpa + (1.0 - xi) * w.e_a_gpa) * 1e9
    done = np.zeros(n)
    if cyc_strain:
        low = xi < 0.2
        high = xi > 0.8
        state, count = False, 0
        for k in range(n):
            if low[k]:
                state = True
            elif state and high[k]:
                state, count = False, count + 1
            done[k] = count
    strain = sigma / e_pa + w.eps_l * xi + w.alpha_per_k * (temp - 22.0) + cyc_strain * done
    length_mm = w.length_mm * (1.0 + strain)
    if friction_n:
        # the wire tension is Mg ± F: a deadband of the length on every reversal (play operator)
        e_eff = 0.5 * (w.e_a_gpa + w.e_m_gpa) * 1e9
        play = friction_n * l0 / (e_eff * area) * 1e3
        out = length_mm.copy()
        for k in range(1, n):
            out[k] = min(max(out[k - 1], length_mm[k] - play), length_mm[k] + play)
        length_mm = out
    pos = length_mm - w.length_mm + w.offset_mm
    delay = fx.get("sensor_lag", 0.0)
    if delay:
        m = int(round(delay / dt))
        pos = np.concatenate((np.full(m, pos[0]), pos[: n - m]))
    meas = pos + rng.normal(0.0, w.noise_mm, n)
    meas = np.round(meas / 0.0005) * 0.0005
    volt = current * res * (1.0 + 0.002 * rng.standard_normal(n))
    return {
        "t_s": t, "current_A": current, "voltage_V": volt, "position_mm": meas,
        "temperature_true_C": temp, "xi": xi, "ambient_true_C": amb,
    }  # fmt: skip


def write_session(folder: Path, world: WireWorld, load_kg: float, sim: dict, rate_hz: float):
    """The session contract, written by hand: session.json + samples.csv at ``rate_hz``."""
    folder.mkdir(parents=True)
    step = int(round(1.0 / (rate_hz * (sim["t_s"][1] - sim["t_s"][0]))))
    sl = slice(None, None, step)
    meta = {
        "schema_version": 1, "load_kg": load_kg, "status": "completed",
        "wire": {"length_mm": world.length_mm, "diameter_mm": world.diameter_mm},
        "source": "tests/independent_sim.py",
    }  # fmt: skip
    (folder / "session.json").write_text(json.dumps(meta, indent=1))
    cols = ["t_s", "current_set_A", "current_A", "voltage_V", "ambient_C", "position_mm"]
    with open(folder / "samples.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(cols)
        t, i, v, p = (sim[k][sl] for k in ("t_s", "current_A", "voltage_V", "position_mm"))
        for k in range(len(t)):
            wr.writerow([f"{t[k]:.4f}", f"{i[k]:.4f}", f"{i[k]:.4f}", f"{v[k]:.5f}",
                         f"{world.ambient_c:.2f}", f"{p[k]:.5f}"])  # fmt: skip
    return folder


def make(folder: Path, effects: dict[str, float], load_kg: float, seed: int,
         n_cycles: int = 9, rate_hz: float = 100.0, world: WireWorld | None = None):  # fmt: skip
    """Draw a bench, simulate ``n_cycles`` varied heating cycles, write the session."""
    rng = np.random.default_rng(seed)
    world = world or WireWorld.draw(rng, **effects)
    t, cur = current_profile(rng, n_cycles)
    sim = simulate(world, load_kg, t, cur, seed)
    write_session(folder, world, load_kg, sim, rate_hz)
    return world, sim


def make_thermo(folder: Path, world: WireWorld, load_kg: float, seed: int,
                rate_k_s: float = 0.5, hot_c: float = 140.0, cold_c: float = 25.0):  # fmt: skip
    """A thermometer loop as a tensile tester in a chamber records it: the temperature ramps
    cold → hot → cold at ``rate_k_s``; the session has temperature_C (measured, ±0.05 K) and
    position_mm, one row per 0.5 s, no current."""
    up = np.arange(cold_c, hot_c, rate_k_s * 0.005)
    temp = np.concatenate((up, up[::-1]))
    t = np.arange(len(temp)) * 0.005
    sim = simulate(world, load_kg, t, np.zeros(len(t)), seed, temperature_c=temp)
    rng = np.random.default_rng(seed + 1)
    sl = slice(None, None, 100)
    folder.mkdir(parents=True)
    meta = {"schema_version": 1, "load_kg": load_kg, "status": "completed",
            "wire": {"length_mm": world.length_mm, "diameter_mm": world.diameter_mm},
            "source": "tests/independent_sim.py (chamber loop)"}  # fmt: skip
    (folder / "session.json").write_text(json.dumps(meta, indent=1))
    with open(folder / "samples.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(["t_s", "temperature_C", "position_mm"])
        for tk, temp_k, pos in zip(t[sl], temp[sl], sim["position_mm"][sl], strict=True):
            wr.writerow([f"{tk:.3f}", f"{temp_k + rng.normal(0.0, 0.05):.3f}", f"{pos:.5f}"])
    return folder
