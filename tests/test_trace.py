"""``smabench mock --trace``: what the plant really got, checkable from outside the host code."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from smabench.drivers.mock.plant_link import TRACE_COLUMNS, PlantLink

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py


def read_trace(path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == TRACE_COLUMNS
    data = np.array(rows[1:], dtype=float)
    return {name: data[:, k] for k, name in enumerate(TRACE_COLUMNS)}


def test_trace_rows_are_the_plant_steps(tmp_path):
    path = tmp_path / "trace.csv"
    link = PlantLink(2.0, trace=path, noise_mm=0.0)
    for _ in range(500):
        link.step(0.002, 1.4)  # 1 s at 1.4 A in 2 ms calls, 1 ms sub-steps
    for _ in range(500):
        link.step(0.002, 0.0)
    link.close()
    tr = read_trace(path)
    assert len(tr["t_s"]) == 2000  # one row per 1 ms sub-step
    assert np.allclose(np.diff(tr["t_s"]), 1e-3)
    assert np.all(tr["current_A"][:1000] == 1.4) and np.all(tr["current_A"][1000:] == 0.0)
    # heated: the temperature rose while the current flowed and fell after
    t = tr["temperature_C"]
    assert t[999] > t[0] + 5.0 and t[-1] < t[999]
    assert link.close() is None  # idempotent


@pytest.mark.slow
def test_session_and_trace_agree_from_outside(tmp_path, run_cli):
    """A short session on the mock: the trace's current is what the session recorded, and never
    above the current limit."""
    trace = tmp_path / "trace.csv"
    proc = run_cli(
        "run", "--mock", "--mock-speed", "5", "--mock-trace", str(trace), "--load-kg", "2",
        "--protocol", "cycles", "--cycles", "1", "--current-a", "1.2", "--heat-s", "2",
        "--cool-timeout-s", "4", "--out", str(tmp_path), "--session-id", "s", "--quiet",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    tr = read_trace(trace)
    assert tr["current_A"].max() <= 1.2 * 1.02  # what flowed never exceeded the command
    heated = tr["current_A"] > 0.6
    assert abs(np.median(tr["current_A"][heated]) - 1.2) < 0.02
    assert tr["t_s"][-1] > 2.0  # the heating and part of the cooling are in the trace


@pytest.mark.slow
def test_thermocouple_channel_reaches_the_session(tmp_path, run_cli):
    """With a MAX31855 on the wire the session's temperature_C is the wire's measured
    temperature (0.25 °C steps, as the chip reports); without one the column stays empty."""
    from smabench.sessions import load_session

    for tc in (True, False):
        trace = tmp_path / f"trace-{tc}.csv"
        args = ["run", "--mock", "--mock-speed", "5", "--mock-trace", str(trace), "--load-kg", "2",
                "--protocol", "cycles", "--cycles", "1", "--current-a", "1.2", "--heat-s", "2",
                "--cool-timeout-s", "3", "--out", str(tmp_path), "--session-id", f"s{tc}",
                "--quiet"]  # fmt: skip
        proc = run_cli(*args, *(["--mock-thermocouple"] if tc else []))
        assert proc.returncode == 0, proc.stderr
        s = load_session(tmp_path / f"s{tc}")
        measured = s.data["temperature_C"] if s.has("temperature_C") else None
        if not tc:
            assert measured is None or not np.isfinite(measured).any()
            continue
        assert np.isfinite(measured).mean() > 0.9
        chip = measured[np.isfinite(measured)]
        assert np.allclose(chip * 4, np.round(chip * 4))  # the MAX31855's 0.25 °C steps
        tr = read_trace(trace)
        # the hottest the chip saw is the hottest the wire got (telemetry lags ≤ a few ms)
        assert abs(np.nanmax(measured) - tr["temperature_C"].max()) < 2.0
