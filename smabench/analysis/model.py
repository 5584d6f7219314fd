"""Compact physical model of an SMA wire session for the discrepancy analysis (pure numpy).

Baseline ("our simulation"): the heat balance eq. (16) with exact zero-order-hold steps on a
uniform grid (current-driven sessions; thermometer loops use the measured temperature), a
Liang–Rogers cosine hysteresis for the martensite fraction ξ with return-point memory (the loop
model's adaptation rules: an incomplete cycle or an inner loop continues from the last reversal
point, scaled branches), a first-order lag of the forward (cooling, nucleation-limited)
transformation, and the length ``L0·((ε_L + σ·ΔC)·ξ + α·(T - 22 °C))`` plus a sensor zero.
With several loads the thermal hysteresis narrows with stress (paper Fig. 11 trend).

Candidate extensions (each its own parameters, 0 = off), in SI-like units inside:

- ``phase_resistance``: R = R_mean·(1 + β·(0.5 - ξ)) in the heat balance (β relative).
- ``latent_heat``: T += λ·Δξ per step (λ = L/cp, K per unit ξ).
- ``stress_shift``: all transformation temperatures move by s·(σ - σ_ref) (s = 1/slope, K/MPa).
- ``convection_nonlinear``: h = h0·(1 + k·(T - T_room)).
- ``sensor_lag``: first-order lag of the position reading, τ s.
- ``ambient_drift``: T_room = recorded ambient + d·t (K/h), unmeasured.
- ``cycle_drift``: residual strain r·n_sat·(1 - exp(-N/n_sat)), N = transformation cycles
  counted as Σ|Δξ|/2 (r strain per cycle, n_sat the saturation constant in cycles).

The coupled effects (phase_resistance, latent_heat, convection_nonlinear) make the heat balance
depend on ξ or T itself: they run a sequential loop of plain floats for the temperature; all
else is vectorised (``scipy.signal.lfilter``, one numpy expression per hysteresis run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

RHO_KG_M3 = 6450.0
CP_J_KGK = 837.0
RESISTIVITY_MEAN_OHM_M = 90e-8
E_AUSTENITE_MPA = 75e3
E_MARTENSITE_MPA = 30e3
DCOMPLIANCE_PER_MPA = 1.0 / E_MARTENSITE_MPA - 1.0 / E_AUSTENITE_MPA
T_REF_C = 22.0
G_M_S2 = 9.80665
_EPS_T = 1e-9

CANDIDATES = (
    "phase_resistance",
    "latent_heat",
    "stress_shift",
    "convection_nonlinear",
    "sensor_lag",
    "ambient_drift",
    "cycle_drift",
)
COUPLED = frozenset({"phase_resistance", "latent_heat", "convection_nonlinear"})


@dataclass
class Grid:
    """One session on a uniform time grid (or its own samples for thermometer loops).

    ``i2[n]`` is the mean of I² over [t[n], t[n+1]) (exact energy of the zero-order hold);
    ``amb[n]`` the recorded ambient there; ``temp`` the measured temperature (thermometer loops).
    """

    name: str
    kind: str  # "current" or "thermo"
    t: np.ndarray
    dt: float
    i2: np.ndarray | None
    amb: np.ndarray | None
    temp: np.ndarray | None
    stress_mpa: float
    length_mm: float
    heat_capacity_j_k: float
    resistance_ohm: float


@dataclass
class ModelSpec:
    """Which parameters are free and their bounds; values of the fixed ones."""

    names: list[str]
    x0: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    fixed: dict[str, float] = field(default_factory=dict)

    def values(self, x: np.ndarray) -> dict[str, float]:
        out = dict(self.fixed)
        out.update(zip(self.names, (float(v) for v in x), strict=True))
        return out


# --------------------------------------------------------------------------- helpers
def uniform_filter(a: float, u: np.ndarray, x0: float) -> np.ndarray:
    """x[0] = x0, x[n+1] = a·x[n] + u[n]; returns len(u) + 1 values (lfilter)."""
    out = np.empty(len(u) + 1)
    out[0] = x0
    if len(u):
        out[1:] = lfilter([1.0], [1.0, -a], u, zi=[a * x0])[0]
    return out


def lag_foh(u: np.ndarray, dt: float, tau: float, x0: float) -> np.ndarray:
    """First-order lag x' = (u - x)/τ, exact for ``u`` linear between samples (first-order
    hold, accurate on coarse grids); x[0] = x0, returns len(u) values."""
    out = np.empty(len(u))
    out[0] = x0
    if len(u) < 2:
        return out
    if tau <= 1e-6:
        out[1:] = u[1:]
        return out
    b = math.exp(-dt / tau)
    c1 = 1.0 - tau * (1.0 - b) / dt
    c0 = (1.0 - b) - c1
    out[1:] = lfilter([c1, c0], [1.0, -b], u[1:], zi=[b * x0 + c0 * u[0]])[0]
    return out


def first_order_lag(x: np.ndarray, dt: float, tau: float) -> np.ndarray:
    """First-order lag of a sampled signal starting at its first value (τ ≤ 0: unchanged)."""
    if tau <= 1e-6 or len(x) < 2:
        return x
    return lag_foh(x, dt, tau, float(x[0]))


def directions(temp: np.ndarray) -> np.ndarray:
    """Direction of each step (len n-1): +1 heating, -1 cooling, tiny moves keep the last sign."""
    d = np.diff(temp)
    s = np.where(d > _EPS_T, 1, np.where(d < -_EPS_T, -1, 0)).astype(np.int8)
    idx = np.where(s != 0, np.arange(len(s)), 0)
    np.maximum.accumulate(idx, out=idx)
    return s[idx]


def runs(direction: np.ndarray) -> list[tuple[int, int, int]]:
    """Maximal runs of equal direction → (start, end, value); the plant's own helper."""
    from smabench.physics.plant import _runs

    return _runs(direction)


def cosine_down(temp, lo: float, hi: float):
    """1 below ``lo``, 0 above ``hi``, half-cosine between."""
    x = np.clip((temp - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


class Temps:
    """Transformation temperatures of one session (°C) from the parameters and its stress."""

    def __init__(self, p: dict[str, float], stress_mpa: float) -> None:
        ds = stress_mpa - p.get("sigma_ref", stress_mpa)
        shift = p.get("ss_k_per_mpa", 0.0) * ds
        half_shrink = 0.5 * p.get("shrink_k_per_mpa", 0.0) * ds
        hm = p["h_mid"] - half_shrink + shift
        cm = p["c_mid"] + half_shrink + shift
        self.as_c, self.af_c = hm - 0.5 * p["h_w"], hm + 0.5 * p["h_w"]
        self.mf_c, self.ms_c = cm - 0.5 * p["c_w"], cm + 0.5 * p["c_w"]

    def heat(self, temp):
        return cosine_down(temp, self.as_c, self.af_c)

    def cool(self, temp):
        return cosine_down(temp, self.mf_c, self.ms_c)


# --------------------------------------------------------------------------- temperature
def temperature(g: Grid, p: dict[str, float]) -> np.ndarray:
    """Wire temperature on the grid, °C (measured for thermometer loops)."""
    if g.kind == "thermo":
        return g.temp
    tau = p["tau_s"]
    conductance = g.heat_capacity_j_k / tau
    k_a2 = g.resistance_ohm / conductance  # K per A²
    n = len(g.t)
    amb = g.amb
    drift = p.get("drift_k_h", 0.0)
    if drift:
        amb = amb + drift / 3600.0 * (g.t - g.t[0])
    if not (p.get("beta") or p.get("lat_k") or p.get("conv_k")):
        a = math.exp(-g.dt / tau)
        t_inf = amb[:-1] + k_a2 * g.i2
        return uniform_filter(a, (1.0 - a) * t_inf, float(amb[0]))[:n]
    return _temperature_coupled(g, p, amb, k_a2)


def _temperature_coupled(g: Grid, p: dict[str, float], amb: np.ndarray, k_a2: float):
    """Sequential heat balance with ξ- or T-dependent terms (plain floats).

    The same discrete equations as the plant's ``Plant.step``; per step only what changes is
    computed: the reference of the scaled branch at each reversal, the cosine inside the
    transformation band only, the exponential only when convection makes it T-dependent."""
    tt = Temps(p, g.stress_mpa)
    as_c, af_c, mf_c, ms_c = tt.as_c, tt.af_c, tt.mf_c, tt.ms_c
    wh = max(af_c - as_c, 1e-6)
    wc = max(ms_c - mf_c, 1e-6)
    beta = p.get("beta", 0.0)
    lat = p.get("lat_k", 0.0)
    conv = p.get("conv_k", 0.0)
    tau_c = p.get("tau_cool_s", 0.0)
    bc = math.exp(-g.dt / tau_c) if tau_c > 1e-6 else 0.0
    tau_h = p.get("tau_heat_s", 0.0)
    bh = math.exp(-g.dt / tau_h) if tau_h > 1e-6 else 0.0
    rate = g.dt / p["tau_s"]
    a_const = math.exp(-rate)
    cos, pi, exp = math.cos, math.pi, math.exp
    ph, pc = pi / wh, pi / wc
    heat_in = (k_a2 * g.i2).tolist()
    ambl = amb.tolist()
    n = len(g.t)
    out = [0.0] * n
    temp = ambl[0]
    out[0] = temp
    xi = xi_eq = xi_r = 1.0
    ref = 1.0
    direction = 0
    eps = _EPS_T
    for k in range(n - 1):
        ta = ambl[k]
        q = heat_in[k]
        if beta:
            q *= 1.0 + beta * (0.5 - xi)
        if conv:
            gf = 1.0 + conv * (temp - ta)
            if gf < 0.05:
                gf = 0.05
            t_inf = ta + q / gf
            new = t_inf + (temp - t_inf) * exp(-rate * gf)
        else:
            t_inf = ta + q
            new = t_inf + (temp - t_inf) * a_const
        d = new - temp
        dn = 1 if d > eps else (-1 if d < -eps else direction)
        if dn != direction:
            xi_r, direction = xi_eq, dn
            if dn > 0:  # ξ_h at the reversal
                x = (temp - as_c) / wh
                ref = 1.0 if x <= 0.0 else (0.0 if x >= 1.0 else 0.5 * (1.0 + cos(pi * x)))
                ref = xi_r / max(ref, 1e-12)
            else:  # 1 - ξ_c at the reversal
                x = (temp - mf_c) / wc
                ref = 0.0 if x <= 0.0 else (1.0 if x >= 1.0 else 0.5 * (1.0 - cos(pi * x)))
                ref = (1.0 - xi_r) / max(ref, 1e-12)
        if dn > 0:
            if new <= as_c:
                gt = 1.0
            elif new >= af_c:
                gt = 0.0
            else:
                gt = 0.5 * (1.0 + cos(ph * (new - as_c)))
            xi_eq = ref * gt
            if xi_eq > xi_r:
                xi_eq = xi_r
            xi_new = bh * xi + (1.0 - bh) * xi_eq
        elif dn < 0:
            if new <= mf_c:
                gt = 0.0
            elif new >= ms_c:
                gt = 1.0
            else:
                gt = 0.5 * (1.0 - cos(pc * (new - mf_c)))  # 1 - ξ_c
            xi_eq = 1.0 - ref * gt
            if xi_eq < xi_r:
                xi_eq = xi_r
            xi_new = bc * xi + (1.0 - bc) * xi_eq
        else:
            xi_new = xi
        if lat:
            new += lat * (xi_new - xi)
        xi = xi_new
        temp = new
        out[k + 1] = new
    return np.asarray(out)


# --------------------------------------------------------------------------- hysteresis
def martensite_fraction(
    temp: np.ndarray, tt: Temps, dt: float, tau_heat: float, tau_cool: float
) -> np.ndarray:
    """ξ along a temperature history: scaled branches from the last reversal (return-point
    memory), first-order lags τ_heat / τ_cool behind the equilibrium on each branch."""
    n = len(temp)
    xi_eq = np.empty(n)
    xi_eq[0] = 1.0
    rr = runs(directions(temp))
    for s, e, d in rr:
        seg = temp[s + 1 : e + 1]
        t_r, xi_r = float(temp[s]), float(xi_eq[s])
        if d > 0:
            ref = max(float(tt.heat(t_r)), 1e-12)
            xi_eq[s + 1 : e + 1] = np.clip(xi_r * tt.heat(seg) / ref, 0.0, xi_r)
        elif d < 0:
            ref = max(1.0 - float(tt.cool(t_r)), 1e-12)
            up = 1.0 - (1.0 - xi_r) * (1.0 - tt.cool(seg)) / ref
            xi_eq[s + 1 : e + 1] = np.clip(up, xi_r, 1.0)
        else:
            xi_eq[s + 1 : e + 1] = xi_r
    if tau_cool <= 1e-6 and tau_heat <= 1e-6:
        return xi_eq
    xi = xi_eq.copy()
    for s, e, d in rr:
        tau = tau_heat if d > 0 else tau_cool
        xi[s : e + 1] = lag_foh(xi_eq[s : e + 1], dt, tau, float(xi[s]))
    return xi


# --------------------------------------------------------------------------- whole model
@dataclass
class Simulated:
    temp: np.ndarray
    xi: np.ndarray
    basis: np.ndarray  # columns: ξ·L0 (strain units → mm), (T - 22)·L0; before the sensor lag
    fixed: np.ndarray  # known part: elastic ξ term + residual strain, mm


def simulate(g: Grid, p: dict[str, float]) -> Simulated:
    """Run the model on one grid; position = offset + ε_L·basis0 + α·basis1 + fixed (lagged)."""
    temp = temperature(g, p)
    tt = Temps(p, g.stress_mpa)
    cur = g.kind == "current"
    tau_h = p.get("tau_heat_s", 0.0) if cur else 0.0
    tau_c = p.get("tau_cool_s", 0.0) if cur else 0.0
    xi = martensite_fraction(temp, tt, g.dt, tau_h, tau_c)
    l0 = g.length_mm
    fixed = l0 * g.stress_mpa * DCOMPLIANCE_PER_MPA * xi
    rate = p.get("cyc_rate", 0.0)
    if rate:
        n_cyc = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(xi))) * 0.5))
        n_sat = p.get("cyc_nsat", 1e3)
        fixed = fixed + l0 * rate * n_sat * (1.0 - np.exp(-n_cyc / n_sat))
    basis = np.column_stack((l0 * xi, l0 * (temp - T_REF_C)))
    lag = p.get("lag_s", 0.0)
    if lag > 1e-6:
        basis = np.column_stack([first_order_lag(basis[:, j], g.dt, lag) for j in range(2)])
        fixed = first_order_lag(fixed, g.dt, lag)
    return Simulated(temp, xi, basis, fixed)
