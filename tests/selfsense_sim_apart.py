"""A second SMA-wire simulator, written apart from ``smabench.physics``, for checking the
self-sensing estimator (``smabench.selfsense``) on a wire it was not tuned on (issue 26, item 8).

It imports nothing from ``smabench.physics`` and differs from the project's plant on purpose:

- hysteresis: major branches are tanh curves (tails, no hard As/Af), and partial loops follow a
  stack of reversal points with the Madelung rules (true return-point memory and wiping-out:
  a minor branch runs from its reversal point to the previous one of the other direction, scaled
  between them, and when it gets there the inner loop is deleted and the outer branch goes on).
  The plant has compact cosine branches, a branch scaled from the last reversal only, and a
  first-order kinetic lag; here there is no kinetic lag, ξ is the equilibrium value;
- stress: Clausius–Clapeyron moves the whole loop (both branches by the same ``dT/dσ``, 1/7
  K/MPa), and the transformation strain saturates with stress, ``ε_T = ε_L·(1 − exp(−σ/σ*))``
  (ε_L 4.2 %, σ* 60 MPa: 3.1, 3.9, 4.1 % at 78, 156, 234 MPa), so a lighter load gives a
  shorter stroke (the plant: a constant ε_L, the hysteresis narrowing with stress). The same
  repository as the measured series (Mecanon/morphing_wing, isobaric tests of one wire,
  experimental/TECA/filtered_data_50MPa.txt and experimental/curve_fitting/
  filtered_data_200MPa.txt) shows this much: 4.1 % at 50 MPa, more than 6 % at 200 MPa (7.44 %
  cold, 0.99 % at 119.6 °C and still falling, less ≈ 0.4 % of elastic change), i.e. σ* ≈ 45-55
  MPa and ε_T(78)/ε_T(156) ≈ 0.8-0.85, as here (0.78);
- heat: forward Euler on 2 ms sub-steps, convection plus a constant linearised radiation term
  ``h_rad``, latent heat Λ as an apparent heat capacity ``c + Λ·|dξ/dT|``, R(ξ, T, ε) in the
  Joule heat; own wire (0.31 mm × 80 mm), own current levels (1.0 A heating, 60 mA probe);
- resistance law of its own: ``R = R_0·(1 + k_ε·ε)·(1 + k_A·(1 − ξ))·(1 + α·(T − 20 °C))·
  (1 + b_R·r)``, r the R-phase fraction: linear in the total strain with a gauge factor
  k_ε = 2.3 (the plant: the volume-conserving ``(1 + ε)²``), the austenite 3.5 % *below* the
  martensite (the plant's preset: 1 % above; the measured TECA run in
  tests/data/mecanon-teca-run5 points this way),
  α = 3e-4 /K for both phases (plant 5e-4), and an R-phase bump of 6 % whose equilibrium
  fraction is a Gaussian in temperature on cooling, weighted by the austenite left, with its
  own first-order time constant (0.4 s) so it does not vanish at once on a reversal, centred
  9 K above the cooling branch's middle at 150 MPa and moving with stress at 0.05 K/MPa only,
  so that under load it overlaps the start of the martensite (the plant's: a cosine ramp
  between Rs and Rf, memoryless, 15 %, clear of Ms);
- measurement: a 14-bit ADC over ±2.048 V at gain 1 (250 µV LSB; the bench: 16 bit, 125 µV at
  the wire), white noise 150 µV RMS, 1/f (pink) noise 60 µV RMS, occasional spikes (one sample
  in 2000, ±2 … 8 mV), the current read with a 0.2 % gain error and 0.5 mA noise, 250 Hz; the
  laser with 2 µm noise and a 1 µm step.

Sessions are written with smabench's session writer (``smabench.sessions.write_session``), the
format the CLI reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

G = 9.80665


@dataclass(frozen=True)
class ApartWire:
    """Wire, material and bench of the simulator written apart. Units in the names."""

    diameter_mm: float = 0.31
    length_mm: float = 80.0
    density_kg_m3: float = 6450.0
    cp_j_kgk: float = 840.0
    h0_w_m2k: float = 70.0
    h_rad_w_m2k: float = 8.0
    latent_j_kg: float = 18_000.0
    # hysteresis at the reference stress: tanh branch centres and half-widths, °C
    heat_mid_c: float = 80.0
    cool_mid_c: float = 58.0
    heat_width_c: float = 4.0
    cool_width_c: float = 5.0
    ref_stress_mpa: float = 150.0
    cc_k_per_mpa: float = 1.0 / 7.0  # Clausius–Clapeyron dT/dσ (7 MPa/K)
    # strain
    eps_l: float = 0.042
    sigma_star_mpa: float = 60.0
    e_m_gpa: float = 28.0
    e_a_gpa: float = 65.0
    alpha_th_per_k: float = 1.0e-5
    # resistance law
    rho0_ohm_m: float = 82e-8  # martensite, stress-free, 20 °C
    k_eps: float = 2.3
    k_a: float = -0.035
    tcr_per_k: float = 3.0e-4
    rphase_bump: float = 0.06
    rphase_centre_above_cool_mid_c: float = 9.0
    rphase_sigma_c: float = 3.0
    rphase_tau_s: float = 0.4
    rphase_cc_k_per_mpa: float = 0.05  # the R-phase moves less with stress than martensite
    # bench
    ambient_c: float = 23.0
    rate_hz: float = 250.0
    heat_a: float = 1.0
    probe_a: float = 0.06

    @property
    def area_m2(self) -> float:
        return math.pi * (0.5e-3 * self.diameter_mm) ** 2


@dataclass(frozen=True)
class Noise:
    """The measurement's imperfections (see the module docstring)."""

    lsb_v: float = 2.048 / 2**13
    full_scale_v: float = 2.048
    white_v: float = 150e-6
    pink_v: float = 60e-6
    spike_rate: float = 1.0 / 2000.0
    spike_v: tuple[float, float] = (2e-3, 8e-3)
    current_gain: float = 0.002
    current_noise_a: float = 0.5e-3
    laser_noise_mm: float = 0.002
    laser_step_mm: float = 0.001
    extras: dict[str, float] = field(default_factory=dict)


def _tanh_branch(t: float, mid: float, width: float) -> float:
    """Martensite fraction on a major branch: 1 cold, 0 hot."""
    return 0.5 * (1.0 - math.tanh((t - mid) / width))


class _Hysteresis:
    """Tanh major branches and a stack of reversal points (Madelung rules).

    ``stack`` holds reversal points (T, ξ) in order; the current branch runs from the last one
    toward its target: the previous one (the last reversal of the other direction), or the major
    branch's end when there is none. Heating (ξ falls) uses the heating branch F_h, cooling F_c:
    ``ξ = ξ_t + (ξ_s − ξ_t)·(F(T) − F(T_t))/(F(T_s) − F(T_t))`` between start s and target t.
    """

    def __init__(self, w: ApartWire, shift_c: float) -> None:
        self.hm, self.hw = w.heat_mid_c + shift_c, w.heat_width_c
        self.cm, self.cw = w.cool_mid_c + shift_c, w.cool_width_c
        self.xi = 1.0
        self.t_prev: float | None = None
        self.heating: bool | None = None
        # outermost start: a rested cold wire on the cooling branch's cold end
        self.stack: list[tuple[float, float]] = []

    def _f(self, t: float, heating: bool) -> float:
        return (_tanh_branch(t, self.hm, self.hw) if heating
                else _tanh_branch(t, self.cm, self.cw))  # fmt: skip

    def peek(self, t: float) -> float:
        """ξ that ``update(t)`` would give, the state left unchanged."""
        saved = (list(self.stack), self.xi, self.t_prev, self.heating)
        xi = self.update(t)
        self.stack, self.xi, self.t_prev, self.heating = saved
        return xi

    def update(self, t: float) -> float:
        if self.t_prev is None:
            self.t_prev = t
            return self.xi
        dt = t - self.t_prev
        if dt == 0.0:
            return self.xi
        heating = dt > 0
        if self.heating is not None and heating != self.heating:
            self.stack.append((self.t_prev, self.xi))  # a reversal
        self.heating = heating
        self.t_prev = t
        while True:
            if not self.stack:
                # no reversal yet: on the major branch of this direction, clipped so that ξ
                # only moves the way the direction allows
                f = self._f(t, heating)
                self.xi = min(self.xi, f) if heating else max(self.xi, f)
                return self.xi
            ts, xs = self.stack[-1]
            if len(self.stack) >= 2:
                tt, xt = self.stack[-2]
            else:
                tt, xt = (math.inf, 0.0) if heating else (-math.inf, 1.0)
            passed = (t >= tt) if heating else (t <= tt)
            if passed and len(self.stack) >= 2:
                # wiping-out: the inner loop closes, continue on the outer branch
                del self.stack[-2:]
                continue
            fs = self._f(ts, heating)
            # the major branch's end: F(+∞) = 0 heating, F(−∞) = 1 cooling
            ft = (0.0 if heating else 1.0) if math.isinf(tt) else self._f(tt, heating)
            ft_now = self._f(t, heating)
            den = fs - ft
            if abs(den) < 1e-12:
                self.xi = xs
            else:
                self.xi = xt + (xs - xt) * (ft_now - ft) / den
            self.xi = min(max(self.xi, 0.0), 1.0)
            return self.xi


def _pink(rng: np.random.Generator, n: int, rms: float) -> np.ndarray:
    """1/f noise by spectral shaping of white noise, scaled to ``rms``."""
    if rms <= 0 or n < 4:
        return np.zeros(n)
    spec = np.fft.rfft(rng.standard_normal(n))
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    x = np.fft.irfft(spec / np.sqrt(f), n)
    x -= x.mean()
    return x * (rms / x.std())


def profile(phases: list[tuple[float, str]], w: ApartWire) -> tuple[np.ndarray, np.ndarray]:
    """(t_s, current set point A) at ``w.rate_hz`` from (duration s, 'heat' | 'probe') phases."""
    dt = 1.0 / w.rate_hz
    cur = np.concatenate([
        np.full(int(round(d / dt)), w.heat_a if kind == "heat" else w.probe_a)
        for d, kind in phases
    ])  # fmt: skip
    return np.arange(len(cur)) * dt, cur


def simulate(w: ApartWire, load_kg: float, t: np.ndarray, current_a: np.ndarray,
             noise: Noise | None, seed: int) -> dict[str, np.ndarray]:  # fmt: skip
    """Run the wire; returns the true state and the measured columns (``noise=None``: exact)."""
    rng = np.random.default_rng(seed)
    area = w.area_m2
    l0 = w.length_mm * 1e-3
    mass = w.density_kg_m3 * area * l0
    surface = math.pi * w.diameter_mm * 1e-3 * l0
    sigma_mpa = load_kg * G / area * 1e-6
    hyst = _Hysteresis(w, (sigma_mpa - w.ref_stress_mpa) * w.cc_k_per_mpa)
    eps_t = w.eps_l * (1.0 - math.exp(-sigma_mpa / w.sigma_star_mpa))
    r0 = w.rho0_ohm_m * l0 / area
    h = w.h0_w_m2k + w.h_rad_w_m2k
    rp_mid = (
        w.cool_mid_c
        + w.rphase_centre_above_cool_mid_c
        + (sigma_mpa - w.ref_stress_mpa) * w.rphase_cc_k_per_mpa
    )

    def strain(xi: float, temp: float) -> float:
        compliance = xi / (w.e_m_gpa * 1e3) + (1.0 - xi) / (w.e_a_gpa * 1e3)  # Reuss, 1/MPa
        return sigma_mpa * compliance + eps_t * xi + w.alpha_th_per_k * (temp - w.ambient_c)

    def resist(xi: float, temp: float, eps: float, rp: float) -> float:
        return (r0 * (1.0 + w.k_eps * eps) * (1.0 + w.k_a * (1.0 - xi))
                * (1.0 + w.tcr_per_k * (temp - 20.0)) * (1.0 + w.rphase_bump * rp))  # fmt: skip

    n = len(t)
    dt = float(t[1] - t[0])
    sub = max(1, int(round(dt / 2e-3)))
    hdt = dt / sub
    out = {k: np.empty(n) for k in ("temperature_c", "xi", "strain", "resistance_ohm", "rphase")}
    temp, xi, rp = w.ambient_c, 1.0, 0.0
    hyst.update(temp)
    for k in range(n):
        i_a = float(current_a[k])
        for _ in range(sub):
            eps = strain(xi, temp)
            r = resist(xi, temp, eps, rp)
            power_w = i_a * i_a * r - h * surface * (temp - w.ambient_c)
            d_temp = hdt * power_w / (mass * w.cp_j_kgk)
            if d_temp == 0.0:
                continue
            # latent heat as an apparent heat capacity c + Λ·|dξ/dT| on the branch being
            # followed (absorbed while ξ falls, released while it rises): the step keeps its sign
            probe = 0.05 if d_temp > 0 else -0.05
            slope = abs(hyst.peek(temp + probe) - xi) / 0.05
            new_temp = temp + d_temp * w.cp_j_kgk / (w.cp_j_kgk + w.latent_j_kg * slope)
            cooling = d_temp < 0
            new_xi = hyst.update(new_temp)
            target = (math.exp(-(((new_temp - rp_mid) / w.rphase_sigma_c) ** 2)) * (1.0 - new_xi)
                      if cooling else 0.0)  # fmt: skip
            rp += (target - rp) * (1.0 - math.exp(-hdt / w.rphase_tau_s))
            temp, xi = new_temp, new_xi
        eps = strain(xi, temp)
        out["temperature_c"][k] = temp
        out["xi"][k] = xi
        out["strain"][k] = eps
        out["rphase"][k] = rp
        out["resistance_ohm"][k] = resist(xi, temp, eps, rp)
    pos = w.length_mm * out["strain"]
    v_true = current_a * out["resistance_ohm"]
    if noise is None:
        out.update(current_meas_a=current_a.astype(float), voltage_v=v_true, position_mm=pos)
        return out
    cur_meas = current_a * (1.0 + noise.current_gain) + rng.normal(0.0, noise.current_noise_a, n)
    v = v_true + rng.normal(0.0, noise.white_v, n) + _pink(rng, n, noise.pink_v)
    spikes = rng.random(n) < noise.spike_rate
    v[spikes] += rng.choice([-1.0, 1.0], spikes.sum()) * rng.uniform(*noise.spike_v, spikes.sum())
    top = math.floor(noise.full_scale_v / noise.lsb_v)
    v = np.clip(np.round(v / noise.lsb_v), -top, top - 1) * noise.lsb_v
    laser = pos + rng.normal(0.0, noise.laser_noise_mm, n)
    laser = np.round(laser / noise.laser_step_mm) * noise.laser_step_mm
    out.update(current_meas_a=cur_meas, voltage_v=v, position_mm=laser)
    return out


def cycles_of(current_a: np.ndarray, level_a: float) -> np.ndarray:
    """Cycle index per sample: a cycle starts with each heating."""
    heat = current_a > level_a
    starts = np.r_[heat[:1], heat[1:] & ~heat[:-1]]
    return np.maximum(np.cumsum(starts) - 1, 0)


def write(folder: Path, w: ApartWire, load_kg: float, t: np.ndarray, current_set_a: np.ndarray,
          sim: dict[str, np.ndarray]) -> Path:  # fmt: skip
    """The session in smabench's format, written by smabench's writer."""
    from smabench.sessions import write_session

    n = len(t)
    data = {
        "t_s": t, "current_set_A": current_set_a, "current_A": sim["current_meas_a"],
        "voltage_V": sim["voltage_v"], "ambient_C": np.full(n, w.ambient_c),
        "position_mm": sim["position_mm"],
        "mode": np.array(["open_loop"] * n, dtype=object),
        "cycle": cycles_of(current_set_a, 0.5 * (w.heat_a + w.probe_a)),
        "flags": np.zeros(n, dtype=int),
    }  # fmt: skip
    meta = {
        "kind": "simulated", "load_kg": load_kg, "source": "tests/selfsense_sim_apart.py",
        "wire": {"length_mm": w.length_mm, "diameter_mm": w.diameter_mm},
        "status": "completed", "end_reason": "protocol completed",
    }  # fmt: skip
    return write_session(folder, meta, data)


__all__ = ["ApartWire", "Noise", "cycles_of", "profile", "replace", "simulate", "write"]
