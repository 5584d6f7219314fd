"""Run one recorded session on the bench: validate settings, open devices, loop, record.

Everything the operator enters is checked before any device is opened, so an out-of-range
setting gets a clear error and nothing is sent. The session folder is created with
``session.json`` (status ``running``) at the start, rows are appended and flushed at least every
0.5 s while running, and ``session.json`` is rewritten atomically with the end status and reason.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from smabench.bench.priority import realtime_thread
from smabench.bench.runtime import BenchRuntime, RunResult, RuntimeConfig
from smabench.bench.tick import FALLBACK_MAX_S
from smabench.calibration_store import session_block
from smabench.commands import CommandSource
from smabench.drivers.base import CurrentSourceDevice, DisplacementDevice
from smabench.physics.wire import PRESETS
from smabench.protocols import Protocol, ProtocolSettings
from smabench.sessions import (
    SCHEMA_VERSION,
    EventLog,
    SessionWriter,
    check_free_space,
    session_columns,
)
from smabench.settings import (
    SETTINGS,
    SettingError,
    StressCheck,
    check_run,
    default,
    stress_check,
    to_mapping,
)

if TYPE_CHECKING:  # imported where used: the controller's modules are heavy
    from smabench.control.factory import ControllerSettings

log = logging.getLogger(__name__)

__all__ = [
    "SCHEMA_VERSION",
    "RunSettings",
    "check_session_space",
    "planned_duration_s",
    "run_session",
    "session_meta",
]

@dataclass
class RunSettings:
    """What the operator chose for one session (units in names). Defaults, ranges, units and
    help: :mod:`smabench.settings`; position limits of ±inf mean none (``None`` there)."""

    load_kg: float
    protocol: ProtocolSettings = field(default_factory=ProtocolSettings)
    rate_hz: float = default("rate_hz")
    wire_preset: str = default("wire_preset")
    current_limit_a: float = default("current_limit_a")
    temperature_limit_c: float = default("temperature_limit_c")
    position_min_mm: float = -math.inf
    position_max_mm: float = math.inf
    max_duration_s: float = default("max_duration_s")
    out_dir: Path = Path(default("out_dir"))
    session_id: str | None = default("session_id")
    time_scale: float = default("time_scale")  # > 1 only against a mock run faster than real
    controller: ControllerSettings | None = None  # closed loop on a reference
    max_load_kg: float = default("max_load_kg")
    long_life_stress_mpa: float | None = default("long_life_stress_mpa")  # None: the wire's
    allow_high_stress: bool = default("allow_high_stress")
    # resistance sensing (issue 26), off by default: a probe current while the wire cools, the
    # position estimated from the resistance (a calibration JSON's path), and its use
    probe_current_a: float = default("probe_current_a")
    selfsense: str | None = default("selfsense")
    feedback: str = default("feedback")
    fallback: str | None = default("fallback")
    _selfsense_cal: tuple[str, Any] | None = field(default=None, init=False, repr=False,
                                                   compare=False)  # fmt: skip

    def values(self) -> dict[str, Any]:
        """Every setting as schema values (flat keys; the controller's only with one)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in _TOP_LEVEL}
        out["out_dir"] = str(self.out_dir)
        for k in ("position_min_mm", "position_max_mm"):
            if not math.isfinite(out[k]):
                out[k] = None
        out.update(self.protocol.values())
        if self.controller is not None:
            out.update(self.controller.values())
        return out

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> RunSettings:
        """From schema values (the CLI's or the runtime's JSON, see :mod:`smabench.settings`);
        missing ones take their defaults. Not validated: call :meth:`validate`."""
        v = {**{k: s.default for k, s in SETTINGS.items() if "." not in k}, **values}
        kw = {k: v[k] for k in _TOP_LEVEL if k in v}
        kw["out_dir"] = Path(kw["out_dir"])
        kw["position_min_mm"] = -math.inf if kw["position_min_mm"] is None else \
            kw["position_min_mm"]  # fmt: skip
        kw["position_max_mm"] = math.inf if kw["position_max_mm"] is None else \
            kw["position_max_mm"]  # fmt: skip
        proto = {k.split(".", 1)[1]: x for k, x in values.items() if k.startswith("protocol.")}
        controller = None
        if values.get("controller.mode") is not None:
            from smabench.control.factory import ControllerSettings

            controller = ControllerSettings.from_values(values, kw["load_kg"])
        return cls(protocol=ProtocolSettings(**proto), controller=controller, **kw)

    def validate(self, device_limit_a: float | None = None) -> StressCheck:
        """Raise ValueError (:class:`smabench.settings.SettingError`) naming the first setting
        that is out of range or refused with the others (load above the max load or, without
        ``allow_high_stress``, above the wire's long-life stress; currents above the current
        limit, the wire's or ``device_limit_a``); returns the stress check."""
        if self.load_kg is None:
            raise SettingError("load_kg", None, "load must be given")
        if self.controller is not None:
            self.controller.validate()
        stress = check_run(self.values(), device_limit_a)
        self.selfsense_calibration()  # a bad file: refused here, before any device opens
        self.runtime_config().validate()
        if self.controller is not None:
            self.build_controller()  # refuses unreachable setpoints before any device opens
        return stress

    def stress(self) -> StressCheck:
        return stress_check(self.load_kg, self.wire_preset, self.long_life_stress_mpa)

    def build_controller(self):
        """The session's controller (identifies the loop model; ValueError when refused)."""
        from smabench.control.factory import build_controller

        return build_controller(
            self.protocol,
            self.controller,
            self.load_kg,
            PRESETS[self.wire_preset],
            self.current_limit_a,
            self.temperature_limit_c,
        )

    def selfsense_calibration(self):
        """The self-sense calibration of :attr:`selfsense`, read once (None without one);
        SettingError (key ``selfsense``, one line) when the file cannot be read or is not a
        calibration."""
        if self.selfsense is None:
            return None
        if self._selfsense_cal is None or self._selfsense_cal[0] != self.selfsense:
            from smabench.physics.selfsense import SelfSenseError, load_calibration

            try:
                cal = load_calibration(self.selfsense)
            except SelfSenseError as exc:
                raise SettingError("selfsense", self.selfsense,
                                   f"self-sense calibration {exc} ({{name}})") from None
            self._selfsense_cal = (self.selfsense, cal)
        return self._selfsense_cal[1]

    def runtime_config(self) -> RuntimeConfig:
        return RuntimeConfig(
            rate_hz=self.rate_hz,
            current_limit_a=self.current_limit_a,
            temperature_limit_c=self.temperature_limit_c,
            position_min_mm=self.position_min_mm,
            position_max_mm=self.position_max_mm,
            max_duration_s=self.max_duration_s,
            wire=PRESETS[self.wire_preset],
            time_scale=self.time_scale,
            probe_current_a=self.probe_current_a,
            selfsense=self.selfsense_calibration(),
            feedback=self.feedback,
            fallback=self.fallback,
        )

    def folder(self) -> Path:
        sid = self.session_id or time.strftime(
            f"%Y%m%d-%H%M%S-{self.protocol.name}-{self.load_kg:g}kg"
        )
        return Path(self.out_dir) / sid


_TOP_LEVEL = tuple(f.name for f in dataclasses.fields(RunSettings) if f.name in SETTINGS)
"""RunSettings' own fields that are settings of :mod:`smabench.settings` (under the same key):
derived, so a new field with a setting's name is carried without another list to edit."""


def session_meta(
    settings: RunSettings,
    devices: dict[str, Any],
    controller: dict | None = None,
    calibration: dict | None = None,
) -> dict[str, Any]:
    """``session.json`` content at the start of a run (session contract, DESIGN §3);
    ``calibration``: :func:`smabench.calibration_store.session_block`."""
    wire = PRESETS[settings.wire_preset]
    proto = asdict(settings.protocol)
    proto["levels_a"] = list(proto["levels_a"])
    stress = settings.stress()
    values = settings.values()
    return {
        "schema_version": SCHEMA_VERSION,
        "kind": "bench",
        "started_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "load_kg": settings.load_kg,
        "wire": {
            "preset": settings.wire_preset,
            "length_mm": wire.length_mm,
            "diameter_mm": wire.diameter_mm,
        },
        "devices": devices,
        "protocol": proto,
        "controller": controller or {"mode": "open_loop"},
        "loop": {"rate_hz": settings.rate_hz, "time_scale": settings.time_scale},
        "limits": {
            "current_limit_a": settings.current_limit_a,
            "temperature_limit_c": settings.temperature_limit_c,
            "position_min_mm": values["position_min_mm"],  # null: no limit
            "position_max_mm": values["position_max_mm"],
            "max_load_kg": settings.max_load_kg,
            "max_duration_s": settings.max_duration_s,
            "stress_MPa": round(stress.stress_mpa, 1),
            "long_life_stress_MPa": stress.limit_mpa,
            "above_long_life_stress": stress.needs_confirmation,
            "allow_high_stress": settings.allow_high_stress,
        },
        "settings": to_mapping(values),  # every setting as the runtime's JSON takes it
        "calibration": calibration,  # current driver (read at connect), wire, sensor tare
        "sensing": sensing_block(settings),  # the wire's resistance as a sensor (issue 26)
    }


def sensing_block(settings: RunSettings) -> dict[str, Any]:
    """``session.json``'s ``sensing``: the probe current, A; the feedback's source and fallback;
    the bound on the fallback, s; and ``selfsense``: the calibration's path and the calibration
    itself (:meth:`smabench.selfsense.SelfSenseCalibration.to_dict`, NaN as null), or null."""
    cal = settings.selfsense_calibration()
    block: dict[str, Any] = {
        "probe_current_a": settings.probe_current_a,
        "feedback": settings.feedback,
        "fallback": settings.fallback,
        "fallback_max_s": FALLBACK_MAX_S,
        "selfsense": None,
    }
    if cal is not None:
        import json

        block["selfsense"] = {
            "path": str(Path(settings.selfsense).resolve()),
            "calibration": json.loads(cal.to_json()),
        }
    return block


def planned_duration_s(settings: RunSettings) -> float:
    """Upper bound of a session's duration in device time, s: the protocol's own bound (every
    cooling to its timeout, every rest to its end), capped by ``max_duration_s``."""
    p = settings.protocol
    n = max(1, int(p.cycles))
    if settings.controller is not None:
        bound = p.lead_in_s + n * p.period_s
    elif p.name == "cycles":
        bound = n * (p.heat_s + p.cool_timeout_s)
    elif p.name == "incomplete":  # partial coolings, then the last one to its timeout
        bound = n * (p.heat_s + max(p.partial_cool_s, p.cool_timeout_s))
    elif p.name == "inner":
        bound = n * (p.heat_s + max(p.inner_cool_s, p.cool_timeout_s))
    elif p.name == "step":  # each level held
        bound = max(1, len(p.levels_a)) * p.hold_s
    elif p.name == "ramp":  # up and down
        bound = n * 2 * p.ramp_s
    else:
        bound = settings.max_duration_s
    return float(min(bound, settings.max_duration_s))


def check_session_space(settings: RunSettings) -> None:
    """Refuse (:class:`smabench.sessions.SessionError`, a ValueError) a session whose folder's
    file system cannot hold its planned duration's rows, or cannot be written at all; called
    before any device is opened."""
    duration_s = planned_duration_s(settings)
    rows = math.ceil(settings.rate_hz * duration_s / max(settings.time_scale, 1e-9)) + 1
    check_free_space(
        settings.out_dir, rows, f"{duration_s:g} s planned at {settings.rate_hz:g} Hz ({rows} rows)"
    )


SIGNAL_REASONS = {
    signal.SIGINT: "interrupted (SIGINT, Ctrl-C)",
    signal.SIGTERM: "terminated (SIGTERM)",
    signal.SIGHUP: "the terminal or the connection closed (SIGHUP)",
}
"""Why a session ended, per signal the recording process got."""


@contextlib.contextmanager
def _signals_end_session(runtime: BenchRuntime):
    """While the session runs (main thread only): SIGINT, SIGTERM and SIGHUP end it as aborted
    with :data:`SIGNAL_REASONS` (the loop makes the devices safe and the writer closes the
    session); a further signal during that shutdown is ignored, so the closing is never cut.
    After a signal the handlers stay in place (the process is ending); otherwise the previous
    ones come back. SIGHUP also points the standard streams that are terminals at /dev/null,
    so the closing lines do not fail on a terminal that is gone."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []

    def handler(signum: int, _frame: object) -> None:
        if got:
            log.info("signal %d during the shutdown: ignored, the session is closing", signum)
            return
        got.append(signum)
        if signum == signal.SIGHUP:
            _detach_from_dead_terminal()
        runtime.abort(
            SIGNAL_REASONS.get(signum, f"signal {signum}"),
            "operator" if signum == signal.SIGINT else "host",
        )

    previous = {sig: signal.signal(sig, handler) for sig in SIGNAL_REASONS}
    try:
        yield
    finally:
        if not got:
            for sig, old in previous.items():
                signal.signal(sig, old)


def _detach_from_dead_terminal() -> None:
    with contextlib.suppress(OSError):
        null = os.open(os.devnull, os.O_WRONLY)
        for fd in (1, 2):
            if os.isatty(fd):
                os.dup2(null, fd)
        os.close(null)


def run_session(
    settings: RunSettings,
    source: CurrentSourceDevice,
    sensor: DisplacementDevice,
    devices: dict[str, Any] | None = None,
    on_sample: Callable[[dict], None] | None = None,
    command: CommandSource | None = None,
    on_start: Callable[[BenchRuntime], None] | None = None,
) -> tuple[Path, RunResult]:
    """Run a validated session on connected devices; returns (folder, result).

    ``source``/``sensor`` are connected device clients; they are made safe at the end whatever
    happens. ``command`` defaults to the settings' controller (closed loop; the gains, the
    reference and the identified model go into ``session.json``) or else their protocol.
    ``on_start(runtime)`` is
    called before the loop starts (to e-stop, stop or switch modes from another thread).

    The loop runs in the calling thread, real-time (SCHED_FIFO) where allowed, for every caller
    (``run``, ``plan``, ``bench control``, the GUI's runtime): it renews the driver's setpoint
    lease, and a busy host must not hold it past that. The thread's scheduling is as before
    afterwards (a plan rests and computes between its steps)."""
    folder = settings.folder()
    check_session_space(settings)
    if command is None:
        command = (
            settings.build_controller()
            if settings.controller is not None
            else Protocol(settings.protocol)
        )
    describe = getattr(command, "describe", None)

    writer = SessionWriter(
        folder,
        session_meta(
            settings, devices or {}, describe() if describe else None, session_block(source)
        ),
        columns=session_columns(selfsense=settings.selfsense is not None),
    )
    runtime = BenchRuntime(
        source, sensor, command, writer.append, settings.runtime_config(), on_sample=on_sample,
        events=EventLog(folder),
    )  # fmt: skip
    result = None
    with _signals_end_session(runtime):
        try:
            if on_start is not None:
                on_start(runtime)
            with realtime_thread():
                result = runtime.run()
        finally:
            _close(writer, result, describe)
    return folder, result


def _close(writer: SessionWriter, result: RunResult | None, describe: Any) -> None:
    """``session.json`` with the end status, reason and loop figures (``result`` None: the
    loop never ran to its end)."""
    if result is None:
        writer.close("aborted", "interrupted")
        return
    periods = result.periods_s
    extra = {"samples": result.samples, "missed_deadlines": result.missed_deadlines}
    if periods.size:
        extra["period_ms"] = {
            "mean": float(periods.mean() * 1e3),
            "p99": float(sorted(periods)[int(0.99 * (periods.size - 1))] * 1e3),
        }
    if describe is not None:  # gains, adapted model and switches as they ended
        extra["controller_end"] = describe()
    writer.close(result.status, result.reason, **extra)
    if writer.full and writer.full not in result.reason:  # the closing found it full
        result.status, result.reason = "aborted", writer.meta["end_reason"]
