"""The host's wall clock stepped by ±1 h during a session (NTP catching up, an operator's
``date -s``), injected from outside the run: Debian's libfaketime preloaded into the installed
``smabench run --mock`` and its mock bench, the wall clock (``CLOCK_REALTIME``) faked from a
timestamp file the test rewrites mid-session, the monotonic clock left alone
(``FAKETIME_DONT_FAKE_MONOTONIC=1``)."""

from __future__ import annotations

import datetime as dt
import glob
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from smabench.sessions import load_session

from .conftest import assert_wire_safe

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

HERE = Path(__file__).resolve().parent
RATE_HZ = 200.0


@pytest.fixture(scope="session")
def faketime_preload(tmp_path_factory) -> str:
    """``LD_PRELOAD`` for a faked wall clock: the monotonic waits libfaketime 0.9.10 gets wrong
    handed straight to glibc (faketime_monotonic_waits.c, built here with clang), then Debian's
    libfaketime (package ``libfaketime``)."""
    found = glob.glob("/usr/lib/*/faketime/libfaketime.so.1")
    if not found:
        pytest.fail("libfaketime is not installed (Makefile APT_PACKAGES: `make sysdeps`)")
    fix = tmp_path_factory.mktemp("faketime") / "monotonic_waits.so"
    subprocess.run(["clang", "-shared", "-fPIC", "-O2", "-o", str(fix),
                    str(HERE / "faketime_monotonic_waits.c"), "-ldl"], check=True,
                   timeout=120)  # fmt: skip
    return f"{fix}:{found[0]}"


def _set_offset(path: Path, offset_s: int) -> None:
    """The faked wall clock: the real one plus ``offset_s`` (replaced whole, never half-read)."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(f"{offset_s:+d}\n")
    os.replace(tmp, path)


def _stamp(text: str) -> dt.datetime:
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%S%z")


@pytest.mark.slow
@pytest.mark.parametrize("step_s", [3600, -3600], ids=["forward-1h", "back-1h"])
def test_wall_clock_stepped_during_a_session_changes_no_timing_and_is_stated(
    tmp_path, run_mock, faketime_preload, step_s
):
    clock = tmp_path / "faketime.txt"
    _set_offset(clock, 0)
    # the file re-read at most once a second (FAKETIME_NO_CACHE=1, a read at every clock call,
    # slows the mock bench's start past its 5 s limit)
    env = {"LD_PRELOAD": faketime_preload, "FAKETIME_DONT_FAKE_MONOTONIC": "1",
           "FAKETIME_TIMESTAMP_FILE": str(clock), "FAKETIME_CACHE_DURATION": "1"}  # fmt: skip
    trace = tmp_path / "trace.csv"
    run = run_mock(tmp_path, "s", "--heat-s", "2", "--cool-timeout-s", "6", trace=trace,
                   cycles=2, env=env)  # fmt: skip
    run.wait_progress(1.0)
    _set_offset(clock, step_s)  # the host's clock stepped, the session running
    t_after = run.wait_progress(3.0)  # seen by the run within its 1 s cache
    rc, out, err = run.finish()
    assert rc == 0 and "Traceback" not in err, (rc, err)
    assert t_after >= 3.0
    meta = json.loads((run.folder / "session.json").read_text())
    assert meta["status"] == "completed", meta
    # the stamps say what happened: the end is an hour off the start plus the session's length,
    # and session.json says by how much the clock was stepped
    assert abs(meta["wall_clock_stepped_s"] - step_s) < 1.0, meta
    s = load_session(run.folder)
    t_s = s.data["t_s"]
    duration_s = float(t_s[-1] - t_s[0])
    span_s = (_stamp(meta["ended_at"]) - _stamp(meta["started_at"])).total_seconds()
    assert abs(span_s - (duration_s + step_s)) < 5.0, (span_s, duration_s)
    # nothing in the timing moved: the samples keep their rate, no gap, no burst, no going back
    dt_s = np.diff(t_s)
    assert np.all(dt_s > 0)
    assert dt_s.max() < 0.1, dt_s.max()
    assert abs(len(t_s) / duration_s - RATE_HZ) < 0.05 * RATE_HZ, (len(t_s), duration_s)
    assert len(s) == meta["rows"]
    assert_wire_safe(trace)
