"""The bench runtime: one fixed-rate loop that owns both device clients (no Qt here).

Each tick: read the displacement sensor, take the latest driver telemetry, estimate the wire
temperature online, ask the active command source (a protocol, or a
:class:`smabench.control.controller.Controller`, which is first given the estimate through
``observe``) for a current,
check the interlocks, command the current, record the sample. The period is measured, not
assumed: ``t_s`` is the sample's own clock reading and every period is kept for the jitter
figures.

Safety: the current limit, an estimated-temperature limit, position limits and an e-stop are
checked every tick; a driver fault, a lost driver link (no telemetry for ``link_timeout_s``), no
valid position for ``sensor_timeout_s`` (shorter bursts are flagged samples) or any exception
puts both devices in their safe state and ends the session with the reason recorded.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from smabench.physics.thermal import TemperatureEstimator
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)

FLAG_SENSOR_INVALID = 1 << 8  # sample's position invalid (sensor flags in the low byte)
FLAG_TELEMETRY_STALE = 1 << 9
FLAG_DEADLINE_MISSED = 1 << 10
FLAG_INTERLOCK = 1 << 11


class CommandSource(Protocol):
    """What the runtime asks for a current each tick (a protocol or a controller)."""

    def update(self, t_s: float, position_mm: float) -> Any: ...


@dataclass
class RuntimeConfig:
    """Loop rate and interlock limits (units in names)."""

    rate_hz: float = 200.0
    current_limit_a: float = 2.0
    temperature_limit_c: float = 160.0
    position_min_mm: float = -math.inf
    position_max_mm: float = math.inf
    link_timeout_s: float = 0.25  # driver telemetry silent this long: abort (safe < 0.5 s)
    sensor_timeout_s: float = 1.0  # no valid position this long: abort (shorter bursts flagged)
    max_duration_s: float = math.inf
    ambient_c: float = 22.0
    wire: Wire = PAPER_WIRE
    time_scale: float = 1.0  # device time / wall time: > 1 only against a mock run faster

    def validate(self) -> None:
        if not 1.0 <= self.rate_hz <= 2000.0:
            raise ValueError(f"loop rate must be in 1 … 2000 Hz, got {self.rate_hz}")
        if not 0.0 < self.current_limit_a <= self.wire.max_current_a * 1.25:
            raise ValueError(f"current limit {self.current_limit_a} A is out of range")
        if not 0.1 <= self.time_scale <= 100.0:
            raise ValueError(f"time scale must be in 0.1 … 100, got {self.time_scale}")
        if not 0.05 <= self.sensor_timeout_s <= 5.0:
            raise ValueError(f"sensor timeout must be in 0.05 … 5 s, got {self.sensor_timeout_s}")
        if not 0.05 <= self.link_timeout_s <= 0.45:
            raise ValueError("link timeout must be in 0.05 … 0.45 s (safe state within 0.5 s)")


@dataclass
class RunResult:
    status: str  # "completed" | "aborted" | "stopped"
    reason: str
    samples: int
    periods_s: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    missed_deadlines: int = 0


class BenchRuntime:
    """Runs one session: call :meth:`run` (blocking) or :meth:`start` (own thread).

    ``source`` is a ``smabench.drivers.current_source.CurrentSource``-like object (``set_current``,
    ``enable``, ``latest()``, ``telemetry_age_s()``, ``fault_text()``, ``make_safe``), ``sensor`` a
    ``DisplacementSensor``-like object (``read_or_flag``, ``make_safe``),
    ``record`` a callable taking one row dict (the session writer's ``append``).
    """

    def __init__(
        self,
        source: Any,
        sensor: Any,
        command: CommandSource,
        record: Callable[[dict], None],
        config: RuntimeConfig | None = None,
        mode: str | None = None,
        on_sample: Callable[[dict], None] | None = None,
    ) -> None:
        self.source, self.sensor, self.command = source, sensor, command
        self.record = record
        self.config = config or RuntimeConfig()
        self.config.validate()
        self._mode_lock = threading.Lock()
        self._mode = "open_loop"
        if mode is not None:
            self.set_mode(mode)
        self.on_sample = on_sample
        self.estimator = TemperatureEstimator(self.config.wire, self.config.ambient_c)
        self._estop = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.result: RunResult | None = None

    # ------------------------------------------------------------------ control from outside
    @property
    def mode(self) -> str:
        """Active control law: ``open_loop``, ``pid``, ``ff`` or ``ffpid`` (a pending switch
        already counts)."""
        if hasattr(self.command, "set_mode"):
            return self.command.mode
        with self._mode_lock:
            return self._mode

    def set_mode(self, mode: str) -> None:
        """Switch the control law (thread-safe; from the next tick, bumpless).

        ValueError on an unknown mode, or on a closed-loop mode when the command source is not
        a controller with a reference (and the law's parts) configured."""
        from smabench.control.controller import MODES

        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
        if hasattr(self.command, "set_mode"):
            self.command.set_mode(mode)
            return
        if mode != "open_loop":
            raise ValueError(
                f"mode {mode!r} needs a controller with a position reference; this session "
                "runs an open-loop protocol"
            )
        with self._mode_lock:
            self._mode = mode

    def set_gains(self, kp: float, ki: float, kd: float) -> None:
        """New PID gains (W/mm, W/(mm·s), W·s/mm) from the next tick (thread-safe)."""
        if not hasattr(self.command, "set_gains"):
            raise ValueError("this session has no PID controller")
        self.command.set_gains(kp, ki, kd)

    def estop(self) -> None:
        """Emergency stop: the current driver's output off now (from any thread: the driver
        client is thread-safe), the session ends as aborted and the loop then makes both
        devices safe. The sensor is passive and its client belongs to the loop thread, so it is
        not touched from here."""
        self._estop.set()
        try:
            self.source.make_safe()
        except Exception:  # make_safe must never stop the e-stop
            log.exception("make_safe failed on %r", self.source)

    def stop(self) -> None:
        """Ask the loop to finish after the current tick (devices made safe)."""
        self._stop.set()

    def start(self) -> threading.Thread:
        self._thread = threading.Thread(target=self.run, name="bench-runtime", daemon=True)
        self._thread.start()
        return self._thread

    def join(self, timeout: float | None = None) -> RunResult | None:
        if self._thread is not None:
            self._thread.join(timeout)
        return self.result

    # ------------------------------------------------------------------ loop
    def _safe_all(self) -> None:
        for dev in (self.source, self.sensor):
            try:
                dev.make_safe()
            except Exception:  # make_safe must never stop the other device's make_safe
                log.exception("make_safe failed on %r", dev)

    def run(self) -> RunResult:
        cfg = self.config
        period_s = 1.0 / cfg.rate_hz
        periods: list[float] = []
        missed = 0
        n = 0
        status, reason = "completed", "protocol completed"
        last_current_set = None
        t0 = time.monotonic()
        next_tick = t0
        last_tick = None
        last_good_position_t = t0
        try:
            self.source.enable(True)
            while True:
                now = time.monotonic()
                if now < next_tick:
                    time.sleep(next_tick - now)
                    now = time.monotonic()
                flags = 0
                if now - next_tick > period_s:
                    missed += 1
                    flags |= FLAG_DEADLINE_MISSED
                    next_tick = now  # do not try to catch up with a burst
                next_tick += period_s
                dt_s = period_s if last_tick is None else now - last_tick
                if last_tick is not None:
                    periods.append(dt_s)
                last_tick = now
                # the recorded clock and the physics run in device time (= wall time on a bench)
                t_s = (now - t0) * cfg.time_scale
                dt_s *= cfg.time_scale

                if self._estop.is_set():
                    status, reason = "aborted", "e-stop"
                    break
                if self._stop.is_set():
                    status, reason = "stopped", "stopped by operator"
                    break
                if now - t0 > cfg.max_duration_s:
                    status, reason = "aborted", f"maximum duration {cfg.max_duration_s} s reached"
                    break

                sample = self.sensor.read_or_flag()
                flags |= int(sample.flags) & 0xFF
                position_mm = float(sample.position_mm)
                if math.isfinite(position_mm):
                    last_good_position_t = now
                else:
                    flags |= FLAG_SENSOR_INVALID
                if now - last_good_position_t > cfg.sensor_timeout_s:
                    status = "aborted"
                    reason = f"displacement sensor lost for {now - last_good_position_t:.2f} s"
                    break

                tel = self.source.latest()
                tel_age_s = self.source.telemetry_age_s()
                if tel is None or tel_age_s is None or tel_age_s > cfg.link_timeout_s:
                    if now - t0 > cfg.link_timeout_s:
                        status = "aborted"
                        reason = (
                            "current driver telemetry lost"
                            if tel_age_s is None
                            else f"current driver telemetry lost for {tel_age_s:.2f} s"
                        )
                        break
                    flags |= FLAG_TELEMETRY_STALE
                fault = self.source.fault_text()
                if fault:
                    status, reason = "aborted", f"current driver fault: {fault}"
                    break
                current_a = tel.current_a if tel is not None else math.nan
                voltage_v = tel.voltage_v if tel is not None else None
                ambient_c = tel.ambient_c if tel is not None else cfg.ambient_c
                temperature_c = self.estimator.update(
                    dt_s, current_a if math.isfinite(current_a) else 0.0, voltage_v, ambient_c
                )

                observe = getattr(self.command, "observe", None)
                if observe is not None:  # a controller: the estimate it plans with
                    observe(
                        temperature_c,
                        ambient_c,
                        self.estimator.measured_resistance_ohm,
                        position_mm if math.isfinite(position_mm) else None,
                    )
                step = self.command.update(t_s, position_mm)
                current_set_a = float(step.current_set_a)
                interlock = self._interlock(current_set_a, temperature_c, position_mm)
                if interlock:
                    status, reason = "aborted", interlock
                    flags |= FLAG_INTERLOCK
                row = {
                    "t_s": t_s,
                    "current_set_A": current_set_a,
                    "current_A": current_a,
                    "voltage_V": voltage_v,
                    "ambient_C": ambient_c,
                    "position_mm": position_mm,
                    "setpoint_mm": getattr(step, "setpoint_mm", None),
                    "temperature_est_C": temperature_c,
                    "mode": getattr(step, "mode", None) or self.mode,
                    "cycle": step.cycle,
                    "flags": flags,
                }
                self.record(row)
                n += 1
                if self.on_sample is not None:
                    self.on_sample(row)
                if interlock:
                    break
                if getattr(step, "done", False):
                    break
                if current_set_a != last_current_set:
                    self.source.set_current(current_set_a)
                    last_current_set = current_set_a
        except Exception as exc:  # any failure ends the session safely, with the reason
            log.exception("runtime loop failed")
            status, reason = "aborted", f"{type(exc).__name__}: {exc}"
        finally:
            self._safe_all()
        self.result = RunResult(status, reason, n, np.asarray(periods), missed)
        log.info("session ended: %s (%s), %d samples", status, reason, n)
        return self.result

    def _interlock(self, current_set_a: float, temperature_c: float, position_mm: float) -> str:
        cfg = self.config
        if not 0.0 <= current_set_a <= cfg.current_limit_a:
            return f"interlock: commanded current {current_set_a:.3f} A outside 0 … " \
                   f"{cfg.current_limit_a} A"
        if temperature_c > cfg.temperature_limit_c:
            return f"interlock: estimated temperature {temperature_c:.1f} °C above " \
                   f"{cfg.temperature_limit_c} °C"
        if math.isfinite(position_mm) and not (
            cfg.position_min_mm <= position_mm <= cfg.position_max_mm
        ):
            return f"interlock: position {position_mm:.3f} mm outside " \
                   f"{cfg.position_min_mm} … {cfg.position_max_mm} mm"
        return ""
