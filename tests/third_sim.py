"""A third SMA wire simulator, written as another team would write it, to check that
``smabench analyze`` answers to physics and not to the forms of the first two simulators.

It imports nothing from smabench and shares no code with ``smabench.physics.plant`` or
``tests/independent_sim.py``. Its choices, fixed from the physics before the analysis was run
on it:

- phase kinetics: Tanaka's exponential law in differential form, dξ = -a_A·ξ·dT on heating above
  As and dξ = a_M·(1-ξ)·(-dT) on cooling below Ms (a = ln 100 / window), which gives partial
  loops scaled through the reversal point; rate dependence by thermally activated nucleation:
  the start temperatures move away by κ·√|dT/dt| (heating later, cooling earlier);
- integration: fixed-step Heun (explicit trapezoidal, 2 ms) of the coupled T, ξ system;
- latent heat as an effective heat capacity over the transformation,
  ``c_eff = cp + L·|dξ/dT|`` on the active branch;
- resistivity with a temperature coefficient (always on, 2e-4 /K) and, as an effect, a
  different resistivity of the two phases, ``ρ = ρ_M·ξ + ρ_A·(1-ξ)``;
- convection ``h·A·ΔT`` or, as an effect, the laminar natural-convection law
  ``h·A·ΔT_ref·(ΔT/ΔT_ref)^(1+n)`` (n ≈ 0.25: Q ∝ ΔT^1.25);
- length: Reuss modulus mixture, a transformation strain that grows with stress
  (detwinning, ``ε_L(σ) = ε_max·(1 - exp(-σ/σ_c))``), thermal expansion of each phase
  (α_M ≈ 6.6e-6, α_A ≈ 11e-6 /K), residual strain growing logarithmically with the
  transformation cycles ``a·ln(1 + N)`` (effect), a pulley dead band (play operator, effect);
- sensor: first-order lag (effect), 1 µm quantisation, noise, 50 Hz with timing jitter;
- room: an unmeasured linear drift (effect); the recorded ambient stays at its first value;
- stress: Clausius–Clapeyron slopes C_A = 1.1·C and C_M = 0.9·C (effect ``stress_shift``,
  value C in MPa/K, reference 120 MPa); no stress dependence of the temperatures without it;
- wire 0.38 or 0.51 mm, 70–160 mm long, material values drawn per world.

``make(folder, effects, load_kg, seed)`` writes a session folder (session.json + samples.csv
by hand with the csv module).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

GRAVITY = 9.81
LN100 = math.log(100.0)
SIGMA_REF_MPA = 120.0
DT_REF_K = 40.0

EFFECTS = (
    "phase_resistance",  # ρ_A - ρ_M, µΩ·cm
    "latent_heat",  # J/kg
    "stress_shift",  # mean Clausius–Clapeyron slope, MPa/K
    "convection_nonlinear",  # exponent increment n (Q ∝ ΔT^(1+n))
    "sensor_lag",  # first-order time constant, s
    "ambient_drift",  # K/h
    "cycle_drift",  # a of a·ln(1 + N), strain
    "pulley_deadband",  # half-width of the play, mm (outside the analysis' list)
)


@dataclass
class World:
    """A bench as the third team built it; ``draw`` fills in physical values."""

    diameter_mm: float = 0.38
    length_mm: float = 100.0
    density: float = 6500.0
    cp: float = 850.0
    h: float = 60.0  # W/(m²·K)
    rho_m_uohm_cm: float = 82.0
    tcr_per_k: float = 2e-4
    as_c: float = 68.0
    af_c: float = 80.0
    ms_c: float = 55.0
    mf_c: float = 44.0
    kappa: float = 1.0  # K per √(K/s): rate dependence of the start temperatures
    eps_max: float = 0.045
    sigma_c_mpa: float = 60.0
    e_a_gpa: float = 75.0
    e_m_gpa: float = 30.0
    alpha_a: float = 11e-6
    alpha_m: float = 6.6e-6
    room_c: float = 23.0
    noise_mm: float = 0.002
    zero_mm: float = 0.0
    effects: dict[str, float] = field(default_factory=dict)

    @classmethod
    def draw(cls, rng: np.random.Generator, **effects: float) -> World:
        unknown = set(effects) - set(EFFECTS)
        if unknown:
            raise ValueError(f"unknown effect(s) {sorted(unknown)}")
        as_c = float(rng.uniform(60.0, 75.0))
        af_c = as_c + float(rng.uniform(8.0, 16.0))
        ms_c = as_c - float(rng.uniform(10.0, 18.0))
        mf_c = ms_c - float(rng.uniform(8.0, 14.0))
        return cls(
            diameter_mm=float(rng.choice([0.38, 0.51])),
            length_mm=float(rng.uniform(70.0, 160.0)),
            density=float(rng.uniform(6400.0, 6500.0)),
            cp=float(rng.uniform(820.0, 880.0)),
            h=float(rng.uniform(45.0, 80.0)),
            rho_m_uohm_cm=float(rng.uniform(76.0, 90.0)),
            as_c=as_c, af_c=af_c, ms_c=ms_c, mf_c=mf_c,
            kappa=float(rng.uniform(0.5, 1.5)),
            eps_max=float(rng.uniform(0.04, 0.05)),
            sigma_c_mpa=float(rng.uniform(40.0, 80.0)),
            e_a_gpa=float(rng.uniform(65.0, 80.0)),
            e_m_gpa=float(rng.uniform(25.0, 35.0)),
            room_c=float(rng.uniform(19.0, 26.0)),
            noise_mm=float(rng.uniform(0.001, 0.003)),
            zero_mm=float(rng.uniform(-2.0, 2.0)),
            effects=dict(effects),
        )  # fmt: skip

    @property
    def area_m2(self) -> float:
        return math.pi * (self.diameter_mm * 0.5e-3) ** 2

    def stress_mpa(self, load_kg: float) -> float:
        return load_kg * GRAVITY / self.area_m2 * 1e-6


def profile(rng: np.random.Generator, world: World, n_cycles: int):
    """Segments (duration s, current A): pulses of one or two levels, rests; every fourth rest
    cut short so that the wire is reheated part-way through its cooling."""
    scale = (world.diameter_mm / 0.38) ** 1.5
    cool_scale = world.diameter_mm / 0.38
    seg = []
    for k in range(n_cycles):
        i1 = float(rng.uniform(1.1, 1.6)) * scale
        if k % 2:
            seg.append((float(rng.uniform(2.0, 3.0)), i1))
            seg.append((float(rng.uniform(1.5, 3.0)), i1 * float(rng.uniform(0.75, 0.9))))
        else:
            seg.append((float(rng.uniform(3.0, 6.0)), i1))
        rest = rng.uniform(4.0, 6.0) if k % 4 == 2 else rng.uniform(14.0, 20.0)
        seg.append((float(rest) * cool_scale, 0.0))
    return seg


def simulate(world: World, load_kg: float, segments, seed: int, dt: float = 2e-3) -> dict:
    """Heun integration of (T, ξ) over the segments; returns arrays on the 2 ms grid."""
    w, fx = world, world.effects
    r_m = w.diameter_mm * 0.5e-3
    area = w.area_m2
    l0 = w.length_mm * 1e-3
    mass = w.density * area * l0
    surf = 2.0 * math.pi * r_m * l0
    sigma = w.stress_mpa(load_kg)
    slope = fx.get("stress_shift", 0.0)
    sh_a = (sigma - SIGMA_REF_MPA) / (1.1 * slope) if slope else 0.0
    sh_m = (sigma - SIGMA_REF_MPA) / (0.9 * slope) if slope else 0.0
    as_c, af_c = w.as_c + sh_a, w.af_c + sh_a
    ms_c, mf_c = w.ms_c + sh_m, w.mf_c + sh_m
    a_a = LN100 / (af_c - as_c)
    a_m = LN100 / (ms_c - mf_c)
    rho_m = w.rho_m_uohm_cm * 1e-8
    rho_a = rho_m + fx.get("phase_resistance", 0.0) * 1e-8
    lat = fx.get("latent_heat", 0.0)
    n_conv = fx.get("convection_nonlinear", 0.0)
    drift_k_s = fx.get("ambient_drift", 0.0) / 3600.0
    current = np.concatenate([np.full(int(round(d / dt)), i) for d, i in segments])
    n = len(current) + 1
    t = np.arange(n) * dt

    def resist(temp, xi):
        rho = (rho_m * xi + rho_a * (1.0 - xi)) * (1.0 + w.tcr_per_k * (temp - 20.0))
        return rho * l0 / area

    def loss(temp, ta):
        d = temp - ta
        if n_conv:
            return w.h * surf * DT_REF_K * math.copysign(abs(d / DT_REF_K) ** (1.0 + n_conv), d)
        return w.h * surf * d

    def rates(temp, xi, i_a, ta, rate_prev):
        """(dT/dt, dξ/dt): the branch follows the sign of the net power (c_eff > 0)."""
        p_net = i_a * i_a * resist(temp, xi) - loss(temp, ta)
        shift = w.kappa * math.sqrt(abs(rate_prev))
        if p_net > 0 and temp > as_c + shift:
            slope_xi = -a_a * xi  # dξ/dT on heating
        elif p_net < 0 and temp < ms_c - shift:
            slope_xi = a_m * (1.0 - xi)  # dξ/dT on cooling (negative dT: ξ grows)
            slope_xi = -slope_xi  # dξ/dT < 0 as T falls and ξ rises
        else:
            slope_xi = 0.0
        c_eff = w.cp + lat * abs(slope_xi)
        d_temp = p_net / (mass * c_eff)
        return d_temp, slope_xi * d_temp

    temp = np.empty(n)
    xi = np.empty(n)
    res = np.empty(n)
    cyc = np.empty(n)
    tk, xk, nk, rate = w.room_c, 1.0, 0.0, 0.0
    for k in range(n):
        temp[k], xi[k], cyc[k] = tk, xk, nk
        res[k] = resist(tk, xk)
        if k == n - 1:
            break
        i_a = current[k]
        ta0 = w.room_c + drift_k_s * t[k]
        ta1 = ta0 + drift_k_s * dt
        f1 = rates(tk, xk, i_a, ta0, rate)
        f2 = rates(tk + dt * f1[0], min(max(xk + dt * f1[1], 0.0), 1.0), i_a, ta1, f1[0])
        rate = 0.5 * (f1[0] + f2[0])
        x_new = min(max(xk + 0.5 * dt * (f1[1] + f2[1]), 0.0), 1.0)
        nk += 0.5 * abs(x_new - xk)
        tk, xk = tk + dt * rate, x_new
    # length
    inv_e = xi / (w.e_m_gpa * 1e3) + (1.0 - xi) / (w.e_a_gpa * 1e3)  # 1/MPa
    eps_l = w.eps_max * (1.0 - math.exp(-sigma / w.sigma_c_mpa))
    alpha = w.alpha_m * xi + w.alpha_a * (1.0 - xi)
    strain = sigma * inv_e + eps_l * xi + alpha * (temp - 20.0)
    a_res = fx.get("cycle_drift", 0.0)
    if a_res:
        strain = strain + a_res * np.log1p(cyc)
    length = w.length_mm * (1.0 + strain)
    play = fx.get("pulley_deadband", 0.0)
    if play:
        out = length.copy()
        for k in range(1, n):
            out[k] = min(max(out[k - 1], length[k] - play), length[k] + play)
        length = out
    pos = length - w.length_mm + w.zero_mm
    tau = fx.get("sensor_lag", 0.0)
    if tau:
        b = math.exp(-dt / tau)
        y = np.empty(n)
        y[0] = pos[0]
        for k in range(1, n):
            y[k] = b * y[k - 1] + (1.0 - b) * pos[k]
        pos = y
    return {"t_s": t, "current_A": np.concatenate((current, [0.0])), "resistance_ohm": res,
            "temperature_C": temp, "xi": xi, "position_mm": pos, "cycles": cyc}  # fmt: skip


def record(world: World, sim: dict, seed: int, rate_hz: float = 50.0) -> dict:
    """What the data logger writes: samples near every 1/rate_hz with jitter, noise,
    quantisation, the voltage from the true resistance, the ambient read once."""
    rng = np.random.default_rng(seed + 7)
    t = sim["t_s"]
    dt = t[1] - t[0]
    step = 1.0 / rate_hz
    nominal = np.arange(t[0], t[-1] - step, step)
    jitter = rng.uniform(-0.004, 0.004, len(nominal))
    idx = np.unique(np.clip(np.rint((nominal + jitter) / dt).astype(int), 0, len(t) - 1))
    pos = sim["position_mm"][idx] + rng.normal(0.0, world.noise_mm, len(idx))
    pos = np.round(pos / 0.001) * 0.001
    cur = sim["current_A"][idx] * (1.0 + 0.001 * rng.standard_normal(len(idx)))
    cur = np.where(sim["current_A"][idx] > 0, cur, 0.0)
    volt = cur * sim["resistance_ohm"][idx] * (1.0 + 0.001 * rng.standard_normal(len(idx)))
    amb = np.round(world.room_c + 0.05 * rng.standard_normal(len(idx)), 1)
    return {"t_s": t[idx], "current_A": cur, "voltage_V": volt, "ambient_C": amb,
            "position_mm": pos}  # fmt: skip


def write(folder: Path, world: World, load_kg: float, rec: dict) -> Path:
    folder.mkdir(parents=True)
    meta = {"schema_version": 1, "load_kg": load_kg, "status": "completed",
            "wire": {"length_mm": round(world.length_mm, 2), "diameter_mm": world.diameter_mm},
            "source": "tests/third_sim.py"}  # fmt: skip
    (folder / "session.json").write_text(json.dumps(meta))
    cols = ["t_s", "current_A", "voltage_V", "ambient_C", "position_mm"]
    with open(folder / "samples.csv", "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(cols)
        for row in zip(*(rec[c] for c in cols), strict=True):
            wr.writerow([f"{row[0]:.3f}", f"{row[1]:.4f}", f"{row[2]:.5f}", f"{row[3]:.1f}",
                         f"{row[4]:.3f}"])  # fmt: skip
    return folder


def make(folder: Path, effects: dict[str, float], load_kg: float, seed: int,
         n_cycles: int = 12, world: World | None = None) -> tuple[World, dict]:  # fmt: skip
    """Draw a world (unless given), simulate ``n_cycles`` cycles at ``load_kg``, write it."""
    rng = np.random.default_rng(seed)
    world = world or World.draw(rng, **effects)
    sim = simulate(world, load_kg, profile(rng, world, n_cycles), seed)
    write(folder, world, load_kg, record(world, sim, seed))
    return world, sim


def loads_for(world: World, stresses_mpa: list[float]) -> list[float]:
    """Hanging masses, kg, that give these stresses on the world's wire."""
    return [s * 1e6 * world.area_m2 / GRAVITY for s in stresses_mpa]
