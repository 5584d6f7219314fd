"""The bench runtime: real-time scheduling and device I/O around one :class:`ControlTick`.

Before the loop: the probe current when the session has one (``RuntimeConfig.probe_current_a``,
SET_PROBE, before the ENABLE), so the wire's resistance is measured from the first frame on.

Each tick: wait for the tick's time on the clock, read the displacement sensor, take the latest
driver telemetry, hand both to the tick (:mod:`smabench.bench.tick`: interlocks, temperature
estimate, the command source, the recorded row), record the row, command the current it returns
(every tick: the command renews the driver's setpoint lease). The period is measured, not
assumed: ``t_s`` is the sample's own clock reading and every period is kept for the jitter
figures; a tick that starts more than one period late is a missed deadline (flagged, and the
schedule restarts from now instead of catching up with a burst).

The clock is injected: ``time.monotonic`` / ``time.sleep`` on the bench, a simulated clock in
the offline closed loop (:mod:`smabench.bench.offline`), which thus runs this very loop.

Safety: e-stop and stop are obeyed at the next tick (the e-stop also turns the driver's output
off at once, from the caller's thread); whatever ends the session — a tick's end status, an
interlock, or any exception — makes both devices safe, with the reason recorded.

The record proves it: a session that did not complete keeps recording (rows flagged
``after_end``, 0 A commanded) until the driver's telemetry shows the output off and the current
below :data:`OFF_CURRENT_A`, or says within :data:`OFF_CONFIRM_S` why it could not; the session's
event log (:class:`smabench.sessions.EventLog`, ``events.jsonl``) gets the chain: the e-stop's
input event (its own timestamp, from the GUI or the signal), the command sent, the session's end,
the output-off frame and the current below the threshold, on the host's monotonic clock and the
driver's own (``t_device_ms``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from smabench.bench.tick import OUTPUT_OFF_UNEXPLAINED, ControlTick, RuntimeConfig
from smabench.commands import CommandSource
from smabench.control.controller import MODES, Controller
from smabench.drivers.base import (
    FLAG_LINK_LOST,
    FLAG_TIMEOUT,
    CurrentSourceDevice,
    DisplacementDevice,
    PendingRead,
    Sample,
)
from smabench.drivers.protocol import Flag, Telemetry
from smabench.sessions import (
    FLAG_DEADLINE_MISSED,
    FLAG_INTERLOCK,
    FLAG_SENSOR_INVALID,
    FLAG_TELEMETRY_STALE,
    DiskFullError,
    EventLog,
)

log = logging.getLogger(__name__)

OFF_CURRENT_A = 0.02
"""Below this measured current the wire is safe: the end of the record's safety chain, A."""
OFF_CONFIRM_S = 1.0
"""How long the runtime keeps recording after an end for the driver to show the output off, s."""
DRIVER_LOST_AFTER_OFF = (
    "current driver lost (its output went off with no reason, then its link went silent)"
)

__all__ = [
    "FLAG_DEADLINE_MISSED",
    "FLAG_INTERLOCK",
    "FLAG_SENSOR_INVALID",
    "FLAG_TELEMETRY_STALE",
    "BenchRuntime",
    "RunResult",
    "RuntimeConfig",
]


@dataclass
class RunResult:
    status: str  # "completed" | "aborted" | "stopped"
    reason: str
    samples: int
    periods_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    missed_deadlines: int = 0
    cause: str = ""  # smabench.bench.tick.CAUSES: completed, operator, interlock, device


FROZEN_ABOVE_AF_K = 20.0
"""A wire estimated from below its As to this far above its Af has transformed (the stress
shifts the temperatures up by ≈ 15 K at 100 MPa): its position must have changed."""


class FrozenSensor:
    """Finds a frozen displacement sensor: the very same valid reading while the wire's
    estimated temperature went through its whole transformation (from below As to
    :data:`FROZEN_ABOVE_AF_K` above Af, or back), which no loaded wire allows. A still wire
    (no current, or too little to transform) is never taken for a frozen sensor."""

    def __init__(self, as_c: float, af_c: float) -> None:
        self.low_c, self.high_c = as_c, af_c + FROZEN_ABOVE_AF_K
        self.value: float | None = None
        self.t0_s = 0.0
        self.t_min_c = self.t_max_c = float("nan")

    def update(self, t_s: float, position_mm: float | None, temperature_c: float) -> str:
        """The reason when frozen, else ``''`` (``position_mm`` None or NaN: not valid)."""
        if position_mm is None or position_mm != position_mm:
            return ""
        if position_mm != self.value:
            self.value, self.t0_s = position_mm, t_s
            self.t_min_c = self.t_max_c = temperature_c
            return ""
        self.t_min_c = min(self.t_min_c, temperature_c)
        self.t_max_c = max(self.t_max_c, temperature_c)
        if self.t_min_c <= self.low_c and self.t_max_c >= self.high_c:
            return (
                f"displacement sensor frozen: the same reading {position_mm:.4f} mm for "
                f"{t_s - self.t0_s:.1f} s while the wire went {self.t_min_c:.0f}–"
                f"{self.t_max_c:.0f} °C, through its transformation"
            )
        return ""


def _age_at(telemetry: Telemetry | None, now: float) -> float | None:
    """The telemetry's age at the tick's time ``now`` (the runtime's clock, as ``host_time``),
    s; None before any frame. Not the age when the tick reads it: a process stopped between
    the two (SIGSTOP, a starved CPU) would see its own stall as the driver's silence, before
    its reader thread took in the frames that came meanwhile. The stall is said at the next
    tick's start; a frame newer than ``now`` is age 0."""
    return None if telemetry is None else max(0.0, now - telemetry.host_time)


SENSOR_PROBE_WHILE_SILENT_S = 0.1
"""While the displacement sensor does not answer (timeouts, a lost link) and the resistance
estimate carries the control, the loop asks it this often, s (host clock), in the background
(:meth:`~smabench.drivers.base.DisplacementDevice.read_in_background`): each request waits the
Modbus timeout (50 ms: ten periods at 200 Hz), which held the loop when it asked in line."""


_SILENT_FLAGS = FLAG_TIMEOUT | FLAG_LINK_LOST


class BenchRuntime:
    """Runs one session: call :meth:`run` (blocking) or :meth:`start` (own thread).

    ``source`` / ``sensor``: connected devices (:class:`~smabench.drivers.base.CurrentSourceDevice`,
    :class:`~smabench.drivers.base.DisplacementDevice`); ``command``: a protocol or a controller;
    ``record``: takes one row dict (the session writer's ``append``); ``on_sample(row)`` after
    each recorded row; ``on_tick(k, t_s)`` before tick ``k`` (device time ``t_s``);
    ``clock`` / ``sleep``: the clock the loop is scheduled on, s; ``events``: the session's
    event log (none: nothing logged, the after-end rows are still recorded).
    """

    def __init__(
        self,
        source: CurrentSourceDevice,
        sensor: DisplacementDevice,
        command: CommandSource,
        record: Callable[[dict], None],
        config: RuntimeConfig | None = None,
        mode: str | None = None,
        on_sample: Callable[[dict], None] | None = None,
        *,
        on_tick: Callable[[int, float], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        events: EventLog | None = None,
    ) -> None:
        self.source, self.sensor, self.command = source, sensor, command
        self.record = record
        self.config = config or RuntimeConfig()
        self.tick = ControlTick(command, self.config)
        wire = self.config.wire
        self.frozen = FrozenSensor(wire.as_c, wire.af_c)
        if mode is not None:
            self.set_mode(mode)
        self.on_sample = on_sample
        self.on_tick = on_tick
        self.clock, self.sleep = clock, sleep
        self.events = events
        self._estop = threading.Event()
        self._stop = threading.Event()
        self._sensor_silent = False  # its last request timed out or found no link
        self._sensor_asked_at = -math.inf  # host clock of the last request
        self._sensor_pending: PendingRead | None = None  # a request in the background
        self._abort_reason: str | None = None
        self._abort_cause = "host"
        self._thread: threading.Thread | None = None
        self.result: RunResult | None = None

    @property
    def estimator(self):
        """The tick's wire-temperature estimator."""
        return self.tick.estimator

    # ------------------------------------------------------------------ control from outside
    @property
    def mode(self) -> str:
        """Active control law: ``open_loop``, ``pid``, ``ff`` or ``ffpid`` (a pending switch
        already counts); always ``open_loop`` for a protocol."""
        if isinstance(self.command, Controller):
            return self.command.mode
        return "open_loop"

    def set_mode(self, mode: str) -> None:
        """Switch the control law (thread-safe; from the next tick, bumpless).

        ValueError on an unknown mode, or on a closed-loop mode when the command source is not
        a controller with a reference (and the law's parts) configured."""
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        if isinstance(self.command, Controller):
            self.command.set_mode(mode)
            return
        if mode != "open_loop":
            raise ValueError(
                f"mode {mode!r} needs a controller with a position reference; this session "
                "runs an open-loop protocol"
            )

    def set_feedback(self, source: str) -> None:
        """The controller's measured position from the next tick: ``laser`` or ``resistance``
        (the estimate from the wire's resistance; bumpless; ValueError when the session has no
        self-sense calibration). See :meth:`ControlTick.set_feedback`."""
        self.tick.set_feedback(source)

    def set_gains(self, kp: float, ki: float, kd: float, law: str = "pid") -> None:
        """New gains from the next tick (thread-safe): ``pid`` in W/mm, W/(mm·s), W·s/mm;
        ``ffpid`` / ``ffpid_hold`` in mm/mm, 1/s, s."""
        if not isinstance(self.command, Controller):
            raise ValueError("this session has no PID controller")
        self.command.set_gains(kp, ki, kd, law=law)

    def estop(self, input_t_s: float | None = None, source: str = "") -> None:
        """Emergency stop: the current driver's output off now (from any thread: the driver
        client is thread-safe), the session ends as aborted and the loop then makes both
        devices safe. The sensor is passive and its client belongs to the loop thread, so it is
        not touched from here.

        ``input_t_s``: when the operator's input happened (``time.monotonic()``, s, from the
        input event itself: a key press, a click, a signal), logged as the chain's first event;
        ``source``: what it was (e.g. ``key Esc``)."""
        first = not self._estop.is_set()
        self._estop.set()
        if self.events is not None and first:
            self.events.write(
                "estop_input", t_host_s=self.clock() if input_t_s is None else input_t_s,
                source=source or "unknown", from_input_event=input_t_s is not None,
            )  # fmt: skip
        self._make_source_safe("e-stop")

    def _make_source_safe(self, why: str) -> bool:
        """ENABLE 0 to the driver (never raises), logged as ``command_sent``."""
        t_sent = self.clock()
        try:
            acked = bool(self.source.make_safe())
        except Exception:  # make_safe must never stop the e-stop
            log.exception("make_safe failed on %r", self.source)
            acked = False
        if self.events is not None:
            self.events.write(
                "command_sent", t_host_s=t_sent, command="ENABLE 0", why=why, acked=acked,
                t_ack_host_s=self.clock() if acked else None,
            )  # fmt: skip
        return acked

    def stop(self) -> None:
        """Ask the loop to finish after the current tick (devices made safe)."""
        self._stop.set()

    def abort(self, reason: str, cause: str = "host") -> None:
        """End the session as ``aborted`` with ``reason`` at the next tick (devices made safe);
        safe to call from a signal handler (it only sets a flag). The first reason stays."""
        if self._abort_reason is None:
            self._abort_cause = cause
            self._abort_reason = reason

    @property
    def aborting(self) -> bool:
        """Whether :meth:`abort` was called."""
        return self._abort_reason is not None

    def start(self) -> threading.Thread:
        self._thread = threading.Thread(target=self.run, name="bench-runtime", daemon=True)
        self._thread.start()
        return self._thread

    def join(self, timeout: float | None = None) -> RunResult | None:
        if self._thread is not None:
            self._thread.join(timeout)
        return self.result

    # ------------------------------------------------------------------ loop
    def _sensor_safe(self) -> None:
        self._sensor_settled()
        try:
            self.sensor.make_safe()
        except Exception:  # make_safe must never stop the session's end
            log.exception("make_safe failed on %r", self.sensor)

    def _record_until_off(self, t0: float, last_row: dict | None) -> tuple[int, bool]:
        """After an end that was not a completion: keep recording (``after_end`` rows) until
        the driver shows its output off and the current below :data:`OFF_CURRENT_A`, at most
        :data:`OFF_CONFIRM_S`; the events say what was seen or why it could not be. Returns
        the rows recorded and whether the driver was found lost (no telemetry)."""
        self._sensor_settled()
        period_s = 1.0 / self.config.rate_hz
        mode = (last_row or {}).get("mode") or self.mode
        cycle = (last_row or {}).get("cycle") or 0
        start = self.clock()
        off_frame = False
        n = 0
        while True:
            now = self.clock()
            tel = self.source.latest()
            row = self.tick.after_end_row(now - t0, self.sensor.read_or_flag(), tel, mode, cycle)
            self.record(row)
            n += 1
            if self.on_sample is not None:
                self.on_sample(row)
            output_off = tel is not None and not tel.flags & Flag.ENABLED
            if output_off and not off_frame:
                off_frame = True
                self._event("output_off_frame", tel.host_time, t_device_ms=tel.t_ms,
                            current_a=tel.current_a)  # fmt: skip
            if output_off and abs(tel.current_a) < OFF_CURRENT_A:
                self._event("current_below_threshold", tel.host_time, t_device_ms=tel.t_ms,
                            current_a=tel.current_a, threshold_a=OFF_CURRENT_A)  # fmt: skip
                return n, False
            age_s = self.source.telemetry_age_s()
            lost = tel is None or age_s is None or age_s > self.config.link_timeout_s
            if lost or now - start >= OFF_CONFIRM_S:  # a lost driver is said at once
                if lost:
                    why = ("no telemetry from the current driver"
                           + ("" if age_s is None else f" for {age_s:.2f} s")
                           + ": the device is lost; its own host timeout and setpoint lease "
                           "turn the output off")  # fmt: skip
                elif not output_off:
                    why = "the current driver still reports its output on"
                else:
                    why = (f"the output is off but {tel.current_a:.3f} A still flows "
                           "(a shorted sink or a wire-to-ground fault?)")  # fmt: skip
                self._event("output_off_not_confirmed", None, waited_s=now - start, reason=why)
                log.info("after the session's end: %s", why)  # the events and the end say it
                return n, lost
            self.sleep(period_s)

    def _event(self, event: str, t_host_s: float | None, **fields) -> None:
        """An event at ``t_host_s`` on the runtime's clock (``time.monotonic()`` on the bench,
        the simulated clock offline, as the telemetry's ``host_time``); None: now."""
        if self.events is not None:
            self.events.write(event, t_host_s=self.clock() if t_host_s is None else t_host_s,
                              **fields)  # fmt: skip

    def _read_sensor(self, now: float) -> Sample:
        """The sensor's reading for this tick. While it is silent (its last request timed out
        or found no link) and the resistance estimate carries the control, it is asked in the
        background every :data:`SENSOR_PROBE_WHILE_SILENT_S`, so its timeouts never hold the
        loop; the tick gets a NaN sample flagged link-lost meanwhile, and the request's own
        reading once it is back."""
        pending = self._sensor_pending
        if pending is not None:
            if not pending.done():
                return self._not_asked(now)
            self._sensor_pending = None
            return self._took(pending.result())
        if self._sensor_silent and self.tick.estimate_carries:
            if now - self._sensor_asked_at >= SENSOR_PROBE_WHILE_SILENT_S:
                self._sensor_asked_at = now
                self._sensor_pending = self.sensor.read_in_background()
            return self._not_asked(now)
        self._sensor_asked_at = now
        return self._took(self.sensor.read_or_flag())

    @staticmethod
    def _not_asked(now: float) -> Sample:
        return Sample(math.nan, now, flags=FLAG_LINK_LOST, error="silent: asked in the background")

    def _took(self, sample: Sample) -> Sample:
        self._sensor_silent = bool(int(sample.flags) & _SILENT_FLAGS) and not math.isfinite(
            sample.position_mm
        )
        return sample

    def _sensor_settled(self) -> None:
        """Wait for a background request before the sensor is used in line again (after the
        session: the after-end rows, make_safe), at most its timeout and a margin."""
        pending, self._sensor_pending = self._sensor_pending, None
        if pending is not None:
            with contextlib.suppress(Exception):
                pending.result(timeout=2.0)

    def run(self) -> RunResult:
        """Run the session until the tick ends it; devices safe afterwards whatever happens."""
        cfg = self.config
        clock, sleep = self.clock, self.sleep
        period_s = 1.0 / cfg.rate_hz
        periods: list[float] = []
        missed = n = 0
        status, reason, cause = "aborted", "interrupted", "device"
        last_row: dict | None = None
        t0 = clock()
        next_tick = t0
        last_tick: float | None = None
        setpoint_undelivered = False
        try:
            if cfg.probe_current_a > 0:  # before the ENABLE: measured from the first frame on
                self.source.set_probe_current(cfg.probe_current_a)
            self.source.enable(True)
            while True:
                now = clock()
                if now < next_tick:
                    sleep(next_tick - now)
                    now = clock()
                flags = 0
                if now - next_tick > period_s:
                    missed += 1
                    flags |= FLAG_DEADLINE_MISSED
                    next_tick = now  # do not try to catch up with a burst
                next_tick += period_s
                if last_tick is not None:
                    periods.append(now - last_tick)
                    if now - last_tick > cfg.link_timeout_s:  # the whole loop was held up
                        status, cause = "aborted", "host"
                        reason = (
                            f"the recording process stalled for {now - last_tick:.2f} s "
                            "(stopped, or starved of CPU): longer than the current driver's "
                            "setpoint lease, which turns its output off"
                        )
                        break
                last_tick = now
                if self.on_tick is not None:
                    self.on_tick(self.tick.ticks, (now - t0) * cfg.time_scale)
                if self._abort_reason is not None:
                    status, reason, cause = "aborted", self._abort_reason, self._abort_cause
                    break
                estop, stop = self._estop.is_set(), self._stop.is_set()
                sample = self._read_sensor(now)
                telemetry = self.source.latest()
                out = self.tick.step(
                    now - t0,
                    sample,
                    telemetry,
                    _age_at(telemetry, now),
                    self.source.fault_text(),
                    flags=flags,
                    estop=estop or self._estop.is_set(),
                    stop=stop,
                )
                if out.row is not None:
                    last_row = out.row
                    frozen = self.frozen.update(
                        out.row["t_s"], out.row["position_mm"], out.row["temperature_est_C"]
                    )
                    if frozen and not out.ended:  # the controller must not act on it
                        out.row["flags"] = int(out.row["flags"] or 0) | FLAG_SENSOR_INVALID
                        self.record(out.row)
                        n += 1
                        status, reason, cause = "aborted", frozen, "device"
                        break
                    self.record(out.row)
                    n += 1
                    if self.on_sample is not None:
                        self.on_sample(out.row)
                if out.ended:
                    status, reason, cause = out.status, out.reason, out.cause
                    break
                try:
                    self.source.set_current(out.current_a)
                except TimeoutError as exc:  # the link is down: the setpoint is not delivered,
                    # the driver's lease turns its output off and the tick ends the session on
                    # the telemetry's loss (one owner of that reason)
                    if not setpoint_undelivered:
                        log.warning("setpoint not delivered: %s", exc)
                    setpoint_undelivered = True
        except DiskFullError as exc:  # the folder's file system is full: rows end at a whole one
            log.info("session folder full: %s", exc)
            status, reason, cause = "aborted", exc.reason, "host"
        except Exception as exc:  # any failure ends the session safely, with the reason
            log.exception("runtime loop failed")
            status, reason, cause = "aborted", f"{type(exc).__name__}: {exc}", "device"
        finally:
            self._event("session_end", None, status=status, reason=reason, cause=cause)
            self._make_source_safe(f"session end: {reason}")
            if status == "completed" or sys.exc_info()[0] is not None:
                self._sensor_safe()  # (an interrupt propagating: no after-end rows)
        if status != "completed":  # the sensor stays open for the after-end rows
            try:
                rows, lost = self._record_until_off(t0, last_row)
                n += rows
                if lost and reason == OUTPUT_OFF_UNEXPLAINED:
                    # a driver that dies may send a last frame with its output off and no
                    # reason (its own shutdown) before it goes silent: it was lost, not tripped
                    reason = DRIVER_LOST_AFTER_OFF
                    self._event("session_end_reason", None, reason=reason)
            except DiskFullError:  # the rows end at the last whole one; the closing fits
                log.info("after-end rows stopped: the session's folder is full")
            except Exception:  # the session is over and safe: the proof is best effort
                log.exception("recording after the end failed")
            finally:
                self._sensor_safe()
        self.result = RunResult(status, reason, n, np.asarray(periods), missed, cause)
        log.info("session ended: %s (%s), %d samples", status, reason, n)
        return self.result
