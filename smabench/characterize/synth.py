"""Loops whose E3097 temperatures are known by construction (tests and the benchmark).

Each branch is three straight lines — martensite, transformation, austenite — meeting at the
set As/Af (heating) and Ms/Mf (cooling), so the tangent-line intersections are those
temperatures exactly; the corners can be rounded (a smooth blend over ``round_k`` kelvin, as a
real transformation starts and ends gradually) without moving the lines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Branches:
    """Known E3097 construction (°C, strain). Under load the wire is longer in martensite."""

    As: float = 70.0
    Af: float = 85.0
    Ms: float = 65.0
    Mf: float = 50.0
    strain_martensite: float = 0.045  # on the martensite line at As
    strain_austenite: float = 0.005  # on the austenite line at Af
    slope_martensite: float = 2e-5  # 1/K
    slope_austenite: float = 1e-5  # 1/K
    round_k: float = 0.0

    def _branch(self, t_c: np.ndarray, start: float, finish: float) -> np.ndarray:
        """Strain along a branch whose transformation runs from ``start`` (martensite side) to
        ``finish`` (austenite side), both °C, start < finish."""
        t = np.asarray(t_c, dtype=float)
        # one martensite and one austenite line for both branches (a closed loop), anchored at
        # As and Af; the transformation line joins them at start and finish
        m_line = self.strain_martensite + self.slope_martensite * (t - self.As)
        a_line = self.strain_austenite + self.slope_austenite * (t - self.Af)
        e_s = self.strain_martensite + self.slope_martensite * (start - self.As)
        e_f = self.strain_austenite + self.slope_austenite * (finish - self.Af)
        tr_line = e_s + (e_f - e_s) * (t - start) / (finish - start)
        if self.round_k <= 0:
            return np.where(t < start, m_line, np.where(t > finish, a_line, tr_line))
        # soft min / soft max (scale: the transformation's strain over round_k / 2 kelvin):
        # smooth corners, the three lines unchanged away from them
        sc = self.round_k * abs(e_f - e_s) / (finish - start) / 2.0
        low = -sc * np.logaddexp(-m_line / sc, -tr_line / sc)
        return sc * np.logaddexp(low / sc, a_line / sc)

    def heating(self, t_c: np.ndarray) -> np.ndarray:
        return self._branch(t_c, self.As, self.Af)

    def cooling(self, t_c: np.ndarray) -> np.ndarray:
        return self._branch(t_c, self.Mf, self.Ms)


def cycle_record(
    br: Branches,
    n: int,
    heat_fraction: float = 0.3,
    lct_c: float = 25.0,
    uct_c: float = 120.0,
    tau_fraction: float = 0.08,
) -> tuple[np.ndarray, np.ndarray]:
    """One cycle of ``n`` samples as a current-driven bench sees it: the temperature rises
    exponentially towards ``uct_c`` for ``heat_fraction`` of the cycle, then falls back towards
    ``lct_c``; returns (temperature °C, strain)."""
    x = np.arange(n) / n
    nh = int(round(heat_fraction * n))
    tau = tau_fraction
    top = lct_c + (uct_c - lct_c) * (1 - np.exp(-heat_fraction / tau))
    t_heat = lct_c + (uct_c - lct_c) * (1 - np.exp(-x[:nh] / tau))
    t_cool = lct_c + (top - lct_c) * np.exp(-(x[nh:] - heat_fraction) / (1.6 * tau))
    t_c = np.concatenate([t_heat, t_cool])
    strain = np.concatenate([br.heating(t_heat), br.cooling(t_cool)])
    return t_c, strain


def ramp_record(
    br: Branches,
    cycles: int,
    points_per_branch: int = 300,
    lct_c: float = 25.0,
    uct_c: float = 120.0,
    noise_t_k: float = 0.0,
    noise_strain: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """``cycles`` linear temperature ramps LCT → UCT → LCT (a chamber), with optional noise."""
    rng = np.random.default_rng(seed)
    up = np.linspace(lct_c, uct_c, points_per_branch, endpoint=False)
    down = np.linspace(uct_c, lct_c, points_per_branch, endpoint=False)
    t_list, e_list = [], []
    for _ in range(cycles):
        t_list += [up, down]
        e_list += [br.heating(up), br.cooling(down)]
    t_list.append(np.array([lct_c]))
    e_list.append(br.cooling(np.array([lct_c])))
    t_c, strain = np.concatenate(t_list), np.concatenate(e_list)
    return (t_c + rng.normal(0, noise_t_k, t_c.size) if noise_t_k else t_c,
            strain + rng.normal(0, noise_strain, t_c.size) if noise_strain else strain)
