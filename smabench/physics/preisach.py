"""A discrete Preisach model: the classical operator peer of the paper's closed-form loop models.

The output is a weighted sum of relay hysterons on a triangular grid of switching temperatures
plus an affine term::

    y(t) = y0 + k·(T(t) − T_ref) + s · Σ_ij w_ij · γ_ij[T](t),   w_ij ≥ 0

where relay γ_ij (up switch α_i > down switch β_j) turns on when T ≥ α_i and off when T ≤ β_j and
otherwise keeps its state, and ``s`` = ±1 is the direction of the stroke on heating (taken from the
data). Diagonal relays (α_i = β_i) are memory-free steps and carry the reversible part. The
weights come from non-negative least squares with a small ridge term that keeps the Preisach
density smooth where the data do not pin it down, solved on the normal equations built run by run
(:func:`_normal_equations`), so memory and time do not grow with the design matrix.

Relays start off (negative saturation: the input came from below the grid), so the model carries
the return-point memory and wiping-out properties of the Preisach operator by construction.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cholesky, solve_triangular
from scipy.optimize import nnls

log = logging.getLogger(__name__)

MIN_POINTS = 20


@dataclass
class PreisachModel:
    """Fitted Preisach weights over ``levels_c`` (°C); output in mm."""

    levels_c: np.ndarray = field(repr=False)
    weights_mm: np.ndarray = field(repr=False)  # (n, n) lower triangle incl. diagonal: [α_i, β_j]
    offset_mm: float
    slope_mm_per_k: float
    t_ref_c: float
    sign: float

    @property
    def n_levels(self) -> int:
        return int(self.levels_c.size)

    def parameters(self) -> dict[str, float]:
        """Summary figures (the weights themselves are in ``weights_mm``)."""
        return {
            "n_levels": float(self.n_levels),
            "n_relays": float(np.count_nonzero(np.tril(np.ones_like(self.weights_mm)))),
            "n_active_relays": float(np.count_nonzero(self.weights_mm > 1e-9)),
            "offset_mm": self.offset_mm,
            "slope_mm_per_k": self.slope_mm_per_k,
            "t_min_c": float(self.levels_c[0]),
            "t_max_c": float(self.levels_c[-1]),
        }

    # ------------------------------------------------------------------ evaluation
    def predict(self, temperature_c) -> np.ndarray:
        """Position (mm) along a temperature sequence (°C), starting from negative saturation."""
        t = _as_temperature(temperature_c)
        relay_sum = _relay_sum(t, self.levels_c, self.weights_mm)
        return self.offset_mm + self.slope_mm_per_k * (t - self.t_ref_c) + self.sign * relay_sum

    # ------------------------------------------------------------------ identification
    @classmethod
    def fit(
        cls,
        temperature_c,
        position_mm,
        *,
        n_levels: int = 40,
        ridge: float = 1e-3,
    ) -> PreisachModel:
        """Least-squares weights for a measured sequence; raises ValueError on unusable data.

        ``n_levels`` switching temperatures span the measured range (n·(n+1)/2 relays);
        ``ridge`` is relative to the number of samples (dimensionless, ≥ 0).
        """
        t = _as_temperature(temperature_c)
        y = np.asarray(position_mm, dtype=float).ravel()
        if t.size != y.size:
            raise ValueError(f"{t.size} temperatures but {y.size} positions")
        if t.size < MIN_POINTS:
            raise ValueError(f"need at least {MIN_POINTS} samples, got {t.size}")
        if not np.all(np.isfinite(y)):
            raise ValueError("positions contain NaN or infinity")
        if not 4 <= n_levels <= 200:
            raise ValueError(f"n_levels {n_levels} out of range 4..200")
        if not ridge > 0:
            raise ValueError(f"ridge must be > 0 (it keeps unexcited relays fixed), got {ridge}")
        t_lo, t_hi = float(t.min()), float(t.max())
        if t_hi - t_lo < 1.0:
            raise ValueError(f"temperature span {t_hi - t_lo:.2f} K is too small for a loop")
        # levels at the cell centres, so that no sample sits exactly on a switching temperature
        step = (t_hi - t_lo) / n_levels
        levels = t_lo + step * (np.arange(n_levels) + 0.5)
        n = t.size
        cold = y[t < t_lo + 0.1 * (t_hi - t_lo)]
        hot = y[t > t_hi - 0.1 * (t_hi - t_lo)]
        sign = 1.0 if np.median(hot) >= np.median(cold) else -1.0
        stroke = float(np.ptp(y)) or 1.0
        gram, rhs = _normal_equations(t - t_lo, y / stroke, levels - t_lo, sign)
        n_relays = gram.shape[0] - 2
        gram[2:, 2:] += ridge * n * np.eye(n_relays)  # the ridge keeps the density smooth
        x = _nonnegative_quadratic(gram, rhs, n_free=2)
        coef = x * stroke
        ii, jj = np.tril_indices(n_levels)
        weights = np.zeros((n_levels, n_levels))
        weights[ii, jj] = np.maximum(coef[2:], 0.0)  # round-off may leave -1e-17
        model = cls(levels, weights, float(coef[0]), float(coef[1]), t_lo, sign)
        log.info(
            "preisach: %d levels, %d of %d relays active, objective %.3g",
            n_levels, np.count_nonzero(coef[2:] > 1e-9), ii.size,
            float(x @ gram @ x - 2 * rhs @ x),
        )  # fmt: skip
        return model


class PreisachStepper:
    """Online evaluation, one temperature sample at a time (same result as ``predict``)."""

    def __init__(self, model: PreisachModel):
        self.model = model
        n = model.n_levels
        self._on = np.zeros((n, n), dtype=bool)
        self._lower = np.tril(np.ones((n, n), dtype=bool))
        self.reset()

    def reset(self) -> None:
        """Back to negative saturation (all relays off)."""
        self._on[:] = False
        self._sum = 0.0

    def step(self, temperature_c: float) -> float:
        """Apply one sample (°C) and return the position (mm)."""
        m = self.model
        t = float(temperature_c)
        n_down = int(np.searchsorted(m.levels_c, t, side="left"))  # β_j ≥ T: off
        n_up = int(np.searchsorted(m.levels_c, t, side="right"))  # α_i ≤ T: on
        self._on[:, n_down:] = False
        self._on[:n_up] = self._lower[:n_up]
        self._sum = float(m.weights_mm[self._on].sum())
        return m.offset_mm + m.slope_mm_per_k * (t - m.t_ref_c) + m.sign * self._sum

    def run(self, temperature_c) -> np.ndarray:
        """Step through a sequence (°C); returns positions (mm)."""
        return np.array([self.step(t) for t in np.asarray(temperature_c, dtype=float)])


# ---------------------------------------------------------------------- relay bookkeeping
def _as_temperature(temperature_c) -> np.ndarray:
    t = np.asarray(temperature_c, dtype=float).ravel()
    if not np.all(np.isfinite(t)):
        raise ValueError("temperatures contain NaN or infinity")
    return t


def _last_crossings(t: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per level and sample, the last index ≤ k with T ≥ level (up) and with T ≤ level (down).

    Both are (n_levels, n_samples) int arrays, −1 where it never happened.
    """
    idx = np.arange(t.size)
    up = np.where(t[None, :] >= levels[:, None], idx, -1)
    down = np.where(t[None, :] <= levels[:, None], idx, -1)
    np.maximum.accumulate(up, axis=1, out=up)
    np.maximum.accumulate(down, axis=1, out=down)
    return up, down


def _normal_equations(
    tau: np.ndarray, y: np.ndarray, levels: np.ndarray, sign: float, chunk: int = 4096
) -> tuple[np.ndarray, np.ndarray]:
    """X'X and X'y of the design ``[1, τ, sign·γ_ij]`` without building X (n × relays).

    Between two neighbouring levels no relay can switch, so a run of samples in one level cell
    shares one row of relay states: one state row per run, weighted by the run's sample count,
    and the runs' sums of τ, τ², y and τ·y carry the rest exactly. Memory is O(relays²) plus one
    chunk of runs; the 26 000-row fit that took 870 MB as a dense design takes a few tens."""
    cells = np.searchsorted(levels, tau)
    starts = np.r_[0, np.nonzero(np.diff(cells))[0] + 1]
    counts = np.diff(np.r_[starts, tau.size]).astype(float)
    s1 = np.add.reduceat(tau, starts)
    s2 = np.add.reduceat(tau * tau, starts)
    sy = np.add.reduceat(y, starts)
    sty = np.add.reduceat(tau * y, starts)
    rep = tau[starts]
    up, down = _last_crossings(rep, levels)
    ii, jj = np.tril_indices(levels.size)
    diag = ii == jj
    m = ii.size
    gram = np.zeros((m + 2, m + 2))
    rhs = np.zeros(m + 2)
    gram[0, 0], gram[0, 1], gram[1, 1] = counts.sum(), s1.sum(), s2.sum()
    rhs[0], rhs[1] = sy.sum(), sty.sum()
    for a in range(0, starts.size, chunk):
        b = slice(a, a + chunk)
        states = up[ii, b] > down[jj, b]  # (relays, runs)
        states[diag] = rep[None, b] >= levels[ii[diag], None]
        sm = sign * states.T.astype(float)  # (runs, relays)
        c = counts[b]
        gram[2:, 2:] += sm.T @ (sm * c[:, None])
        gram[0, 2:] += c @ sm
        gram[1, 2:] += s1[b] @ sm
        rhs[2:] += sy[b] @ sm
    gram[1, 0] = gram[0, 1]
    gram[2:, 0] = gram[0, 2:]
    gram[2:, 1] = gram[1, 2:]
    return gram, rhs


def _nonnegative_quadratic(gram: np.ndarray, rhs: np.ndarray, n_free: int) -> np.ndarray:
    """argmin x'Gx − 2h'x with x[n_free:] ≥ 0 (G positive definite).

    The free coefficients are eliminated (Schur complement); the rest is a non-negative least
    squares problem ‖L'x − L⁻¹h‖² on the Cholesky factor L of the reduced Gram matrix, which
    Lawson–Hanson (``scipy.optimize.nnls``) solves in as many steps as there are active relays."""
    g_ff, g_fs, g_ss = gram[:n_free, :n_free], gram[:n_free, n_free:], gram[n_free:, n_free:]
    k = np.linalg.solve(g_ff, g_fs)
    reduced = g_ss - g_fs.T @ k
    h_red = rhs[n_free:] - k.T @ rhs[:n_free]
    chol = cholesky(reduced, lower=True)
    x_s, _ = nnls(chol.T, solve_triangular(chol, h_red, lower=True), maxiter=50 * reduced.shape[0])
    if not np.all(np.isfinite(x_s)):
        raise ValueError("least squares did not converge")
    x_f = np.linalg.solve(g_ff, rhs[:n_free] - g_fs @ x_s)
    return np.r_[x_f, x_s]


def _relay_states(t: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Relay states (n_samples, n_relays) in ``np.tril_indices`` order; relay on ⇔ last up-crossing
    of α_i is later than the last down-crossing of β_j (diagonal: T ≥ α_i now)."""
    up, down = _last_crossings(t, levels)
    ii, jj = np.tril_indices(levels.size)
    out = np.empty((t.size, ii.size))
    for k, (i, j) in enumerate(zip(ii, jj, strict=True)):
        out[:, k] = up[i] > down[j] if i != j else t >= levels[i]
    return out


def _relay_sum(t: np.ndarray, levels: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ w_ij γ_ij(t) without building the full state matrix (memory O(n_levels · n))."""
    up, down = _last_crossings(t, levels)
    total = np.zeros(t.size)
    for i in range(levels.size):
        w_row = weights[i, :i]
        active = np.nonzero(w_row > 0)[0]
        if active.size:
            total += w_row[active] @ (up[i][None, :] > down[active]).astype(float)
        if weights[i, i] > 0:
            total += weights[i, i] * (t >= levels[i])
    return total
