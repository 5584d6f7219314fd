"""Identify a loop model from a measured loop (position vs temperature) by least squares.

Steps, as in Shibly & Söffker: split the samples into heating and cooling branches; find the two
common points where the branches diverge and meet again; rotate (model 1) or not (model 2); read
the crossing point of the heating branch and the amplitudes from the data; then refine with
scipy's ``least_squares`` starting from those values. Our :class:`SigmoidModel` and the
Preisach peer are fitted to the same samples. Data with partial loops (first-order reversal
curves, inner loops: :func:`partial_loop_runs`) are split into branch runs by the reversal
memory; the major-loop law is fitted on the major branches' samples and our model's minor-branch
law (``memory_theta``) along the whole history. The geometry follows the data's orientation
(:func:`_orientation`): fitting −y gives the mirror image of the model of y.

Errors reported for every fit:

- ``rmse_mm``: root mean square of measured − model position, mm;
- ``nrmse_percent``: ``rmse_mm`` as % of the loop's stroke (max − min measured position);
- ``ard_percent``: the paper's average relative deviation, ``mean(|measured − model| / ref)``
  in %. The paper takes it relative to the measured length; our positions have an arbitrary
  zero (0 at the hot end for strain data), so ``ref`` is the wire length when the caller gives
  it (``reference_length_mm``) and the stroke otherwise.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from threadpoolctl import threadpool_limits

from smabench.physics.loop_models import (
    CommonPoints,
    FractionBranch,
    LoopStepper,
    Model1,
    Model2,
    SigmoidModel,
    branch_directions,
    run_history,
    starts_heating,
)
from smabench.physics.memory import branch_runs

log = logging.getLogger(__name__)

MIN_POINTS = 20
MIN_BRANCH_POINTS = 5
MIN_GAP_FRACTION = 0.03  # the branches must be this far apart (fraction of stroke) to be a loop
COMMON_POINT_FRACTION = 0.03  # branches "meet" where their gap is below this share of the max gap


class FitError(ValueError):
    """The data cannot be fitted: NaNs, too few points, not a loop, no convergence."""


@dataclass
class LoopData:
    """A measured loop split into branches. Temperatures °C, positions mm."""

    temperature_c: np.ndarray
    position_mm: np.ndarray
    heating: np.ndarray
    deadband_k: float
    stroke_mm: float
    grid_c: np.ndarray = field(repr=False)
    heating_curve_mm: np.ndarray = field(repr=False)
    cooling_curve_mm: np.ndarray = field(repr=False)


@dataclass
class FitResult:
    """A fitted model and its errors on the samples it was fitted to."""

    model: str
    parameters: dict[str, float]
    rmse_mm: float
    nrmse_percent: float
    ard_percent: float
    n_points: int
    loop_model: object = field(repr=False)
    deadband_k: float = 1.0

    def predict(self, temperature_c: np.ndarray) -> np.ndarray:
        """Model position (mm) along a temperature sequence, history included."""
        t = np.asarray(temperature_c, dtype=float)
        if hasattr(self.loop_model, "predict"):
            return self.loop_model.predict(t)
        if t.size == 0:
            return np.empty(0)
        heating = starts_heating(self.loop_model, float(t[0]))
        return run_history(self.loop_model, t, self.deadband_k, heating)

    def stepper(self) -> LoopStepper:
        """An online stepper for this model (closed-form models only)."""
        return LoopStepper(self.loop_model, self.deadband_k)


# --------------------------------------------------------------------------- data checks
def prepare_loop(temperature_c, position_mm) -> LoopData:
    """Validate a measured loop and split it into branches; raises :class:`FitError`."""
    t = np.asarray(temperature_c, dtype=float).ravel()
    y = np.asarray(position_mm, dtype=float).ravel()
    if t.shape != y.shape:
        raise FitError(f"temperature has {t.size} values but position has {y.size}")
    bad = ~(np.isfinite(t) & np.isfinite(y))
    if bad.any():
        i = int(np.nonzero(bad)[0][0])
        raise FitError(
            f"{int(bad.sum())} NaN or infinite values (first at sample {i}); clean the data"
        )
    if t.size < MIN_POINTS:
        raise FitError(f"too few points to fit a loop: {t.size} < {MIN_POINTS}")
    span = float(t.max() - t.min())
    stroke = float(y.max() - y.min())
    if span < 5.0 or stroke <= 0.0:
        raise FitError(f"not a loop: temperature spans {span:.2f} K and position {stroke:.4g} mm")
    deadband = max(0.5, 0.02 * span)
    heating = branch_directions(t, deadband)
    n_h, n_c = int(heating.sum()), int((~heating).sum())
    if min(n_h, n_c) < MIN_BRANCH_POINTS:
        raise FitError(
            f"not a loop: {n_h} heating and {n_c} cooling samples; need both branches "
            f"(at least {MIN_BRANCH_POINTS} each)"
        )
    grid = np.linspace(t.min(), t.max(), 61)
    centres = 0.5 * (grid[1:] + grid[:-1])
    hc = _binned_median(t[heating], y[heating], grid)
    cc = _binned_median(t[~heating], y[~heating], grid)
    gap = hc - cc
    ok = np.isfinite(gap)
    if ok.sum() < 5 or np.nanmax(np.abs(gap)) < MIN_GAP_FRACTION * stroke:
        raise FitError(
            "not a loop: heating and cooling branches do not separate "
            f"(largest gap {np.nanmax(np.abs(gap)) if ok.any() else 0:.4g} mm, "
            f"stroke {stroke:.4g} mm)"
        )
    return LoopData(t, y, heating, deadband, stroke, centres, hc, cc)


def major_loop_of(loop: LoopData, runs) -> LoopData | None:
    """The samples of ``loop`` on its major branches (branches that start at a common point),
    labelled by the history's runs; None when too few are left for a loop."""
    on_major, heating = major_branch_samples(runs, loop.temperature_c.size)
    t, y, h = loop.temperature_c[on_major], loop.position_mm[on_major], heating[on_major]
    if min(int(h.sum()), int((~h).sum())) < MIN_BRANCH_POINTS:
        return None
    grid = np.linspace(t.min(), t.max(), 61)
    hc = _binned_median(t[h], y[h], grid)
    cc = _binned_median(t[~h], y[~h], grid)
    return LoopData(t, y, h, loop.deadband_k, loop.stroke_mm, 0.5 * (grid[1:] + grid[:-1]), hc, cc)


def _binned_median(t: np.ndarray, y: np.ndarray, edges: np.ndarray) -> np.ndarray:
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, edges.size - 2)
    out = np.full(edges.size - 1, np.nan)
    for k in np.unique(idx):
        out[k] = np.median(y[idx == k])
    return out


def find_common_points(loop: LoopData) -> CommonPoints:
    """Common points where the branches diverge (T1) and meet again (T2), lines outside them."""
    gap = loop.heating_curve_mm - loop.cooling_curve_mm
    ok = np.isfinite(gap)
    g = np.where(ok, np.abs(gap), 0.0)
    sep = np.nonzero(g > COMMON_POINT_FRACTION * g.max())[0]
    i1, i2 = int(sep[0]), int(sep[-1])
    t1, t2 = float(loop.grid_c[i1]), float(loop.grid_c[i2])

    def level(i: int) -> float:
        vals = [v[i] for v in (loop.heating_curve_mm, loop.cooling_curve_mm) if np.isfinite(v[i])]
        return float(np.mean(vals))

    t, y = loop.temperature_c, loop.position_mm
    cp = CommonPoints(t1, level(i1), t2, level(i2))
    lo = t < t1
    if lo.sum() >= 3:
        cp.low_slope_mm_per_k = float(np.polyfit(t[lo] - t1, y[lo] - cp.y1_mm, 1)[0])
    hi = t > t2
    if hi.sum() >= 4:
        d = t[hi] - t2
        a = np.column_stack([d, d * d])
        coef, *_ = np.linalg.lstsq(a, y[hi] - cp.y2_mm, rcond=None)
        cp.exp1_mm_per_k, cp.exp2_mm_per_k2 = float(coef[0]), float(coef[1])
    return cp


# --------------------------------------------------------------------------- fitting
def _refine(residual: Callable, x0, lo, hi, what: str, max_nfev: int = 4000, tol: float = 1e-8):
    x0 = np.clip(np.asarray(x0, dtype=float), lo, hi)
    try:
        # one BLAS thread: the SVDs of these tall, thin Jacobians are fastest on one core, and
        # a threaded BLAS on a busy 2-core machine made each one ~100x slower
        with threadpool_limits(1, user_api="blas"):
            res = least_squares(residual, x0, bounds=(lo, hi), x_scale="jac", max_nfev=max_nfev,
                                ftol=tol, xtol=tol)  # fmt: skip
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FitError(f"{what}: least squares failed: {exc}") from exc
    if not np.all(np.isfinite(res.fun)):
        raise FitError(f"{what}: the fit did not converge to finite values")
    return res.x


def _cp_from(x, base: CommonPoints) -> CommonPoints:
    return CommonPoints(
        float(x[0]), float(x[1]), float(x[2]), float(x[3]),
        float(x[4]), float(x[5]), float(x[6]),
    )  # fmt: skip


def _cp_vector(cp: CommonPoints) -> list[float]:
    return [
        cp.t1_c, cp.y1_mm, cp.t2_c, cp.y2_mm,
        cp.low_slope_mm_per_k, cp.exp1_mm_per_k, cp.exp2_mm_per_k2,
    ]  # fmt: skip


def _cp_bounds(loop: LoopData, cp: CommonPoints) -> tuple[list[float], list[float]]:
    t, y = loop.temperature_c, loop.position_mm
    tmin, tmax = float(t.min()), float(t.max())
    mid = 0.5 * (cp.t1_c + cp.t2_c)
    ylo, yhi = float(y.min()) - loop.stroke_mm, float(y.max()) + loop.stroke_mm
    big = 10.0 * loop.stroke_mm / max(tmax - tmin, 1.0)
    lo = [tmin - 5.0, ylo, mid + 1.0, ylo, -big, -big, -big]
    hi = [mid - 1.0, yhi, tmax + 5.0, yhi, big, big, big]
    return lo, hi


def _orientation(loop: LoopData) -> float:
    """+1 when the heating branch lies above the cooling branch (in the sign of the data's
    position), −1 when below: the models' geometry follows the data, not a sign convention."""
    gap = loop.heating_curve_mm - loop.cooling_curve_mm
    return 1.0 if float(np.nansum(gap)) >= 0.0 else -1.0


def _model1_start(loop: LoopData, cp: CommonPoints, aspect: float) -> list[float]:
    """The paper's identification in the rotated frame: amplitudes and crossing point (in the
    orientation ``o`` of the data: o·a1 < 0, o·a21 > 0, o·a22 < 0)."""
    o = _orientation(loop)
    t, y, h = loop.temperature_c, loop.position_mm * aspect, loop.heating
    y1, y2 = cp.y1_mm * aspect, cp.y2_mm * aspect
    alpha = math.atan2(y2 - y1, cp.t2_c - cp.t1_c)
    ca, sa = math.cos(alpha), math.sin(alpha)
    length = math.hypot(cp.t2_c - cp.t1_c, y2 - y1)
    tr = cp.t2_c + (t - cp.t2_c) * ca + (y - y2) * sa
    yr = o * (y2 - (t - cp.t2_c) * sa + (y - y2) * ca - y2) / aspect  # deviation, mm, oriented
    t11 = cp.t2_c - length
    inside = (tr > t11) & (tr < cp.t2_c)
    cool, heat = inside & ~h, inside & h
    s = loop.stroke_mm
    a1 = float(np.min(yr[cool])) if cool.any() else -0.3 * s
    a21 = float(np.max(yr[heat])) if heat.any() else 0.3 * s
    a22 = float(np.min(yr[heat])) if heat.any() else -0.1 * s
    f12 = 0.7
    if heat.any():
        order = np.argsort(tr[heat])
        trh, yrh = tr[heat][order], yr[heat][order]
        k = int(np.argmax(yrh))
        after = np.nonzero(yrh[k:] <= 0.0)[0]
        if after.size:
            f12 = float((trh[k + after[0]] - t11) / length)
    return [o * min(a1, -1e-6), o * max(a21, 1e-6), o * min(a22, -1e-6), min(max(f12, 0.1), 0.95)]


def fit_model1(loop: LoopData) -> Model1:
    """Paper's model 1: rotate, read the half-sine amplitudes, then refine by least squares.

    Started twice, from the paper's raw-unit rotation and from a rotation in a frame where the
    diagonal is at 45°; the aspect is refined with the rest and the better fit is kept.
    """
    cp = find_common_points(loop)
    t, y, h = loop.temperature_c, loop.position_mm, loop.heating
    s = loop.stroke_mm
    lo_cp, hi_cp = _cp_bounds(loop, cp)
    lo = [*lo_cp, -2 * s, 0.0, -2 * s, 0.05, math.log(1e-3)]
    hi = [*hi_cp, 0.0, 2 * s, 0.0, 0.97, math.log(1e4)]
    if _orientation(loop) < 0:  # heating branch below: the amplitudes change sign
        lo[7:10], hi[7:10] = [0.0, -2 * s, 0.0], [2 * s, 0.0, 2 * s]

    def build(x) -> Model1:
        return Model1(_cp_from(x, cp), *map(float, x[7:11]), math.exp(float(x[11])))

    best, best_cost = None, math.inf
    for aspect in (1.0, (cp.t2_c - cp.t1_c) / max(abs(cp.y2_mm - cp.y1_mm), 1e-9)):
        x0 = [*_cp_vector(cp), *_model1_start(loop, cp, aspect), math.log(aspect)]
        x = _refine(lambda x: build(x).evaluate(t, h) - y, x0, lo, hi, "model 1")
        model = build(x)
        cost = float(np.sum((model.evaluate(t, h) - y) ** 2))
        if cost < best_cost:
            best, best_cost = model, cost
    return _on_major_branches(best, loop, fit_model1)


def fit_model2(loop: LoopData) -> Model2:
    """Paper's model 2: identify f and A from the data (c = 1), then tune c11, c21, c22.

    The common points, f and the cooling branch's own T2 (ratio g, the paper's rule for a
    bending cooling branch) are refined with the c's.
    """
    cp = find_common_points(loop)
    t, y, h = loop.temperature_c, loop.position_mm, loop.heating
    grid, hc, cc = loop.grid_c, loop.heating_curve_mm, loop.cooling_curve_mm
    slope = (cp.y2_mm - cp.y1_mm) / (cp.t2_c - cp.t1_c)
    diag = cp.y1_mm + slope * (grid - cp.t1_c)
    inside = (grid > cp.t1_c) & (grid < cp.t2_c) & np.isfinite(hc) & np.isfinite(cc)
    f = 0.6
    o = _orientation(loop)
    dev_h = np.where(inside, o * (hc - diag), np.nan)
    if np.any(dev_h > 0):
        k = int(np.nanargmax(dev_h))
        below = np.nonzero((dev_h[k:] <= 0) & inside[k:])[0]
        if below.size:
            f = float((grid[k + below[0]] - cp.t1_c) / (cp.t2_c - cp.t1_c))
    f = min(max(f, 0.1), 0.95)
    tcr = cp.t1_c + f * (cp.t2_c - cp.t1_c)
    gap = np.interp(tcr, grid[inside], (hc - cc)[inside]) if inside.any() else loop.stroke_mm / 2
    amplitude = o * float(max(o * gap, 0.05 * loop.stroke_mm))  # signed: o·A > 0
    s = loop.stroke_mm
    lo_cp, hi_cp = _cp_bounds(loop, cp)
    cmax = 20.0 * s / abs(amplitude)
    x0 = [*_cp_vector(cp), f, 1.0, 1.0, 1.0, 1.0]
    lo = [*lo_cp, 0.05, 0.0, 0.0, 0.0, 0.2]
    hi = [*hi_cp, 0.97, cmax, cmax, cmax, 1.0]

    def build(x) -> Model2:
        return Model2(_cp_from(x, cp), amplitude, float(x[7]), *map(float, x[8:12]))

    untuned = build(x0)
    best, best_cost = None, math.inf
    for g0 in (1.0, 0.6):  # plain model 2, and a cooling branch whose T2 moved
        x0[11] = g0
        x = _refine(lambda x: build(x).evaluate(t, h) - y, x0, lo, hi, "model 2")
        model = build(x)
        cost = float(np.sum((model.evaluate(t, h) - y) ** 2))
        if cost < best_cost:
            best, best_cost = model, cost
    model = best
    model.untuned_nrmse_percent = _nrmse(untuned.evaluate(t, h) - y, s)
    return _on_major_branches(model, loop, fit_model2)


def _on_major_branches(model, loop: LoopData, fit: Callable):
    """When the data hold partial loops (:func:`partial_loop_runs`), ``fit`` again on the samples
    of the major branches only (the paper's models have no minor-branch parameter: their minor
    branches follow from the major loop by the adaptation rules)."""
    if getattr(loop, "major_only", False):
        return model
    runs = partial_loop_runs(loop, model)
    if runs is None:
        return model
    major = major_loop_of(loop, runs)
    if major is None or major.temperature_c.size < MAJOR_SHARE * loop.temperature_c.size:
        return model  # the major loop is not well sampled: the fit on every sample stays
    major.major_only = True
    refit = fit(major)
    refit.fitted_on_history = True
    return refit


HISTORY_MAX_NFEV = 300
"""Evaluations of the refit along a history with partial loops (each one runs the history)."""
PARTIAL_SHARE = 0.05
"""Share of the samples that must lie on minor branches for a refit along the history."""


MAJOR_SHARE = 0.25
"""Share of the samples on major branches for the major-loop law to be refitted on them alone."""
THETA_BOUNDS = (-10.0, 60.0)
"""Search range of Frank's θ (60: each grain's two switching temperatures all but locked)."""


def major_branch_samples(runs, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(on a major branch, heating) for each of ``n`` samples from a history's branch runs: the
    samples of branches that start at a common point, and every sample's branch direction."""
    on_major = np.zeros(n, bool)
    heating = np.zeros(n, bool)
    for r in runs:
        heating[r.i0 : r.i1] = r.heating
        if r.start < 0:
            on_major[r.i0 : r.i1] = True
    return on_major, heating


def partial_loop_runs(loop: LoopData, model) -> list | None:
    """The branch runs of the data's history (:func:`~smabench.physics.memory.branch_runs`)
    when at least :data:`PARTIAL_SHARE` of the samples lie on minor branches (branches that
    start at a reversal inside the loop), else None: a major loop fit is all there is to do.
    ``model``: a loop model, or :class:`CommonPoints` (e.g. the data's own)."""
    t = loop.temperature_c
    if isinstance(model, CommonPoints):
        cp, heating = model, bool(t[0] < 0.5 * (model.t1_c + model.t2_c))
    else:
        cp = model.common_points() if hasattr(model, "common_points") else model.cp
        heating = starts_heating(model, float(t[0]))
    runs = branch_runs(t, cp.t1_c, cp.t2_c, loop.deadband_k, heating)
    minor = sum(r.i1 - r.i0 for r in runs if r.start >= 0 and r.i1 - r.i0 >= 3)
    return runs if minor >= max(MIN_POINTS, PARTIAL_SHARE * t.size) else None


HISTORY_SAMPLES = 3000  # samples of a refit along the history
MAJOR_FIT_SAMPLES = 10_000  # samples of the major-loop law's fit


def _history_samples(loop: LoopData, model, runs) -> tuple[np.ndarray, np.ndarray, list]:
    """At most about :data:`HISTORY_SAMPLES` samples of the history for a refit along it: every
    k-th sample plus the first and last of every branch run (the reversal points stay)."""
    t, y = loop.temperature_c, loop.position_mm
    k = int(math.ceil(t.size / HISTORY_SAMPLES))
    if k <= 1:
        return t, y, runs
    keep = np.zeros(t.size, bool)
    keep[::k] = True
    for r in runs:
        keep[r.i0] = keep[r.i1 - 1] = True
    cp = model.common_points() if hasattr(model, "common_points") else model.cp
    ts, ys = t[keep], y[keep]
    heating = starts_heating(model, float(ts[0]))
    return ts, ys, branch_runs(ts, cp.t1_c, cp.t2_c, loop.deadband_k, heating)


def fit_sigmoid(loop: LoopData) -> SigmoidModel:
    """Our model: two-component logistic fractions on each branch, by least squares on the
    major-loop law; when the data hold partial loops (:func:`partial_loop_runs`), refined along
    the history with the minor-branch law's ``memory_theta``."""
    t, y, h = loop.temperature_c, loop.position_mm, loop.heating
    t_ref = float(t.min())
    span = float(t.max() - t.min())
    mid = 0.5 * (y.max() + y.min())
    # temperatures where each branch crosses mid-stroke
    centres = []
    for curve in (loop.heating_curve_mm, loop.cooling_curve_mm):
        ok = np.isfinite(curve)
        g, c = loop.grid_c[ok], curve[ok]
        k = np.nonzero(np.diff(np.sign(c - mid)) != 0)[0]
        centres.append(float(g[k[0]]) if k.size else float(np.mean(g)))
    th, tc = centres
    cold = t < t_ref + 0.1 * span
    hot = t > t.max() - 0.1 * span
    ym = float(np.median(y[cold]))
    ya = float(np.median(y[hot]))
    w = 0.02 * span
    x0 = [ym, 0.0, ya, 0.0, th, w, th, 5 * w, 0.3, tc, w, tc, 5 * w, 0.3]
    lo_t, hi_t = float(t.min()) - 0.2 * span, float(t.max()) + 0.2 * span
    wmin, wmax = 1e-3 * span, span
    kmax = 10 * loop.stroke_mm / span
    s = loop.stroke_mm
    lo = [y.min() - s, -kmax, y.min() - s, -kmax, lo_t, wmin, lo_t, wmin, 0.0]
    hi = [y.max() + s, kmax, y.max() + s, kmax, hi_t, wmax, hi_t, wmax, 1.0]
    lo += lo[4:9]
    hi += hi[4:9]

    def build(x) -> SigmoidModel:
        return SigmoidModel(
            float(x[0]), float(x[1]), float(x[2]), float(x[3]),
            FractionBranch(*map(float, x[4:9])), FractionBranch(*map(float, x[9:14])), t_ref,
        )  # fmt: skip

    # the major-loop law: every k-th sample will do (a start only when the data hold partial
    # loops, by the data's own common points)
    partial = partial_loop_runs(loop, find_common_points(loop)) is not None
    k = int(math.ceil(t.size / (HISTORY_SAMPLES if partial else MAJOR_FIT_SAMPLES)))

    def major_cost(x) -> float:
        return float(np.sum((build(x).evaluate(t[::k], h[::k]) - y[::k]) ** 2))

    # two starts (sharp and broad transformations): a single start can stall with one branch's
    # fraction held part-way through the data's range (the demo session of issue 24)
    starts = [x0, [*x0[:5], 5 * w, x0[6], 15 * w, 0.5, x0[9], 5 * w, x0[11], 15 * w, 0.5]]
    fits = [_refine(lambda x: build(x).evaluate(t[::k], h[::k]) - y[::k], x_start, lo, hi,
                    "sigmoid model") for x_start in starts]  # fmt: skip
    x = min(fits, key=major_cost)
    runs = partial_loop_runs(loop, build(x))
    if runs is None:
        return build(x)
    major_law = build(x)
    # partial loops in the data. With a well-sampled major loop: the major-loop law again on the
    # samples of its branches only, then the minor-branch law's θ along the whole history (a 1-D
    # search). Without (cycles that never leave the model's transformation tails): every
    # parameter along the history.
    on_major, heating = major_branch_samples(runs, t.size)
    well_sampled = major_loop_of(loop, runs) is not None and on_major.mean() >= MAJOR_SHARE
    if well_sampled:
        sel = np.nonzero(on_major)[0]
        sel = sel[:: int(math.ceil(sel.size / HISTORY_SAMPLES))]
        x = _refine(lambda x: build(x).evaluate(t[sel], heating[sel]) - y[sel], x, lo, hi,
                    "sigmoid model on the major branches")  # fmt: skip
    ts, ys, runs = _history_samples(loop, build(x), runs)

    def build_theta(x, theta: float) -> SigmoidModel:
        m = build(x)
        m.memory_theta = float(theta)
        return m

    def residual(x, theta: float) -> np.ndarray:
        m = build_theta(x, theta)
        return run_history(m, ts, loop.deadband_k, starts_heating(m, ts[0]), runs) - ys

    theta = minimize_scalar(lambda th: float(np.sum(residual(x, th) ** 2)), bounds=THETA_BOUNDS,
                            method="bounded", options={"xatol": 0.05}).x  # fmt: skip
    if not well_sampled:
        x = _refine(lambda z: residual(z[:-1], z[-1]), [*x, theta], lo + [THETA_BOUNDS[0]],
                    hi + [THETA_BOUNDS[1]], "sigmoid model along the history",
                    max_nfev=HISTORY_MAX_NFEV, tol=1e-6)  # fmt: skip
        x, theta = x[:-1], x[-1]
    model = build_theta(x, theta)
    model.fitted_on_history = True
    # the refit along the history must not end worse than the major-loop law it started from,
    # both run along the same history from the state its first samples show
    major_law.fitted_on_history = True
    return min((model, major_law), key=lambda m: _history_cost(m, loop))


def _history_cost(model, loop: LoopData) -> float:
    """Sum of squared errors of ``model`` run along the loop's whole history (as scored)."""
    t = loop.temperature_c
    pred = run_history(model, t, loop.deadband_k, starts_heating(model, float(t[0])))
    err = pred - loop.position_mm
    return float(np.sum(err**2)) if np.all(np.isfinite(err)) else math.inf


def fit_preisach(loop: LoopData):
    """The Preisach-type reference peer, fitted to the same samples."""
    from smabench.physics.preisach import PreisachModel

    try:
        return PreisachModel.fit(loop.temperature_c, loop.position_mm)
    except ValueError as exc:
        raise FitError(f"preisach: {exc}") from exc


MODELS: dict[str, Callable[[LoopData], object]] = {
    "1": fit_model1,
    "2": fit_model2,
    "sigmoid": fit_sigmoid,
    "preisach": fit_preisach,
}


def _nrmse(err: np.ndarray, stroke: float) -> float:
    return float(100.0 * np.sqrt(np.mean(err**2)) / stroke)


def fit_loop(
    temperature_c,
    position_mm,
    model: str = "1",
    *,
    reference_length_mm: float | None = None,
) -> FitResult:
    """Fit ``model`` (a key of :data:`MODELS`) to a measured loop; raises :class:`FitError`."""
    if model not in MODELS:
        raise FitError(f"unknown model {model!r}; choose from {', '.join(MODELS)}")
    loop = prepare_loop(temperature_c, position_mm)
    fitted = MODELS[model](loop)
    result = FitResult(model, {}, 0.0, 0.0, 0.0, loop.temperature_c.size, fitted, loop.deadband_k)
    if hasattr(fitted, "evaluate") and not getattr(fitted, "fitted_on_history", False):
        pred = fitted.evaluate(loop.temperature_c, loop.heating)
    else:
        pred = result.predict(loop.temperature_c)
    err = pred - loop.position_mm
    ref = reference_length_mm if reference_length_mm else loop.stroke_mm
    result.rmse_mm = float(np.sqrt(np.mean(err**2)))
    result.nrmse_percent = _nrmse(err, loop.stroke_mm)
    result.ard_percent = float(100.0 * np.mean(np.abs(err)) / ref)
    params = dict(fitted.parameters())
    if hasattr(fitted, "untuned_nrmse_percent"):
        params["untuned_nrmse_percent"] = fitted.untuned_nrmse_percent
    result.parameters = {k: float(v) for k, v in params.items()}
    log.info("model %s: nrmse %.3f %% of stroke", model, result.nrmse_percent)
    return result


# --------------------------------------------------------------------------- fitted models as data
DOCUMENT_VERSION = 1


def model_document(fit: FitResult) -> dict:
    """A fitted model as JSON-ready data that :func:`fit_from_document` rebuilds exactly."""
    m = fit.loop_model
    if fit.model == "preisach":
        state = {
            "levels_c": m.levels_c.tolist(),
            "weights_mm": m.weights_mm.tolist(),
            "offset_mm": m.offset_mm,
            "slope_mm_per_k": m.slope_mm_per_k,
            "t_ref_c": m.t_ref_c,
            "sign": m.sign,
        }
    else:
        state = asdict(m)
    return {
        "document": "smabench fitted loop model",
        "version": DOCUMENT_VERSION,
        "model": fit.model,
        "deadband_k": fit.deadband_k,
        "state": state,
    }


def fit_from_document(doc: dict) -> FitResult:
    """Rebuild a fitted model from :func:`model_document` data (FitError when it is not one)."""
    from smabench.physics.preisach import PreisachModel

    if not isinstance(doc, dict) or doc.get("document") != "smabench fitted loop model":
        raise FitError("not a fitted model (write one with `smabench fit … --json FILE`)")
    if doc.get("version") != DOCUMENT_VERSION:
        raise FitError(f"fitted-model document version {doc.get('version')!r} is not supported")
    kind, s = doc.get("model"), doc.get("state") or {}
    try:
        if kind == "1":
            m = Model1(**{**s, "cp": CommonPoints(**s["cp"])})
        elif kind == "2":
            m = Model2(**{**s, "cp": CommonPoints(**s["cp"])})
        elif kind == "sigmoid":
            m = SigmoidModel(**{
                **s,
                "heating_branch": FractionBranch(**s["heating_branch"]),
                "cooling_branch": FractionBranch(**s["cooling_branch"]),
            })  # fmt: skip
        elif kind == "preisach":
            arrays = {k: np.asarray(s[k], dtype=float) for k in ("levels_c", "weights_mm")}
            m = PreisachModel(**{**s, **arrays})
        else:
            raise FitError(f"unknown model {kind!r} in the document")
    except (KeyError, TypeError, ValueError) as exc:
        raise FitError(f"broken fitted-model document: {exc}") from None
    return FitResult(str(kind), dict(m.parameters()), math.nan, math.nan, math.nan, 0, m,
                     float(doc.get("deadband_k", 1.0)))  # fmt: skip


def nrmse_on(fit: FitResult, temperature_c, position_mm, scored=None) -> float:
    """nrmse (% of the scored samples' stroke) of the model run along the whole sequence, history
    included, scored on ``scored`` (a boolean mask; all samples when None)."""
    t = np.asarray(temperature_c, dtype=float)
    y = np.asarray(position_mm, dtype=float)
    pred = fit.predict(t)
    mask = np.ones(t.size, bool) if scored is None else np.asarray(scored, bool)
    mask &= np.isfinite(pred) & np.isfinite(y)
    if mask.sum() < 2:
        raise FitError("fewer than 2 samples to score the model on")
    stroke = float(np.ptp(y[mask])) or 1.0
    return _nrmse(pred[mask] - y[mask], stroke)
