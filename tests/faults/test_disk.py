"""Disk faults: a full file system at the start and during a session, a read-only folder."""

from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pytest

from smabench.sessions import (
    LOCK_FILE,
    RESERVE_FILE,
    SAMPLES_FILE,
    DiskFullError,
    SessionWriter,
    load_session,
)

from .conftest import (
    assert_ends_aborted,
    assert_wire_safe,
    command_cwd,
    command_env,
    rows_on_disk,
    smabench_command,
)

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py


def _row(i: int) -> dict:
    return {"t_s": i * 0.005, "current_A": 0.5, "position_mm": 1.0 + i * 1e-4, "cycle": i // 400,
            "flags": 0}  # fmt: skip


def _fill(path) -> None:
    """Fill the file system holding ``path`` to the last byte (another program's file)."""
    with open(path / "filler", "wb", buffering=0) as fh:
        try:
            while fh.write(b"\0" * 4096):
                pass
        except OSError as exc:
            assert exc.errno == 28, exc


def test_writer_on_a_full_disk_keeps_whole_rows_and_still_closes(small_fs):
    """The writer alone: rows until the disk fills, then DiskFullError; the file ends at a whole
    row, the closing fits (the reserve), session.json says aborted, disk full."""
    fs = small_fs("200k")
    w = SessionWriter(fs / "s", {"kind": "test"}, flush_s=0.0)
    assert (fs / "s" / RESERVE_FILE).stat().st_size > 0
    _fill(fs)
    appended = 0
    with pytest.raises(DiskFullError) as err:
        for i in range(100_000):
            w.append(_row(i))
            appended += 1
    assert err.value.reason == "disk full"
    w.close("aborted", "disk full")
    meta = json.loads((fs / "s" / "session.json").read_text())
    assert meta["status"] == "aborted" and meta["end_reason"] == "disk full"
    raw = (fs / "s" / SAMPLES_FILE).read_bytes()
    assert raw.endswith(b"\n")
    s = load_session(fs / "s")
    assert len(s) == meta["rows"] <= appended
    assert np.all(np.diff(s.data["t_s"]) > 0)
    assert not (fs / "s" / RESERVE_FILE).exists() and not (fs / "s" / LOCK_FILE).exists()


def test_disk_full_at_the_start_is_refused_with_the_space_needed(small_fs, tmp_path):
    fs = small_fs("120k")
    proc = subprocess.run(
        [*smabench_command(), "run", "--mock", "--load-kg", "1", "--cycles", "5",
         "--out", str(fs), "--session-id", "s"],
        capture_output=True, text=True, timeout=120, cwd=command_cwd(), env=command_env(),
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    # 5 cycles of 3 s heat + 15 s cooling at 200 Hz: 18 001 rows, MB needed, ~100 kB free
    assert "not enough free space" in lines[0] and "90 s planned at 200 Hz" in lines[0], lines
    assert " MB, " in lines[0] and "kB free" in lines[0], lines
    assert not (fs / "s").exists()  # nothing started, nothing half-written


def test_read_only_session_folder_is_refused_before_any_device(small_fs):
    fs = small_fs("1m", ro=True)
    proc = subprocess.run(
        [*smabench_command(), "run", "--mock", "--load-kg", "1", "--cycles", "1",
         "--out", str(fs / "sessions"), "--session-id", "s"],
        capture_output=True, text=True, timeout=120, cwd=command_cwd(), env=command_env(),
    )  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "read-only file system" in lines[0], proc.stderr
    assert "mock bench" not in proc.stdout  # refused before the mock was started


@pytest.mark.slow
def test_disk_full_during_a_session_stops_at_the_last_whole_row(small_fs, tmp_path, run_mock):
    fs = small_fs("3m")
    trace = tmp_path / "trace.csv"
    run = run_mock(fs, "s", trace=trace, cycles=2)
    run.wait_progress(1.0)
    rows_before = rows_on_disk(run.folder)
    _fill(fs)  # another program fills the disk
    rc, out, err = run.finish()
    assert_ends_aborted(rc, err, "disk full")
    meta = json.loads((run.folder / "session.json").read_text())
    assert meta["status"] == "aborted" and meta["end_reason"] == "disk full", meta
    raw = (run.folder / SAMPLES_FILE).read_bytes()
    assert raw.endswith(b"\n")
    s = load_session(run.folder)
    assert len(s) == meta["rows"] >= rows_before
    assert np.all(np.diff(s.data["t_s"]) > 0)
    assert not (run.folder / RESERVE_FILE).exists()
    os.unlink(fs / "filler")
    assert_wire_safe(trace)
