"""``smabench bench gui``: the GUI's frame time with an hour of data, and whether the GUI disturbs
the control loop.

1. Frame time: the main window holds one hour of samples at 200 Hz (720 000 rows simulated by the
   plant: heating cycles) and every frame appends the next 33 ms of rows, then redraws: time of
   ``on_frame`` plus the repaint it triggers (median, p99, frames/s).
2. Loop jitter: the same recorded session (current steps, ``duration_s``) on the mock bench, once
   headless (``smabench run``) and once started from the GUI while it draws at 30 Hz; jitter is
   |period − nominal| of the recorded tick times ``t_s`` (p50, p99, max), so both are measured the
   same way.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from smabench.gui.link import PLOT_COLUMNS
from smabench.sessions import load_session

RATE_HZ = 200.0


def hour_of_rows(rate_hz: float = RATE_HZ, duration_s: float = 3600.0) -> np.ndarray:
    """(n, len(PLOT_COLUMNS)) rows of heating cycles under 2 kg from the plant simulation."""
    from smabench.physics.plant import heating_cycles_profile, simulate_plant

    period_s = 18.0
    cycles = int(duration_s / period_s)
    t, i = heating_cycles_profile(cycles, 1.4, 3.0, period_s - 3.0, 1.0 / rate_hz, load_kg=2.0)
    tr = simulate_plant(t, i, load_kg=2.0)
    rows = np.full((t.size, len(PLOT_COLUMNS)), np.nan)
    cols = {"t_s": t, "current_set_A": i, "current_A": tr.current_a,
            "position_mm": tr.position_mm, "temperature_est_C": tr.temperature_c,
            "cycle": np.floor(t / period_s)}  # fmt: skip
    for k, name in enumerate(PLOT_COLUMNS):
        if name in cols:
            rows[:, k] = cols[name]
    return rows


def frame_times(n_frames: int = 300) -> dict:
    from smabench.gui.app import make_app
    from smabench.gui.window import MainWindow

    app = make_app()
    rows = hour_of_rows()
    per_frame = int(RATE_HZ * 0.033)
    n0 = rows.shape[0] - n_frames * per_frame
    with tempfile.TemporaryDirectory() as tmp:
        win = MainWindow(tmp)
        win.timer.stop()  # frames are driven here
        win.show()
        win.buffer.append_rows(rows[:n0])
        win.on_frame()
        app.processEvents()
        times = []
        for k in range(n_frames):
            t0 = time.perf_counter()
            win.buffer.append_rows(rows[n0 + k * per_frame : n0 + (k + 1) * per_frame])
            win.on_frame()
            app.processEvents()  # delivers the repaint the frame asked for
            times.append(time.perf_counter() - t0)
        hours = win.buffer.n / RATE_HZ / 3600.0
        win.close()
    a = np.asarray(times) * 1e3
    return {"hours": hours, "frames": n_frames, "median_ms": float(np.median(a)),
            "p99_ms": float(np.percentile(a, 99)), "fps": float(1e3 / np.median(a))}  # fmt: skip


def _jitter(folder: Path) -> dict:
    s = load_session(folder)
    t = s.data["t_s"]
    periods = np.diff(t)
    jit = np.abs(periods - 1.0 / RATE_HZ) * 1e3
    return {"ticks": int(t.size), "achieved_hz": float(1.0 / periods.mean()),
            "p50_ms": float(np.percentile(jit, 50)), "p99_ms": float(np.percentile(jit, 99)),
            "max_ms": float(jit.max())}  # fmt: skip


def _step_settings(duration_s: float) -> dict:
    return {"name": "step", "levels_a": [0.6, 0.9], "hold_s": duration_s / 2, "current_a": 0.9}


def loop_headless(duration_s: float, out: Path) -> dict:
    """The same runtime process the GUI uses, started and followed without a window."""
    from smabench.gui.link import RuntimeLink

    link = RuntimeLink({"mock": ["--load-kg", "2"]})
    try:
        end = None
        deadline = time.monotonic() + duration_s + 60.0
        started = False
        while end is None and time.monotonic() < deadline:
            link.take_rows()
            for kind, payload in link.poll():
                if kind == "P" and not started:
                    link.start({"load_kg": 2.0, "out_dir": str(out), "session_id": "headless",
                                "protocol": _step_settings(duration_s)})  # fmt: skip
                    started = True
                elif kind in ("E", "Q"):
                    end = payload
            time.sleep(0.05)
    finally:
        link.close()
    if end is None or end.get("status") != "completed":
        raise RuntimeError(f"headless session did not complete: {end}")
    return _jitter(out / "headless")


def loop_with_gui(duration_s: float, out: Path) -> dict:
    from PySide6 import QtCore

    from smabench.gui.app import make_app
    from smabench.gui.window import MainWindow

    make_app()
    win = MainWindow(out)
    win.show()
    win.connect_devices()
    if not win.wait_connected(30.0):
        raise RuntimeError(f"GUI could not connect to the mock bench: {win.last_error}")
    # through the window's own start path, so it draws the session as an operator sees it
    win._send_start({"load_kg": 2.0, "out_dir": str(out), "session_id": "gui",
                    "protocol": _step_settings(duration_s)})  # fmt: skip
    # an ordinary event loop, as in `smabench gui`: idle between the 30 Hz frames
    loop = QtCore.QEventLoop()
    win.session_ended.connect(lambda _end: loop.quit())
    QtCore.QTimer.singleShot(int((duration_s + 30.0) * 1000), loop.quit)
    loop.exec()
    end = win.last_end
    win.close()
    if end is None or end["status"] != "completed":
        raise RuntimeError(f"GUI session did not complete: {end}")
    return _jitter(out / "gui")


def format_report(frames: dict, headless: dict, gui: dict) -> str:
    lines = [
        f"GUI frame with {frames['hours']:.2f} h of 200 Hz data in the plots: median "
        f"{frames['median_ms']:.1f} ms, p99 {frames['p99_ms']:.1f} ms "
        f"({frames['fps']:.0f} frames/s at the median; {frames['frames']} frames)",
        f"{'control loop, 200 Hz':24s} {'ticks':>6s} {'achieved Hz':>11s} {'jitter p50 ms':>13s} "
        f"{'p99 ms':>7s} {'max ms':>7s}",
    ]
    for name, j in (("headless", headless), ("with the GUI running", gui)):
        lines.append(f"{name:24s} {j['ticks']:6d} {j['achieved_hz']:11.2f} {j['p50_ms']:13.3f} "
                     f"{j['p99_ms']:7.3f} {j['max_ms']:7.2f}")  # fmt: skip
    lines.append(f"jitter p99 with the GUI / headless: {gui['p99_ms'] / headless['p99_ms']:.2f}×")
    return "\n".join(lines)


def cmd_bench_gui(args) -> int:
    print("frame time …", flush=True)
    frames = frame_times(args.frames)
    with tempfile.TemporaryDirectory(prefix="smabench-bench-gui-") as tmp:
        print(f"control loop headless, {args.duration_s:g} s …", flush=True)
        headless = loop_headless(args.duration_s, Path(tmp))
        print(f"control loop with the GUI, {args.duration_s:g} s …", flush=True)
        gui = loop_with_gui(args.duration_s, Path(tmp))
    print(format_report(frames, headless, gui))
    return 0


def add_bench_gui(bsub, positive) -> None:
    b = bsub.add_parser("gui", help="GUI frame time with 1 h of data; loop jitter with the GUI")
    b.add_argument("--duration-s", type=positive, default=60.0, help="each loop run, s (60)")
    b.add_argument("--frames", type=int, default=300, help="frames timed (300)")
    b.set_defaults(func=cmd_bench_gui)
