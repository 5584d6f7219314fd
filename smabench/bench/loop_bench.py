"""``smabench bench loop``: the bench runtime's timing against the mock bench over real transports.

For each configuration (loop rate, current-driver firmware) a mock bench runs in its own process;
the runtime runs a recorded session (a constant current with slow steps, so the driver is busy)
for ``duration_s`` and the measured tick periods give the achieved rate, the jitter (deviation of
each period from the nominal one: p50, p99, max) and the missed deadlines (ticks that started more
than one period late).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np

from smabench.bench.headless import MockProcess, open_devices
from smabench.bench.session_run import RunSettings, run_session
from smabench.commands import CommandStep
from smabench.protocols import ProtocolSettings

log = logging.getLogger(__name__)


class TimedSteps:
    """Current steps 0.3 → 0.9 A every 2 s, done after ``duration_s`` (device time)."""

    def __init__(self, duration_s: float) -> None:
        self.duration_s = duration_s

    def update(self, t_s: float, position_mm: float) -> CommandStep:
        if t_s >= self.duration_s:
            return CommandStep(0.0, 0, "done", done=True)
        return CommandStep(0.3 if int(t_s / 2.0) % 2 == 0 else 0.9, 0, "steps")


def loop_timing(
    rate_hz: float,
    firmware: str,
    duration_s: float,
    sensor: str = "tcp",
    adapter_latency_ms: float = 0.0,
) -> dict:
    """One configuration; returns the figures as a dict. ``adapter_latency_ms``: the mock's
    sensor holds every answer this long (an FTDI USB/RS-485 adapter's latency timer)."""
    with tempfile.TemporaryDirectory(prefix="smabench-bench-loop-") as tmp:
        settings = RunSettings(
            load_kg=2.0,
            protocol=ProtocolSettings(name="step", levels_a=(0.9,)),
            rate_hz=rate_hz,
            out_dir=Path(tmp),
            session_id="bench",
            max_duration_s=duration_s + 30.0,
        )
        settings.validate()
        mock_args = ["--load-kg", "2", "--firmware", firmware]
        mock_args += ["--adapter-latency-ms", f"{adapter_latency_ms:g}"]
        with MockProcess(mock_args) as mock:
            spec = mock.ports.sensor_tcp if sensor == "tcp" else mock.ports.sensor_rtu
            source, dev_sensor = open_devices(mock.ports.driver, spec, settings)
            try:
                _, result = run_session(
                    settings, source, dev_sensor, command=TimedSteps(duration_s)
                )
            finally:
                source.close()
                dev_sensor.close()
    periods = result.periods_s
    if result.status != "completed" or periods.size < 10:
        raise RuntimeError(f"loop benchmark run ended {result.status}: {result.reason}")
    nominal = 1.0 / rate_hz
    jitter = np.abs(periods - nominal)
    return {
        "rate_hz": rate_hz,
        "firmware": firmware,
        "sensor": sensor,
        "adapter_latency_ms": adapter_latency_ms,
        "duration_s": float(periods.sum()),
        "ticks": int(periods.size + 1),
        "achieved_hz": float(1.0 / periods.mean()),
        "jitter_p50_ms": float(np.percentile(jitter, 50) * 1e3),
        "jitter_p99_ms": float(np.percentile(jitter, 99) * 1e3),
        "jitter_max_ms": float(jitter.max() * 1e3),
        "missed": int(result.missed_deadlines),
    }


def format_rows(rows: list[dict]) -> str:
    head = (
        f"{'rate Hz':>7s} {'firmware':9s} {'sensor':6s} {'adapter ms':>10s} {'s':>5s} "
        f"{'ticks':>6s} "
        f"{'achieved Hz':>11s} {'jitter p50 ms':>13s} {'p99 ms':>7s} {'max ms':>7s} {'missed':>6s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['rate_hz']:7.0f} {r['firmware']:9s} {r['sensor']:6s} "
            f"{r.get('adapter_latency_ms', 0.0):10g} {r['duration_s']:5.0f} "
            f"{r['ticks']:6d} {r['achieved_hz']:11.2f} {r['jitter_p50_ms']:13.3f} "
            f"{r['jitter_p99_ms']:7.3f} {r['jitter_max_ms']:7.2f} {r['missed']:6d}"
        )
    return "\n".join(lines)
