"""``smabench bench link``: latency and throughput of both device links over the real transports.

Against a mock bench in its own process (by default with the real firmware in simavr):
- command round trip to the current driver (PING and SET_CURRENT → ACK): median and p99;
- telemetry: frames per second achieved at the firmware's fastest period vs what the serial line
  could carry at its baud rate (10 bits per byte, 8N1);
- Modbus read latency of the displacement sensor over TCP and over RTU (socat pty pair).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from smabench.bench.headless import MockProcess
from smabench.drivers import protocol as p
from smabench.drivers.base import SensorTimeout
from smabench.drivers.current_source import CurrentSource
from smabench.drivers.displacement import DisplacementSensor

log = logging.getLogger(__name__)

SENSOR_MAP = "generic-rs485-laser"


def _stats_ms(values_s: list[float]) -> dict:
    a = np.asarray(values_s) * 1e3
    return {
        "n": int(a.size),
        "median_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
    }


def command_round_trips(source: CurrentSource, n: int) -> dict[str, dict]:
    """PING and SET_CURRENT (waited for) round trips, and what a control loop pays for a
    posted setpoint (``set_current`` without waiting: the call alone)."""
    pings = [source.ping() for _ in range(n)]
    sets = []
    for i in range(n):
        t0 = time.perf_counter()
        source.set_current(0.1 * (i % 5), wait=True)
        sets.append(time.perf_counter() - t0)
    posted = []
    for i in range(n):
        t0 = time.perf_counter()
        source.set_current(0.1 * (i % 5))
        posted.append(time.perf_counter() - t0)
        time.sleep(0.005)  # one control tick at 200 Hz
    source.set_current(0.0, wait=True)
    return {
        "PING": _stats_ms(pings),
        "SET_CURRENT": _stats_ms(sets),
        "set_current posted (call)": _stats_ms(posted),
    }


def telemetry_rate(source: CurrentSource, seconds: float) -> dict:
    """Frames per second (host clock and device clock) at the fastest telemetry period."""
    period_s = p.TELEMETRY_PERIOD_RANGE_S[0]
    source.set_telemetry(period_s)
    frames: list[p.Telemetry] = []
    lock = threading.Lock()

    def on_frame(t: p.Telemetry) -> None:
        with lock:
            frames.append(t)

    time.sleep(0.2)  # let the new period take effect
    unsubscribe = source.subscribe(on_frame)
    time.sleep(seconds)
    unsubscribe()
    with lock:
        got = list(frames)
    frame_bytes = len(p.encode_frame(0, p.MsgType.TELEMETRY, bytes(p.TELEMETRY_LEN)))
    line_limit = p.BAUDRATE / 10.0 / frame_bytes
    device_s = (got[-1].t_ms - got[0].t_ms) / 1e3 if len(got) > 1 else float("nan")
    return {
        "requested_hz": 1.0 / period_s,
        "achieved_hz": (len(got) - 1) / (got[-1].host_time - got[0].host_time),
        "achieved_device_hz": (len(got) - 1) / device_s,
        "frame_bytes": frame_bytes,
        "line_limit_hz": line_limit,
        "line_use_percent": 100.0 * (len(got) - 1) / device_s / line_limit,
    }


def modbus_latency(spec: str, n: int) -> dict:
    """Read latency of ``n`` reads; a read that got no answer within the sensor's timeout is
    counted (``no_response``), not timed: on a loaded machine the mock sensor can miss it, and
    how often is a figure of the benchmark. Raises when no read at all was answered, or on any
    other failure."""
    with DisplacementSensor(SENSOR_MAP, spec) as sensor:
        lat: list[float] = []
        missed = 0
        for k in range(n + 1):  # the first read warms the link up and is not timed
            t0 = time.perf_counter()
            try:
                sample = sensor.read()
            except SensorTimeout as exc:
                missed += k > 0
                log.warning("benchmark read %d: %s", k, exc)
                continue
            if k:
                lat.append(time.perf_counter() - t0)
            if not sample.ok:
                raise RuntimeError(f"Modbus read failed during the benchmark: {sample.error}")
    if not lat:
        raise RuntimeError(f"{spec}: none of {n} Modbus reads was answered")
    return {**_stats_ms(lat), "no_response": missed}


def link_figures(firmware: str = "emulated", n: int = 500, telemetry_s: float = 5.0) -> dict:
    with MockProcess(["--load-kg", "2", "--firmware", firmware]) as mock:
        source = CurrentSource(mock.ports.driver)
        try:
            info = source.connect()
            out = {"firmware": firmware, "device": info.name, "round_trips": {}}
            out["round_trips"] = command_round_trips(source, n)
            out["telemetry"] = telemetry_rate(source, telemetry_s)
        finally:
            source.make_safe()
            source.close()
        out["modbus"] = {"tcp": modbus_latency(mock.ports.sensor_tcp, n)}
        if mock.ports.sensor_rtu:
            out["modbus"]["rtu"] = modbus_latency(mock.ports.sensor_rtu, n)
    return out


def format_figures(f: dict) -> str:
    lines = [f"current driver: {f['device']} ({f['firmware']} firmware) over a pty at "
             f"{p.BAUDRATE} baud"]  # fmt: skip
    for name, s in f["round_trips"].items():
        lines.append(
            f"  {name:26s}: median {s['median_ms']:.2f} ms, p99 {s['p99_ms']:.2f} ms, "
            f"max {s['max_ms']:.2f} ms (n={s['n']})"
        )
    t = f["telemetry"]
    lines.append(
        f"  telemetry: {t['requested_hz']:.0f} Hz asked (the fastest period), achieved "
        f"{t['achieved_hz']:.1f} Hz host clock / {t['achieved_device_hz']:.1f} Hz device clock; "
        f"a {t['frame_bytes']}-byte frame, line limit {t['line_limit_hz']:.0f} frames/s "
        f"({t['line_use_percent']:.0f} % of the line)"
    )
    for kind, s in f["modbus"].items():
        lines.append(
            f"displacement sensor, Modbus {kind.upper()}: read latency median "
            f"{s['median_ms']:.2f} ms, p99 {s['p99_ms']:.2f} ms, max {s['max_ms']:.2f} ms "
            f"(n={s['n']}, no response in time: {s['no_response']})"
        )
    return "\n".join(lines)
