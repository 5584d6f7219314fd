"""A discrete Preisach model: the classical operator peer of the paper's closed-form loop models.

The output is a weighted sum of relay hysterons on a triangular grid of switching temperatures
plus an affine term::

    y(t) = y0 + k·(T(t) − T_ref) + s · Σ_ij w_ij · γ_ij[T](t),   w_ij ≥ 0

where relay γ_ij (up switch α_i > down switch β_j) turns on when T ≥ α_i and off when T ≤ β_j and
otherwise keeps its state, and ``s`` = ±1 is the direction of the stroke on heating (taken from the
data). Diagonal relays (α_i = β_i) are memory-free steps and carry the reversible part. The
weights come from non-negative least squares (``scipy.optimize.lsq_linear``) with a small ridge
term that keeps the Preisach density smooth where the data do not pin it down.

Relays start off (negative saturation: the input came from below the grid), so the model carries
the return-point memory and wiping-out properties of the Preisach operator by construction.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear

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

        states = _relay_states(t, levels)  # (n, n_relays) of 0/1
        ii, jj = np.tril_indices(n_levels)
        x = np.hstack([np.ones((n, 1)), (t - t_lo)[:, None], sign * states])
        stroke = float(np.ptp(y)) or 1.0
        lam = np.sqrt(ridge * n)
        reg = np.hstack([np.zeros((ii.size, 2)), lam * np.eye(ii.size)])
        a = np.vstack([x, reg])  # solve for coefficients in units of the stroke
        b = np.concatenate([y / stroke, np.zeros(ii.size)])
        lb = np.r_[-np.inf, -np.inf, np.zeros(ii.size)]
        sol = lsq_linear(a, b, bounds=(lb, np.inf), method="bvls")
        if not np.all(np.isfinite(sol.x)):
            raise ValueError("least squares did not converge")
        coef = sol.x * stroke
        weights = np.zeros((n_levels, n_levels))
        weights[ii, jj] = np.maximum(coef[2:], 0.0)  # bvls may leave -1e-17
        model = cls(levels, weights, float(coef[0]), float(coef[1]), t_lo, sign)
        log.info(
            "preisach: %d levels, %d of %d relays active, cost %.3g",
            n_levels, np.count_nonzero(coef[2:] > 1e-9), ii.size, sol.cost,
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
