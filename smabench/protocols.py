"""Experiment protocols: online state machines that turn time and position into a current command.

The paper's three excitations plus steps and ramps:
- ``complete``: heat at ``current_a`` for ``heat_s``, then cool with no current until the position
  has settled (mean drift below ``settle_mm`` across ``settle_window_s``) or after
  ``cool_timeout_s``.
- ``incomplete``: as complete, but reheat after ``partial_cool_s`` (before the wire has cooled), so
  the first common point moves to the reversal point.
- ``inner``: short heat/cool pulses (``inner_heat_s``/``inner_cool_s``) inside the transformation,
  after one complete heat-up, making inner loops.
- ``step``: current steps through ``levels_a``, each held ``hold_s``.
- ``ramp``: current ramps 0 → ``current_a`` → 0 over ``ramp_s`` each way, ``cycles`` times.

Position references for the closed-loop controllers (:mod:`smabench.control`), ``cycles``
periods of ``period_s`` about ``offset_mm`` with ``amplitude_mm``, after a ``lead_in_s`` hold:
``step`` (with a controller: a square wave in position; without one: current steps),
``staircase``, ``sine``, ``triangle``; see :class:`smabench.control.reference.Reference`.

Each protocol is fed ``update(t_s, position_mm)`` at the loop rate and returns a
:class:`~smabench.commands.CommandStep`; ``done`` is True once it has finished.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

from smabench.commands import CommandStep

log = logging.getLogger(__name__)

PROTOCOL_NAMES = ("cycles", "incomplete", "inner", "step", "ramp", "staircase", "sine", "triangle")
REFERENCE_NAMES = ("step", "staircase", "sine", "triangle")
"""Protocols that are position references for a controller (``step`` is both)."""
OPEN_LOOP_NAMES = ("cycles", "incomplete", "inner", "step", "ramp")


@dataclass
class ProtocolSettings:
    """Parameters of every protocol; each protocol reads the ones it needs (units in names)."""

    name: str = "cycles"
    cycles: int = 5
    current_a: float = 1.0
    heat_s: float = 3.0
    cool_timeout_s: float = 15.0
    min_cool_s: float = 3.0
    settle_mm: float = 0.005
    settle_window_s: float = 1.0
    partial_cool_s: float = 2.0
    inner_heat_s: float = 0.4
    inner_cool_s: float = 0.8
    levels_a: tuple[float, ...] = (0.4, 0.8, 1.2, 0.8, 0.4, 0.0)
    hold_s: float = 4.0
    ramp_s: float = 5.0
    # position references (closed loop)
    amplitude_mm: float = 0.8
    offset_mm: float | None = None  # None: the middle of the reachable stroke
    period_s: float = 20.0
    lead_in_s: float = 8.0
    max_rise_mm_s: float | None = None  # natural-cooling limit told to the reference generator

    def validate(self, max_current_a: float, closed_loop: bool = False) -> None:
        """Raise ValueError naming the setting that is out of range. ``closed_loop``: the
        protocol feeds a controller (a position reference) rather than the current directly."""
        if self.name not in PROTOCOL_NAMES:
            raise ValueError(
                f"unknown protocol {self.name!r}; choose from {', '.join(PROTOCOL_NAMES)}"
            )
        if closed_loop and self.name not in REFERENCE_NAMES:
            raise ValueError(
                f"protocol {self.name!r} is open loop; with a controller choose a reference: "
                f"{', '.join(REFERENCE_NAMES)}"
            )
        if not closed_loop and self.name not in OPEN_LOOP_NAMES:
            raise ValueError(
                f"protocol {self.name!r} is a position reference: it needs a controller "
                "(--controller pid|ff|ffpid)"
            )
        if closed_loop:
            if not (math.isfinite(self.amplitude_mm) and 0.0 <= self.amplitude_mm <= 50.0):
                raise ValueError(f"amplitude must be in 0 … 50 mm, got {self.amplitude_mm}")
            if not 0.5 <= self.period_s <= 3600.0:
                raise ValueError(f"period must be in 0.5 … 3600 s, got {self.period_s}")
            if not 0.0 <= self.lead_in_s <= 600.0:
                raise ValueError(f"lead-in must be in 0 … 600 s, got {self.lead_in_s}")
            if self.max_rise_mm_s is not None and not self.max_rise_mm_s > 0:
                raise ValueError(f"max_rise_mm_s must be > 0, got {self.max_rise_mm_s}")
        if not 1 <= self.cycles <= 10_000:
            raise ValueError(f"cycles must be in 1 … 10000, got {self.cycles}")
        currents = (self.current_a, *self.levels_a) if self.name == "step" else (self.current_a,)
        for c in currents:
            if not 0.0 <= c <= max_current_a:
                raise ValueError(f"current {c} A is outside 0 … {max_current_a} A (driver limit)")
        for name in (
            "heat_s",
            "cool_timeout_s",
            "partial_cool_s",
            "inner_heat_s",
            "inner_cool_s",
            "hold_s",
            "ramp_s",
            "settle_window_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


class _Settle:
    """Tracks whether the position has settled: mean drift across a trailing window, mm."""

    def __init__(self, window_s: float, tol_mm: float) -> None:
        self.window_s, self.tol_mm = window_s, tol_mm
        self.buf: deque[tuple[float, float]] = deque()

    def reset(self) -> None:
        self.buf.clear()

    def update(self, t_s: float, position_mm: float) -> bool:
        if not math.isfinite(position_mm):
            return False
        self.buf.append((t_s, position_mm))
        while self.buf and t_s - self.buf[0][0] > self.window_s:
            self.buf.popleft()
        if t_s - self.buf[0][0] < 0.9 * self.window_s:
            return False
        # drift between the window's halves: insensitive to sensor noise, unlike max − min
        values = [p for _, p in self.buf]
        half = len(values) // 2
        drift = sum(values[half:]) / (len(values) - half) - sum(values[:half]) / max(half, 1)
        return abs(drift) <= self.tol_mm


class Protocol:
    """One run of a protocol; create anew for every run."""

    def __init__(self, settings: ProtocolSettings) -> None:
        if settings.name not in OPEN_LOOP_NAMES:
            raise ValueError(
                f"protocol {settings.name!r} is a position reference: run it with a controller"
            )
        self.s = settings
        self.cycle = 0
        self.phase = "heat"
        self.phase_t0_s: float | None = None
        self.settle = _Settle(settings.settle_window_s, settings.settle_mm)
        self.finished = False

    @property
    def progress(self) -> float:
        """Fraction done, 0 … 1."""
        total = self.s.cycles if self.s.name != "step" else len(self.s.levels_a)
        return min(1.0, self.cycle / max(total, 1))

    def _enter(self, phase: str, t_s: float) -> None:
        self.phase, self.phase_t0_s = phase, t_s
        self.settle.reset()

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        if self.phase_t0_s is None:
            self.phase_t0_s = t_s
        if self.finished:
            return CommandStep(0.0, self.cycle, "done", done=True)
        dt = t_s - self.phase_t0_s
        s = self.s
        name = s.name
        if name == "step":
            if dt >= s.hold_s:
                self.cycle += 1
                self._enter("hold", t_s)
                if self.cycle >= len(s.levels_a):
                    return self._finish()
            return CommandStep(s.levels_a[self.cycle], self.cycle, "hold")
        if name == "ramp":
            if dt >= 2 * s.ramp_s:
                self.cycle += 1
                self._enter("ramp", t_s)
                if self.cycle >= s.cycles:
                    return self._finish()
                dt = 0.0
            frac = dt / s.ramp_s if dt < s.ramp_s else 2.0 - dt / s.ramp_s
            return CommandStep(s.current_a * frac, self.cycle, "ramp")
        heat_s = s.heat_s
        if name == "inner" and self.cycle > 0:
            heat_s = s.inner_heat_s
        if self.phase == "heat":
            if dt >= heat_s:
                self._enter("cool", t_s)
                return CommandStep(0.0, self.cycle, "cool")
            return CommandStep(s.current_a, self.cycle, "heat")
        # cooling
        settled = self.settle.update(t_s, position_mm)
        if name == "incomplete" and self.cycle < s.cycles - 1:
            end = dt >= s.partial_cool_s
        elif name == "inner" and self.cycle < s.cycles - 1:
            end = dt >= s.inner_cool_s
        else:
            end = (dt >= s.min_cool_s and settled) or dt >= s.cool_timeout_s
        if end:
            self.cycle += 1
            if self.cycle >= s.cycles:
                return self._finish()
            self._enter("heat", t_s)
            return CommandStep(s.current_a, self.cycle, "heat")
        return CommandStep(0.0, self.cycle, "cool")

    def _finish(self) -> CommandStep:
        self.finished = True
        self.cycle = max(0, self.cycle - 1)
        return CommandStep(0.0, self.cycle, "done", done=True)
