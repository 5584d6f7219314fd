"""Reversal memory of a hysteresis branch: direction, turning points, return-point memory.

One implementation for every place that walks a loop model along a history: the online loop
stepper (:class:`~smabench.physics.loop_models.LoopStepper`, input = temperature), the
controller's inverse loop (:class:`~smabench.control.model.InverseLoop`, input = the position
setpoint) and the temperature observer. Pure Python, no I/O.

- :class:`TurnDetector` follows a scalar input in one direction and reports a reversal when the
  input has moved back more than a deadband from its extreme (noise inside the deadband is not a
  reversal).
- :class:`ReversalMemory` keeps the reversal points (points ``(T °C, y mm)``) with the paper's
  adaptation rules: a branch starts at the last reversal point and heads for the previous one
  (an inner loop: both common points moved) or, when there is none, for the major common point
  (an incomplete cycle: one common point moved). A reversal at or beyond a major common point
  ends a complete half cycle and clears the memory. Passing the previous reversal point wipes
  the inner loop out (return-point memory), so inner loops close where they started.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

Point = tuple[float, float]  # (temperature °C, position mm)


@dataclass
class TurnDetector:
    """Direction of a scalar input with a reversal deadband.

    ``rising``: the current direction; ``extreme``: the furthest input reached in it (None before
    the first sample). :meth:`update` returns True when the input has moved back more than
    ``deadband`` from the extreme: the direction flips and the new extreme is this input.
    """

    deadband: float
    rising: bool = True
    extreme: float | None = None
    turn_at: float | None = None  # the extreme where the last reversal happened

    def update(self, x: float) -> bool:
        """Feed one input sample; True when it completes a reversal (at ``turn_at``)."""
        if self.extreme is None:
            self.extreme = x
            return False
        if (x >= self.extreme) if self.rising else (x <= self.extreme):
            self.extreme = x
            return False
        if abs(x - self.extreme) > self.deadband:
            self.turn_at = self.extreme
            self.rising = not self.rising
            self.extreme = x
            return True
        return False

    def backing(self, x: float) -> bool:
        """True when ``x`` is behind the extreme but still inside the deadband (a reversal that
        may come: the branch it would start is already the right one to follow)."""
        if self.extreme is None:
            return False
        return x < self.extreme if self.rising else x > self.extreme

    def reset(self, rising: bool = True) -> None:
        self.rising = rising
        self.extreme = None


@dataclass
class ReversalMemory:
    """The reversal points of a hysteresis history (see module docstring).

    ``low`` / ``high``: the major loop's common points (cold and hot end). ``heating``: the
    branch direction. ``key``: the coordinate of a point the driving input is compared with when
    wiping out (0: temperature, 1: position). ``depth``: most reversal points kept (None: all;
    1: the paper's moved first common point only).
    """

    low: Point
    high: Point
    heating: bool = True
    key: int = 0
    depth: int | None = None
    stack: list[Point] = field(default_factory=list)

    def reset(self, heating: bool = True) -> None:
        """Forget the history: on the major branch in the given direction."""
        self.heating = heating
        self.stack.clear()

    def start_target(self) -> tuple[Point, Point]:
        """The branch's start point and the point it heads for."""
        s = self.stack
        if self.heating:
            return (s[-1] if s else self.low), (s[-2] if len(s) >= 2 else self.high)
        return (s[-1] if s else self.high), (s[-2] if len(s) >= 2 else self.low)

    def inner(self) -> bool:
        """True when the branch heads for a previous reversal point (an inner loop)."""
        return len(self.stack) >= 2

    def reverse(self, point: Point) -> None:
        """The branch turns at ``point``: flip the direction and remember the point, unless it
        lies at or beyond a common point (a complete half cycle: back on the major loop)."""
        self.heating = not self.heating
        if point[0] >= self.high[0] or point[0] <= self.low[0]:
            self.stack.clear()
            return
        self.stack.append(point)
        if self.depth is not None and len(self.stack) > self.depth:
            del self.stack[: len(self.stack) - self.depth]

    def _input_rising(self) -> bool:
        """Whether the driving input rises on the current branch."""
        if self.key == 0:
            return self.heating
        return self.heating == (self.high[self.key] > self.low[self.key])

    def wipe(self, x: float) -> int:
        """Wipe out the inner loops whose target the input ``x`` has passed; returns how many."""
        n = 0
        k = self.key
        while len(self.stack) >= 2:
            target = self.stack[-2][k]
            if not ((x > target) if self._input_rising() else (x < target)):
                break
            del self.stack[-2:]
            n += 1
        return n

    def reversed_at(self, point: Point, x: float | None = None) -> ReversalMemory:
        """A copy of this memory after a reversal at ``point`` (and a wipe at input ``x``):
        the branch that a reversal now would start, without changing this memory."""
        other = ReversalMemory(self.low, self.high, self.heating, self.key, self.depth,
                               list(self.stack))  # fmt: skip
        other.reverse(point)
        if x is not None:
            other.wipe(x)
        return other


@dataclass(frozen=True)
class Run:
    """Samples ``i0 … i1-1`` of a history that lie on one branch. ``start`` / ``target``: the
    sample index of the reversal point the branch leaves / heads for, or ``LOW`` / ``HIGH`` for
    the major common points."""

    i0: int
    i1: int
    heating: bool
    start: int
    target: int


LOW, HIGH = -1, -2


def branch_runs(temperature_c, t_low_c: float, t_high_c: float, deadband_k: float,
                heating: bool = True) -> list[Run]:  # fmt: skip
    """Split a temperature history into runs on one branch each, by the same rules as an online
    stepper (:class:`TurnDetector` + :class:`ReversalMemory`, the pending reversal inside the
    deadband included); reversal points are named by their sample index. The runs depend on the
    temperatures only, so a model can be evaluated run by run, vectorised, once the length at
    every reversal sample is known (it lies in an earlier run)."""
    mem = ReversalMemory((t_low_c, LOW), (t_high_c, HIGH), heating)
    turns = TurnDetector(deadband_k, heating)
    runs: list[Run] = []
    ext_i = 0
    cur = None
    i0 = 0
    for i, t in enumerate(map(float, temperature_c)):
        if turns.update(t):
            mem.reverse((turns.turn_at, ext_i))
        mem.wipe(t)
        if turns.backing(t):
            m = mem.reversed_at((turns.extreme, ext_i), t)
        else:
            m, ext_i = mem, i
        (_, s), (_, g) = m.start_target()
        key = (m.heating, int(s), int(g))
        if key != cur:
            if cur is not None:
                runs.append(Run(i0, i, *cur))
            cur, i0 = key, i
    if cur is not None:
        runs.append(Run(i0, len(temperature_c), *cur))
    return runs
