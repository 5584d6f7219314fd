"""Issue 28 as a script: each thing an operator tripped over in the GUI's second pass, done
again with real key and mouse events (pytest-qt) on the real window against the mock bench,
asserting what the operator must see instead.

1. a lost device: one state on screen, the right reason saved, no row after the loss drawn live;
2. after an E-STOP or a trip every readout cleared or stale with its age, the wire temperature
   still estimated;
3. a fit finishing during a run changes neither the view nor the safety message;
4. a layout that does not move: the banner's place reserved, Acknowledge beside the E-STOP,
   dialogs closed by the E-STOP;
5. the replay's whole time range, trends with whole cycles and a visible first cycle;
6. words: labels and tooltips from the schema, one notation for ranges, every invalid field
   listed and the message following the fixes;
7. settings remembered (a temporary QSettings location: ``conftest.gui_settings_store``) with
   Defaults; connect says what it does and can be cancelled; a clean quit.
"""

from __future__ import annotations

import json
import os
import re
import signal
import time

import numpy as np
import pytest

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from gui_support import (  # noqa: E402
    FAST_MOCK_SPEED,
    dispose,
    measured_current_a,
    open_window,
    run_until_completed,
    start_running,
)
from PySide6 import QtCore, QtWidgets  # noqa: E402
from PySide6.QtTest import QTest  # noqa: E402
from test_gui_walkthrough import click, cycles, simulated_session, type_into  # noqa: E402

from smabench.gui.state import State  # noqa: E402

Qt = QtCore.Qt
MOCK_SPEED = 1.0
KEY_LIKE = re.compile(r"\(\w+(\.\w+)+\)|\b[a-z]+_[a-z_]+\b")  # "(protocol.current_a)", "d_filter_s"
INTERVAL = re.compile(r"[\[(]-?[\d.]+, ?-?[\d.]+[\])]|…")  # "(0, 10]", "0 … 2.5"


@pytest.fixture
def win(qtbot, tmp_path):
    w = open_window(tmp_path / "sessions", MOCK_SPEED)
    qtbot.addWidget(w)
    qtbot.waitExposed(w)
    yield w
    dispose(w)


def record_frames(w) -> list[dict]:
    """After every frame of the window: what the operator sees (state, health, buttons,
    readouts, message) and when."""
    frames: list[dict] = []

    def snap() -> None:
        frames.append({"t": time.monotonic(), "state": w.state_label.text(),
                       "health": w.health.text(), "start": w.start_button.isEnabled(),
                       "pause": w.pause_button.isEnabled(), "readout": w.readout.text(),
                       "message": w.message.text(), "times": w.times.text()})  # fmt: skip

    w.timer.timeout.connect(snap)
    return frames


def heating(qtbot, w, current_a: float = 1.4) -> None:
    cycles(qtbot, w, n=3, heat_s=60.0, current_a=current_a)
    start_running(qtbot, w, lambda: click(qtbot, w.start_button))


# ----------------------------------------------------------------------------- 1. lost device
@pytest.mark.slow
def test_lost_device_one_state_right_reason_no_live_row_after(qtbot, win):
    heating(qtbot, win)
    qtbot.waitUntil(lambda: win.buffer.n > 300, timeout=10000)  # 1.5 s recorded
    folder = win.session_folder
    frames = record_frames(win)
    killed = time.monotonic()
    os.kill(win.link.ports["mock_pid"], signal.SIGKILL)
    qtbot.waitUntil(lambda: win.state == State.ERROR, timeout=15000)
    qtbot.waitUntil(lambda: win.last_end is not None, timeout=15000)
    shown = time.monotonic()
    qtbot.waitUntil(lambda: time.monotonic() > shown + 1.0, timeout=5000)
    # no frame in which two widgets disagreed: once anything said "lost", the state said so
    told = False
    for f in frames:
        told = told or "LOST" in f["health"] or "stopped answering" in f["message"]
        if told:
            assert f["state"] == "Not connected" and not f["pause"], f
            assert "device lost" in f["readout"] or "not connected" in f["readout"], f
    assert told
    # the window never froze while the link went (an E-STOP key is handled in a frame)
    gaps = np.diff([killed] + [f["t"] for f in frames])
    assert gaps.max() < 1.0, gaps.max()
    assert win.connect_button.text() == "Connect" and win.start_button.isEnabled()
    assert "Device lost" in win.message.text() and str(folder) in win.message.text()
    # the saved reason names the lost device
    meta = json.loads((folder / "session.json").read_text())
    assert meta["status"] == "aborted" and "lost" in meta["end_reason"], meta["end_reason"]
    # rows the runtime recorded after the driver went silent carry its last 1.4 A: not live
    t, cur = win.buffer.column("t_s"), win.buffer.column("current_A")
    assert np.isfinite(cur[t < t[-1] - 0.5]).any()
    assert not np.isfinite(cur[t > t[-1] - 0.2]).any(), cur[-10:]


def test_the_first_status_with_the_driver_down_ends_everything_at_once(qtbot, win):
    """The message order seen at load 13: the session's end with the device's output off, then
    the status with the link down. The window goes to 'not connected' on that status, not
    'Connected · idle' beside 'driver LOST'."""
    win.fire("connect")
    win.link = type("L", (), {"ports": {}, "alive": True, "close": lambda self, **k: None,
                              "estop": lambda self: True, "poll": lambda self: [],
                              "take_rows": lambda self: np.empty((0, 8))})()  # fmt: skip
    win.fire("connected")
    win.on_event("E", {"status": "aborted", "reason": "current driver output turned off by "
                       "the device", "samples": 10, "folder": "/tmp/x"})  # fmt: skip
    win.on_event("S", {"running": False, "driver_link_ok": False, "driver_fault": "link lost",
                       "sensor_stats": {}, "readout": {"current_a": 1.4}})  # fmt: skip
    assert win.state == State.ERROR and win.state_label.text() == "Not connected"
    assert "1.4" not in win.readout.text() and win.health.text() == "not connected"


# ----------------------------------------------------------------------------- 2. stale values
@pytest.mark.slow
def test_estop_leaves_no_live_looking_readout_and_keeps_the_wire_estimate(qtbot, win):
    heating(qtbot, win)
    qtbot.waitUntil(lambda: (win.status.get("readout", {}).get("temperature_c") or 0) > 45,
                    timeout=30000)  # fmt: skip
    frames = record_frames(win)
    QTest.keyClick(win.fit_cycle, Qt.Key.Key_E, Qt.KeyboardModifier.ControlModifier)
    pressed = time.monotonic()
    qtbot.waitUntil(lambda: win.last_end is not None, timeout=10000)
    qtbot.waitUntil(lambda: time.monotonic() > pressed + 1.5, timeout=5000)
    after = [f for f in frames if f["t"] > pressed]
    assert after
    for f in after:
        assert "current 1.4" not in f["readout"] and "law Open loop" not in f["readout"], f
        assert "heat" not in f["times"] and "cycle 1 of 3" not in f["times"], f
        m = re.search(r"wire \(estimated[^)]*\) ([\d.]+) °C", f["readout"])
        assert m and float(m.group(1)) > 30, f  # an estimate, not "–"
        assert "E-STOP" in f["readout"]
    assert re.search(r"[\d.]+ s ago", after[-1]["readout"]), after[-1]
    t0 = float(re.search(r"\) ([\d.]+) °C", after[0]["readout"]).group(1))
    t1 = float(re.search(r"\) ([\d.]+) °C", after[-1]["readout"]).group(1))
    assert t1 < t0  # cooling at no current
    click(qtbot, win.ack_button)
    qtbot.waitUntil(lambda: "ago" not in win.readout.text() and "current" in win.readout.text(),
                    timeout=5000)  # fmt: skip


@pytest.mark.slow
def test_a_trip_marks_the_readouts_stale(qtbot, win):
    win.mock_speed.set_value(FAST_MOCK_SPEED)
    cycles(qtbot, win, n=3, heat_s=60.0)
    win.settings_tabs.setCurrentIndex(1)
    type_into(qtbot, win.fields["temperature_limit_c"], "45")
    end = run_until_completed(qtbot, win, lambda: click(qtbot, win.start_button))
    assert end is not None and end["status"] == "aborted" and "interlock" in end["reason"], end
    assert "temperature limit" in win.message.text()
    assert "stopped" in win.readout.text() and "current –" in win.readout.text()
    assert re.search(r"wire \(estimated, cooling\) [\d.]+ °C", win.readout.text())


# ----------------------------------------------------------------------------- 3. background
@pytest.mark.slow
def test_a_fit_finishing_during_a_run_changes_neither_view_nor_safety_message(qtbot, win):
    simulated_session(win.sessions_dir)
    heating(qtbot, win, current_a=0.9)
    win.tabs.setCurrentIndex(1)
    click(qtbot, next(b for b in win.findChildren(QtWidgets.QPushButton)
                      if b.text() == "Refresh"))  # fmt: skip
    qtbot.waitUntil(lambda: win.session_list.topLevelItemCount() >= 2, timeout=10000)
    items = [win.session_list.topLevelItem(i) for i in range(2)]
    sim = next(i for i in items if "sim-3cycles" in i.text(4))
    rect = win.session_list.visualItemRect(sim)
    qtbot.mouseClick(win.session_list.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())
    win.fit_model.setCurrentText("sigmoid")
    click(qtbot, win.fit_button)
    bar = win.tabs.tabBar()
    qtbot.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(0).center())  # Live
    assert win.tabs.currentIndex() == 0
    QTest.keyClick(win, Qt.Key.Key_F12)
    qtbot.waitUntil(lambda: win.last_estop is not None, timeout=10000)
    estop_text = win.message.text()
    assert estop_text.startswith("E-STOP")
    qtbot.waitUntil(lambda: getattr(win, "last_fit", None) is not None, timeout=180000)
    for _ in range(3):
        win.on_frame()
    assert win.tabs.currentIndex() == 0  # still Live
    assert win.message.text() == estop_text
    assert "Fit done" in win.jobs_label.text() and win.replay.folder.name == "sim-3cycles"


# ----------------------------------------------------------------------------- 4. layout
@pytest.mark.parametrize("size", [(1280, 800), (1920, 1080)])
def test_the_layout_does_not_move_and_acknowledge_is_beside_the_estop(qtbot, win, size):
    win.resize(*size)
    qtbot.waitUntil(lambda: win.size() == QtCore.QSize(*size), timeout=5000)
    QtWidgets.QApplication.processEvents()

    def places() -> dict[str, QtCore.QPoint]:
        return {n: w.mapTo(win, QtCore.QPoint(0, 0)) for n, w in
                (("tabs", win.tabs), ("settings", win.settings_tabs), ("readout", win.readout),
                 ("message", win.message), ("start", win.start_button))}  # fmt: skip

    before = places()
    # a file dialog open when the E-STOP is pressed (by key) is closed by it
    click(qtbot, next(b for b in win.findChildren(QtWidgets.QPushButton)
                      if b.text() == "Open a session folder…"))  # fmt: skip
    qtbot.waitUntil(lambda: win._dialog.isVisible(), timeout=5000)
    QTest.keyClick(win._dialog.focusWidget() or win._dialog, Qt.Key.Key_Escape)
    QtWidgets.QApplication.processEvents()
    assert win.state == State.ESTOPPED and not win._dialog.isVisible()
    assert win.banner_label.text().startswith("E-STOP")
    assert places() == before  # the banner appeared in its reserved place
    e, a = win.estop_button, win.ack_button
    e_rect = QtCore.QRect(e.mapTo(win, QtCore.QPoint(0, 0)), e.size())
    a_rect = QtCore.QRect(a.mapTo(win, QtCore.QPoint(0, 0)), a.size())
    assert a.isEnabled() and win.rect().contains(a_rect)
    assert 0 <= a_rect.left() - e_rect.right() <= 20 and abs(a_rect.top() - e_rect.top()) <= 5
    click(qtbot, a)
    assert win.state == State.DISCONNECTED and places() == before


# ----------------------------------------------------------------------------- 5. readable
@pytest.mark.slow
def test_replay_shows_the_whole_session_and_trends_whole_cycles(qtbot, win, tmp_path):
    win.mock_speed.set_value(FAST_MOCK_SPEED)
    cycles(qtbot, win, n=1, heat_s=3.0, cool_s=4.0)
    end = run_until_completed(qtbot, win, lambda: click(qtbot, win.start_button))
    assert end is not None and end["status"] == "completed", end
    # the Trends tab after one cycle: a visible point at cycle 1, ticks on whole cycles
    bar = win.tabs.tabBar()
    qtbot.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(3).center())
    qtbot.waitUntil(lambda: win.trend_plots.c_stroke.getData()[0] is not None
                    and len(win.trend_plots.c_stroke.getData()[0]) == 1, timeout=10000)
    tp = win.trend_plots
    assert tp.c_stroke.opts["symbol"] is not None
    axis = tp.p_temp.getAxis("bottom")
    x0, x1 = tp.p_temp.viewRange()[0]
    assert x0 < 1 < x1
    ticks = [v for _, vs in axis.tickValues(x0, x1, axis.width() or 800) for v in vs]
    assert ticks and all(float(v).is_integer() for v in ticks), ticks
    # the Replay of a longer recorded session, opened by double-click: its whole time range
    other = simulated_session(win.sessions_dir, n=2)  # 36 s
    qtbot.mouseClick(bar, Qt.MouseButton.LeftButton, pos=bar.tabRect(1).center())
    win.refresh_sessions()
    qtbot.waitUntil(lambda: win.session_list.topLevelItemCount() == 2, timeout=10000)
    item = next(win.session_list.topLevelItem(i) for i in range(2)
                if win.session_list.topLevelItem(i).text(4) == other.name)  # fmt: skip
    rect = win.session_list.visualItemRect(item)
    qtbot.mouseClick(win.session_list.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())
    qtbot.mouseDClick(win.session_list.viewport(), Qt.MouseButton.LeftButton, pos=rect.center())
    qtbot.waitUntil(lambda: win.replay.folder == other, timeout=20000)
    QtWidgets.QApplication.processEvents()
    t0, t1 = win.replay.time_plots.p_current.viewRange()[0]
    assert t0 <= 0.5 and t1 >= 35.5, (t0, t1)
    # every legend inside its plot
    for plot in (win.replay.time_plots.p_current, win.replay.time_plots.p_temp,
                 win.replay.time_plots.p_pos):  # fmt: skip
        legend = plot.legend.sceneBoundingRect()
        assert plot.sceneBoundingRect().contains(legend), (legend, plot.sceneBoundingRect())


# ----------------------------------------------------------------------------- 6. words
def test_words_labels_ranges_and_every_invalid_field(qtbot, win):
    f = win.fields
    for key, field in f.items():
        tip = field.toolTip()
        assert not KEY_LIKE.search(tip) and not INTERVAL.search(tip), (key, tip)
    labels = [lbl.text() for lbl in win.findChildren(QtWidgets.QLabel)]
    assert not [t for t in labels if KEY_LIKE.search(t)], [t for t in labels if KEY_LIKE.search(t)]
    win.mode_buttons["pid"].setChecked(True)
    win.settings_tabs.setCurrentIndex(2)
    form = win.gain_boxes["pid"].layout()
    names = [form.labelForField(f[k]).text() for k in ("controller.gains.kp",
                                                        "controller.gains.d_filter_s")]
    assert names[1] == "derivative filter (s)" and "_" not in names[0], names
    win.mode_buttons["open_loop"].setChecked(True)
    win.settings_tabs.setCurrentIndex(0)
    cycles(qtbot, win)
    type_into(qtbot, f["load_kg"], "-5")
    type_into(qtbot, f["protocol.current_a"], "9")
    click(qtbot, win.start_button)
    text = win.message.text().lower()
    assert win.state == State.DISCONNECTED
    assert "load" in text and "current" in text, text  # both listed
    assert "more than 0, up to 10 kg" in text and "0 to 2.5 a" in text, text
    assert not INTERVAL.search(text) and not KEY_LIKE.search(text), text
    type_into(qtbot, f["load_kg"], "2")  # fixed: gone from the message at once
    assert "load" not in win.message.text().lower() and "current" in win.message.text().lower()
    type_into(qtbot, f["protocol.current_a"], "1.4")
    assert "Not started" not in win.message.text()


# ----------------------------------------------------------------------------- 7. remembered
def test_settings_are_remembered_and_defaults_restore_them(qtbot, tmp_path):
    w = open_window(tmp_path / "sessions", MOCK_SPEED)
    qtbot.waitExposed(w)
    w.protocol.setCurrentText("incomplete")
    type_into(qtbot, w.fields["protocol.cycles"], "7")
    type_into(qtbot, w.fields["protocol.current_a"], "1.1")
    type_into(qtbot, w.fields["load_kg"], "3")
    dispose(w)
    w = open_window(tmp_path / "sessions", None)
    qtbot.waitExposed(w)
    try:
        assert w.protocol.currentText() == "incomplete"
        assert (w.fields["protocol.cycles"].text(), w.fields["protocol.current_a"].text(),
                w.fields["load_kg"].text()) == ("7", "1.1", "3")  # fmt: skip
        click(qtbot, w.defaults_button)
        from smabench import settings as schema

        assert w.fields["protocol.cycles"].value() == schema.get("protocol.cycles").default
        assert w.fields["load_kg"].value() == schema.get("load_kg").default
        assert w.protocol.currentText() == schema.get("protocol.name").default
    finally:
        dispose(w)


@pytest.mark.slow
def test_connect_says_what_it_does_and_can_be_cancelled(qtbot, win):
    click(qtbot, win.connect_button)
    assert win.state == State.CONNECTING and win.connect_button.text() == "Cancel"
    qtbot.waitUntil(lambda: "mock bench" in win.message.text()
                    or win.state != State.CONNECTING, timeout=30000)  # fmt: skip
    assert win.state == State.CONNECTING, win.message.text()
    assert re.search(r"Connecting … \d+ s: .*Cancel", win.message.text())
    link = win.link
    click(qtbot, win.connect_button)  # Cancel
    assert win.state == State.DISCONNECTED and "cancelled" in win.message.text()
    qtbot.waitUntil(lambda: link.proc.poll() is not None, timeout=20000)


@pytest.mark.slow
def test_quitting_is_clean(qtbot, tmp_path):
    w = open_window(tmp_path / "sessions", MOCK_SPEED)
    click(qtbot, w.connect_button)
    qtbot.waitUntil(lambda: w.state == State.IDLE, timeout=60000)
    link = w.link
    qtbot.waitUntil(lambda: w.status.get("readout") is not None, timeout=10000)
    # the GUI going away first (as a GUI process that exits: its end of the pipe closed under
    # the runtime's status lines), then the window closing
    link.proc.stdout.close()
    dispose(w)
    assert link.proc.poll() is not None
    assert not [x for x in link.stderr_lines if "Traceback" in x or "Error" in x], \
        link.stderr_lines  # fmt: skip



# ------------------------------------------------------------------------- the record (issue 25)
@pytest.mark.slow
def test_an_estopped_sessions_record_shows_the_current_reaching_zero_and_the_chain(qtbot, win):
    """Esc mid-heating: the session keeps recording until the driver reports the current below
    20 mA, and events.jsonl holds the chain from the key press (its own time) to that frame."""
    from smabench.sessions import FLAG_AFTER_END, load_session, read_events

    heating(qtbot, win)
    qtbot.waitUntil(lambda: measured_current_a(win) > 1.2, timeout=30000)
    QTest.keyClick(win.fit_cycle, Qt.Key.Key_Escape)
    handled_t = time.monotonic()
    qtbot.waitUntil(lambda: win.last_end is not None, timeout=15000)
    folder = win.last_end["folder"]
    # the e-stop (reader thread) and the loop's end write concurrently: order by their times
    events = sorted(read_events(folder), key=lambda e: e["t_host_s"])
    # the loop's own ENABLE 0 at its end is not the chain's: under load it may come after the
    # current already fell (a busy loop thread), so it is checked apart
    ends = [e for e in events
            if e["event"] == "command_sent" and e["why"].startswith("session end")]  # fmt: skip
    assert len(ends) == 1, events
    events = [e for e in events if e is not ends[0]]
    names = [e["event"] for e in events]
    # the session's end is written by the loop, which may come before or after the chain
    chain = [n for n in names if n != "session_end"]
    assert names.count("session_end") == 1, names
    assert chain[:2] == ["estop_input", "command_sent"], names
    assert chain[-1] == "current_below_threshold", names
    # the session's end may come first or last (the loop's own timing): the chain's ends are its
    # first and last events of their kind (f33 took a last session_end for the frame below)
    first = next(e for e in events if e["event"] == "estop_input")
    below = next(e for e in reversed(events) if e["event"] == "current_below_threshold")
    sent = next(e for e in events if e["event"] == "command_sent" and e["why"] == "e-stop")
    assert first["source"] == "key Esc"
    assert first["t_host_s"] <= sent["t_host_s"] <= handled_t + 0.5
    assert sent["acked"] is True and sent["why"] == "e-stop"
    assert below["current_a"] < 0.02 and below["t_host_s"] >= sent["t_host_s"]
    assert below["t_host_s"] - first["t_host_s"] < 1.0
    data = load_session(folder)
    flags = np.asarray(data.data["flags"], dtype=int)
    current = np.asarray(data.data["current_A"], dtype=float)
    assert (flags[-1] & FLAG_AFTER_END) and abs(current[-1]) < 0.02  # the record ends at 0 A
    assert (current[(flags & FLAG_AFTER_END) == 0][-5:] > 1.0).all()  # stopped mid-heating
    meta = data.meta
    assert meta["status"] == "aborted" and meta["end_reason"] == "e-stop"
