"""The run bar's live readouts and how fresh they are (no Qt here).

The runtime reports the latest current (A), position (mm), wire temperature estimate (°C),
measured wire temperature (°C, a thermocouple) and ambient (°C) twice a second. After an E-STOP,
a trip or a lost device those numbers are no longer the bench's: :class:`Readouts` then shows
each as stale with its age ("position 2.806 mm, 3.2 s ago"), or as cleared when the bench is
gone; the current and the law are cleared. The wire temperature keeps an estimate:
from the last estimate it cools at no current towards the ambient, with the wire preset's time
constant (:func:`smabench.physics.thermal.step_exact`), marked "estimated, cooling".
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

FRESH = "fresh"
STALE = "stale"  # an E-STOP, a trip or a session's end: the last values, with their age
GONE = "gone"  # the bench is not connected (lost or never connected): nothing to show


@dataclass
class Readouts:
    """Last values and the time (``time.monotonic()``, s) they came."""

    values: dict[str, float | None] = field(default_factory=dict)
    t_s: float | None = None
    mode: str = FRESH
    why: str = ""  # "E-STOP", "trip", "device lost", "not connected"
    law: str = ""
    wire_preset: str = "paper"
    _cool_from: tuple[float, float, float] | None = None  # (t_s, temperature_c, ambient_c)

    def update(self, readout: dict[str, float | None], now_s: float, law: str = "") -> None:
        """A status from the runtime (only while ``mode`` is fresh: a status line written
        before the stop must not bring old numbers back)."""
        if self.mode != FRESH:
            return
        if readout.get("temperature_c") is None and self._cool_from is None:
            t = self.values.get("temperature_c")
            if t is not None and self.t_s is not None:  # a session ended: keep the estimate
                self._cool_from = (self.t_s, t, self.values.get("ambient_c") or 22.0)
        elif readout.get("temperature_c") is not None:
            self._cool_from = None
        self.values = dict(readout)
        self.t_s = now_s
        self.law = law

    def freeze(self, why: str, now_s: float, gone: bool = False,
               temperature_c: float | None = None) -> None:  # fmt: skip
        """An E-STOP, a trip or a loss: the values stay only as stale (or are cleared when
        ``gone``); the wire temperature keeps cooling from its last estimate
        (``temperature_c``: the newest streamed estimate, °C, fresher than the last status)."""
        ambient = self.values.get("ambient_c") or 22.0
        if temperature_c is not None and math.isfinite(temperature_c) and self.mode == FRESH:
            self._cool_from = (now_s, float(temperature_c), ambient)
        t = self.values.get("temperature_c")
        if self._cool_from is None and t is not None and self.t_s is not None:
            self._cool_from = (self.t_s, t, ambient)
        self.mode = GONE if gone else STALE
        self.why = why
        self.law = ""

    def thaw(self) -> None:
        """Acknowledged or reconnected: the next status is shown as it comes."""
        self.mode = FRESH
        self.why = ""

    def forget(self) -> None:
        self.values, self.t_s, self._cool_from = {}, None, None

    def wire_estimate_c(self, now_s: float) -> float | None:
        """The wire temperature estimate now: the runtime's while it has one, else cooling at
        no current from the last one."""
        if self._cool_from is None:
            return self.values.get("temperature_c") if self.mode == FRESH else None
        from smabench.physics.thermal import step_exact
        from smabench.physics.wire import PRESETS

        t0, temp0, ambient = self._cool_from
        wire = PRESETS.get(self.wire_preset) or PRESETS["paper"]
        return float(step_exact(temp0, 0.0, max(0.0, now_s - t0), wire, ambient))

    def text(self, now_s: float) -> str:
        """The readout line."""
        v = self.values
        wire = self.wire_estimate_c(now_s)
        cooling = self._cool_from is not None
        wire_text = ("wire (estimated) –" if wire is None else
                     f"wire (estimated{', cooling' if cooling else ''}) {wire:.1f} °C")  # fmt: skip
        if self.mode == GONE:
            return f"{self.why}: no readouts · {wire_text}"
        if self.mode == STALE:
            age = "" if self.t_s is None else f", {now_s - self.t_s:.1f} s ago"
            pos = v.get("position_mm")
            pos_text = "position –" if pos is None else f"position {pos:.3f} mm (last{age})"
            return f"{self.why}: current – · {pos_text} · {wire_text} · law –"

        def fmt(key: str, f: str) -> str:
            x = v.get(key)
            return "–" if x is None or not math.isfinite(x) else format(x, f)

        measured = v.get("temperature_measured_c")
        return (f"current {fmt('current_a', '.3f')} A · position {fmt('position_mm', '.3f')} mm"
                f" · {wire_text}"
                + ("" if measured is None else f" · wire (measured) {measured:.1f} °C")
                + f" · ambient {fmt('ambient_c', '.1f')} °C · law {self.law or '–'}")
