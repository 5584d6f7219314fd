"""Discrepancy analysis: baseline fit, held-out simulation, candidate extensions, the verdict.

Protocol (see ``docs/analysis-flexinol.md`` for a worked example):

1. Folds: blocked cross-validation. Every session's cycles form three contiguous blocks (a
   session with fewer cycles: thirds of its samples). One or two loads: three folds, each
   holds one block out of every session and trains on the other two (with two loads, leaving
   a whole load out would leave no stress slope to learn; two single-loop sessions get six
   folds, one load's third at a time). Three loads or more: leave one load
   out entirely (the held-out sessions only get their sensor zero from their first samples).
   Every cycle is held out once.
2. Every model (the baseline and each candidate extension) is fitted by ``least_squares`` on the
   training part and then simulated from the input alone (current, or measured temperature) over
   the whole session; the held-out error is taken on the held-out samples. Candidates start from
   the baseline's fit and, for the coupled ones, also from fresh starts found from the data.
   Parameter uncertainties are cluster-robust (the training cycles are the clusters).
3. Verdict: per held-out unit (the heating and the cooling branch of every held-out cycle, split
   into blocks when there are fewer than 16) the RMSE of the baseline and of each extension; a
   one-sided paired test across the units (Wilcoxon signed-rank and a log-ratio t-test,
   Bonferroni) and a minimum gain decide whether an extension removes structure. ``none`` when
   none does and the baseline is within its floor (noise, accuracy, and what the current's
   switching instants, known to a sample, alone would cost: :func:`structure`), or when the
   wire's own rate-dependent kinetics bring it there (:data:`RATE_KINETICS`); ``unexplained``
   when structure remains that no candidate removes, or when the best two candidates cannot be
   told apart.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, replace

import numba
import numpy as np
from scipy.optimize import least_squares
from scipy.stats import ttest_1samp, wilcoxon
from threadpoolctl import threadpool_limits

from smabench.analysis.candidates import (
    BASELINE,
    CANDIDATES,
    COUPLED,
    CP_J_KGK,
    PARAMS,
    REGISTRY,
    cause_text,
    members,
    unit_of,
)
from smabench.analysis.data import AnalysisError, SessionData, make_grid
from smabench.analysis.model import (
    LINEAR,
    Grid,
    Temps,
    directions,
    fill_pointwise,
    first_order_lag,
    pointwise,
    residual_strain,
    simulate,
    temperature,
    wire_key,
    wire_state,
)

log = logging.getLogger(__name__)

ALPHA = 0.01
"""Significance level of the one-sided paired test (extension better than the baseline)."""
MIN_GAIN = 0.15
"""An extension must cut the held-out RMSE by at least this fraction to be named."""
SEPARATION = 2.0
"""The runner-up's held-out RMSE must be at least this × the winner's (or lose a paired test
against it at ALPHA_SEPARATION) for the winner to be named; otherwise ``unexplained``. A ratio
of remaining errors, not of gains: 95 % against 90 % gain is a factor 2 in what is left."""
ALPHA_SEPARATION = 0.05
"""Level of the second-stage test between the two best candidates. Both already beat the
baseline at ALPHA; which of two physical extensions fits the held-out data better is a choice
between named alternatives, judged at the conventional 5 %."""
FLOOR_NOISE = 3.0
FLOOR_STROKE = 0.005
"""The baseline leaves structure when its held-out RMSE exceeds both FLOOR_NOISE × the sensor
noise and FLOOR_STROKE × the stroke (half the paper's loop-model accuracy of about 1 %)."""
STRUCTURED_QUANTILE = 75.0
"""The baseline leaves structure when its pooled held-out RMSE and this percentile of its
per-unit RMSEs both exceed the floor."""
SWITCH_RMS = 1.0 / math.sqrt(3.0)
"""The recorded current changes at a sample; the wire's current changed at some instant of the
sample interval before it. The model takes the late end: with the instant uniform over the
interval, its error is u·D (u uniform on 0…1, D the change of the prediction when every switch
moves one sample earlier), whose RMS is D/√3. Sharp transformations make D large (seen: 0.3 mm
at the onsets of the third simulator's Tanaka kinetics sampled at 50 Hz)."""
TIE_NOISE = 1.25
"""A held-out unit where two models both stay below this × the sensor noise is a tie."""
FIT_DT_MIN = 0.05
"""Step of the fitting grid, s (or the sample step when longer): fine enough for the heat
balance and the transformation kinetics whatever the session's length."""
FIT_POINTS_MAX = 15000
"""Most training residuals per fit: a longer training part keeps whole cycles evenly spread
over it (every k-th cycle; the simulation still runs through all of them)."""

_BASE_NAMES = frozenset(p.name for p in BASELINE)


SHAPE_STARTS = ((-0.8, -0.8), (-0.8, 0.8), (0.8, -0.8), (0.8, 0.8), (0.0, 0.0))
"""Branch shapes (h_shape, c_shape) the baseline fit starts from (Tanaka-like, logistic,
cosine), each for SCREEN_NFEV evaluations before the full fit from the best."""
SCREEN_NFEV = 12
FIT_TOL = 1e-5
"""ftol and xtol of every least_squares fit: a relative change of the training cost below 1e-5
is far below anything the held-out test can see (at 1e-7 the fits crawled on for a fifth more
evaluations; the verdicts of every analysis test are the same at both)."""
TAU_STARTS = 2
"""The baseline's shape screens start from the best this many thermal time constants of
:func:`_start`: a short τ with the transformation temperatures squeezed towards the room's can
fit the first samples better and then hold the fit in its own basin (seen: one fold of a
nominal 1 kg mock session, τ 1.5 s against 4.3 s, 1.2 × the training error and 20 × the
held-out error of the other folds)."""
KEEP_STARTS = 2
"""Full fits from this many of a model's starts, the best after SCREEN_NFEV evaluations (on
the independent simulator the eventual best was among the two best screened in 85 of 94
multi-start fits, and the train cost lost in the others stayed below 0.5 %; keeping one lost
``latent_heat`` in the third simulator's stress + latent heat case)."""

@dataclass
class Fold:
    name: str
    train: dict[str, np.ndarray]  # session name → bool mask over its samples
    test: dict[str, np.ndarray]


@dataclass
class FitResult:
    model: str
    names: list[str]
    x: np.ndarray
    cov: np.ndarray  # covariance of x, physical units
    se: np.ndarray
    values: dict[str, float]
    linear: dict[str, float]
    offsets: dict[str, float]
    train_rmse_mm: float
    nfev: int
    seconds: float


@dataclass
class Problem:
    sessions: list[SessionData]
    sigma_ref: float
    multi_load: bool
    candidates: list[str]
    skipped: dict[str, str]
    fit_grids: dict[str, tuple[Grid, np.ndarray]] = field(default_factory=dict)
    full_grids: dict[str, tuple[Grid, np.ndarray]] = field(default_factory=dict)


# --------------------------------------------------------------------------- set-up
def stress_groups(sessions: list[SessionData]) -> list[float]:
    """Distinct stresses, MPa (within 5 % of each other count as one load)."""
    out: list[float] = []
    for s in sorted(x.stress_mpa for x in sessions if x.stress_mpa is not None):
        if not out or abs(s - out[-1]) > 0.05 * max(abs(out[-1]), 1.0):
            out.append(s)
    return out


def make_problem(sessions: list[SessionData], requested: list[str] | None = None) -> Problem:
    kinds = {s.kind for s in sessions}
    if len(sessions) > 1 and any(s.stress_mpa is None for s in sessions):
        missing = [s.name for s in sessions if s.stress_mpa is None]
        raise AnalysisError(
            f"several sessions need their loads: no load_kg for {', '.join(missing)} "
            "(session.json, a stress_MPa column or --load-kg)"
        )
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        for i, s in enumerate(sessions):
            s.name = f"{i}:{s.name}"
    loads = stress_groups(sessions)
    multi = len(loads) >= 2
    stresses = [s.stress_mpa or 0.0 for s in sessions]
    sigma_ref = float(np.mean(stresses)) if stresses else 0.0
    skipped: dict[str, str] = {}
    most_cycles = max(s.n_complete for s in sessions)
    for c in CANDIDATES:
        needs = REGISTRY[c].needs
        if needs == "loads" and not multi:
            skipped[c] = "needs sessions at two loads or more"
        elif needs == "heat_balance" and "current" not in kinds:
            skipped[c] = "needs a heat balance (current-driven sessions); thermometer loops only"
        elif needs == "cycles" and most_cycles < REGISTRY[c].min_cycles:
            skipped[c] = (f"needs {REGISTRY[c].min_cycles} complete cycles in one session or "
                          f"more (most here: {most_cycles})")  # fmt: skip
    if requested:
        unknown = [c for c in requested if c not in CANDIDATES]
        if unknown:
            raise AnalysisError(
                f"unknown candidate(s) {', '.join(unknown)}; known: {', '.join(CANDIDATES)}"
            )
        for c in requested:
            if c in skipped:
                if c == "stress_shift":
                    raise AnalysisError(
                        f"stress_shift asked for, but all sessions are at one load "
                        f"({loads[0] if loads else 'unknown'} MPa): a stress question needs "
                        "sessions at two loads or more"
                    )
                raise AnalysisError(f"{c} asked for, but it {skipped[c]}")
        cands = list(requested)
    else:
        cands = [c for c in CANDIDATES if c not in skipped]
    prob = Problem(list(sessions), sigma_ref, multi, cands, skipped)
    for s in sessions:
        stress = s.stress_mpa if s.stress_mpa is not None else sigma_ref
        if s.kind == "current":
            dt_med = float(np.median(np.diff(s.t)))
            dt_fit = max(dt_med, FIT_DT_MIN)
            prob.fit_grids[s.name] = make_grid(s, dt_fit, stress)
            prob.full_grids[s.name] = make_grid(s, None, stress)
        else:
            g = make_grid(s, None, stress)
            prob.fit_grids[s.name] = g
            prob.full_grids[s.name] = g
    return prob


N_BLOCKS = 3
"""Blocked cross-validation: each session's cycles fall into this many contiguous blocks, and
every block is held out once (so every cycle gives held-out evidence, but see
:data:`TRAINING_ONLY`)."""

TRAINING_ONLY = -1
"""Block of the first cycle when the later cycles fill :data:`N_BLOCKS` on their own: it trains
every fold and is held out in none. It alone starts from the room's temperature (a colder
start, a lower peak); a fold without it extrapolates the end of the heating branch from the
warm cycles' range. Seen on a latent-heat recording made by CI: the fold holding cycles 0-1
out mispredicted the first cycle by 86-152 µm with the latent heat (0.02-0.08 mm without), the
other folds' units fell from 8-21 µm to 2-11 µm, and the cause was missed (``unexplained``);
two nominal 4-cycle recordings came out ``ambient_drift`` (baseline held-out 0.13 and 0.32
mm). With the first cycle training only: ``latent_heat`` and ``none`` (0.018, 0.022 mm)."""


def _blocks(s: SessionData) -> np.ndarray:
    """Block of every sample: :data:`TRAINING_ONLY` for the first cycle when N_BLOCKS or more
    follow it, then 0 … N_BLOCKS-1, contiguous groups of whole cycles (fewer cycles: every
    cycle in a block of its own from the first; fewer cycles than blocks: contiguous thirds of
    its samples)."""
    ids = np.unique(s.cycle)
    if len(ids) > N_BLOCKS:
        warm = len(ids) - 1
        block_of_id = np.concatenate([[TRAINING_ONLY], (np.arange(warm) * N_BLOCKS) // warm])
        return block_of_id[np.searchsorted(ids, s.cycle)]
    if len(ids) == N_BLOCKS:
        return np.searchsorted(ids, s.cycle)
    n = len(s.t)
    return (np.arange(n) * N_BLOCKS) // n


def make_folds(prob: Problem) -> list[Fold]:
    """One or two loads: one fold per block, held out in every session (two single-loop
    sessions: in one session at a time), trained on the rest (of both loads: a stress slope
    needs both). Three loads or more: leave one load out."""
    sessions = prob.sessions
    loads = stress_groups(sessions)
    blocks = {s.name: _blocks(s) for s in sessions}

    def group(s):
        if s.stress_mpa is None:
            return 0
        return int(np.argmin([abs(s.stress_mpa - x) for x in loads]))

    folds = []
    if len(loads) >= 3:
        for li, load in enumerate(loads):
            test = {s.name: (group(s) == li) & s.valid for s in sessions}
            train = {s.name: (group(s) != li) & s.valid for s in sessions}
            folds.append(Fold(f"load {load:.0f} MPa held out", train, test))
        return folds
    whole_cycles = all(len(np.unique(s.cycle)) >= N_BLOCKS for s in sessions)
    # blocks of whole cycles: one block of every session at once; blocks inside a single loop
    # (thermometer loops): one load at a time, so that the other load's same part of the loop
    # trains (the same third missing from both loops would leave that part unseen)
    per_load = len(loads) == 2 and not whole_cycles
    for li, load in enumerate(loads if per_load else [None]):
        for b in range(N_BLOCKS):
            test = {
                s.name: (blocks[s.name] == b) & (not per_load or group(s) == li)
                for s in sessions
            }
            train = {s.name: ~test[s.name] & s.valid for s in sessions}
            test = {s.name: test[s.name] & s.valid for s in sessions}
            where = f"load {load:.0f} MPa, " if per_load else ""
            folds.append(Fold(f"{where}block {b + 1}/{N_BLOCKS} held out", train, test))
    return folds


# --------------------------------------------------------------------------- fitting
def _spec(prob: Problem, model: str) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray,
                                              np.ndarray]:  # fmt: skip
    """Names, scales, bounds and starts of ``model``'s parameters ("baseline", a candidate, or
    candidates joined by "+"), all from the registry."""
    kinds = {s.kind for s in prob.sessions}
    names = []
    if "current" in kinds:
        names += ["tau_s"]
    names += ["h_mid", "h_w", "hyst_k", "c_w", "h_shape", "c_shape", "memory"]
    if "current" in kinds:
        names += ["heat_lag_ratio", "tau_cool_s"]
        if RATE_KINETICS in model.split("+"):
            names += ["rate_shift_k"]
    n_loads = len(stress_groups(prob.sessions))
    if n_loads >= 3 or (n_loads == 2 and all(len(np.unique(s.cycle)) >= 3 for s in prob.sessions)):
        # loops narrow under load (paper Fig. 11). Two loads: learnt when the training part
        # holds complete cycles of both (three cycles or more per session); a single loop per
        # load (thermometer loops) loses part of a branch to the held-out third, and narrowing
        # and a common shift could not both be learnt from the rest: width fixed then
        names += ["shrink_k_per_mpa"]
    most_cycles = max(s.n_complete for s in prob.sessions)
    rival = KINETIC_RIVAL in model.split("+")  # alone, or on top of causes named before
    if rival:
        names += ["xi_delay_s"]
    for c in members(model):
        cand = REGISTRY[c]
        names += [n for n in cand.param_names
                  if not (n in cand.many_cycles and most_cycles < 20)]  # fmt: skip
    table = [PARAMS[n] for n in names]
    scale = np.array([p.scale for p in table])
    lo = np.array([p.lo for p in table])
    hi = np.array([p.hi for p in table])
    start = np.array([p.start for p in table])
    if rival and "heat_lag_ratio" in names:
        hi[names.index("heat_lag_ratio")] = KINETIC_RIVAL_RATIO
    return names, scale, lo, hi, start


KINETIC_RIVAL = "kinetic_lag"
"""Not a cause: the baseline with lags of ξ allowed up to KINETIC_RIVAL_RATIO × as long on
heating as on cooling and a dead time of ξ (``xi_delay_s``: rate-dependent nucleation moves the
transformation by about delay × dT/dt). ``sensor_lag`` is named only when it beats this rival
too: a sensor delays everything (thermal expansion, rests), kinetics only the transformation."""
KINETIC_RIVAL_RATIO = 2.0

RATE_KINETICS = "rate_kinetics"
"""Not a cause: the baseline whose transformation starts later the faster the temperature
moves (``rate_shift_k``: thermally activated nucleation, see ``model``). The candidates are
tested against the baseline without it, as its delay of the transformation takes up a sensor's
(on the independent simulator, with it in the baseline, sensor lags were found 3 times in 10,
without it 10 in 10). When no candidate is named and the baseline leaves structure, the verdict
is ``none`` if this generalisation of the wire's own kinetics brings the held-out error within
the floor (the same test as the baseline's): the structure was the wire's kinetics, not a hidden
effect (seen: Tanaka kinetics whose nucleation waits κ·√|dT/dt|, on the third simulator)."""


def _obs_on_grid(pos: np.ndarray, idx: np.ndarray, mask: np.ndarray, m: int):
    """Mean observed position per grid point over the masked samples; NaN where none."""
    cnt = np.bincount(idx[mask], minlength=m)
    tot = np.bincount(idx[mask], weights=pos[mask], minlength=m)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = tot / cnt
    return out, cnt


class _Objective:
    """Training residuals of one model on one fold (position on the fitting grid, mm), linear
    parameters projected out; ``clusters`` holds the branch of every residual."""

    def __init__(self, prob: Problem, fold: Fold, names: list[str], scale: np.ndarray) -> None:
        self.prob = prob
        self.names = names
        self.scale = scale
        self.items = []
        clusters = []
        for s in prob.sessions:
            mask = fold.train[s.name]
            if not mask.any():
                continue
            g, idx = prob.fit_grids[s.name]
            obs, cnt = _obs_on_grid(s.pos, idx, mask, len(g.t))
            branch = np.zeros(len(g.t), dtype=np.int64)
            branch[idx[mask]] = branch_ids(s)[mask]
            sel = np.flatnonzero(cnt > 0)
            per_session = FIT_POINTS_MAX // max(1, len(prob.sessions))
            if len(sel) > per_session:  # every k-th training cycle
                cyc = branch[sel] // 2
                ids = np.unique(cyc)
                k_step = int(math.ceil(len(sel) / per_session))
                sel = sel[np.isin(cyc, ids[::k_step])]
            k = len(self.items)
            if len(sel):  # nothing after the last training point is needed
                g = g.head(int(sel[-1]) + 1)
            self.items.append((s, g, sel, obs[sel]))
            clusters.append(k * 1_000_000 + branch[sel])
        self.clusters = np.concatenate([*clusters, np.zeros(0, dtype=np.int64)])
        self.fixed = {"sigma_ref": prob.sigma_ref}
        self.nfev = 0
        self.last_linear: dict[str, float] = {}
        self.last_offsets: dict[str, float] = {}
        # the residuals' rows of every session (each has its own sensor zero)
        self.rows = np.cumsum([0] + [len(it[2]) for it in self.items]).astype(np.int64)
        # wire states by their inputs: a finite-difference step in a parameter that acts after
        # the wire (sensor lag, residual strain) reuses the state of the point it steps from
        self.states: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def params(self, z: np.ndarray) -> dict[str, float]:
        p = dict(self.fixed)
        p.update(zip(self.names, (float(v) for v in z * self.scale), strict=True))
        return p

    STATES_KEPT = 32
    """Wire states remembered (more than one finite-difference Jacobian's worth of steps)."""

    def __call__(self, z: np.ndarray) -> np.ndarray:
        self.nfev += 1
        p = self.params(z)
        n_s = len(self.items)
        basis = np.empty((int(self.rows[-1]), len(LINEAR)))
        y = np.empty(len(basis))
        key = wire_key(p)
        fast = pointwise(p)
        for k, (_s, g, sel, obs) in enumerate(self.items):
            state = self.states.get((k, key))
            if state is None:
                state = wire_state(g, p)
                if len(self.states) >= self.STATES_KEPT * n_s:
                    del self.states[next(iter(self.states))]
                self.states[(k, key)] = state
            a, b = self.rows[k], self.rows[k + 1]
            if fast:
                fill_pointwise(g, p, state, sel, obs, basis, y, a)
                continue
            sim = simulate(g, p, state, at=sel)
            basis[a:b] = sim.basis
            y[a:b] = obs - sim.fixed
        r, coef, offsets = _project(basis, y, self.rows)
        if not np.all(np.isfinite(r)):
            return np.full_like(r, 1e3)
        self.last_offsets = {it[0].name: float(offsets[k]) for k, it in enumerate(self.items)}
        self.last_linear = {n: float(c) for n, c in zip(LINEAR, coef, strict=True)}
        return r


PINV_RCOND = 1e-13
"""A basis column whose part not explained by the columns already taken is below this (squared
sine of its angle to them) is left out of the linear solve (constant columns, columns that
repeat one another: ξ ≡ 1 where the wire never transforms)."""


@numba.njit(cache=True, error_model="numpy")
def _project(basis: np.ndarray, y: np.ndarray, rows: np.ndarray):
    """Least squares of ``y`` on one offset per block of rows (``rows[s]:rows[s+1]``, a
    session's sensor zero) and the four ``basis`` columns (:data:`LINEAR`): (residuals, basis
    coefficients, offsets).

    The offsets are projected out by centring every block; the basis columns are solved by
    their normal equations (:func:`_solve_sym`) with one step of iterative refinement. The
    residuals agree with ``numpy.linalg.lstsq`` of the whole design matrix to 3e-11 mm (a
    Householder QR agrees with these to 3e-14 mm, with lstsq to 7e-12 mm) at a third of its
    cost: this is the inner loop of every fit. The four columns are spelt out in local scalars:
    accumulators kept in arrays are carried through memory and cost three times more."""
    n = basis.shape[0]
    n_s = len(rows) - 1
    mean_b = np.zeros((n_s, 4))
    mean_y = np.zeros(n_s)
    g00 = g01 = g02 = g03 = g11 = g12 = g13 = g22 = g23 = g33 = h0 = h1 = h2 = h3 = 0.0
    for s in range(n_s):
        a, b = rows[s], rows[s + 1]
        if b <= a:
            continue
        m0 = m1 = m2 = m3 = my = 0.0
        for i in range(a, b):
            m0 += basis[i, 0]
            m1 += basis[i, 1]
            m2 += basis[i, 2]
            m3 += basis[i, 3]
            my += y[i]
        k = 1.0 / (b - a)
        m0, m1, m2, m3, my = m0 * k, m1 * k, m2 * k, m3 * k, my * k
        mean_b[s, 0], mean_b[s, 1], mean_b[s, 2], mean_b[s, 3], mean_y[s] = m0, m1, m2, m3, my
        for i in range(a, b):  # centred on the fly: no n × 4 temporary
            x0 = basis[i, 0] - m0
            x1 = basis[i, 1] - m1
            x2 = basis[i, 2] - m2
            x3 = basis[i, 3] - m3
            e = y[i] - my
            g00 += x0 * x0
            g01 += x0 * x1
            g02 += x0 * x2
            g03 += x0 * x3
            g11 += x1 * x1
            g12 += x1 * x2
            g13 += x1 * x3
            g22 += x2 * x2
            g23 += x2 * x3
            g33 += x3 * x3
            h0 += x0 * e
            h1 += x1 * e
            h2 += x2 * e
            h3 += x3 * e
    gram = np.array([[g00, g01, g02, g03],
                     [g01, g11, g12, g13],
                     [g02, g12, g22, g23],
                     [g03, g13, g23, g33]])
    coef = _solve_sym(gram, np.array([h0, h1, h2, h3]))
    r = np.empty(n)
    for refine in range(2):  # one step of iterative refinement, then the residuals
        c0, c1, c2, c3 = coef[0], coef[1], coef[2], coef[3]
        h0 = h1 = h2 = h3 = 0.0
        for s in range(n_s):
            m0, m1, m2, m3, my = mean_b[s, 0], mean_b[s, 1], mean_b[s, 2], mean_b[s, 3], mean_y[s]
            for i in range(rows[s], rows[s + 1]):
                x0 = basis[i, 0] - m0
                x1 = basis[i, 1] - m1
                x2 = basis[i, 2] - m2
                x3 = basis[i, 3] - m3
                e = y[i] - my - x0 * c0 - x1 * c1 - x2 * c2 - x3 * c3
                r[i] = e
                h0 += x0 * e
                h1 += x1 * e
                h2 += x2 * e
                h3 += x3 * e
        if refine == 0:
            coef = coef + _solve_sym(gram, np.array([h0, h1, h2, h3]))
    offsets = np.empty(n_s)
    for s in range(n_s):
        offsets[s] = mean_y[s] - (mean_b[s, 0] * coef[0] + mean_b[s, 1] * coef[1]
                                  + mean_b[s, 2] * coef[2] + mean_b[s, 3] * coef[3])  # fmt: skip
    return r, coef, offsets


@numba.njit(cache=True, error_model="numpy")
def _solve_sym(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve the small normal equations ``gram · x = rhs`` (symmetric, positive semi-definite)
    by Gauss–Jordan with diagonal pivoting on the matrix scaled to unit diagonal; a direction
    whose remaining diagonal falls below PINV_RCOND is left out (its coefficient 0: the same
    residuals, the column adds nothing: a stress column with one load). Plain loops: no LAPACK
    code to compile or load."""
    nc = len(rhs)
    d = np.ones(nc)
    for j in range(nc):
        if gram[j, j] > 0.0:
            d[j] = math.sqrt(gram[j, j])
    m = np.empty((nc, nc))
    b = np.empty(nc)
    for i in range(nc):
        b[i] = rhs[i] / d[i]
        for j in range(nc):
            m[i, j] = gram[i, j] / (d[i] * d[j])
    done = np.zeros(nc, dtype=np.bool_)
    x = np.zeros(nc)
    for _step in range(nc):
        p = -1
        best = PINV_RCOND
        for i in range(nc):
            if not done[i] and m[i, i] > best:
                best, p = m[i, i], i
        if p < 0:
            break
        done[p] = True
        piv = m[p, p]
        for j in range(nc):
            m[p, j] /= piv
        b[p] /= piv
        for i in range(nc):
            if i != p:
                f = m[i, p]
                for j in range(nc):
                    m[i, j] -= f * m[p, j]
                b[i] -= f * b[p]
    for i in range(nc):
        if done[i]:
            x[i] = b[i] / d[i]
    return x


def _initial_temps(temp: np.ndarray, pos: np.ndarray) -> dict[str, float]:
    """Transformation windows from position against temperature on each branch."""
    hi, lo = np.percentile(pos, 98), np.percentile(pos, 2)
    xi = (pos - lo) / max(hi - lo, 1e-9)
    d = np.concatenate(([0], directions(temp)))
    out = {}
    for tag, sign in (("h", 1), ("c", -1)):
        on = d == sign
        band = {}
        for q in (0.15, 0.5, 0.85):
            m = on & (np.abs(xi - q) < 0.1)
            band[q] = float(np.median(temp[m])) if m.sum() >= 2 else math.nan
        if not all(math.isfinite(v) for v in band.values()):
            continue
        out[f"{tag}_mid"] = band[0.5]
        out[f"{tag}_w"] = float(np.clip(abs(band[0.15] - band[0.85]) / 0.77, 1.0, 60.0))
    return out


def _start(prob: Problem, fold: Fold, names, scale, lo, hi, start,
           keep: int = 1) -> np.ndarray | list[np.ndarray]:  # fmt: skip
    """A start from the data alone: for a few thermal time constants, the transformation
    windows read off position against the temperature they give; the best of them by cost
    (``keep`` > 1: the best ``keep``, best first). Parameters other than these keep their value
    in ``start`` (a candidate's own, say)."""
    x = start.copy()
    idx = {n: i for i, n in enumerate(names)}
    fixed = {"sigma_ref": prob.sigma_ref}
    extra = {n: float(x[i]) for n, i in idx.items() if n not in _BASE_NAMES}

    def temps_for(tau: float):
        ts, ps = [], []
        for s in prob.sessions:
            mask = fold.train[s.name]
            if not mask.any():
                continue
            g, gidx = prob.fit_grids[s.name]
            p = dict(fixed, tau_s=tau, h_mid=0, h_w=1, c_mid=0, c_w=1, **extra)
            temp = temperature(g, p)
            ts.append(temp[gidx[mask]])
            ps.append(s.pos[mask] - np.median(s.pos[mask]))
        return np.concatenate(ts), np.concatenate(ps)

    taus = [4.0] if "tau_s" not in idx else [1.0, 2.0, 4.0, 8.0, 16.0]
    tried = []
    obj = _Objective(prob, fold, names, scale)
    for tau in taus:
        temp, pos = temps_for(tau)
        guess = _initial_temps(temp, pos)
        xt = x.copy()
        if "tau_s" in idx:
            xt[idx["tau_s"]] = tau
        if "c_mid" in guess:  # the cooling centre as the loop's width below the heating one
            h_mid = guess.get("h_mid", float(xt[idx["h_mid"]]))
            guess["hyst_k"] = max(h_mid - guess.pop("c_mid"), 1.0)
        for k, v in guess.items():
            xt[idx[k]] = v
        xt = np.clip(xt, lo, hi)
        tried.append((float(np.sum(obj(xt / scale) ** 2)), len(tried), xt))
    tried.sort(key=lambda c: c[:2])
    return tried[0][2] if keep == 1 else [c[2] for c in tried[:keep]]


def fit_model(
    prob: Problem,
    fold: Fold,
    model: str,
    base: FitResult | None = None,
    max_nfev: int | None = None,
    starts_from: list[np.ndarray] | None = None,
    consensus: bool = False,
) -> FitResult:
    """Fit ``model`` ('baseline' or a candidate) on the fold's training part; ``base`` is the
    fold's baseline fit (candidates start from it), ``starts_from`` replaces the usual starts
    by these parameter vectors (physical units). Several starts are screened (SCREEN_NFEV
    evaluations each) and fitted in full from the best KEEP_STARTS (``consensus``: the other
    folds' solutions, from the best one)."""
    # one BLAS thread: the Jacobians are tall and thin (n × ~12), where a threaded OpenBLAS
    # SVD is ~50× slower than a serial one on a busy 2-core machine; parallelism is per fit
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit_model(prob, fold, model, base, max_nfev, starts_from, consensus)


def _fit_model(
    prob: Problem,
    fold: Fold,
    model: str,
    base: FitResult | None,
    max_nfev: int | None,
    starts_from: list[np.ndarray] | None,
    consensus: bool = False,
) -> FitResult:
    t0 = time.perf_counter()
    if max_nfev is None:
        max_nfev = 60 if base is None else 100
    names, scale, lo, hi, start = _spec(prob, model)
    tau_starts: list[np.ndarray] = []
    if base is None:
        tau_starts = _start(prob, fold, names, scale, lo, hi, start, keep=TAU_STARTS)
        x0 = tau_starts[0]
    else:
        x0 = start.copy()
        for i, n in enumerate(names):
            if n in base.values:
                x0[i] = base.values[n]
    x0 = np.clip(x0, lo, hi)
    obj = _Objective(prob, fold, names, scale)
    starts = [x0]
    for cand in (REGISTRY[c] for c in members(model)):
        pname = cand.params[0].name
        if cand.second_start is not None:  # the baseline compensates strong effects elsewhere
            xs = x0.copy()
            xs[names.index(pname)] = cand.second_start
            starts.append(xs)
        if base is not None and cand.fresh_starts and len(members(model)) == 1:
            # a strong coupled effect bends the baseline's thermal parameters far from their
            # true values, and the fit from there can stall: fresh starts, the effect on
            for v in cand.fresh_starts:
                xs = start.copy()
                xs[names.index(pname)] = v
                starts.append(np.clip(_start(prob, fold, names, scale, lo, hi, xs), lo, hi))
    if "lag_s" in names and "tau_cool_s" in names:
        # the baseline's cooling lag (and its rate-dependent nucleation) absorbs part of a
        # sensor delay: starts that move the cooling lag into the sensor, whole or half
        ic = names.index("tau_cool_s")
        if x0[ic] > 0.02:
            for into, part in (("lag_s", 1.0), ("delay_s", 1.0), ("lag_s", 0.5)):
                xs = x0.copy()
                il = names.index(into)
                xs[il] = min(part * x0[ic], hi[il])
                xs[ic] -= xs[il]
                starts.append(np.clip(xs, lo, hi))
    if starts_from is not None:
        starts = [np.clip(np.asarray(x, float), lo, hi) for x in starts_from]

    def run(xs, nfev=None):
        return least_squares(
            obj, xs / scale, bounds=(lo / scale, hi / scale), diff_step=1e-4,
            max_nfev=nfev or max_nfev, x_scale=1.0, method="trf", ftol=FIT_TOL, xtol=FIT_TOL,
        )  # fmt: skip

    if base is None and starts_from is None:
        # branch shapes have local minima apart (a Tanaka-like start against a logistic tail):
        # a short fit from each shape pair (from the best TAU_STARTS thermal time constants),
        # then full fits from the best KEEP_STARTS of them
        ih, ic = names.index("h_shape"), names.index("c_shape")
        screen = []
        for xt in tau_starts:
            for hs, cs in SHAPE_STARTS:
                xs = np.clip(xt, lo, hi)
                xs[ih], xs[ic] = hs, cs
                r0 = run(np.clip(xs, lo, hi), SCREEN_NFEV)
                screen.append((r0.cost, len(screen), r0.x * scale))
        screen.sort(key=lambda c: c[:2])
        starts = [c[2] for c in screen[:KEEP_STARTS]]

    keep = 1 if consensus else KEEP_STARTS
    if len(starts) > keep and not (base is None and starts_from is None):
        # a short fit from every start; the full fits from the best few, from where they
        # began (a full fit from a start kept is the same as without the screen)
        screen = [run(xs, SCREEN_NFEV).cost for xs in starts]
        best_few = sorted(range(len(starts)), key=lambda k: screen[k])[:keep]
        starts = [starts[k] for k in sorted(best_few)]
    best = None
    for xs in starts:
        res = run(xs)
        if best is None or res.cost < best.cost:
            best = res
    if base is not None and _rmse(best.fun) > base.train_rmse_mm * 1.00005:
        # worse than the baseline it contains: restart from the baseline (extension off)
        xs = x0.copy()
        for i, n in enumerate(names):
            if n not in base.values:
                xs[i] = 0.0 if lo[i] <= 0.0 <= hi[i] else start[i]
        res = run(xs)
        if res.cost < best.cost:
            best = res
    res = best
    r = obj(res.x)  # sets last_linear / offsets at the optimum
    z_lo, z_hi = lo / scale, hi / scale
    span = np.maximum(z_hi - z_lo, 1e-12)
    free = (np.minimum(res.x - z_lo, z_hi - res.x) > 1e-4 * span) & (
        np.linalg.norm(res.jac, axis=0) > 1e-9 * max(float(np.linalg.norm(res.jac)), 1e-30)
    )
    cov = _covariance(res.jac, r, obj.clusters, free) * np.outer(scale, scale)
    return FitResult(
        model=model, names=names, x=res.x * scale, cov=cov,
        se=np.sqrt(np.maximum(np.diag(cov), 0.0)), values=obj.params(res.x),
        linear=obj.last_linear, offsets=obj.last_offsets, train_rmse_mm=_rmse(r),
        nfev=obj.nfev, seconds=time.perf_counter() - t0,
    )  # fmt: skip


def _covariance(jac: np.ndarray, r: np.ndarray, clusters: np.ndarray,
                free: np.ndarray) -> np.ndarray:  # fmt: skip
    """Parameter covariance, cluster-robust (sandwich) with the training branches as clusters.

    The residuals of a fitted loop model are smooth misfits correlated along a branch, so
    J'J·s² would be far too optimistic; the sandwich (J'J)⁻¹·Σ_c (J_c'r_c)(J_c'r_c)'·(J'J)⁻¹
    lets each heating or cooling branch count once, with the small-sample factor
    G/(G-1)·(n-1)/(n-k). Only the ``free`` parameters (off their bounds, with a gradient)
    enter; the others get NaN: they are not identified by these data."""
    n, k = jac.shape
    cov = np.full((k, k), math.nan)
    ids, inv = np.unique(clusters, return_inverse=True)
    g = len(ids)
    j = jac[:, free]
    kf = j.shape[1]
    if g < 2 or n <= kf or kf == 0:
        return cov
    bread = np.linalg.pinv(j.T @ j, rcond=1e-10)
    score = np.zeros((g, kf))
    np.add.at(score, inv, j * r[:, None])
    sub = bread @ (score.T @ score) @ bread * (g / (g - 1.0)) * ((n - 1.0) / (n - kf))
    cov[np.ix_(free, free)] = sub
    return cov


# --------------------------------------------------------------------------- prediction
@dataclass
class Prediction:
    position_mm: np.ndarray  # at the original samples
    temp_c: np.ndarray
    xi: np.ndarray


def predict(prob: Problem, fit: FitResult, s: SessionData, train_mask: np.ndarray) -> Prediction:
    """Simulate a whole session from its input with the fitted parameters (full grid)."""
    g, idx = prob.full_grids[s.name]
    sim = simulate(g, fit.values)
    lin = fit.linear
    pos = sim.fixed + sim.basis @ np.array([lin[n] for n in LINEAR])
    pos_s = pos[idx]
    if s.name in fit.offsets:
        off = fit.offsets[s.name]
    else:  # no training data from this session: zero the sensor on its first samples
        n0 = max(5, len(s.t) // 50)
        first = np.flatnonzero(s.valid)[:n0]
        off = float(np.mean(s.pos[first] - pos_s[first]))
    return Prediction(pos_s + off, sim.temp[idx], sim.xi[idx])


# --------------------------------------------------------------------------- verdict
MIN_UNITS = 16
"""Held-out units wanted for the paired tests: each held-out cycle is split into its heating
and cooling branch, and the branches into equal contiguous blocks until there are this many (16
units: the smallest one-sided Wilcoxon p is 1/65536, so one or two units that an extension does
not help cannot hide a clear gain at α = 0.01)."""


def branch_ids(s: SessionData) -> np.ndarray:
    """Branch of every sample: 2·cycle on heating, 2·cycle + 1 on cooling. Heating is the
    current on (current-driven sessions) or, in a thermometer loop, the samples up to the
    cycle's hottest one."""
    if s.kind == "current" and s.current is not None:
        on = s.current > 0.05 * max(float(np.max(s.current)), 1e-9)
        return 2 * s.cycle + (~on).astype(np.int64)
    out = 2 * s.cycle.astype(np.int64)
    for c in np.unique(s.cycle):
        ii = np.flatnonzero(s.cycle == c)
        out[ii[int(np.argmax(s.temp[ii])) + 1 :]] += 1
    return out


def held_out_units(prob: Problem, folds: list[Fold], min_units: int = MIN_UNITS):
    """(session, fold index, sample indices) per held-out unit: the heating and the cooling
    branch of every held-out cycle, split into equal blocks when there are fewer than
    ``min_units`` of them."""
    branches = []
    for fi, fold in enumerate(folds):
        for s in prob.sessions:
            m = fold.test[s.name]
            if not m.any():
                continue
            ids = branch_ids(s)
            for b in np.unique(ids[m]):
                ii = np.flatnonzero(m & (ids == b))
                if len(ii) >= 4:
                    branches.append((s.name, fi, ii))
    if not branches:
        return []
    per = int(math.ceil(min_units / len(branches)))
    if per <= 1:
        return branches
    return [
        (name, fi, blk)
        for name, fi, ii in branches
        for blk in np.array_split(ii, per)
        if len(blk) >= 2
    ]


def wilcoxon_greater(a: np.ndarray, b: np.ndarray) -> float:
    """One-sided p that a > b (paired), Wilcoxon signed-rank; 1.0 when undefined."""
    d = np.asarray(a) - np.asarray(b)
    if len(d) < 2 or np.all(d == 0):
        return 1.0
    try:
        return float(wilcoxon(a, b, alternative="greater").pvalue)
    except ValueError:
        return 1.0


def ttest_log_greater(a: np.ndarray, b: np.ndarray) -> float:
    """One-sided p that log(a) > log(b) on average (paired t-test of per-unit log RMSE
    ratios): scale-free, so units with a large and a small error weigh alike."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = (a > 0) & (b > 0) & np.isfinite(a) & np.isfinite(b)
    d = np.log(a[ok]) - np.log(b[ok])
    if len(d) < 3 or np.all(d == d[0]):
        return 1.0 if len(d) < 3 or d[0] <= 0 else 0.0
    r = ttest_1samp(d, 0.0, alternative="greater")
    return float(r.pvalue) if math.isfinite(r.pvalue) else 1.0


def paired_greater(a: np.ndarray, b: np.ndarray, tie_mm: float = 0.0) -> float:
    """One-sided p that the per-unit errors ``a`` exceed ``b``: the smaller of the Wilcoxon
    signed-rank and the log-ratio t-test p, Bonferroni-corrected for taking two (× 2).

    Units where both errors are below ``tie_mm`` (both models at the sensor noise: a rest at
    the hot or cold end) are ties and left out: they say nothing about which model is right."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    keep = np.maximum(a, b) >= tie_mm
    a, b = a[keep], b[keep]
    return min(1.0, 2.0 * min(wilcoxon_greater(a, b), ttest_log_greater(a, b)))


HEAT_PAIR = {"latent_heat", "phase_resistance"}
"""Two heat-balance causes that the cooling branches tell apart (no current, no I²R)."""


def unit_gain(base: np.ndarray, ext: np.ndarray, tie_mm: float = 0.0) -> float:
    """Typical held-out gain: 1 − the median over the units of extended/baseline RMSE (units
    where both stay below ``tie_mm`` left out). Robust where the pooled RMSE is not: one
    unit that both models miss badly (a part-way reversal) does not decide it."""
    base, ext = np.asarray(base, float), np.asarray(ext, float)
    keep = (np.maximum(base, ext) >= tie_mm) & (base > 0)
    if not keep.any():
        return 0.0
    return float(1.0 - np.median(ext[keep] / base[keep]))


def structure(units: np.ndarray, pooled: float, floor: float,
              switch_units: np.ndarray | None = None) -> dict:  # fmt: skip
    """Whether a model's held-out errors leave structure: its pooled RMSE above the floor and
    STRUCTURED_QUANTILE of its units above theirs (on most units, not in one: a part-way
    reversal that any model misses would otherwise make a clean session "unexplained" on its
    own). With ``switch_units`` (per-unit RMS error from the switching instants alone,
    :func:`switch_errors`) each unit's floor is √(floor² + that²), the pooled one likewise."""
    units = np.asarray(units, float)
    sw = np.zeros(len(units)) if switch_units is None else np.asarray(switch_units, float)
    unit_floor = np.hypot(floor, sw)
    pooled_floor = float(np.hypot(floor, np.sqrt(np.mean(sw**2)))) if len(sw) else floor
    ratio = float(np.percentile(units / unit_floor, STRUCTURED_QUANTILE)) if len(units) else 0.0
    structured = bool(pooled > pooled_floor and ratio > 1.0)
    sw_rms = float(np.sqrt(np.mean(sw**2))) if len(sw) else 0.0
    text = (f"held-out RMSE {pooled:.4g} mm vs floor {pooled_floor:.4g} mm ({floor:.4g} mm of "
            f"noise/stroke, {sw_rms:.2g} mm from the switching instants); "
            f"{STRUCTURED_QUANTILE:.0f} % of the units below {ratio:.2f} × their floor")
    return {"structured": structured, "floor_mm": pooled_floor, "unit_ratio": ratio,
            "text": text}  # fmt: skip


def verdict(
    base_units: np.ndarray,
    cand_units: dict[str, np.ndarray],
    base_rmse: float,
    cand_rmse: dict[str, float],
    noise_mm: float,
    stroke_mm: float,
    ruled_out: dict[str, str] | None = None,
    cooling: np.ndarray | None = None,
    switch_units: np.ndarray | None = None,
) -> dict:
    """Name the cause (or ``none`` / ``unexplained``) from per-unit held-out RMSEs.

    Candidates pass when their paired test against the baseline reaches ALPHA and their
    typical gain (:func:`unit_gain`) MIN_GAIN; the best passing one is named unless the second
    passing one leaves less than SEPARATION × its typical held-out error and cannot be told
    apart from it at ALPHA_SEPARATION. The runner-up reported is the second passing candidate,
    or else the next by typical gain."""
    rows = {}
    tie = TIE_NOISE * noise_mm
    for c, u in cand_units.items():
        gain = 1.0 - cand_rmse[c] / base_rmse if base_rmse > 0 else 0.0
        p = paired_greater(base_units, u, tie)
        ug = unit_gain(base_units, u, tie)
        rows[c] = {"gain": gain, "unit_gain": ug, "p_value": p,
                   "significant": bool(p < ALPHA and ug >= MIN_GAIN)}  # fmt: skip
        if ruled_out and c in ruled_out:
            rows[c]["significant"] = False
            rows[c]["ruled_out"] = ruled_out[c]
    order = sorted(rows, key=lambda c: -rows[c]["unit_gain"])
    floor = max(FLOOR_NOISE * noise_mm, FLOOR_STROKE * stroke_mm)
    st = structure(base_units, base_rmse, floor, switch_units)
    structured = st["structured"]
    sig = [c for c in order if rows[c]["significant"]]
    runner = None
    reason = ""
    if not sig:
        cause = "unexplained" if structured else "none"
        runner = order[0] if order else None
        reason = (
            f"no extension cuts the held-out error significantly (α = {ALPHA}, typical gain ≥ "
            f"{MIN_GAIN:.0%}); baseline {st['text']}"
        )
        barred = [c for c in order if rows[c].get("ruled_out") and rows[c]["p_value"] < ALPHA
                  and rows[c]["unit_gain"] >= MIN_GAIN]  # fmt: skip
        for c in barred:  # it would have passed: say why it is not named
            reason += (f"; {c} would (typical gain {rows[c]['unit_gain']:.1%}, "
                       f"p = {rows[c]['p_value']:.2g}) but is ruled out: "
                       f"{rows[c]['ruled_out']}")  # fmt: skip
    else:
        best = sig[0]
        runner = next((c for c in order if c != best), None)
        rival = sig[1] if len(sig) > 1 else None  # only a candidate that passes can compete
        cause = best
        reason = (f"{best}: gain {rows[best]['gain']:.1%} (typical unit "
                  f"{rows[best]['unit_gain']:.1%}), p = {rows[best]['p_value']:.2g}")
        if rival is not None:
            runner = rival
            # the runner-up's remaining error over the winner's, on the typical unit
            ratio = 1.0 / max(1.0 - unit_gain(cand_units[runner], cand_units[best], tie), 1e-9)
            p_sep = paired_greater(cand_units[runner], cand_units[best], tie)
            rows[best]["p_vs_runner_up"] = p_sep
            pair = {best, runner}
            if (ratio < SEPARATION and p_sep >= ALPHA_SEPARATION and cooling is not None
                    and pair == HEAT_PAIR and cooling.sum() >= 4):
                # current off, the resistance heats nothing: only latent heat changes how the
                # wire cools, so the cooling branches decide between the two
                for a, b in ((best, runner), (runner, best)):
                    p_cool = paired_greater(cand_units[b][cooling], cand_units[a][cooling], tie)
                    if p_cool < ALPHA_SEPARATION:
                        best, runner, p_sep, ratio = a, b, p_cool, math.inf
                        cause = best
                        rows[best]["p_vs_runner_up_cooling"] = p_cool
                        reason = (f"{best}: gain {rows[best]['gain']:.1%}; told apart from "
                                  f"{runner} on the cooling branches (p = {p_cool:.2g})")
                        break
            if ratio < SEPARATION and p_sep >= ALPHA_SEPARATION:
                cause = "unexplained"
                reason = (
                    f"{best} (gain {rows[best]['gain']:.1%}) and {runner} "
                    f"(gain {rows[runner]['gain']:.1%}) cannot be told apart (p = {p_sep:.2g})"
                )
    return {
        "cause": cause,
        "runner_up": runner,
        "leader": order[0] if order else None,
        "reason": reason,
        "structured": structured,
        "floor_mm": floor,
        "switch_floor_mm": st["floor_mm"],
        "rows": rows,
    }


# --------------------------------------------------------------------------- driver
CONSENSUS_TOL = 0.25
"""Folds whose fits of one model differ by more than this × the parameter's scale (in the
candidate's own parameters; any parameter for the baseline) are refitted from each other's
solution."""


def _consensus(prob: Problem, folds: list[Fold], model: str, fits: dict, run_all,
               report) -> None:  # fmt: skip
    """Refit every fold of ``model`` from the other folds' solutions where they differ, and keep
    what fits its own training part better (:func:`_consensus_tasks`, then
    :func:`_consensus_apply`)."""
    tasks, where = _consensus_tasks(prob, folds, model, fits)
    _consensus_apply(model, fits, where, run_all(tasks), report)


def _consensus_tasks(prob: Problem, folds: list[Fold], model: str,
                     fits: dict) -> tuple[list[tuple], list[int]]:  # fmt: skip
    """The refits of :func:`_consensus` (fit_model arguments) and the folds they are for. The
    folds share most of their training data, so one that ended far from the others usually
    stalled in a local minimum (seen: a sensor lag taken up by the kinetic lags in one fold of
    three)."""
    if len(folds) < 2:
        return [], []
    names, scale, *_ = _spec(prob, model)
    own = [i for i, n in enumerate(names) if n not in _BASE_NAMES] if model != "baseline" \
        else list(range(len(names)))  # fmt: skip
    cur = fits[model]
    tasks, where = [], []
    for i in range(len(folds)):
        other = [cur[j].x for j in range(len(folds)) if j != i and np.max(
            np.abs(cur[j].x[own] - cur[i].x[own]) / scale[own]) > CONSENSUS_TOL]  # fmt: skip
        if other:
            base = fits["baseline"][i] if model != "baseline" else None
            tasks.append((folds[i], model, base, None, other, True))
            where.append(i)
    return tasks, where


def _consensus_apply(model: str, fits: dict, where: list[int], done: list[FitResult],
                     report) -> None:  # fmt: skip
    """Keep each refit of :func:`_consensus_tasks` that fits its training part better."""
    cur = fits[model]
    for i, f in zip(where, done, strict=True):
        report(model, i, f, " (restarted from the other folds)")
        if f.train_rmse_mm < cur[i].train_rmse_mm:
            cur[i] = f


@dataclass
class Analysis:
    prob: Problem
    folds: list[Fold]
    fits: dict[str, list[FitResult]]  # model → one per fold
    preds: dict[str, dict[str, Prediction]]  # model → session → prediction (held-out fold)
    heldout: dict[str, np.ndarray]  # session → bool mask (held out in some fold)
    units: list
    unit_rmse: dict[str, np.ndarray]
    rmse: dict[str, float]
    result: dict
    timing: dict[str, float]


def _rmse(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


_SHARED: dict[int, Problem] = {}
"""Problems of the running analyses, by id: the fork pool's workers inherit them, so a task
sends only its fold and starts (a long session's problem is tens of MB to pickle)."""


def _fit_shared(key: int, *task) -> FitResult:
    """fit_model on a problem of :data:`_SHARED` (in a forked worker)."""
    return fit_model(_SHARED[key], *task)


def _pool(workers: int | None, n_tasks: int):
    """A process pool for the candidate fits (None: fit in this process)."""
    if workers is None:
        workers = min(os.cpu_count() or 1, 4)
    if workers <= 1 or n_tasks <= 1:
        return None
    try:
        ctx = multiprocessing.get_context("fork")
    except ValueError:
        return None
    _load_compiled()
    return ProcessPoolExecutor(max_workers=min(workers, n_tasks), mp_context=ctx)


_COMPILED_LOADED = False


def _load_compiled() -> None:
    """Load the fits' compiled functions (numba's cache) into this process once, before a fork:
    the workers inherit them instead of each loading them again for every analysis (a worker
    paid 0.2-0.5 s for it, the first one in a process seconds)."""
    global _COMPILED_LOADED
    if _COMPILED_LOADED:
        return
    z = np.zeros(3)
    for coupled in (0.0, 0.1):
        g = Grid("warm-up", "current", z, 1.0, z[:2], z, None, 0.0, 55.0, 0.01, 1.0)
        wire_state(g, {"tau_s": 1.0, "h_mid": 70.0, "h_w": 10.0, "hyst_k": 20.0, "c_w": 10.0,
                       "lat_k": coupled})  # fmt: skip
    fill_pointwise(g, {}, (z, z), np.array([1]), z[:1], np.zeros((1, len(LINEAR))), z[:1], 0)
    for series in (z, np.zeros((3, 3))[:, 0]):  # a sensor lag filters columns and vectors
        first_order_lag(series, 1.0, 1.0)
    _project(np.zeros((2, len(LINEAR))), z[:2], np.array([0, 2], dtype=np.int64))
    _COMPILED_LOADED = True


def analyse(
    sessions: list[SessionData],
    candidates: list[str] | None = None,
    progress=None,
    workers: int | None = None,
):
    """Run the whole protocol; returns an :class:`Analysis`. ``workers``: processes for the
    candidate fits (default: the CPU count, at most 4; 1 = no pool)."""
    t_start = time.perf_counter()
    say = progress or (lambda msg: None)
    prob = make_problem(sessions, candidates)
    folds = make_folds(prob)
    models = ["baseline"] + prob.candidates
    fits: dict[str, list[FitResult]] = {m: [] for m in models}
    timing: dict[str, float] = {}
    order = sorted(prob.candidates, key=lambda c: c not in COUPLED)  # slow ones first
    key = id(prob)
    _SHARED[key] = prob  # before the pool forks its workers
    pool = _pool(workers, len(order) * len(folds))

    def submit(tasks: list[tuple]) -> list[Future]:
        """fit_model(prob, *task) for every task: in the pool when there is one (running),
        else here (done)."""
        if pool is not None:
            return [pool.submit(_fit_shared, key, *t) for t in tasks]
        out = []
        for t in tasks:
            fut: Future = Future()
            fut.set_result(fit_model(prob, *t))
            out.append(fut)
        return out

    def run_all(tasks: list[tuple]) -> list[FitResult]:
        """fit_model(prob, *task) for every task, in the pool when there is one."""
        return [f.result() for f in submit(tasks)]

    def report(model: str, fi: int, f: FitResult, what: str = "") -> None:
        timing[model] = timing.get(model, 0.0) + f.seconds
        say(f"[{folds[fi].name}] {model}{what}: train rmse {f.train_rmse_mm:.4g} mm "
            f"({f.nfev} evaluations, {f.seconds:.1f} s)")  # fmt: skip

    heldout = {s.name: np.zeros(len(s.t), dtype=bool) for s in prob.sessions}
    preds: dict[str, dict[str, Prediction]] = {}
    unit_rmse: dict[str, np.ndarray] = {}
    rmse: dict[str, float] = {}
    units = held_out_units(prob, folds)
    by_name = {s.name: s for s in prob.sessions}
    for s in prob.sessions:
        for fold in folds:
            heldout[s.name] |= fold.test[s.name]

    def errors(pred: dict[str, Prediction]) -> tuple[np.ndarray, float]:
        """Per-unit and pooled held-out RMSE of predictions."""
        u, allres = [], []
        for name, _fi, ii in units:
            r = pred[name].position_mm[ii] - by_name[name].pos[ii]
            u.append(_rmse(r))
            allres.append(r)
        return np.array(u), _rmse(np.concatenate(allres)) if allres else math.nan

    def evaluate(model: str) -> None:
        preds[model] = _predictions(prob, folds, fits[model])
        unit_rmse[model], rmse[model] = errors(preds[model])

    noise = float(np.median([s.noise_mm() for s in prob.sessions]))
    stroke = float(np.median([np.nanpercentile(s.pos, 98) - np.nanpercentile(s.pos, 2)
                              for s in prob.sessions]))  # fmt: skip
    try:
        fits["baseline"] = run_all([(fold, "baseline") for fold in folds])
        for fi, f in enumerate(fits["baseline"]):
            report("baseline", fi, f)
        _consensus(prob, folds, "baseline", fits, run_all, report)
        rival = "sensor_lag" in prob.candidates and "current" in {s.kind for s in prob.sessions}
        _candidate_fits(prob, folds, order, fits, submit, report, rival)
        for model in models:
            evaluate(model)
        if rival:
            evaluate(KINETIC_RIVAL)
        ruled_out = _evidence(prob, fits, preds, unit_rmse, TIE_NOISE * noise, units)
        cooling = np.array([branch_ids(by_name[name])[ii[0]] % 2 == 1 for name, _f, ii in units],
                           dtype=bool)  # fmt: skip
        def decide() -> dict:
            return verdict(
                unit_rmse["baseline"], {c: unit_rmse[c] for c in prob.candidates},
                rmse["baseline"], {c: rmse[c] for c in prob.candidates}, noise, stroke,
                ruled_out, cooling,
                switch_errors(prob, folds, fits["baseline"], preds["baseline"], units),
            )  # fmt: skip

        v = decide()
        # the baseline from where the best candidate ended: its gain may be the shared
        # parameters' better optimum, not the cause's (judged again when the baseline improves)
        lead = v["cause"] if v["cause"] in REGISTRY else v["leader"]
        if lead and _refit_from(prob, folds, fits, "baseline", lead, run_all, report):
            evaluate("baseline")
            v = decide()
        if (v["cause"] == "unexplained" and v["structured"] and "current" in
                {s.kind for s in prob.sessions}
                and not any(r["significant"] for r in v["rows"].values())):  # fmt: skip
            _rate_kinetics(prob, folds, fits, v, run_all, report, evaluate, unit_rmse, rmse,
                           preds, units)  # fmt: skip
        v["causes"] = []
        if v["cause"] in REGISTRY:
            v["causes"] = _more_causes(prob, folds, fits, v, run_all, report, evaluate,
                                       unit_rmse, rmse, noise, ruled_out)  # fmt: skip
        elif v.get("kinetics") and not v["kinetics"]["within_floor"]:
            _causes_on_kinetics(prob, folds, fits, v, run_all, report, evaluate, unit_rmse,
                                rmse, noise, ruled_out)  # fmt: skip
    finally:
        if pool is not None:
            pool.shutdown()
        _SHARED.pop(key, None)
    v["noise_mm"] = noise
    v["stroke_mm"] = stroke
    timing["total"] = time.perf_counter() - t_start
    return Analysis(prob, folds, fits, preds, heldout, units, unit_rmse, rmse, v, timing)


def _candidate_fits(prob: Problem, folds: list[Fold], order: list[str], fits: dict, submit,
                    report, rival: bool) -> None:  # fmt: skip
    """Every candidate on every fold, then its consensus refits (:func:`_consensus`), and the
    kinetic rival of ``sensor_lag`` when ``rival``; a candidate's refits start as soon as its
    own folds are done (no fit waits for another candidate's), so the pool stays busy."""
    futs = {c: [] for c in order}
    for fi, fold in enumerate(folds):
        for c in order:
            futs[c].append(submit([(fold, c, fits["baseline"][fi])])[0])
    stage = dict.fromkeys(order, "fit")
    refits: dict[str, tuple[list[int], list[Future]]] = {}
    rival_futs: list[Future] | None = None
    while True:
        for c in order:
            if stage[c] == "fit" and all(f.done() for f in futs[c]):
                fits[c] = [f.result() for f in futs[c]]
                for fi, f in enumerate(fits[c]):
                    report(c, fi, f)
                tasks, where = _consensus_tasks(prob, folds, c, fits)
                refits[c] = (where, submit(tasks))
                stage[c] = "consensus"
            if stage[c] == "consensus" and all(f.done() for f in refits[c][1]):
                where, done = refits[c]
                _consensus_apply(c, fits, where, [f.result() for f in done], report)
                stage[c] = "done"
        if rival and rival_futs is None and stage.get("sensor_lag") == "done":
            rival_futs = submit(_rival_tasks(prob, folds, fits))
        waiting = [f for c in order for f in futs[c] if not f.done()]
        waiting += [f for c in order if c in refits for f in refits[c][1] if not f.done()]
        waiting += [f for f in rival_futs or [] if not f.done()]
        if not waiting and all(v == "done" for v in stage.values()):
            break
        if waiting:
            wait(waiting, return_when=FIRST_COMPLETED)
    if rival:
        fits[KINETIC_RIVAL] = [f.result() for f in rival_futs]
        for fi, f in enumerate(fits[KINETIC_RIVAL]):
            report(KINETIC_RIVAL, fi, f)


def _rival_tasks(prob: Problem, folds: list[Fold], fits: dict) -> list[tuple]:
    """Fits of KINETIC_RIVAL per fold, from the baseline's fit with: no dead time of ξ, equal
    lags on both branches, and the sensor fit's delay as a delay of the transformation; and
    from where the sensor fit ended, its delay moved into ξ (the rival gets the sensor's
    chance: from the baseline's start one fold of a no-effect session stalled at 1.6 × the
    sensor's training error, and the sensor was named)."""
    names = _spec(prob, KINETIC_RIVAL)[0]
    tasks = []
    for fi, fold in enumerate(folds):
        x = np.append(fits["baseline"][fi].x, 0.0)
        x_eq = x.copy()
        x_eq[names.index("heat_lag_ratio")] = 1.0  # equal lags on both branches
        x_dt = x.copy()  # the sensor fit's delay, as a delay of the transformation
        lag = fits["sensor_lag"][fi].values
        delay = lag.get("lag_s", 0.0) + lag.get("delay_s", 0.0)
        x_dt[-1] = delay
        x_s = np.array([lag.get(n, PARAMS[n].start) for n in names])
        x_s[-1] = delay
        tasks.append((fold, KINETIC_RIVAL, None, None, [x, x_eq, x_dt, x_s]))
    return tasks


def switch_errors(prob: Problem, folds: list[Fold], fits: list[FitResult], preds: dict,
                  units: list) -> np.ndarray:  # fmt: skip
    """Per held-out unit, the RMS error of a model's prediction (``preds``, from ``fits``) that
    the switching instants of the current alone would cause (:data:`SWITCH_RMS`): the
    prediction again with every change of the current one sample earlier. 0 for thermometer
    loops."""
    early = {}
    for s in prob.sessions:
        g, idx = prob.full_grids[s.name]
        if g.kind == "current":
            early[s.name] = (replace(g, i2=np.append(g.i2[1:], g.i2[-1])), idx)
    if not early:
        return np.zeros(len(units))
    moved = _predictions(replace(prob, full_grids={**prob.full_grids, **early}), folds, fits)
    return np.array([SWITCH_RMS * _rmse(preds[name].position_mm[ii] - moved[name].position_mm[ii])
                     for name, _fi, ii in units])  # fmt: skip


RATE_STARTS = (0.3, 0.8, 1.5)
"""Starts of ``rate_shift_k``, K/√(K/s), from the baseline's fit (one start stalled at a
quarter of the value on a third-simulator session)."""


def _rate_kinetics(prob: Problem, folds: list[Fold], fits: dict, v: dict, run_all, report,
                   evaluate, unit_rmse: dict, rmse: dict, preds: dict,
                   units: list) -> None:  # fmt: skip
    """Fit :data:`RATE_KINETICS` in every fold (from the baseline's fit), and make the verdict
    ``none`` when its held-out error is within the floor, with the reason and the fitted shift
    in ``v["kinetics"]``; ``v`` changed in place."""
    names = _spec(prob, RATE_KINETICS)[0]
    at = names.index("rate_shift_k")
    tasks = []
    for fi, fold in enumerate(folds):
        have = fits["baseline"][fi].values
        x = np.array([have.get(n, PARAMS[n].start) for n in names])
        starts = [np.where(np.arange(len(x)) == at, k, x) for k in RATE_STARTS]
        tasks.append((fold, RATE_KINETICS, fits["baseline"][fi], None, starts))
    fits[RATE_KINETICS] = run_all(tasks)
    for fi, f in enumerate(fits[RATE_KINETICS]):
        report(RATE_KINETICS, fi, f)
    _consensus(prob, folds, RATE_KINETICS, fits, run_all, report)
    evaluate(RATE_KINETICS)
    pooled = rmse[RATE_KINETICS]
    st = structure(unit_rmse[RATE_KINETICS], pooled, v["floor_mm"],
                   switch_errors(prob, folds, fits[RATE_KINETICS], preds[RATE_KINETICS], units))
    shift = [f.values["rate_shift_k"] for f in fits[RATE_KINETICS]]
    within = bool(not st["structured"]
                  and max(shift) > OFF_TOL * PARAMS["rate_shift_k"].scale)  # fmt: skip
    v["kinetics"] = {"model": RATE_KINETICS, "rate_shift_k": float(np.mean(shift)),
                     "rate_shift_k_per_fold": shift, "heldout_rmse_mm": pooled,
                     "floor_mm": st["floor_mm"], "unit_ratio": st["unit_ratio"],
                     "within_floor": within}  # fmt: skip
    said = (f"with transformation temperatures that move with the rate (rate_shift_k = "
            f"{np.mean(shift):.2g} K/√(K/s)): {st['text']}")
    if within:
        v["cause"] = "none"
        v["reason"] += (f"; {said}, within the floor: the structure is the wire's "
                        "rate-dependent kinetics, not a hidden effect")  # fmt: skip
    else:
        v["reason"] += f"; {said}, still above the floor"


def _causes_on_kinetics(prob, folds, fits, v, run_all, report, evaluate, unit_rmse, rmse,
                        noise, ruled_out) -> None:  # fmt: skip
    """When the wire's rate-dependent kinetics leave structure and no candidate was named over
    the baseline: every candidate on top of :data:`RATE_KINETICS` with the same test (a sensor
    lag against the kinetic rival on top of it; the rival is what rules it out here, not the
    baseline's); ``v`` changed in place when one passes. Seen: the third simulator's sensor
    lags and convection laws were diluted by the baseline's miss of its nucleation."""
    keep = {c: why for c, why in ruled_out.items() if not why.startswith(RIVAL_LOST)}
    causes = _more_causes(prob, folds, fits, v, run_all, report, evaluate, unit_rmse, rmse,
                          noise, keep, under=RATE_KINETICS)  # fmt: skip
    if not causes:
        return
    v["causes"] = causes
    v["cause"] = causes[0]["cause"]
    v["reason"] += "; on top of them: " + ", ".join(
        f"{c['cause']} (typical gain {c['gain']:.1%}, p = {c['p_value']:.2g})" for c in causes)


MAX_CAUSES = 3
"""At most this many causes are named together."""


def _more_causes(prob, folds, fits, v, run_all, report, evaluate, unit_rmse, rmse, noise,
                 ruled_out, under: str | None = None) -> list[dict]:  # fmt: skip
    """After the first cause: fit every other candidate on top of the causes named so far and
    name each that passes the same held-out paired test against them (α, minimum gain), best
    first; a cause added on top of another is tested at ALPHA / the number tried there. ``under``
    (RATE_KINETICS): no cause yet, every candidate tried on top of that model instead, and the
    first that passes (at ALPHA, as a first cause) is the first cause."""
    if under is None:
        first = v["cause"]
        chain = [first]
        out = [{"cause": first, "model": first, "gain": v["rows"][first]["unit_gain"],
                "p_value": v["rows"][first]["p_value"], "over": "baseline"}]  # fmt: skip
    else:
        chain, out = [under], []
    tie = TIE_NOISE * noise
    while len(out) < MAX_CAUSES:
        current = "+".join(chain)
        # every candidate not ruled out: one masked by the first cause's misfit may gain
        # nothing on its own (seen: a residual-strain drift under an unmodelled stress shift)
        others = [c for c in prob.candidates if c not in chain and c not in ruled_out]
        if not others:
            break
        # the best of several tried on top of a cause: Bonferroni over them (seen at α: a
        # room drift of −4 … −11 K/h added on top of a large phase resistance, p = 0.006)
        alpha = ALPHA if not out else ALPHA / len(others)
        tasks = []
        for c in others:
            combo = current + "+" + c
            names = _spec(prob, combo)[0]
            for fi, fold in enumerate(folds):
                have = dict(fits[c][fi].values)
                have.update(fits[current][fi].values)
                x = np.array([have.get(n, PARAMS[n].start) for n in names])
                tasks.append((fold, combo, fits[current][fi], None, [x]))
        done = run_all(tasks)
        best = None
        for k, c in enumerate(others):
            combo = current + "+" + c
            fits[combo] = done[k * len(folds):(k + 1) * len(folds)]
            for fi, f in enumerate(fits[combo]):
                report(combo, fi, f)
            evaluate(combo)
            if off_everywhere(c, fits[combo]):
                continue  # on top of the causes it is off: nothing of its own to name
            gain = unit_gain(unit_rmse[current], unit_rmse[combo], tie)
            p = paired_greater(unit_rmse[current], unit_rmse[combo], tie)
            v["rows"][c].setdefault("on_top", {})[current] = {"unit_gain": gain, "p_value": p,
                                                               "alpha": alpha}  # fmt: skip
            if p < alpha and gain >= MIN_GAIN and (best is None or gain > best[1]):
                best = (c, gain, p)
        if best is not None and best[0] == "sensor_lag":
            why = _rival_on_top(prob, folds, fits, current, run_all, report, evaluate,
                                unit_rmse)  # fmt: skip
            if why:
                v["rows"]["sensor_lag"]["on_top"][current]["ruled_out"] = why
                best = None
        if best is None:
            break
        if _refit_from(prob, folds, fits, current, current + "+" + best[0], run_all, report):
            evaluate(current)  # the smaller model did better from there: test again
            combo = current + "+" + best[0]
            gain = unit_gain(unit_rmse[current], unit_rmse[combo], tie)
            p = paired_greater(unit_rmse[current], unit_rmse[combo], tie)
            v["rows"][best[0]]["on_top"][current] = {"unit_gain": gain, "p_value": p,
                                                      "after_refit": True}  # fmt: skip
            if not (p < alpha and gain >= MIN_GAIN):
                break
            best = (best[0], gain, p)
        chain.append(best[0])
        out.append({"cause": best[0], "model": "+".join(chain), "gain": best[1],
                    "p_value": best[2], "over": current})  # fmt: skip
    return out


RIVAL_LOST = "no better than kinetic lags of ξ alone"
"""How the reason a sensor lag lost to its kinetic rival begins."""


def _rival_lost(rival: np.ndarray, lag: np.ndarray) -> str | None:
    """Why a sensor lag is ruled out against the kinetic rival (per-unit held-out errors of
    both), or None when it beats it: one-sided paired test at ALPHA_SEPARATION, typical gain
    above 0. No ties: the rests, where both sit near the noise, are part of the evidence (a
    sensor delays their slow thermal motion too, kinetics does not)."""
    p = paired_greater(rival, lag, 0.0)
    g = unit_gain(rival, lag, 0.0)
    if p < ALPHA_SEPARATION and g > 0:
        return None
    return (f"{RIVAL_LOST} (typical gain {g:.1%}, p = {p:.2g}): "
            "a delayed transformation explains the data as well as a delayed reading "
            "(the reading's delay would show in the thermal expansion and the rests)")


def _rival_on_top(prob: Problem, folds: list[Fold], fits: dict, current: str, run_all, report,
                  evaluate, unit_rmse: dict) -> str | None:  # fmt: skip
    """A sensor lag added on top of ``current`` must beat the kinetic rival on top of it too
    (:func:`_rival_lost`); the rival starts from ``current``'s fit, with equal lags, and with
    the sensor fit's delay as a dead time of ξ. Seen without this: a sensor lag added on top
    of convection where the linear-in-T conductance missed a ΔT^1.32 law."""
    rival = current + "+" + KINETIC_RIVAL
    combo = current + "+sensor_lag"
    names = _spec(prob, rival)[0]
    tasks = []
    for fi, fold in enumerate(folds):
        have = fits[current][fi].values
        x = np.array([have.get(n, PARAMS[n].start) for n in names])
        x[names.index("xi_delay_s")] = 0.0
        x_eq = x.copy()
        x_eq[names.index("heat_lag_ratio")] = 1.0
        x_dt = x.copy()
        lag = fits[combo][fi].values
        x_dt[names.index("xi_delay_s")] = lag.get("lag_s", 0.0) + lag.get("delay_s", 0.0)
        tasks.append((fold, rival, fits[current][fi], None, [x, x_eq, x_dt]))
    fits[rival] = run_all(tasks)
    for fi, f in enumerate(fits[rival]):
        report(rival, fi, f)
    evaluate(rival)
    # whole units only: on the still parts a sensor lag of 0.1 s beat the rival on top of a
    # room drift (third simulator, no lag hidden), where the rival on whole units ruled it out
    return _rival_lost(unit_rmse[rival], unit_rmse[combo])


def _refit_from(prob: Problem, folds: list[Fold], fits: dict, small: str, big: str, run_all,
                report) -> bool:  # fmt: skip
    """Refit ``small`` from ``big``'s solution in every fold (its own parameters taken from
    there), keeping what fits the training part better; True when any fold improved. A cause
    is added on top of ``small`` only when it beats what ``small`` reaches from the same
    place: the larger model's fit may have found a better optimum of the shared parameters
    (seen: convection at conv_k = 8e-5 1/K 'adding' 68 % on top of a stress shift)."""
    names = _spec(prob, small)[0]
    tasks = []
    for fi, fold in enumerate(folds):
        have = fits[big][fi].values
        x = np.array([have.get(n, fits[small][fi].values.get(n, PARAMS[n].start))
                      for n in names])  # fmt: skip
        base = fits["baseline"][fi] if small != "baseline" else None
        tasks.append((fold, small, base, None, [x], True))
    improved = False
    for fi, f in enumerate(run_all(tasks)):
        report(small, fi, f, f" (restarted from {big})")
        if f.train_rmse_mm < fits[small][fi].train_rmse_mm:
            fits[small][fi] = f
            improved = True
    return improved


def _predictions(prob: Problem, folds: list[Fold], fits: list[FitResult]
                 ) -> dict[str, Prediction]:  # fmt: skip
    """Each session predicted by the fold that holds it out (where a session is never held
    out, by the first fold that trains on it: in-sample)."""
    out: dict[str, Prediction] = {}
    for s in prob.sessions:
        for fi, fold in enumerate(folds):
            m = fold.test[s.name]
            if not m.any():
                continue
            pr = predict(prob, fits[fi], s, fold.train[s.name])
            old = out.get(s.name)
            if old is None:
                out[s.name] = Prediction(np.where(m, pr.position_mm, np.nan), pr.temp_c, pr.xi)
            else:
                old.position_mm[m] = pr.position_mm[m]
        if s.name not in out:
            out[s.name] = predict(prob, fits[0], s, folds[0].train[s.name])
            continue
        pm = out[s.name].position_mm
        nan = ~np.isfinite(pm)
        if nan.any():
            fi = next((i for i, f in enumerate(folds) if f.train[s.name].any()), 0)
            pm[nan] = predict(prob, fits[fi], s, folds[fi].train[s.name]).position_mm[nan]
    return out


VI_FLAT = 0.3
"""phase_resistance is ruled out when the wire's V/I against ξ changes by less than this
fraction of the resistivity difference its fit needs (the voltage measures R directly)."""


OFF_TOL = 1e-3
"""A candidate's magnitude parameter within this × its scale of 0 is off."""


def off_everywhere(cand: str, fits: list[FitResult]) -> str | None:
    """Why ``cand`` cannot be named when its fits (one per fold) have it off in every fold
    (all of ``Candidate.off_params`` within OFF_TOL × scale of 0): whatever the model gains
    over the baseline then comes from refitting the baseline's parameters (another optimum),
    not from the cause. None when it is on in some fold."""
    names = REGISTRY[cand].off_params
    if not fits or any(any(abs(f.values.get(n, 0.0)) > OFF_TOL * PARAMS[n].scale
                           for n in names) for f in fits):  # fmt: skip
        return None
    shown = ", ".join(f"{n} = {np.mean([f.values.get(n, 0.0) for f in fits]):.2g}"
                      for n in names)  # fmt: skip
    return (f"its own parameter is 0 in every fold ({shown}): the gain is the baseline's "
            "parameters refitted to another optimum, not this cause")


XI_STILL = 0.002
"""ξ within this of 0 or 1 in both models: the transformation is still, only the thermal
expansion (and the rests) can move the reading there."""


STILL_UNITS = 6
"""Fewest held-out units with still parts for that evidence to count."""


def _still_errors(prob: Problem, preds: dict, units: list, a: str, b: str):
    """Per-unit held-out RMSE of models ``a`` and ``b`` on the samples of each unit where both
    models' ξ is still (:data:`XI_STILL`); units with fewer than 10 such samples left out."""
    by_name = {s.name: s for s in prob.sessions}
    ea, eb = [], []
    for name, _fi, ii in units:
        xa, xb = preds[a][name].xi[ii], preds[b][name].xi[ii]
        m = (np.minimum(xa, 1.0 - xa) < XI_STILL) & (np.minimum(xb, 1.0 - xb) < XI_STILL)
        if m.sum() < 10:
            continue
        y = by_name[name].pos[ii][m]
        ea.append(_rmse(preds[a][name].position_mm[ii][m] - y))
        eb.append(_rmse(preds[b][name].position_mm[ii][m] - y))
    return np.array(ea), np.array(eb)


def _evidence(prob: Problem, fits: dict, preds: dict, unit_rmse: dict, tie: float,
              units: list) -> dict[str, str]:  # fmt: skip
    """Candidates the data rule out, with the reason: a candidate that is off in every fold
    (:func:`off_everywhere`); a flat V/I against ξ rules out phase_resistance whatever its fit
    of the position gains; a sensor_lag that does no better than equal kinetic lags of ξ (the
    rival), neither over whole units nor where the transformation is still
    (:func:`_still_errors`), cannot be told from the wire's kinetics."""
    out: dict[str, str] = {}
    for c in prob.candidates:
        why = off_everywhere(c, fits.get(c, []))
        if why:
            out[c] = why
    if "sensor_lag" in fits and KINETIC_RIVAL in unit_rmse:
        why = _rival_lost(unit_rmse[KINETIC_RIVAL], unit_rmse["sensor_lag"])
        if why:
            # where the transformation is still, kinetics delays nothing and a sensor still
            # delays the thermal expansion and the rests: the evidence the whole units dilute
            rival, lag = _still_errors(prob, preds, units, KINETIC_RIVAL, "sensor_lag")
            if len(rival) < STILL_UNITS or _rival_lost(rival, lag):
                out["sensor_lag"] = why
    if "phase_resistance" in fits and fits["phase_resistance"]:
        vi = _vi_fit(prob.sessions, preds["phase_resistance"])
        if vi is not None:
            beta = float(np.mean([f.values["beta"] for f in fits["phase_resistance"]]))
            need = beta * vi["rho_mean_uohm_cm"]
            have = vi["difference_uohm_cm"]
            if abs(need) > 0 and (abs(have) < VI_FLAT * abs(need) or have * need < 0):
                out["phase_resistance"] = (
                    f"ruled out by V/I against ξ: the measured resistivity difference is "
                    f"{have:.2f} ± {vi['difference_uncertainty_uohm_cm']:.2g} µΩ·cm where the "
                    f"fit needs {need:.2f} µΩ·cm"
                )
    return out


# --------------------------------------------------------------------------- parameters
TEMPERATURE_PARAMS = ("h_mid", "c_mid")
"""Parameters that are temperatures: flagged when they lie outside the data's range."""


def physical_parameters(an: Analysis, model: str) -> dict[str, dict]:
    """Fitted parameters of ``model`` in physical units: value, standard uncertainty, unit,
    and ``flags`` (at a bound in some fold, uncertainty larger than the value, a temperature
    outside the data's range).

    Over several folds: the mean, and an uncertainty combining the fits' own standard errors
    with the spread between folds."""
    fits = an.fits[model]
    out: dict[str, dict] = {}

    def combine(vals, ses):
        """Mean over the folds; uncertainty: the fits' own (cluster-robust) standard error
        and the spread between folds, in quadrature (NaN: at a bound, not identified)."""
        vals, ses = np.asarray(vals, float), np.asarray(ses, float)
        mean = float(np.mean(vals))
        spread = float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0
        ok = np.isfinite(ses)
        u = float(np.sqrt(np.mean(ses[ok] ** 2) + spread**2)) if ok.any() else math.nan
        return mean, u, vals.tolist()

    for i, n in enumerate(fits[0].names):
        v, u, per = combine([f.x[i] for f in fits], [f.se[i] for f in fits])
        prm = PARAMS[n]
        span = prm.hi - prm.lo
        at = [b for b, lim in (("lower", prm.lo), ("upper", prm.hi))
              if any(abs(f.x[i] - lim) <= 1e-3 * span for f in fits)]  # fmt: skip
        out[n] = {"value": v, "uncertainty": u, "unit": prm.unit, "per_fold": per,
                  "at_bound": at}  # fmt: skip
    # the cooling centre, derived from the heating centre and the loop's width
    ih, ik = fits[0].names.index("h_mid"), fits[0].names.index("hyst_k")

    def se_diff(f: FitResult) -> float:
        c = f.cov[np.ix_([ih, ik], [ih, ik])]
        var = c[0, 0] + c[1, 1] - 2.0 * c[0, 1]
        return math.sqrt(var) if math.isfinite(var) and var >= 0 else math.nan

    v, u, per = combine([f.x[ih] - f.x[ik] for f in fits], [se_diff(f) for f in fits])
    out["c_mid"] = {"value": v, "uncertainty": u, "unit": "°C", "per_fold": per,
                    "note": "cooling centre = h_mid − hyst_k"}  # fmt: skip
    for n in LINEAR:
        vals = [f.linear.get(n, math.nan) for f in fits]
        out[n] = {"value": float(np.mean(vals)), "uncertainty": float(np.std(vals)) if
                  len(vals) > 1 else math.nan, "unit": unit_of(n), "per_fold": vals}  # fmt: skip
    for c in members(model):
        _DERIVED.get(c, lambda *_: None)(an, model, out, combine)
    return out


def _derive_stress_shift(an: Analysis, model: str, out: dict, combine) -> None:
    s, u = out["ss_k_per_mpa"]["value"], out["ss_k_per_mpa"]["uncertainty"]
    out["stress_rate_mpa_per_k"] = {
        "value": 1.0 / s if s > 0 else math.inf, "uncertainty": u / s**2 if s > 0 else math.inf,
        "unit": "MPa/K",
        "per_fold": [1.0 / v if v > 0 else math.inf for v in out["ss_k_per_mpa"]["per_fold"]],
    }  # fmt: skip


def _derive_phase_resistance(an: Analysis, model: str, out: dict, combine) -> None:
    vi = resistance_check(an, model)
    if vi is not None:
        rho, how = vi["rho_mean_uohm_cm"] * 1e-8, "ρ_mean from V/I at ξ = 0.5"
        out["resistance_check"] = vi
    else:
        cur = [s for s in an.prob.sessions if s.kind == "current"]
        rho = float(np.mean([s.resistance_ohm()[0] * s.area_m2 / (s.length_mm * 1e-3)
                             for s in cur]))  # fmt: skip
        how = "nominal ρ_mean (no voltage recorded)"
    b, u = out["beta"]["value"], out["beta"]["uncertainty"]
    out["resistivity_difference_uohm_cm"] = {
        "value": b * rho * 1e8, "uncertainty": u * rho * 1e8, "unit": "µΩ·cm",
        "note": f"austenite minus martensite: β·ρ_mean from R = R_mean·(1 + β(0.5 - ξ)), {how}",
    }  # fmt: skip


def _derive_latent_heat(an: Analysis, model: str, out: dict, combine) -> None:
    v, u = out["lat_k"]["value"], out["lat_k"]["uncertainty"]
    out["latent_heat_j_kg"] = {
        "value": v * CP_J_KGK, "uncertainty": u * CP_J_KGK, "unit": "J/kg",
        "note": f"λ·cp with cp = {CP_J_KGK:g} J/(kg·K) (smabench.physics.wire)",
    }  # fmt: skip


def _derive_sensor_lag(an: Analysis, model: str, out: dict, combine) -> None:
    fits = an.fits[model]
    il, idl = fits[0].names.index("lag_s"), fits[0].names.index("delay_s")

    def se_sum(f: FitResult) -> float:
        c = f.cov[np.ix_([il, idl], [il, idl])]
        if not np.isfinite(c).any():
            return math.nan
        return math.sqrt(max(float(np.nansum(c)), 0.0))  # a part at its bound adds none

    v, u, per = combine([f.x[il] + f.x[idl] for f in fits], [se_sum(f) for f in fits])
    rows = any(s.row_time for s in an.prob.sessions)
    # no t_s column: time is the row index, so the delay is in samples and named so
    key = "sensor_delay_samples" if rows else "sensor_delay_s"
    out[key] = {
        "value": v, "uncertainty": u, "unit": "samples" if rows else "s", "per_fold": per,
        "note": "mean delay of the reading: first-order lag τ plus dead time",
    }  # fmt: skip


DRIFT_CYCLES = 10
"""The cycle drift's headline: the residual strain over the first this many transformation
cycles, per cycle (a linear drift: its rate). The rate at the first cycle alone is not
determined where the rate falls (r and n0 of r·n0·ln(1 + N/n0) trade against each other over a
dozen cycles: 42-70 % off on the third simulator); their accumulated strain is."""


def _derive_cycle_drift(an: Analysis, model: str, out: dict, combine) -> None:
    fits = an.fits[model]
    names = [n for n in ("cyc_rate", "cyc_n0", "cyc_q") if n in fits[0].names]

    def mean_rate(f: FitResult, x: np.ndarray | None = None) -> float:
        v = dict(f.values)
        if x is not None:
            v.update(zip(names, x, strict=True))
        return float(residual_strain(np.array([float(DRIFT_CYCLES)]), v["cyc_rate"],
                                     v.get("cyc_n0", 1e3), v.get("cyc_q", 1.0))[0]) / DRIFT_CYCLES

    def se(f: FitResult) -> float:  # delta method over the fitted drift parameters
        idx = [f.names.index(n) for n in names]
        x0 = f.x[idx]
        grad = np.empty(len(idx))
        for k in range(len(idx)):
            h = 1e-6 * max(abs(x0[k]), 1e-9)
            up, dn = x0.copy(), x0.copy()
            up[k] += h
            dn[k] -= h
            grad[k] = (mean_rate(f, up) - mean_rate(f, dn)) / (2.0 * h)
        var = float(grad @ f.cov[np.ix_(idx, idx)] @ grad)
        return math.sqrt(var) if math.isfinite(var) and var >= 0 else math.nan

    v, u, per = combine([mean_rate(f) for f in fits], [se(f) for f in fits])
    out["drift_per_cycle"] = {
        "value": v, "uncertainty": u, "unit": "strain/cycle", "per_fold": per,
        "note": f"residual strain over the first {DRIFT_CYCLES} transformation cycles / "
        f"{DRIFT_CYCLES} (the rate of a linear drift)",
    }  # fmt: skip


_DERIVED = {
    "cycle_drift": _derive_cycle_drift,
    "stress_shift": _derive_stress_shift,
    "phase_resistance": _derive_phase_resistance,
    "latent_heat": _derive_latent_heat,
    "sensor_lag": _derive_sensor_lag,
}
"""Candidate → how its headline parameter is derived from the fitted ones (the others report a
fitted parameter directly: ``Candidate.headline``)."""


def headline_key(an: Analysis, cause: str) -> str:
    """The headline parameter's key for ``cause`` (units in the name)."""
    key = REGISTRY[cause].headline
    if key == "sensor_delay_s" and any(s.row_time for s in an.prob.sessions):
        return "sensor_delay_samples"
    return key


def data_temperature_range(an: Analysis, model: str = "baseline") -> tuple[float, float]:
    """The temperatures the data cover, °C: measured (thermometer loops) or the model's
    estimate from the current (2nd to 98th percentile)."""
    temps = []
    for s in an.prob.sessions:
        temps.append(s.temp if s.kind == "thermo" else an.preds[model][s.name].temp_c)
    t = np.concatenate(temps)
    return float(np.percentile(t, 2)), float(np.percentile(t, 98))


def parameter_flags(an: Analysis, model: str, params: dict[str, dict]) -> list[str]:
    """Honesty flags of one model's parameters: at a bound, uncertainty larger than the value,
    a transformation temperature outside the temperatures the data cover."""
    flags = []
    lo_t, hi_t = data_temperature_range(an, model)
    for name, pv in params.items():
        if "value" not in pv:
            continue
        v, u = pv.get("value"), pv.get("uncertainty")
        unit = pv.get("unit", "")
        unit = "" if unit.startswith("1") else f" {unit.split(' (')[0]}"  # short: a name's unit
        if pv.get("at_bound"):
            flags.append(f"{model}: {name} = {v:.4g}{unit} at its "
                         f"{'/'.join(pv['at_bound'])} bound in some fold (not identified)")
        if name in ("c_mid",) and params.get("hyst_k", {}).get("at_bound") == ["lower"]:
            continue
        if v is not None and u is not None and math.isfinite(u) and abs(u) > abs(v) > 0:
            flags.append(f"{model}: {name} = {v:.4g} ± {u:.2g}: uncertainty larger than "
                         "the value")
        if name in TEMPERATURE_PARAMS and v is not None and not lo_t <= v <= hi_t:
            flags.append(f"{model}: {name} = {v:.4g} °C outside the data's temperatures "
                         f"{lo_t:.1f}…{hi_t:.1f} °C")
    return flags


def resistance_check(an: Analysis, model: str = "baseline") -> dict | None:
    """V/I against the model's martensite fraction while the current is on (sessions with the
    wire voltage): R = R_0.5 + ΔR·(0.5 - ξ) by least squares, as resistivities. A direct
    measurement of ``phase_resistance`` that does not go through the heat balance."""
    return _vi_fit(an.prob.sessions, an.preds[model])


def _vi_fit(sessions: list[SessionData], preds: dict[str, Prediction]) -> dict | None:
    xs, ys, geo = [], [], []
    for s in sessions:
        if s.voltage is None or s.current is None:
            continue
        i = s.current
        on = np.isfinite(s.voltage) & (i > 0.2 * np.max(i)) & (i > 0.02)
        if on.sum() < 20:
            continue
        xi = preds[s.name].xi[on]
        xs.append(0.5 - xi)
        ys.append(s.voltage[on] / i[on] * s.area_m2 / (s.length_mm * 1e-3) * 1e8)  # µΩ·cm
        geo.append(s.name)
    if not xs:
        return None
    x, y = np.concatenate(xs), np.concatenate(ys)
    if np.ptp(x) < 0.3:
        return None  # the current-on samples do not span the transformation
    a = np.column_stack((np.ones_like(x), x))
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    r = y - a @ coef
    cov = np.linalg.pinv(a.T @ a) * float(np.sum(r**2)) / max(len(y) - 2, 1)
    return {
        "rho_mean_uohm_cm": float(coef[0]),
        "difference_uohm_cm": float(coef[1]),
        "difference_uncertainty_uohm_cm": float(math.sqrt(max(cov[1, 1], 0.0))),
        "rms_uohm_cm": float(np.sqrt(np.mean(r**2))),
        "samples": len(y),
        "sessions": geo,
    }


EFFECT_PARAMETER = {c: REGISTRY[c].headline for c in CANDIDATES}
"""Candidate → its headline parameter in :func:`physical_parameters` (from the registry)."""

CAUSE_TEXT = {c: cause_text(c) for c in (*CANDIDATES, "none", "unexplained")}
"""What each verdict means physically (from the registry)."""

__all__ = [
    "COUPLED",
    "Analysis",
    "analyse",
    "physical_parameters",
    "Temps",
]
