"""What the GUI test files share: windows, one bench window for several tests, starting a
session (one press of Start, no retry)."""

from __future__ import annotations

import gc
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtWidgets

from smabench.drivers.mock.bench import REALTIME_MAX_SPEED
from smabench.gui.app import make_app
from smabench.gui.state import State
from smabench.gui.window import MainWindow

FAST_MOCK_SPEED = REALTIME_MAX_SPEED
"""Mock bench speed (×) for tests that wait for a session to run its course, not for anything
timed in real time (the E-STOP's key-to-output-off time runs on a real-time mock): protocol
durations and recorded times are device time, so the session is the same, in a fifth of the
wall time. The GUI's runtime scales the driver's setpoint lease, host timeout and telemetry
period with the speed (the same wall-clock timing as at 1×; ``test_gui_trends``), and up to
this speed the mock still runs real-time scheduled, as at 1×."""


def open_window(sessions_dir: str | Path, mock_speed: float = 1.0,
                size: tuple[int, int] = (1280, 800)) -> MainWindow:  # fmt: skip
    """A shown main window on the mock bench (not connected)."""
    make_app()
    w = MainWindow(sessions_dir, mock_speed=mock_speed)
    w.resize(*size)
    w.show()
    return w


def fresh_window(qtbot, tmp_path: Path, mock_speed: float) -> Iterator[MainWindow]:
    """Fixture body: a shown window (not connected) with its own sessions folder, disposed
    after the test."""
    w = open_window(tmp_path / "sessions", mock_speed)
    qtbot.addWidget(w)
    yield w
    dispose(w)


def dispose(w: MainWindow) -> None:
    """Close the window and destroy its Qt objects here, on the GUI thread (a later garbage
    collection in another thread would run Qt destructors there)."""
    w.close()
    w.deleteLater()
    QtCore.QCoreApplication.sendPostedEvents(None, QtCore.QEvent.Type.DeferredDelete)
    gc.collect()


class SharedBench:
    """One window and its connection to the mock bench (runtime process, mock process) for
    several tests of a module, instead of a window, a runtime and a mock started and closed
    for each. :meth:`for_test` gives each test the window as a fresh one would be: popups and
    dialogs closed, no session running, an E-STOP acknowledged, every field, choice and tab as
    when the window was made, its own sessions folder, nothing left of the previous test's
    results. It stays connected when it is (a test that lost the bench leaves it not
    connected; Start connects again, as for a fresh window)."""

    def __init__(self, sessions_dir: Path, mock_speed: float = 1.0) -> None:
        self.w = open_window(sessions_dir, mock_speed)
        self.closed = False
        self._entries = _entries(self.w)
        self._tabs = (self.w.tabs.currentIndex(), self.w.settings_tabs.currentIndex())

    def for_test(self, qtbot, sessions_dir: Path) -> MainWindow:
        w = self.w
        _close_overlays(w)
        if w.state in (State.STARTING, State.RUNNING, State.PAUSED):  # a failed test's session
            w.last_end = None
            w.estop()
            qtbot.waitUntil(lambda: w.last_end is not None or w.link is None, timeout=15000)
        if w.state == State.CONNECTING:
            qtbot.waitUntil(lambda: w.state != State.CONNECTING, timeout=60000)
        w.acknowledge_estop()
        # a fit still computing would draw into this test's Sessions tab
        qtbot.waitUntil(lambda: not w.jobs.busy, timeout=180000)
        _restore_entries(w, self._entries)
        w.tabs.setCurrentIndex(self._tabs[0])
        w.settings_tabs.setCurrentIndex(self._tabs[1])
        w.set_sessions_dir(sessions_dir)
        qtbot.waitUntil(lambda: not w.jobs.busy, timeout=10000)  # the list read
        w.last_end = w.last_estop = w.estop_time = w.last_fit = None
        w.pending_start = None
        w._clear_live()  # no samples of the previous test's session in the plots
        w.status = {}  # nor its last status (the runtime sends the next within 0.5 s)
        w.say("")
        assert w.state in (State.IDLE, State.DISCONNECTED, State.ERROR), w.sm.history[-4:]
        return w

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            _close_overlays(self.w)
            dispose(self.w)


def _close_overlays(w: MainWindow) -> None:
    """Popups, menus and dialogs a test left open (the E-STOP key closes them in a test that
    passes; one that failed may not have got there)."""
    for _ in range(5):
        popup = QtWidgets.QApplication.activePopupWidget()
        if popup is None:
            break
        popup.close()
    modal = QtWidgets.QApplication.activeModalWidget()
    if isinstance(modal, QtWidgets.QDialog):
        modal.reject()
    dialog = getattr(w, "_dialog", None)
    if dialog is not None and dialog.isVisible():
        dialog.reject()
    QtWidgets.QApplication.processEvents()


def _entry_widgets(w: MainWindow) -> dict[str, QtWidgets.QWidget]:
    """What an operator can enter or choose: the settings fields, the protocol, the law, the
    gain tables, the fit model and cycle, the mock's options."""
    out: dict[str, QtWidgets.QWidget] = {f"field:{k}": f for k, f in w.fields.items()}
    out.update({f"mode:{m}": b for m, b in w.mode_buttons.items()})
    out.update({f"gain_table:{law}": b for law, b in w.gain_table_boxes.items()})
    out.update(protocol=w.protocol, fit_model=w.fit_model, fit_cycle=w.fit_cycle,
               use_mock=w.use_mock, use_real=w.use_real, mock_effect=w.mock_effect,
               mock_thermocouple=w.mock_thermocouple,
               mock_resistivity=w.mock_resistivity)  # fmt: skip
    return out


def _entries(w: MainWindow) -> dict[str, object]:
    out: dict[str, object] = {}
    for name, wdg in _entry_widgets(w).items():
        if isinstance(wdg, QtWidgets.QLineEdit):
            out[name] = wdg.text()
        elif isinstance(wdg, QtWidgets.QComboBox):
            out[name] = wdg.currentText()
        elif isinstance(wdg, QtWidgets.QAbstractButton):
            out[name] = wdg.isChecked()
    out["custom_gains"] = dict(w.custom_gains)
    return out


def _restore_entries(w: MainWindow, entries: dict[str, object]) -> None:
    """Back to ``entries`` (from :func:`_entries`): choices first, then the gain tables (which
    rewrite their gain fields), then the fields' text."""
    widgets = _entry_widgets(w)
    for name, wdg in widgets.items():
        if isinstance(wdg, QtWidgets.QComboBox):
            wdg.setCurrentText(entries[name])
        elif isinstance(wdg, QtWidgets.QRadioButton) and entries[name]:
            wdg.setChecked(True)  # (its group unchecks the others)
    for name, wdg in widgets.items():
        if isinstance(wdg, QtWidgets.QCheckBox):
            wdg.setChecked(entries[name])
    for name, wdg in widgets.items():
        if isinstance(wdg, QtWidgets.QLineEdit):
            wdg.setText(entries[name])
    assert _entries(w) == entries, "the shared window's entries were not restored"


def ensure_connected(qtbot, w) -> None:
    """Connected and idle: Connect pressed once when the window is not."""
    if w.state != State.IDLE:
        qtbot.mouseClick(w.connect_button, QtCore.Qt.MouseButton.LeftButton)
        qtbot.waitUntil(lambda: w.state in (State.IDLE, State.ERROR), timeout=60000)
    assert w.state == State.IDLE, (w.state, w.message.text(), w.sm.history[-4:])


def measured_current_a(w) -> float:
    """The current the driver measured, A (0 when none yet), as the window has it: in the
    newest streamed sample (every 30 ms; the window holds only the running session's) or in the
    runtime's status readout (twice a second), the larger."""
    status = w.status.get("readout", {}).get("current_a") or 0.0
    streamed = w.buffer.column("current_A")[-1] if w.buffer.n else np.nan
    return float(max(status, streamed if np.isfinite(streamed) else 0.0))


def start_running(qtbot, w, press_start: Callable[[], None]) -> None:
    """Press Start once (``press_start``); the session must run with the output on (the
    driver measures > 0.5 A). No second press: a session that does not start is a failure,
    with the window's state, message and last transitions."""
    w.last_end = None
    press_start()
    qtbot.waitUntil(lambda: w.state in (State.RUNNING, State.ERROR) or w.last_end or (
        w.state == State.IDLE and "Not started" in w.message.text()), timeout=60000)
    if w.state == State.RUNNING:
        qtbot.waitUntil(lambda: measured_current_a(w) > 0.5 or w.state != State.RUNNING,
                        timeout=30000)  # fmt: skip
    assert w.state == State.RUNNING, (w.state, w.message.text(), w.last_end, w.sm.history[-4:])


def run_until_completed(qtbot, w, press_start: Callable[[], None],
                        timeout_ms: int = 60000) -> dict | None:  # fmt: skip
    """Press Start once (``press_start``) and wait for the session's end; returns its end
    report (None when it did not start)."""
    w.last_end = None
    press_start()
    qtbot.waitUntil(lambda: w.last_end is not None or w.state in (
        State.ERROR, State.DISCONNECTED) or (
        w.state == State.IDLE and "Not started" in w.message.text()),
        timeout=timeout_ms)  # fmt: skip
    return w.last_end


def last_to_use(request, fixture: str) -> bool:
    """The running test is the last of its module (in this run) that uses ``fixture``: a
    shared bench is closed after it, not at the module's end (its mock, at real time, takes a
    fifth of a core, and its window redraws, under the tests after it)."""
    users = [item for item in request.session.items if item.module is request.node.module
             and fixture in getattr(item, "fixturenames", ())]  # fmt: skip
    return bool(users) and users[-1] is request.node
