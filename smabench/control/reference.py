"""Position references for the closed-loop controllers: step, staircase, sine, triangle.

All waveforms run ``cycles`` periods of ``period_s`` about ``offset_mm`` with ``amplitude_mm``
(from :class:`~smabench.protocols.ProtocolSettings`), phased so that each period ends at
``offset + amplitude`` (the long, cold side); before the first period the setpoint is held there
for ``lead_in_s`` so the wire starts from rest:

- ``step``: a square wave, ``offset − A`` for the first half period (a heating step), then
  ``offset + A`` (a cooling step);
- ``staircase``: eight stairs per period, ``A·(½, 0, −½, −1, −½, 0, ½, 1)``;
- ``sine``: ``offset + A·cos(2πt/P)``;
- ``triangle``: linear from ``+A`` to ``−A`` and back.

Cooling is passive, so a falling setpoint can be followed as fast as the current allows but a
rising one only as fast as the wire cools by itself. ``max_rise_mm_s`` tells the generator that
natural cooling limit: the setpoint then rises no faster (see :func:`natural_rise_rate_mm_s`
for a value from the loop model and the heat balance).
"""

from __future__ import annotations

import math

from smabench.physics.thermal import time_constant_s
from smabench.physics.wire import Wire
from smabench.protocols import REFERENCE_NAMES, ProtocolSettings

STAIRS = (0.5, 0.0, -0.5, -1.0, -0.5, 0.0, 0.5, 1.0)

BENCHMARK_REFERENCES = {
    "step": ("step", 30.0, 2),
    "staircase": ("staircase", 40.0, 1),
    "sine 20 s": ("sine", 20.0, 2),
    "sine 10 s": ("sine", 10.0, 3),
}
"""The references of ``smabench bench control`` and of the gain tuning: label → (kind, period s,
cycles)."""


def waveform(kind: str, phase: float) -> float:
    """Normalised waveform (−1 … 1) at ``phase`` in periods (any real; periodic)."""
    x = phase % 1.0
    if kind == "step":
        return -1.0 if x < 0.5 else 1.0
    if kind == "staircase":
        return STAIRS[min(int(x * len(STAIRS)), len(STAIRS) - 1)]
    if kind == "sine":
        return math.cos(2.0 * math.pi * x)
    if kind == "triangle":
        return 1.0 - 4.0 * x if x < 0.5 else 4.0 * x - 3.0
    raise ValueError(f"unknown reference {kind!r}; choose from {', '.join(REFERENCE_NAMES)}")


def natural_rise_rate_mm_s(
    inverse, wire: Wire, ambient_c: float, fraction: float = 0.8
) -> float:
    """Mean rate (mm/s) at which the position rises while the wire cools by itself through the
    middle ``fraction`` of the cooling branch of the loop model (``inverse``: an InverseLoop)."""
    (t1, _), (t2, _) = inverse.low, inverse.high
    tau = time_constant_s(wire)
    lo = t1 + 0.5 * (1 - fraction) * (t2 - t1)
    hi = t2 - 0.5 * (1 - fraction) * (t2 - t1)
    dy = abs(inverse.forward(lo, False) - inverse.forward(hi, False))
    dt = tau * math.log(max(hi - ambient_c, 1e-6) / max(lo - ambient_c, 1e-6))
    return dy / max(dt, 1e-6)


class Reference:
    """Setpoint generator; ``update(t_s)`` once per tick, ``peek(t_s)`` for look-ahead."""

    def __init__(self, settings: ProtocolSettings, offset_mm: float | None = None) -> None:
        if settings.name not in REFERENCE_NAMES:
            raise ValueError(
                f"protocol {settings.name!r} is not a position reference; "
                f"choose from {', '.join(REFERENCE_NAMES)}"
            )
        self.s = settings
        self.kind = settings.name
        self.offset_mm = settings.offset_mm if offset_mm is None else offset_mm
        if self.offset_mm is None:
            raise ValueError("the reference needs an offset (or the controller's stroke)")
        self.t0: float | None = None
        self._last: float | None = None
        self._last_t: float | None = None

    @property
    def range_mm(self) -> tuple[float, float]:
        """Lowest and highest setpoint of the reference."""
        a = abs(self.s.amplitude_mm)
        return self.offset_mm - a, self.offset_mm + a

    @property
    def duration_s(self) -> float:
        return self.s.lead_in_s + self.s.cycles * self.s.period_s

    def raw(self, t_rel: float) -> float:
        """Setpoint (mm) at ``t_rel`` s after the start, before any rate limit."""
        s = self.s
        if t_rel < s.lead_in_s:
            return self.offset_mm + s.amplitude_mm
        phase = min((t_rel - s.lead_in_s) / s.period_s, s.cycles - 1e-12)
        return self.offset_mm + s.amplitude_mm * waveform(self.kind, phase)

    def cycle(self, t_s: float) -> int:
        t_rel = t_s - (self.t0 if self.t0 is not None else t_s)
        return max(0, min(int((t_rel - self.s.lead_in_s) // self.s.period_s), self.s.cycles - 1))

    def edges_s(self) -> list[float]:
        """Times (s after the start) where a step/staircase setpoint jumps."""
        s = self.s
        per = {"step": 2, "staircase": len(STAIRS)}.get(self.kind, 0)
        return [s.lead_in_s + s.period_s * k / per for k in range(per * s.cycles)] if per else []

    def _limited(self, t_s: float, y: float) -> float:
        lim = self.s.max_rise_mm_s
        if lim is None or self._last is None:
            return y
        dt = max(t_s - self._last_t, 0.0)
        return min(y, self._last + lim * dt)

    def peek(self, t_s: float) -> float:
        """Setpoint at a (future) time without advancing the state."""
        t0 = self.t0 if self.t0 is not None else t_s
        return self._limited(t_s, self.raw(t_s - t0))

    def update(self, t_s: float) -> tuple[float, bool]:
        """(setpoint mm, done) at this tick."""
        if self.t0 is None:
            self.t0 = t_s
        t_rel = t_s - self.t0
        y = self._limited(t_s, self.raw(t_rel))
        self._last, self._last_t = y, t_s
        return y, t_rel >= self.duration_s
