"""ASTM E3097 properties of constant-force thermal cycles, from temperature–strain data.

Pure numpy. :func:`split_cycles` finds the thermal cycles, :func:`analyze_cycle` computes one
cycle's properties, :func:`characterize_arrays` does both for a whole record.

**Cycles.** A Schmitt trigger on the temperature (thresholds at 25 % and 75 % of the record's
5–95 % temperature range) marks the hot and cold phases; the coldest sample of each cold phase
is a lower turning point, the hottest of each hot phase an upper one. A cycle is one heating
(lower turning point → upper) followed by one cooling (upper → next lower), so it starts and ends
in martensite; a record that does not reach both thresholds twice has no complete cycle.
Noise smaller than half the trigger band cannot make a false cycle.

**Noisy thermometers.** When the temperature's sample-to-sample noise (robust spread of its
second differences) exceeds 0.3 K, it is smoothed by a centred moving average of up to 5 samples
(no lag on a ramp; a fast transformation may take only ~10 samples, so no more); LCT and UCT are
still the measured extremes at the turning points.

**Tangent lines** (the E3097 construction; how the lines are chosen): each branch is first
averaged over consecutive groups of samples (≈ 60 groups per branch: the branch runs forward in
time, so this averages noise in temperature *and* strain, which binning by temperature does
not when the temperature is noisy). Then, in two passes:

1. the branch's *progress* p ∈ [0, 1] is its strain change relative to the two plateaus (first
   pass: the mean strain of the first and last 10 % of the groups; second pass: the two plateau
   lines fitted in pass 1, so a sloped plateau, thermal expansion, does not bias p);
2. the **martensite line** is a least-squares line ε(T) through the groups with p ≤ 0.05 on the
   cold side of the transformation, the **austenite line** through p ≥ 0.95 on the hot side
   (narrowed to the far 2 %, then 1 %, when that line is steeper than a quarter of the
   transformation line: a plateau still curving, as behind a lagging chamber);
   the **transformation line** is a least-squares line T(ε) through the groups with
   0.25 ≤ p ≤ 0.75 (T on ε because the transformation is steep in T); finally it is refitted
   through the raw samples in that band (at least 8, widening the band to 0.1–0.9 until there
   are, and until its slope has the physical sign: temperature rising from the martensite to
   the austenite strain), because a fast transformation holds only a few groups.
3. As / Af (heating) and Ms / Mf (cooling) are the intersections of the transformation line with
   the martensite and austenite lines.

No model is fitted to the whole branch, so there is nothing that can "go flat" (the failure of
a fitted sigmoid's steepest-point tangent, as in ASMADA): the lines are regressions over data
ranges chosen by progress, and the transformation line uses the central half of the
transformation instead of one steepest point. A plateau with fewer than 3 groups gets a flat
line through what is there (noted), a transformation line with fewer than 2 groups widens its
band to 0.1–0.9; an intersection outside the branch's temperature range (± its span) or out of
order (As > Af), or on a "plateau" steeper than a quarter of the transformation line (the
branch ended inside the transformation: heated or cooled too little), is reported as null with a
note, never guessed; the other end of that branch is still reported.

**Strains** are position / wire length (offset as the sensor's zero; only differences are
physical). Per cycle: actuation strain = ε(end of cooling, LCT) − ε(UCT); heating / cooling
transformation strain = ε(As) − ε(Af) / ε(Mf) − ε(Ms); residual strain = ε(end) − ε(start) of the
cycle (both in martensite at the lower turning points), its running sum is the accumulated
residual strain; the austenite-side residual ε(UCT_k) − ε(UCT_k−1) is given too (ASMADA's
"TRIP strain"). Thermal hysteresis at mid-transformation = the temperature between the heating
and the cooling transformation lines at the mid strain between the martensite and austenite
lines. Spans: Af − As, Ms − Mf and Af − Mf.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

GROUPS_PER_BRANCH = 60
MIN_POINTS_PER_BRANCH = 12
"""A branch with fewer samples cannot give three lines (bad input, not a result)."""
PLATEAU_P = 0.05
TRANSFORMATION_P = (0.25, 0.75)
TRANSFORMATION_P_WIDE = (0.10, 0.90)
PLATEAU_SLOPE_FRACTION = 0.25
"""A plateau line steeper than this fraction of the transformation line is no plateau."""
MIN_TRANSFORMATION_FRACTION = 0.2
"""A branch whose strain change is below this fraction of the record's largest change shows no
transformation (a partial or failed cycle): its temperatures are null."""

TEMPERATURE_KEYS = ("As", "Af", "Ms", "Mf")


class CharacterizeError(ValueError):
    """Input that cannot give any E3097 result (message says why)."""


class NoCompleteCycleError(CharacterizeError):
    """The session holds no complete thermal cycle (an incomplete or aborted step): skipped
    among others, refused alone."""


@dataclass
class Line:
    """``y = a + b·x`` from least squares, with the RMS residual and point count."""

    a: float
    b: float
    rms: float
    n: int

    def __call__(self, x: Any) -> Any:
        return self.a + self.b * np.asarray(x, dtype=float)


@dataclass
class BranchResult:
    """Tangent construction on one branch (``kind`` ``heating`` or ``cooling``)."""

    kind: str
    t_c: np.ndarray  # grouped temperatures, °C
    strain: np.ndarray  # grouped strains
    martensite: Line | None  # strain(T)
    austenite: Line | None  # strain(T)
    transformation: Line | None  # T(strain)
    start: tuple[float, float] | None  # (T, strain) As or Ms
    finish: tuple[float, float] | None  # (T, strain) Af or Mf
    notes: list[str] = field(default_factory=list)


def _fit(x: np.ndarray, y: np.ndarray) -> Line | None:
    """Ordinary least squares y = a + b·x (closed form: this runs six times per cycle)."""
    n = len(x)
    if n == 0:
        return None
    ym = float(y.mean())
    if n == 1:
        return Line(ym, 0.0, 0.0, 1)
    xm = float(x.mean())
    dx = x - xm
    sxx = float(dx @ dx)
    if sxx <= 1e-24:
        return Line(ym, 0.0, float(np.std(y)), n)
    b = float(dx @ (y - ym)) / sxx
    a = ym - b * xm
    r = y - (a + b * x)
    return Line(a, b, float(np.sqrt((r @ r) / n)), n)


def _flat(y: np.ndarray) -> Line:
    return Line(float(np.mean(y)), 0.0, float(np.std(y)), len(y))


def _intersect(plateau: Line, trans: Line) -> tuple[float, float] | None:
    """Plateau ε = a + b·T with transformation T = c + d·ε → (T, ε)."""
    den = 1.0 - plateau.b * trans.b
    if abs(den) < 1e-9:
        return None
    e = (plateau.a + plateau.b * trans.a) / den
    return float(trans(e)), float(e)


def group_means(t_c: np.ndarray, strain: np.ndarray, groups: int = GROUPS_PER_BRANCH):
    """Means over consecutive groups of samples (≈ ``groups`` groups)."""
    n = len(t_c)
    size = max(1, n // groups)
    starts = np.arange(0, n, size)
    counts = np.diff(np.append(starts, n))
    return np.add.reduceat(t_c, starts) / counts, np.add.reduceat(strain, starts) / counts


MIN_RAW_TRANSFORMATION_POINTS = 8


def _raw_transformation(
    t_c: np.ndarray, strain: np.ndarray, cold: Line, hot: Line, change: float
) -> Line | None:
    """T(ε) through the raw samples whose progress is in the central band, widened until it
    holds :data:`MIN_RAW_TRANSFORMATION_POINTS` and its slope has the physical sign (the
    temperature rises from the martensite to the austenite strain); None when no band does."""
    gap = cold(t_c) - hot(t_c)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (cold(t_c) - strain) / gap
    for lo, hi in (TRANSFORMATION_P, (0.2, 0.8), (0.15, 0.85), TRANSFORMATION_P_WIDE):
        idx = np.flatnonzero((p >= lo) & (p <= hi))
        if len(idx) >= MIN_RAW_TRANSFORMATION_POINTS:
            line = _fit(strain[idx], t_c[idx])
            if line is not None and line.b * change < 0:
                return line
    return None


def tangent_branch(t_c: np.ndarray, strain: np.ndarray, kind: str, min_change: float = 0.0):
    """The E3097 tangent construction on one branch in time order (see module docstring).

    Heating runs cold → hot, cooling hot → cold; under a tensile load the wire is longer in
    martensite, but the construction only assumes that the strain changes monotonically
    overall, either way.
    """
    gt, ge = group_means(t_c, strain)
    if kind == "cooling":  # work cold → hot for both branches
        gt, ge = gt[::-1], ge[::-1]
    n = len(gt)
    notes: list[str] = []
    k = max(1, n // 10)
    e_cold, e_hot = float(np.mean(ge[:k])), float(np.mean(ge[-k:]))
    change = e_cold - e_hot
    res = BranchResult(kind, gt if kind == "heating" else gt[::-1],
                       ge if kind == "heating" else ge[::-1], None, None, None, None, None, notes)
    if abs(change) <= max(min_change, 1e-12):
        notes.append(f"{kind}: no transformation (strain change {change:.2e})")
        return res
    cold_line: Line | None = None
    hot_line: Line | None = None
    trans: Line | None = None
    for _ in range(2):
        if cold_line is None or hot_line is None:
            p = (e_cold - ge) / change
        else:
            gap = cold_line(gt) - hot_line(gt)
            gap = np.where(np.abs(gap) < 1e-12 * max(1.0, abs(change)), np.nan, gap)
            p = (cold_line(gt) - ge) / gap
        # the transformation's middle: first group past p = 0.5 (from the cold end)
        over = np.flatnonzero(p >= 0.5)
        mid = int(over[0]) if over.size else n // 2
        cold_idx = np.flatnonzero((p <= PLATEAU_P) & (np.arange(n) < mid))
        hot_idx = np.flatnonzero((p >= 1.0 - PLATEAU_P) & (np.arange(n) >= mid))
        new_cold = _fit(gt[cold_idx], ge[cold_idx]) if len(cold_idx) >= 3 else None
        new_hot = _fit(gt[hot_idx], ge[hot_idx]) if len(hot_idx) >= 3 else None
        if new_cold is None:
            new_cold = _flat(ge[cold_idx] if len(cold_idx) else ge[:1])
        if new_hot is None:
            new_hot = _flat(ge[hot_idx] if len(hot_idx) else ge[-1:])
        cold_line, hot_line = new_cold, new_hot
        lo, hi = TRANSFORMATION_P
        t_idx = np.flatnonzero((p >= lo) & (p <= hi))
        if len(t_idx) < 2:
            lo, hi = TRANSFORMATION_P_WIDE
            t_idx = np.flatnonzero((p >= lo) & (p <= hi))
        if len(t_idx) < 2 and 0 < mid < n:  # one step across: the secant over it
            t_idx = np.array([mid - 1, mid])
        trans = _fit(ge[t_idx], gt[t_idx]) if len(t_idx) >= 2 else None
    # a plateau still curving into the transformation (a lagging chamber, a short dwell):
    # keep only its far end (p within 2 %, then 1 %) when that is flat enough
    if trans is not None and trans.b:
        steep = PLATEAU_SLOPE_FRACTION * abs(1.0 / trans.b)
        for frac in (0.02, 0.01):
            if abs(cold_line.b) > steep:
                idx = np.flatnonzero((p <= frac) & (np.arange(n) < mid))
                line = _fit(gt[idx], ge[idx]) if len(idx) >= 3 else None
                if line is not None and abs(line.b) <= steep:
                    cold_line = line
            if abs(hot_line.b) > steep:
                idx = np.flatnonzero((p >= 1.0 - frac) & (np.arange(n) >= mid))
                line = _fit(gt[idx], ge[idx]) if len(idx) >= 3 else None
                if line is not None and abs(line.b) <= steep:
                    hot_line = line
    # final transformation line from the raw samples in the band (progress against the plateau
    # lines): the groups average noise well on the plateaus, but a fast transformation holds
    # only a few groups, and with a noisy temperature their line can tilt either way
    raw = _raw_transformation(t_c, strain, cold_line, hot_line, change)
    if raw is not None:
        trans = raw
    if cold_line.n < 3:
        notes.append(f"{kind}: short martensite plateau ({cold_line.n} groups): flat line")
    if hot_line.n < 3:
        notes.append(f"{kind}: short austenite plateau ({hot_line.n} groups): flat line")
    res.martensite, res.austenite, res.transformation = cold_line, hot_line, trans
    if trans is None:
        notes.append(f"{kind}: no transformation line")
        return res
    p_cold = _intersect(cold_line, trans)
    p_hot = _intersect(hot_line, trans)
    span = float(gt.max() - gt.min())
    trans_slope = abs(1.0 / trans.b) if trans.b else math.inf  # strain per K
    ok = []
    for name, pt, line in (("martensite", p_cold, cold_line), ("austenite", p_hot, hot_line)):
        if abs(line.b) > PLATEAU_SLOPE_FRACTION * trans_slope:
            # the branch ended inside the transformation (heated or cooled too little):
            # what is left at that end is no plateau, so no intersection there
            notes.append(f"{kind}: no {name} plateau (the branch ends inside the "
                         "transformation)")  # fmt: skip
            ok.append(None)
            continue
        good = pt is not None and gt.min() - span <= pt[0] <= gt.max() + span
        if not good:
            notes.append(f"{kind}: {name} intersection outside the data")
        ok.append(pt if good else None)
    p_cold, p_hot = ok
    if p_cold is not None and p_hot is not None and p_cold[0] > p_hot[0] + 1e-9:
        notes.append(f"{kind}: intersections out of order")
        p_cold = p_hot = None
    if kind == "heating":
        res.start, res.finish = p_cold, p_hot  # As, Af
    else:
        res.start, res.finish = p_hot, p_cold  # Ms, Mf
    return res


# --------------------------------------------------------------------------- cycles
def trigger_levels(t_c: np.ndarray) -> tuple[float, float] | None:
    """The Schmitt trigger's (low, high) temperatures: 25 % / 75 % of the 5–95 % range."""
    t_c = np.asarray(t_c, dtype=float)
    if len(t_c) < 3:
        return None
    p5, p95 = np.percentile(t_c, [5, 95])
    rng = p95 - p5
    if not rng > 0:
        return None
    return float(p5 + 0.25 * rng), float(p95 - 0.25 * rng)


def split_cycles(
    t_c: np.ndarray, levels: tuple[float, float] | None = None
) -> list[tuple[int, int, int]]:
    """Complete thermal cycles as index triples (start, top, end): heating start → top, cooling
    top → end (``end`` is the next cycle's ``start``). Indices into ``t_c`` (no NaN)."""
    t_c = np.asarray(t_c, dtype=float)
    levels = levels or trigger_levels(t_c)
    if levels is None or len(t_c) < 3:
        return []
    lo, hi = levels
    s = np.where(t_c > hi, 1, np.where(t_c < lo, -1, 0))
    idx = np.where(s != 0, np.arange(len(s)), 0)
    np.maximum.accumulate(idx, out=idx)
    state = s[idx]
    state[s[idx] == 0] = 0  # before the first threshold crossing: unknown
    change = np.flatnonzero(np.diff(state) != 0) + 1
    bounds = [0, *change.tolist(), len(t_c)]
    turning: list[tuple[int, int]] = []  # (state, index of extreme)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        st = int(state[a])
        if st == 0:
            continue
        seg = t_c[a:b]
        i = a + int(np.argmax(seg) if st > 0 else np.argmin(seg))
        if turning and turning[-1][0] == st:  # same phase again (unknown gap): keep the extreme
            j = turning[-1][1]
            if (st > 0 and t_c[i] > t_c[j]) or (st < 0 and t_c[i] < t_c[j]):
                turning[-1] = (st, i)
            continue
        turning.append((st, i))
    # a record that starts cold but before the lower threshold is crossed: its first sample
    # belongs to the first cold phase (extend that phase back to the start)
    if turning and turning[0][0] < 0 and state[0] == 0:
        first_cold = bounds[1] if len(bounds) > 1 else 0
        i0 = int(np.argmin(t_c[: max(first_cold, turning[0][1] + 1)]))
        if t_c[i0] <= t_c[turning[0][1]]:
            turning[0] = (-1, i0)
    cycles = []
    for k in range(len(turning) - 2):
        (s0, i0), (s1, i1), (s2, i2) = turning[k], turning[k + 1], turning[k + 2]
        if s0 < 0 < s1 and s2 < 0:
            cycles.append((i0, i1, i2))
    return cycles


def _nan_to_none(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def analyze_cycle(
    t_c: np.ndarray,
    strain: np.ndarray,
    bounds: tuple[int, int, int],
    min_change: float = 0.0,
    t_raw: np.ndarray | None = None,
    half_window: int = 0,
) -> tuple[dict[str, Any], BranchResult, BranchResult]:
    """One cycle's properties (keys as in the JSON; None where not determined). ``t_c`` may be
    smoothed (``half_window`` samples each side); LCT and UCT then come from ``t_raw``, the
    measured extreme within that window of the turning point, as E3097 reports them."""
    i0, i1, i2 = bounds
    heat = tangent_branch(t_c[i0 : i1 + 1], strain[i0 : i1 + 1], "heating", min_change)
    cool = tangent_branch(t_c[i1 : i2 + 1], strain[i1 : i2 + 1], "cooling", min_change)
    # values at the turning points: means over a window centred on them (half a group each
    # side), the same window for a cycle's end and the next one's start, so that the residual
    # strains add up exactly to the change over the record
    w = max(0, min(i1 - i0, i2 - i1) // GROUPS_PER_BRANCH // 2)

    def at(x: np.ndarray, i: int) -> float:
        return float(np.mean(x[max(0, i - w) : i + w + 1]))

    e_start, e_top, e_end = at(strain, i0), at(strain, i1), at(strain, i2)

    def extreme(i: int, pick) -> float:
        if t_raw is None or half_window < 1:
            return at(t_c, i)
        return float(pick(t_raw[max(0, i - half_window) : i + half_window + 1]))
    As = heat.start[0] if heat.start else math.nan
    Af = heat.finish[0] if heat.finish else math.nan
    Ms = cool.start[0] if cool.start else math.nan
    Mf = cool.finish[0] if cool.finish else math.nan
    eAs = heat.start[1] if heat.start else math.nan
    eAf = heat.finish[1] if heat.finish else math.nan
    eMs = cool.start[1] if cool.start else math.nan
    eMf = cool.finish[1] if cool.finish else math.nan
    hyst = math.nan
    if heat.transformation and cool.transformation and all(
        math.isfinite(v) for v in (eAs, eAf, eMs, eMf)
    ):
        e_mid = 0.25 * (eAs + eAf + eMs + eMf)
        hyst = float(heat.transformation(e_mid) - cool.transformation(e_mid))
    props = {
        "LCT_C": extreme(i0, np.min),
        "UCT_C": extreme(i1, np.max),
        "LCT_end_C": extreme(i2, np.min),
        "As_C": As,
        "Af_C": Af,
        "Ms_C": Ms,
        "Mf_C": Mf,
        "As_strain": eAs,
        "Af_strain": eAf,
        "Ms_strain": eMs,
        "Mf_strain": eMf,
        "strain_start": e_start,
        "strain_UCT": e_top,
        "strain_end": e_end,
        "actuation_strain": e_end - e_top,
        "heating_transformation_strain": eAs - eAf,
        "cooling_transformation_strain": eMf - eMs,
        "residual_strain": e_end - e_start,
        "hysteresis_K": hyst,
        "heating_span_K": Af - As,
        "cooling_span_K": Ms - Mf,
        "transformation_span_K": Af - Mf,
        "temperature_uncertainty_K": float(
            np.sqrt(np.mean([ln.rms**2 for ln in (heat.transformation, cool.transformation)
                             if ln is not None] or [math.nan]))
        ),
    }
    out = {k: (_nan_to_none(v) if isinstance(v, float) else v) for k, v in props.items()}
    out["notes"] = heat.notes + cool.notes
    return out, heat, cool


NOISE_SMOOTH_K = 0.3
MAX_SMOOTH_HALF = 2  # at most 5 samples: a fast transformation may take only ~10
"""Temperature noise (K, from second differences) above which the temperature is smoothed."""


def temperature_noise_k(t_c: np.ndarray) -> float:
    """Sample-to-sample noise of a temperature record, K: the robust spread of its second
    differences (1.4826 · MAD / √6), blind to smooth ramps."""
    if len(t_c) < 5:
        return 0.0
    d2 = np.diff(t_c, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def smooth_window(noise_k: float) -> int:
    """Centred moving-average length (odd) that brings ``noise_k`` to about NOISE_SMOOTH_K."""
    if noise_k <= NOISE_SMOOTH_K:
        return 1
    half = int(np.clip(round((noise_k / NOISE_SMOOTH_K) ** 2 / 2), 1, MAX_SMOOTH_HALF))
    return 2 * half + 1


def smooth(t_c: np.ndarray, window: int) -> np.ndarray:
    """Centred moving average (edges: the window shrinks), no lag on a linear ramp."""
    if window <= 1 or len(t_c) < window:
        return t_c
    c = np.concatenate([[0.0], np.cumsum(t_c)])
    h = window // 2
    i = np.arange(len(t_c))
    lo, hi = np.maximum(0, i - h), np.minimum(len(t_c), i + h + 1)
    return (c[hi] - c[lo]) / (hi - lo)


class CycleStream:
    """E3097 over a record fed in pieces (chunk files): memory is that of one piece plus the
    unfinished cycle carried to the next. The trigger levels and the 'no transformation' floor
    come from the first piece that has complete cycles."""

    def __init__(self, keep_branches: set[int] | str | None = None) -> None:
        """``keep_branches``: cycle numbers whose tangent construction is kept for plots, or
        ``"auto"``: the first, a middle one and the last (bounded memory)."""
        self.auto = keep_branches == "auto"
        self.keep = set() if self.auto or not keep_branches else set(keep_branches)
        self._last: tuple[int, tuple[BranchResult, BranchResult]] | None = None
        self.cycles: list[dict[str, Any]] = []
        self.kept: dict[int, tuple[BranchResult, BranchResult]] = {}
        self.levels: tuple[float, float] | None = None
        self.min_change: float | None = None
        self.short = 0
        self._k = 0
        self._acc = 0.0
        self._prev_top: float | None = None
        self._carry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.window: int | None = None  # temperature smoothing, samples (1: none)
        self.noise_k = 0.0

    def feed(self, t_c: np.ndarray, strain: np.ndarray, t_s: np.ndarray, final: bool) -> None:
        t_c, strain, t_s = (np.asarray(x, dtype=float) for x in (t_c, strain, t_s))
        ok = np.isfinite(t_c) & np.isfinite(strain) & np.isfinite(t_s)
        t_c, strain, t_s = t_c[ok], strain[ok], t_s[ok]
        if self._carry is not None:
            t_c, strain, t_s = (np.concatenate([c, x]) for c, x in zip(self._carry,
                                                                       (t_c, strain, t_s),
                                                                       strict=True))
            self._carry = None
        if self.window is None:  # from the first piece: noisy thermocouples are smoothed
            self.noise_k = temperature_noise_k(t_c)
            self.window = smooth_window(self.noise_k)
        t_raw, t_c = t_c, smooth(t_c, self.window)
        levels = self.levels or trigger_levels(t_c)
        bounds = split_cycles(t_c, levels)
        if not final:
            if len(bounds) <= 1:  # nothing closed yet: carry all
                self._carry = (t_raw, strain, t_s)
                return
            last = bounds.pop()
            self._carry = (t_raw[last[0]:], strain[last[0]:], t_s[last[0]:])
        if not bounds:
            return
        if self.levels is None:
            self.levels = levels
            changes = [abs(float(strain[a] - strain[b])) for a, b, _ in bounds]
            self.min_change = MIN_TRANSFORMATION_FRACTION * max(changes) * 0.5
        for b in bounds:
            self._k += 1
            k = self._k
            if min(b[1] - b[0] + 1, b[2] - b[1] + 1) < MIN_POINTS_PER_BRANCH:
                self.short += 1
                log.info("cycle %d skipped: too few points per branch", k)
                continue
            props, heat, cool = analyze_cycle(t_c, strain, b, self.min_change or 0.0,
                                              t_raw, (self.window or 1) // 2)  # fmt: skip
            self._acc += props["residual_strain"] or 0.0
            row: dict[str, Any] = {"cycle": k, "t_start_s": float(t_s[b[0]]),
                                   "t_end_s": float(t_s[b[2]])}
            row.update(props)
            row["accumulated_residual_strain"] = self._acc
            top = props["strain_UCT"]
            prev = self._prev_top
            row["residual_strain_austenite"] = None if prev is None else top - prev
            self._prev_top = top
            self.cycles.append(row)
            if k in self.keep or (self.auto and k & (k - 1) == 0):  # auto: powers of two
                self.kept[k] = (heat, cool)
            if self.auto:
                self._last = (k, (heat, cool))

    def result(self):
        """(cycles, kept branches); :class:`CharacterizeError` when there is nothing to report."""
        if not self._k:
            raise NoCompleteCycleError(
                "no complete thermal cycle (heating then cooling across the temperature range)"
            )
        if not self.cycles:
            raise CharacterizeError(
                f"too few points per branch (fewer than {MIN_POINTS_PER_BRANCH} samples in every "
                "heating or cooling branch)"
            )
        if self.auto and self._last is not None:
            last = self._last[0]
            middle = max((k for k in self.kept if k <= (last + 1) // 2), default=1)
            self.kept = {k: v for k, v in self.kept.items() if k in (1, middle)}
            self.kept[last] = self._last[1]
        return self.cycles, self.kept


def characterize_arrays(
    t_c: np.ndarray,
    strain: np.ndarray,
    t_s: np.ndarray | None = None,
    keep_branches: set[int] | None = None,
) -> tuple[list[dict[str, Any]], dict[int, tuple[BranchResult, BranchResult]]]:
    """Split a record into cycles and analyse each. Returns (cycles, branches kept for plots).

    Raises :class:`CharacterizeError` when there is no complete cycle or every branch has fewer
    than :data:`MIN_POINTS_PER_BRANCH` samples.
    """
    t_c = np.asarray(t_c, dtype=float)
    if t_s is None:
        t_s = np.arange(len(t_c), dtype=float)
    stream = CycleStream(keep_branches)
    stream.feed(t_c, strain, t_s, final=True)
    return stream.result()
