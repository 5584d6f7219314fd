"""The controller's loop model of the wire under load, and its online inverse.

Identification (:func:`identify_loop_model`): the model is fitted to an identification cycle
simulated with :func:`smabench.physics.plant.simulate_plant` for the configured wire and load —
two slow ramps of the heating power (0 → the power that holds 100 °C → 0 over 240 s each way,
then passive cooling), slow enough (≈ 0.3 K/s through the transformation) that the loop is the
quasi-static one: a faster ramp bakes the wire's kinetic lag into the branches (with 30 s ramps
the cooling branch came out 1.3 K colder, 0.5 mm at its steepest, than the wire at 1 K/s).
The kinetic lag is identified separately (:func:`identify_kinetic_lag`): the delay of the
temperature that maps a second, 8× faster cycle onto the quasi-static model, per branch
(≈ 0.04 s heating, 0.42 s cooling on the mock's wire); the feed-forward leads by it. Both runs
have **no plant effects switched on**, whatever the bench runs with: the controller's model
never knows latent heat, sensor lag etc. The temperature axis is the one the runtime estimates
online (the heat balance driven by the current, :mod:`smabench.physics.thermal`), the length
axis the simulated sensor reading (with its noise). The identification could equally be run on
the bench (``ramp`` sessions fed to :func:`fit_from_samples`); the simulated cycles are the
default because they cost about a second and need no wire time.

Inverse (:class:`InverseLoop`): position setpoint → temperature on the branch that the motion
needs (the setpoint falling = the wire shortening = heating branch; rising = cooling branch).
Reversal points follow the rules of :class:`~smabench.physics.loop_models.LoopStepper` — the
same :class:`~smabench.physics.memory.ReversalMemory`, here driven by the setpoint:
an incomplete cycle moves the first common point to the reversal point (the branch runs from
there to the major common point); with ``memory`` > 1 the older reversal points are kept as
well, so inner loops head for the previous reversal point and are wiped out when it is passed.
The default keeps one point: the references here do not nest loops, and a stack of measured
points drifts apart from the model's when the wire lags the reference.

Online adaptation, as in the paper:

- at a reversal the reversal point is taken from the wire — its extreme on the branch just
  left (the temperature the law plans with — the runtime's estimate, or FF+PID's observed
  temperature — and the measured position at that sample) — not
  from the model, so the new branch starts where the wire really turned (the first common
  point of the new branch is updated);
- the first measured values on each new branch (``refit_samples`` samples once the branch has
  moved clear of the reversal) refit the branch amplitude — the deviation of the branch from the
  chord between its start and target point — by one-parameter least squares; the refit scale is
  used for the rest of the branch and carried (averaged) to the next branch of the same
  direction, so the model follows the wire during a run.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from smabench.physics.identify import FitResult, fit_loop
from smabench.physics.memory import ReversalMemory, TurnDetector
from smabench.physics.plant import simulate_plant
from smabench.physics.thermal import current_for_steady_temperature, simulate_temperature
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)

Point = tuple[float, float]  # (temperature °C, position mm)

IDENT_HOT_C = 100.0
IDENT_SLOW_RAMP_S = 240.0
"""Ramp time, s, of the quasi-static identification cycle: slow enough (≈ 0.3 K/s through the
transformation) that the kinetic lag of the wire shifts the branches by < 0.2 K."""
IDENT_SLOW_DT_S = 0.05
IDENT_FIT_SAMPLES = 4000  # samples of the slow cycle given to the fit (its cost grows ~ n²)
IDENT_FAST_RAMP_S = 30.0
"""Ramp time, s, of the second cycle, ≈ 8× faster: the branch shift against the quasi-static
model gives each branch's kinetic lag."""
IDENT_FAST_DT_S = 0.01


def identification_profile(
    wire: Wire = PAPER_WIRE,
    ambient_c: float = 22.0,
    ramp_s: float = IDENT_SLOW_RAMP_S,
    dt_s: float = IDENT_SLOW_DT_S,
) -> tuple[np.ndarray, np.ndarray]:
    """Current profile of an identification run: two ramp cycles, each 0 → the power that holds
    100 °C → 0 over ``ramp_s`` s each way (linear in power), then passive cooling;
    returns (t_s, current_a)."""
    i_hot = float(current_for_steady_temperature(IDENT_HOT_C, wire, ambient_c))
    n = int(round(ramp_s / dt_s))
    up = np.sqrt(np.linspace(0.0, 1.0, n)) * i_hot  # linear in power: even heating rates
    cool = int(round(max(10.0, ramp_s / 3.0) / dt_s))
    one = np.concatenate([up, np.full(n // 10, i_hot), up[::-1], np.zeros(cool)])
    cur = np.concatenate([one, one])
    return np.arange(cur.size) * dt_s, cur


def _second_cycle(load_kg, wire, ambient_c, seed, ramp_s, dt_s):
    t, cur = identification_profile(wire, ambient_c, ramp_s, dt_s)
    trace = simulate_plant(t, cur, load_kg=load_kg, wire=wire, ambient_c=ambient_c, seed=seed)
    temp = simulate_temperature(t, cur, wire, ambient_c)
    half = t.size // 2
    return t[half:], temp[half:], trace.position_mm[half:]


def identify_loop_model(
    load_kg: float,
    wire: Wire = PAPER_WIRE,
    model: str = "sigmoid",
    ambient_c: float = 22.0,
    seed: int = 1,
) -> FitResult:
    """Fit ``model`` (``sigmoid``, ``1`` or ``2``) to the simulated quasi-static identification
    cycle of the nominal plant (no effects) under ``load_kg``; the fit uses the second cycle
    (history-free)."""
    _, temp, pos = _second_cycle(load_kg, wire, ambient_c, seed, IDENT_SLOW_RAMP_S,
                                 IDENT_SLOW_DT_S)  # fmt: skip
    every = max(1, temp.size // IDENT_FIT_SAMPLES)
    return fit_from_samples(temp[::every], pos[::every], model)


def identify_kinetic_lag(
    fit: FitResult,
    load_kg: float,
    wire: Wire = PAPER_WIRE,
    ambient_c: float = 22.0,
    seed: int = 2,
    max_lag_s: float = 2.0,
) -> tuple[float, float]:
    """Kinetic lag (s) of the heating and of the cooling branch: the delay of the temperature
    that best maps the fast identification cycle onto the quasi-static model ``fit`` (least
    squares over the samples where the wire moves). The wire's transformation lags its
    temperature; the feed-forward leads the reference by these times."""
    t, temp, pos = _second_cycle(load_kg, wire, ambient_c, seed, IDENT_FAST_RAMP_S,
                                 IDENT_FAST_DT_S)  # fmt: skip
    dt = float(t[1] - t[0])
    heating = np.gradient(temp) > 0
    moving = np.abs(np.gradient(pos)) > 1e-2 * dt * (pos.max() - pos.min())
    lags = []
    for branch in (True, False):
        sel = moving & (heating == branch)
        best = (0.0, math.inf)
        for k in range(int(max_lag_s / dt) + 1):
            lagged = np.concatenate([np.full(k, temp[0]), temp[: temp.size - k]])
            model_y = fit.loop_model.evaluate(lagged, np.full(temp.size, branch))
            cost = float(np.mean((model_y - pos)[sel] ** 2))
            if cost < best[1]:
                best = (k * dt, cost)
        lags.append(best[0])
    log.info("kinetic lag: heating %.3f s, cooling %.3f s", lags[0], lags[1])
    return lags[0], lags[1]


def fit_from_samples(temperature_c, position_mm, model: str = "sigmoid") -> FitResult:
    """Fit a loop model to measured (estimated temperature, position) samples of a cycle."""
    result = fit_loop(temperature_c, position_mm, model)
    log.info("controller loop model %s: %.2f %% of stroke", model, result.nrmse_percent)
    return result


def common_points(model) -> tuple[Point, Point]:
    cp = model.common_points() if hasattr(model, "common_points") else model.cp
    return (cp.t1_c, cp.y1_mm), (cp.t2_c, cp.y2_mm)


@dataclass
class _Table:
    key: tuple
    y: np.ndarray  # increasing
    t: np.ndarray


class InverseLoop:
    """Online inverse of a loop model with reversal memory and adaptation (module docstring).

    ``t_min_c`` / ``t_max_c``: coldest (ambient) and hottest temperature the controller may use.
    ``deadband_mm``: the setpoint must move back this far from its extreme to count as a
    reversal. ``adapt``: take reversal points from the wire and refit amplitudes; a refitted
    amplitude outside ``scale_range`` is not used (it comes from samples the kinetic lag
    displaced, e.g. right after a step, not from the branch). ``memory``: reversal points kept
    (1 = the paper's moved first common point only). The reversal points and the direction live
    in a :class:`~smabench.physics.memory.ReversalMemory` driven by the setpoint.
    """

    def __init__(
        self,
        model,
        t_min_c: float,
        t_max_c: float,
        deadband_mm: float = 0.003,
        adapt: bool = True,
        refit_samples: int = 12,
        table_points: int = 97,
        scale_range: tuple[float, float] = (0.5, 2.0),
        memory: int = 1,
        flat_fraction: float = 0.004,
        heating: bool = True,
    ) -> None:
        self.model = model
        self.t_min_c, self.t_max_c = float(t_min_c), float(t_max_c)
        self.deadband_mm = deadband_mm
        self.adapt = adapt
        self.refit_samples = refit_samples
        self.table_points = table_points
        self.scale_range = scale_range  # plausible refitted amplitudes
        self.memory = memory
        self.flat_fraction = flat_fraction  # "no motion" band at a branch start, of the stroke
        self.scale: dict[bool, float] = {True: 1.0, False: 1.0}
        self.low, self.high = common_points(self.model)
        self.reversal_memory = ReversalMemory(self.low, self.high, heating, key=1, depth=memory)
        self.turns = TurnDetector(deadband_mm, self._setpoint_rising(heating))
        self._tables: dict[tuple, _Table] = {}  # branch tables by key (shared with previews)
        self._branch_scale = 1.0
        self._table: _Table | None = None
        self._obs: list[Point] = []
        self._refit_done = False
        self._wire_point: Point | None = None
        self._wire_ext: Point | None = None  # the wire's extreme on the current branch
        self.reversals = 0
        self.refits: list[float] = []

    def _setpoint_rising(self, heating: bool) -> bool:
        """Whether the position setpoint rises on a branch of this direction."""
        return heating == (self.high[1] > self.low[1])

    @property
    def heating(self) -> bool:
        return self.reversal_memory.heating

    @property
    def stack(self) -> list[Point]:
        return self.reversal_memory.stack

    # ----------------------------------------------------------------- geometry
    def forward(self, t_c: float, heating: bool) -> float:
        """Model position on the major branch at temperature ``t_c``."""
        start, target = (self.low, self.high) if heating else (self.high, self.low)
        return float(self.model.branch(float(t_c), heating, start, target))

    def reachable_mm(self, margin_fraction: float = 0.1) -> tuple[float, float]:
        """(shortest, longest) position the controller can hold: the hot end at ``t_max_c`` and
        the cold end at ``t_min_c`` + 1 K, each moved inward by ``margin_fraction`` of the
        stroke (near the ends the wire barely moves with temperature)."""
        grid = np.linspace(self.t_min_c + 1.0, self.t_max_c, 200)
        ys = [self.forward(t, h) for t in grid for h in (True, False)]
        lo, hi = float(min(ys)), float(max(ys))
        m = margin_fraction * (hi - lo)
        return lo + m, hi - m

    def _start_target(self) -> tuple[Point, Point]:
        return self.reversal_memory.start_target()

    def _branch_array(self, ts: np.ndarray, start: Point, target: Point, s: float) -> np.ndarray:
        """:meth:`_branch_y` over an array of temperatures (vectorised where the model has a
        ``branch_array``, point by point otherwise)."""
        m = self.model
        if not hasattr(m, "branch_array"):
            return np.array([self._branch_y(float(t), start, target, s) for t in ts])
        y = m.branch_array(ts, self.heating, start, target)
        if s != 1.0 and target[0] != start[0]:
            u = (ts - start[0]) / (target[0] - start[0])
            chord = start[1] + u * (target[1] - start[1])
            inside = (u >= 0.0) & (u <= 1.0)
            y = np.where(inside, chord + s * (y - chord), y)
        return y

    def _branch_y(self, t: float, start: Point, target: Point, s: float) -> float:
        y = float(self.model.branch(t, self.heating, start, target))
        if s != 1.0 and target[0] != start[0]:
            u = (t - start[0]) / (target[0] - start[0])
            if 0.0 <= u <= 1.0:
                chord = start[1] + u * (target[1] - start[1])
                y = chord + s * (y - chord)
        return y

    def _get_table(self) -> _Table:
        start, target = self._start_target()
        inner = self.reversal_memory.inner()
        if self.heating:
            t_end = target[0] if inner else self.t_max_c
        else:
            t_end = target[0] if inner else self.t_min_c
        key = (self.heating, start, target, t_end, self._branch_scale)
        if self._table is not None and self._table.key == key:
            return self._table
        cached = self._tables.get(key)
        if cached is not None:
            self._table = cached
            return cached
        # the table spans only temperatures the wire can have (a major branch's common point
        # may lie far outside, where the model's tails are flat)
        t0 = max(start[0], self.t_min_c) if self.heating else min(start[0], self.t_max_c)
        if (t_end - t0) * (1 if self.heating else -1) <= 1e-6:
            t_end = t0 + (1e-3 if self.heating else -1e-3)
        ts = np.linspace(t0, t_end, self.table_points)
        ys = self._branch_array(ts, start, target, self._branch_scale)
        if t0 == start[0]:
            ys[0] = start[1]
        k = np.arange(ys.size) * 1e-9
        # monotone envelope: heating, position falls with T; cooling (T decreasing), it rises
        ys = np.minimum.accumulate(ys) - k if self.heating else np.maximum.accumulate(ys) + k
        order = np.argsort(ys)
        self._table = _Table(key, ys[order], ts[order])
        if len(self._tables) > 64:
            self._tables.clear()
        self._tables[key] = self._table
        return self._table

    def _invert(self, y: float) -> float:
        """Temperature for ``y`` on the current branch. A setpoint behind the branch's start
        (not reachable in this direction, e.g. right after a reversal inside the hysteresis
        gap) maps to the end of the flat part next to the start — where the branch starts to
        move — rather than to the start itself: the wire crosses the gap at once."""
        tab = self._get_table()
        tol = self.flat_fraction * abs(self.high[1] - self.low[1])
        if self.heating:
            y_start = tab.y[-1]
            if y >= y_start - tol:
                k = int(np.searchsorted(tab.y, y_start - tol))
                return float(tab.t[min(max(k - 1, 0), tab.t.size - 1)])
        else:
            y_start = tab.y[0]
            if y <= y_start + tol:
                k = int(np.searchsorted(tab.y, y_start + tol))
                return float(tab.t[min(k, tab.t.size - 1)])
        return float(np.interp(y, tab.y, tab.t))

    def branch_position(self, t_c: float) -> float:
        """Model position (mm) at ``t_c`` on the active branch (the one the inverse uses)."""
        tab = self._get_table()
        return float(np.interp(t_c, tab.t[::-1], tab.y[::-1]))

    def slope_mm_per_k(self, t_c: float, half_width_k: float = 0.5) -> float:
        """dy/dT (mm/K, ≤ 0: the wire shortens as it heats) of the active branch at ``t_c``."""
        y_hi = self.branch_position(t_c + half_width_k)
        y_lo = self.branch_position(t_c - half_width_k)
        return (y_hi - y_lo) / (2.0 * half_width_k)

    # ----------------------------------------------------------------- online
    def observe(self, temperature_c: float, position_mm: float) -> None:
        """The wire's state this tick (estimated temperature, measured position)."""
        if not (math.isfinite(temperature_c) and math.isfinite(position_mm)):
            return
        self._wire_point = (float(temperature_c), float(position_mm))
        ext = self._wire_ext
        if ext is None or (temperature_c > ext[0] if self.heating else temperature_c < ext[0]):
            self._wire_ext = self._wire_point
        if not self.adapt or self._refit_done:
            return
        start, target = self._start_target()
        span = target[0] - start[0]
        if abs(span) < 1.0:
            return
        u = (temperature_c - start[0]) / span
        if 0.05 < u < 0.95:
            self._obs.append(self._wire_point)
            if len(self._obs) >= self.refit_samples:
                self._refit(start, target)

    def _refit(self, start: Point, target: Point) -> None:
        self._refit_done = True
        ts = np.array([p[0] for p in self._obs])
        ym = np.array([p[1] for p in self._obs])
        u = (ts - start[0]) / (target[0] - start[0])
        chord = start[1] + u * (target[1] - start[1])
        dev = np.array([self.model.branch(float(t), self.heating, start, target) for t in ts])
        dev = dev - chord
        denom = float(np.dot(dev, dev))
        stroke = abs(self.high[1] - self.low[1])
        if denom < (0.03 * stroke) ** 2 * len(ts):
            return  # the branch is too close to its chord here: amplitude not observable
        s = float(np.dot(dev, ym - chord) / denom)
        if not self.scale_range[0] <= s <= self.scale_range[1]:
            log.info("branch amplitude refit %.2f outside %s: not used", s, self.scale_range)
            return
        self._branch_scale = s
        self.scale[self.heating] = 0.5 * (self.scale[self.heating] + s)
        self.refits.append(s)

    def _reverse(self, y_ext: float) -> None:
        if self.adapt and self._wire_ext is not None:
            point = self._wire_ext
        else:
            point = (self._invert(y_ext), y_ext)
        self.reversal_memory.reverse(point)
        self.reversals += 1
        self._branch_scale = self.scale[self.heating]
        self._obs = []
        self._refit_done = False
        self._wire_ext = self._wire_point

    def temperature(
        self, y_sp: float, commit: bool = True, deadband_mm: float | None = None
    ) -> float:
        """Temperature (°C) for position setpoint ``y_sp`` (mm). With ``commit`` the direction
        and reversal memory advance (once per tick); without, a look-ahead on the current
        branch that leaves the state alone. ``deadband_mm``: this tick's reversal deadband
        (default ``self.deadband_mm``)."""
        y = float(y_sp)
        if not commit:
            return self._invert(y)
        self.turns.deadband = self.deadband_mm if deadband_mm is None else deadband_mm
        if self.turns.update(y):
            self._reverse(self.turns.turn_at)
        self.reversal_memory.wipe(y)
        return self._invert(y)

    def preview(self, ys) -> list[float]:
        """Temperatures for a future setpoint sequence, reversals included, without touching
        this inverse's state (reversal points from the model, no refit)."""
        p = object.__new__(InverseLoop)
        p.__dict__.update(self.__dict__)
        m = self.reversal_memory
        p.reversal_memory = ReversalMemory(m.low, m.high, m.heating, m.key, m.depth, list(m.stack))
        p.turns = TurnDetector(self.turns.deadband, self.turns.rising, self.turns.extreme)
        p.scale = dict(self.scale)
        p.refits = []
        p.adapt = False
        p._wire_point = p._wire_ext = None
        p._refit_done = True
        return [p.temperature(y, commit=True) for y in ys]

    def state(self) -> dict:
        return {
            "heating": self.heating,
            "stack": [list(p) for p in self.stack],
            "scale_heating": self.scale[True],
            "scale_cooling": self.scale[False],
            "reversals": self.reversals,
            "refits": len(self.refits),
        }
