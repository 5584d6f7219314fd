"""Experiment protocols: online state machines that turn time and position into a current command.

The paper's three excitations plus steps and ramps:
- ``complete``: heat at ``current_a`` for ``heat_s``, then cool with no current until the wire
  has stretched back (by :data:`RECOVERED_FRACTION` of the heating's stroke: it holds still and
  contracted while it cools to Ms, which must not count as settled) and its position has settled
  (mean drift below ``settle_mm`` across ``settle_window_s``), or after ``cool_timeout_s``.
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
from dataclasses import asdict, dataclass
from typing import Any

from smabench.commands import CommandStep
from smabench.settings import (
    OPEN_LOOP_NAMES,
    PROTOCOL_NAMES,
    REFERENCE_NAMES,
    check_protocol,
    default,
)

log = logging.getLogger(__name__)

__all__ = ["OPEN_LOOP_NAMES", "PROTOCOL_NAMES", "REFERENCE_NAMES", "Protocol", "ProtocolSettings"]

_P = "protocol."

RECOVERED_FRACTION = 0.5
"""Part of the heating's stroke (position at the heat's start − at its end) the wire must have
stretched back before a complete cycle's cooling may settle."""


@dataclass
class ProtocolSettings:
    """Parameters of every protocol; each protocol reads the ones it needs (units in names).
    Defaults, ranges and help: :mod:`smabench.settings` (keys ``protocol.<field>``)."""

    name: str = default(_P + "name")
    cycles: int = default(_P + "cycles")
    current_a: float = default(_P + "current_a")
    heat_s: float = default(_P + "heat_s")
    cool_timeout_s: float = default(_P + "cool_timeout_s")
    min_cool_s: float = default(_P + "min_cool_s")
    settle_mm: float = default(_P + "settle_mm")
    settle_window_s: float = default(_P + "settle_window_s")
    partial_cool_s: float = default(_P + "partial_cool_s")
    inner_heat_s: float = default(_P + "inner_heat_s")
    inner_cool_s: float = default(_P + "inner_cool_s")
    levels_a: tuple[float, ...] = default(_P + "levels_a")
    hold_s: float = default(_P + "hold_s")
    ramp_s: float = default(_P + "ramp_s")
    # position references (closed loop)
    amplitude_mm: float = default(_P + "amplitude_mm")
    offset_mm: float | None = default(_P + "offset_mm")  # None: the middle of the stroke
    period_s: float = default(_P + "period_s")
    lead_in_s: float = default(_P + "lead_in_s")
    max_rise_mm_s: float | None = default(_P + "max_rise_mm_s")  # natural-cooling limit

    def validate(self, max_current_a: float, closed_loop: bool = False) -> None:
        """Raise ValueError (:class:`smabench.settings.SettingError`) naming the setting that is
        out of range. ``closed_loop``: the protocol feeds a controller (a position reference)
        rather than the current directly; ``max_current_a`` bounds its currents."""
        check_protocol(asdict(self), max_current_a, closed_loop)

    def values(self) -> dict[str, Any]:
        """The settings as schema values (keys ``protocol.<field>``)."""
        return {_P + k: v for k, v in asdict(self).items()}


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
        self._heat_start_mm = self._hot_mm = math.nan  # the current cycle's stroke, mm
        self._recovered = False  # the wire stretched back in this cooling

    @property
    def progress(self) -> float:
        """Fraction done, 0 … 1."""
        total = self.s.cycles if self.s.name != "step" else len(self.s.levels_a)
        return min(1.0, self.cycle / max(total, 1))

    def _enter(self, phase: str, t_s: float) -> None:
        self.phase, self.phase_t0_s = phase, t_s
        self.settle.reset()
        if phase == "heat":
            self._heat_start_mm = self._hot_mm = math.nan
            self._recovered = False

    def _track(self, position_mm: float) -> bool:
        """Follow the stroke (heat: its start and end positions); in cooling, whether the wire
        has stretched back by RECOVERED_FRACTION of it (once, then for the rest of the phase)."""
        if not math.isfinite(position_mm):
            return self._recovered
        if self.phase == "heat":
            if math.isnan(self._heat_start_mm):
                self._heat_start_mm = position_mm
            self._hot_mm = position_mm
            return False
        stroke = abs(self._heat_start_mm - self._hot_mm)
        if math.isnan(stroke) or abs(position_mm - self._hot_mm) >= RECOVERED_FRACTION * stroke:
            self._recovered = True
        return self._recovered

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
        recovered = self._track(position_mm)
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
            end = (dt >= s.min_cool_s and settled and recovered) or dt >= s.cool_timeout_s
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
