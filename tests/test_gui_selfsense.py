"""The wire as its own sensor in the operator window (issue 26, items 4 and 5), offscreen
(pytest-qt) on the mock bench through the real transports.

The calibration is learnt offline from four heating cycles of the plant with the Flexinol
resistivity (:func:`test_selfsense_run.offline`, ≈ 3 s); the mock bench runs the same plant
(``--resistivity flexinol``, the Connection tab's "wire resistance" choice). The mock's sensor is
made to stop answering through the runtime's ``mock`` command (the mock's own control channel,
``sensor-drop S``), as a laser whose cable is pulled.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from gui_support import FAST_MOCK_SPEED, SharedBench, last_to_use, start_running  # noqa: E402
from PySide6 import QtCore, QtWidgets  # noqa: E402
from test_selfsense_run import CYCLES, PROBE_A, arrays, offline  # noqa: E402

from smabench.gui.state import State  # noqa: E402
from smabench.gui.window import MainWindow  # noqa: E402
from smabench.protocols import Protocol, ProtocolSettings  # noqa: E402
from smabench.selfsense import calibrate  # noqa: E402
from smabench.sessions import (  # noqa: E402
    FLAG_AFTER_END,
    FLAG_FEEDBACK_RESISTANCE,
    FLAG_SENSOR_INVALID,
    load_session,
)

Qt = QtCore.Qt


@pytest.fixture(scope="module")
def cal_file(tmp_path_factory) -> Path:
    result, rows = offline(Protocol(ProtocolSettings(cycles=4, **CYCLES)),
                           probe_current_a=PROBE_A)  # fmt: skip
    assert result.status == "completed", result.reason
    path = tmp_path_factory.mktemp("gui-selfsense") / "cal.json"
    path.write_text(calibrate([arrays(rows)]).to_json())
    return path


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    bench = SharedBench(tmp_path_factory.mktemp("gui-selfsense-shared") / "sessions",
                        FAST_MOCK_SPEED)  # fmt: skip
    yield bench
    bench.close()


@pytest.fixture
def win(qtbot, shared, tmp_path, request):
    """The module's window on the mock bench with the Flexinol resistivity."""
    w = shared.for_test(qtbot, tmp_path / "sessions")
    w.mock_resistivity.setCurrentText("flexinol")
    yield w
    if last_to_use(request, "win"):
        shared.close()


def type_into(qtbot, field, text: str) -> None:
    field.setFocus()
    qtbot.keyClick(field, Qt.Key.Key_A, Qt.KeyboardModifier.ControlModifier)
    if text:
        qtbot.keyClicks(field, text)
    else:
        qtbot.keyClick(field, Qt.Key.Key_Backspace)


def choose(field, value) -> None:
    """A drop-down's choice by its value, as a click on the item does."""
    field.setCurrentIndex(field.findData(value))


def cycles(qtbot, w: MainWindow, n: int, heat_s: float = 3.0) -> None:
    w.protocol.setCurrentText("cycles")
    type_into(qtbot, w.fields["protocol.cycles"], str(n))
    type_into(qtbot, w.fields["protocol.current_a"], f"{CYCLES['current_a']:g}")
    type_into(qtbot, w.fields["protocol.heat_s"], f"{heat_s:g}")


def sensing(qtbot, w: MainWindow, cal: Path | None, fallback: str | None = None) -> None:
    type_into(qtbot, w.fields["probe_current_a"], f"{PROBE_A:g}")
    type_into(qtbot, w.fields["selfsense"], str(cal) if cal else "")
    choose(w.fields["fallback"], fallback)
    choose(w.fields["feedback"], "laser")


def stop_and_load(qtbot, w: MainWindow):
    w.last_end = None
    qtbot.mouseClick(w.stop_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: w.last_end is not None, timeout=30000)
    assert w.last_end["status"] == "stopped", w.last_end
    return load_session(w.last_end["folder"])


def flags_of(s) -> np.ndarray:
    return s.data["flags"].astype(int)


def test_the_fallback_is_shown_live_and_ends_when_the_laser_is_back(qtbot, win, cal_file):
    """The laser stops answering for 1.5 s (wall) mid-run: the window says the control runs on
    the wire's resistance, then that the laser is back; the session's rows on the estimate are
    flagged (only while the laser was invalid) and the resistance plots hold data."""
    w = win
    cycles(qtbot, w, 4)
    sensing(qtbot, w, cal_file, fallback="resistance")
    start_running(qtbot, w, lambda: qtbot.mouseClick(w.start_button, Qt.MouseButton.LeftButton))
    assert w.selfsense_plots.isVisible()
    places = {n: x.mapTo(w, QtCore.QPoint(0, 0)) for n, x in
              (("tabs", w.tabs), ("message", w.message), ("start", w.start_button))}  # fmt: skip
    qtbot.waitUntil(lambda: np.isfinite(w.buffer.column("position_est_mm")).sum() > 200,
                    timeout=20000)  # fmt: skip
    assert "laser" in w.sensing_label.text() and "fallback" in w.sensing_label.text()
    w.link.send("mock sensor-drop 1.5")
    qtbot.waitUntil(lambda: "laser lost" in w.sensing_label.text().lower(), timeout=10000)
    on_estimate_text = w.sensing_label.text()
    assert "wire's resistance" in on_estimate_text, on_estimate_text
    QtWidgets.QApplication.processEvents()
    assert {n: x.mapTo(w, QtCore.QPoint(0, 0)) for n, x in
            (("tabs", w.tabs), ("message", w.message), ("start", w.start_button))} == places
    qtbot.waitUntil(lambda: "resistance" in w.message.text(), timeout=5000)  # the runtime's word
    qtbot.waitUntil(lambda: "laser back" in w.sensing_label.text().lower(), timeout=15000)
    qtbot.waitUntil(lambda: "laser is back" in w.message.text(), timeout=5000)
    assert w.state == State.RUNNING, (w.state, w.message.text())
    back_text, back_message = w.sensing_label.text(), w.message.text()
    # the plots: R against the laser's position, laser and estimate against time
    r_x, r_y = w.selfsense_plots.c_map.getData()
    assert r_x is not None and np.isfinite(r_x).sum() > 100 and np.all(np.nanmin(r_y) > 0.1)
    t, est = w.selfsense_plots.c_est.getData()
    assert t is not None and np.isfinite(est).sum() > 100
    _, on_est = w.selfsense_plots.c_on_est.getData()
    assert on_est is not None and np.isfinite(on_est).sum() >= 5  # the fallback's stretch
    s = stop_and_load(qtbot, w)
    flags = flags_of(s)
    fb = (flags & FLAG_FEEDBACK_RESISTANCE) != 0
    invalid = (flags & FLAG_SENSOR_INVALID) != 0
    assert fb.sum() >= 5 and np.all(invalid[fb]), (fb.sum(), invalid.sum())
    assert np.isfinite(s.data["position_mm"][np.flatnonzero(fb)[-1] + 1 :]).mean() > 0.9
    gap = s.data["t_s"][fb]
    est_err = s.data["position_est_mm"] - s.data["position_mm"]
    print(f"\nGUI fallback: {fb.sum()} rows on the estimate over {gap[-1] - gap[0]:.2f} s "
          f"device time; estimate − laser {np.sqrt(np.nanmean(est_err**2)):.3f} mm RMS; "
          f"shown: {on_estimate_text!r} → {back_text!r}; message {back_message!r}")  # fmt: skip


def test_the_feedback_switches_live_only_with_a_calibration(qtbot, win, cal_file):
    """Without a calibration the runtime refuses ``feedback resistance`` (one line, the window
    says it) and the window's choice is not offered mid-run; with one, the choice switches the
    running session's feedback and every row after it is flagged."""
    w = win
    cycles(qtbot, w, 3, heat_s=60.0)
    sensing(qtbot, w, cal_file.with_name("missing.json"))  # refused in one line, nothing runs
    w.last_end = None
    qtbot.mouseClick(w.start_button, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: "Not started" in w.message.text(), timeout=60000)
    assert "calibration" in w.message.text() and w.state == State.IDLE, w.message.text()
    print(f"\nmissing calibration: {w.message.text()!r}")
    sensing(qtbot, w, None)
    start_running(qtbot, w, lambda: qtbot.mouseClick(w.start_button, Qt.MouseButton.LeftButton))
    assert not w.fields["feedback"].isEnabled() and not w.selfsense_plots.isVisible()
    assert w.sensing_label.text() == ""
    w.link.send("feedback resistance")
    qtbot.waitUntil(lambda: "self-sense calibration" in w.message.text(), timeout=5000)
    s = stop_and_load(qtbot, w)
    assert not np.any(flags_of(s) & FLAG_FEEDBACK_RESISTANCE)
    assert "resistance_ohm" not in s.columns  # a session without the options is as before

    cycles(qtbot, w, 3, heat_s=60.0)
    sensing(qtbot, w, cal_file)
    start_running(qtbot, w, lambda: qtbot.mouseClick(w.start_button, Qt.MouseButton.LeftButton))
    field = w.fields["feedback"]
    assert field.isEnabled()
    qtbot.waitUntil(lambda: w.buffer.n > 100, timeout=10000)
    choose(field, "resistance")
    qtbot.waitUntil(lambda: w.status.get("feedback") == "resistance", timeout=5000)
    qtbot.waitUntil(lambda: "wire's resistance (chosen)" in w.sensing_label.text(), timeout=5000)
    qtbot.waitUntil(lambda: np.nansum(w.buffer.column("feedback_resistance")) > 50, timeout=10000)
    s = stop_and_load(qtbot, w)
    flags = flags_of(s)[(flags_of(s) & FLAG_AFTER_END) == 0]  # the session's own rows
    fb = (flags & FLAG_FEEDBACK_RESISTANCE) != 0
    k = int(np.argmax(fb))
    print(f"\nlive switch at {s.data['t_s'][k]:.2f} s device time; {fb.sum()} rows after it")
    assert k > 100 and not fb[:k].any() and fb[k:].all()


# ----------------------------------------------------------------------------- no bench
def test_streamed_rows_carry_the_selfsense_columns_and_only_such_sessions_store_them():
    from smabench.bench.remote import STREAM_COLUMNS as SENT
    from smabench.gui.link import (
        LINK_COLUMNS,
        PLOT_COLUMNS,
        SELFSENSE_PLOT_COLUMNS,
        STREAM_COLUMNS,
        SampleBuffer,
        parse_rows,
        select,
    )
    from smabench.sessions import format_row

    assert SENT == STREAM_COLUMNS
    plain = {"t_s": 1.0, "position_mm": 2.5, "flags": 0, "cycle": 1}
    sensed = {"t_s": 1.005, "position_mm": None, "flags": FLAG_FEEDBACK_RESISTANCE
              | FLAG_SENSOR_INVALID, "resistance_ohm": 0.512, "position_est_mm": 2.49}  # fmt: skip
    old = format_row(plain).split(",")  # a runtime without the self-sensing cells
    rows = parse_rows([format_row(plain, SENT), format_row(sensed, SENT), ",".join(old)])
    col = {c: rows[:, i] for i, c in enumerate(LINK_COLUMNS)}
    assert col["position_mm"][0] == 2.5 and np.isnan(col["position_mm"][1])
    assert np.isnan(col["resistance_ohm"][[0, 2]]).all() and col["resistance_ohm"][1] == 0.512
    assert col["position_est_mm"][1] == 2.49
    assert col["feedback_resistance"].tolist() == [0.0, 1.0, 0.0]
    buf = SampleBuffer(full_rows=2000, envelope_rows=1000, fold=8)
    base = buf.nbytes
    buf.clear(PLOT_COLUMNS + SELFSENSE_PLOT_COLUMNS)
    buf.append_rows(select(rows, buf.columns))
    assert buf.column("feedback_resistance").tolist() == [0.0, 1.0, 0.0]
    assert buf.nbytes == base * len(buf.columns) // len(PLOT_COLUMNS)
    buf.clear(PLOT_COLUMNS)  # a plain session after it: the eight columns' memory again
    assert buf.nbytes == base and not buf.has("position_est_mm")
    # bounded with the wider columns too: a long run folds as before
    many = np.tile(select(rows, PLOT_COLUMNS + SELFSENSE_PLOT_COLUMNS), (4000, 1))
    many[:, 0] = np.arange(many.shape[0]) * 0.005
    buf.clear(PLOT_COLUMNS + SELFSENSE_PLOT_COLUMNS)
    buf.append_rows(many)
    assert buf.total == 12000 and buf.n <= 2000 + 1000 + 333
    assert np.nanmax(buf.column("feedback_resistance")) == 1.0  # the envelope keeps the stretch


def test_the_loops_warnings_in_plain_words():
    from smabench.gui import words

    lost = ("displacement sensor: no valid reading for 0.31 s; control goes on with the position "
            "from the wire's resistance (rows flagged feedback_resistance; the session ends if "
            "the laser stays away 120 s)")  # fmt: skip
    back = "displacement sensor back after 1.52 s: control on the laser again"
    assert words.sensing_notice(lost) == ("The laser gives no valid reading: control goes on "
                                          "with the position from the wire's resistance until "
                                          "it is back.", False)  # fmt: skip
    assert words.sensing_notice(back) == ("The laser is back: control on the laser again.",
                                          True)  # fmt: skip
    # the loop's other warnings are not the sensing line's (a lost driver is the status's)
    assert words.sensing_notice("current driver reports telemetry lost; the output is on, the "
                                "session goes on") is None  # fmt: skip


def test_a_start_within_the_same_second_gets_a_folder_of_its_own(tmp_path):
    from smabench.bench.remote import unused_session_id
    from smabench.bench.session_run import RunSettings

    s = RunSettings(load_kg=2.0, out_dir=tmp_path)
    first = unused_session_id(s)
    (tmp_path / first).mkdir()
    second = unused_session_id(s)
    if second.rsplit("-", 1)[0] == first:  # (the clock's second did not move on meanwhile)
        assert second == f"{first}-2"
    assert not (tmp_path / second).exists()


def test_the_calibration_is_chosen_with_its_button_and_the_four_settings_are_shown(qtbot, win,
                                                                                   cal_file):
    w = win
    w.settings_tabs.setCurrentIndex(0)
    for key in ("probe_current_a", "selfsense", "feedback", "fallback"):
        assert w.fields[key].isVisibleTo(w), key
    assert w.fields["feedback"].setting.live  # switchable in a run, as the schema says
    qtbot.mouseClick(w.selfsense_browse, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: w._dialog.isVisible(), timeout=5000)
    w._dialog.selectFile(str(cal_file))
    w._dialog.accept()
    assert w.fields["selfsense"].text() == str(cal_file) and not w.fields["selfsense"].error()
    settings = w.settings_dict()
    assert settings["selfsense"] == str(cal_file)
    assert "feedback" not in settings and "fallback" not in settings  # the defaults: left out
