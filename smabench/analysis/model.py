"""Compact physical model of an SMA wire session for the discrepancy analysis.

Baseline ("our simulation"): the heat balance eq. (16) with exact zero-order-hold steps on a
uniform grid (current-driven sessions; thermometer loops use the measured temperature); the
martensite fraction ξ on major branches between the transformation temperatures, each a blend
of the Liang–Rogers half-cosine and a logistic of the same centre and mid slope (``h_shape``,
``c_shape``: 0 cosine … 1 logistic, the erf-like branches of a Preisach distribution); from the
last reversal the loop model's adaptation rule (``memory`` 0: the major branch scaled through
the reversal point, the paper's moving common point; 1: ξ held until the major branch returns,
a Preisach model's wiping-out; between: a blend); first-order lags of ξ behind its equilibrium
on each branch (``tau_cool_s``, the nucleation-limited forward transformation, and
``tau_heat_s`` = ``heat_lag_ratio``·τ_cool ≤ τ_cool/2: the reverse transformation needs no
nucleation, so equal lags on both branches are a sensor's, not the wire's); rate-dependent
transformation temperatures (``rate_shift_k``: each branch starts at As + k·√|dT/dt| on heating,
Ms − k·√|dT/dt| on cooling, later the faster the temperature moves, as thermally activated
nucleation takes time; once started it follows the temperature, its shift held at the value it
started with; a first-order lag alone moves the branches in proportion to the rate); the length
``L0·((ε_L + ε_σ·(σ - σ_ref) + σ·ΔC)·ξ + ε_mix·ξ(1-ξ) + α·(T - 22 °C))`` plus a sensor zero,
with ε_L, ε_σ (``eps_l_per_mpa``: the stroke grows with stress, detwinning), ε_mix, α and the
zero solved linearly. With several loads the thermal hysteresis narrows
with stress (paper Fig. 11 trend).

Candidate extensions (each its own parameters, 0 = off), in SI-like units inside:

- ``phase_resistance``: R = R_mean·(1 + β·(0.5 - ξ)) in the heat balance (β relative).
- ``latent_heat``: T += λ·Δξ per step (λ = L/cp, K per unit ξ).
- ``stress_shift``: all transformation temperatures move by s·(σ - σ_ref) (s = 1/slope, K/MPa).
- ``convection_nonlinear``: h = h0·(1 + k·(T - T_room)).
- ``sensor_lag``: the position reading lags: a first-order lag τ (s, a filter) followed by a
  dead time d (s, transport and buffering); reported as their sum, the mean delay τ + d.
- ``ambient_drift``: T_room = recorded ambient + d·t (K/h), unmeasured.
- ``cycle_drift``: residual strain whose rate per cycle falls as r/(1 + N/n0)^q (linear,
  logarithmic or saturating: :func:`residual_strain`), N = transformation cycles counted as
  Σ|Δξ|/2 (r strain per cycle at the first cycle).

Temperature and ξ come from sequential passes over the grid compiled with numba (one coupled pass
when phase_resistance, latent_heat or convection_nonlinear make the heat balance depend on ξ or T
itself); the length is vectorised, the sensor lag a compiled first-order filter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from smabench.analysis.candidates import DCOMPLIANCE_PER_MPA

T_REF_C = 22.0
_EPS_T = 1e-9
LOGISTIC_K = 2.0 * math.pi
"""Logistic branch steepness per unit window: the same slope at the centre as the cosine."""
LN2 = math.log(2.0)

LINEAR = ("eps_l", "alpha_per_k", "eps_mix", "eps_l_per_mpa")
"""Coefficients of the basis columns, solved by linear least squares inside every fit:
ξ (the transformation strain at the reference stress), T − 22 °C (thermal expansion),
ξ·(1 − ξ) (a bent ξ → length map) and ξ·(σ − σ_ref) (the transformation strain grows with
stress: detwinning and the elastic part together; a single load leaves it 0)."""


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

    def head(self, n: int) -> Grid:
        """The first ``n`` grid points (the model is causal: the same values there)."""
        if n >= len(self.t):
            return self

        def cut(a: np.ndarray | None, k: int) -> np.ndarray | None:
            return None if a is None else a[:k]

        return replace(self, t=self.t[:n], i2=cut(self.i2, n - 1), amb=cut(self.amb, n),
                       temp=cut(self.temp, n))  # fmt: skip


# --------------------------------------------------------------------------- helpers
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
    _foh_filter(u, b * x0 + c0 * u[0], b, c1, c0, out)
    return out


@numba.njit(cache=True, error_model="numpy")
def _foh_filter(u, zi, b, c1, c0, out):  # fmt: skip
    """``out[1:] = lfilter([c1, c0], [1, -b], u[1:], zi=[zi])[0]``, the same operations in the
    same order as scipy's direct form II transposed (bit for bit, checked on 2000 random
    series), without its per-call overhead (a sensor-lag fit filters four series per
    evaluation)."""
    z = zi
    for n in range(1, len(u)):
        y = z + c1 * u[n]
        z = u[n] * c0 - y * (-b)
        out[n] = y


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


class Temps:
    """Transformation temperatures of one session (°C) from the parameters and its stress."""

    def __init__(self, p: dict[str, float], stress_mpa: float) -> None:
        ds = stress_mpa - p.get("sigma_ref", stress_mpa)
        shift = p.get("ss_k_per_mpa", 0.0) * ds
        half_shrink = 0.5 * p.get("shrink_k_per_mpa", 0.0) * ds
        gap = p["hyst_k"] if "hyst_k" in p else p["h_mid"] - p["c_mid"]
        # the loop's direction: heating centre above the cooling one, whatever the stress
        half_shrink = min(half_shrink, 0.45 * gap) if gap > 0 else 0.0
        hm = p["h_mid"] - half_shrink + shift
        cm = p["h_mid"] - gap + half_shrink + shift
        self.as_c, self.af_c = hm - 0.5 * p["h_w"], hm + 0.5 * p["h_w"]
        self.mf_c, self.ms_c = cm - 0.5 * p["c_w"], cm + 0.5 * p["c_w"]
        self.h_shape = p.get("h_shape", 0.0)
        self.c_shape = p.get("c_shape", 0.0)


# --------------------------------------------------------------------------- wire state
def _foh(dt: float, tau: float) -> tuple[float, float, float]:
    """(b, c1, c0) of the first-order lag x[n+1] = b·x[n] + c1·u[n+1] + c0·u[n], exact for
    ``u`` linear between grid points (accurate on coarse grids); τ ≤ 1 µs: x = u."""
    if tau <= 1e-6:
        return 0.0, 1.0, 0.0
    b = math.exp(-dt / tau)
    c1 = 1.0 - tau * (1.0 - b) / dt
    return b, c1, (1.0 - b) - c1


def wire_state(g: Grid, p: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Temperature (°C) and martensite fraction ξ on the grid.

    Current-driven grids: the heat balance (exact zero-order-hold steps) from the recorded
    ambient (plus ``drift_k_h``) with the coupled terms of the candidates; thermometer loops:
    the measured temperature. ξ: scaled branches from the last reversal (return-point memory),
    seen at T ∓ ``rate_shift_k``·√|dT/dt| (current-driven grids), first-order lags τ_heat /
    τ_cool behind the equilibrium on each branch."""
    tt = Temps(p, g.stress_mpa)
    thermo = g.kind == "thermo"
    if thermo:
        temp_in, heat_k, amb, rate = np.ascontiguousarray(g.temp, dtype=float), _NONE, _NONE, 0.0
        tau_h = tau_c = shift_k = 0.0
    else:
        k_a2 = g.resistance_ohm * p["tau_s"] / g.heat_capacity_j_k  # K per A²
        amb = g.amb
        drift = p.get("drift_k_h", 0.0)
        if drift:
            amb = amb + drift / 3600.0 * (g.t - g.t[0])
        temp_in, heat_k, rate = _NONE, k_a2 * g.i2, g.dt / p["tau_s"]
        amb = np.ascontiguousarray(amb, dtype=float)
        tau_c = p.get("tau_cool_s", 0.0)
        tau_h = p["tau_heat_s"] if "tau_heat_s" in p else p.get("heat_lag_ratio", 0.0) * tau_c
        shift_k = p.get("rate_shift_k", 0.0) / math.sqrt(g.dt)  # K per √(K per step)
    beta, lat, conv = p.get("beta", 0.0), p.get("lat_k", 0.0), p.get("conv_k", 0.0)
    # the temperature does not depend on ξ (no phase resistance, no latent heat): three short
    # passes give the same numbers as the one coupled pass in about half the time
    kernel = _wire_kernel if (beta or lat) and not thermo else _wire_kernel_uncoupled
    return kernel(
        thermo, temp_in, heat_k, amb, rate, beta, lat, conv, shift_k,
        *_foh(g.dt, tau_h), *_foh(g.dt, tau_c),
        tt.as_c, tt.af_c, tt.h_shape, tt.mf_c, tt.ms_c, tt.c_shape, p.get("memory", 0.0),
    )  # fmt: skip


_NONE = np.zeros(0)


@numba.njit(cache=True, inline="always", error_model="numpy")
def _branch(t: float, lo: float, hi: float, shape: float, sign: float) -> float:
    """Major branch falling from 1 to 0 across [lo, hi] (sign +1, heating; sign -1, cooling:
    its complement is returned), all of the same centre and mid slope:

    - ``shape`` 0: the compact Liang–Rogers half-cosine;
    - ``shape`` 0 … 1: blended with a logistic whose tails reach beyond [lo, hi] (the erf-like
      branches of a Preisach distribution of switching temperatures);
    - ``shape`` 0 … -1: blended with Tanaka's exponential law, which starts sharply where the
      transformation starts (low end on heating, high end on cooling) and ends in a long tail.
    """
    w = max(hi - lo, 1e-6)
    if t <= lo:
        v = 1.0
    elif t >= hi:
        v = 0.0
    else:
        v = 0.5 * (1.0 + math.cos(math.pi * (t - lo) / w))
    if shape > 0.0:
        z = LOGISTIC_K * (t - 0.5 * (lo + hi)) / w
        z = min(max(z, -60.0), 60.0)
        v = (1.0 - shape) * v + shape / (1.0 + math.exp(z))
    elif shape < 0.0:
        a = math.pi / w  # the cosine's mid slope is a/2
        mid = 0.5 * (lo + hi)
        if sign > 0:  # heating: ξ = exp(-a(T - T0)) above T0 = mid - ln2/a
            x = a * (t - mid) + LN2
            e = 1.0 if x <= 0.0 else math.exp(-x)
        else:  # cooling: 1 - ξ = exp(-a(T1 - T)) below T1 = mid + ln2/a
            x = a * (mid - t) + LN2
            e = 0.0 if x <= 0.0 else 1.0 - math.exp(-x)
        v = (1.0 + shape) * v - shape * e
    return v if sign > 0 else 1.0 - v


XI_MOVED = 1e-3
"""A branch has started (its rate shift is held from there) once it has moved this much."""


@numba.njit(inline="always", error_model="numpy")
def _rate_shift(dn, new, d, shift_k, frozen, as_c, af_c, sh, mf_c, ms_c, sc):
    """(shift, frozen) of one step: the branch is read at T - shift. Until the branch has
    started (moved by XI_MOVED: nucleated) the shift follows the rate, ``shift_k``·√|ΔT| (K per
    √K of one step's change); from there it stays at its value then: once nucleated, the
    transformation follows the temperature whatever the rate does. ``frozen`` < 0: not started
    (reset at every reversal)."""
    if shift_k == 0.0 or dn == 0:
        return 0.0, frozen
    if frozen >= 0.0:
        return dn * frozen, frozen
    s = shift_k * math.sqrt(abs(d))
    m = (_branch(new - s, as_c, af_c, sh, 1.0) if dn > 0
         else _branch(new + s, mf_c, ms_c, sc, -1.0))  # fmt: skip
    if m < 1.0 - XI_MOVED:
        frozen = s
    return dn * s, frozen


XI_START = 1.0
"""ξ at the first grid point of every simulation: the wire starts cold, fully martensitic."""


@numba.njit(inline="always", error_model="numpy")
def _reversal_ref(xi_r, dn, t, as_c, af_c, sh, mf_c, ms_c, sc):
    """The scaling of the branch that starts at a reversal (T = ``t``, ξ = ``xi_r``) in
    direction ``dn`` (the paper's moving common point)."""
    if dn > 0:
        return xi_r / max(_branch(t, as_c, af_c, sh, 1.0), 1e-12)
    return (1.0 - xi_r) / max(_branch(t, mf_c, ms_c, sc, -1.0), 1e-12)


@numba.njit(inline="always", error_model="numpy")
def _xi_step(dn, m, ref, xi_r, xi, xi_eq, memory, bh, c1h, c0h, bc, c1c, c0c):
    """One step of ξ: its equilibrium on the branch from the last reversal (``m`` = the major
    branch at the new temperature, ξ_h heating, 1 - ξ_c cooling; unused with no direction yet),
    blended by ``memory`` (see :func:`_wire_kernel`), and the first-order-hold lag behind it.
    Returns (ξ, ξ_eq)."""
    if dn > 0:
        eq = min((1.0 - memory) * ref * m + memory * min(m, xi_r), xi_r)
        return bh * xi + c1h * eq + c0h * xi_eq, eq
    if dn < 0:
        eq = max((1.0 - memory) * (1.0 - ref * m) + memory * max(1.0 - m, xi_r), xi_r)
        return bc * xi + c1c * eq + c0c * xi_eq, eq
    return bc * xi + c1c * xi_eq + c0c * xi_eq, xi_eq


@numba.njit(cache=True, error_model="numpy")
def _wire_kernel(thermo, temp_in, heat_k, amb, rate, beta, lat, conv, shift_k,
                 bh, c1h, c0h, bc, c1c, c0c, as_c, af_c, sh, mf_c, ms_c, sc, memory):  # fmt: skip
    """One pass over the grid (the same discrete equations as the plant's ``Plant.step``).

    ``heat_k[n]`` = R·I²/conductance (K) over step n, ``rate`` = dt/τ; the heat input scales
    with 1 + β(0.5 - ξ), the conductance with 1 + k(T - T_a); latent heat adds λ·Δξ. A new
    direction of T (moves below 1e-9 K keep the last one) starts a scaled branch at the
    reversal; the branches are read at T - dn·shift (:func:`_rate_shift`: transformation
    temperatures that move with the rate until the branch starts); ξ lags its
    equilibrium value by (b, c1, c0) per branch (see :func:`_foh`).
    ``memory`` blends the branch from a reversal (T_r, ξ_r): 0 scales the major branch through
    the reversal point (the paper's moving common point; Liang–Rogers, Brinson), 1 holds ξ_r
    until the major branch comes back to it (a Preisach model's wiping-out memory)."""
    n = len(temp_in) if thermo else len(amb)
    temp_out = np.empty(n)
    xi_out = np.empty(n)
    temp = temp_in[0] if thermo else amb[0]
    temp_out[0] = temp
    xi = xi_eq = xi_r = xi_out[0] = XI_START
    ref = 1.0  # the major branch unscaled until the first reversal
    direction = 0
    frozen = -1.0
    a_const = math.exp(-rate)
    for k in range(n - 1):
        if thermo:
            new = temp_in[k + 1]
        else:
            ta = amb[k]
            q = heat_k[k]
            if beta != 0.0:
                q *= 1.0 + beta * (0.5 - xi)
            if conv != 0.0:
                gf = max(1.0 + conv * (temp - ta), 0.05)
                t_inf = ta + q / gf
                new = t_inf + (temp - t_inf) * math.exp(-rate * gf)
            else:
                t_inf = ta + q
                new = t_inf + (temp - t_inf) * a_const
        d = new - temp
        dn = 1 if d > _EPS_T else (-1 if d < -_EPS_T else direction)
        if dn != direction:
            frozen = -1.0
        shift, frozen = _rate_shift(dn, new, d, shift_k, frozen, as_c, af_c, sh, mf_c, ms_c, sc)
        if dn != direction:  # a reversal: the scaled branch starts here
            xi_r = xi_eq
            direction = dn
            ref = _reversal_ref(xi_r, dn, temp - shift, as_c, af_c, sh, mf_c, ms_c, sc)
        if dn > 0:
            major = _branch(new - shift, as_c, af_c, sh, 1.0)
        elif dn < 0:
            major = _branch(new - shift, mf_c, ms_c, sc, -1.0)  # 1 - ξ_c
        else:
            major = 0.0
        xi_new, xi_eq = _xi_step(dn, major, ref, xi_r, xi, xi_eq, memory,
                                 bh, c1h, c0h, bc, c1c, c0c)  # fmt: skip
        if lat != 0.0 and not thermo:
            new += lat * (xi_new - xi)
        xi = xi_new
        temp = new
        temp_out[k + 1] = new
        xi_out[k + 1] = xi
    return temp_out, xi_out


@numba.njit(cache=True, error_model="numpy")
def _wire_kernel_uncoupled(thermo, temp_in, heat_k, amb, rate, beta, lat, conv, shift_k,
                           bh, c1h, c0h, bc, c1c, c0c, as_c, af_c, sh, mf_c, ms_c, sc,
                           memory):  # fmt: skip
    """:func:`_wire_kernel` where the temperature does not depend on ξ (``beta``, ``lat`` unused,
    taken as 0; ``conv`` acts on T alone): the same discrete equations and the same numbers, in
    three passes: the temperature and its directions; the major branch at every step (the
    exp/cos of :func:`_branch` in a tight loop of their own, not in the long recurrence where
    every call spills its many live values); then ξ's recurrence from those."""
    n = len(temp_in) if thermo else len(amb)
    temp_out = np.empty(n)
    xi_out = np.empty(n)
    dirs = np.zeros(n, dtype=np.int8)
    major = np.zeros(n)
    t_rev = np.empty(n)  # T - shift at step k, seen from the step k → k+1 (a reversal's point)
    t_br = np.empty(n)  # T - shift at step k, seen from the step k-1 → k (the branch's)
    temp = temp_in[0] if thermo else amb[0]
    temp_out[0] = temp
    a_const = math.exp(-rate)
    direction = 0
    frozen = -1.0
    for k in range(n - 1):
        if thermo:
            new = temp_in[k + 1]
        elif conv != 0.0:  # the conductance follows T, not ξ: still uncoupled
            ta = amb[k]
            gf = max(1.0 + conv * (temp - ta), 0.05)
            t_inf = ta + heat_k[k] / gf
            new = t_inf + (temp - t_inf) * math.exp(-rate * gf)
        else:
            t_inf = amb[k] + heat_k[k]
            new = t_inf + (temp - t_inf) * a_const
        d = new - temp
        dn = 1 if d > _EPS_T else (-1 if d < -_EPS_T else direction)
        if dn != direction:
            frozen = -1.0
        direction = dn
        dirs[k + 1] = direction
        shift, frozen = _rate_shift(direction, new, d, shift_k, frozen, as_c, af_c, sh,
                                    mf_c, ms_c, sc)
        t_rev[k] = temp - shift
        t_br[k + 1] = new - shift
        temp = new
        temp_out[k + 1] = new
    for k in range(1, n):
        if dirs[k] > 0:
            major[k] = _branch(t_br[k], as_c, af_c, sh, 1.0)
        elif dirs[k] < 0:
            major[k] = _branch(t_br[k], mf_c, ms_c, sc, -1.0)
    xi = xi_eq = xi_r = xi_out[0] = XI_START
    ref = 1.0  # the major branch unscaled until the first reversal
    direction = 0
    for k in range(n - 1):
        dn = dirs[k + 1]
        if dn != direction:  # a reversal: the scaled branch starts here
            xi_r = xi_eq
            direction = dn
            ref = _reversal_ref(xi_r, dn, t_rev[k], as_c, af_c, sh, mf_c, ms_c, sc)
        xi, xi_eq = _xi_step(dn, major[k + 1], ref, xi_r, xi, xi_eq, memory,
                             bh, c1h, c0h, bc, c1c, c0c)  # fmt: skip
        xi_out[k + 1] = xi
    return temp_out, xi_out


def temperature(g: Grid, p: dict[str, float]) -> np.ndarray:
    """Wire temperature on the grid, °C (measured for thermometer loops)."""
    return wire_state(g, p)[0]


# --------------------------------------------------------------------------- whole model
@dataclass
class Simulated:
    temp: np.ndarray
    xi: np.ndarray
    basis: np.ndarray  # columns (× L0, mm per unit of LINEAR): ξ, T - 22 °C, ξ·(1 - ξ),
    # ξ·(σ - σ_ref)
    fixed: np.ndarray  # known part: elastic ξ term + residual strain, mm


POST_WIRE = frozenset(("xi_delay_s", "cyc_rate", "cyc_n0", "cyc_q", "lag_s", "delay_s"))
"""Parameters that act after the wire's temperature and ξ (:func:`wire_state` reads none)."""


def wire_key(p: dict[str, float]) -> tuple:
    """What :func:`wire_state` depends on in ``p`` (for one grid): equal keys, equal states."""
    return tuple(sorted((k, v) for k, v in p.items() if k not in POST_WIRE))


def simulate(
    g: Grid,
    p: dict[str, float],
    state: tuple[np.ndarray, np.ndarray] | None = None,
    at: np.ndarray | None = None,
) -> Simulated:
    """Run the model on one grid; position = offset + basis @ (ε_L, α, ε_mix) + fixed, all
    behind the sensor lag. ε_mix bends the ξ → length map: a modulus mixed by volume (Voigt,
    as in Brinson's model) instead of compliance (Reuss), or a strain that is not linear in ξ.
    ``state``: :func:`wire_state` of ``g`` and ``p`` when already known (not modified);
    ``at``: grid indices where ``basis`` and ``fixed`` are wanted (None: everywhere; the same
    values as the whole grid's at these points)."""
    temp, xi = wire_state(g, p) if state is None else state
    xi_delay = p.get("xi_delay_s", 0.0)
    if xi_delay > 1e-6:  # the transformation late, the thermal expansion not (kinetic rival)
        xi = dead_time(xi, g.t, xi_delay)
    temp_all, xi_all = temp, xi
    lag = p.get("lag_s", 0.0)
    delay = p.get("delay_s", 0.0)
    rate = p.get("cyc_rate", 0.0)
    pick = at is not None and lag <= 1e-6 and delay <= 1e-6  # pointwise from here on
    if rate:
        n_cyc = np.concatenate(([0.0], np.cumsum(np.abs(np.diff(xi))) * 0.5))
        if pick:
            n_cyc = n_cyc[at]
    if pick:
        xi, temp = xi[at], temp[at]
    l0 = g.length_mm
    fixed = l0 * g.stress_mpa * DCOMPLIANCE_PER_MPA * xi
    if rate:
        fixed = fixed + l0 * residual_strain(n_cyc, rate, p.get("cyc_n0", 1e3),
                                             p.get("cyc_q", 1.0))  # fmt: skip
    ds = g.stress_mpa - p.get("sigma_ref", g.stress_mpa)
    basis = np.column_stack((l0 * xi, l0 * (temp - T_REF_C), l0 * xi * (1.0 - xi),
                             l0 * ds * xi))  # fmt: skip
    if lag > 1e-6:
        basis = np.column_stack(
            [first_order_lag(basis[:, j], g.dt, lag) for j in range(basis.shape[1])]
        )
        fixed = first_order_lag(fixed, g.dt, lag)
    if delay > 1e-6:  # read late: interpolated only where wanted (pointwise, the same values)
        t_read = g.t - delay if at is None else g.t[at] - delay
        basis = np.column_stack([np.interp(t_read, g.t, basis[:, j])
                                 for j in range(basis.shape[1])])  # fmt: skip
        fixed = np.interp(t_read, g.t, fixed)
    elif at is not None and not pick:
        basis, fixed = basis[at], fixed[at]
    return Simulated(temp_all, xi_all, basis, fixed)


def pointwise(p: dict[str, float]) -> bool:
    """True when :func:`simulate` reads the basis at the wanted points straight from the wire
    state (no dead time of ξ, no residual strain, no sensor lag or delay): then
    :func:`fill_pointwise` gives the same values."""
    return (p.get("xi_delay_s", 0.0) <= 1e-6 and not p.get("cyc_rate", 0.0)
            and p.get("lag_s", 0.0) <= 1e-6 and p.get("delay_s", 0.0) <= 1e-6)  # fmt: skip


def fill_pointwise(g: Grid, p: dict[str, float], state: tuple[np.ndarray, np.ndarray],
                   at: np.ndarray, obs: np.ndarray, basis: np.ndarray, y: np.ndarray,
                   row0: int) -> None:  # fmt: skip
    """:func:`simulate`'s basis at grid points ``at`` into ``basis[row0:]`` and ``obs`` minus
    its fixed part into ``y[row0:]``, in place, for parameters where :func:`pointwise` holds
    (the same numbers, without the temporaries: the inner loop of every fit)."""
    temp, xi = state
    k_fixed = g.length_mm * g.stress_mpa * DCOMPLIANCE_PER_MPA
    ds = g.stress_mpa - p.get("sigma_ref", g.stress_mpa)
    _fill_pointwise(temp, xi, at, g.length_mm, k_fixed, ds, obs, basis, y, row0)


@numba.njit(cache=True, error_model="numpy")
def _fill_pointwise(temp, xi, at, l0, k_fixed, ds, obs, basis, y, row0):  # fmt: skip
    for i in range(len(at)):
        x = xi[at[i]]
        basis[row0 + i, 0] = l0 * x
        basis[row0 + i, 1] = l0 * (temp[at[i]] - T_REF_C)
        basis[row0 + i, 2] = l0 * x * (1.0 - x)
        basis[row0 + i, 3] = l0 * ds * x
        y[row0 + i] = obs[i] - k_fixed * x


def residual_strain(n_cyc: np.ndarray, rate: float, n0: float, q: float) -> np.ndarray:
    """Residual strain after ``n_cyc`` transformation cycles when its rate per cycle falls as
    ``rate/(1 + N/n0)^q``: q = 0 linear, q = 1 logarithmic ``rate·n0·ln(1 + N/n0)``, q > 1
    saturating; n0 → ∞ linear whatever q. A flexible monotone shape, not one law."""
    x = n_cyc / n0
    if abs(q - 1.0) < 1e-6:
        return rate * n0 * np.log1p(x)
    return rate * n0 * (np.power(1.0 + x, 1.0 - q) - 1.0) / (1.0 - q)


def dead_time(x: np.ndarray, t: np.ndarray, delay_s: float) -> np.ndarray:
    """``x`` read ``delay_s`` late (linear interpolation; the first value before the start)."""
    return np.interp(t - delay_s, t, x)
