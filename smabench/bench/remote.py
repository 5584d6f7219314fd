"""The bench runtime in its own process, driven over stdin/stdout (used by the GUI).

Why a process: the control loop then never waits for the GUI (no shared interpreter lock), and a
GUI that crashes or freezes closes the pipe, which this process answers by ending the session and
making both devices safe.

Start: ``python -m smabench.bench.remote DEVICES_JSON`` with ``{"mock": [mock args…]}`` or
``{"port": DEV, "sensor": SPEC, "sensor_map": NAME}``. The devices stay open between sessions.

Out (stdout), one line each:
- ``P <json>``: the ports and device info once connected;
- ``R <csv row>``: one sample, columns as ``samples.csv`` with the self-sensing columns after
  them (``resistance_ohm``, ``position_est_mm``: empty without a self-sense calibration),
  batched every ~30 ms;
- ``S <json>``: status twice a second (link health, ``readout``: the latest current, position,
  temperature, also while idle; phase, cycle, progress, ``feedback`` (``laser`` or
  ``resistance``, the controller's position source now) while running), ``started`` (the session
  folder) when a start was accepted, or an ``error`` for a refused command;
- ``W <json>``: a warning of the running session's loop (``{"text": …}``), as it logs it: e.g.
  the control falling back on the position from the wire's resistance, and the laser back;
- ``X <json>``: after an ``estop``, what the driver's telemetry showed: when the command arrived
  (``received_t``), when the output-off frame arrived (``output_off_t``) and when the measured
  current fell below 20 mA (``current_off_t``), all ``time.monotonic()`` (one clock for every
  process on Linux), or ``confirmed: false``;
- ``E <json>``: a session ended (status, reason, samples, folder);
- ``Q <json>``: the process is closing.
In (stdin): ``start <settings json>`` (the settings of :mod:`smabench.settings` in its JSON
shape, see ``values_from_mapping``), ``estop [INPUT_T [SOURCE]]`` (the input event's own
``time.monotonic()`` and what it was, for the session's event log), ``stop``, ``pause``,
``resume``, ``mode NAME``,
``gains KP KI KD [LAW]`` (LAW: ``pid``, ``ffpid`` or ``ffpid_hold``), ``open_current A`` (the
current held when switched to open loop), ``feedback laser|resistance`` (the controller's
position source, live; resistance needs the session's self-sense calibration), ``mock COMMAND``
(the mock bench's fault injection, ``smabench mock --control-stdin``'s commands, e.g.
``sensor-drop 1.5``; refused on real devices), ``quit``. ``estop`` is obeyed on the reading
thread at once, whatever another command is doing. EOF on stdin (the GUI died) e-stops and
closes everything.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any

from smabench.bench.headless import MockProcess, open_devices
from smabench.bench.priority import normal_thread, raise_priority, realtime_process
from smabench.bench.session_run import RunSettings, run_session
from smabench.drivers.protocol import Flag
from smabench.protocols import Protocol
from smabench.sessions import format_row, session_columns
from smabench.settings import values_from_mapping

log = logging.getLogger(__name__)

BATCH_S = 0.03
STATUS_S = 0.5
STREAM_COLUMNS = session_columns(selfsense=True)
"""The cells of an ``R`` line (the self-sensing ones empty in a session without them)."""
NOTICE_LOGGERS = ("smabench.bench.tick",)
"""Loggers whose warnings go to the GUI as ``W`` lines (the session loop's)."""


class PausableCommand:
    """Wraps a protocol: while paused the current is 0 and the protocol's clock stands still."""

    def __init__(self, protocol: Protocol) -> None:
        self.protocol = protocol
        self._paused = threading.Event()
        self._paused_total_s = 0.0
        self._pause_t_s: float | None = None

    def pause(self, on: bool) -> None:
        if on:
            self._paused.set()
        else:
            self._paused.clear()

    @property
    def paused(self) -> bool:
        return self._paused.is_set()

    def update(self, t_s: float, position_mm: float):
        if self._paused.is_set():
            if self._pause_t_s is None:
                self._pause_t_s = t_s
            return dataclasses.replace(
                self.protocol.update(self._pause_t_s - self._paused_total_s, position_mm),
                current_set_a=0.0,
                phase="paused",
                done=False,
            )
        if self._pause_t_s is not None:
            self._paused_total_s += t_s - self._pause_t_s
            self._pause_t_s = None
        return self.protocol.update(t_s - self._paused_total_s, position_mm)


def settings_from_json(cfg: dict[str, Any]) -> RunSettings:
    """The ``start`` message's settings, checked against :mod:`smabench.settings` (the same
    schema as the command line's options); ValueError naming the setting, value and range."""
    settings = RunSettings.from_values(values_from_mapping(cfg))
    settings.validate()
    return settings


class _Emitter:
    """Batches sample rows to stdout from a thread of its own (the loop only enqueues)."""

    def __init__(self, out) -> None:
        self.out = out
        self.rows: queue.SimpleQueue[dict | None] = queue.SimpleQueue()
        self.notices: queue.SimpleQueue[str] = queue.SimpleQueue()  # W lines, after the rows
        self._lock = threading.Lock()
        self.gone = False  # the reader closed its end
        self._thread = threading.Thread(target=self._run, name="emit", daemon=True)
        self._thread.start()

    def line(self, kind: str, payload: Any) -> None:
        self._write(f"{kind} {json.dumps(payload)}\n")

    def _write(self, text: str) -> None:
        """Write and flush; once the reader is gone (the GUI closed its end: EPIPE) every
        later line is dropped quietly: the process is closing anyway."""
        with self._lock:
            if self.gone:
                return
            try:
                self.out.write(text)
                self.out.flush()
            except (BrokenPipeError, OSError, ValueError):
                self.gone = True

    def _run(self) -> None:
        done = False
        while not done:
            time.sleep(BATCH_S)
            batch = []
            while True:
                try:
                    row = self.rows.get_nowait()
                except queue.Empty:
                    break
                if row is None:
                    done = True
                    break
                batch.append("R " + format_row(row, STREAM_COLUMNS))
            while True:  # a notice follows the rows before it (the loop never writes here)
                try:
                    batch.append("W " + json.dumps({"text": self.notices.get_nowait()}))
                except queue.Empty:
                    break
            if batch:
                self._write("\n".join(batch) + "\n")

    def notice(self, text: str) -> None:
        """A ``W`` line with the next batch (any thread; never blocks)."""
        self.notices.put(text)

    def flush_rows(self) -> None:
        """Wait until the rows queued so far are written (before an end line)."""
        deadline = time.monotonic() + 1.0
        while not self.rows.empty() and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(BATCH_S)

    def close(self) -> None:
        self.rows.put(None)
        self._thread.join(2.0)


class BenchServer:
    """Devices opened once; sessions started and steered by line commands."""

    def __init__(self, devices_cfg: dict[str, Any], emit: _Emitter) -> None:
        self.emit = emit
        self.mock: MockProcess | None = None
        if "mock" in devices_cfg:
            self._connecting("starting the mock bench")
            self.mock = MockProcess(list(devices_cfg["mock"]))
            self.port, self.spec = self.mock.ports.driver, self.mock.ports.sensor_tcp
        else:
            self.port, self.spec = devices_cfg["port"], devices_cfg["sensor"]
        self._connecting("opening the current driver and the displacement sensor")
        # devices are opened with permissive settings; each session checks its own
        probe = RunSettings(load_kg=1.0, time_scale=float(devices_cfg.get("time_scale", 1.0)))
        self.source, self.sensor = open_devices(
            self.port, self.spec, probe, devices_cfg.get("sensor_map", "generic-rs485-laser"),
            unit_id=devices_cfg.get("unit_id"),
        )  # fmt: skip
        self.info = dataclasses.asdict(self.source.info)
        self.runtime = None
        self.command: PausableCommand | None = None
        self.protocol: Any = None  # a Protocol, or a Controller on a reference
        self.last_row: dict[str, Any] = {}
        self.settings: RunSettings | None = None
        self._session: threading.Thread | None = None
        self._t0 = time.monotonic()
        self.closed = threading.Event()
        self._estops = 0  # e-stops so far: a start in flight when one arrives is e-stopped too
        self._idle_lock = threading.Lock()  # the sensor is read while idle only under this lock
        self._starting = False

    def _connecting(self, step: str) -> None:
        """Tell the GUI what connecting is doing now (``S {"connecting": …}``)."""
        if self.emit is not None:
            self.emit.line("S", {"connecting": step})

    @property
    def running(self) -> bool:
        return self._session is not None and self._session.is_alive()

    def start_session(self, settings_cfg: dict[str, Any]) -> None:
        if self.running:
            raise ValueError("a session is running")
        estops_before = self._estops
        with self._idle_lock:  # no idle sensor read from here on
            self._starting = True
        try:
            self._start_session(settings_cfg, estops_before)
        finally:
            self._starting = False

    def _start_session(self, settings_cfg: dict[str, Any], estops_before: int) -> None:
        settings = settings_from_json(settings_cfg)
        if settings.session_id is None:  # the folder is named now, so the GUI can show it
            settings.session_id = unused_session_id(settings)
        settings.validate(device_limit_a=self.source.info.hard_limit_a)
        self.source.clear_faults()
        if settings.controller is not None:  # the controller is the command; no pause
            with normal_thread():  # seconds of CPU: not above the kernel's pty worker
                self.protocol = settings.build_controller()
            self.command = None
            command = self.protocol
        else:
            self.protocol = Protocol(settings.protocol)
            self.command = PausableCommand(self.protocol)
            command = self.command
        self.settings = settings
        self.last_row: dict[str, Any] = {}

        def on_sample(row: dict) -> None:
            self.last_row = row
            self.emit.rows.put(row)

        self.runtime = None
        ready = threading.Event()
        self._t0 = time.monotonic()

        def on_start(runtime) -> None:
            self.runtime = runtime
            if self._estops != estops_before:  # an e-stop came while this start was prepared
                runtime.estop()
            ready.set()  # this thread runs the loop next (real-time: run_session's own)

        def run() -> None:
            try:
                folder, result = run_session(
                    settings, self.source, self.sensor,
                    {"port": self.port, "sensor": self.spec, "device": self.info},
                    on_sample=on_sample, command=command, on_start=on_start,
                )  # fmt: skip
                end = {"status": result.status, "reason": result.reason,
                       "samples": result.samples, "folder": str(folder)}  # fmt: skip
            except Exception as exc:  # the session could not run: say why, keep serving
                log.exception("session failed")
                end = {"status": "error", "reason": f"{type(exc).__name__}: {exc}"}
            ready.set()
            self.emit.flush_rows()
            self.emit.line("E", end)

        self._session = threading.Thread(target=run, name="session", daemon=True)
        self._session.start()
        ready.wait(5.0)
        self.emit.line("S", {"started": str(settings.folder())})

    def estop(self, input_t: float | None = None, source: str = "") -> None:
        """Output off now: through the running session's runtime (which then ends it as
        aborted, keeps recording until the current is off and logs the chain in the session's
        ``events.jsonl``) or straight to the driver when idle; then report what the telemetry
        shows. ``input_t``: the operator's input event's own time (``time.monotonic()``, s);
        ``source``: what it was (``key Esc``, ``button``…)."""
        received_t = time.monotonic()
        self._estops += 1
        frames: dict[str, Any] = {}
        done = threading.Event()

        def watch(tel) -> None:  # the driver's owner thread: keep it short
            if tel.host_time < received_t:
                return
            if "output_off_t" not in frames and not tel.flags & Flag.ENABLED:
                frames["output_off_t"] = tel.host_time
            if "output_off_t" in frames and abs(tel.current_a) < 0.02:
                frames["current_off_t"] = tel.host_time
                done.set()

        unsubscribe = self.source.subscribe(watch)
        rt = self.runtime if self.running else None
        if rt is not None:
            rt.estop(input_t, source)
        else:
            self.source.make_safe()

        def report() -> None:
            done.wait(1.0)
            unsubscribe()
            self.emit.line("X", {"received_t": received_t, "input_t": input_t,
                                 "confirmed": "output_off_t" in frames, **frames})  # fmt: skip

        threading.Thread(target=report, name="estop-report", daemon=True).start()

    def handle(self, line: str) -> bool:
        """One command line; returns False on ``quit``."""
        words = line.split(maxsplit=1)
        if not words:
            return True
        cmd, rest = words[0], (words[1] if len(words) > 1 else "")
        rt = self.runtime if self.running else None
        try:
            if cmd == "quit":
                return False
            if cmd == "start":
                self.start_session(json.loads(rest))
            elif cmd == "estop":
                self.estop(*parse_estop(rest))
            elif cmd == "stop" and rt is not None:
                rt.stop()
            elif cmd in ("pause", "resume") and rt is not None:
                if self.command is None:
                    raise ValueError("pause is for open-loop protocols, not a position reference")
                self.command.pause(cmd == "pause")
            elif cmd == "mode" and rt is not None:
                rt.set_mode(rest.strip())
            elif cmd == "gains" and rt is not None:
                args = rest.split()
                law = args[3] if len(args) > 3 else "pid"
                if self.command is not None:
                    raise ValueError("gains are for a position reference under a controller")
                self.protocol.set_gains(*map(float, args[:3]), law=law)
            elif cmd == "feedback" and rt is not None:
                rt.set_feedback(rest.strip())
            elif cmd == "mock":
                if self.mock is None:
                    raise ValueError("mock commands are for the built-in mock bench")
                self.mock.send(rest.strip())
            elif cmd == "open_current" and rt is not None:
                if self.command is not None:
                    raise ValueError("the open-loop current is for a controller session")
                self.protocol.set_open_loop_current(float(rest))
            elif cmd not in ("stop", "pause", "resume", "mode", "gains", "open_current",
                             "feedback"):  # fmt: skip
                raise ValueError(f"unknown command {cmd!r}")
            else:
                raise ValueError(f"{cmd}: no session running")
        except Exception as exc:  # refused (or the devices failed): say why, keep serving
            self.emit.line("S", {"error": f"{cmd}: {type(exc).__name__}: {exc}", "command": cmd})
        return True

    def status(self) -> dict[str, Any]:
        st: dict[str, Any] = {
            "running": self.running,
            "driver_link_ok": bool(self.source.link_ok),
            "driver_fault": self.source.fault_text(),
            "sensor_stats": dict(self.sensor.stats),
            "readout": self.readout(),
        }
        if self.protocol is not None and self.settings is not None:
            row = self.last_row
            if self.command is not None:  # open-loop protocol
                phase = "paused" if self.command.paused else self.protocol.phase
                progress = self.protocol.progress
            else:  # controller on a reference: progress in device time
                phase = "tracking"
                progress = min(1.0, row.get("t_s", 0.0) / self.protocol.reference.duration_s)
            st.update(
                elapsed_s=time.monotonic() - self._t0,
                cycle=int(row.get("cycle") or 0),
                cycles=self.settings.protocol.cycles,
                phase=phase,
                progress=progress,
                mode=getattr(self.runtime, "mode", "open_loop"),
            )
            tick = getattr(self.runtime, "tick", None)
            if tick is not None:
                st["feedback"] = tick.feedback
        return st

    def readout(self) -> dict[str, float | None]:
        """Latest current (A), position (mm), temperature estimate (°C), measured wire
        temperature (°C, a thermocouple; None without one), ambient (°C): from the session's last
        sample while running, else from the telemetry and one sensor read."""
        tel = self.source.latest()
        out: dict[str, float | None] = {
            "current_a": tel.current_a if tel is not None else None,
            "ambient_c": tel.ambient_c if tel is not None else None,
            "position_mm": None, "temperature_c": None,
            "temperature_measured_c": getattr(tel, "thermocouple_c", None),
        }  # fmt: skip
        if self.running:
            row = self.last_row
            out.update(position_mm=row.get("position_mm"),
                       temperature_c=row.get("temperature_est_C"),
                       temperature_measured_c=row.get("temperature_C"))  # fmt: skip
        elif self._idle_lock.acquire(timeout=0.05):
            try:
                if not self._starting and not self.running:
                    pos = float(self.sensor.read_or_flag().position_mm)
                    out["position_mm"] = pos if math.isfinite(pos) else None
            finally:
                self._idle_lock.release()
        return {k: (v if v is None or math.isfinite(v) else None) for k, v in out.items()}

    def status_loop(self) -> None:
        while not self.closed.wait(STATUS_S):
            with contextlib.suppress(Exception):
                self.emit.line("S", self.status())

    def close(self) -> None:
        """E-stop a running session, devices safe, everything closed."""
        self.closed.set()
        if self.running and self.runtime is not None:
            self.runtime.estop()
            self._session.join(3.0)
        for dev in (self.source, self.sensor):
            with contextlib.suppress(Exception):
                dev.make_safe()
            with contextlib.suppress(Exception):
                dev.close()
        if self.mock is not None:
            self.mock.close()


def unused_session_id(settings: RunSettings) -> str:
    """The session folder's name from the time, protocol and load, with ``-2``, ``-3``… when a
    session of the same second has it already (a Stop and a Start within one second)."""
    base = settings.folder().name
    sid, n = base, 1
    while (Path(settings.out_dir) / sid).exists():
        n += 1
        sid = f"{base}-{n}"
    return sid


class _NoticeHandler(logging.Handler):
    """The session loop's warnings to the GUI too (``W`` lines; queued, the loop never waits)."""

    def __init__(self, emit: _Emitter) -> None:
        super().__init__(logging.WARNING)
        self.emit_to = emit

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):
            self.emit_to.notice(record.getMessage())


def parse_estop(rest: str) -> tuple[float | None, str]:
    """``estop [INPUT_T [SOURCE…]]``'s arguments: the input event's ``time.monotonic()``
    (s; absent or not a finite number: None) and its source words."""
    words = rest.split(maxsplit=1)
    try:
        input_t = float(words[0]) if words else None
    except ValueError:
        return None, rest.strip()
    if input_t is not None and not math.isfinite(input_t):
        input_t = None
    return input_t, words[1].strip() if len(words) > 1 else ""


def serve(devices_cfg: dict[str, Any], stdin=None, stdout=None) -> int:
    """Open the devices, then obey stdin until ``quit`` or EOF (EOF = the GUI went away)."""
    stdin = stdin or sys.stdin
    emit = _Emitter(stdout or sys.stdout)
    try:
        server = BenchServer(devices_cfg, emit)
    except Exception as exc:
        emit.line("E", {"status": "error", "reason": f"{type(exc).__name__}: {exc}"})
        emit.close()
        return 2
    realtime_process()  # after the mock process was started: it keeps normal scheduling
    notices = _NoticeHandler(emit)
    for name in NOTICE_LOGGERS:
        logging.getLogger(name).addHandler(notices)
    emit.line("P", {"driver": server.port, "sensor": server.spec, "device": server.info,
                    "mock_pid": server.mock.proc.pid if server.mock else None})  # fmt: skip
    threading.Thread(target=server.status_loop, name="status", daemon=True).start()
    lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()

    def read() -> None:  # an e-stop never waits behind a slow command (a start builds a model)
        for line in stdin:
            if line.split(maxsplit=1)[:1] == ["estop"]:
                server.handle(line)
            else:
                lines.put(line)
        lines.put(None)

    threading.Thread(target=read, name="stdin", daemon=True).start()
    try:
        while (line := lines.get()) is not None:
            if not server.handle(line):
                break
    finally:
        server.close()
        for name in NOTICE_LOGGERS:
            logging.getLogger(name).removeHandler(notices)
        emit.line("Q", {"reason": "closed"})
        emit.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    raise_priority()
    return serve(json.loads(argv[0]) if argv else {"mock": ["--load-kg", "2"]})


if __name__ == "__main__":
    sys.exit(main())
