"""The operator GUI offscreen (pytest-qt), on the mock bench through the real transports."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6 import QtCore  # noqa: E402

from smabench.gui.app import make_app  # noqa: E402
from smabench.gui.window import MainWindow  # noqa: E402


@pytest.fixture
def win(qtbot, tmp_path):
    make_app()
    w = MainWindow(tmp_path / "sessions", mock_speed=5.0)
    qtbot.addWidget(w)
    w.show()
    yield w
    w.close()


def _short_protocol(w: MainWindow, cycles: int = 1, heat_s: float = 4.0) -> None:
    w.protocol.setCurrentText("cycles")
    w.cycles.setValue(cycles)
    w.current_a.setValue(1.4)
    w.heat_s.setValue(heat_s)
    w.cool_s.setValue(3.0)


def _wait_end(qtbot, w: MainWindow, timeout_ms: int = 30000) -> dict:
    qtbot.waitUntil(lambda: w.last_end is not None, timeout=timeout_ms)
    return w.last_end


def test_short_protocol_fills_the_plots_and_exports(qtbot, win, tmp_path):
    _short_protocol(win)
    qtbot.mouseClick(win.start_button, QtCore.Qt.MouseButton.LeftButton)
    end = _wait_end(qtbot, win)
    assert end["status"] == "completed", end
    win.on_frame()
    assert win.buffer.n == end["samples"] > 50
    x, y = win.loop_plot.current.getData()
    assert x is not None and len(x) > 50 and np.nanmax(y) - np.nanmin(y) > 2.0
    t, pos = win.time_plots.c_pos.getData()
    assert len(t) == win.buffer.n
    assert "driver ok" in win.health.text()
    # the finished session is listed; export writes all its rows
    assert win.session_list.count() == 1
    win.session_list.setCurrentRow(0)
    out = tmp_path / "export.csv"
    assert win.export_session(win.selected_session(), out) == end["samples"]
    assert out.read_text().splitlines()[0].startswith("t_s,")
    # replay it and fit a model to the last cycle
    win.open_selected()
    assert win.buffer.n == end["samples"]
    figures = win.fit_shown()
    assert figures is not None and figures["nrmse_percent"] < 5.0
    assert "nrmse" in win.fit_text.toPlainText()


def test_estop_makes_the_devices_safe_within_0_2_s(qtbot, win):
    _short_protocol(win, cycles=5, heat_s=20.0)
    win.start_experiment()
    qtbot.waitUntil(lambda: win.buffer.n > 40, timeout=20000)
    clicked = time.monotonic()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)  # the keyboard way to the E-STOP
    end = _wait_end(qtbot, win, 5000)
    took_s = time.monotonic() - clicked
    print(f"\nE-STOP to session ended with devices safe: {took_s * 1e3:.0f} ms")
    assert end["status"] == "aborted" and end["reason"] == "e-stop"
    assert took_s < 0.2
    win.on_frame()
    assert win.buffer.column("current_set_A")[-1] >= 0  # recorded up to the stop
    assert not win.running and win.start_button.isEnabled()


def test_lost_device_shows_an_error_and_the_gui_stays_usable(qtbot, win):
    _short_protocol(win, cycles=5, heat_s=20.0)
    win.start_experiment()
    qtbot.waitUntil(lambda: win.buffer.n > 40, timeout=20000)
    os.kill(win.link.ports["mock_pid"], signal.SIGKILL)
    end = _wait_end(qtbot, win, 5000)
    assert end["status"] == "aborted" and "lost" in end["reason"]
    assert "lost" in win.last_error
    qtbot.waitUntil(lambda: "LOST" in win.health.text(), timeout=3000)
    # usable: reconnect and run a short session
    win.disconnect_devices()
    _short_protocol(win)
    win.start_experiment()
    assert _wait_end(qtbot, win)["status"] == "completed"


def test_bench_gui_frame_time_with_an_hour_of_data(qtbot):
    """Short version of `smabench bench gui` (the README figures come from the full run)."""
    from smabench.gui.bench_gui import frame_times

    f = frame_times(n_frames=20)
    assert f["hours"] > 0.99 and f["frames"] == 20
    assert 0 < f["median_ms"] <= f["p99_ms"]


def test_controller_mode_switches_live(qtbot, win):
    """A sine reference under PID, switched to FF+PID mid-run from the controller panel."""
    from smabench.sessions import load_session

    win.protocol.setCurrentText("sine")
    win.cycles.setValue(1)
    win.period_s.setValue(10.0)
    win.amplitude_mm.setValue(0.6)
    win.mode_buttons["pid"].setChecked(True)
    win.start_experiment()
    qtbot.waitUntil(lambda: win.status.get("mode") == "pid" and win.buffer.n > 100,
                    timeout=30000)  # fmt: skip
    qtbot.mouseClick(win.mode_buttons["ffpid"], QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: win.status.get("mode") == "ffpid", timeout=3000)
    win.stop_experiment()
    end = _wait_end(qtbot, win)
    assert end["status"] == "stopped", end
    s = load_session(end["folder"])
    modes = list(dict.fromkeys(s.data["mode"]))
    assert modes[:2] == ["pid", "ffpid"], modes
    assert np.isfinite(s.data["setpoint_mm"]).all()
    # bumpless: no step in the commanded current at the switch beyond the PID's own moves
    i = s.data["current_set_A"]
    k = int(np.argmax(s.data["mode"] == "ffpid"))
    jump = abs(i[k] - i[k - 1])
    usual = np.percentile(np.abs(np.diff(i[:k])), 99)
    assert jump <= max(0.15, 2 * usual), (jump, usual)
