"""Recorded sessions: the list (date, load, protocol, status) and the replay view.

Reading folders and loading samples happen off the GUI thread (:class:`Jobs`); a replay is drawn
in a :class:`ReplayView` of its own, labelled with the folder, never into the live plots.
Cycles are shown counting from 1 everywhere (the recorded ``cycle`` column counts from 0).
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PySide6 import QtCore, QtWidgets

from smabench.gui.link import SampleBuffer
from smabench.gui.plots import LoopPlot, TimePlots

log = logging.getLogger(__name__)


def shown_cycle(index: float) -> int:
    """The cycle number the operator sees for a recorded ``cycle`` index (0 → 1)."""
    return int(index) + 1


class Jobs:
    """Work off the GUI thread (file I/O, fits, exports); results handed back by :meth:`poll`
    on the GUI thread, so callbacks may touch widgets."""

    def __init__(self, workers: int = 2) -> None:
        self.pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="gui-job")
        self.pending: list[tuple[concurrent.futures.Future, Callable, Callable]] = []

    def submit(self, fn: Callable[[], Any], done: Callable[[Any], None],
               failed: Callable[[BaseException], None]) -> concurrent.futures.Future:  # fmt: skip
        fut = self.pool.submit(fn)
        self.pending.append((fut, done, failed))
        return fut

    @property
    def busy(self) -> bool:
        return bool(self.pending)

    def poll(self) -> None:
        still = []
        for fut, done, failed in self.pending:
            if not fut.done():
                still.append((fut, done, failed))
                continue
            exc = fut.exception()
            try:
                failed(exc) if exc is not None else done(fut.result())
            except Exception:  # a display error must not stop the others
                log.exception("job callback failed")
        self.pending = still

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


@dataclass
class SessionRow:
    folder: Path
    started: str
    load_kg: float | None
    protocol: str
    status: str
    mtime: float


def read_session_rows(root: Path) -> list[SessionRow]:
    """The sessions in ``root`` (newest first) from their ``session.json`` (off the GUI thread)."""
    rows = []
    if not root.is_dir():
        return rows
    for folder in root.iterdir():
        meta_path = folder / "session.json"
        if not meta_path.is_file():
            continue
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError):
            meta = {"status": "unreadable"}
        proto = meta.get("protocol", {})
        name = proto.get("name", "–") if isinstance(proto, dict) else str(proto)
        ctl = meta.get("controller", {})
        if isinstance(ctl, dict) and ctl.get("mode") not in (None, "open_loop"):
            name += f" ({ctl['mode']})"
        started = str(meta.get("started_at", ""))[:19].replace("T", " ")
        load = meta.get("load_kg")
        rows.append(SessionRow(folder, started, load if isinstance(load, (int, float)) else None,
                               name, str(meta.get("status", "–")),
                               meta_path.stat().st_mtime))  # fmt: skip
    rows.sort(key=lambda r: r.mtime, reverse=True)
    return rows


def replay_columns(session) -> dict[str, np.ndarray]:
    """A loaded session's columns as the plots want them."""
    n = len(session)
    cols = {c: session.data[c] for c in session.data if c != "mode"}
    if "temperature_est_C" not in cols and "temperature_C" in cols:
        cols["temperature_est_C"] = cols["temperature_C"]
    if "t_s" not in cols:
        cols["t_s"] = np.arange(n, dtype=float)
    cols.setdefault("cycle", np.zeros(n))
    return cols


class ReplayView(QtWidgets.QWidget):
    """One recorded session: its title, its own loop and time plots, the fit result."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        v = QtWidgets.QVBoxLayout(self)
        self.title = QtWidgets.QLabel("No session opened: double-click one in Sessions.")
        self.title.setStyleSheet("font-weight: bold; padding: 4px; background: #e8eef7;")
        self.title.setWordWrap(True)
        v.addWidget(self.title)
        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        self.loop_plot = LoopPlot()
        self.time_plots = TimePlots()
        self.time_plots.follow = False
        split.addWidget(self.loop_plot)
        split.addWidget(self.time_plots)
        v.addWidget(split, 1)
        self.fit_text = QtWidgets.QPlainTextEdit()
        self.fit_text.setReadOnly(True)
        self.fit_text.setMaximumHeight(110)
        v.addWidget(self.fit_text)
        self.buffer = SampleBuffer()
        self.folder: Path | None = None

    def show_session(self, folder: Path, session, row: SessionRow | None) -> None:
        self.folder = Path(folder)
        self.buffer.clear()
        self.loop_plot.reset()
        self.time_plots.reset()
        self.buffer.append_columns(replay_columns(session))
        self.loop_plot.update_from(self.buffer)
        self.time_plots.update_from(self.buffer)
        self.time_plots.show_all()
        self.loop_plot.autoRange()
        meta = session.meta
        cycles = self.buffer.column("cycle")
        finite = cycles[np.isfinite(cycles)]
        n_cycles = int(finite.max()) + 1 if finite.size else 0
        load = meta.get("load_kg")
        proto = meta.get("protocol", {})
        self.title.setText(
            f"REPLAY of {self.folder.name} (recorded, not live) · "
            f"{str(meta.get('started_at', ''))[:19].replace('T', ' ')} · "
            f"{'–' if load is None else f'{load:g} kg'} · "
            f"{proto.get('name', '–') if isinstance(proto, dict) else proto} · "
            f"{meta.get('status', '–')} · {len(session)} samples, {n_cycles} cycle(s) · "
            f"folder {self.folder}"
        )
        self.fit_text.setPlainText("")

    def show_fit(self, text: str, temp: np.ndarray | None = None,
                 pos: np.ndarray | None = None) -> None:  # fmt: skip
        self.fit_text.setPlainText(text)
        if temp is not None and pos is not None:
            self.loop_plot.show_model(temp, pos)


def fit_session(folder: Path, model: str, cycle: int | None) -> dict[str, Any]:
    """Load ``folder`` and fit ``model`` to cycle ``cycle`` (counted from 1; None: the last
    complete one); runs off the GUI thread. ValueError in words when it cannot."""
    from smabench.physics.identify import FitError, fit_loop
    from smabench.sessions import load_session

    t0 = time.perf_counter()
    s = load_session(folder)
    cols = replay_columns(s)
    idx = np.asarray(cols["cycle"], dtype=float)
    finite = idx[np.isfinite(idx)]
    if cycle is None:
        chosen = float(finite.max()) if finite.size else 0.0
    else:
        chosen = float(cycle - 1)
        if finite.size and chosen not in set(finite.tolist()):
            raise ValueError(f"this session has cycles 1 … {shown_cycle(finite.max())}, "
                             f"not {cycle}")  # fmt: skip
    sel = idx == chosen if finite.size else np.ones(idx.size, bool)
    temp = np.asarray(cols["temperature_est_C"], float)[sel]
    pos = np.asarray(cols["position_mm"], float)[sel]
    ok = np.isfinite(temp) & np.isfinite(pos)
    try:
        fit = fit_loop(temp[ok], pos[ok], model)
    except FitError as exc:
        raise ValueError(f"the {model} model could not be fitted to cycle "
                         f"{shown_cycle(chosen)}: {exc}") from None  # fmt: skip
    lines = [f"{Path(folder).name}: model {fit.model} on cycle {shown_cycle(chosen)} "
             f"({fit.n_points} points, {time.perf_counter() - t0:.1f} s)",
             f"rmse {fit.rmse_mm:.4f} mm   nrmse {fit.nrmse_percent:.3f} % of stroke   "
             f"ard {fit.ard_percent:.3f} %"]  # fmt: skip
    lines += [f"  {k} = {v:.6g}" for k, v in fit.parameters.items()]
    return {"text": "\n".join(lines), "temp": temp[ok], "model_mm": fit.predict(temp[ok]),
            "nrmse_percent": fit.nrmse_percent, "rmse_mm": fit.rmse_mm,
            "cycle": shown_cycle(chosen), "folder": str(folder)}  # fmt: skip
