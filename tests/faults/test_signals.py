"""Signals to the recording process: the terminal closing (SIGHUP), SIGTERM, Ctrl-C (SIGINT)
and a second Ctrl-C during the shutdown, kill -9, the process stopped (SIGSTOP) for 2 s."""

from __future__ import annotations

import contextlib
import json
import re
import signal
import subprocess
import textwrap
import time

import numpy as np
import pytest

from smabench.sessions import RECORDER_DIED, SAMPLES_FILE, load_session, session_status

from .conftest import (
    END_TIMEOUT_S,
    assert_ends_aborted,
    assert_wire_safe,
    command_cwd,
    command_env,
    rows_on_disk,
    smabench_command,
)

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

HEATING = re.compile(r"heat\s+I (\d+\.\d+) A")


def _check_closed(folder, reason: str, rows_before: int) -> None:
    meta = json.loads((folder / "session.json").read_text())
    assert meta["status"] == "aborted" and reason in meta["end_reason"], meta
    assert (folder / SAMPLES_FILE).read_bytes().endswith(b"\n")
    s = load_session(folder)
    assert len(s) == meta["rows"] >= rows_before
    assert np.all(np.diff(s.data["t_s"]) > 0)
    assert session_status(folder) == ("aborted", meta["end_reason"])


@pytest.mark.slow
@pytest.mark.parametrize(
    "sig, reason",
    [
        (signal.SIGHUP, "SIGHUP"),
        (signal.SIGTERM, "SIGTERM"),
        (signal.SIGINT, "SIGINT"),
    ],
    ids=["sighup", "sigterm", "sigint"],
)
def test_signal_during_a_session_closes_it_aborted(tmp_path, run_mock, sig, reason):
    trace = tmp_path / "trace.csv"
    run = run_mock(tmp_path, "s", trace=trace)
    run.wait_progress(1.0)
    rows_before = rows_on_disk(run.folder)
    run.signal(sig)  # to the process group, as the terminal sends it
    rc, out, err = run.finish()
    assert_ends_aborted(rc, err, reason)
    _check_closed(run.folder, reason, rows_before)
    assert_wire_safe(trace)


@pytest.mark.slow
def test_a_second_ctrl_c_during_the_shutdown_does_not_cut_the_closing(tmp_path, run_mock):
    trace = tmp_path / "trace.csv"
    run = run_mock(tmp_path, "s", trace=trace)
    run.wait_progress(1.0)
    rows_before = rows_on_disk(run.folder)
    run.signal(signal.SIGINT)
    run.signal(signal.SIGINT)  # impatient: at once, while the first one is being handled
    deadline = time.monotonic() + END_TIMEOUT_S
    while session_status(run.folder)[0] == "running" and time.monotonic() < deadline:
        time.sleep(0.01)  # polls the condition: the session closed, the devices still open
    with contextlib.suppress(ProcessLookupError):  # and once more while it shuts down
        run.signal(signal.SIGINT)
    rc, out, err = run.finish()
    assert_ends_aborted(rc, err, "SIGINT")
    _check_closed(run.folder, "SIGINT", rows_before)
    assert_wire_safe(trace)


@pytest.mark.slow
def test_kill_9_reads_as_aborted_the_recording_process_died(tmp_path, run_mock):
    run = run_mock(tmp_path, "s")
    run.wait_progress(1.0)
    assert session_status(run.folder) == ("running", "")  # alive: it holds the lock
    run.kill()
    meta = json.loads((run.folder / "session.json").read_text())
    assert meta["status"] == "running"  # nobody wrote its end...
    assert session_status(run.folder) == ("aborted", RECORDER_DIED)  # ...every reader says so
    assert len(load_session(run.folder)) > 100
    from smabench.gui.sessions_view import read_session_rows  # the GUI's session list

    (row,) = read_session_rows(tmp_path)
    assert row.status == "aborted"


PLAN = """
[plan]
name = "k9"
wire = "paper"
rate_hz = 200
current_limit_a = 2.0
max_step_s = 600
out = "{out}"
mock_speed = 5
retries = 0

[[step]]
name = "one"
protocol = "cycles"
load_kg = 1.0
cycles = {cycles}
current_a = 1.5
heat_s = 2.0
cool_timeout_s = 6.0
min_cool_s = 4.0
rest_s = 0.0
"""


@pytest.mark.slow
def test_kill_9_of_a_plan_then_resume_shows_the_killed_session_aborted(tmp_path, run_mock):
    plan = tmp_path / "k9.toml"
    plan.write_text(textwrap.dedent(PLAN.format(out=tmp_path / "out", cycles=1)))
    proc = subprocess.Popen([*smabench_command(), "plan", "run", str(plan), "--mock"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=command_cwd(), env=command_env(),
                            start_new_session=True)  # fmt: skip
    killed = tmp_path / "out" / "k9" / "01-one"
    try:
        deadline = time.monotonic() + 120
        while not ((killed / SAMPLES_FILE).is_file()
                   and (killed / SAMPLES_FILE).stat().st_size > 2000):  # fmt: skip
            assert time.monotonic() < deadline and proc.poll() is None, proc.stderr.read()
            time.sleep(0.05)  # polling a file's size: the condition, not a fixed wait
    finally:
        import os

        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert session_status(killed) == ("aborted", RECORDER_DIED)
    res = subprocess.run([*smabench_command(), "plan", "resume", str(tmp_path / "out" / "k9"),
                          "--mock"], capture_output=True, text=True, cwd=command_cwd(),
                         env=command_env(), timeout=300)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert f"01-one aborted: {RECORDER_DIED}" in res.stdout, res.stdout
    meta = json.loads((killed / "session.json").read_text())
    assert meta["status"] == "aborted" and meta["end_reason"] == RECORDER_DIED
    assert meta["rows"] == len(load_session(killed))


@pytest.mark.slow
def test_process_stopped_2_s_the_lease_trips_and_the_session_says_so(tmp_path, run_mock):
    trace = tmp_path / "trace.csv"
    run = run_mock(tmp_path, "s", trace=trace)
    run.wait_line(lambda ln: (m := HEATING.search(ln)) is not None and float(m[1]) > 0.5)
    rows_before = rows_on_disk(run.folder)
    run.signal(signal.SIGSTOP, group=False)  # the recording process only: the bench runs on
    t_stop = time.monotonic()
    # the plant's own trace shows the wire safe while the host is still stopped
    deadline = t_stop + 2.0
    safe_while_stopped = False
    while time.monotonic() < deadline:
        data = np.genfromtxt(trace, delimiter=",", names=True)
        if data.size and data["t_s"][-1] > 0 and abs(data["current_A"][-1]) < 0.02:
            safe_while_stopped = True
        time.sleep(0.05)
    run.signal(signal.SIGCONT, group=False)
    rc, out, err = run.finish()
    assert safe_while_stopped, "the lease did not turn the current off within 2 s"
    # the driver's link says what it saw while the host was stopped (link lost, host timeout)
    assert_ends_aborted(rc, err, "stalled for 2.", warnings_from="WARNING smabench.drivers.")
    _check_closed(run.folder, "setpoint lease", rows_before)
    assert_wire_safe(trace)
