"""``smabench bench gui``: the GUI's frame time with hours of data, and whether the GUI disturbs
the control loop.

1. Frame time: the main window is fed ``--hours`` of samples at 200 Hz (one hour simulated by the
   plant, heating cycles of 18 s under 2 kg with a measured temperature beside the estimate,
   repeated with time and cycle offsets: 24 h is 17.3 M rows, streamed in one-minute blocks into
   the window's bounded buffer) and every frame appends the next 33 ms of rows, then redraws:
   time of ``on_frame`` plus the repaint it triggers (median, p99, frames/s). Also reported: the
   buffer's memory, the process's peak RSS, and one redraw of the per-cycle trends holding every
   cycle (its ``cycles.csv`` written beforehand).
2. Loop jitter: the same recorded session (current steps, ``duration_s``) on the mock bench, once
   headless (``smabench run``) and once started from the GUI while it draws at 30 Hz; jitter is
   |period − nominal| of the recorded tick times ``t_s`` (p50, p99, max), so both are measured the
   same way.
"""

from __future__ import annotations

import os
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
    # a thermocouple's reading: the plant's temperature seen through a 0.3 s first-order lag
    alpha = (1.0 / rate_hz) / 0.3
    from scipy.signal import lfilter

    measured = lfilter([alpha], [1.0, alpha - 1.0], tr.temperature_c - tr.temperature_c[0])
    cols = {"t_s": t, "current_set_A": i, "current_A": tr.current_a,
            "position_mm": tr.position_mm, "temperature_est_C": tr.temperature_c,
            "temperature_C": measured + tr.temperature_c[0],
            "cycle": np.floor(t / period_s)}  # fmt: skip
    for k, name in enumerate(PLOT_COLUMNS):
        if name in cols:
            rows[:, k] = cols[name]
    return rows


class TiledRows:
    """Rows ``a:b`` of an endless recording: one simulated hour repeated, with ``t_s`` and
    ``cycle`` carried on (so the GUI sees time and cycles grow as in a long session)."""

    def __init__(self, hour: np.ndarray) -> None:
        self.hour = hour
        self.n = hour.shape[0]
        self.span_s = self.n / RATE_HZ
        cyc = hour[:, PLOT_COLUMNS.index("cycle")]
        self.cycles = int(np.nanmax(cyc)) + 1
        self._t, self._c = PLOT_COLUMNS.index("t_s"), PLOT_COLUMNS.index("cycle")

    def rows(self, a: int, b: int) -> np.ndarray:
        idx = np.arange(a, b)
        rep, within = np.divmod(idx, self.n)
        out = self.hour[within].copy()
        out[:, self._t] += rep * self.span_s
        out[:, self._c] += rep * self.cycles
        return out


def write_cycles_csv(folder: Path, tiles: TiledRows, total_rows: int) -> int:
    """The ``cycles.csv`` a session of ``total_rows`` rows would have (the trends view reads
    it); returns the number of cycles."""
    from smabench.sessions import CYCLE_COLUMNS, CYCLES_FILE

    h = tiles.hour
    col = {c: h[:, PLOT_COLUMNS.index(c)] for c in PLOT_COLUMNS}
    cyc = col["cycle"].astype(int)
    starts = np.r_[0, np.nonzero(np.diff(cyc))[0] + 1]
    ends = np.r_[starts[1:], h.shape[0]]

    def per(name: str, fn) -> np.ndarray:
        return np.array([fn(col[name][a:b]) for a, b in zip(starts, ends, strict=True)])

    base = {"t_start_s": col["t_s"][starts], "t_end_s": col["t_s"][ends - 1],
            "rows": ends - starts, "flagged_rows": np.zeros(starts.size),
            "current_max_A": per("current_A", np.nanmax),
            "temperature_est_min_C": per("temperature_est_C", np.nanmin),
            "temperature_est_max_C": per("temperature_est_C", np.nanmax),
            "temperature_min_C": per("temperature_C", np.nanmin),
            "temperature_max_C": per("temperature_C", np.nanmax),
            "position_start_mm": col["position_mm"][starts],
            "position_end_mm": col["position_mm"][ends - 1],
            "position_min_mm": per("position_mm", np.nanmin),
            "position_max_mm": per("position_mm", np.nanmax)}  # fmt: skip
    rep, within = divmod(total_rows - 1, tiles.n)
    n_cycles = int(rep * tiles.cycles + cyc[within])  # the finished ones
    lines = [",".join(CYCLE_COLUMNS)]
    for k in range(n_cycles):
        rep, j = divmod(k, tiles.cycles)
        vals = {c: v[j] for c, v in base.items()}
        vals["cycle"] = k
        vals["t_start_s"] += rep * tiles.span_s
        vals["t_end_s"] += rep * tiles.span_s
        vals["position_end_mm"] -= 1e-6 * k  # a slow drift, as a long campaign shows
        lines.append(",".join(f"{vals[c]:.6g}" for c in CYCLE_COLUMNS))
    (folder / CYCLES_FILE).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return n_cycles


def frame_times(n_frames: int = 300, hours: float = 1.0) -> dict:
    import resource

    from smabench.gui.app import make_app
    from smabench.gui.window import MainWindow

    app = make_app()
    tiles = TiledRows(hour_of_rows())
    per_frame = int(RATE_HZ * 0.033)
    n0 = int(hours * 3600 * RATE_HZ)
    block = int(60 * RATE_HZ)  # streamed in one-minute blocks
    with tempfile.TemporaryDirectory() as tmp:
        win = MainWindow(tmp, remember=False)
        win.timer.stop()  # frames are driven here
        win.show()
        t_load = time.perf_counter()
        for a in range(0, n0, block):
            win.buffer.append_rows(tiles.rows(a, min(a + block, n0)))
            if (a // block) % 60 == 0:  # a frame per simulated hour: cycles freeze as they go
                win.on_frame()
        load_s = time.perf_counter() - t_load
        win.on_frame()
        app.processEvents()
        times = []
        for k in range(n_frames):
            t0 = time.perf_counter()
            win.buffer.append_rows(tiles.rows(n0 + k * per_frame, n0 + (k + 1) * per_frame))
            win.on_frame()
            app.processEvents()  # delivers the repaint the frame asked for
            times.append(time.perf_counter() - t0)
        loadavg = os.getloadavg()  # the machine's load while the frames were timed
        # the per-cycle trends with every cycle of the session
        n_cycles = write_cycles_csv(Path(tmp), tiles, n0)
        win.cycle_tail.reset(tmp)
        t0 = time.perf_counter()
        win.cycle_tail.read()
        read_s = time.perf_counter() - t0
        win.tabs.setCurrentWidget(win.trend_plots)
        app.processEvents()
        t0 = time.perf_counter()
        win.on_frame()
        app.processEvents()
        trends_s = time.perf_counter() - t0
        stored, total = win.buffer.n, win.buffer.total
        nbytes = win.buffer.nbytes
        win.close()
        # destroyed now, while Qt is whole (left to interpreter exit it can crash there)
        from PySide6 import QtCore

        win.deleteLater()
        QtCore.QCoreApplication.sendPostedEvents(None, QtCore.QEvent.Type.DeferredDelete)
        del win
    a = np.asarray(times) * 1e3
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"hours": total / RATE_HZ / 3600.0, "rows": total, "stored_rows": stored,
            "buffer_mb": nbytes / 1e6, "peak_rss_mb": rss_mb, "load_s": load_s,
            "frames": n_frames, "median_ms": float(np.median(a)),
            "p99_ms": float(np.percentile(a, 99)), "fps": float(1e3 / np.median(a)),
            "cycles": n_cycles, "trends_read_ms": read_s * 1e3,
            "trends_frame_ms": trends_s * 1e3, "loadavg": loadavg}  # fmt: skip


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
    win = MainWindow(out, remember=False)
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
    lines = [*format_frames(frames).splitlines(),
        f"{'control loop, 200 Hz':24s} {'ticks':>6s} {'achieved Hz':>11s} {'jitter p50 ms':>13s} "
        f"{'p99 ms':>7s} {'max ms':>7s}",
    ]
    for name, j in (("headless", headless), ("with the GUI running", gui)):
        lines.append(f"{name:24s} {j['ticks']:6d} {j['achieved_hz']:11.2f} {j['p50_ms']:13.3f} "
                     f"{j['p99_ms']:7.3f} {j['max_ms']:7.2f}")  # fmt: skip
    lines.append(f"jitter p99 with the GUI / headless: {gui['p99_ms'] / headless['p99_ms']:.2f}×")
    return "\n".join(lines)


def format_frames(frames: dict) -> str:
    load = ", ".join(f"{v:.2f}" for v in frames["loadavg"])
    return "\n".join([
        f"GUI frame with {frames['hours']:.2f} h of 200 Hz data ({frames['rows']:,} rows; "
        f"{frames['stored_rows']:,} kept: the newest 0.5–1 h whole, older as a min–max envelope, "
        f"{frames['buffer_mb']:.0f} MB; peak RSS {frames['peak_rss_mb']:.0f} MB; streamed in "
        f"{frames['load_s']:.0f} s): median {frames['median_ms']:.1f} ms, p99 "
        f"{frames['p99_ms']:.1f} ms ({frames['fps']:.0f} frames/s at the median; "
        f"{frames['frames']} frames)",
        f"per-cycle trends, {frames['cycles']} cycles: cycles.csv read "
        f"{frames['trends_read_ms']:.0f} ms, one redraw {frames['trends_frame_ms']:.0f} ms",
        f"load average (1, 5, 15 min) when the frames were timed: {load}",
    ])


def cmd_bench_gui(args) -> int:
    print(f"frame time with {args.hours:g} h of data …", flush=True)
    frames = frame_times(args.frames, args.hours)
    if args.frames_only:
        print(format_frames(frames))
        return 0
    with tempfile.TemporaryDirectory(prefix="smabench-bench-gui-") as tmp:
        print(f"control loop headless, {args.duration_s:g} s …", flush=True)
        headless = loop_headless(args.duration_s, Path(tmp))
        print(f"control loop with the GUI, {args.duration_s:g} s …", flush=True)
        gui = loop_with_gui(args.duration_s, Path(tmp))
    print(format_report(frames, headless, gui))
    return 0


def add_bench_gui(bsub, positive) -> None:
    b = bsub.add_parser("gui", help="GUI frame time with hours of data; loop jitter with the GUI")
    b.add_argument("--hours", type=positive, default=24.0,
                   help="hours of 200 Hz data fed to the window before the timed frames (24)")
    b.add_argument("--frames-only", action="store_true",
                   help="only the frame time (no control-loop runs)")
    b.add_argument("--duration-s", type=positive, default=60.0, help="each loop run, s (60)")
    b.add_argument("--frames", type=int, default=300, help="frames timed (300)")
    b.set_defaults(func=cmd_bench_gui)
