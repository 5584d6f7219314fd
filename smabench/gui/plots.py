"""Live plots: the hysteresis loop and the time traces (pyqtgraph, no OpenGL).

pyqtgraph's auto-downsampling and clipToView assume increasing x, so on the loop (XY) plot they
would draw nothing: each finished cycle is frozen as its own faded curve (thinned to at most
``LOOP_POINTS`` points once, when it finishes) and only the current cycle is redrawn. The time
plots do use peak downsampling and clipToView.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from smabench.gui.link import SampleBuffer

LOOP_POINTS = 600
TIME_WINDOW_S = 120.0
BRIGHT = (230, 90, 30)
FADED = (120, 140, 180, 90)


def thin(n: int, limit: int) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / limit))))


class LoopPlot(pg.PlotWidget):
    """Position vs estimated temperature; finished cycles faded, the current one bright."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setLabel("bottom", "estimated wire temperature", units="°C")
        self.setLabel("left", "position", units="mm")
        self.showGrid(x=True, y=True, alpha=0.3)
        self.addLegend(offset=(-10, 10))
        self.current = self.plot([], [], pen=pg.mkPen(BRIGHT, width=1), name="current cycle")
        dashed = pg.mkPen((20, 20, 20), width=1, style=QtCore.Qt.PenStyle.DashLine)
        self.model_curve = self.plot([], [], pen=dashed, name="model")
        self.frozen: list[pg.PlotDataItem] = []
        self._cycle_start = 0
        self._cycle = None

    def reset(self) -> None:
        for item in self.frozen:
            self.removeItem(item)
        self.frozen.clear()
        self.current.setData([], [])
        self.model_curve.setData([], [])
        self._cycle_start, self._cycle = 0, None

    def update_from(self, buf: SampleBuffer) -> None:
        n = buf.n
        if n == 0:
            return
        temp, pos, cycle = (buf.column(c) for c in ("temperature_est_C", "position_mm", "cycle"))
        if self._cycle is None:
            self._cycle = cycle[0]
        # freeze every cycle that has finished since the last frame
        changes = np.nonzero(cycle[self._cycle_start : n] != self._cycle)[0]
        while changes.size:
            end = self._cycle_start + int(changes[0])
            sel = thin(end - self._cycle_start, LOOP_POINTS)
            item = self.plot(temp[self._cycle_start : end][sel], pos[self._cycle_start : end][sel],
                             pen=pg.mkPen(FADED, width=1))  # fmt: skip
            self.frozen.append(item)
            self._cycle_start, self._cycle = end, cycle[end]
            changes = np.nonzero(cycle[self._cycle_start : n] != self._cycle)[0]
        sel = thin(n - self._cycle_start, 4 * LOOP_POINTS)
        self.current.setData(temp[self._cycle_start : n][sel], pos[self._cycle_start : n][sel],
                             connect="finite")  # fmt: skip

    def show_model(self, temperature_c: np.ndarray, position_mm: np.ndarray) -> None:
        self.model_curve.setData(temperature_c, position_mm, connect="finite")


class TimePlots(pg.GraphicsLayoutWidget):
    """Current (set, measured), estimated temperature, position and setpoint against time."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.p_current = self.addPlot(row=0, col=0)
        self.p_temp = self.addPlot(row=1, col=0)
        self.p_pos = self.addPlot(row=2, col=0)
        for p, label, unit in ((self.p_current, "current", "A"),
                               (self.p_temp, "temperature", "°C"),
                               (self.p_pos, "position", "mm")):  # fmt: skip
            p.setLabel("left", label, units=unit)
            p.showGrid(x=True, y=True, alpha=0.3)
            p.setDownsampling(auto=True, mode="peak")
            p.setClipToView(True)
            p.addLegend(offset=(-10, 5))
        self.p_temp.setXLink(self.p_current)
        self.p_pos.setXLink(self.p_current)
        self.p_pos.setLabel("bottom", "time", units="s")
        self.c_set = self.p_current.plot(pen=pg.mkPen((150, 150, 150), width=1), name="set")
        self.c_meas = self.p_current.plot(pen=pg.mkPen(BRIGHT, width=1), name="measured")
        self.c_temp = self.p_temp.plot(pen=pg.mkPen((200, 40, 40), width=1), name="estimated")
        self.c_pos = self.p_pos.plot(pen=pg.mkPen((30, 90, 200), width=1), name="position")
        self.c_setpoint = self.p_pos.plot(pen=pg.mkPen((40, 160, 60), width=1), name="setpoint")
        self.follow = True

    def reset(self) -> None:
        for c in (self.c_set, self.c_meas, self.c_temp, self.c_pos, self.c_setpoint):
            c.setData([], [])

    def update_from(self, buf: SampleBuffer) -> None:
        if buf.n == 0:
            return
        t_all = buf.column("t_s")
        # following the present, only the visible window is handed over (cheap at any length)
        i0 = int(np.searchsorted(t_all, t_all[-1] - TIME_WINDOW_S)) if self.follow else 0
        t = t_all[i0:]
        for curve, name in ((self.c_set, "current_set_A"), (self.c_meas, "current_A"),
                            (self.c_temp, "temperature_est_C"), (self.c_pos, "position_mm"),
                            (self.c_setpoint, "setpoint_mm")):  # fmt: skip
            curve.setData(t, buf.column(name)[i0:], connect="finite")
        if self.follow:
            self.p_current.setXRange(max(0.0, t[-1] - TIME_WINDOW_S), t[-1] + 1.0, padding=0)
