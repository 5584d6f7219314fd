"""Per-cycle trends, live: the running session's ``cycles.csv`` read as it grows, drawn against
the cycle number.

The session writer appends one summary row per finished cycle (:data:`CYCLE_COLUMNS`) and
flushes it; :class:`CycleTail` reads only the bytes added since the last read (a partial last
line waits for the next read), so a read costs the new cycles, not the file. Memory is bounded:
past ``max_rows`` cycles every second stored row is dropped (the trend keeps its shape; 10 000
cycles stay whole with the default).

:class:`TrendPlots` draws, per cycle: the position's minimum and maximum (the two ends of the
stroke), the stroke (max − min) and the accumulated residual (cycle end − first cycle's start),
and the peak wire temperature — measured when the session has ``temperature_C``, estimated
otherwise (the legend says which).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6 import QtWidgets

from smabench.gui.plots import add_legend, label_axis
from smabench.sessions import CYCLE_COLUMNS, CYCLES_FILE

log = logging.getLogger(__name__)

MAX_ROWS = 20_000


class CycleTail:
    """The per-cycle rows of one session's ``cycles.csv``, read incrementally."""

    def __init__(self, folder: str | Path | None = None, max_rows: int = MAX_ROWS) -> None:
        self.max_rows = int(max_rows)
        self.reset(folder)

    def reset(self, folder: str | Path | None) -> None:
        self.path = None if folder is None else Path(folder) / CYCLES_FILE
        self._offset = 0
        self._partial = ""
        self._header: list[str] | None = None
        self._data = np.full((len(CYCLE_COLUMNS), 256), np.nan)
        self.n = 0
        self.version = 0  # bumped whenever rows are added

    def column(self, name: str) -> np.ndarray:
        return self._data[CYCLE_COLUMNS.index(name), : self.n]

    def read(self) -> int:
        """Read what was appended since the last call; returns the number of new cycles."""
        if self.path is None:
            return 0
        try:
            with self.path.open("rb") as fh:
                fh.seek(self._offset)
                chunk = fh.read()
        except OSError:  # not written yet (no cycle finished)
            return 0
        if not chunk:
            return 0
        self._offset += len(chunk)
        text = self._partial + chunk.decode("utf-8", errors="replace")
        lines = text.split("\n")
        self._partial = lines.pop()  # "" after a complete line
        rows = []
        for line in lines:
            line = line.strip()
            if not line:
                continue
            if self._header is None:
                self._header = line.split(",")
                continue
            rows.append(self._parse(line.split(",")))
        if rows:
            self._append(np.array(rows))
        return len(rows)

    def _parse(self, cells: list[str]) -> list[float]:
        by_name = dict(zip(self._header or (), cells, strict=False))
        out = []
        for c in CYCLE_COLUMNS:
            try:
                out.append(float(by_name.get(c) or "nan"))
            except ValueError:
                out.append(math.nan)
        return out

    def _append(self, rows: np.ndarray) -> None:
        k = rows.shape[0]
        if self.n + k > self._data.shape[1]:
            grown = np.full((len(CYCLE_COLUMNS), max(2 * self._data.shape[1], self.n + k)),
                            np.nan)  # fmt: skip
            grown[:, : self.n] = self._data[:, : self.n]
            self._data = grown
        self._data[:, self.n : self.n + k] = rows.T
        self.n += k
        while self.n > self.max_rows:  # bounded: every second row of the older cycles
            kept = self._data[:, : self.n : 2].copy()
            if (self.n - 1) % 2:  # always keep the newest cycle
                kept = np.concatenate([kept, self._data[:, self.n - 1 : self.n]], axis=1)
            self.n = kept.shape[1]
            self._data[:, : self.n] = kept
        self.version += 1


class CycleAxis(pg.AxisItem):
    """A cycle-number axis: ticks on whole cycles only (1, 2, 5, 10, 20 … apart)."""

    def tickValues(self, minVal, maxVal, size):  # noqa: N802,N803 (pyqtgraph's names)
        out = []
        for spacing, values in super().tickValues(minVal, maxVal, size):
            if spacing < 1:
                continue
            ints = [v for v in values if abs(v - round(v)) < 1e-9 and v >= 1]
            out.append((spacing, ints))
        if not any(v for _, v in out):  # a short range: every cycle in it
            lo, hi = max(1, int(np.ceil(minVal))), int(np.floor(maxVal))
            out = [(1.0, [float(v) for v in range(lo, hi + 1)])]
        return out

    def tickStrings(self, values, scale, spacing):  # noqa: N802 (pyqtgraph's name)
        return [str(int(round(v))) for v in values]


class TrendPlots(pg.GraphicsLayoutWidget):
    """Positions, stroke and residual, peak temperature against the cycle number."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.p_pos = self.addPlot(row=0, col=0)
        self.p_stroke = self.addPlot(row=1, col=0)
        self.p_temp = self.addPlot(row=2, col=0, axisItems={"bottom": CycleAxis("bottom")})
        for p, label, unit in ((self.p_pos, "position", "mm"), (self.p_stroke, "stroke", "mm"),
                               (self.p_temp, "peak T", "°C")):  # fmt: skip
            label_axis(p, "left", label, unit)
            add_legend(p)
        for p in (self.p_stroke, self.p_temp):
            p.setXLink(self.p_pos)
        label_axis(self.p_temp, "bottom", "cycle", "#")
        self.c_min = self.p_pos.plot(pen=pg.mkPen((30, 90, 200), width=1),
                                     name="position min per cycle")  # fmt: skip
        self.c_max = self.p_pos.plot(pen=pg.mkPen((230, 90, 30), width=1),
                                     name="position max per cycle")  # fmt: skip
        self.c_stroke = self.p_stroke.plot(pen=pg.mkPen((20, 20, 20), width=1),
                                           name="stroke (max − min)")  # fmt: skip
        self.c_residual = self.p_stroke.plot(pen=pg.mkPen((40, 160, 60), width=1),
                                             name="accumulated residual (end − first start)")
        self.c_temp = self.p_temp.plot(pen=pg.mkPen((200, 40, 40), width=1),
                                       name="peak wire temperature (estimated)")  # fmt: skip
        for c in (self.c_min, self.c_max, self.c_stroke, self.c_residual, self.c_temp):
            # a marker on each cycle: one finished cycle is a visible point, not nothing
            c.setSymbol("o")
            c.setSymbolSize(5)
            c.setSymbolPen(c.opts["pen"])
            c.setSymbolBrush(c.opts["pen"].color())
        for p in (self.p_pos, self.p_stroke):
            p.getAxis("bottom").setStyle(showValues=False)
        self.measured = False
        self.shown_version = -1

    def reset(self) -> None:
        for c in (self.c_min, self.c_max, self.c_stroke, self.c_residual, self.c_temp):
            c.setData([], [])
        self.shown_version = -1

    def update_from(self, tail: CycleTail) -> bool:
        """Redraw when ``tail`` has new cycles; True when it redrew."""
        if tail.version == self.shown_version or tail.n == 0:
            return False
        self.shown_version = tail.version
        x = tail.column("cycle") + 1  # as the operator counts cycles (from 1)
        lo, hi = tail.column("position_min_mm"), tail.column("position_max_mm")
        start, end = tail.column("position_start_mm"), tail.column("position_end_mm")
        first = start[np.isfinite(start)]
        self.c_min.setData(x, lo, connect="finite")
        self.c_max.setData(x, hi, connect="finite")
        self.c_stroke.setData(x, hi - lo, connect="finite")
        self.c_residual.setData(x, end - (first[0] if first.size else np.nan), connect="finite")
        measured = tail.column("temperature_max_C")
        use = bool(np.isfinite(measured).any())
        if use != self.measured:
            self.measured = use
            self.p_temp.legend.clear()
            self.p_temp.legend.addItem(self.c_temp, "peak wire temperature (measured)" if use
                                       else "peak wire temperature (estimated)")  # fmt: skip
        peak = measured if use else tail.column("temperature_est_max_C")
        self.c_temp.setData(x, peak, connect="finite")
        # whole cycles in view, at least 1 … 5 (one cycle is a point in the middle, not a
        # range of fractions)
        self.p_temp.setXRange(0.5, max(5.5, float(np.nanmax(x)) + 0.5), padding=0)
        for plot, ys in ((self.p_pos, (lo, hi)), (self.p_stroke, (hi - lo, end - (
                first[0] if first.size else np.nan))), (self.p_temp, (peak,))):  # fmt: skip
            v = np.concatenate([np.asarray(y, dtype=float) for y in ys])
            if np.isfinite(v).any():
                a, b = float(np.nanmin(v)), float(np.nanmax(v))
                pad = 0.1 * (b - a) or max(0.05, 0.05 * abs(b))
                plot.setYRange(a - pad, b + pad, padding=0)
        return True
