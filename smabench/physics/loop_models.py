"""Closed-form hysteresis loop models: length y (mm) vs wire temperature T (°C).

Shibly & Söffker's two models are built on the diagonal between the two common points
(T1, Y1) (low temperature, where heating and cooling branches diverge) and (T2, Y2) (high
temperature, where they meet again):

- :class:`Model1` rotates the loop about (T2, Y2) so that the diagonal is horizontal, describes
  the cooling branch by one half-sine and the heating branch by two (they cross the diagonal at
  T12), and rotates back.
- :class:`Model2` adds half-sine branches to the diagonal without rotation: cooling
  ``-c11·A·sin``, heating ``+c21·A·sin`` up to the crossing point (ratio f) then ``-c22·A·sin``.

Above T2 both use a 2nd-order polynomial for the metal's expansion, below T1 a straight line.

:class:`SigmoidModel` is ours: the austenite fraction on each branch is a mixture of two logistic
steps (a sharp core and a broad tail), and the length mixes a martensite and an austenite line.
It keeps the closed form and the online speed and follows the sharp transitions of real wires.

Every model has a vectorised major-loop form ``evaluate(T, heating)`` and a scalar ``branch``
form used by :class:`LoopStepper`, the online stepper that tracks the branch direction and the
reversal points, and a vectorised ``branch_array`` that :func:`run_history` evaluates run by
run. Their memory (:mod:`smabench.physics.memory`) implements the paper's adaptation rules: an
incomplete cycle (reheated before it cooled) moves the first common point to the reversal point;
an inner loop moves both common points (the branch heads for the previous reversal point, and a
loop is wiped out when the temperature passes it, so inner loops close where they started).

All functions are pure numpy; temperatures in °C, lengths/positions in mm.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from smabench.physics.memory import HIGH, LOW, ReversalMemory, TurnDetector, branch_runs

log = logging.getLogger(__name__)

Point = tuple[float, float]  # (temperature °C, length mm)


def branch_directions(temperature_c: np.ndarray, deadband_k: float = 1.0) -> np.ndarray:
    """Heating (True) or cooling (False) for every sample of a temperature sequence.

    The direction flips only when the temperature has moved more than ``deadband_k`` (K) back
    from its last extreme, so sensor noise does not create false reversals. The samples between
    an extreme and the detection of the reversal are labelled with the new direction.
    """
    t = np.asarray(temperature_c, dtype=float)
    n = t.size
    heating = np.ones(n, dtype=bool)
    if n == 0:
        return heating
    # initial direction: the first clear move
    moved = np.nonzero(np.abs(t - t[0]) > deadband_k)[0]
    direction = bool(t[moved[0]] > t[0]) if moved.size else True
    ext_i = 0
    start = 0
    for i in range(1, n):
        if direction:
            if t[i] > t[ext_i]:
                ext_i = i
            elif t[ext_i] - t[i] > deadband_k:
                heating[start : ext_i + 1] = True
                start, direction, ext_i = ext_i + 1, False, i
        else:
            if t[i] < t[ext_i]:
                ext_i = i
            elif t[i] - t[ext_i] > deadband_k:
                heating[start : ext_i + 1] = False
                start, direction, ext_i = ext_i + 1, True, i
    heating[start:] = direction
    return heating


def _expansion(t: np.ndarray, t2: float, y2: float, e1: float, e2: float) -> np.ndarray:
    """Metal expansion above T2: y = Y2 + e1·(T−T2) + e2·(T−T2)²."""
    d = t - t2
    return y2 + e1 * d + e2 * d * d


@dataclass
class CommonPoints:
    """The two common points of a loop and the straight lines outside them.

    t1_c, y1_mm: first common point (low temperature); t2_c, y2_mm: second (high temperature).
    low_slope_mm_per_k: slope of the martensite line below T1.
    exp1_mm_per_k, exp2_mm_per_k2: expansion polynomial above T2.
    """

    t1_c: float
    y1_mm: float
    t2_c: float
    y2_mm: float
    low_slope_mm_per_k: float = 0.0
    exp1_mm_per_k: float = 0.0
    exp2_mm_per_k2: float = 0.0

    def outside(self, t: np.ndarray) -> np.ndarray:
        """Length outside [T1, T2] (NaN inside)."""
        out = np.full(t.shape, np.nan)
        lo = t < self.t1_c
        hi = t > self.t2_c
        out[lo] = self.y1_mm + self.low_slope_mm_per_k * (t[lo] - self.t1_c)
        out[hi] = _expansion(t[hi], self.t2_c, self.y2_mm, self.exp1_mm_per_k, self.exp2_mm_per_k2)
        return out

    def outside_scalar(self, t: float) -> float:
        if t < self.t1_c:
            return self.y1_mm + self.low_slope_mm_per_k * (t - self.t1_c)
        d = t - self.t2_c
        return self.y2_mm + self.exp1_mm_per_k * d + self.exp2_mm_per_k2 * d * d


# --------------------------------------------------------------------------- model 1
@dataclass
class Model1:
    """Paper's model 1 (rotated half-sines).

    The loop is rotated about (T2, Y2) so that the diagonal lies flat at ordinate Y2, from
    T11 = T2 − L to T2 (L = diagonal length). Cooling: ``yr = Y2 + a1·sin(π(Tr−T11)/L)``.
    Heating: ``Y2 + a21·sin(π(Tr−T11)/(T12−T11))`` up to T12 = T11 + f12·L, then
    ``Y2 + a22·sin(π(Tr−T12)/(T2−T12))``. Amplitudes in mm (a1 < 0, a21 > 0, a22 < 0 for a wire
    whose heating branch lies above the cooling branch, all signs flipped when it lies below:
    the rotation is mirror-symmetric, so the model of −y is the mirror image of the model of y).
    Minor branches (:meth:`branch`) use the geometry of their own start and target points with
    the amplitudes scaled by the sub-loop's share of the major stroke (:meth:`sub_scale`).

    The rotation needs a common scale for both axes: lengths are multiplied by
    ``aspect_k_per_mm`` (K per mm) before rotating. The paper rotates in its plot's units; we fit
    the aspect with the other parameters (on the Flexinol loops it lowers the error from about
    3.4 % to 2.6–2.9 % of stroke, because the rotated half-sines then lean like the real branches).
    """

    cp: CommonPoints
    a1_mm: float
    a21_mm: float
    a22_mm: float
    f12: float  # crossing point of the heating branch, fraction of the rotated diagonal (0 … 1)
    aspect_k_per_mm: float = 1.0

    name = "1"
    table_points = 257  # samples per branch of the table the vectorised form interpolates

    def _geometry(self, p1: Point, p2: Point):
        k = self.aspect_k_per_mm
        t1, t2 = p1[0], p2[0]
        y1, y2 = p1[1] * k, p2[1] * k
        alpha = math.atan2(y2 - y1, t2 - t1)
        length = math.hypot(t2 - t1, y2 - y1)
        t11 = t2 - length
        t12 = t11 + self.f12 * length
        return k, t2, y2, math.cos(alpha), math.sin(alpha), length, t11, t12

    def _tables(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """(T, y) tables of the rotated-back heating and cooling branches, T increasing."""
        cached = self.__dict__.get("_table_cache")
        if cached is not None:
            return cached
        cp = self.cp
        k, t2, y2, ca, sa, length, t11, t12 = self._geometry(
            (cp.t1_c, cp.y1_mm), (cp.t2_c, cp.y2_mm)
        )
        tr = np.linspace(t11, t2, self.table_points)
        w1, w2 = max(t12 - t11, 1e-9), max(t2 - t12, 1e-9)
        heat = np.where(
            tr < t12,
            self.a21_mm * np.sin(np.pi * np.clip((tr - t11) / w1, 0.0, 1.0)),
            self.a22_mm * np.sin(np.pi * np.clip((tr - t12) / w2, 0.0, 1.0)),
        )
        cool = self.a1_mm * np.sin(np.pi * (tr - t11) / length)
        tables = []
        for dev_mm in (heat, cool):
            d = dev_mm * k
            t_back = np.maximum.accumulate(t2 + (tr - t2) * ca - d * sa)
            y_back = (y2 + (tr - t2) * sa + d * ca) / k
            tables.append((t_back, y_back))
        self.__dict__["_table_cache"] = tuple(tables)
        return self.__dict__["_table_cache"]

    def evaluate(self, temperature_c: np.ndarray, heating: np.ndarray) -> np.ndarray:
        """Major loop, vectorised: heating[i] selects the branch for temperature_c[i]."""
        t = np.asarray(temperature_c, dtype=float)
        h = np.broadcast_to(np.asarray(heating, dtype=bool), t.shape)
        (th, yh), (tc, yc) = self._tables()
        y = np.where(h, np.interp(t, th, yh), np.interp(t, tc, yc))
        cp = self.cp
        out = (t < cp.t1_c) | (t > cp.t2_c)
        if np.any(out):
            y = np.where(out, cp.outside(t), y)
        return y

    def branch(self, t: float, heating: bool, start: Point, target: Point) -> float:
        """One sample on a (possibly minor) branch from ``start`` towards ``target``.

        Inverts the rotation for this one temperature by a safeguarded Newton iteration.
        """
        cp = self.cp
        if t < cp.t1_c or t > cp.t2_c:
            return cp.outside_scalar(t)
        p1, p2 = (start, target) if target[0] >= start[0] else (target, start)
        if p2[0] - p1[0] <= 1e-9:
            return start[1]
        scale = self.sub_scale(start, target)
        k, t2, y2, ca, sa, length, t11, t12 = self._geometry(p1, p2)
        pi = math.pi
        if not heating:
            a, lo, w = self.a1_mm, t11, length
        else:
            a, lo, w = self.a21_mm, t11, max(t12 - t11, 1e-9)
        a *= k * scale
        a22, w22 = self.a22_mm * k * scale, max(t2 - t12, 1e-9)

        def dev(tr: float) -> tuple[float, float]:
            if heating and tr >= t12:
                u = min(max((tr - t12) / w22, 0.0), 1.0)
                return a22 * math.sin(pi * u), a22 * pi / w22 * math.cos(pi * u)
            u = min(max((tr - lo) / w, 0.0), 1.0)
            return a * math.sin(pi * u), a * pi / w * math.cos(pi * u)

        lo_b, hi_b = t11, t2
        tr = min(max(t2 + (t - t2) / ca, lo_b), hi_b)
        for _ in range(30):
            d, dd = dev(tr)
            g = t2 + (tr - t2) * ca - d * sa - t
            if abs(g) < 1e-9:
                break
            if g > 0:
                hi_b = tr
            else:
                lo_b = tr
            slope = ca - dd * sa
            nxt = tr - g / slope if slope > 1e-6 else 0.5 * (lo_b + hi_b)
            tr = nxt if lo_b < nxt < hi_b else 0.5 * (lo_b + hi_b)
        d, _ = dev(tr)
        return (y2 + (tr - t2) * sa + d * ca) / k

    def sub_scale(self, start: Point, target: Point) -> float:
        """Amplitude scale of the sub-loop between ``start`` and ``target``: its share of the
        major stroke (a reversal early in a transformation opens a small loop however many
        kelvin it spans)."""
        cp = self.cp
        major = abs(cp.y2_mm - cp.y1_mm)
        return min(abs(target[1] - start[1]) / major, 1.0) if major > 1e-12 else 1.0

    def branch_array(self, t: np.ndarray, heating: bool, start: Point, target: Point):
        """:meth:`branch` over an array of temperatures (the same safeguarded Newton
        iteration, vectorised)."""
        cp = self.cp
        t = np.asarray(t, dtype=float)
        p1, p2 = (start, target) if target[0] >= start[0] else (target, start)
        if p2[0] - p1[0] <= 1e-9:
            y = np.full(t.shape, float(start[1]))
        else:
            scale = self.sub_scale(start, target)
            k, t2, y2, ca, sa, length, t11, t12 = self._geometry(p1, p2)
            w12, w22 = max(t12 - t11, 1e-9), max(t2 - t12, 1e-9)
            a1, a21, a22 = (v * k * scale for v in (self.a1_mm, self.a21_mm, self.a22_mm))

            def dev(tr):
                if heating:
                    second = tr >= t12
                    amp = np.where(second, a22, a21)
                    width = np.where(second, w22, w12)
                    u = np.clip((tr - np.where(second, t12, t11)) / width, 0.0, 1.0)
                else:
                    amp, width = a1, length
                    u = np.clip((tr - t11) / width, 0.0, 1.0)
                return amp * np.sin(np.pi * u), amp * np.pi / width * np.cos(np.pi * u)

            lo_b, hi_b = np.full(t.shape, t11), np.full(t.shape, t2)
            tr = np.clip(t2 + (t - t2) / ca, t11, t2)
            for _ in range(30):
                d, dd = dev(tr)
                g = t2 + (tr - t2) * ca - d * sa - t
                done = np.abs(g) < 1e-9
                if done.all():
                    break
                hi_b = np.where(g > 0, tr, hi_b)
                lo_b = np.where(g > 0, lo_b, tr)
                slope = ca - dd * sa
                with np.errstate(divide="ignore", invalid="ignore"):
                    nxt = np.where(slope > 1e-6, tr - g / slope, 0.5 * (lo_b + hi_b))
                ok = (lo_b < nxt) & (nxt < hi_b)
                tr = np.where(done, tr, np.where(ok, nxt, 0.5 * (lo_b + hi_b)))
            d, _ = dev(tr)
            y = (y2 + (tr - t2) * sa + d * ca) / k
        out = (t < cp.t1_c) | (t > cp.t2_c)
        if np.any(out):
            y = np.where(out, cp.outside(t), y)
        return y

    def parameters(self) -> dict[str, float]:
        d = asdict(self.cp)
        d.update(
            a1_mm=self.a1_mm,
            a21_mm=self.a21_mm,
            a22_mm=self.a22_mm,
            f12=self.f12,
            aspect_k_per_mm=self.aspect_k_per_mm,
        )
        return d


# --------------------------------------------------------------------------- model 2
@dataclass
class Model2:
    """Paper's model 2 (diagonal plus half-sines, no rotation).

    Cooling: ``b + a·T − c11·A·sin(π(T−T1)/(g·L1))`` on [T1, T1 + g·L1] and the diagonal above;
    heating: ``b + a·T + c21·A·sin(π(T−T1)/(f·L1))`` on [T1, Tcr] and
    ``b + a·T − c22·A·sin(π(T−Tcr)/((1−f)·L1))`` on [Tcr, T2]; L1 = T2 − T1, Tcr = T1 + f·L1.
    A (mm) is the gap between the branches at the crossing point Tcr. ``g`` (0 … 1] is the
    paper's rule for a bending cooling branch: only its T2 moves (g = 1 is the plain model).
    """

    cp: CommonPoints
    amplitude_mm: float
    f: float
    c11: float = 1.0
    c21: float = 1.0
    c22: float = 1.0
    g: float = 1.0

    name = "2"

    def _dev(self, t: np.ndarray, heating: np.ndarray, t1: float, t2: float, a: float):
        l1 = max(t2 - t1, 1e-9)
        tcr = t1 + self.f * l1
        cool = -self.c11 * a * np.sin(np.pi * np.clip((t - t1) / (self.g * l1), 0.0, 1.0))
        h1 = self.c21 * a * np.sin(np.pi * np.clip((t - t1) / (self.f * l1), 0.0, 1.0))
        h2 = -self.c22 * a * np.sin(np.pi * np.clip((t - tcr) / ((1.0 - self.f) * l1), 0.0, 1.0))
        return np.where(heating, np.where(t < tcr, h1, h2), cool)

    def evaluate(self, temperature_c: np.ndarray, heating: np.ndarray) -> np.ndarray:
        """Major loop, vectorised: heating[i] selects the branch for temperature_c[i]."""
        t = np.asarray(temperature_c, dtype=float)
        h = np.broadcast_to(np.asarray(heating, dtype=bool), t.shape)
        cp = self.cp
        slope = (cp.y2_mm - cp.y1_mm) / (cp.t2_c - cp.t1_c)
        y = cp.y1_mm + slope * (t - cp.t1_c) + self._dev(t, h, cp.t1_c, cp.t2_c, self.amplitude_mm)
        out = (t < cp.t1_c) | (t > cp.t2_c)
        if np.any(out):
            y = np.where(out, cp.outside(t), y)
        return y

    def branch(self, t: float, heating: bool, start: Point, target: Point) -> float:
        """One sample of :meth:`branch_array` (scalar arithmetic: the online stepper's speed)."""
        cp = self.cp
        if t < cp.t1_c or t > cp.t2_c:
            return cp.outside_scalar(t)
        (t1, y1), (t2, y2) = (start, target) if target[0] >= start[0] else (target, start)
        l1 = t2 - t1
        if l1 <= 1e-9:
            return start[1]
        major = abs(cp.y2_mm - cp.y1_mm)  # sub_amplitude, inline for the stepper's speed
        a = self.amplitude_mm * (min(abs(y2 - y1) / major, 1.0) if major > 1e-12 else 1.0)
        u = min(max((t - t1) / l1, 0.0), 1.0)
        y = y1 + (y2 - y1) * u
        if not heating:
            return y - self.c11 * a * math.sin(math.pi * min(u / self.g, 1.0))
        if u < self.f:
            return y + self.c21 * a * math.sin(math.pi * u / self.f)
        return y - self.c22 * a * math.sin(math.pi * (u - self.f) / (1.0 - self.f))

    def branch_array(self, t: np.ndarray, heating: bool, start: Point, target: Point):
        """A (possibly minor) branch from ``start`` towards ``target`` over temperatures ``t``:
        the major branch's shape on the sub-loop's chord, its amplitude rescaled to the
        sub-loop (:meth:`sub_amplitude`)."""
        cp = self.cp
        t = np.asarray(t, dtype=float)
        (t1, y1), (t2, y2) = (start, target) if target[0] >= start[0] else (target, start)
        l1 = t2 - t1
        if l1 <= 1e-9:
            y = np.full(t.shape, float(start[1]))
        else:
            a = self.sub_amplitude(start, target)
            u = np.clip((t - t1) / l1, 0.0, 1.0)
            y = y1 + (y2 - y1) * u
            if not heating:
                y = y - self.c11 * a * np.sin(np.pi * np.minimum(u / self.g, 1.0))
            else:
                y = y + np.where(
                    u < self.f,
                    self.c21 * a * np.sin(np.pi * u / self.f),
                    -self.c22 * a * np.sin(np.pi * (u - self.f) / (1.0 - self.f)),
                )
        out = (t < cp.t1_c) | (t > cp.t2_c)
        if np.any(out):
            y = np.where(out, cp.outside(t), y)
        return y

    def sub_amplitude(self, start: Point, target: Point) -> float:
        """Amplitude (mm) on the sub-loop between ``start`` and ``target``: the major one times
        the share of the major stroke that the sub-loop spans (a reversal early in a
        transformation opens a small loop however many kelvin it spans)."""
        cp = self.cp
        major = abs(cp.y2_mm - cp.y1_mm)
        share = abs(target[1] - start[1]) / major if major > 1e-12 else 1.0
        return self.amplitude_mm * min(share, 1.0)

    def parameters(self) -> dict[str, float]:
        d = asdict(self.cp)
        d.update(
            amplitude_mm=self.amplitude_mm,
            f=self.f,
            c11=self.c11,
            c21=self.c21,
            c22=self.c22,
            g=self.g,
        )
        return d


# --------------------------------------------------------------------------- our model
def _logistic(z):
    return 0.5 * (1.0 + np.tanh(0.5 * z))


@dataclass
class FractionBranch:
    """Austenite fraction on one major branch: a sharp and a broad logistic step.

    ``xi(T) = (1−w_broad)·σ((T−t_sharp)/s_sharp) + w_broad·σ((T−t_broad)/s_broad)``, σ the
    logistic function; centres in °C, widths in K, w_broad in [0, 1].
    """

    t_sharp_c: float
    s_sharp_k: float
    t_broad_c: float
    s_broad_k: float
    w_broad: float

    def xi(self, t):
        return (1.0 - self.w_broad) * _logistic((t - self.t_sharp_c) / self.s_sharp_k) + (
            self.w_broad * _logistic((t - self.t_broad_c) / self.s_broad_k)
        )

    def xi_scalar(self, t: float) -> float:
        def s(z: float) -> float:
            return 0.5 * (1.0 + math.tanh(0.5 * z))

        return (1.0 - self.w_broad) * s((t - self.t_sharp_c) / self.s_sharp_k) + self.w_broad * s(
            (t - self.t_broad_c) / self.s_broad_k
        )


def frank_copula(u, v, theta: float):
    """Frank's copula C(u, v) (u, v in [0, 1]): θ = 0 independence (u·v), θ → ∞ the upper
    bound min(u, v), θ < 0 towards the lower bound; scalars or arrays."""
    if isinstance(u, float) and isinstance(v, float):
        return _frank_scalar(u, v, theta)
    u = np.clip(u, 0.0, 1.0)
    v = np.clip(v, 0.0, 1.0)
    if abs(theta) < 1e-6:
        return u * v
    if theta < 0:
        return -np.log1p(np.expm1(-theta * u) * np.expm1(-theta * v) / np.expm1(-theta)) / theta
    # θ > 0 in a form without cancellation: min(u, v) minus a correction that vanishes as θ grows
    lo, hi = np.minimum(u, v), np.maximum(u, v)
    inner = 1.0 + np.exp(-theta * (hi - lo)) - np.exp(-theta * hi) - np.exp(-theta * (1.0 - lo))
    return lo - (np.log(np.maximum(inner, 1e-300)) - np.log1p(-np.exp(-theta))) / theta


def _frank_scalar(u: float, v: float, theta: float) -> float:
    """:func:`frank_copula` for two floats (the online stepper's speed)."""
    return _frank_of(theta)(u, v)


@functools.lru_cache(maxsize=256)
def _frank_of(theta: float):
    """:func:`_frank_scalar` for one θ: a function of (u, v) with θ's constants computed once
    (a fit evaluates it about a million times on a noisy recording)."""
    exp, expm1, log, log1p = math.exp, math.expm1, math.log, math.log1p
    if abs(theta) < 1e-6:
        return lambda u, v: min(max(u, 0.0), 1.0) * min(max(v, 0.0), 1.0)
    if theta < 0:
        e_theta = expm1(-theta)

        def lower(u: float, v: float) -> float:
            u, v = min(max(u, 0.0), 1.0), min(max(v, 0.0), 1.0)
            return -log1p(expm1(-theta * u) * expm1(-theta * v) / e_theta) / theta

        return lower
    c = log1p(-exp(-theta))

    def upper(u: float, v: float) -> float:
        u, v = min(max(u, 0.0), 1.0), min(max(v, 0.0), 1.0)
        lo, hi = min(u, v), max(u, v)
        inner = 1.0 + exp(-theta * (hi - lo)) - exp(-theta * hi) - exp(-theta * (1.0 - lo))
        return lo - (log(max(inner, 1e-300)) - c) / theta

    return upper


@dataclass
class SigmoidModel:
    """Our model: phase-fraction mixing of a martensite and an austenite line.

    ``y = (1−ξ)·(ym + km·(T−t_ref)) + ξ·(ya + ka·(T−t_ref))`` with ξ the austenite fraction of
    the branch (:class:`FractionBranch`). A minor branch from a reversal point (start) runs to
    its target (the previous reversal point or a common point, return-point memory) as
    ``ξ = ξs + (ξt − ξs)·(K(g) − K(gs))/(K(gt) − K(gs))``, g the major branch of the new
    direction at T, gs/gt at the start/target temperatures, so the model stays continuous at
    reversals and inner loops close. ``K`` comes from reading the two major branches as the
    distributions of the up- and down-switching temperatures of the wire's grains, coupled by
    Frank's copula C with ``memory_theta`` θ (a Preisach view in closed form): on heating
    ``K(u) = u − C(u, ξs)``, on cooling ``K(v) = C(ξs, v)``. θ = 0 (independent switching
    temperatures) is the scaled law: the major branch scaled through the reversal point, as in
    Liang–Rogers or Brinson; θ → ∞ (each grain's two temperatures locked together) holds ξ until
    the major branch comes back to it, a Preisach wiping-out; in between the first-order
    reversal curves of a Preisach density. θ is fitted on partial loops when the data have them.
    """

    ym_mm: float
    km_mm_per_k: float
    ya_mm: float
    ka_mm_per_k: float
    heating_branch: FractionBranch
    cooling_branch: FractionBranch
    t_ref_c: float = 30.0
    memory_theta: float = 0.0

    name = "sigmoid"

    def _lines(self, t):
        d = t - self.t_ref_c
        return self.ym_mm + self.km_mm_per_k * d, self.ya_mm + self.ka_mm_per_k * d

    def evaluate(self, temperature_c: np.ndarray, heating: np.ndarray) -> np.ndarray:
        """Major loop, vectorised: heating[i] selects the branch for temperature_c[i]."""
        t = np.asarray(temperature_c, dtype=float)
        xi = np.where(heating, self.heating_branch.xi(t), self.cooling_branch.xi(t))
        ym, ya = self._lines(t)
        return ym + xi * (ya - ym)

    def fraction_at(self, t: float, y: float) -> float:
        """Austenite fraction (0 … 1) that gives length y at temperature t."""
        ym, ya = self._lines(t)
        if abs(ya - ym) < 1e-12:
            return 0.0
        return min(max((y - ym) / (ya - ym), 0.0), 1.0)

    def _minor_fraction(self, g, heating: bool, start: Point, target: Point):
        """ξ on the branch from ``start`` to ``target`` where the major branch of this
        direction is ``g`` (scalar or array)."""
        br = self.heating_branch if heating else self.cooling_branch
        xs = self.fraction_at(*start)
        xe = self.fraction_at(*target)
        gs, ge = br.xi_scalar(start[0]), br.xi_scalar(target[0])
        th = self.memory_theta
        if th != 0.0:
            if heating:
                g, gs, ge = (u - frank_copula(u, xs, th) for u in (g, gs, ge))
            else:
                g, gs, ge = (frank_copula(xs, v, th) for v in (g, gs, ge))
        lo, hi = min(xs, xe), max(xs, xe)
        if isinstance(g, float):
            return xs if abs(ge - gs) < 1e-12 else min(max(xs + (xe - xs) * (g - gs) / (ge - gs),
                                                           lo), hi)  # fmt: skip
        if abs(ge - gs) < 1e-12:
            return xs + 0.0 * g
        return np.clip(xs + (xe - xs) * (g - gs) / (ge - gs), lo, hi)

    def branch(self, t: float, heating: bool, start: Point, target: Point) -> float:
        """One sample on a (possibly minor) branch from ``start`` towards ``target``."""
        br = self.heating_branch if heating else self.cooling_branch
        xi = float(self._minor_fraction(br.xi_scalar(t), heating, start, target))
        d = t - self.t_ref_c
        ym = self.ym_mm + self.km_mm_per_k * d
        ya = self.ya_mm + self.ka_mm_per_k * d
        return ym + xi * (ya - ym)

    def branch_run(
        self, ts: list[float], heating: bool, start: Point, target: Point
    ) -> list[float]:
        """:meth:`branch` at each of a few temperatures (°C) of one run, the same numbers, with
        what depends on the run's ends computed once (a noisy recording's many short runs)."""
        br = self.heating_branch if heating else self.cooling_branch
        xs = self.fraction_at(*start)
        xe = self.fraction_at(*target)
        gs, ge = br.xi_scalar(start[0]), br.xi_scalar(target[0])
        th = self.memory_theta
        cop = _frank_of(th)
        if th != 0.0:
            if heating:
                gs, ge = gs - cop(gs, xs), ge - cop(ge, xs)
            else:
                gs, ge = cop(xs, gs), cop(xs, ge)
        lo, hi = min(xs, xe), max(xs, xe)
        flat = abs(ge - gs) < 1e-12
        out = []
        for t in ts:
            g = br.xi_scalar(t)
            if th != 0.0:
                g = g - cop(g, xs) if heating else cop(xs, g)
            xi = xs if flat else min(max(xs + (xe - xs) * (g - gs) / (ge - gs), lo), hi)
            d = t - self.t_ref_c
            ym = self.ym_mm + self.km_mm_per_k * d
            ya = self.ya_mm + self.ka_mm_per_k * d
            out.append(ym + xi * (ya - ym))
        return out

    def branch_array(self, t: np.ndarray, heating: bool, start: Point, target: Point):
        """:meth:`branch` over an array of temperatures (°C)."""
        br = self.heating_branch if heating else self.cooling_branch
        xi = self._minor_fraction(br.xi(t), heating, start, target)
        ym, ya = self._lines(t)
        return ym + xi * (ya - ym)

    def transformation_range(self, tail: float = 0.005) -> tuple[float, float]:
        """Temperatures (°C) below/above which both branches are within ``tail`` of pure phase."""
        grid = np.linspace(-100.0, 400.0, 5001)
        xh = self.heating_branch.xi(grid)
        xc = self.cooling_branch.xi(grid)
        lo = grid[np.nonzero(np.maximum(xh, xc) > tail)[0][0]]
        hi = grid[np.nonzero(np.minimum(xh, xc) < 1.0 - tail)[0][-1]]
        return float(lo), float(hi)

    def common_points(self) -> CommonPoints:
        t1, t2 = self.transformation_range()
        ym1, _ = self._lines(t1)
        _, ya2 = self._lines(t2)
        return CommonPoints(t1, float(ym1), t2, float(ya2))

    def parameters(self) -> dict[str, float]:
        d = {
            "ym_mm": self.ym_mm,
            "km_mm_per_k": self.km_mm_per_k,
            "ya_mm": self.ya_mm,
            "ka_mm_per_k": self.ka_mm_per_k,
            "t_ref_c": self.t_ref_c,
            "memory_theta": self.memory_theta,
        }
        for prefix, br in (("heat", self.heating_branch), ("cool", self.cooling_branch)):
            for k, v in asdict(br).items():
                d[f"{prefix}_{k}"] = v
        return d


# --------------------------------------------------------------------------- online stepper
class LoopStepper:
    """Online, one sample at a time: tracks branch direction and reversal points.

    ``step(T)`` returns the modelled length. A reversal is detected when the temperature moves
    more than ``deadband_k`` back from its extreme; the extreme becomes a reversal point
    (:class:`~smabench.physics.memory.ReversalMemory`: the branch runs from it towards the
    previous reversal point of the other kind, an inner loop, or, when there is none, towards
    the major common point, an incomplete cycle; passing the target wipes the inner loop out).
    While the temperature is back from its extreme but still inside the deadband, the length
    follows the branch that a reversal at the extreme would start: that branch passes through
    the extreme point, so the path is continuous whether the reversal is then confirmed or the
    temperature goes on past the extreme (the old branch passes through it as well).
    """

    def __init__(self, model, deadband_k: float = 0.5, heating: bool = True) -> None:
        self.model = model
        self.deadband_k = float(deadband_k)
        cp = model.common_points() if hasattr(model, "common_points") else model.cp
        self.low: Point = (cp.t1_c, cp.y1_mm)
        self.high: Point = (cp.t2_c, cp.y2_mm)
        self.memory = ReversalMemory(self.low, self.high, heating)
        self.turns = TurnDetector(self.deadband_k, heating)
        self.reset(heating)

    @property
    def heating(self) -> bool:
        return self.memory.heating

    @property
    def stack(self) -> list[Point]:
        return self.memory.stack

    def reset(self, heating: bool = True) -> None:
        """Forget the history: start on the major branch in the given direction."""
        self.memory.reset(heating)
        self.turns.reset(heating)
        self._ext_y = math.nan
        self.last_y_mm = float("nan")

    def step(self, temperature_c: float) -> float:
        """Length (mm) at this temperature sample, given the history so far."""
        t = float(temperature_c)
        mem, turns = self.memory, self.turns
        if turns.update(t):
            mem.reverse((turns.turn_at, self._ext_y))
        mem.wipe(t)
        if turns.backing(t):
            pending = mem.reversed_at((turns.extreme, self._ext_y), t)
            y = self.model.branch(t, pending.heating, *pending.start_target())
        else:
            y = self.model.branch(t, mem.heating, *mem.start_target())
            self._ext_y = y
        self.last_y_mm = y
        return y

    def run(self, temperature_c: np.ndarray) -> np.ndarray:
        """Step through a whole sequence (convenience for offline use)."""
        return np.array([self.step(t) for t in np.asarray(temperature_c, dtype=float)])


SHORT_RUN = 8  # runs shorter than this are stepped point by point (numpy's overhead)


def starts_heating(model, temperature_c: float) -> bool:
    """The major branch a history starts on, from the state its first sample shows: a recording
    that starts in the cold half of the model's transformation range (below the middle of its
    common points) starts at the martensite end, on the heating branch from the cold common
    point, whichever way the temperature moves first (a first move down is then a reversal on
    the martensite line, not a start on the cooling branch at mid-stroke); one that starts in
    the hot half starts at the austenite end, on the cooling branch. The cold half: below the
    heating branch's half-transformation for a phase-fraction model (its common points follow
    the tails of both branches, which the data need not constrain), else below the middle of
    the common points."""
    t0 = float(temperature_c)
    if hasattr(model, "heating_branch"):
        return model.heating_branch.xi_scalar(t0) < 0.5
    cp = model.common_points() if hasattr(model, "common_points") else model.cp
    return t0 < 0.5 * (cp.t1_c + cp.t2_c)


def run_history(model, temperature_c, deadband_k: float, heating: bool = True,
                runs=None) -> np.ndarray:  # fmt: skip
    """Length (mm) along a whole temperature history, the same as stepping a
    :class:`LoopStepper` through it, but run by run (:func:`~smabench.physics.memory.branch_runs`)
    and vectorised where the model has a ``branch_array``. ``runs``: precomputed runs of this
    history (they depend on the temperatures and the common points' temperatures only)."""
    t = np.asarray(temperature_c, dtype=float)
    cp = model.common_points() if hasattr(model, "common_points") else model.cp
    low, high = (cp.t1_c, cp.y1_mm), (cp.t2_c, cp.y2_mm)
    if runs is None:
        runs = branch_runs(t, low[0], high[0], deadband_k, heating)
    y = np.empty(t.size)
    fixed = {LOW: low, HIGH: high}
    vector = hasattr(model, "branch_array")
    by_run = hasattr(model, "branch_run")
    for r in runs:
        start = fixed[r.start] if r.start < 0 else (float(t[r.start]), float(y[r.start]))
        target = fixed[r.target] if r.target < 0 else (float(t[r.target]), float(y[r.target]))
        seg = t[r.i0 : r.i1]
        if vector and seg.size >= SHORT_RUN:
            y[r.i0 : r.i1] = model.branch_array(seg, r.heating, start, target)
        elif by_run:
            y[r.i0 : r.i1] = model.branch_run(seg.tolist(), r.heating, start, target)
        else:
            y[r.i0 : r.i1] = [model.branch(float(x), r.heating, start, target) for x in seg]
    return y
