"""An archive larger than the memory given to the analysis (issue 29: 5 GB of sessions under a
1 GB limit), scaled down for test time: 100 sessions of 18 MB (1.8 GB, hard links of one
simulated session) under an address-space limit of 900 MB per process (``RLIMIT_AS``, as
``prlimit --as`` or ``ulimit -v`` sets it, from outside the command): twice the limit
(at 600–700 MB, pyarrow's own allocations failed once the sessions' text is read exactly).
``smabench characterize`` streams it (one chunk file at a time) and completes; ``smabench
analyze``, which holds whole sessions, is refused up front with what it needs, exit 2; neither
is killed half-way."""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import time

import pytest

from .conftest import command_cwd, command_env, smabench_command

LIMIT_BYTES = 900 * 2**20
SESSIONS = 100


def _limited(*args: str, timeout_s: float = 900.0) -> tuple[subprocess.CompletedProcess, float]:
    """The installed ``smabench ARGS`` under the address-space limit; (result, wall seconds)."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (LIMIT_BYTES, LIMIT_BYTES))

    t0 = time.monotonic()
    proc = subprocess.run([*smabench_command(), *args], capture_output=True, text=True,
                          cwd=command_cwd(), env=command_env(), timeout=timeout_s,
                          preexec_fn=limit)  # fmt: skip
    return proc, time.monotonic() - t0


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> list[str]:
    """SESSIONS session folders of one simulated 20-cycle session at 1 kHz (its samples.csv
    hard-linked: 1.8 GB to read, 18 MB on disk)."""
    root = tmp_path_factory.mktemp("archive")
    base = root / "base"
    subprocess.run([*smabench_command(), "simulate", "--cycles", "20", "--rate-hz", "1000",
                    "--out", str(base)], check=True, capture_output=True, cwd=command_cwd(),
                   env=command_env(), timeout=600)  # fmt: skip
    folders = []
    for k in range(SESSIONS):
        f = root / f"s{k:03d}"
        f.mkdir()
        os.link(base / "samples.csv", f / "samples.csv")
        shutil.copy(base / "session.json", f / "session.json")
        folders.append(str(f))
    return folders


def _archive_bytes(folders: list[str]) -> int:
    return sum(os.stat(os.path.join(f, "samples.csv")).st_size for f in folders)


@pytest.mark.slow
def test_characterize_streams_an_archive_larger_than_its_memory_limit(archive, tmp_path):
    assert _archive_bytes(archive) > 2 * LIMIT_BYTES
    out = tmp_path / "c.json"
    proc, _ = _limited("characterize", *archive, "--json", str(out), "--workers", "2")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "MemoryError" not in proc.stderr, proc.stderr
    doc = json.loads(out.read_text())
    assert len(doc["sessions"]) == SESSIONS and not doc["skipped"]
    cycles = {s["n_cycles"] for s in doc["sessions"]}
    assert len(cycles) == 1 and cycles.pop() >= 18, cycles  # every copy, every cycle


@pytest.mark.slow
@pytest.mark.parametrize("each", [False, True], ids=["together", "each"])
def test_analyze_of_an_archive_beyond_its_memory_is_refused_up_front(archive, each):
    proc, wall_s = _limited("analyze", *archive, *(["--each", "--workers", "2"] if each else []))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])  # not killed (< 0)
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("smabench analyze: error: analysing "), lines
    limit = f"free (address-space limit {LIMIT_BYTES / 1e6:.0f} MB"
    assert " needs about " in lines[0] and limit in lines[0], lines
    assert wall_s < 60, wall_s  # up front: nothing was loaded
