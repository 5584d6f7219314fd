"""Plant simulation of an SMA wire carrying a hanging load: physics, not the paper's loop model.

State and equations (SI inside, °C / mm / MPa at the edges):

- Temperature: heat balance eq. (16), exact step with the current held over each sample
  (``smabench.physics.thermal``), plus the optional effects below.
- Martensite fraction ξ: cosine kinetics between the transformation temperatures. Major curves
  ``ξ_h(T)`` (heating, 1 → 0 from As to Af) and ``ξ_c(T)`` (cooling, 0 → 1 from Ms to Mf).
  From the last temperature reversal (T_r, ξ_r) the equilibrium fraction follows the scaled
  branch (return-point memory of partial transformations, so incomplete cycles and inner loops
  come out by themselves):
  heating ``ξ = ξ_r·ξ_h(T)/ξ_h(T_r)``, cooling ``ξ = 1 - (1-ξ_r)·(1-ξ_c(T))/(1-ξ_c(T_r))``.
  Stress narrows the thermal hysteresis: As, Af drop and Ms, Mf rise by
  ``wire.hysteresis_shrink_k_per_mpa·σ/2`` each (default 0.03 K/MPa: 26 K stress-free, ≈ 16 K at
  4 kg). The actual ξ lags its equilibrium value with a first-order time constant
  ``wire.kinetics_tau_heating_s`` (0.05 s) / ``wire.kinetics_tau_cooling_s`` (0.5 s, nucleation-
  limited forward transformation): the loop widens in temperature by ≈ τ·|dT/dt|.
- Length: ``L = L0·(1 + σ/E(ξ) + ε_L·ξ + α·(T - 22 °C) + ε_res)`` with the Reuss mixture
  ``1/E = ξ/E_M + (1-ξ)/E_A``, ε_L = ``wire.max_strain``, ε_res from ``cycle_drift``.
- Sensor: ``position_mm = L - L0`` (the slider grows with the wire length; heating lowers it),
  optional first-order lag, plus Gaussian noise (std ``noise_mm``, seeded).

Paper Fig. 11 trends (measured with ``loop_width_k`` / ``loop_mean_length_mm`` on the noise-free
length against the simulated temperature, same current profile):
- more load: the loop moves up (mean length grows: elastic strain σ/E) and gets narrower
  (width at mid-stroke shrinks with ``hysteresis_shrink_k_per_mpa``);
- larger h: wider (faster cooling → the lagging forward transformation bends the cooling branch
  to lower temperatures; width at mid-stroke grows);
- larger cp: thinner (slower heating and cooling → less kinetic lag; width shrinks).

Vectorisation (``simulate_plant``, ≈ 7e6–1e7 samples/s): temperature by one ``lfilter``; then the
hysteresis run by run between temperature reversals (each run one numpy expression), the kinetic
lag by one ``lfilter`` per run, friction (a play operator) run by run between length reversals,
the sensor lag by ``lfilter``. The effects that feed ξ or T back into the heat balance
(``latent_heat``, ``phase_resistance``, ``convection_nonlinear``) make the model sequential:
``simulate_plant`` then loops over ``Plant.step`` (≈ 1.5e5 steps/s, logged). Both paths implement
the same discrete equations (see ``Plant.step``) and agree to rounding.

Resistance (opt-in, ``resistivity=``, issue 26): with a
:class:`~smabench.physics.resistance.ResistivityModel` the wire's resistance is
``resistance_ohm(ξ, T, ε, wire, model, rphase_fraction(T, cooling, model))``
(:mod:`smabench.physics.resistance`) with ε = length / ``wire.length_mm`` − 1 (the strain the
plant computes: elastic, transformation, thermal, after friction) and ``cooling`` the branch the
plant tracks (its temperature direction < 0), used for the Joule heat and for ``voltage_v`` /
``resistance_ohm``. R then depends on the state, so the simulation is sequential, as for the
coupled effects. Without it (the default) R is ``R_mean + ΔR·(0.5 − ξ)`` (``phase_resistance``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields

import numpy as np

from smabench.physics.effects import (
    CYCLE_DRIFT_TAU_CYCLES,
    EFFECT_DOCS,
    REFERENCE_STRESS_MPA,
    Effects,
)
from smabench.physics.resistance import ResistivityModel
from smabench.physics.thermal import (
    linear_recurrence,
    steady_state_temperature,
    step_exact,
    thermal_constants,
    time_constant_s,
)
from smabench.physics.wire import PAPER_WIRE, Wire, stress_mpa

__all__ = [
    "EFFECT_DOCS",
    "Effects",
    "Plant",
    "PlantState",
    "PlantTrace",
    "benchmark_plant",
    "heating_cycles_profile",
    "loop_mean_length_mm",
    "loop_width_k",
    "simulate_plant",
    "transformation_temperatures_c",
]

log = logging.getLogger(__name__)

T_REF_C = 22.0
"""Temperature, °C, at which thermal expansion is zero."""
_EPS_T = 1e-9  # K: temperature moves below this keep the previous direction
_EPS_L = 1e-12  # mm: same for the friction play operator


@dataclass
class PlantTrace:
    """Simulated samples; every field an array of len(t_s).

    Row n: ``current_a[n]`` is applied from ``t_s[n]`` to ``t_s[n+1]``; ``voltage_v[n]`` =
    current_a[n]·resistance_ohm[n] is the wire voltage during that interval; the other fields
    are the state at ``t_s[n]``. ``ambient_c`` is the true (possibly drifting) room temperature.
    """

    t_s: np.ndarray
    current_a: np.ndarray
    temperature_c: np.ndarray
    martensite_fraction: np.ndarray
    length_mm: np.ndarray
    position_mm: np.ndarray
    voltage_v: np.ndarray
    resistance_ohm: np.ndarray
    ambient_c: np.ndarray


@dataclass(frozen=True)
class PlantState:
    """One ``Plant.step`` result: state at ``t_s`` (end of the step); ``current_a`` and
    ``voltage_v`` are the values applied/measured during the step just taken."""

    t_s: float
    current_a: float
    temperature_c: float
    martensite_fraction: float
    length_mm: float
    position_mm: float
    voltage_v: float
    resistance_ohm: float
    ambient_c: float


def transformation_temperatures_c(
    load_kg: float, wire: Wire = PAPER_WIRE, effects: Effects | None = None
) -> dict[str, float]:
    """As, Af, Ms, Mf, °C, under ``load_kg`` (hysteresis shrink, plus stress_shift if on)."""
    effects = effects or Effects()
    sigma = float(stress_mpa(load_kg, wire))
    width = 0.5 * (wire.as_c + wire.af_c) - 0.5 * (wire.ms_c + wire.mf_c)
    half = 0.5 * min(wire.hysteresis_shrink_k_per_mpa * sigma, 0.8 * width)
    shift = (sigma - REFERENCE_STRESS_MPA) / effects.stress_shift if effects.stress_shift else 0.0
    return {
        "as_c": wire.as_c - half + shift,
        "af_c": wire.af_c - half + shift,
        "ms_c": wire.ms_c + half + shift,
        "mf_c": wire.mf_c + half + shift,
    }


class _Params:
    """Constants of one simulation (load, wire, effects), plain floats."""

    def __init__(
        self,
        load_kg: float,
        wire: Wire,
        effects: Effects,
        ambient_c: float,
        resistivity: ResistivityModel | None = None,
    ) -> None:
        self.wire = wire
        if resistivity is not None and effects.phase_resistance:
            raise ValueError("give resistivity or the phase_resistance effect, not both")
        self.rmodel = resistivity
        self.geom_ohm_per_ohm_m = wire.length_m / wire.area_m2
        self.effects = effects
        self.sigma_pa = float(stress_mpa(load_kg, wire)) * 1e6
        tt = transformation_temperatures_c(load_kg, wire, effects)
        self.as_c, self.af_c, self.ms_c, self.mf_c = tt["as_c"], tt["af_c"], tt["ms_c"], tt["mf_c"]
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.h_k = effects.convection_nonlinear
        self.r_mean = wire.resistance_mean_ohm
        # phase_resistance: µΩ·cm → Ω·m → Ω over the wire; R = R_mean + ΔR·(0.5 - ξ)
        self.dr_ohm = effects.phase_resistance * 1e-8 * wire.length_m / wire.area_m2
        self.latent_k = effects.latent_heat / wire.cp_j_kgk  # K per unit ξ
        self.tau_heat = wire.kinetics_tau_heating_s
        self.tau_cool = wire.kinetics_tau_cooling_s
        self.inv_ea = 1.0 / wire.e_austenite_pa
        self.inv_em = 1.0 / wire.e_martensite_pa
        self.eps_l = wire.max_strain
        self.alpha = wire.alpha_per_k
        self.l0_mm = wire.length_mm
        e_eff = 2.0 / (self.inv_ea + self.inv_em)
        self.play_mm = effects.pulley_friction * wire.length_m / (e_eff * wire.area_m2) * 1e3
        self.tau_sensor = effects.sensor_lag
        self.ambient_c = ambient_c
        self.drift_k_s = effects.ambient_drift / 3600.0
        self.sine_k = effects.ambient_sine
        self.sine_w = 2.0 * math.pi / effects.ambient_sine_period
        self.drift_rate = effects.cycle_drift
        self.drift_tau = CYCLE_DRIFT_TAU_CYCLES

    def ambient(self, t_s):
        out = self.ambient_c + self.drift_k_s * t_s
        if self.sine_k:
            out = out + self.sine_k * np.sin(self.sine_w * t_s)
        return out

    def decay(self, dt_s, tau_s):
        return np.exp(-dt_s / tau_s) if tau_s > 0 else 0.0 * dt_s

    # --- kinetics (numpy, also fine on floats)
    def xi_heat(self, temp):
        x = np.clip((temp - self.as_c) / (self.af_c - self.as_c), 0.0, 1.0)
        return 0.5 * (1.0 + np.cos(np.pi * x))

    def xi_cool(self, temp):
        x = np.clip((temp - self.mf_c) / (self.ms_c - self.mf_c), 0.0, 1.0)
        return 0.5 * (1.0 + np.cos(np.pi * x))

    def branch(self, direction: int, temp, t_r: float, xi_r: float):
        """Equilibrium ξ on the branch leaving the reversal (t_r, xi_r)."""
        if direction > 0:
            ref = max(float(self.xi_heat(t_r)), 1e-12)
            return np.clip(xi_r * self.xi_heat(temp) / ref, 0.0, xi_r)
        if direction < 0:
            ref = max(1.0 - float(self.xi_cool(t_r)), 1e-12)
            return np.clip(1.0 - (1.0 - xi_r) * (1.0 - self.xi_cool(temp)) / ref, xi_r, 1.0)
        return xi_r + 0.0 * temp

    def resistance(self, xi):
        return self.r_mean + self.dr_ohm * (0.5 - xi)

    def model_resistance(self, xi: float, temp: float, length_mm: float, cooling: bool) -> float:
        """R, Ω, of the resistivity model at one state (floats): the scalar form of
        ``resistance_ohm(xi, temp, length_mm/l0 - 1, wire, model, rphase_fraction(temp,
        cooling, model))`` (same operations; a test checks they agree to rounding)."""
        m = self.rmodel
        dt = temp - m.ref_c
        rho_a = m.rho_austenite_ohm_m * (1.0 + m.tcr_austenite_per_k * dt)
        rest = rho_a
        if cooling and m.rho_rphase_ohm_m is not None:
            x = min(max((temp - m.rf_c) / (m.rs_c - m.rf_c), 0.0), 1.0)
            r = 0.5 * (1.0 + math.cos(math.pi * x))
            rho_r = m.rho_rphase_ohm_m * (1.0 + m.tcr_austenite_per_k * dt)
            rest = (1.0 - r) * rho_a + r * rho_r
        rho = xi * m.rho_martensite_ohm_m * (1.0 + m.tcr_martensite_per_k * dt) + (1.0 - xi) * rest
        return rho * self.geom_ohm_per_ohm_m * (1.0 + (length_mm / self.l0_mm - 1.0)) ** 2

    def residual_strain(self, cycles):
        if not self.drift_rate:
            return 0.0 * cycles
        return self.drift_rate * self.drift_tau * (1.0 - np.exp(-cycles / self.drift_tau))

    def free_length_mm(self, temp, xi, cycles):
        inv_e = xi * self.inv_em + (1.0 - xi) * self.inv_ea
        strain = (
            self.sigma_pa * inv_e
            + self.eps_l * xi
            + self.alpha * (temp - T_REF_C)
            + self.residual_strain(cycles)
        )
        return self.l0_mm * (1.0 + strain)


class Plant:
    """Online plant for the real-time mock bench: ``step(dt_s, current_a)`` in O(1).

    Discrete equations of one step from t to t+dt (shared with ``simulate_plant``):
    ambient T_a(t); R = R(ξ); h·A = h0·A·(1 + k·(T - T_a)); exact thermal step; direction of
    T (moves < 1e-9 K keep the previous one), a new direction stores the reversal (T, ξ_eq);
    ξ_eq on the branch; ξ ← b·ξ + (1-b)·ξ_eq with b = exp(-dt/τ_heating|cooling);
    T += L/cp·Δξ (latent heat); cycles += |Δξ|/2; free length; friction play
    L ← clip(L, L_free - d, L_free + d); sensor lag; noise.

    ``resistivity``: R from the resistivity model (module docstring), else ``R_mean + ΔR·(0.5 −
    ξ)``; the R of a state is the one the next step heats with.
    """

    def __init__(
        self,
        load_kg: float,
        wire: Wire = PAPER_WIRE,
        effects: Effects | None = None,
        *,
        ambient_c: float = 22.0,
        temperature_c: float | None = None,
        martensite_fraction: float = 1.0,
        noise_mm: float = 0.002,
        seed: int = 0,
        resistivity: ResistivityModel | None = None,
    ) -> None:
        self.p = _Params(load_kg, wire, effects or Effects(), ambient_c, resistivity)
        self.load_kg = load_kg
        self.noise_mm = noise_mm
        self.rng = np.random.default_rng(seed)
        self.t_s = 0.0
        ta = float(self.p.ambient(0.0))
        self.temperature_c = ta if temperature_c is None else float(temperature_c)
        self.xi = self.xi_eq = self.xi_r = float(martensite_fraction)
        self.t_r = self.temperature_c
        self.direction = 0
        self.cycles = 0.0
        self.length_mm = float(self.p.free_length_mm(self.temperature_c, self.xi, 0.0))
        self.position_true_mm = self.length_mm - self.p.l0_mm
        noise = self.rng.normal(0.0, noise_mm) if noise_mm > 0 else 0.0
        if self.p.rmodel is None:
            r = float(self.p.resistance(self.xi))
        else:
            r = self.p.model_resistance(self.xi, self.temperature_c, self.length_mm, False)
        self._resistance_ohm = r
        self.state = PlantState(
            0.0, 0.0, self.temperature_c, self.xi, self.length_mm,
            self.position_true_mm + noise, 0.0, r, ta,
        )  # fmt: skip

    def step(self, dt_s: float, current_a: float) -> PlantState:
        """Apply ``current_a`` (A) for ``dt_s`` (s); returns the state at the end of the step."""
        p = self.p
        t0 = self.t_s
        ta = p.ambient_c + p.drift_k_s * t0
        if p.sine_k:
            ta += p.sine_k * math.sin(p.sine_w * t0)
        temp, xi = self.temperature_c, self.xi
        r = p.r_mean + p.dr_ohm * (0.5 - xi) if p.rmodel is None else self._resistance_ohm
        g = p.conductance * (1.0 + p.h_k * (temp - ta)) if p.h_k else p.conductance
        g = max(g, 1e-9)
        t_inf = ta + current_a * current_a * r / g
        temp_new = t_inf + (temp - t_inf) * math.exp(-dt_s * g / p.heat_capacity)
        d_temp = temp_new - temp
        d = 1 if d_temp > _EPS_T else (-1 if d_temp < -_EPS_T else self.direction)
        if d != self.direction:
            self.t_r, self.xi_r, self.direction = temp, self.xi_eq, d
        if d > 0:
            x = min(max((temp_new - p.as_c) / (p.af_c - p.as_c), 0.0), 1.0)
            g_t = 0.5 * (1.0 + math.cos(math.pi * x))
            x = min(max((self.t_r - p.as_c) / (p.af_c - p.as_c), 0.0), 1.0)
            g_r = max(0.5 * (1.0 + math.cos(math.pi * x)), 1e-12)
            self.xi_eq = min(max(self.xi_r * g_t / g_r, 0.0), self.xi_r)
            tau = p.tau_heat
        elif d < 0:
            x = min(max((temp_new - p.mf_c) / (p.ms_c - p.mf_c), 0.0), 1.0)
            g_t = 0.5 * (1.0 + math.cos(math.pi * x))
            x = min(max((self.t_r - p.mf_c) / (p.ms_c - p.mf_c), 0.0), 1.0)
            g_r = max(1.0 - 0.5 * (1.0 + math.cos(math.pi * x)), 1e-12)
            self.xi_eq = min(max(1.0 - (1.0 - self.xi_r) * (1.0 - g_t) / g_r, self.xi_r), 1.0)
            tau = p.tau_cool
        else:
            tau = p.tau_cool
        b = math.exp(-dt_s / tau) if tau > 0 else 0.0
        xi_new = b * xi + (1.0 - b) * self.xi_eq
        if p.latent_k:
            temp_new += p.latent_k * (xi_new - xi)
        self.cycles += abs(xi_new - xi) * 0.5
        inv_e = xi_new * p.inv_em + (1.0 - xi_new) * p.inv_ea
        strain = p.sigma_pa * inv_e + p.eps_l * xi_new + p.alpha * (temp_new - T_REF_C)
        if p.drift_rate:
            strain += p.drift_rate * p.drift_tau * (1.0 - math.exp(-self.cycles / p.drift_tau))
        free = p.l0_mm * (1.0 + strain)
        self.length_mm = min(max(self.length_mm, free - p.play_mm), free + p.play_mm)
        bs = math.exp(-dt_s / p.tau_sensor) if p.tau_sensor > 0 else 0.0
        self.position_true_mm = bs * self.position_true_mm + (1.0 - bs) * (self.length_mm - p.l0_mm)
        noise = self.rng.normal(0.0, self.noise_mm) if self.noise_mm > 0 else 0.0
        self.temperature_c, self.xi = temp_new, xi_new
        self.t_s = t0 + dt_s
        ta1 = p.ambient_c + p.drift_k_s * self.t_s
        if p.sine_k:
            ta1 += p.sine_k * math.sin(p.sine_w * self.t_s)
        if p.rmodel is None:
            self._resistance_ohm = p.r_mean + p.dr_ohm * (0.5 - xi_new)
        else:
            self._resistance_ohm = p.model_resistance(xi_new, temp_new, self.length_mm, d < 0)
        self.state = PlantState(
            self.t_s, current_a, temp_new, xi_new, self.length_mm,
            self.position_true_mm + noise, current_a * r, self._resistance_ohm, ta1,
        )  # fmt: skip
        return self.state


def _runs(direction: np.ndarray) -> list[tuple[int, int, int]]:
    """Maximal runs [start, end) of equal values in ``direction`` → (start, end, value)."""
    if len(direction) == 0:
        return []
    edges = np.flatnonzero(np.diff(direction)) + 1
    starts = np.concatenate(([0], edges))
    ends = np.concatenate((edges, [len(direction)]))
    return list(zip(starts.tolist(), ends.tolist(), direction[starts].tolist(), strict=True))


def _directions(delta: np.ndarray, eps: float) -> np.ndarray:
    """Sign of ``delta`` with |delta| < eps carrying the previous sign forward (0 at the start)."""
    d = np.where(delta > eps, 1, np.where(delta < -eps, -1, 0)).astype(np.int8)
    idx = np.where(d != 0, np.arange(len(d)), 0)
    np.maximum.accumulate(idx, out=idx)
    return d[idx]


def _play(x: np.ndarray, half_width: float) -> np.ndarray:
    """Play (backlash) operator y[n] = clip(y[n-1], x[n]-w, x[n]+w), y[0] = x[0]; by runs."""
    if half_width <= 0 or len(x) < 2:
        return x.copy()
    y = np.empty_like(x)
    y[0] = x[0]
    for s, e, d in _runs(_directions(np.diff(x), _EPS_L)):
        seg = x[s + 1 : e + 1]
        y_s = y[s]
        if d >= 0:
            y[s + 1 : e + 1] = np.minimum(np.maximum(y_s, seg - half_width), seg + half_width)
        else:
            y[s + 1 : e + 1] = np.maximum(np.minimum(y_s, seg + half_width), seg - half_width)
    return y


def simulate_plant(
    t_s: np.ndarray,
    current_a: np.ndarray,
    *,
    load_kg: float,
    wire: Wire = PAPER_WIRE,
    ambient_c: float = 22.0,
    effects: Effects | None = None,
    noise_mm: float = 0.002,
    seed: int = 0,
    temperature_c: float | None = None,
    martensite_fraction: float = 1.0,
    resistivity: ResistivityModel | None = None,
) -> PlantTrace:
    """Simulate the plant over a current profile sampled at ``t_s`` (s, increasing).

    ``current_a[n]`` (A, 0 … ~2) is held from t_s[n] to t_s[n+1]; ``load_kg`` the hanging mass
    (1–4 kg); ``ambient_c`` the nominal room temperature, °C; ``noise_mm`` the sensor noise std,
    mm; the wire starts at ambient (or ``temperature_c``) and fully martensitic;
    ``resistivity``: R from that resistivity model (module docstring), opt-in.
    Vectorised unless a coupled effect is on or ``resistivity`` is given (then a loop over
    ``Plant.step``).
    """
    effects = effects or Effects()
    t_s = np.asarray(t_s, dtype=float)
    cur = np.broadcast_to(np.asarray(current_a, dtype=float), t_s.shape).copy()
    n = len(t_s)
    if n == 0:
        raise ValueError("simulate_plant needs at least one sample time")
    if effects.coupled or resistivity is not None:
        return _simulate_sequential(
            t_s, cur, load_kg, wire, ambient_c, effects, noise_mm, seed, temperature_c,
            martensite_fraction, resistivity,
        )  # fmt: skip
    p = _Params(load_kg, wire, effects, ambient_c)
    amb = p.ambient(t_s)
    dt = np.diff(t_s)
    uniform = len(dt) > 0 and bool(np.allclose(dt, dt[0], rtol=1e-9, atol=0.0))
    # temperature: one linear recurrence (exact zero-order-hold steps)
    a_th = np.exp(-dt * p.conductance / p.heat_capacity)
    if uniform:
        a_th = float(a_th[0])
    t_inf = amb[:-1] + cur[:-1] ** 2 * p.r_mean / p.conductance
    t0 = float(amb[0]) if temperature_c is None else float(temperature_c)
    temp = linear_recurrence(a_th, (1.0 - np.asarray(a_th)) * t_inf, t0)[:n]
    # equilibrium fraction: run by run between temperature reversals
    direction = _directions(np.diff(temp), _EPS_T)
    xi_eq = np.empty(n)
    xi_eq[0] = martensite_fraction
    runs = _runs(direction)
    for s, e, d in runs:
        xi_eq[s + 1 : e + 1] = p.branch(d, temp[s + 1 : e + 1], temp[s], xi_eq[s])
    # kinetic lag: constant coefficient within a run
    xi = np.empty(n)
    xi[0] = martensite_fraction
    for s, e, d in runs:
        tau = p.tau_heat if d > 0 else p.tau_cool
        b = p.decay(dt[s:e], tau)
        if uniform:
            b = float(b[0])
        xi[s : e + 1] = linear_recurrence(b, (1.0 - np.asarray(b)) * xi_eq[s + 1 : e + 1], xi[s])
    cycles = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(xi))) * 0.5))
    length = _play(p.free_length_mm(temp, xi, cycles), p.play_mm)
    pos = length - p.l0_mm
    if p.tau_sensor > 0 and n > 1:
        bs = p.decay(dt, p.tau_sensor)
        if uniform:
            bs = float(bs[0])
        pos = linear_recurrence(bs, (1.0 - np.asarray(bs)) * pos[1:], pos[0])
    if noise_mm > 0:
        pos = pos + np.random.default_rng(seed).normal(0.0, noise_mm, n)
    res = p.resistance(xi)
    return PlantTrace(t_s, cur, temp, xi, length, pos, cur * res, res, amb)


def _simulate_sequential(
    t_s, cur, load_kg, wire, ambient_c, effects, noise_mm, seed, temperature_c, xi0,
    resistivity=None,
) -> PlantTrace:  # fmt: skip
    n = len(t_s)
    why = effects.active() + (["resistivity"] if resistivity is not None else [])
    log.info("coupled effects %s: sequential simulation of %d samples", why, n)
    plant = Plant(
        load_kg, wire, effects, ambient_c=ambient_c, temperature_c=temperature_c,
        martensite_fraction=xi0, noise_mm=noise_mm, seed=seed, resistivity=resistivity,
    )  # fmt: skip
    out = np.empty((n, 9))
    s0 = plant.state
    out[0] = [
        t_s[0] if n else 0.0, 0.0, s0.temperature_c, s0.martensite_fraction, s0.length_mm,
        s0.position_mm, 0.0, s0.resistance_ohm, s0.ambient_c,
    ]  # fmt: skip
    for k, (dt, i) in enumerate(zip(np.diff(t_s).tolist(), cur[:-1].tolist(), strict=True)):
        s = plant.step(dt, i)
        out[k + 1] = [
            s.t_s, 0.0, s.temperature_c, s.martensite_fraction, s.length_mm,
            s.position_mm, 0.0, s.resistance_ohm, s.ambient_c,
        ]  # fmt: skip
    res = out[:, 7]
    return PlantTrace(
        t_s, cur, out[:, 2], out[:, 3], out[:, 4], out[:, 5], cur * res, res, out[:, 8]
    )


def heating_cycles_profile(
    n_cycles: int,
    current_a: float,
    heat_s: float,
    cool_s: float,
    dt_s: float = 1e-3,
    kind: str = "complete",
    *,
    wire: Wire = PAPER_WIRE,
    load_kg: float = 2.0,
    ambient_c: float = 22.0,
    effects: Effects | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Current profile of the paper's three excitations; returns ``(t_s, current_a)``.

    - ``complete``: n × (heat ``heat_s`` at ``current_a``, then off for ``cool_s``).
    - ``incomplete``: every cycle heats for ``heat_s``; all but the last cooling stop (and the
      wire is reheated) when the heat balance says the wire reached the middle of Ms…Mf, so
      the martensite never forms fully (capped at ``cool_s``).
    - ``inner``: one full heating, then n - 1 short cycles reversing in the middle of Ms…Mf
      (cooling) and of As…Af (heating), so both reversals fall inside the transformation
      (inner loops), then a full ``cool_s`` cooling.
    The switch times come from the exact heat balance of ``wire`` at the transformation
    temperatures under ``load_kg`` (kg) and ``effects``; a phase never exceeds heat_s/cool_s.
    """
    if kind not in ("complete", "incomplete", "inner"):
        raise ValueError(f"kind must be complete, incomplete or inner, got {kind!r}")
    tt = transformation_temperatures_c(load_kg, wire, effects)
    cool_mid = 0.5 * (tt["ms_c"] + tt["mf_c"])
    heat_mid = 0.5 * (tt["as_c"] + tt["af_c"])
    tau = time_constant_s(wire)
    hot = steady_state_temperature(current_a, wire, ambient_c)

    def time_to(temp0: float, target: float, t_inf: float, cap: float) -> float:
        ratio = (temp0 - t_inf) / (target - t_inf) if target != t_inf else math.inf
        return min(cap, tau * math.log(ratio)) if ratio > 1.0 else cap

    phases: list[tuple[float, float]] = []
    temp = ambient_c

    def add(duration: float, current: float) -> None:
        nonlocal temp
        phases.append((duration, current))
        temp = float(step_exact(temp, current, duration, wire, ambient_c))

    if kind == "complete":
        for _ in range(n_cycles):
            add(heat_s, current_a)
            add(cool_s, 0.0)
    elif kind == "incomplete":
        for _ in range(max(n_cycles - 1, 0)):
            add(heat_s, current_a)
            add(time_to(temp, cool_mid, ambient_c, cool_s), 0.0)
        add(heat_s, current_a)
        add(cool_s, 0.0)
    else:
        add(heat_s, current_a)
        for _ in range(max(n_cycles - 1, 0)):
            add(time_to(temp, cool_mid, ambient_c, cool_s), 0.0)
            add(time_to(temp, heat_mid, hot, heat_s), current_a)
        add(cool_s, 0.0)
    counts = [int(round(d / dt_s)) for d, _ in phases]
    cur = np.repeat([c for _, c in phases], counts).astype(float)
    return np.arange(len(cur)) * dt_s, cur


def loop_width_k(temperature_c: np.ndarray, length_mm: np.ndarray) -> float:
    """Loop width, K, at mid-stroke: T where the heating branch crosses the mid length minus T
    where the cooling branch crosses it (first crossings of one cycle; > 0 for a normal loop)."""
    temp = np.asarray(temperature_c, dtype=float)
    length = np.asarray(length_mm, dtype=float)
    mid = 0.5 * (length.max() + length.min())
    k_peak = int(np.argmax(temp))
    heat_t = _crossing(temp[: k_peak + 1], length[: k_peak + 1], mid)
    cool_t = _crossing(temp[k_peak:], length[k_peak:], mid)
    return heat_t - cool_t


def _crossing(temp: np.ndarray, length: np.ndarray, level: float) -> float:
    above = length > level
    k = int(np.flatnonzero(above[1:] != above[:-1])[0])
    f = (level - length[k]) / (length[k + 1] - length[k])
    return float(temp[k] + f * (temp[k + 1] - temp[k]))


def loop_mean_length_mm(length_mm: np.ndarray) -> float:
    """Mean of the loop's length range, mm: (max + min)/2 (its vertical position)."""
    return 0.5 * float(np.max(length_mm) + np.min(length_mm))


def benchmark_plant(duration_s: float = 60.0, dt_s: float = 1e-3, repeat: int = 3) -> dict:
    """Speed of ``simulate_plant`` at a 1 kHz step and of ``Plant.step``.

    Returns ``{"steps_per_s", "x_real_time", "plant_step_us", "samples"}``.
    """
    t_s, cur = heating_cycles_profile(
        max(1, int(duration_s // 10)), 1.3, 4.0, 6.0, dt_s, "complete"
    )
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        simulate_plant(t_s, cur, load_kg=2.0)
        best = min(best, time.perf_counter() - t0)
    steps_per_s = len(t_s) / best
    plant = Plant(2.0)
    n_step = 20000
    t0 = time.perf_counter()
    for i in cur[:n_step].tolist():
        plant.step(dt_s, i)
    step_us = (time.perf_counter() - t0) / n_step * 1e6
    return {
        "steps_per_s": steps_per_s,
        "x_real_time": steps_per_s * dt_s,
        "plant_step_us": step_us,
        "samples": len(t_s),
    }


# keep the dataclass field list handy for writers (CSV export etc.)
TRACE_FIELDS = [f.name for f in fields(PlantTrace)]
