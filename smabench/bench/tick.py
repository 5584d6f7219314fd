"""One control tick of the bench: the per-tick work, once, with no I/O of its own.

:class:`ControlTick` is driven by whoever owns the clock and the devices: the live runtime
(:class:`smabench.bench.runtime.BenchRuntime`, monotonic clock, real devices) and the offline
closed loop (:mod:`smabench.bench.offline`, a simulated clock, the in-process devices of
:mod:`smabench.drivers.sim`) call the same :meth:`ControlTick.step` with what they read. Each
tick, in this order:

1. end requests: e-stop, stop, the maximum duration;
2. the sensor sample: a finite position without invalid flags is valid (sensor status-error
   bits count as invalid: such a position is never fed to the controller); no valid position
   for ``sensor_timeout_s`` ends the session, shorter bursts are flagged rows;
3. the driver telemetry: none, or older than ``link_timeout_s``, ends the session (after a
   start-up grace of ``link_timeout_s``, in which frames that do not report the output on yet
   are stale: they predate the session's ENABLE); the output reported off ends it, with the
   device's fault text (a latched fault, a host timeout, an expired lease, its e-stop). A fault
   that leaves the output on (the NTC, the thermocouple, the wire-voltage ADC) is logged and
   the session goes on: the estimate then does without the missing value;
4. the temperature estimate (:class:`~smabench.physics.thermal.TemperatureEstimator`) from the
   telemetry's current, wire voltage (so the measured resistance V/I) and ambient (the first
   frame's ambient is also the wire's starting temperature);
5. the command source: a controller (:class:`~smabench.commands.ObservingCommandSource`) first
   observes the estimate, ambient, measured resistance and position; then ``update``;
6. the interlocks on the result: commanded current, estimated temperature, position limits and
   a broken wire (the position jumped further in one tick than the wire can move: the load fell);
7. the recorded row (the session columns of :data:`smabench.sessions.COLUMNS`) and the current
   to command. The current is commanded EVERY tick, not only on change: that command is what
   renews the driver's setpoint lease (a host whose loop hangs stops renewing it).

Times: ``clock_s`` is the owner's clock since the session started (host seconds; timeouts and
the maximum duration are in this clock), ``t_s = clock_s · time_scale`` is device time (recorded,
fed to the estimator and the command source; ``time_scale`` > 1 only against a mock run faster
than real time). Temperatures °C, currents A, positions mm.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from smabench.commands import CommandSource, CommandStep, ObservingCommandSource
from smabench.drivers.base import FLAG_SENSOR_STATUS, Sample, Telemetry
from smabench.drivers.protocol import Flag
from smabench.physics.thermal import TemperatureEstimator
from smabench.physics.wire import PAPER_WIRE, Wire
from smabench.sessions import (
    COLUMNS,
    FLAG_AFTER_END,
    FLAG_INTERLOCK,
    FLAG_SENSOR_INVALID,
    FLAG_TELEMETRY_STALE,
    FLAGS_POSITION_INVALID,
    SENSOR_FLAGS_MASK,
)
from smabench.settings import check_current_limit, check_value, default

log = logging.getLogger(__name__)

FASTEST_STRAIN_RATE_PER_S = 0.5
"""Fastest length change of a loaded wire, 1/s of its length: measured on the plant, the
contraction at the driver's 2.5 A hard limit under 1–4 kg runs at 20–23 mm/s on 55 mm
(0.37–0.42 /s); cooling runs at ≈ 2 mm/s. The broken-wire check allows this much motion over
the time between two valid samples on top of ``max_jump_mm``."""

OUTPUT_OFF_UNEXPLAINED = "current driver output turned off by the device"
"""The end reason when the driver's output went off with no fault it names (the runtime renames
it a lost driver when the link then goes silent)."""

CAUSES = ("completed", "operator", "interlock", "safety", "device", "host")
"""Why a session ended: the source finished; e-stop or stop; an interlock (current,
temperature, position, broken wire, maximum duration: running again would trip it again or is
unsafe); the driver's own safety trip (:data:`SAFETY_TRIPS`: over-temperature or energy
budget, over-current, open wire, e-stop, setpoint lease: as unsafe to repeat unattended as an
interlock); a device problem (a lost sensor or driver link, the output off for another reason:
only this one may be retried); the host (a full disk, a signal to the recording process:
running again does not help)."""

SAFETY_TRIPS = Flag.OVERTEMP | Flag.OVERCURRENT | Flag.OPEN_WIRE | Flag.ESTOP | Flag.LEASE_EXPIRED
"""Driver flags that turn its output off as a safety function (cause ``safety``)."""

POSITION_INVALID_BITS = FLAGS_POSITION_INVALID | FLAG_SENSOR_STATUS
"""Sample flags that make a position invalid: link problems and the sensor's own error bits."""


@dataclass
class RuntimeConfig:
    """Loop rate and interlock limits of one session (units in names).

    ``max_jump_mm``: the broken-wire check. A free-falling load moves ½·g·t²: at a 200 Hz loop
    it passes 1 mm per tick ≈ 20 ms after the break (≈ 2 mm fallen), while the wire itself
    moves at most ≈ 0.12 mm per 5 ms tick (:data:`FASTEST_STRAIN_RATE_PER_S`, which is added for
    slow loops), so the default 1 mm never trips on the wire's own motion.
    """

    rate_hz: float = default("rate_hz")  # defaults and ranges of the operator's settings:
    current_limit_a: float = default("current_limit_a")  # smabench.settings, declared once
    temperature_limit_c: float = default("temperature_limit_c")
    position_min_mm: float = -math.inf
    position_max_mm: float = math.inf
    link_timeout_s: float = 0.25  # driver telemetry silent this long: abort (safe < 0.5 s)
    telemetry_stale_s: float = 0.05  # a frame older than this (5 periods) flags its row stale
    sensor_timeout_s: float = 1.0  # no valid position this long: abort (shorter bursts flagged)
    max_duration_s: float = math.inf
    ambient_c: float = 22.0
    wire: Wire = PAPER_WIRE
    time_scale: float = default("time_scale")  # device time / wall time (> 1: a faster mock)
    max_jump_mm: float = 1.0  # broken wire: position jump between two valid samples, mm

    def validate(self) -> None:
        # the operator's settings: ranges from the one schema (smabench.settings)
        check_value("rate_hz", self.rate_hz)
        check_current_limit(self.current_limit_a, self.wire)
        check_value("time_scale", self.time_scale)
        check_value("temperature_limit_c", self.temperature_limit_c)
        if not 0.05 <= self.sensor_timeout_s <= 5.0:
            raise ValueError(f"sensor timeout must be in 0.05 … 5 s, got {self.sensor_timeout_s}")
        if not 0.05 <= self.link_timeout_s <= 0.45:
            raise ValueError("link timeout must be in 0.05 … 0.45 s (safe state within 0.5 s)")
        if not 0.05 <= self.max_jump_mm <= 50.0:
            raise ValueError(f"broken-wire jump must be in 0.05 … 50 mm, got {self.max_jump_mm}")


@dataclass(frozen=True)
class TickResult:
    """What one tick decided.

    ``row``: the sample to record (None when the session ended before anything was measured:
    e-stop, stop, duration, a lost device, a fault); ``current_a``: the current to command now
    (None when the session ends: the owner makes both devices safe instead); ``status`` /
    ``reason``: set when the session must end (``aborted``, ``stopped`` or ``completed``);
    ``cause``: one of :data:`CAUSES`, so that callers (an unattended plan deciding whether to
    run a step again) need not parse the reason.
    """

    row: dict[str, Any] | None
    current_a: float | None
    status: str | None = None
    reason: str = ""
    cause: str = ""  # why it ended: see CAUSES

    @property
    def ended(self) -> bool:
        return self.status is not None


class ControlTick:
    """The per-tick work of one session (see the module docstring); create one per session."""

    def __init__(self, command: CommandSource, config: RuntimeConfig | None = None) -> None:
        if not isinstance(command, CommandSource):
            raise TypeError(f"{type(command).__name__} is not a command source (no update)")
        self.command = command
        self.observing = isinstance(command, ObservingCommandSource)
        self.config = config or RuntimeConfig()
        self.config.validate()
        self.estimator = TemperatureEstimator(self.config.wire, self.config.ambient_c)
        self._last_clock_s: float | None = None
        self._last_good_clock_s = 0.0
        self._last_valid: tuple[float, float] | None = None  # (t_s, position_mm)
        self._ambient_known = False
        self._reported_fault = ""
        self.ticks = 0

    def _end(self, status: str, reason: str, cause: str, row: dict | None = None) -> TickResult:
        return TickResult(row, None, status, reason, cause)

    def step(
        self,
        clock_s: float,
        sample: Sample,
        telemetry: Telemetry | None,
        telemetry_age_s: float | None,
        fault: str = "",
        *,
        flags: int = 0,
        estop: bool = False,
        stop: bool = False,
    ) -> TickResult:
        """One tick at ``clock_s`` (s since the start) with what the owner just read.

        ``fault``: the driver's fault text ('' when none); ``flags``: the owner's row flags
        (e.g. a missed deadline); ``estop`` / ``stop``: the operator's requests."""
        cfg = self.config
        period_s = 1.0 / cfg.rate_hz
        dt_clock = period_s if self._last_clock_s is None else clock_s - self._last_clock_s
        self._last_clock_s = clock_s
        t_s = clock_s * cfg.time_scale
        dt_s = dt_clock * cfg.time_scale

        if estop:
            return self._end("aborted", "e-stop", "operator")
        if stop:
            return self._end("stopped", "stopped by operator", "operator")
        if clock_s > cfg.max_duration_s:
            return self._end(
                "aborted", f"maximum duration {cfg.max_duration_s} s reached", "interlock"
            )

        flags |= int(sample.flags) & SENSOR_FLAGS_MASK
        position_mm = float(sample.position_mm)
        valid = math.isfinite(position_mm) and not int(sample.flags) & POSITION_INVALID_BITS
        if valid:
            self._last_good_clock_s = clock_s
        else:
            flags |= FLAG_SENSOR_INVALID
            position_mm = math.nan
        lost_s = clock_s - self._last_good_clock_s
        if lost_s > cfg.sensor_timeout_s:
            return self._end("aborted", f"displacement sensor lost for {lost_s:.2f} s", "device")

        starting = clock_s <= cfg.link_timeout_s  # start-up grace: the first frames may be old
        if telemetry is None or telemetry_age_s is None or telemetry_age_s > cfg.link_timeout_s:
            if not starting:
                return self._end(
                    "aborted",
                    "current driver telemetry lost"
                    if telemetry_age_s is None
                    else f"current driver telemetry lost for {telemetry_age_s:.2f} s",
                    "device",
                )
            flags |= FLAG_TELEMETRY_STALE
        elif telemetry_age_s > cfg.telemetry_stale_s:  # not lost yet, but not live either
            flags |= FLAG_TELEMETRY_STALE
        output_on = telemetry is not None and bool(telemetry.flags & Flag.ENABLED)
        if not output_on:
            if not starting:  # the device turned its output off: a fault, an event, e-stop
                tripped = telemetry is not None and bool(telemetry.flags & SAFETY_TRIPS)
                return self._end(
                    "aborted",
                    f"current driver fault: {fault}" if fault else OUTPUT_OFF_UNEXPLAINED,
                    "safety" if tripped else "device",
                )
            # a frame from before the session's ENABLE: its events (a host timeout while the
            # session was being set up) are history, not this session's fault
            flags |= FLAG_TELEMETRY_STALE
        elif fault and fault != self._reported_fault:  # output on: a sensor fault, degraded
            self._reported_fault = fault
            if "link lost" in fault:  # the output was on at its last report, 0.25 s from end
                log.warning(
                    "current driver reports %s; its last telemetry (%.2f s ago) had the output "
                    "on: the session aborts unless telemetry returns within %.2f s",
                    fault,
                    telemetry_age_s,
                    cfg.link_timeout_s,
                )
            else:
                log.warning("current driver reports %s; the output is on, the session goes on",
                            fault)  # fmt: skip
        current_a = telemetry.current_a if telemetry is not None else math.nan
        voltage_v = telemetry.voltage_v if telemetry is not None else None
        ambient_c = telemetry.ambient_c if telemetry is not None else cfg.ambient_c
        if telemetry is not None and not self._ambient_known:
            # the session starts with the wire at rest: at the room's measured temperature
            self._ambient_known = True
            if math.isfinite(ambient_c):
                self.estimator.reset(ambient_c)
        temperature_c = self.estimator.update(
            dt_s, current_a if math.isfinite(current_a) else 0.0, voltage_v, ambient_c
        )

        if self.observing:  # a controller: the estimate it plans with
            self.command.observe(
                temperature_c,
                ambient_c,
                self.estimator.measured_resistance_ohm,
                position_mm if valid else None,
            )
        step: CommandStep = self.command.update(t_s, position_mm)
        current_set_a = float(step.current_set_a)
        interlock = self._interlock(current_set_a, temperature_c, position_mm)
        if not interlock and valid:
            interlock = self._broken_wire(t_s, position_mm)
        if interlock:
            flags |= FLAG_INTERLOCK
        row = dict.fromkeys(COLUMNS)
        row.update(
            t_s=t_s,
            current_set_A=current_set_a,
            current_A=current_a,
            voltage_V=voltage_v,
            ambient_C=ambient_c,
            position_mm=position_mm,
            setpoint_mm=step.setpoint_mm,
            temperature_est_C=temperature_c,
            mode=step.mode,
            cycle=step.cycle,
            flags=flags,
            temperature_C=telemetry.thermocouple_c if telemetry is not None else None,
        )
        self.ticks += 1
        if interlock:
            return self._end("aborted", interlock, "interlock", row)
        if step.done:
            return self._end("completed", "protocol completed", "completed", row)
        return TickResult(row, current_set_a)

    def _interlock(self, current_set_a: float, temperature_c: float, position_mm: float) -> str:
        cfg = self.config
        if not 0.0 <= current_set_a <= cfg.current_limit_a:
            return (
                f"interlock: commanded current {current_set_a:.3f} A outside 0 … "
                f"{cfg.current_limit_a} A"
            )
        if temperature_c > cfg.temperature_limit_c:
            return (
                f"interlock: estimated temperature {temperature_c:.1f} °C above "
                f"{cfg.temperature_limit_c} °C"
            )
        if math.isfinite(position_mm) and not (
            cfg.position_min_mm <= position_mm <= cfg.position_max_mm
        ):
            return (
                f"interlock: position {position_mm:.3f} mm outside "
                f"{cfg.position_min_mm} … {cfg.position_max_mm} mm"
            )
        return ""

    def _broken_wire(self, t_s: float, position_mm: float) -> str:
        """'' unless the position moved further since the last valid sample than the wire can."""
        last, self._last_valid = self._last_valid, (t_s, position_mm)
        if last is None:
            return ""
        gap_s = max(t_s - last[0], 0.0)
        jump_mm = position_mm - last[1]
        allowed = self.config.max_jump_mm + (
            FASTEST_STRAIN_RATE_PER_S * self.config.wire.length_mm * gap_s
        )
        if abs(jump_mm) <= allowed:
            return ""
        return (
            f"broken wire: position jumped {jump_mm:+.3f} mm in {gap_s * 1e3:.0f} ms "
            f"(more than {allowed:.3f} mm: the load fell)"
        )

    def after_end_row(
        self, clock_s: float, sample: Sample, telemetry: Telemetry | None, mode: str, cycle: int
    ) -> dict[str, Any]:
        """A row recorded after the session ended, while its owner waits for the driver to
        show the output off (flag ``after_end``; the current commanded is 0): what the sensor
        and the driver report, the temperature estimate going on from the measured current."""
        cfg = self.config
        dt_s = (clock_s - (self._last_clock_s if self._last_clock_s is not None else clock_s))
        self._last_clock_s = clock_s
        position_mm = float(sample.position_mm)
        flags = FLAG_AFTER_END | (int(sample.flags) & SENSOR_FLAGS_MASK)
        if not (math.isfinite(position_mm) and not int(sample.flags) & POSITION_INVALID_BITS):
            flags |= FLAG_SENSOR_INVALID
            position_mm = math.nan
        current_a = telemetry.current_a if telemetry is not None else math.nan
        voltage_v = telemetry.voltage_v if telemetry is not None else None
        ambient_c = telemetry.ambient_c if telemetry is not None else cfg.ambient_c
        temperature_c = self.estimator.update(
            dt_s * cfg.time_scale, current_a if math.isfinite(current_a) else 0.0, voltage_v,
            ambient_c,
        )  # fmt: skip
        row = dict.fromkeys(COLUMNS)
        row.update(
            t_s=clock_s * cfg.time_scale, current_set_A=0.0, current_A=current_a,
            voltage_V=voltage_v, ambient_C=ambient_c, position_mm=position_mm, setpoint_mm=None,
            temperature_est_C=temperature_c, mode=mode, cycle=cycle, flags=flags,
            temperature_C=telemetry.thermocouple_c if telemetry is not None else None,
        )  # fmt: skip
        return row
