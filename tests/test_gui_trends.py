"""Issue 15 in the GUI: the measured wire temperature beside the estimate, the live per-cycle
trends, the bounded sample buffer behind 24 h of data, the plan's load-change dialog; and two
fixes found on the way (an explicit open-loop current at the switch tick, the setpoint lease on
a fast mock).

Offscreen (pytest-qt). Nothing here depends on wall-clock speed: frame times are printed by
``smabench bench gui``, not asserted.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6 import QtCore, QtWidgets  # noqa: E402
from PySide6.QtCore import Qt  # noqa: E402

from smabench.gui.app import make_app  # noqa: E402
from smabench.gui.link import PLOT_COLUMNS, SampleBuffer  # noqa: E402
from smabench.gui.plots import MAX_FROZEN, LoopPlot, TimePlots  # noqa: E402
from smabench.gui.trends import CycleTail, TrendPlots  # noqa: E402
from smabench.sessions import CYCLE_COLUMNS, CYCLES_FILE  # noqa: E402

RATE_HZ = 200.0


def rows_for(t: np.ndarray, period_s: float = 10.0, measured: bool = True) -> np.ndarray:
    """Plot rows of cycles: estimated T a sine, measured T 3 K below it, position follows."""
    phase = 2 * np.pi * t / period_s
    est = 60.0 + 30.0 * np.sin(phase)
    cols = {"t_s": t, "current_set_A": 1.0 + 0.0 * t, "current_A": 1.0 + 0.0 * t,
            "position_mm": 3.0 - 2.0 * (np.sin(phase) > 0), "setpoint_mm": np.nan * t,
            "temperature_est_C": est, "cycle": np.floor(t / period_s),
            "temperature_C": est - 3.0 if measured else np.nan * t}  # fmt: skip
    return np.column_stack([cols[c] for c in PLOT_COLUMNS])


# --------------------------------------------------------------------------- buffer
def test_buffer_stays_bounded_keeps_the_recent_rows_whole_and_every_peak():
    buf = SampleBuffer(full_rows=2000, envelope_rows=1000, fold=8)
    t = np.arange(400_000) / RATE_HZ  # 2000 s, 200× the full-resolution part
    rows = rows_for(t)
    pos = PLOT_COLUMNS.index("position_mm")
    rows[123_457, pos] = 9.5  # a single-sample spike, long folded by the end
    rows[5_000, PLOT_COLUMNS.index("temperature_est_C")] = -7.0
    for a in range(0, t.size, 333):  # streamed in uneven blocks
        buf.append_rows(rows[a : a + 333])
    assert buf.total == t.size
    assert buf.n <= 2000 + 1000 + 333 and buf.nbytes <= 8 * len(PLOT_COLUMNS) * 4 * 3333
    ts = buf.column("t_s")
    assert np.all(np.diff(ts) >= 0) and ts[0] == 0.0 and ts[-1] == t[-1]
    # the newest rows are the rows as streamed, and index_of maps appended rows onto them
    k = buf.n - buf.full_start
    assert k >= 1000
    np.testing.assert_array_equal(buf._data[:, buf.full_start : buf.n].T, rows[-k:])
    assert buf.index_of(t.size - 1) == buf.n - 1
    assert buf.index_of(0) == buf.full_start  # folded rows clamp to full resolution
    # min-max folding keeps every extreme a time plot must show
    assert buf.column("position_mm").max() == 9.5
    assert buf.column("temperature_est_C").min() == -7.0
    buf.clear()
    assert buf.n == buf.total == 0
    buf.append_rows(rows)  # a replay: all at once, still bounded
    assert buf.total == t.size and buf.n <= 3000 and buf.column("position_mm").max() == 9.5


def test_loop_plot_freezes_cycles_across_folds_and_keeps_a_bounded_number():
    make_app()
    buf = SampleBuffer(full_rows=4000, envelope_rows=2000, fold=4)
    plot = LoopPlot()
    period = 10.0
    n_cycles = MAX_FROZEN + 40
    t = np.arange(int(n_cycles * period * RATE_HZ)) / RATE_HZ
    rows = rows_for(t, period)
    for a in range(0, t.size, 1000):  # 5 s between frames: the buffer folds in between
        buf.append_rows(rows[a : a + 1000])
        plot.update_from(buf)
    assert len(plot.frozen) == MAX_FROZEN  # the oldest dropped, memory bounded
    # each frozen cycle is a whole cycle at full resolution (thinned), not envelope rows
    x, y = plot.frozen[-1]
    assert 300 <= x.size <= 600 and np.all(np.diff(x[: x.size // 4]) > 0)
    assert plot.measured and "measured" in plot.getAxis("bottom").labelText
    assert np.nanmax(x) == pytest.approx(90.0 - 3.0, abs=0.1)  # measured, not the estimate


def test_time_plots_draw_the_measured_temperature_beside_the_estimate_only_when_present():
    make_app()
    plots = TimePlots()
    buf = SampleBuffer()
    buf.append_rows(rows_for(np.arange(4000) / RATE_HZ, measured=False))
    plots.update_from(buf)
    names = [label.text for _, label in plots.p_temp.legend.items]
    assert plots.c_tmeas is None and names == ["wire temperature (estimated)"]
    buf.append_rows(rows_for(np.arange(4000, 6000) / RATE_HZ, measured=True))
    plots.update_from(buf)
    names = [label.text for _, label in plots.p_temp.legend.items]
    assert names == ["wire temperature (estimated)", "wire temperature (measured)"]
    x, y = plots.c_tmeas.getData()
    est = plots.c_temp.getData()[1]
    ok = np.isfinite(y)
    assert ok.sum() == 2000 and np.allclose(est[ok] - y[ok], 3.0)
    plots.reset()  # the next session starts without it
    assert plots.c_tmeas is None and len(plots.p_temp.legend.items) == 1


# --------------------------------------------------------------------------- trends
def cycle_line(k: int, measured: bool = True) -> str:
    v = {c: 0.0 for c in CYCLE_COLUMNS}
    v.update(cycle=k, t_start_s=10.0 * k, t_end_s=10.0 * k + 9.995, rows=2000,
             position_start_mm=3.0 + 0.001 * k, position_end_mm=3.0 + 0.001 * (k + 1),
             position_min_mm=1.0 + 0.0005 * k, position_max_mm=3.0 + 0.001 * k,
             temperature_est_max_C=90.0, temperature_max_C=85.0 + 0.01 * k if measured else "")
    return ",".join(str(v[c]) if v[c] != "" else "" for c in CYCLE_COLUMNS)


def test_cycle_tail_reads_only_what_was_appended_and_waits_for_whole_lines(tmp_path):
    path = tmp_path / CYCLES_FILE
    tail = CycleTail(tmp_path)
    assert tail.read() == 0  # no file yet: nothing, no error
    header = ",".join(CYCLE_COLUMNS) + "\n"
    path.write_text(header + cycle_line(0) + "\n" + cycle_line(1)[:7])  # a line half-written
    assert tail.read() == 1 and tail.n == 1
    with path.open("a") as fh:
        fh.write(cycle_line(1)[7:] + "\n" + cycle_line(2) + "\n")
    assert tail.read() == 2 and tail.n == 3
    assert tail.read() == 0
    np.testing.assert_array_equal(tail.column("cycle"), [0, 1, 2])
    assert tail.column("temperature_max_C")[2] == pytest.approx(85.02)


def test_cycle_tail_memory_is_bounded_and_keeps_the_newest_cycle(tmp_path):
    lines = [",".join(CYCLE_COLUMNS)] + [cycle_line(k) for k in range(12_001)]
    (tmp_path / CYCLES_FILE).write_text("\n".join(lines) + "\n")
    tail = CycleTail(tmp_path, max_rows=5000)
    assert tail.read() == 12_001
    cyc = tail.column("cycle")
    assert tail.n <= 5000 and cyc[0] == 0 and cyc[-1] == 12_000 and np.all(np.diff(cyc) > 0)
    whole = CycleTail(tmp_path)  # the default keeps 10 000 cycles whole
    whole.read()
    assert whole.n == 12_001


def test_trend_plots_show_stroke_residual_and_the_measured_peak(tmp_path):
    make_app()
    lines = [",".join(CYCLE_COLUMNS)] + [cycle_line(k, measured=False) for k in range(50)]
    (tmp_path / CYCLES_FILE).write_text("\n".join(lines) + "\n")
    tail = CycleTail(tmp_path)
    tail.read()
    plots = TrendPlots()
    assert plots.update_from(tail) and not plots.update_from(tail)  # redraws only on news
    x, stroke = plots.c_stroke.getData()
    assert x[0] == 1 and x[-1] == 50  # cycles counted from 1 as the operator counts
    np.testing.assert_allclose(stroke, 2.0 + 0.0005 * np.arange(50))
    np.testing.assert_allclose(plots.c_residual.getData()[1], 0.001 * np.arange(1, 51))
    assert not plots.measured and np.all(plots.c_temp.getData()[1] == 90.0)
    with (tmp_path / CYCLES_FILE).open("a") as fh:
        fh.write(cycle_line(50) + "\n")
    tail.read()
    assert plots.update_from(tail) and plots.measured
    assert [label.text for _, label in plots.p_temp.legend.items] == [
        "peak wire temperature (measured)"]


def test_window_follows_the_running_sessions_cycles(qtbot, tmp_path):
    from smabench.gui.window import TREND_EVERY, MainWindow

    make_app()
    win = MainWindow(tmp_path / "sessions")
    qtbot.addWidget(win)
    win.timer.stop()
    folder = tmp_path / "s"
    folder.mkdir()
    win.session_folder = folder
    win.cycle_tail.reset(folder)
    win.tabs.setCurrentWidget(win.trend_plots)
    (folder / CYCLES_FILE).write_text(",".join(CYCLE_COLUMNS) + "\n" + cycle_line(0) + "\n")
    for _ in range(TREND_EVERY):
        win.on_frame()
    assert win.cycle_tail.n == 1 and win.trend_plots.c_stroke.getData()[0].size == 1
    with (folder / CYCLES_FILE).open("a") as fh:
        fh.write(cycle_line(1) + "\n")
    for _ in range(TREND_EVERY):
        win.on_frame()
    assert win.trend_plots.c_stroke.getData()[0].size == 2
    win.close()


@pytest.mark.slow
def test_live_session_with_a_thermocouple_plots_measured_and_trends(qtbot, tmp_path):
    from gui_support import FAST_MOCK_SPEED, open_window, run_until_completed

    from smabench.gui.state import State

    # three cycles of device time on a faster mock (the same session in a fifth of the time)
    win = open_window(tmp_path / "sessions", FAST_MOCK_SPEED)
    qtbot.addWidget(win)
    win.mock_thermocouple.setChecked(True)
    win.protocol.setCurrentText("cycles")
    for key, text in (("protocol.cycles", "3"), ("protocol.current_a", "1.4"),
                      ("protocol.heat_s", "4"), ("protocol.cool_timeout_s", "3")):  # fmt: skip
        field = win.fields[key]
        field.setFocus()
        qtbot.keyClick(field, Qt.Key.Key_A, Qt.KeyboardModifier.ControlModifier)
        qtbot.keyClicks(field, text)
    end = run_until_completed(
        qtbot, win, lambda: qtbot.mouseClick(win.start_button, Qt.MouseButton.LeftButton),
        timeout_ms=90000,
    )  # fmt: skip
    assert end is not None and end["status"] == "completed", (end, win.message.text())
    assert win.state == State.IDLE
    win.on_frame()
    assert win.time_plots.c_tmeas is not None  # the measured curve beside the estimate
    t_meas = win.time_plots.c_tmeas.getData()[1]
    t_est = win.time_plots.c_temp.getData()[1]
    assert np.isfinite(t_meas).sum() > 100 and np.nanmax(t_meas) > 40.0
    # the thermocouple follows the wire: peaks within 15 K of the estimate's
    assert abs(np.nanmax(t_meas) - np.nanmax(t_est)) < 15.0
    assert win.loop_plot.measured
    assert "wire (measured)" in win.readout.text()  # the readout names both temperatures
    # the finished cycles reached the trends (cycles.csv written live by the session)
    assert win.cycle_tail.n >= 2
    assert np.all(np.isfinite(win.cycle_tail.column("temperature_max_C")))
    win.tabs.setCurrentWidget(win.trend_plots)
    win.on_frame()
    assert win.trend_plots.measured
    stroke = win.trend_plots.c_stroke.getData()[1]
    tail = win.cycle_tail
    np.testing.assert_allclose(stroke, tail.column("position_max_mm")
                               - tail.column("position_min_mm"))  # fmt: skip
    assert stroke[0] > 1.0  # the first cycle's full stroke (3 s of cooling is short after it)
    win.close()


# --------------------------------------------------------------------------- plans
def answer_dialog(qtbot, button_text: str) -> list[str]:
    """Press ``button_text`` in the load-change dialog once it is up; returns its text."""
    seen: list[str] = []

    def press() -> None:
        box = QtWidgets.QApplication.activeModalWidget()
        if not isinstance(box, QtWidgets.QMessageBox):
            QtCore.QTimer.singleShot(20, press)
            return
        seen.append(box.text())
        button = next(b for b in box.buttons() if b.text() == button_text)
        qtbot.mouseClick(button, Qt.MouseButton.LeftButton)

    QtCore.QTimer.singleShot(20, press)
    return seen


def test_load_change_dialog_continues_or_stops(qtbot):
    from smabench.gui.plan_prompt import ask_load_dialog

    make_app()
    seen = answer_dialog(qtbot, "Continue")
    assert ask_load_dialog(2.0, 1.0, "b") is True
    assert "from 1 kg to 2 kg" in seen[0] and "Step b" in seen[0]
    seen = answer_dialog(qtbot, "Stop here")
    assert ask_load_dialog(3.0, 2.0, "c") is False
    assert "plan resume" in seen[0]


def test_plan_uses_the_dialog_when_a_display_is_there(monkeypatch):
    from smabench import plan
    from smabench.gui.plan_prompt import ask_load_dialog

    monkeypatch.setenv("QT_QPA_PLATFORM", "xcb")
    monkeypatch.setenv("DISPLAY", ":0")
    assert plan.asker("auto") is ask_load_dialog
    assert plan.asker("terminal") is plan.ask_load
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert plan.asker("auto") is plan.ask_load
    assert plan.asker("gui") is ask_load_dialog
    args = plan_args(["plan", "run", "x.toml", "--mock", "--prompt", "gui"])
    assert args.prompt == "gui"


def plan_args(argv: list[str]):
    import argparse

    from smabench import plan

    parser = argparse.ArgumentParser()
    plan.add_commands(parser.add_subparsers())
    return parser.parse_args(argv)


def test_plan_execute_stops_when_the_dialog_says_stop(qtbot, tmp_path, monkeypatch):
    """The dialog as the plan's hook: a Stop at the load change leaves the step pending."""
    from smabench import plan as planmod
    from smabench.gui.plan_prompt import ask_load_dialog

    make_app()
    ran: list[str] = []

    class Result:
        status, reason, samples = "completed", "done", 10

    def fake_step(plan, step, sid, dev):
        ran.append(sid)
        folder = tmp_path / sid
        folder.mkdir()
        return folder, Result()

    monkeypatch.setattr(planmod, "_run_step_session", fake_step)
    text = ("[plan]\nname = 'p'\nout = '%s'\nmock_speed = 5\n"
            "[[step]]\nname = 'a'\nprotocol = 'cycles'\nload_kg = 1.0\ncycles = 1\n"
            "current_a = 1.0\nheat_s = 2.0\ncool_timeout_s = 8.0\n"
            "[[step]]\nname = 'b'\nprotocol = 'cycles'\nload_kg = 2.0\ncycles = 1\n"
            "current_a = 1.0\nheat_s = 2.0\ncool_timeout_s = 8.0\n") % (tmp_path / "out")
    path = tmp_path / "plan.toml"
    path.write_text(text)
    plan = planmod.load_plan(path)
    seen = answer_dialog(qtbot, "Stop here")
    code = planmod.execute(plan, planmod.new_state(plan), planmod.Devices(mock=True),
                           ask=ask_load_dialog, sleep=lambda s: None)  # fmt: skip
    assert code == 3 and ran == ["01-a"] and "to 2 kg" in seen[0]


# --------------------------------------------------------------------------- fixes
def test_explicit_open_loop_current_wins_at_the_switch_tick():
    from smabench.control import ControllerSettings, build_controller
    from smabench.physics.wire import PAPER_WIRE
    from smabench.protocols import ProtocolSettings

    def controller():
        p = ProtocolSettings(name="sine", cycles=2, period_s=20.0, amplitude_mm=0.8)
        c = build_controller(p, ControllerSettings(mode="pid"), 2.0, PAPER_WIRE, 2.0)
        for k in range(200):
            held = c.update(k * 0.02, 3.0).current_set_a
        return c, held

    c, held = controller()
    assert abs(held - 0.35) > 0.1  # the PID's current differs from the operator's
    c.set_mode("open_loop")
    c.set_open_loop_current(0.35)  # both land on the same tick
    steps = [c.update((200 + k) * 0.02, 3.0) for k in range(3)]
    assert [s.mode for s in steps] == ["open_loop"] * 3
    assert [s.current_set_a for s in steps] == [0.35] * 3
    c, held = controller()  # a switch alone still holds the current it had
    c.set_mode("open_loop")
    assert c.update(4.0, 3.0).current_set_a == pytest.approx(held)


def test_gui_runtime_scales_the_setpoint_lease_with_the_mock_speed(monkeypatch):
    """The GUI's runtime opens the driver with the mock's speed, as `smabench run --mock`."""
    from smabench.bench import headless, remote
    from smabench.drivers import current_source
    from smabench.drivers import protocol as p

    seen: dict = {}

    class StopError(Exception):
        pass

    class FakeSource:
        def __init__(self, port, **kw):
            seen.update(kw)

        def connect(self):
            raise StopError

        def close(self):
            pass

    monkeypatch.setattr(current_source, "CurrentSource", FakeSource)
    with pytest.raises(StopError):
        remote.BenchServer({"port": "/dev/null", "sensor": "tcp:x:1", "time_scale": 8.0},
                           emit=None)  # fmt: skip
    assert seen["lease_s"] == pytest.approx(min(5.0, p.LEASE_DEFAULT_S * 8.0))
    assert seen["lease_s"] > p.LEASE_DEFAULT_S
    # and the window sends the mock's speed as the runtime's time scale
    make_app()
    from smabench.gui.window import MainWindow

    win = MainWindow("sessions", mock_speed=8.0)
    cfg = win.devices_config()
    assert cfg["time_scale"] == 8.0 and cfg["mock"][cfg["mock"].index("--speed") + 1] == "8"
    assert headless.open_devices is remote.open_devices
    win.close()


def test_replay_draws_a_recorded_measured_temperature_and_fits_on_it():
    """A recorded session with temperature_C: replay plots it beside the estimate (not in its
    place) and the loop uses it."""
    from types import SimpleNamespace

    from smabench.gui.sessions_view import ReplayView, replay_columns

    make_app()
    rows = rows_for(np.arange(6000) / RATE_HZ)
    data = {c: rows[:, k] for k, c in enumerate(PLOT_COLUMNS)}

    class Session(SimpleNamespace):
        def __len__(self) -> int:
            return 6000

    s = Session(data=data, meta={"load_kg": 2.0, "status": "completed"})
    cols = replay_columns(s)
    assert np.array_equal(cols["temperature_est_C"], data["temperature_est_C"])
    view = ReplayView()
    view.show_session("/tmp/x", s, None)
    assert view.loop_plot.measured
    est = view.time_plots.c_temp.getData()[1]
    meas = view.time_plots.c_tmeas.getData()[1]
    assert np.allclose(est - meas, 3.0)


def test_bench_gui_tiles_a_simulated_hour_into_a_long_session(tmp_path):
    """`bench gui --hours 24` feeds repeats of one simulated span with time and cycles carried
    on, and the trends read the matching cycles.csv."""
    from smabench.gui.bench_gui import TiledRows, write_cycles_csv

    span = rows_for(np.arange(int(100 * RATE_HZ)) / RATE_HZ)  # 100 s, 10 cycles of 10 s
    tiles = TiledRows(span)
    assert tiles.cycles == 10 and tiles.span_s == pytest.approx(100.0)
    rows = tiles.rows(15_000, 45_000)  # across two repeat boundaries
    t = rows[:, PLOT_COLUMNS.index("t_s")]
    c = rows[:, PLOT_COLUMNS.index("cycle")]
    np.testing.assert_allclose(np.diff(t), 1 / RATE_HZ)
    assert np.all(np.diff(c) >= 0) and c[0] == 7 and c[-1] == 22
    n = write_cycles_csv(tmp_path, tiles, 45_000)
    tail = CycleTail(tmp_path)
    assert tail.read() == n == 22  # cycles 0 … 21 finished, the 23rd running
    np.testing.assert_array_equal(tail.column("cycle"), np.arange(22))
    np.testing.assert_allclose(tail.column("t_start_s"), 10.0 * np.arange(22))
