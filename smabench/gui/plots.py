"""Live plots: the hysteresis loop and the time traces (pyqtgraph, no OpenGL).

pyqtgraph's auto-downsampling and clipToView assume increasing x, so on the loop (XY) plot they
would draw nothing: each finished cycle is frozen as its own faded curve (thinned to at most
``LOOP_POINTS`` points once, when it finishes) and only the current cycle is redrawn. The time
plots do use peak downsampling and clipToView. The loop plot keeps the last ``MAX_FROZEN``
finished cycles (bounded however long the session runs); the per-cycle trends
(:class:`TrendPlots`) show every cycle.

Temperatures: the measured wire temperature ``temperature_C`` (a thermocouple, when the bench has
one) is drawn beside the estimate ``temperature_est_C`` in the time plots, and the loop plot uses
it instead of the estimate when it is present (its axis says which).
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from smabench.gui.link import SampleBuffer

LOOP_POINTS = 600
MAX_FROZEN = 300
TIME_WINDOW_S = 120.0
BRIGHT = (230, 90, 30)
FADED = (120, 140, 180, 90)


def add_legend(plot) -> pg.LegendItem:
    """A legend that stays readable in a small plot: small type, entries side by side, a
    translucent box in the top-right corner."""
    return plot.addLegend(offset=(-5, 2), labelTextSize="8pt", colCount=2, verSpacing=-6,
                          brush=pg.mkBrush(255, 255, 255, 200))  # fmt: skip


def thin(n: int, limit: int) -> slice:
    return slice(None, None, max(1, int(np.ceil(n / limit))))


def label_axis(plot, side: str, text: str, unit: str) -> None:
    """An axis label with its unit as written ("position (mm)"): pyqtgraph's automatic SI
    prefix would turn mm into "mmm" or "kmm"."""
    axis = plot.getAxis(side)
    axis.enableAutoSIPrefix(False)
    plot.setLabel(side, f"{text} ({unit})")


def keep_range(plot, axis: str, lo: float, hi: float, pad: float = 0.08) -> None:
    """Set a view range only when the data leave it or fill less than half of it.

    Axis items repaint (text and ticks, the most expensive part of a frame) whenever the range
    moves, so a range that follows every new sample costs a full axis repaint per frame.
    """
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return
    span = max(hi - lo, 1e-6)
    (x0, x1), (y0, y1) = plot.viewRange()
    cur_lo, cur_hi = (x0, x1) if axis == "x" else (y0, y1)
    if lo < cur_lo or hi > cur_hi or (cur_hi - cur_lo) > 2.0 * span * (1 + 2 * pad):
        setter = plot.setXRange if axis == "x" else plot.setYRange
        setter(lo - pad * span, hi + pad * span, padding=0)


def has_measured(buf: SampleBuffer, start: int = 0) -> bool:
    """Whether the buffer holds measured wire temperatures (``temperature_C``) from ``start``."""
    return bool(np.isfinite(buf.column("temperature_C")[start:]).any())


class LoopPlot(pg.PlotWidget):
    """Position vs wire temperature (measured when present, else estimated); finished cycles
    faded, the current one bright."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        label_axis(self.plotItem, "bottom", "estimated wire temperature", "°C")
        label_axis(self.plotItem, "left", "position", "mm")
        self.showGrid(x=False, y=False)
        add_legend(self.plotItem)
        self.current = self.plot([], [], pen=pg.mkPen(BRIGHT, width=1), name="current cycle")
        dashed = pg.mkPen((20, 20, 20), width=1, style=QtCore.Qt.PenStyle.DashLine)
        self.model_curve = self.plot([], [], pen=dashed, name="model")
        # finished cycles share one faded item (NaN between cycles): one paint call, not hundreds
        self.frozen_item = self.plot([], [], pen=pg.mkPen(FADED, width=1), name="earlier cycles")
        # drawn once into a pixmap, reused until the cycles or the view change
        self.frozen_item.curve.setCacheMode(
            QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache
        )
        self.frozen: list[tuple[np.ndarray, np.ndarray]] = []
        self._cycle_start = 0  # in rows appended since the buffer's clear (SampleBuffer.total)
        self._cycle = None
        self._bounds = None
        self.measured = False  # x is the measured temperature (fixed once a cycle is frozen)
        self.disableAutoRange()

    def reset(self) -> None:
        self.frozen.clear()
        self.frozen_item.setData([], [])
        self.current.setData([], [])
        self.model_curve.setData([], [])
        self._cycle_start, self._cycle = 0, None
        self._bounds: tuple[float, float, float, float] | None = None
        self._use_measured(False)

    def _use_measured(self, on: bool) -> None:
        self.measured = on
        label_axis(self.plotItem, "bottom", "measured wire temperature" if on
                   else "estimated wire temperature", "°C")  # fmt: skip

    def update_from(self, buf: SampleBuffer) -> None:
        n = buf.n
        if n == 0:
            return
        start = buf.index_of(self._cycle_start)  # storage index (older rows may be folded)
        if not self.frozen and not self.measured and has_measured(buf, start):
            self._use_measured(True)
        name = "temperature_C" if self.measured else "temperature_est_C"
        temp, pos, cycle = (buf.column(c) for c in (name, "position_mm", "cycle"))
        if self._cycle is None:
            self._cycle = cycle[start]
        # freeze every cycle that has finished since the last frame
        changes = np.nonzero(cycle[start:n] != self._cycle)[0]
        froze = False
        while changes.size:
            end = start + int(changes[0])
            sel = thin(end - start, LOOP_POINTS)
            self.frozen.append((temp[start:end][sel].copy(), pos[start:end][sel].copy()))
            start, self._cycle = end, cycle[end]
            changes = np.nonzero(cycle[start:n] != self._cycle)[0]
            froze = True
        self._cycle_start = buf.total - (n - start)
        if froze:
            del self.frozen[:-MAX_FROZEN]
            gap = np.array([np.nan])
            xs = np.concatenate([a for x, _ in self.frozen for a in (x, gap)])
            ys = np.concatenate([a for _, y in self.frozen for a in (y, gap)])
            self.frozen_item.setData(xs, ys, connect="finite")
        sel = thin(n - start, 4 * LOOP_POINTS)
        self.current.setData(temp[start:n][sel], pos[start:n][sel], connect="finite")
        self._grow(temp[start:n], pos[start:n])

    def _grow(self, temp: np.ndarray, pos: np.ndarray) -> None:
        """The view covers everything drawn so far (ranges kept from earlier cycles)."""
        if temp.size == 0 or not np.isfinite(temp).any() or not np.isfinite(pos).any():
            return
        lo_t, hi_t = float(np.nanmin(temp)), float(np.nanmax(temp))
        lo_y, hi_y = float(np.nanmin(pos)), float(np.nanmax(pos))
        if self._bounds is not None:
            lo_t, hi_t = min(lo_t, self._bounds[0]), max(hi_t, self._bounds[1])
            lo_y, hi_y = min(lo_y, self._bounds[2]), max(hi_y, self._bounds[3])
        self._bounds = (lo_t, hi_t, lo_y, hi_y)
        keep_range(self.plotItem, "x", lo_t, hi_t, 0.03)
        keep_range(self.plotItem, "y", lo_y, hi_y, 0.05)

    def show_model(self, temperature_c: np.ndarray, position_mm: np.ndarray) -> None:
        self.model_curve.setData(temperature_c, position_mm, connect="finite")


class TimePlots(pg.GraphicsLayoutWidget):
    """Current (set, measured), wire temperature (estimated; measured beside it when the bench
    has a thermocouple), position and setpoint against time."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.p_current = self.addPlot(row=0, col=0)
        self.p_temp = self.addPlot(row=1, col=0)
        self.p_pos = self.addPlot(row=2, col=0)
        for p, label, unit in ((self.p_current, "I", "A"),  # short: three stacked plots
                               (self.p_temp, "T", "°C"),
                               (self.p_pos, "x", "mm")):  # fmt: skip
            label_axis(p, "left", label, unit)
            p.showGrid(x=False, y=False)
            p.setDownsampling(auto=True, mode="peak")
            p.setClipToView(True)
            add_legend(p)
            p.disableAutoRange()
        self.p_temp.setXLink(self.p_current)
        self.p_pos.setXLink(self.p_current)
        label_axis(self.p_pos, "bottom", "time", "s")
        self.p_current.hideAxis("bottom")
        self.p_temp.hideAxis("bottom")
        self.c_set = self.p_current.plot(pen=pg.mkPen((150, 150, 150), width=1), name="current set")
        self.c_meas = self.p_current.plot(pen=pg.mkPen(BRIGHT, width=1), name="current measured")
        self.c_temp = self.p_temp.plot(pen=pg.mkPen((200, 40, 40), width=1),
                                       name="wire temperature (estimated)")
        self.c_tmeas: pg.PlotDataItem | None = None  # added when measured values first arrive
        self.c_pos = self.p_pos.plot(pen=pg.mkPen((30, 90, 200), width=1), name="position")
        self.c_setpoint = self.p_pos.plot(pen=pg.mkPen((40, 160, 60), width=1), name="setpoint")
        self.follow = True

    def reset(self) -> None:
        for c in (self.c_set, self.c_meas, self.c_temp, self.c_pos, self.c_setpoint):
            c.setData([], [])
        if self.c_tmeas is not None:
            self.p_temp.removeItem(self.c_tmeas)
            self.c_tmeas = None

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
        if self.c_tmeas is None and has_measured(buf, i0):
            self.c_tmeas = self.p_temp.plot(pen=pg.mkPen((120, 0, 120), width=1),
                                            name="wire temperature (measured)")  # fmt: skip
            self.c_tmeas.setDownsampling(auto=True, method="peak")
            self.c_tmeas.setClipToView(True)
        if self.c_tmeas is not None:
            self.c_tmeas.setData(t, buf.column("temperature_C")[i0:], connect="finite")
        if self.follow:  # page the time axis every tenth of a window, not every frame
            x0, x1 = self.p_current.viewRange()[0]
            if t[-1] > x1 or t[-1] < x0:
                right = t[-1] + 0.1 * TIME_WINDOW_S
                self.p_current.setXRange(max(0.0, right - TIME_WINDOW_S), right, padding=0)
        for plot, names in ((self.p_current, ("current_set_A", "current_A")),
                            (self.p_temp, ("temperature_est_C", "temperature_C")),
                            (self.p_pos, ("position_mm", "setpoint_mm"))):  # fmt: skip
            values = np.concatenate([buf.column(n)[i0:] for n in names])
            if np.isfinite(values).any():
                keep_range(plot, "y", float(np.nanmin(values)), float(np.nanmax(values)))

    def show_all(self, buf: SampleBuffer) -> None:
        """Replay: the whole session in view (ranges from the data itself: pyqtgraph's own
        auto-range sees only what clipToView kept of a view not yet laid out)."""
        t = buf.column("t_s")
        finite = t[np.isfinite(t)]
        if finite.size:
            self.p_current.setXRange(float(finite[0]), float(finite[-1]), padding=0.01)
        for plot, names in ((self.p_current, ("current_set_A", "current_A")),
                            (self.p_temp, ("temperature_est_C", "temperature_C")),
                            (self.p_pos, ("position_mm", "setpoint_mm"))):  # fmt: skip
            values = np.concatenate([buf.column(n) for n in names])
            if np.isfinite(values).any():
                lo, hi = float(np.nanmin(values)), float(np.nanmax(values))
                pad = 0.08 * (hi - lo) or 0.5
                plot.setYRange(lo - pad, hi + pad, padding=0)


class SelfSensePlots(pg.GraphicsLayoutWidget):
    """Resistance sensing live (issue 26), for a session with a self-sense calibration.

    Left: the wire's resistance against the laser's position (dots of the last
    ``TIME_WINDOW_S``): the map the calibration learnt, its hysteresis, and whether today's wire
    still follows it. Right: the laser's position and the estimate against time (the time
    plots' axis), the stretches the controller ran on the estimate drawn thick. Against time,
    not estimate against laser as XY: while the laser is lost (the fallback) there is no laser
    position to draw the estimate against, and that is when the operator needs to see it carry
    on; the estimate's error reads as a distance in mm between two traces."""

    MAP_POINTS = 1500
    MAP_EVERY = 5  # frames between redraws of the dots (6 Hz): the noisy R needs no more

    def __init__(self, time_axis_of=None, parent: QtWidgets.QWidget | None = None) -> None:
        """``time_axis_of``: a plot whose time axis the estimate plot follows (linked)."""
        super().__init__(parent)
        self.p_map = self.addPlot(row=0, col=0)
        self.p_est = self.addPlot(row=0, col=1)
        label_axis(self.p_map, "bottom", "laser position", "mm")
        label_axis(self.p_map, "left", "R", "Ω")
        label_axis(self.p_est, "bottom", "time", "s")
        label_axis(self.p_est, "left", "x", "mm")
        for p in (self.p_map, self.p_est):
            p.showGrid(x=False, y=False)
            add_legend(p)
            p.disableAutoRange()
        self.p_est.setDownsampling(auto=True, mode="peak")
        self.p_est.setClipToView(True)
        if time_axis_of is not None:
            self.p_est.setXLink(time_axis_of)
        self.c_map = self.p_map.plot([], [], pen=None, symbol="o", symbolSize=3,
                                     symbolPen=None, symbolBrush=pg.mkBrush(*BRIGHT, 120),
                                     name="wire resistance")  # fmt: skip
        self.c_laser = self.p_est.plot(pen=pg.mkPen((30, 90, 200), width=1), name="laser")
        self.c_est = self.p_est.plot(pen=pg.mkPen((150, 60, 160), width=1),
                                     name="from resistance")  # fmt: skip
        self.c_on_est = self.p_est.plot(pen=pg.mkPen((230, 140, 0), width=3),
                                        name="controlled on it")  # fmt: skip
        self._frames = 0

    def reset(self) -> None:
        for c in (self.c_map, self.c_laser, self.c_est, self.c_on_est):
            c.setData([], [])
        self._frames = 0

    def update_from(self, buf: SampleBuffer) -> None:
        if buf.n == 0 or not buf.has("position_est_mm"):
            return
        t_all = buf.column("t_s")
        i0 = int(np.searchsorted(t_all, t_all[-1] - TIME_WINDOW_S))
        t = t_all[i0:]
        laser = buf.column("position_mm")[i0:]
        est = buf.column("position_est_mm")[i0:]
        on = buf.column("feedback_resistance")[i0:] > 0.5
        self.c_laser.setData(t, laser, connect="finite")
        self.c_est.setData(t, est, connect="finite")
        self.c_on_est.setData(t, np.where(on, est, np.nan), connect="finite")
        values = np.concatenate([laser, est])
        if np.isfinite(values).any():
            keep_range(self.p_est, "y", float(np.nanmin(values)), float(np.nanmax(values)))
        if self._frames % self.MAP_EVERY == 0:
            r = buf.column("resistance_ohm")[i0:]
            ok = np.isfinite(r) & np.isfinite(laser)
            x, y = laser[ok], r[ok]
            sel = thin(x.size, self.MAP_POINTS)
            self.c_map.setData(x[sel], y[sel])
            if x.size:
                keep_range(self.p_map, "x", float(x.min()), float(x.max()))
                keep_range(self.p_map, "y", float(y.min()), float(y.max()))
        self._frames += 1
