"""Recorded sessions: the list (date, load, protocol, status) and the replay view.

Reading folders and loading samples happen off the GUI thread (:class:`Jobs`); a replay is drawn
in a :class:`ReplayView` of its own, labelled with the folder, never into the live plots.
Cycles are shown counting from 1 everywhere (the recorded ``cycle`` column counts from 0).
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PySide6 import QtCore, QtWidgets

from smabench.gui import words
from smabench.gui.fitjob import fit_session, replay_columns
from smabench.gui.link import SampleBuffer
from smabench.gui.plots import LoopPlot, TimePlots
from smabench.gui.worker import ComputeWorker
from smabench.sessions import session_status

log = logging.getLogger(__name__)


class Jobs:
    """Work off the GUI thread; results handed back by :meth:`poll` on the GUI thread, so
    callbacks may touch widgets. File I/O runs on threads (:meth:`submit`); computations run in
    the computation process (:meth:`compute`, :class:`~smabench.gui.worker.ComputeWorker`),
    started with the window at the lowest priority, so a fit never holds the GUI's interpreter
    lock nor takes the CPU while the operator reaches for the E-STOP."""

    def __init__(self, workers: int = 2) -> None:
        self.pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="gui-job")
        self.worker = ComputeWorker()
        self.pending: list[tuple[concurrent.futures.Future, Callable, Callable]] = []

    def start_worker(self) -> None:
        """Start the computation process now (its start-up then never meets a fit request)."""
        self.worker.start()

    def submit(self, fn: Callable[[], Any], done: Callable[[Any], None],
               failed: Callable[[BaseException], None]) -> concurrent.futures.Future:  # fmt: skip
        fut = self.pool.submit(fn)
        self.pending.append((fut, done, failed))
        return fut

    def compute(self, fn: Callable[..., Any], args: tuple, done: Callable[[Any], None],
                failed: Callable[[BaseException], None]) -> concurrent.futures.Future:  # fmt: skip
        """``fn(*args)`` in the computation process (``fn`` a module-level function of a module
        without Qt, ``args`` picklable)."""
        fut = self.worker.submit(fn, args)
        self.pending.append((fut, done, failed))
        return fut

    @property
    def busy(self) -> bool:
        return bool(self.pending)

    @property
    def computing(self) -> bool:
        """A computation is running in the computation process now."""
        return self.worker.computing

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
        self.worker.close()  # a fit in progress is not waited for


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
                               name, session_status(folder, meta)[0] or "–",
                               meta_path.stat().st_mtime))  # fmt: skip
    rows.sort(key=lambda r: r.mtime, reverse=True)
    return rows


class ReplayView(QtWidgets.QWidget):
    """One recorded session: its title, its own loop and time plots, the fit result."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        v = QtWidgets.QVBoxLayout(self)
        self.title = QtWidgets.QLabel("No session opened: double-click one in Sessions.")
        self.title.setStyleSheet("font-weight: bold; padding: 4px; background: #e8eef7;")
        self.title.setWordWrap(True)
        v.addWidget(self.title)
        split = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)  # as the Live tab
        self.loop_plot = LoopPlot()
        self.time_plots = TimePlots()
        self.time_plots.follow = False
        split.addWidget(self.loop_plot)
        split.addWidget(self.time_plots)
        split.setSizes([400, 600])
        v.addWidget(split, 1)
        self.fit_text = QtWidgets.QPlainTextEdit()
        self.fit_text.setReadOnly(True)
        self.fit_text.setMaximumHeight(80)
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
        self.time_plots.show_all(self.buffer)
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
            f"{session_status(self.folder, meta)[0] or '–'} · {len(session)} samples, "
            f"{n_cycles} cycle(s) · "
            f"folder {self.folder}"
        )
        self.fit_text.setPlainText("")

    def show_fit(self, text: str, temp: np.ndarray | None = None,
                 pos: np.ndarray | None = None) -> None:  # fmt: skip
        self.fit_text.setPlainText(text)
        if temp is not None and pos is not None:
            self.loop_plot.show_model(temp, pos)


class SessionsMixin:
    """The Sessions tab's behaviour (a mixin of :class:`~smabench.gui.window.MainWindow`): list,
    folder, replay, export and fit, all file work off the GUI thread."""

    # ------------------------------------------------------------------ sessions
    def refresh_sessions(self) -> None:
        root = self.sessions_dir
        self.sessions_label.setText(f"Sessions folder: {root.resolve()}")
        self.jobs.submit(lambda: read_session_rows(root), self._fill_sessions,
                         lambda exc: self.show_error(str(exc)))  # fmt: skip

    def _fill_sessions(self, rows: list[SessionRow]) -> None:
        keep = self.selected_session()
        self.session_list.clear()
        for r in rows:
            item = QtWidgets.QTreeWidgetItem([
                r.started, "–" if r.load_kg is None else f"{r.load_kg:g} kg", r.protocol,
                r.status, r.folder.name])  # fmt: skip
            item.setData(0, QtCore.Qt.ItemDataRole.UserRole, str(r.folder))
            self.session_list.addTopLevelItem(item)
            if keep is not None and r.folder == keep:
                self.session_list.setCurrentItem(item)
        for i in range(5):
            self.session_list.resizeColumnToContents(i)
        self.sessions_loaded = len(rows)

    def selected_session(self) -> Path | None:
        item = self.session_list.currentItem()
        return Path(item.data(0, QtCore.Qt.ItemDataRole.UserRole)) if item else None

    def open_session(self, folder: str | Path, after: Any = None, switch: bool = True) -> None:
        """Replay a recorded session in the Replay tab (loaded off the GUI thread); then
        ``after()``. ``switch``: the operator asked for it (the Replay tab comes to the front
        when it is loaded, unless a session is running); a background result draws there
        without changing the view."""
        from smabench.sessions import load_session

        folder = Path(folder)
        self.announce(f"Opening {folder.name} …")

        def done(s) -> None:
            self.replay.show_session(folder, s, None)
            if switch and not self.running:
                self.tabs.setCurrentWidget(self.replay)
            self.announce(f"{folder.name} ({len(s)} samples) is in the Replay tab.")
            if after is not None:
                after()

        self.jobs.submit(lambda: load_session(folder), done,
                         lambda exc: self.announce(
                             f"Cannot open {folder}: {words.plain(str(exc))}", error=True))

    def open_selected(self) -> None:
        folder = self.selected_session()
        if folder is None:
            self.announce("Choose a session in the list first.", error=True)
            return
        self.open_session(folder)

    def _dialog_for(self, title: str, mode: str, start: str) -> QtWidgets.QFileDialog:
        """A non-native, non-modal file dialog (the E-STOP button stays usable beside it);
        ``mode``: ``dir`` (a folder), ``json`` (a JSON file to read) or ``save`` (a CSV)."""
        dlg = QtWidgets.QFileDialog(self, title, start)
        dlg.setOption(QtWidgets.QFileDialog.Option.DontUseNativeDialog, True)
        dlg.setWindowModality(QtCore.Qt.WindowModality.NonModal)
        if mode == "dir":
            dlg.setFileMode(QtWidgets.QFileDialog.FileMode.Directory)
            dlg.setOption(QtWidgets.QFileDialog.Option.ShowDirsOnly, True)
        elif mode == "json":  # an existing JSON file to read
            dlg.setFileMode(QtWidgets.QFileDialog.FileMode.ExistingFile)
            dlg.setNameFilter("JSON (*.json)")
        else:
            dlg.setAcceptMode(QtWidgets.QFileDialog.AcceptMode.AcceptSave)
            dlg.setNameFilter("CSV (*.csv)")
        self._dialog = dlg
        return dlg

    def choose_sessions_dir(self) -> None:
        dlg = self._dialog_for("Sessions folder", "dir", str(self.sessions_dir))
        dlg.fileSelected.connect(lambda path: self.set_sessions_dir(path))
        dlg.show()

    def set_sessions_dir(self, path: str | Path) -> None:
        self.sessions_dir = Path(path)
        self.refresh_sessions()

    def open_folder_dialog(self) -> None:
        dlg = self._dialog_for("Open a session folder", "dir", str(self.sessions_dir))
        dlg.fileSelected.connect(lambda path: self.open_session(path))
        dlg.show()

    def export_session(self, folder: str | Path, out: str | Path) -> None:
        """Write the session's samples as one CSV (off the GUI thread)."""
        from smabench.sessions import export_csv, load_session

        def done(n: int) -> None:
            self.last_export_rows = n
            self.announce(f"{n} rows written to {out}.")

        self.jobs.submit(lambda: export_csv(load_session(folder), out), done,
                         lambda exc: self.announce(f"Export failed: {words.plain(str(exc))}",
                                                   error=True))  # fmt: skip

    def export_dialog(self) -> None:
        folder = self.selected_session()
        if folder is None:
            self.announce("Choose a session to export in the list first.", error=True)
            return
        dlg = self._dialog_for("Export CSV", "save", str(folder.with_suffix(".csv")))
        dlg.fileSelected.connect(lambda out: self.export_session(folder, out))
        dlg.show()

    def fit_selected(self) -> None:
        """Fit the chosen model to the selected session (off the GUI thread); the result is
        drawn in the Replay tab, over that session."""
        folder = self.selected_session()
        if folder is None:
            self.announce("Choose a session to fit in the list first.", error=True)
            return
        if self.fit_cycle.error():
            self.announce(f"Not fitted: {self.fit_cycle.error()}.", error=True)
            return
        model, cycle = self.fit_model.currentText(), self.fit_cycle.value()
        self.last_fit = None
        self.announce(f"Fitting the {model} model to {folder.name} …")

        def done(fit: dict[str, Any]) -> None:
            # a background result: drawn in the Replay tab, announced beside the message
            # line; the view and the message line (an E-STOP's, a saved session's) stay
            def show() -> None:
                self.replay.show_fit(fit["text"], fit["temp"], fit["model_mm"])
                self.last_fit = fit
                self.announce(f"Fit done: {model} on {folder.name}, cycle {fit['cycle']}, "
                              f"nrmse {fit['nrmse_percent']:.2f} % of stroke (Replay tab).")

            if self.replay.folder != folder:  # drawn over the session it was fitted to
                self.open_session(folder, after=show, switch=False)
            else:
                show()

        self.jobs.compute(fit_session, (folder, model, cycle), done,
                         lambda exc: self.announce(f"Not fitted: {words.plain(str(exc))}",
                                                   error=True))  # fmt: skip

