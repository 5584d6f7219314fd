"""The wire as its own position sensor (issue 26): the resistance → position maps, their
calibration and the online estimator, pure numpy (no session files, no CLI: those are in
:mod:`smabench.selfsense`). Units: A, V, Ω, mm, s.

Learn the resistance → position map from sessions recorded with the laser, then estimate the
position from the resistance alone (``smabench selfsense calibrate|estimate``). Units: A, V, Ω,
mm, s.

Resistance: ``R = voltage_V / current_A`` (the Kelvin wire voltage over the measured current)
where ``current_A ≥ min_current_a`` (20 mA), NaN elsewhere. For learning, a row also needs a
valid laser position: finite, and ``flags`` without
:data:`~smabench.sessions.FLAG_SENSOR_INVALID` (1 << 8) or the sensor's own invalid bits
(:data:`~smabench.sessions.FLAGS_POSITION_INVALID`, as the other session readers).

Filter: R is noisy sample to sample (the bench's ADS1115 chain, 125 µV RMS per reading: ≈ 0.09
mΩ at 1.4 A but ≈ 1.3 mΩ at a 0.1 A probe current, against ≈ 37 mΩ over the stroke), so it goes
through a causal first-order filter ``R_f += (1 − exp(−Δt/τ))·(R − R_f)``, ``τ = filter_tau_s``
(0.02 s, 4 samples at 200 Hz) while heating and ``filter_tau_cooling_s`` (0.2 s) while cooling.
Measured (figures below): cooling τ 0.05, 0.1, 0.2, 0.4 s gave held-out
major cycles 1.5, 0.9, 0.65, 0.8 % and partial loops 3.4, 3.4, 3.8, 3.9 % (3× the noise: major
5.0, 3.0, 1.7, 1.0 %, partial 6.0, 4.5, 4.3, 4.0 %): a short τ lets the noise ratchet the
estimate forward, a long one lags behind the reversals; 0.2 s balances them. Heating τ 0, 0.01,
0.02, 0.05 s: major 0.76, 0.71, 0.65, 0.60 %, partial 3.6, 3.7, 3.8, 4.4 %. The same code runs in
:meth:`SelfSenseEstimator.update`, so learning and estimation see the same lag.

Branches (hysteresis): heating while ``current_A > probe_level_a`` (0.2 A), cooling at or below
it (the firmware holds a probe current ≤ 0.1 A while the wire cools, so R stays measurable).
Each branch has its own map ``x = f_b(R)``, monotone, learned from the part of every branch run
where the transformation moves the wire: from the run's backward extreme of R (the martensite's
resistance rising with temperature before As, or the austenite's falling before Ms) to its
forward extreme (where the transformation ends); outside that part R moves with the temperature
alone while the position stays put (and with an R-phase the cooling branch's R first rises by
≈ 15 % at a constant position), so those rows would make the map many-valued.

Figures below: the plant (:mod:`smabench.physics.plant`, resistivity
:data:`~smabench.physics.resistance.FLEXINOL_RESISTIVITY`, Flexinol 0.38 mm × 55 mm under 2 kg,
1.4 A heating, 0.1 A probe, 200 Hz) through the ADS1115 chain's noise; RMS error against the laser
in % of stroke (2.67 mm), six major cycles learnt, three others estimated (tests/test_selfsense.py).

Fit: a least-squares polynomial of degree 5 in the normalised R, its degree lowered until it is
monotone on the learning range (``fit="poly"``, the default), against a monotone PCHIP through
the isotonic equal-count binned medians (``fit="pchip"``): held-out major cycles 0.63 against
0.71 % (3× the noise: 1.81 against 1.97 %; a cubic: 0.78 and 1.58 %; over three other seeds
the means are 0.69, 0.73, 0.84 % for degree 5, PCHIP, cubic, and with the R-phase preset 0.57,
0.67, 0.72 %). The degree-5 polynomial is kept; the differences are small.

Reversal rule (``reversal=True``, the default), as the loop models' scaled branches: at a branch
switch the estimate starts at the last one, ``x_r``, with the anchor ``R_r`` the R of the switch;
as R moves toward the branch's end the estimate joins the branch's map,
``x = f_b(R) + (x_r − f_b(R_r))·w``, ``w = (R_end − R)/(R_end − R_r)`` clipped to 0 … 1 (1 while
the anchor lies beyond the map's end: nothing left to transform). While R moves away from the
branch's end (the temperature alone, or the transformation still running on after the switch)
the anchor follows R, and ``x_r`` slides onto the map where the map lies further back (the major
branch bounds the state): without the slide, partial loops 5.2 % instead of 3.8 %. Within a
branch the martensite fraction moves one way only, so the estimate does too: without that
ratchet, major cycles 10.3 % (the austenite's R rising after Af reads as motion). Measured on
partial loops (heating and cooling cut short inside the transformation): with the rule 3.8 %,
the plain per-branch map ``x = f_b(R_f)`` 16.5 % (major cycles 0.6 against 18.7 %). The rule is
kept. What is left on partial loops comes from the second or so after a reversal, while the
plant's lagging transformation still moves the wire and R moves with the temperature as well.

The estimator starts as after a complete cooling (a rested wire): its first estimate is the
cooling map's end (the long, martensitic position) until R says otherwise. Without a resistance
(current below ``min_current_a``) it holds its last estimate; NaN until it has had an R.

Uncertainty: each branch's ``rms_mm`` is the RMS error of the estimator (maps and reversal rule)
on that branch's rows, every cycle estimated with maps learnt without it (cycles in at most 10
folds) when there are two cycles or more, in-sample otherwise.

Limits: a load other than the calibration's moves the elastic strain, the transformation
temperatures and R together (a map taken at 2 kg reads 1 kg and 3 kg at 2.6 and 2.8 %: re-take it
for a new load); with an R-phase, a reversal to heating inside it drops R at once (the model's
memoryless R-phase), which the estimate reads as motion (partial loops 6.8 %).
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

SCHEMA_VERSION = 1
"""Version of the calibration file (``SelfSenseCalibration.to_json``)."""
MIN_CURRENT_A = 0.02
"""Below this current no resistance is taken (the reading is mostly noise), A."""
PROBE_LEVEL_A = 0.2
"""Heating above this current, cooling at or below it (the probe current ≤ 0.1 A), A."""
FILTER_TAU_S = 0.02
"""First-order filter time constant while heating, s (4 samples at 200 Hz)."""
FILTER_TAU_COOLING_S = 0.2
"""... while cooling at the probe current (≈ 14× noisier per reading at 0.1 A than at 1.4 A; 40
samples at 200 Hz; the balance of 0.05, 0.1, 0.2, 0.4 s on held-out major and partial cycles)."""
MIN_ROWS = 200
"""Fewest rows with a resistance and a valid position a calibration accepts."""
MIN_BRANCH_ROWS = 30
"""Fewest learning rows (the transformation part) per branch."""
POLY_DEGREE = 5
"""Degree of the polynomial map (lowered until monotone on the learning range)."""
MAX_BINS = 24
ROWS_PER_BIN = 40
FOLDS_MAX = 10
"""Held-out RMS: cycles are held out in at most this many folds."""
HEATING, COOLING = 0, 1
BRANCH_NAMES = ("heating", "cooling")
THERMAL_REF_C = 20.0
"""Reference temperature of the thermal map's resistance, °C."""
THERMAL_DEGREE = 2
"""Degree of the thermal map's polynomial in the resistance at the reference temperature."""
MAPS = ("branches", "thermal")
"""What the estimator reads, chosen at calibration: the branch maps with the reversal rule on R
alone, or the thermal map (R at a reference temperature from the bench's heat balance).
Measured: the branch maps on open-loop cycles (a mock session's 2 cycles: 3.8 % of the stroke,
the thermal map 6.8 %); the thermal map under control (`smabench bench selfsense`, 1× noise:
a hold with the laser gone 60 s within 1.5 % of the stroke, the branch maps 38.6 %; the worse
sine tracked 1.69× the laser's error, the branch maps 2.81×)."""
THERMAL_FILTER_REF_A = 0.5
"""With the thermal map, R's filter time constant is ``filter_tau_s`` × (this / I)² below this
current, A: each reading weighted by its signal to noise. Measured (`smabench bench selfsense`,
1× noise), reference 0.3 / 0.5 / 0.7 / 1.0 A: PID on the estimate tracks the worse sine 1.60 /
1.69 / 1.75 / 1.98× the laser's error and holds with the laser gone within 8.2 / 1.5 / 0.5 / 0.6 %
of the stroke (a fixed 0.02 s: 1.63×, 14 %: the PID swings between the probe and 2 A on the
probe's 0.2 %-of-R voltage steps)."""
TCR_GRID_PER_K = tuple(float(v) for v in np.linspace(0.0, 1.5e-3, 61))
"""Temperature coefficients the thermal map tries, 1/K (NiTi's 1e-4 … 1e-3 and beyond)."""


class SelfSenseError(ValueError):
    """Bad input to self-sensing (a session without voltage, too few rows with R …)."""


# --------------------------------------------------------------------------- thermal map
@dataclass(frozen=True)
class ThermalMap:
    """Position from the resistance and the wire's temperature: x = Σ c_k·u^k (mm) with
    u = (R_c − r0)/r_scale and R_c = R / (1 + tcr·(T − ref_c)), the resistance at the
    reference temperature. R is one function of (ξ, T, ε): the loop's hysteresis is in ξ(T),
    not in R(ξ, T), so this map needs no branch rule; T comes from the bench's heat balance.
    ``rms_mm``: its RMS error on the rows it was learnt from, mm."""

    tcr_per_k: float
    r0_ohm: float
    r_scale_ohm: float
    coeffs: tuple[float, ...]
    rms_mm: float = math.nan
    ref_c: float = THERMAL_REF_C

    def compensated(self, r_ohm: float, temperature_c: float) -> float:
        """The resistance at the reference temperature, Ω."""
        return r_ohm / (1.0 + self.tcr_per_k * (temperature_c - self.ref_c))

    def of_compensated(self, rc_ohm: float) -> float:
        """Position for a resistance at the reference temperature, mm."""
        u = (rc_ohm - self.r0_ohm) / self.r_scale_ohm
        x = 0.0
        for c in reversed(self.coeffs):
            x = x * u + c
        return x

    def at(self, r_ohm: float, temperature_c: float) -> float:
        """Position for one resistance (Ω) at one temperature (°C), mm."""
        return self.of_compensated(self.compensated(r_ohm, temperature_c))

    def __call__(self, r_ohm: np.ndarray, temperature_c: np.ndarray) -> np.ndarray:
        rc = np.asarray(r_ohm, float) / (
            1.0 + self.tcr_per_k * (np.asarray(temperature_c, float) - self.ref_c)
        )
        return np.polynomial.polynomial.polyval((rc - self.r0_ohm) / self.r_scale_ohm,
                                                self.coeffs)  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["coeffs"] = list(self.coeffs)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ThermalMap:
        return cls(float(d["tcr_per_k"]), float(d["r0_ohm"]), float(d["r_scale_ohm"]),
                   tuple(float(c) for c in d["coeffs"]), float(d.get("rms_mm", math.nan)),
                   float(d.get("ref_c", THERMAL_REF_C)))  # fmt: skip


def fit_thermal_map(r_ohm: np.ndarray, temperature_c: np.ndarray, x_mm: np.ndarray,
                    degree: int = THERMAL_DEGREE) -> ThermalMap:  # fmt: skip
    """The thermal map of least RMS error over :data:`TCR_GRID_PER_K` (each a linear least
    squares in the polynomial's coefficients)."""
    r, t, x = (np.asarray(a, dtype=float) for a in (r_ohm, temperature_c, x_mm))
    ok = np.isfinite(r) & np.isfinite(t) & np.isfinite(x)
    r, t, x = r[ok], t[ok], x[ok]
    if len(r) < MIN_ROWS:
        raise SelfSenseError(f"{len(r)} rows with a resistance, a temperature and a position; "
                             f"at least {MIN_ROWS} needed for the thermal map")  # fmt: skip
    best: ThermalMap | None = None
    for tcr in TCR_GRID_PER_K:
        rc = r / (1.0 + tcr * (t - THERMAL_REF_C))
        r0, rs = float(np.mean(rc)), float(np.std(rc)) or 1.0
        u = (rc - r0) / rs
        design = np.vander(u, degree + 1, increasing=True)
        coef, *_ = np.linalg.lstsq(design, x, rcond=None)
        rms = float(np.sqrt(np.mean((x - design @ coef) ** 2)))
        if best is None or rms < best.rms_mm:
            best = ThermalMap(tcr, r0, rs, tuple(float(c) for c in coef), rms)
    assert best is not None
    return best


def a_rc(tau_s: float, dt_s: float) -> float:
    """The gain of a first-order filter's step of ``dt_s`` (s) with time constant ``tau_s``."""
    return 1.0 if tau_s <= 0 else -math.expm1(-max(dt_s, 0.0) / tau_s)


# --------------------------------------------------------------------------- resistance
def resistance_from(
    current_a: np.ndarray, voltage_v: np.ndarray, min_current_a: float = MIN_CURRENT_A
) -> np.ndarray:
    """R = V/I, Ω, where ``current_a ≥ min_current_a`` and both are finite; NaN elsewhere."""
    i = np.asarray(current_a, dtype=float)
    v = np.asarray(voltage_v, dtype=float)
    ok = np.isfinite(i) & np.isfinite(v) & (i >= min_current_a)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, v / np.where(ok, i, 1.0), np.nan)


def branch_of(current_a: np.ndarray, probe_level_a: float = PROBE_LEVEL_A) -> np.ndarray:
    """0 (heating) where ``current_a > probe_level_a``, 1 (cooling) elsewhere."""
    return np.where(np.asarray(current_a, dtype=float) > probe_level_a, HEATING, COOLING)


# --------------------------------------------------------------------------- maps
def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch–Carlson slopes of the monotone piecewise-cubic Hermite interpolant."""
    n = len(x)
    if n < 2:
        return np.zeros(n)
    h = np.diff(x)
    d = np.diff(y) / h
    if n == 2:
        return np.array([d[0], d[0]])
    m = np.zeros(n)
    w1 = 2.0 * h[1:] + h[:-1]
    w2 = h[1:] + 2.0 * h[:-1]
    same = d[:-1] * d[1:] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inner = (w1 + w2) / (w1 / d[:-1] + w2 / d[1:])
    m[1:-1] = np.where(same, inner, 0.0)

    def end(h0: float, h1: float, d0: float, d1: float) -> float:
        s = ((2.0 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)
        if np.sign(s) != np.sign(d0):
            return 0.0
        if np.sign(d0) != np.sign(d1) and abs(s) > abs(3.0 * d0):
            return 3.0 * d0
        return float(s)

    m[0] = end(h[0], h[1], d[0], d[1])
    m[-1] = end(h[-1], h[-2], d[-1], d[-2])
    return m


def _isotonic(y: np.ndarray, w: np.ndarray, increasing: bool) -> np.ndarray:
    """Weighted least-squares monotone fit (pool adjacent violators)."""
    sign = 1.0 if increasing else -1.0
    vals: list[float] = []
    wts: list[float] = []
    lens: list[int] = []
    for yi, wi in zip((sign * y).tolist(), w.tolist(), strict=True):
        vals.append(yi)
        wts.append(wi)
        lens.append(1)
        while len(vals) > 1 and vals[-2] > vals[-1]:
            v1, w1, n1 = vals.pop(), wts.pop(), lens.pop()
            wsum = wts[-1] + w1
            vals[-1] = (vals[-1] * wts[-1] + v1 * w1) / wsum
            wts[-1] = wsum
            lens[-1] += n1
    return sign * np.repeat(vals, lens)


@dataclass(frozen=True)
class BranchMap:
    """One branch's monotone map x = f(R) and what the reversal rule needs.

    ``kind``: ``pchip`` (knots ``r_knots_ohm``/``x_knots_mm``) or ``poly`` (``coeffs`` of the
    polynomial in z = (R − r_center_ohm)/r_scale_ohm, highest power first). Outside
    ``r_lo_ohm … r_hi_ohm`` the map holds its end values. ``forward``: +1 when R rises as the
    branch's transformation proceeds, −1 when it falls; ``x_direction``: +1 when the position
    grows on this branch. ``noise_ohm``: standard deviation of the filtered R's noise on this
    branch, Ω (for information); ``rms_mm``: RMS error of the estimate on this branch (held out
    by cycle when ``heldout``), mm; ``rows``: learning rows.
    """

    kind: str
    r_lo_ohm: float
    r_hi_ohm: float
    forward: int
    x_direction: int
    r_knots_ohm: tuple[float, ...] = ()
    x_knots_mm: tuple[float, ...] = ()
    coeffs: tuple[float, ...] = ()
    r_center_ohm: float = 0.0
    r_scale_ohm: float = 1.0
    noise_ohm: float = 0.0
    rms_mm: float = math.nan
    heldout: bool = False
    rows: int = 0
    _slopes: tuple[float, ...] = field(default=(), repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in ("pchip", "poly"):
            raise SelfSenseError(f"unknown map kind {self.kind!r} (pchip or poly)")
        if self.kind == "pchip":
            r = np.asarray(self.r_knots_ohm, dtype=float)
            x = np.asarray(self.x_knots_mm, dtype=float)
            if len(r) < 2 or len(r) != len(x) or np.any(np.diff(r) <= 0):
                raise SelfSenseError("a pchip map needs ≥ 2 knots with increasing R")
            object.__setattr__(self, "_slopes", tuple(_pchip_slopes(r, x).tolist()))
        elif not self.coeffs:
            raise SelfSenseError("a poly map needs coefficients")
        if self.forward not in (-1, 1) or self.x_direction not in (-1, 1):
            raise SelfSenseError("forward and x_direction must be +1 or -1")

    @property
    def r_start_ohm(self) -> float:
        """R where the branch's transformation starts (the map's backward end)."""
        return self.r_lo_ohm if self.forward > 0 else self.r_hi_ohm

    @property
    def r_end_ohm(self) -> float:
        """R where the branch's transformation ends."""
        return self.r_hi_ohm if self.forward > 0 else self.r_lo_ohm

    def at(self, r: float) -> float:
        """f(R) for one float (clamped to the map's R range)."""
        r = min(max(r, self.r_lo_ohm), self.r_hi_ohm)
        if self.kind == "poly":
            z = (r - self.r_center_ohm) / self.r_scale_ohm
            y = 0.0
            for c in self.coeffs:
                y = y * z + c
            return y
        rk, xk, mk = self.r_knots_ohm, self.x_knots_mm, self._slopes
        k = min(max(bisect.bisect_right(rk, r) - 1, 0), len(rk) - 2)
        h = rk[k + 1] - rk[k]
        s = (r - rk[k]) / h
        s2, s3 = s * s, s * s * s
        return (
            (2 * s3 - 3 * s2 + 1) * xk[k]
            + (s3 - 2 * s2 + s) * h * mk[k]
            + (-2 * s3 + 3 * s2) * xk[k + 1]
            + (s3 - s2) * h * mk[k + 1]
        )

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """f(R) for an array (NaN stays NaN)."""
        r = np.asarray(r, dtype=float)
        out = np.full(r.shape, np.nan)
        ok = np.isfinite(r)
        out[ok] = [self.at(v) for v in r[ok].tolist()]
        return out

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("_slopes")
        for k in ("r_knots_ohm", "x_knots_mm", "coeffs"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BranchMap:
        d = dict(d)
        for k in ("r_knots_ohm", "x_knots_mm", "coeffs"):
            d[k] = tuple(float(v) for v in d.get(k, ()))
        d.pop("_slopes", None)
        return cls(**d)


def fit_branch_map(
    r_ohm: np.ndarray, x_mm: np.ndarray, forward: int, x_direction: int, kind: str = "poly",
    degree: int = POLY_DEGREE,
) -> BranchMap:  # fmt: skip
    """Monotone fit of position ``x_mm`` against resistance ``r_ohm`` (learning rows).

    ``pchip``: R cut into equal-count bins (≈ 40 rows each, at most 24), the bins' median R
    and median x, made monotone by weighted isotonic regression, joined by a PCHIP. ``poly``:
    least squares of ``degree`` in the normalised R, the degree lowered until it is monotone on
    the learning range. The monotone sense is ``forward·x_direction`` (x rises with R when +1).
    """
    r = np.asarray(r_ohm, dtype=float)
    x = np.asarray(x_mm, dtype=float)
    ok = np.isfinite(r) & np.isfinite(x)
    r, x = r[ok], x[ok]
    if len(r) < 4:
        raise SelfSenseError(f"too few rows to fit a map ({len(r)})")
    increasing = forward * x_direction > 0
    lo, hi = float(np.min(r)), float(np.max(r))
    if kind == "poly":
        center, scale = 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-12)
        z = (r - center) / scale
        grid = np.linspace(-1.0, 1.0, 201)
        for deg in range(min(degree, len(r) - 1), 0, -1):
            c = np.polyfit(z, x, deg)
            slope = np.polyval(np.polyder(c), grid)
            if np.all(slope >= 0) if increasing else np.all(slope <= 0):
                break
        else:
            raise SelfSenseError("the position does not follow the resistance one way")
        return BranchMap(
            "poly", lo, hi, forward, x_direction, coeffs=tuple(c.tolist()),
            r_center_ohm=center, r_scale_ohm=scale, rows=len(r),
        )  # fmt: skip
    if kind != "pchip":
        raise SelfSenseError(f"unknown fit {kind!r} (pchip or poly)")
    order = np.argsort(r, kind="stable")
    r, x = r[order], x[order]
    nbins = int(min(MAX_BINS, max(2, len(r) // ROWS_PER_BIN)))
    edges = np.linspace(0, len(r), nbins + 1).round().astype(int)
    rk = np.array([np.median(r[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    xk = np.array([np.median(x[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)])
    wk = np.diff(edges).astype(float)
    keep = np.concatenate(([True], np.diff(rk) > 1e-12 * max(abs(hi), 1.0)))
    if not keep.all():  # equal medians (a quantised R): merge into the first
        groups = np.cumsum(keep) - 1
        rk = np.bincount(groups, rk * wk) / np.bincount(groups, wk)
        xk = np.bincount(groups, xk * wk) / np.bincount(groups, wk)
        wk = np.bincount(groups, wk)
    if len(rk) < 2:
        raise SelfSenseError("the learning rows span no resistance range")
    xk = _isotonic(xk, wk, increasing)
    return BranchMap(
        "pchip", float(rk[0]), float(rk[-1]), forward, x_direction,
        r_knots_ohm=tuple(rk.tolist()), x_knots_mm=tuple(xk.tolist()), rows=len(r),
    )  # fmt: skip


# --------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class SelfSenseCalibration:
    """A learned resistance → position map (``to_json``/``from_json``).

    ``heating``/``cooling``: the branch maps (:class:`BranchMap`, each with its RMS error, mm);
    ``min_current_a``, ``probe_level_a``: R threshold and branch split, A; ``filter_tau_s``,
    ``filter_tau_cooling_s``: the R filter's time constants, s; ``reversal``: the reversal rule
    on; ``r_range_ohm``: filtered R seen while learning, Ω; ``x_range_mm``: the laser's position
    range (1st … 99th percentile), mm, whose width is the stroke; ``sessions``: where it came
    from (path, load_kg, wire, rows); ``load_kg``/``wire``: the sessions' (None when they
    differ or are not recorded).
    """

    heating: BranchMap
    cooling: BranchMap
    min_current_a: float = MIN_CURRENT_A
    probe_level_a: float = PROBE_LEVEL_A
    filter_tau_s: float = FILTER_TAU_S
    filter_tau_cooling_s: float = FILTER_TAU_COOLING_S
    reversal: bool = True
    r_range_ohm: tuple[float, float] = (math.nan, math.nan)
    x_range_mm: tuple[float, float] = (math.nan, math.nan)
    sessions: tuple[dict[str, Any], ...] = ()
    load_kg: float | None = None
    wire: dict[str, Any] | None = None
    thermal: ThermalMap | None = None
    map: str = "branches"
    schema_version: int = SCHEMA_VERSION

    @property
    def stroke_mm(self) -> float:
        return self.x_range_mm[1] - self.x_range_mm[0]

    def branch(self, b: int) -> BranchMap:
        return self.heating if b == HEATING else self.cooling

    def percent_of_stroke(self, mm: float) -> float:
        return 100.0 * mm / self.stroke_mm if self.stroke_mm > 0 else math.nan

    def to_dict(self) -> dict[str, Any]:
        d = {
            "schema_version": self.schema_version,
            "kind": "smabench-selfsense",
            "heating": self.heating.to_dict(),
            "cooling": self.cooling.to_dict(),
        }
        for k in ("min_current_a", "probe_level_a", "filter_tau_s", "filter_tau_cooling_s",
                  "reversal", "load_kg", "wire"):  # fmt: skip
            d[k] = getattr(self, k)
        d["r_range_ohm"] = list(self.r_range_ohm)
        d["x_range_mm"] = list(self.x_range_mm)
        d["stroke_mm"] = self.stroke_mm
        d["rms_mm"] = {n: self.branch(b).rms_mm for b, n in enumerate(BRANCH_NAMES)}
        d["sessions"] = [dict(s) for s in self.sessions]
        d["map"] = self.map
        if self.thermal is not None:
            d["thermal"] = self.thermal.to_dict()
        return d

    def to_json(self) -> str:
        """The calibration as JSON text (one trailing newline; NaN written as null)."""
        return json.dumps(_nan_to_none(self.to_dict()), indent=2) + "\n"

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SelfSenseCalibration:
        version = d.get("schema_version")
        if version != SCHEMA_VERSION:
            raise SelfSenseError(
                f"self-sense calibration schema {version!r} not supported (expected "
                f"{SCHEMA_VERSION})"
            )
        try:
            return cls(
                heating=BranchMap.from_dict(_none_to_nan(d["heating"])),
                cooling=BranchMap.from_dict(_none_to_nan(d["cooling"])),
                min_current_a=float(d["min_current_a"]),
                probe_level_a=float(d["probe_level_a"]),
                filter_tau_s=float(d["filter_tau_s"]),
                filter_tau_cooling_s=float(d["filter_tau_cooling_s"]),
                reversal=bool(d["reversal"]),
                r_range_ohm=_pair(d["r_range_ohm"]),
                x_range_mm=_pair(d["x_range_mm"]),
                sessions=tuple(d.get("sessions", ())),
                load_kg=None if d.get("load_kg") is None else float(d["load_kg"]),
                wire=d.get("wire"),
                thermal=None if d.get("thermal") is None else ThermalMap.from_dict(d["thermal"]),
                map=str(d.get("map", "branches")),
            )
        except (KeyError, TypeError) as exc:
            raise SelfSenseError(f"not a self-sense calibration ({exc!r})") from None

    @classmethod
    def from_json(cls, text: str) -> SelfSenseCalibration:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SelfSenseError(f"not JSON ({exc.msg}, line {exc.lineno})") from None
        if not isinstance(d, dict):
            raise SelfSenseError("not a self-sense calibration (a JSON object expected)")
        return cls.from_dict(d)


def _pair(v: Any) -> tuple[float, float]:
    a, b = v
    return (math.nan if a is None else float(a), math.nan if b is None else float(b))


def _nan_to_none(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_nan_to_none(v) for v in obj]
    return obj


def _none_to_nan(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (math.nan if v is None and k == "rms_mm" else v) for k, v in d.items()}


# --------------------------------------------------------------------------- estimator
class SelfSenseEstimator:
    """Position from the wire's resistance, one sample at a time (causal, online).

    ``update(t_s, current_a, voltage_v)`` → the position estimate, mm (NaN until a sample has
    had a resistance; the last estimate while the current is below ``min_current_a``).
    ``estimate(t_s, current_a, voltage_v)`` runs ``update`` over arrays in order (same floats).
    """

    def __init__(self, calibration: SelfSenseCalibration) -> None:
        self.calibration = calibration
        self._maps = (calibration.heating, calibration.cooling)
        self.reset()

    def reset(self) -> None:
        """Forget the history (the next sample starts as a rested wire)."""
        self._rf = math.nan  # filtered R
        self._t = math.nan  # time of the last R
        self._x = math.nan  # last estimate
        self._branch = COOLING
        self._xr = [math.nan, math.nan]  # per branch: position at its switch
        self._ur = [math.nan, math.nan]  # per branch: anchor, forward·R
        self._fr = [math.nan, math.nan]  # per branch: f(R_r)

    @property
    def resistance_ohm(self) -> float:
        """The filtered resistance of the last sample with one, Ω (NaN before)."""
        return self._rf

    def _anchor(self, b: int, rf: float) -> None:
        m = self._maps[b]
        self._ur[b] = m.forward * rf
        self._fr[b] = m.at(rf)

    def _follow(self, b: int, rf: float, x_prev: float) -> float:
        """Branch b's reversal rule at R_f = rf (its anchor follows backward moves)."""
        m = self._maps[b]
        u = m.forward * rf
        fx = m.at(rf)
        if u < self._ur[b]:  # moving away from the branch's end: the anchor follows
            self._ur[b], self._fr[b] = u, fx
            # ... and the reversal point slides onto the branch's map where the map lies
            # further back (the major branch bounds the state)
            xr = self._xr[b]
            x_prev = self._xr[b] = min(xr, fx) if m.x_direction > 0 else max(xr, fx)
        u_r = self._ur[b]
        u_end = m.forward * m.r_end_ohm
        w = 1.0 if u_r >= u_end else min(max((u_end - u) / (u_end - u_r), 0.0), 1.0)
        x = fx + (self._xr[b] - self._fr[b]) * w
        # the martensite fraction moves one way on a branch, so does the estimate
        return max(x, x_prev) if m.x_direction > 0 else min(x, x_prev)

    def update(self, t_s: float, current_a: float, voltage_v: float,
               temperature_c: float = math.nan) -> float:  # fmt: skip
        """One sample (time, s; measured current, A; Kelvin wire voltage, V; the wire's
        temperature from the heat balance, °C, NaN when not known) → position, mm. The thermal
        map (no branch rule) when the calibration chose it (``map``) and there is a
        temperature; else the branch maps."""
        cal = self.calibration
        i, v, t = float(current_a), float(voltage_v), float(t_s)
        if not (i >= cal.min_current_a) or not math.isfinite(v) or not math.isfinite(t):
            return self._x
        r = v / i
        b = HEATING if i > cal.probe_level_a else COOLING
        tau = cal.filter_tau_s if b == HEATING else cal.filter_tau_cooling_s
        thermal = cal.map == "thermal" and cal.thermal is not None and math.isfinite(temperature_c)
        if thermal:
            # a reading's variance grows as 1/I² (the voltage's noise and 0.1 mV steps are fixed)
            tau = cal.filter_tau_s * max(1.0, (THERMAL_FILTER_REF_A / i) ** 2)
        if math.isnan(self._rf):  # the first R: a rested wire, at the cooling map's end
            rf = r
            m = self._maps[COOLING]
            self._branch = COOLING
            self._x = self._xr[COOLING] = m.at(m.r_end_ohm)
            self._anchor(COOLING, rf)
        else:
            rf = self._rf + a_rc(tau, t - self._t) * (r - self._rf)
        self._rf, self._t = rf, t
        if thermal:
            # the filtered R with the heat balance's temperature of this instant: filtering
            # the compensated R instead (R and T of one instant together) held the position
            # with the laser gone within 24 % of the stroke, not 1.5 % (the heat balance's
            # temperature leads the wire's after a current swing)
            lo, hi = cal.x_range_mm
            margin = 0.1 * (hi - lo)  # the map's polynomial is not trusted far past its data
            self._x = min(max(cal.thermal.at(rf, float(temperature_c)), lo - margin), hi + margin)
            return self._x
        m = self._maps[b]
        if not cal.reversal:
            self._branch = b
            self._x = m.at(rf)
            return self._x
        x_prev = self._x
        if b != self._branch:
            self._branch = b
            self._xr[b] = x_prev
            self._anchor(b, rf)
        self._x = self._follow(b, rf, x_prev)
        return self._x

    def estimate(self, t_s: np.ndarray, current_a: np.ndarray, voltage_v: np.ndarray,
                 temperature_c: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """``update`` over arrays, in order, from the estimator's present state (``temperature_c``:
        the heat balance's per row, as the bench records it, or None)."""
        t = np.asarray(t_s, dtype=float).tolist()
        i = np.asarray(current_a, dtype=float).tolist()
        v = np.asarray(voltage_v, dtype=float).tolist()
        temp = ([math.nan] * len(t) if temperature_c is None
                else np.asarray(temperature_c, dtype=float).tolist())  # fmt: skip
        if not len(t) == len(i) == len(v) == len(temp):
            raise SelfSenseError("t_s, current_a, voltage_v and temperature_c must be equally long")
        up = self.update
        return np.array([up(a, b, c, d) for a, b, c, d in zip(t, i, v, temp, strict=True)],
                        dtype=float)  # fmt: skip

    def _set_maps(self, heating: BranchMap, cooling: BranchMap) -> None:
        """Swap the maps mid-stream (the held-out RMS: each cycle with maps that never saw it);
        the anchors' f(R_r) are re-evaluated with the new maps."""
        self._maps = (heating, cooling)
        for b, m in enumerate(self._maps):
            if math.isfinite(self._ur[b]):
                self._fr[b] = m.at(m.forward * self._ur[b])


# --------------------------------------------------------------------------- learning


def load_calibration(path: str | Path) -> SelfSenseCalibration:
    """The calibration in the JSON file ``path``; :class:`SelfSenseError` (one line naming the
    file) when it cannot be read or is not a calibration."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise SelfSenseError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise SelfSenseError(f"{path}: not a JSON text file") from None
    try:
        cal = SelfSenseCalibration.from_json(text)
    except (ValueError, TypeError, AttributeError, KeyError) as exc:  # SelfSenseError too
        raise SelfSenseError(f"{path}: {exc}") from None
    ok = (0 < cal.min_current_a < cal.probe_level_a < math.inf
          and 0 <= cal.filter_tau_s < math.inf and 0 <= cal.filter_tau_cooling_s < math.inf
          and cal.stroke_mm > 0)  # fmt: skip
    if not ok:
        raise SelfSenseError(
            f"{path}: not a usable self-sense calibration (need 0 < min_current_a < "
            "probe_level_a, finite filter time constants ≥ 0 s and a stroke > 0 mm)"
        )
    return cal
