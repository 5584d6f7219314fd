"""The operator GUI offscreen (pytest-qt), on the mock bench through the real transports.

The E-STOP tests measure on the device side: the runtime reports when the driver's telemetry
first showed the output off (``X`` report, ``time.monotonic()``, one clock for all processes on
Linux), and the test subtracts the time it pressed the key.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from gui_support import (  # noqa: E402
    FAST_MOCK_SPEED,
    ensure_connected,
    fresh_window,
    run_until_completed,
    start_running,
)
from PySide6 import QtCore, QtGui, QtWidgets  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402

from smabench.gui.state import State  # noqa: E402
from smabench.gui.window import MainWindow  # noqa: E402

Qt = QtCore.Qt
ESTOP_LIMIT_S = 0.100
# real time, as at the bench: the E-STOP's key-to-output-off time and the live controller tests
# (whose timing checks are in device time) run on it; runs that only have to run their course
# use gui_support.FAST_MOCK_SPEED
MOCK_SPEED = 1.0


@pytest.fixture
def win(qtbot, tmp_path):
    """A fresh window, not connected."""
    yield from fresh_window(qtbot, tmp_path, MOCK_SPEED)


@pytest.fixture
def fast_win(qtbot, tmp_path):
    """A fresh window on a faster mock bench (a session that must run its course)."""
    yield from fresh_window(qtbot, tmp_path, FAST_MOCK_SPEED)


def type_into(qtbot, field, text: str) -> None:
    """Real key events: focus, select all, type."""
    field.setFocus()
    qtbot.keyClick(field, Qt.Key.Key_A, Qt.KeyboardModifier.ControlModifier)
    qtbot.keyClicks(field, text)


def short_cycles(qtbot, w: MainWindow, cycles: int = 1, heat_s: float = 4.0) -> None:
    w.protocol.setCurrentText("cycles")
    type_into(qtbot, w.fields["protocol.cycles"], str(cycles))
    type_into(qtbot, w.fields["protocol.current_a"], "1.4")
    type_into(qtbot, w.fields["protocol.heat_s"], f"{heat_s:g}")
    type_into(qtbot, w.fields["protocol.cool_timeout_s"], "3")


def wait_end(qtbot, w: MainWindow, timeout_ms: int = 40000) -> dict:
    qtbot.waitUntil(lambda: w.last_end is not None, timeout=timeout_ms)
    return w.last_end




def start_heating(qtbot, w: MainWindow) -> None:
    """A long heating cycle, running with the output on (the driver measures > 0.5 A)."""
    short_cycles(qtbot, w, cycles=3, heat_s=60.0)
    start_running(
        qtbot, w, lambda: qtbot.mouseClick(w.start_button, Qt.MouseButton.LeftButton)
    )


def press_estop_key(qtbot, target: QtWidgets.QWidget, key=Qt.Key.Key_Escape) -> float:
    """Press the key on ``target`` (where the focus or the popup is); returns the press time."""
    t = time.monotonic()
    QTest.keyClick(target, key)
    return t


def estop_latency_s(qtbot, w: MainWindow, pressed_t: float) -> float:
    """Key press → the driver's telemetry shows the output off (device side), s."""
    qtbot.waitUntil(lambda: w.last_estop is not None, timeout=10000)
    report = w.last_estop
    assert report["confirmed"], report
    w.estop_split_ms = ((report["received_t"] - pressed_t) * 1e3,
                        (report["output_off_t"] - report["received_t"]) * 1e3)  # fmt: skip
    return report["output_off_t"] - pressed_t


@pytest.mark.slow
def test_short_protocol_fills_the_plots_and_is_listed(qtbot, fast_win, tmp_path):
    win = fast_win
    short_cycles(qtbot, win)
    end = run_until_completed(
        qtbot, win, lambda: qtbot.mouseClick(win.start_button, Qt.MouseButton.LeftButton)
    )
    assert end is not None and end["status"] == "completed", (end, win.message.text())
    assert win.state == State.IDLE
    win.on_frame()
    assert win.buffer.n == end["samples"] > 50
    x, y = win.loop_plot.current.getData()
    assert x is not None and len(x) > 50 and np.nanmax(y) - np.nanmin(y) > 2.0
    assert "driver ok" in win.health.text()
    assert end["folder"] in win.message.text()  # the end message names the saved folder
    # every recorded session listed (one, or more when a link loss started it again), the
    # newest, this one, on top
    recorded = [d for d in win.sessions_dir.iterdir() if (d / "session.json").is_file()]
    assert Path(end["folder"]) in recorded
    qtbot.waitUntil(lambda: win.session_list.topLevelItemCount() == len(recorded), timeout=5000)
    item = win.session_list.topLevelItem(0)
    assert item.text(2) == "cycles" and item.text(3) == "completed" and item.text(1) == "2 kg"


@pytest.mark.parametrize(
    "key", [Qt.Key.Key_Escape, pytest.param(Qt.Key.Key_F12, marks=pytest.mark.slow)]
)
def test_estop_key_with_focus_in_a_field(qtbot, bench_win, key):
    win = bench_win
    start_heating(qtbot, win)
    field = win.fit_cycle  # a field enabled during a run (the Sessions tab)
    field.setFocus()
    t = press_estop_key(qtbot, field, key)
    took = estop_latency_s(qtbot, win, t)
    print(f"\nE-STOP ({QtGui.QKeySequence(key).toString()}, focus in a field) → driver output "
          f"off: {took * 1e3:.1f} ms (GUI → runtime {win.estop_split_ms[0]:.1f} ms, runtime → "
          f"off {win.estop_split_ms[1]:.1f} ms)")
    assert took <= ESTOP_LIMIT_S
    end = wait_end(qtbot, win, 10000)
    assert end["status"] == "aborted" and end["reason"] == "e-stop"
    # latched: banner, Start disabled until acknowledged
    assert win.state == State.ESTOPPED and win.banner.isVisible()
    assert not win.start_button.isEnabled()
    qtbot.mouseClick(win.ack_button, Qt.MouseButton.LeftButton)
    assert win.state == State.IDLE and win.start_button.isEnabled()


def test_estop_with_nothing_connected_says_so(qtbot, win):
    qtbot.mouseClick(win.estop_button, Qt.MouseButton.LeftButton)
    assert win.state == State.ESTOPPED
    assert "nothing is connected" in win.message.text()
    assert not win.start_button.isEnabled()
    win.acknowledge_estop()
    assert win.state == State.DISCONNECTED and win.start_button.isEnabled()


@pytest.mark.slow
def test_lost_device_closes_the_session_and_offers_connect(qtbot, bench_win):
    win = bench_win
    start_heating(qtbot, win)
    os.kill(win.link.ports["mock_pid"], signal.SIGKILL)
    end = wait_end(qtbot, win, 10000)
    assert end["status"] == "aborted" and "lost" in end["reason"]
    qtbot.waitUntil(lambda: win.state == State.ERROR, timeout=5000)
    assert win.connect_button.text() == "Connect"
    assert "stopped answering" in win.message.text()
    assert "Exception" not in win.message.text() and "{" not in win.message.text()
    # usable again: Start reconnects and runs a session (how long the mock keeps up on a
    # loaded machine is not the GUI's business: the session is stopped once it runs)
    win.last_end = None
    start_heating(qtbot, win)
    assert win.link.ports["mock_pid"] is not None and win.connect_button.text() == "Disconnect"
    qtbot.mouseClick(win.stop_button, Qt.MouseButton.LeftButton)
    assert wait_end(qtbot, win)["status"] in ("stopped", "aborted")
    assert win.state in (State.IDLE, State.ERROR)


def test_bench_gui_frame_time_with_an_hour_of_data(qtbot):
    """Short version of `smabench bench gui` (the README figures come from the full run)."""
    from smabench.gui.bench_gui import frame_times

    f = frame_times(n_frames=20)
    assert f["hours"] > 0.99 and f["frames"] == 20
    assert 0 < f["median_ms"] <= f["p99_ms"]


@pytest.mark.slow
def test_controller_mode_switches_live(qtbot, bench_win):
    """A sine reference under PID, switched to FF+PID mid-run from the controller panel."""
    win = bench_win
    from smabench.sessions import load_session

    win.mode_buttons["pid"].setChecked(True)
    win.protocol.setCurrentText("sine")
    type_into(qtbot, win.fields["protocol.cycles"], "1")
    type_into(qtbot, win.fields["protocol.period_s"], "10")
    type_into(qtbot, win.fields["protocol.amplitude_mm"], "0.6")
    qtbot.mouseClick(win.start_button, Qt.MouseButton.LeftButton)
    # connecting again (a test before lost the bench) and building the controller's model take
    # tens of seconds at load 15: the same deadline as gui_support.start_running, and the
    # window's own account when it did not get there
    qtbot.waitUntil(lambda: (win.status.get("mode") == "pid" and win.buffer.n > 100)
                    or win.state in (State.ERROR, State.IDLE, State.DISCONNECTED),
                    timeout=60000)  # fmt: skip
    assert win.status.get("mode") == "pid" and win.state == State.RUNNING, (
        win.state, win.message.text(), win.last_end, win.sm.history[-4:])  # fmt: skip
    assert "PID" in win.active_mode.text()
    qtbot.mouseClick(win.mode_buttons["ffpid"], Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: win.status.get("mode") == "ffpid", timeout=5000)
    qtbot.waitUntil(lambda: "FF+PID" in win.active_mode.text(), timeout=5000)
    qtbot.mouseClick(win.stop_button, Qt.MouseButton.LeftButton)
    end = wait_end(qtbot, win)
    assert end["status"] == "stopped", end
    s = load_session(end["folder"])
    modes = list(dict.fromkeys(s.data["mode"]))
    assert modes[:2] == ["pid", "ffpid"], modes
    i = s.data["current_set_A"]
    k = int(np.argmax(s.data["mode"] == "ffpid"))
    jump = abs(i[k] - i[k - 1])
    usual = np.percentile(np.abs(np.diff(i[:k])), 99)
    assert jump <= max(0.15, 2 * usual), (jump, usual)


def test_state_machine_latches_the_estop_and_refuses_what_a_state_does_not_allow():
    from smabench.gui.state import StateMachine, controls_for

    sm = StateMachine()
    assert sm.fire("start") == State.DISCONNECTED  # ignored: not connected
    for event, want in (("connect", State.CONNECTING), ("connected", State.IDLE),
                        ("start", State.STARTING), ("refused", State.IDLE),
                        ("start", State.STARTING), ("started", State.RUNNING),
                        ("pause", State.PAUSED), ("estop", State.ESTOPPED),
                        ("ended", State.ESTOPPED), ("lost", State.ESTOPPED),
                        ("acknowledge_disconnected", State.DISCONNECTED)):  # fmt: skip
        assert sm.fire(event) == want, (event, sm.history)
    c = controls_for(State.ESTOPPED)
    assert not c.start and c.acknowledge
    c = controls_for(State.RUNNING)
    assert not c.start and c.stop and c.pause and not c.session_fields and c.live_fields
    assert controls_for(State.ERROR).connect_label == "Connect"
    assert controls_for(State.IDLE).connect_label == "Disconnect"


@pytest.mark.parametrize("raw, want", [
    ("start: ValueError: protocol 'sine' is a position reference: it needs a controller "
     "(--controller pid|ff|ffpid)", "The sine protocol is a position reference"),
    ("current driver telemetry lost for 0.31 s", "The current driver stopped answering"),
    ("runtime process exited (-9)", "The bench program stopped unexpectedly"),
    ("SerialException: could not open port /dev/ttyUSB0: [Errno 2] No such file or directory: "
     "'/dev/ttyUSB0'", "serial port cannot be opened"),
    ("interlock: commanded current 2.100 A outside 0 … 2.0 A", "Stopped by the current limit"),
    ("load must be in (0, 10] kg, got -5 kg (load_kg)",
     "Load must be more than 0, up to 10 kg, got -5 kg."),
    ("cycles must be in 1 … 10000, got 0", "Cycles must be 1 to 10000, got 0."),
    ('start: JSONDecodeError: Expecting value {"a": 1}', "Expecting value."),
])  # fmt: skip
def test_messages_are_plain_words(raw, want):
    from smabench.gui.words import plain

    text = plain(raw)
    assert want in text, text
    for bad in ("{", "--", "Error:", "Exception", "Errno", "(load_kg)"):
        assert bad not in text, text


@pytest.mark.slow
def test_device_lost_while_idle_is_noticed(qtbot, bench_win):
    win = bench_win
    ensure_connected(qtbot, win)  # (Connect pressed when the shared window is not connected)
    qtbot.waitUntil(lambda: win.status.get("readout", {}).get("position_mm") is not None,
                    timeout=10000)  # fmt: skip
    os.kill(win.link.ports["mock_pid"], signal.SIGKILL)
    qtbot.waitUntil(lambda: win.state == State.ERROR, timeout=15000)
    assert win.connect_button.text() == "Connect" and win.link is None
    assert "stopped answering" in win.message.text()


@pytest.mark.slow  # the worker's imports run at nice 19: on a loaded machine that takes minutes
def test_computation_worker_lowest_priority_results_errors_and_a_crash(tmp_path):
    """The GUI's computation process: lowered before its imports, answers in order, says when
    a job computes (its own clock), fails a job whose process died, and starts again."""
    from smabench.gui.fitjob import fit_session, shown_cycle
    from smabench.gui.worker import WORKER_NICE, ComputeWorker
    from smabench.sessions import SessionError

    w = ComputeWorker()
    try:
        w.start()
        assert w.ready.wait(120)
        assert os.getpriority(os.PRIO_PROCESS, w.pid) == WORKER_NICE
        assert "libQt6" not in Path(f"/proc/{w.pid}/maps").read_text()  # no Qt in the worker
        assert w.submit(shown_cycle, (2.0,)).result(60) == 3
        with pytest.raises(SessionError, match="no such session"):
            w.submit(fit_session, (tmp_path / "none", "sigmoid", None)).result(60)
        assert [j.end_t is not None and j.end_t >= j.begin_t for j in w.finished] == [True] * 2
        slow = w.submit(time.sleep, (60.0,))
        deadline = time.monotonic() + 60
        while not w.computing and time.monotonic() < deadline:
            time.sleep(0.01)
        assert w.computing and w.current.end_t is None
        first = w.pid
        os.kill(first, signal.SIGKILL)
        with pytest.raises(RuntimeError, match="stopped"):
            slow.result(60)
        assert not w.computing
        assert w.submit(shown_cycle, (0.0,)).result(120) == 1 and w.pid != first
    finally:
        w.close()
    assert not w.alive
