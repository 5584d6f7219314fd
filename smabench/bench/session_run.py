"""Run one recorded session on the bench: validate settings, open devices, loop, record.

Everything the operator enters is checked before any device is opened, so an out-of-range
setting gets a clear error and nothing is sent. The session folder is created with
``session.json`` (status ``running``) at the start, rows are appended and flushed at least every
0.5 s while running, and ``session.json`` is rewritten atomically with the end status and reason.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from smabench.bench.runtime import BenchRuntime, RunResult, RuntimeConfig
from smabench.physics.wire import PRESETS
from smabench.protocols import Protocol, ProtocolSettings
from smabench.sessions import SCHEMA_VERSION, SessionWriter

log = logging.getLogger(__name__)

__all__ = ["SCHEMA_VERSION", "RunSettings", "run_session", "session_meta"]
MAX_LOAD_KG = 10.0


@dataclass
class RunSettings:
    """What the operator chose for one session (units in names)."""

    load_kg: float
    protocol: ProtocolSettings = field(default_factory=ProtocolSettings)
    rate_hz: float = 200.0
    wire_preset: str = "paper"
    current_limit_a: float = 2.0
    temperature_limit_c: float = 160.0
    position_min_mm: float = -math.inf
    position_max_mm: float = math.inf
    max_duration_s: float = 3600.0
    out_dir: Path = Path("sessions")
    session_id: str | None = None
    time_scale: float = 1.0  # > 1 only against a mock bench run faster than real time
    controller: Any = None  # smabench.control.ControllerSettings: closed loop on a reference

    def validate(self, device_limit_a: float | None = None) -> None:
        """Raise ValueError naming the first setting that is out of range."""
        if not (isinstance(self.load_kg, (int, float)) and 0.0 < self.load_kg <= MAX_LOAD_KG):
            raise ValueError(f"load must be in (0, {MAX_LOAD_KG}] kg, got {self.load_kg}")
        if self.wire_preset not in PRESETS:
            raise ValueError(
                f"unknown wire preset {self.wire_preset!r}; choose from {', '.join(PRESETS)}"
            )
        wire = PRESETS[self.wire_preset]
        limit = min(self.current_limit_a, wire.max_current_a)
        if device_limit_a is not None:
            limit = min(limit, device_limit_a)
        if not 0.0 < self.current_limit_a <= wire.max_current_a * 1.25:
            raise ValueError(f"current limit {self.current_limit_a} A is out of range")
        self.protocol.validate(limit, closed_loop=self.controller is not None)
        self.runtime_config().validate()
        if self.controller is not None:
            self.controller.validate()
            self.build_controller()  # refuses unreachable setpoints before any device opens

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
        )

    def folder(self) -> Path:
        sid = self.session_id or time.strftime(
            f"%Y%m%d-%H%M%S-{self.protocol.name}-{self.load_kg:g}kg"
        )
        return Path(self.out_dir) / sid


def session_meta(
    settings: RunSettings, devices: dict[str, Any], controller: dict | None = None
) -> dict[str, Any]:
    """``session.json`` content at the start of a run (session contract, DESIGN §3)."""
    wire = PRESETS[settings.wire_preset]
    proto = asdict(settings.protocol)
    proto["levels_a"] = list(proto["levels_a"])
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
            "position_min_mm": settings.position_min_mm,
            "position_max_mm": settings.position_max_mm,
        },
    }


def run_session(
    settings: RunSettings,
    source: Any,
    sensor: Any,
    devices: dict[str, Any] | None = None,
    on_sample: Callable[[dict], None] | None = None,
    command: Any = None,
    on_start: Callable[[BenchRuntime], None] | None = None,
) -> tuple[Path, RunResult]:
    """Run a validated session on connected devices; returns (folder, result).

    ``source``/``sensor`` are connected device clients; they are made safe at the end whatever
    happens. ``command`` defaults to the settings' controller (closed loop; the gains, the
    reference and the identified model go into ``session.json``) or else their protocol.
    ``on_start(runtime)`` is
    called before the loop starts (to e-stop, stop or switch modes from another thread).
    """
    folder = settings.folder()
    if command is None:
        command = (
            settings.build_controller()
            if settings.controller is not None
            else Protocol(settings.protocol)
        )
    describe = getattr(command, "describe", None)
    writer = SessionWriter(
        folder, session_meta(settings, devices or {}, describe() if describe else None)
    )
    runtime = BenchRuntime(
        source, sensor, command, writer.append, settings.runtime_config(), on_sample=on_sample
    )
    result = None
    try:
        if on_start is not None:
            on_start(runtime)
        result = runtime.run()
    finally:
        if result is None:
            writer.close("aborted", "interrupted")
        else:
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
    return folder, result
