"""Issue 17 as a script: what a first-time operator did at the mock bench, with real widgets and
real key and mouse events (pytest-qt, QTest), asserting each thing the issue asked for.

- The E-STOP in every state (focus in a field, a drop-down, a menu, a non-modal and a modal file
  dialog, a long fit running off the GUI thread), measured on the device side: the runtime
  reports when the driver's telemetry first showed the output off (``time.monotonic()``, one
  clock for every process on Linux); the test subtracts the time it pressed the key. ≤ 100 ms.
- The run controls at 1280×800, 1400×900 and 1920×1080: each inside the visible window, not
  clipped; screenshots to ``docs/`` with ``SMABENCH_DOCS_SCREENSHOTS=1`` (offscreen).
- No wheel edits, refused input kept as typed with the range shown, only the chosen protocol's
  and device kind's fields, the state machine (refused start, lost device, dead runtime), the
  operator's settings and the sessions browser.
"""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from gui_support import (  # noqa: E402
    FAST_MOCK_SPEED,
    dispose,
    open_window,
    run_until_completed,
    start_running,
)
from PySide6 import QtCore, QtGui, QtWidgets  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from smabench.gui.state import State  # noqa: E402
from smabench.gui.worker import WORKER_NICE  # noqa: E402

Qt = QtCore.Qt
ESTOP_LIMIT_S = 0.100
# real time, as at the bench: the E-STOP's key-to-output-off time and the live controller tests
# (whose timing checks are in device time) run on it; runs that only have to run their course
# use gui_support.FAST_MOCK_SPEED
MOCK_SPEED = 1.0
WALK_MOCK_SPEED = 3.0
"""The walkthrough's first run on a faster mock (as FAST_MOCK_SPEED, but slower: its pause must
land in the second cycle, 7 s of device time, 2.3 s of wall time at 3×)."""
DOCS = Path(__file__).resolve().parents[1] / "docs"
SIZES = ((1280, 800), (1400, 900), (1920, 1080))
pytestmark = [pytest.mark.slow, pytest.mark.realtime_bench]


@pytest.fixture
def win(qtbot, tmp_path):
    """A fresh window, not connected; it keeps every message the operator saw and counts the
    runtime's status reports it showed."""
    w = open_window(tmp_path / "sessions", MOCK_SPEED)
    qtbot.addWidget(w)
    qtbot.waitExposed(w)
    messages: list[str] = []
    original, show_status = w.say, w._show_status

    def say(text: str, error: bool = False) -> None:  # every message the operator saw
        messages.append(text)
        original(text, error)

    def counted(st: dict) -> None:
        w.statuses_shown += 1
        show_status(st)

    w.say, w._show_status = say, counted
    w.messages, w.statuses_shown = messages, 0
    yield w
    dispose(w)


def type_into(qtbot, field, text: str) -> None:
    field.setFocus()
    qtbot.keyClick(field, Qt.Key.Key_A, Qt.KeyboardModifier.ControlModifier)
    qtbot.keyClicks(field, text)


def click(qtbot, widget) -> None:
    """A left click where a person would: on the indicator of a radio button or check box."""
    if isinstance(widget, (QtWidgets.QRadioButton, QtWidgets.QCheckBox)):
        pos = QtCore.QPoint(8, widget.height() // 2)
        qtbot.mouseClick(widget, Qt.MouseButton.LeftButton, pos=pos)
    else:
        qtbot.mouseClick(widget, Qt.MouseButton.LeftButton)


def cycles(qtbot, w, n: int = 1, heat_s: float = 4.0, cool_s: float = 3.0,
           current_a: float = 1.4) -> None:  # fmt: skip
    w.protocol.setCurrentText("cycles")
    type_into(qtbot, w.fields["protocol.cycles"], str(n))
    type_into(qtbot, w.fields["protocol.current_a"], f"{current_a:g}")
    type_into(qtbot, w.fields["protocol.heat_s"], f"{heat_s:g}")
    type_into(qtbot, w.fields["protocol.cool_timeout_s"], f"{cool_s:g}")


def wait_end(qtbot, w, timeout_ms: int = 60000) -> dict:
    qtbot.waitUntil(lambda: w.last_end is not None, timeout=timeout_ms)
    return w.last_end




def start_heating(qtbot, w, current_a: float = 1.4) -> None:
    """A long heating session running with the output on (the driver measures > 0.5 A)."""
    cycles(qtbot, w, n=3, heat_s=60.0, current_a=current_a)
    start_running(qtbot, w, lambda: click(qtbot, w.start_button))


def estop_latency_s(qtbot, w, pressed_t: float) -> float:
    qtbot.waitUntil(lambda: w.last_estop is not None, timeout=10000)
    report = w.last_estop
    assert report["confirmed"], report
    w.estop_split_ms = ((report["received_t"] - pressed_t) * 1e3,
                        (report["output_off_t"] - report["received_t"]) * 1e3)  # fmt: skip
    return report["output_off_t"] - pressed_t


def plain(text: str) -> bool:
    """No raw JSON, exception names, command-line hints or library sentences."""
    return not any(bad in text for bad in ("{", "}", "--", "Error:", "Exception", "Traceback",
                                           "Errno", "smabench "))  # fmt: skip


def simulated_session(root: Path, name: str = "sim-3cycles", n: int = 3) -> Path:
    """A recorded session from the plant simulation (for the sessions browser and fits)."""
    from smabench.physics.plant import heating_cycles_profile, simulate_plant
    from smabench.sessions import write_session

    t, i = heating_cycles_profile(n, 1.4, 3.0, 15.0, 0.005, load_kg=2.0)
    tr = simulate_plant(t, i, load_kg=2.0)
    data = {"t_s": t, "current_set_A": i, "current_A": tr.current_a,
            "position_mm": tr.position_mm, "temperature_est_C": tr.temperature_c,
            "cycle": np.floor(t / 18.0)}  # fmt: skip
    meta = {"kind": "bench", "load_kg": 2.0, "protocol": {"name": "cycles"},
            "started_at": "2026-11-20T10:00:00"}  # fmt: skip
    return write_session(root / name, meta, data)


# ----------------------------------------------------------------------------- E-STOP
def _open_dropdown(qtbot, w):
    w.tabs.setCurrentIndex(1)
    w.fit_model.setFocus()
    w.fit_model.showPopup()
    qtbot.waitUntil(lambda: QtWidgets.QApplication.activePopupWidget() is not None, timeout=5000)
    popup = QtWidgets.QApplication.activePopupWidget()
    return QtWidgets.QApplication.focusWidget() if popup.isAncestorOf(
        QtWidgets.QApplication.focusWidget()) else popup  # fmt: skip


def _open_menu(qtbot, w):
    menu = w.fit_cycle.createStandardContextMenu()
    menu.popup(w.fit_cycle.mapToGlobal(QtCore.QPoint(5, 5)))
    qtbot.waitUntil(lambda: QtWidgets.QApplication.activePopupWidget() is menu, timeout=5000)
    w._test_menu = menu
    return menu


def _open_file_dialog(qtbot, w, modal: bool):
    w.open_folder_dialog()
    dlg = w._dialog
    if modal:
        dlg.hide()
        dlg.setWindowModality(Qt.WindowModality.ApplicationModal)
        dlg.show()
    qtbot.waitExposed(dlg)
    assert dlg.testOption(QtWidgets.QFileDialog.Option.DontUseNativeDialog)
    dlg.activateWindow()
    return dlg.focusWidget() or dlg


def _long_fit(qtbot, w, tmp_path):
    """A Preisach fit of a recorded session through the Sessions tab's Fit button, computing
    in the GUI's computation process when this returns (that process says so itself: no
    assumption about how long a fit takes on this machine)."""
    folder = tmp_path / "elsewhere" / "sim-3cycles"
    if not folder.exists():
        simulated_session(folder.parent)
    w.set_sessions_dir(folder.parent)
    qtbot.waitUntil(lambda: w.session_list.topLevelItemCount() >= 1, timeout=10000)
    w.session_list.setCurrentItem(w.session_list.topLevelItem(0))
    w.fit_model.setCurrentText("preisach")
    click(qtbot, w.fit_button)
    # the worker started with the window at the lowest priority: on a loaded machine its
    # imports may still be going on; the key is pressed once the fit itself computes
    qtbot.waitUntil(lambda: w.jobs.computing, timeout=180000)
    w.fit_job, w.fit_folder = w.jobs.worker.current, folder
    return w.fit_cycle


def _gui_threads_nice() -> list[int]:
    """The nice value of every thread of this (the GUI's) process."""
    out = []
    for task in Path("/proc/self/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:  # the thread ended meanwhile
            continue
        out.append(int(stat.rsplit(")", 1)[1].split()[16]))
    return out


# below the energy budget's steady-state limit, sqrt(G·ΔT/R) = sqrt(0.0059 · 140 / 0.55) ≈ 1.2 A
# (drivers.protocol.HeatModel defaults), above the 0.5 A that shows the output on
HOLD_CURRENT_A = 0.9
STATES = ["drop-down", "menu", "file dialog", "modal file dialog", "fit running"]


@pytest.mark.parametrize("where", STATES)
def test_estop_key_stops_the_output_in_every_state(qtbot, bench_win, tmp_path, where):
    win = bench_win
    # a fit may take long on a loaded machine (its worker has the lowest priority): meanwhile
    # the wire is held at a current the driver's energy budget allows for ever
    start_heating(qtbot, win, HOLD_CURRENT_A if where == "fit running" else 1.4)
    if where == "drop-down":
        target = _open_dropdown(qtbot, win)
    elif where == "menu":
        target = _open_menu(qtbot, win)
    elif where == "file dialog":
        target = _open_file_dialog(qtbot, win, modal=False)
    elif where == "modal file dialog":
        target = _open_file_dialog(qtbot, win, modal=True)
        assert QtWidgets.QApplication.activeModalWidget() is win._dialog
    else:
        target = _long_fit(qtbot, win, tmp_path)
    assert win.state == State.RUNNING
    pressed = time.monotonic()
    QTest.keyClick(target, Qt.Key.Key_Escape)
    took = estop_latency_s(qtbot, win, pressed)
    print(f"\nE-STOP (Esc, {where}) → driver output off: {took * 1e3:.1f} ms"
          f" (GUI → runtime {win.estop_split_ms[0]:.1f} ms, runtime → off "
          f"{win.estop_split_ms[1]:.1f} ms)")
    assert took <= ESTOP_LIMIT_S, f"{where}: {took * 1e3:.0f} ms"
    end = wait_end(qtbot, win, 10000)
    assert end["status"] == "aborted" and end["reason"] == "e-stop"
    assert win.state == State.ESTOPPED and not win.start_button.isEnabled()
    assert QtWidgets.QApplication.activePopupWidget() is None  # what Esc would have closed
    if where == "fit running":
        # the fit computed through the whole key-to-output-off interval (the worker's clock)
        job, off_t = win.fit_job, win.last_estop["output_off_t"]
        assert job.begin_t < pressed and (job.end_t is None or job.end_t > off_t), (job, off_t)
        # in a process of its own at the lowest priority; no thread of the GUI process lowered
        # (one holding the interpreter lock would hold up the GUI's E-STOP path)
        assert os.getpriority(os.PRIO_PROCESS, win.jobs.worker.pid) == WORKER_NICE
        assert max(_gui_threads_nice()) < WORKER_NICE
        # the fit is not stopped by the E-STOP: it goes on and ends in the replay view
        qtbot.waitUntil(lambda: getattr(win, "last_fit", None) is not None, timeout=180000)
        assert win.last_fit["folder"] == str(win.fit_folder)


def test_estop_button_by_mouse_beside_an_open_file_dialog(qtbot, bench_win):
    win = bench_win
    start_heating(qtbot, win)
    win.open_folder_dialog()
    qtbot.waitExposed(win._dialog)
    pressed = time.monotonic()
    qtbot.mousePress(win.estop_button, Qt.MouseButton.LeftButton)
    took = estop_latency_s(qtbot, win, pressed)
    qtbot.mouseRelease(win.estop_button, Qt.MouseButton.LeftButton)
    print(f"\nE-STOP (mouse, file dialog open) → driver output off: {took * 1e3:.1f} ms"
          f" (GUI → runtime {win.estop_split_ms[0]:.1f} ms, runtime → off "
          f"{win.estop_split_ms[1]:.1f} ms)")
    assert took <= ESTOP_LIMIT_S
    assert win.state == State.ESTOPPED


# ----------------------------------------------------------------------------- layout
def _inside(win, w) -> bool:
    """The widget is shown whole inside the window's visible area."""
    if not w.isVisible():
        return False
    top_left = w.mapTo(win, QtCore.QPoint(0, 0))
    rect = QtCore.QRect(top_left, w.size())
    whole = w.visibleRegion().boundingRect() == w.rect()
    return win.rect().contains(rect) and whole


def test_run_controls_are_never_clipped_and_screenshots(qtbot, win, tmp_path):
    win.mock_speed.set_value(FAST_MOCK_SPEED)  # the run's cycles in a fifth of the time
    cycles(qtbot, win, n=4, heat_s=3.0, cool_s=8.0)  # a finished run in the plots
    end = run_until_completed(qtbot, win, lambda: click(qtbot, win.start_button))
    assert end is not None and end["status"] == "completed", (end, win.message.text())
    win.open_session(end["folder"])  # its replay (and its trends) for the screenshots
    qtbot.waitUntil(lambda: win.replay.folder == Path(end["folder"]), timeout=20000)
    win.tabs.setCurrentIndex(0)
    for width, height in SIZES:
        win.resize(width, height)
        qtbot.waitUntil(lambda w=width, h=height: win.size() == QtCore.QSize(w, h), timeout=5000)
        QtWidgets.QApplication.processEvents()
        for tab in range(win.settings_tabs.count()):  # whatever tab the operator is in
            win.settings_tabs.setCurrentIndex(tab)
            QtWidgets.QApplication.processEvents()
            for ctl in (win.estop_button, win.start_button, win.pause_button, win.stop_button,
                        win.connect_button, win.progress, win.times, win.state_label):
                assert _inside(win, ctl), (width, height, tab, ctl.text()
                                           if hasattr(ctl, "text") else ctl)  # fmt: skip
        win.settings_tabs.setCurrentIndex(0)
        QtWidgets.QApplication.processEvents()
        # docs/ only when asked (SMABENCH_DOCS_SCREENSHOTS=1), so test runs leave the tree alone
        shots = DOCS if os.environ.get("SMABENCH_DOCS_SCREENSHOTS") == "1" else tmp_path
        shots.mkdir(exist_ok=True)
        assert win.grab().save(str(shots / f"gui-{width}x{height}.png"))
        for tab, name in ((win.replay, "replay"), (win.trend_plots, "trends")):
            win.tabs.setCurrentWidget(tab)
            for _ in range(3):  # laid out, then drawn (the trends redraw on a frame)
                QtWidgets.QApplication.processEvents()
                win.on_frame()
            if tab is win.replay:  # the whole session in view at this size
                t0, t1 = win.replay.time_plots.p_current.viewRange()[0]
                assert t1 - t0 >= 0.95 * float(end["samples"]) * 0.005, (t0, t1)
            assert win.grab().save(str(shots / f"gui-{width}x{height}-{name}.png"))
        win.tabs.setCurrentIndex(0)
    # the latched E-STOP banner is in reach too
    win.estop()
    QtWidgets.QApplication.processEvents()
    assert _inside(win, win.banner) and _inside(win, win.ack_button)
    win.acknowledge_estop()


# ----------------------------------------------------------------------------- walkthrough
def test_operator_walkthrough(qtbot, win, tmp_path):
    f = win.fields
    # 1. the wheel over an unfocused field or drop-down changes nothing
    win.protocol.setCurrentText("inner")
    inner = f["protocol.inner_heat_s"]
    assert inner.isVisible() and inner.text() == "0.4"
    win.estop_button.setFocus()
    pos = QtCore.QPointF(inner.rect().center())
    for target in (inner, win.protocol):
        for delta in (-120, 120, -120):
            ev = QtGui.QWheelEvent(pos, QtCore.QPointF(target.mapToGlobal(pos.toPoint())),
                                   QtCore.QPoint(), QtCore.QPoint(0, delta),
                                   Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier,
                                   Qt.ScrollPhase.NoScrollPhase, False)  # fmt: skip
            QtWidgets.QApplication.sendEvent(target, ev)
    assert inner.text() == "0.4" and win.protocol.currentText() == "inner"
    # 2. only the chosen protocol's fields, only the chosen device kind's fields
    assert not f["protocol.amplitude_mm"].isVisibleTo(win)
    win.protocol.setCurrentText("sine")
    assert not f["protocol.inner_heat_s"].isVisibleTo(win)
    win.mode_buttons["pid"].setChecked(True)
    assert f["protocol.amplitude_mm"].isVisibleTo(win) and not f["protocol.heat_s"].isVisibleTo(win)
    win.settings_tabs.setCurrentIndex(3)  # Connection
    assert win.mock_speed.isVisible() and not win.port_row.isVisible()
    click(qtbot, win.use_real)
    assert win.port_row.isVisible() and win.sensor_host.isVisible()
    assert not win.mock_speed.isVisible() and not win.sensor_baud.isVisible()
    win.sensor_kind.setCurrentText("RTU")
    assert win.sensor_baud.isVisible() and not win.sensor_host.isVisible()
    click(qtbot, win.use_mock)
    win.settings_tabs.setCurrentIndex(0)
    # 3. a refused start (sine, open loop) stays idle and says why in words
    win.mode_buttons["open_loop"].setChecked(True)
    click(qtbot, win.start_button)
    assert win.state == State.DISCONNECTED and win.start_button.isEnabled()
    assert "position reference" in win.message.text() and plain(win.message.text())
    # 4. out-of-range input is refused with the range, never altered
    cycles(qtbot, win)
    type_into(qtbot, f["load_kg"], "-5")
    click(qtbot, win.start_button)
    assert f["load_kg"].text() == "-5" and win.state == State.DISCONNECTED
    assert "load" in win.message.text().lower() and "more than 0, up to 10 kg" in win.message.text()
    type_into(qtbot, f["protocol.cycles"], "50000")
    assert f["protocol.cycles"].text() == "50000" and "10000" in f["protocol.cycles"].error()
    type_into(qtbot, f["protocol.cycles"], "1")
    type_into(qtbot, f["load_kg"], "2")
    # the current limit is the operator's and is checked before anything is sent
    win.settings_tabs.setCurrentIndex(1)
    type_into(qtbot, f["current_limit_a"], "1.0")
    click(qtbot, win.start_button)
    assert win.state == State.DISCONNECTED and "limit" in win.message.text()
    assert f["position_min_mm"].isVisible() and f["position_max_mm"].isVisible()
    type_into(qtbot, f["current_limit_a"], "2")
    win.settings_tabs.setCurrentIndex(0)
    # 5. connect (to a faster mock, chosen in the Connection tab: the run below takes a third of
    #    the time; the controller session reconnects at real time): live readouts while idle
    win.settings_tabs.setCurrentIndex(3)
    type_into(qtbot, win.mock_speed, f"{WALK_MOCK_SPEED:g}")
    win.settings_tabs.setCurrentIndex(0)
    click(qtbot, win.connect_button)
    assert win.state == State.CONNECTING
    qtbot.waitUntil(lambda: win.state == State.IDLE, timeout=40000)
    assert win.connect_button.text() == "Disconnect"
    qtbot.waitUntil(lambda: win.status.get("readout", {}).get("position_mm") is not None,
                    timeout=10000)  # fmt: skip
    assert "position –" not in win.readout.text()
    # 6. a run: fields that cannot change mid-run are disabled; remaining time frozen in pause
    cycles(qtbot, win, n=2, heat_s=3.0, cool_s=4.0)
    shown_times: list[str] = []
    win.timer.timeout.connect(lambda: shown_times.append(win.times.text()))
    start_running(qtbot, win, lambda: click(qtbot, win.start_button))
    assert not f["load_kg"].isEnabled() and not f["protocol.cycles"].isEnabled()
    assert not win.protocol.isEnabled() and not f["current_limit_a"].isEnabled()
    assert not win.start_button.isEnabled() and win.stop_button.isEnabled()
    # progress and remaining time from the protocol's plan from the first second of cycle 1
    assert running_until(qtbot, win, lambda: "cycle 1 of 2" in win.times.text()
                         and win.progress.value() > 0 and "remaining –" not in win.times.text())
    assert running_until(qtbot, win, lambda: "cycle 2 of 2" in win.times.text())
    click(qtbot, win.pause_button)
    assert win.state == State.PAUSED and win.pause_button.text() == "Resume"
    qtbot.waitUntil(lambda: "paused" in win.times.text(), timeout=5000)
    frozen = win.times.text().split("remaining")[1].split()[0]
    # through three more status reports (1.5 s), each of which recomputes it while running
    shown = win.statuses_shown
    qtbot.waitUntil(lambda: win.statuses_shown >= shown + 3, timeout=10000)
    assert "paused" in win.times.text()
    assert win.times.text().split("remaining")[1].split()[0] == frozen
    click(qtbot, win.pause_button)
    assert win.state == State.RUNNING
    end = wait_end(qtbot, win)
    assert end["status"] == "completed", end
    assert win.state == State.IDLE and f["load_kg"].isEnabled()
    # the remaining time only goes down (it rose 27 → 33 s in 3 s when it was extrapolated
    # from the finished cycles), and it was there from cycle 1 on
    remaining = [float(m.group(1)) for t in shown_times
                 if (m := re.search(r"remaining (\d+) s", t))]  # fmt: skip
    assert remaining and max(np.diff(remaining), default=0.0) <= 1.0, remaining
    assert any("cycle 1 of 2" in t and "remaining –" not in t for t in shown_times)
    assert end["folder"] in win.message.text()  # the end message names the saved folder
    # cycles counted the same way: the run showed "cycle k of 2"; the record has 2 cycles
    from smabench.sessions import FLAG_AFTER_END, load_session

    recorded = load_session(end["folder"])
    assert shown_cycles(recorded.data["cycle"]) == 2
    live_n = win.buffer.n
    # 7. sessions: the list, double-click to replay in its own labelled view, fit the selection
    win.tabs.setCurrentIndex(1)
    assert str(win.sessions_dir.resolve()) in win.sessions_label.text()
    qtbot.waitUntil(lambda: win.session_list.topLevelItemCount() == 1, timeout=10000)
    item = win.session_list.topLevelItem(0)
    assert [item.text(i) for i in (1, 2, 3)] == ["2 kg", "cycles", "completed"]
    assert item.text(0)[:4].isdigit()
    rect = win.session_list.visualItemRect(item)
    # a double click as a mouse makes it: a click, then the double-click event
    qtbot.mouseClick(win.session_list.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())
    qtbot.mouseDClick(win.session_list.viewport(), Qt.MouseButton.LeftButton,
                      pos=rect.center())  # fmt: skip
    qtbot.waitUntil(lambda: win.replay.folder == Path(end["folder"]), timeout=20000)
    assert "REPLAY" in win.replay.title.text() and Path(end["folder"]).name in \
        win.replay.title.text() and "2 cycle(s)" in win.replay.title.text()
    assert win.buffer.n == live_n  # the live plots did not get the replay
    other = simulated_session(tmp_path / "elsewhere")
    win.open_session(other)  # any folder (the dialog's choice, without the dialog)
    qtbot.waitUntil(lambda: win.replay.folder == other, timeout=20000)
    win.tabs.setCurrentIndex(1)
    win.session_list.setCurrentItem(win.session_list.topLevelItem(0))
    win.fit_model.setCurrentText("sigmoid")
    click(qtbot, win.fit_button)
    # the fit's process (nice 19, started with the window 10 s ago) may still be importing
    # beside other work: the same generous deadline as the fit-running E-STOP test's
    qtbot.waitUntil(lambda: getattr(win, "last_fit", None) is not None, timeout=180000)
    assert win.last_fit["folder"] == end["folder"]  # the selected session, not what was shown
    assert win.replay.folder == Path(end["folder"])
    assert Path(end["folder"]).name in win.replay.fit_text.toPlainText()
    # 8. a refused start in the runtime (unreachable reference) goes back to idle, in words
    win.mode_buttons["pid"].setChecked(True)
    win.protocol.setCurrentText("sine")
    type_into(qtbot, f["protocol.amplitude_mm"], "40")
    click(qtbot, win.start_button)
    qtbot.waitUntil(lambda: win.state == State.IDLE and "Not started" in win.message.text(),
                    timeout=30000)  # fmt: skip
    assert plain(win.message.text()) and win.start_button.isEnabled()
    assert not win.stop_button.isEnabled() and win.buffer.n == live_n  # plots not wiped
    # 9. the mock bench killed mid-run: words, session aborted, buttons back to Connect
    cycles(qtbot, win, n=3, heat_s=60.0)
    win.mode_buttons["open_loop"].setChecked(True)
    win.last_end = None
    click(qtbot, win.start_button)
    qtbot.waitUntil(lambda: win.state == State.RUNNING and win.buffer.n > 20, timeout=30000)
    os.kill(win.link.ports["mock_pid"], signal.SIGKILL)
    end = wait_end(qtbot, win, 15000)
    assert end["status"] == "aborted"
    qtbot.waitUntil(lambda: win.state == State.ERROR, timeout=10000)
    assert win.connect_button.text() == "Connect" and win.start_button.isEnabled()
    assert "stopped answering" in win.message.text() and plain(win.message.text())
    # 10. controller session, at real time (the open-loop current's timing below is device
    #     time): Start reconnects first. FF+PID gains apply to FF+PID, not to the PID; back to
    #     the table; the active law shown; the open-loop current when switching live
    win.settings_tabs.setCurrentIndex(3)  # not connected: the connection settings are open
    type_into(qtbot, win.mock_speed, f"{MOCK_SPEED:g}")
    win.settings_tabs.setCurrentIndex(0)
    win.protocol.setCurrentText("sine")
    type_into(qtbot, f["protocol.amplitude_mm"], "0.6")
    type_into(qtbot, f["protocol.period_s"], "10")
    type_into(qtbot, f["protocol.cycles"], "3")
    win.mode_buttons["pid"].setChecked(True)
    win.settings_tabs.setCurrentIndex(2)
    assert win.gain_boxes["pid"].isVisible() and not win.gain_boxes["ffpid"].isVisible()
    win.last_end = None
    click(qtbot, win.start_button)
    assert win.state == State.CONNECTING  # Start reconnects first
    qtbot.waitUntil(lambda: win.state == State.RUNNING and win.status.get("mode") == "pid",
                    timeout=40000)  # fmt: skip
    assert win.link_config["time_scale"] == MOCK_SPEED
    assert "PID" in win.active_mode.text()
    click(qtbot, win.mode_buttons["ffpid"])  # live switch
    qtbot.waitUntil(lambda: win.status.get("mode") == "ffpid", timeout=10000)
    qtbot.waitUntil(lambda: "FF+PID" in win.active_mode.text(), timeout=5000)
    assert win.gain_boxes["ffpid"].isVisible() and win.gain_boxes["ffpid_hold"].isVisible()
    assert f["controller.ffpid_gains.kp"].isEnabled()  # live settings stay editable
    win.gain_table_boxes["ffpid"].setChecked(False)
    type_into(qtbot, f["controller.ffpid_gains.kp"], "0.123")
    click(qtbot, win.gain_apply["ffpid"])
    assert "applied to the running session" in win.message.text()
    type_into(qtbot, f[win.OPEN_LOOP_KEY], "0.5")
    click(qtbot, win.mode_buttons["open_loop"])
    qtbot.waitUntil(lambda: win.status.get("mode") == "open_loop", timeout=10000)
    assert "Open loop" in win.active_mode.text()
    click(qtbot, win.stop_button)
    end = wait_end(qtbot, win)
    assert end["status"] == "stopped"
    s = load_session(end["folder"])
    meta = json.loads((Path(end["folder"]) / "session.json").read_text())
    ctl = meta["controller_end"]
    assert ctl["ffpid_gains"]["kp"] == pytest.approx(0.123)  # FF+PID's, not the PID law's
    if "gains" in ctl:
        from smabench.control import gains_for_load

        assert ctl["gains"]["kp"] == pytest.approx(gains_for_load(2.0).kp)
    live = (s.data["flags"].astype(int) & FLAG_AFTER_END) == 0  # not the rows after the stop
    ol = (s.data["mode"] == "open_loop") & live
    held = s.data["current_set_A"][ol]
    # the operator's 0.5 A within half a second of the switch (one status period at most)
    t_ol = s.data["t_s"][ol]
    at = t_ol[np.argmax(np.isclose(held, 0.5, atol=0.01))] - t_ol[0]
    assert np.allclose(held[-10:], 0.5, atol=0.01) and at <= 0.6, (held[:5], held[-5:], at)
    # back to the per-load table: the fields show it again and the next start sends none
    click(qtbot, win.gain_table_boxes["ffpid"])
    assert win.custom_gains["ffpid"] is None and "per-load table" in win.message.text()
    assert f["controller.ffpid_gains.kp"].text() != "0.123"
    win.mode_buttons["ffpid"].setChecked(True)
    assert "ffpid_gains" not in (win.settings_dict().get("controller") or {})
    # 11. the runtime process killed mid-run: words, the session closed as aborted, Connect
    cycles(qtbot, win, n=3, heat_s=60.0)
    win.mode_buttons["open_loop"].setChecked(True)
    win.last_end = None
    click(qtbot, win.start_button)
    qtbot.waitUntil(lambda: win.state == State.RUNNING and win.buffer.n > 20, timeout=40000)
    folder = win.session_folder
    os.kill(win.link.proc.pid, signal.SIGKILL)
    qtbot.waitUntil(lambda: win.state == State.ERROR, timeout=15000)
    assert win.connect_button.text() == "Connect"
    assert "stopped unexpectedly" in win.message.text() and plain(win.message.text())
    assert json.loads((folder / "session.json").read_text())["status"] == "aborted"
    assert "cycle 1 of 3" not in win.times.text()
    # 12. nothing the operator read was raw JSON, a command-line hint or a library sentence
    bad = [m for m in win.messages if not plain(m)]
    assert not bad, bad


def running_until(qtbot, w, condition, timeout_ms: int = 30000) -> bool:
    """Wait until ``condition()`` or the session stops running; returns ``condition()``."""
    qtbot.waitUntil(lambda: condition() or w.state != State.RUNNING, timeout=timeout_ms)
    return bool(condition())


def shown_cycles(cycle_column: np.ndarray) -> int:
    from smabench.gui.fitjob import shown_cycle

    finite = cycle_column[np.isfinite(cycle_column)]
    return shown_cycle(finite.max())
