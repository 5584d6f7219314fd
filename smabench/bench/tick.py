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
5. with a self-sense calibration (``RuntimeConfig.selfsense``, issue 26, optional): the
   position estimated from the wire's resistance (:class:`~smabench.selfsense.
   SelfSenseEstimator` on the row's measured current and wire voltage, every tick, so it is
   ready whenever it is needed) and the command source's measured position
   (:meth:`ControlTick.feedback_position`): the laser's, or the estimate with ``feedback
   resistance``, or the estimate while the laser's reading is invalid with ``fallback
   resistance``; a change of source is bumpless (the difference at the change decays with
   :data:`FEEDBACK_BLEND_TAU_S`); rows controlled on the estimate are flagged
   :data:`~smabench.sessions.FLAG_FEEDBACK_RESISTANCE`. While the estimate carries the control
   (feedback or fallback resistance) a lost sensor ends the session only when the estimate is
   not valid (:data:`ESTIMATE_MAX_AGE_S`) or after ``fallback_max_s``;
6. the command source: a controller (:class:`~smabench.commands.ObservingCommandSource`) first
   observes the estimate, ambient, measured resistance and position; then ``update``;
7. the interlocks on the result: commanded current, estimated temperature, position limits (on
   the laser's position, or on the estimate the control uses while the laser's is invalid) and
   a broken wire (the position jumped further in one tick than the wire can move: the load fell);
8. the recorded row (the session columns of :data:`smabench.sessions.COLUMNS`) and the current
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
from typing import TYPE_CHECKING, Any

from smabench.commands import CommandSource, CommandStep, ObservingCommandSource
from smabench.drivers.base import FLAG_SENSOR_STATUS, Sample, Telemetry
from smabench.drivers.protocol import Flag
from smabench.physics.thermal import TemperatureEstimator
from smabench.physics.wire import PAPER_WIRE, Wire
from smabench.sessions import (
    COLUMNS,
    FLAG_AFTER_END,
    FLAG_FEEDBACK_RESISTANCE,
    FLAG_INTERLOCK,
    FLAG_SENSOR_INVALID,
    FLAG_TELEMETRY_STALE,
    FLAGS_POSITION_INVALID,
    SELFSENSE_COLUMNS,
    SENSOR_FLAGS_MASK,
)
from smabench.settings import SettingError, check_current_limit, check_value, default

if TYPE_CHECKING:
    from smabench.physics.selfsense import SelfSenseCalibration

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

FALLBACK_MAX_S = 120.0
"""Longest time without a valid laser reading that the resistance estimate may carry the
control, s (host clock, as ``sensor_timeout_s``): the position limits then act on the estimate,
but the broken-wire check needs the laser, and the estimate's error grows with what the
calibration did not see (another load, a drifting wire); after this the session ends as with a
lost sensor."""
ESTIMATE_MAX_AGE_S = 0.5
"""The resistance estimate is valid while its last resistance (a row with at least the
calibration's ``min_current_a`` and a wire voltage) is at most this old, s of device time: the
probe current keeps it fresh; without a current the estimate only holds its last value."""
FEEDBACK_BLEND_TAU_S = 1.0
"""A change of the feedback's source is bumpless: the controller's position continues from the
last one, and the difference between the sources at the change decays with this time constant,
s of device time."""
FALLBACK_NOTICE_S = 0.1
"""A fallback is announced (one warning line, and another when the laser is back) once the
laser's reading has been invalid this long, s: single late readings, flagged, say nothing."""


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
    # resistance sensing (issue 26; smabench.settings): all off by default
    probe_current_a: float = default("probe_current_a")  # SET_PROBE before the ENABLE
    selfsense: SelfSenseCalibration | None = None  # the estimate's calibration, loaded
    feedback: str = default("feedback")  # laser | resistance
    fallback: str | None = default("fallback")  # None | resistance
    fallback_max_s: float = FALLBACK_MAX_S  # see FALLBACK_MAX_S

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
        check_value("probe_current_a", self.probe_current_a)
        check_value("feedback", self.feedback)
        check_value("fallback", self.fallback)
        if not self.sensor_timeout_s <= self.fallback_max_s <= 3600.0:
            raise ValueError(f"fallback bound must be in {self.sensor_timeout_s:g} … 3600 s, got "
                             f"{self.fallback_max_s}")  # fmt: skip
        for key, on in (("feedback", self.feedback == "resistance"),
                        ("fallback", self.fallback == "resistance")):  # fmt: skip
            if not on:
                continue
            if self.selfsense is None:
                raise SettingError(key, "resistance", "{name} resistance needs a self-sense "
                                   "calibration (--selfsense CAL.json)")  # fmt: skip
            need_a = self.selfsense.min_current_a
            if self.probe_current_a < need_a:
                raise SettingError(
                    "probe_current_a", self.probe_current_a,
                    f"{key} resistance needs a probe current of at least {need_a:g} A (the "
                    "calibration's min_current_a), so the resistance is measured while the wire "
                    f"cools; got {self.probe_current_a:g} A ({{name}})",
                )  # fmt: skip


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
        # resistance sensing (issue 26): the estimator runs every tick when there is one
        self.selfsense = None
        if self.config.selfsense is not None:
            from smabench.physics.selfsense import SelfSenseEstimator

            self.selfsense = SelfSenseEstimator(self.config.selfsense)
        self.feedback = self.config.feedback  # live: set_feedback
        self.columns = COLUMNS + (SELFSENSE_COLUMNS if self.selfsense is not None else ())
        self._last_r_t_s = -math.inf  # device time of the last row with a resistance
        self._source = "laser"  # where the command source's position came from last tick
        self._x_fed_mm = math.nan  # the last finite position fed to the command source
        self._offset_mm = 0.0  # bumpless transfer: fed = source + offset, offset decaying
        self._fallback_announced = False

    def set_feedback(self, source: str) -> None:
        """The command source's measured position from the next tick: ``laser`` or
        ``resistance`` (bumpless; ValueError without a self-sense calibration). For a live
        switch (e.g. the GUI's); a session's ``feedback`` setting starts it."""
        check_value("feedback", source)
        if source == "resistance" and self.selfsense is None:
            raise ValueError("feedback resistance needs a self-sense calibration")
        self.feedback = source

    @property
    def estimate_carries(self) -> bool:
        """Whether the resistance estimate may carry the control without the laser now."""
        return self.selfsense is not None and (
            self.feedback == "resistance" or self.config.fallback == "resistance"
        )

    def _estimate(self, t_s: float, current_a: float, voltage_v: float | None,
                  temperature_c: float) -> tuple[float, float, bool]:  # fmt: skip
        """(resistance, Ω, of this row or NaN; position estimate, mm; whether it is valid);
        ``temperature_c``: the heat balance's wire temperature (the thermal map's)."""
        est = self.selfsense
        if est is None:
            return math.nan, math.nan, False
        v = math.nan if voltage_v is None else float(voltage_v)
        x = est.update(t_s, current_a, v, temperature_c)
        r = math.nan
        if math.isfinite(current_a) and current_a >= est.calibration.min_current_a and \
                math.isfinite(v):  # fmt: skip
            r = v / current_a
            self._last_r_t_s = t_s
        return r, x, math.isfinite(x) and t_s - self._last_r_t_s <= ESTIMATE_MAX_AGE_S

    def feedback_position(self, dt_s: float, laser_mm: float, estimate_mm: float,
                          estimate_ok: bool) -> tuple[float, bool]:  # fmt: skip
        """(the position the command source gets this tick, mm (NaN: none); whether it came
        from the resistance estimate). ``laser_mm``: the laser's position, NaN when invalid.
        Without a calibration it is the laser's, unchanged. A change of source is bumpless: the
        position continues from the last one fed, the difference decaying with
        :data:`FEEDBACK_BLEND_TAU_S`."""
        if self.selfsense is None:
            return laser_mm, False
        if self.feedback == "resistance":
            use = True
        else:
            use = (self.config.fallback == "resistance" and not math.isfinite(laser_mm)
                   and estimate_ok)  # fmt: skip
        source, x = ("resistance", estimate_mm) if use else ("laser", laser_mm)
        if source != self._source:
            self._source = source
            ok = math.isfinite(self._x_fed_mm) and math.isfinite(x)
            self._offset_mm = self._x_fed_mm - x if ok else 0.0
        elif self._offset_mm:
            self._offset_mm *= math.exp(-max(dt_s, 0.0) / FEEDBACK_BLEND_TAU_S)
        fed = x + self._offset_mm
        if math.isfinite(fed):
            self._x_fed_mm = fed
        return fed, use

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
        gap_s = clock_s - self._last_good_clock_s  # since the last valid reading before this
        if valid:
            self._last_good_clock_s = clock_s
        else:
            flags |= FLAG_SENSOR_INVALID
            position_mm = math.nan
        lost_s = clock_s - self._last_good_clock_s
        if lost_s > cfg.sensor_timeout_s and not self.estimate_carries:
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
        resistance_ohm, estimate_mm, estimate_ok = self._estimate(t_s, current_a, voltage_v,
                                                                  temperature_c)
        if lost_s > cfg.sensor_timeout_s:  # only here when the estimate may carry the control
            if not estimate_ok:
                return self._end("aborted", f"displacement sensor lost for {lost_s:.2f} s, and "
                                 "no valid position from the wire's resistance to control on",
                                 "device")  # fmt: skip
            if lost_s > cfg.fallback_max_s:
                return self._end("aborted", f"displacement sensor lost for {lost_s:.2f} s: "
                                 f"longer than the {cfg.fallback_max_s:g} s the position from "
                                 "the wire's resistance may carry the control", "device")
        fed_mm, on_estimate = self.feedback_position(dt_s, position_mm, estimate_mm, estimate_ok)
        if on_estimate:
            flags |= FLAG_FEEDBACK_RESISTANCE
        if self.selfsense is not None and self.feedback == "laser":
            self._announce_fallback(valid, on_estimate, gap_s)

        if self.observing:  # a controller: the estimate it plans with
            self.command.observe(
                temperature_c,
                ambient_c,
                self.estimator.measured_resistance_ohm,
                fed_mm if math.isfinite(fed_mm) else None,
            )
        step: CommandStep = self.command.update(t_s, fed_mm)
        current_set_a = float(step.current_set_a)
        limited_mm = position_mm if valid or not on_estimate else fed_mm
        interlock = self._interlock(current_set_a, temperature_c, limited_mm)
        if not interlock and valid:
            interlock = self._broken_wire(t_s, position_mm)
        if interlock:
            flags |= FLAG_INTERLOCK
        row = dict.fromkeys(self.columns)
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
        if self.selfsense is not None:
            row.update(resistance_ohm=resistance_ohm, position_est_mm=estimate_mm)
        self.ticks += 1
        if interlock:
            return self._end("aborted", interlock, "interlock", row)
        if step.done:
            return self._end("completed", "protocol completed", "completed", row)
        return TickResult(row, current_set_a)

    def _announce_fallback(self, valid: bool, on_estimate: bool, gap_s: float) -> None:
        """One warning line when the control falls back on the resistance estimate (once the
        laser has been invalid for :data:`FALLBACK_NOTICE_S`) and one when the laser is back.
        ``gap_s``: host time since the laser's last valid reading before this tick, s."""
        if on_estimate and not self._fallback_announced and gap_s >= FALLBACK_NOTICE_S:
            self._fallback_announced = True
            log.warning(
                "displacement sensor: no valid reading for %.2f s; control goes on with the "
                "position from the wire's resistance (rows flagged feedback_resistance; the "
                "session ends if the laser stays away %g s)", gap_s, self.config.fallback_max_s,
            )  # fmt: skip
        elif valid and self._fallback_announced:
            self._fallback_announced = False
            scale = self.config.time_scale
            session = "" if scale == 1.0 else \
                f" ({gap_s * scale:.2f} s of the session's time at {scale:g}×)"  # fmt: skip
            log.warning("displacement sensor back after %.2f s%s: control on the laser again",
                        gap_s, session)  # fmt: skip

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
        resistance_ohm, estimate_mm, _ = self._estimate(clock_s * cfg.time_scale, current_a,
                                                        voltage_v, temperature_c)  # fmt: skip
        row = dict.fromkeys(self.columns)
        row.update(
            t_s=clock_s * cfg.time_scale, current_set_A=0.0, current_A=current_a,
            voltage_V=voltage_v, ambient_C=ambient_c, position_mm=position_mm, setpoint_mm=None,
            temperature_est_C=temperature_c, mode=mode, cycle=cycle, flags=flags,
            temperature_C=telemetry.thermocouple_c if telemetry is not None else None,
        )  # fmt: skip
        if self.selfsense is not None:
            row.update(resistance_ohm=resistance_ohm, position_est_mm=estimate_mm)
        return row
