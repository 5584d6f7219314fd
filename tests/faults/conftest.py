"""Fault injection at the bench: fixtures that run the *installed* ``smabench run --mock`` (the
console script of a clean ``pip install .`` into a fresh venv, :mod:`journeys.harness`, never
this checkout's modules) as a subprocess over the real transports and inject faults from outside
it (signals, a small file system, a second program on the port, the mock bench's fault commands,
a faked wall clock, a memory limit), and wait on what the run prints or writes (never a fixed
sleep).

Each test checks the same ending (issue 29): the wire safe, the session closed ``aborted`` with
a reason in words, every row written before readable, the exit code the README gives (1 for an
aborted session), one line on stderr and no traceback. docs/faults.md lists the faults and the
tests; keep both true.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from journeys.harness import Installed, installed_once

START_TIMEOUT_S = 120.0  # the mock's and the run's start-up beside other work on two cores
END_TIMEOUT_S = 60.0
SAFE_CURRENT_A = 0.020
PROGRESS = re.compile(r"^\s+t\s+(-?[\d.]+) s")


_INSTALLED: list[Installed] = []  # the one installed smabench of this run (set below)


@pytest.fixture(scope="session", autouse=True)
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """smabench installed from a clean copy of this checkout into a fresh venv, once per test run
    (the journey tests' venv and lock: one install serves both folders and every xdist worker)."""
    inst = installed_once(tmp_path_factory)
    _INSTALLED[:] = [inst]
    return inst


def _installed() -> Installed:
    assert _INSTALLED, "the session fixture `installed` has not run"
    return _INSTALLED[0]


def smabench_command() -> list[str]:
    """The smabench command line: the installed console script (no ``python -m`` of this
    checkout)."""
    return [str(_installed().script)]


def installed_python() -> Path:
    """The installed venv's interpreter (a client program of the installed package)."""
    return _installed().python


def command_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment the installed command runs in: no PYTHON*/SMABENCH_* of the caller's, a
    HOME of its own, plus ``extra``."""
    return _installed().env(extra)


def command_cwd() -> Path:
    """The working directory of the commands: outside the checkout."""
    return _installed().home


class Run:
    """``smabench run --mock …`` in its own process group (as a shell job is), its stdout and
    stderr read on threads; :meth:`wait_line` / :meth:`wait_progress` wait on what it prints."""

    def __init__(self, out: Path, sid: str, *extra: str, trace: Path | None = None,
                 cycles: int = 20, env: dict[str, str] | None = None,
                 devices: list[str] | None = None) -> None:  # fmt: skip
        self.out, self.sid = Path(out), sid
        self.folder = self.out / sid
        self.trace = trace
        args = [
            *smabench_command(), "run", *(devices or ["--mock"]), "--load-kg", "1",
            "--cycles", str(cycles), "--current-a", "1.0", "--out", str(out), "--session-id",
            sid, *extra,
        ]  # fmt: skip
        if trace is not None:
            args += ["--mock-trace", str(trace)]
        self.proc = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            cwd=command_cwd(), start_new_session=True, env=command_env(env),
        )  # fmt: skip
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._readers = [
            threading.Thread(target=self._read, args=(self.proc.stdout, self.stdout, True)),
            threading.Thread(target=self._read, args=(self.proc.stderr, self.stderr, False)),
        ]
        for t in self._readers:
            t.daemon = True
            t.start()

    def _read(self, stream, sink: list[str], feed: bool) -> None:
        for line in stream:
            sink.append(line)
            if feed:
                self.lines.put(line)
        if feed:
            self.lines.put(None)

    def wait_line(self, pred: Callable[[str], bool], timeout_s: float = START_TIMEOUT_S) -> str:
        """The first stdout line (from now) for which ``pred`` is true; fails at the deadline or
        when the run ends first."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                pytest.fail(f"no such line within {timeout_s:g} s; stdout: {self.stdout[-5:]}")
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                pytest.fail(f"the run ended first ({self.proc.wait()}): {''.join(self.stderr)}")
            if pred(line):
                return line

    def wait_progress(self, t_s: float, timeout_s: float = START_TIMEOUT_S) -> float:
        """Wait for a progress line at session time ``t_s`` or later; returns its time."""
        line = self.wait_line(
            lambda ln: (m := PROGRESS.match(ln)) is not None and float(m.group(1)) >= t_s,
            timeout_s,
        )
        return float(PROGRESS.match(line).group(1))

    def signal(self, sig: int, group: bool = True) -> None:
        """``sig`` to the run's process group (as a terminal sends it), or to the run alone."""
        if group:
            os.killpg(self.proc.pid, sig)
        else:
            os.kill(self.proc.pid, sig)

    def finish(self, timeout_s: float = END_TIMEOUT_S) -> tuple[int, str, str]:
        """Wait for the end; (exit code, stdout, stderr)."""
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"the run did not end within {timeout_s:g} s")
        for t in self._readers:
            t.join(10)
        return rc, "".join(self.stdout), "".join(self.stderr)

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def mock_pid(self) -> int:
        """The pid of the mock bench the run started (its child process)."""
        kids = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children").read_text().split()
        for pid in kids:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if b"mock" in cmd:
                return int(pid)
        raise AssertionError(f"no mock bench among the run's children {kids}")


class Mock:
    """``smabench mock --control-stdin`` of its own (the bench a run connects to with
    ``--port``/``--sensor``): :meth:`send` injects a fault (``sensor-exception CODE N``,
    ``sensor-delay S N``, …), :attr:`devices` are the run's options to reach it."""

    def __init__(self, trace: Path, *extra: str, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [*smabench_command(), "mock", "--control-stdin", "--load-kg", "1", "--trace",
             str(trace), *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
            cwd=command_cwd(), env=command_env(env),
        )  # fmt: skip
        found: dict[str, str] = {}
        for line in self.proc.stdout:
            if line.strip() == "ready":
                break
            key, sep, value = line.strip().partition(": ")
            if sep:
                found[key] = value
        else:
            pytest.fail(f"the mock bench ended before ready ({self.proc.wait()})")
        threading.Thread(target=lambda: [None for _ in self.proc.stdout], daemon=True).start()
        self.driver, self.sensor = found["driver"], found["sensor-tcp"]
        self.devices = ["--port", self.driver, "--sensor", self.sensor]

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def mock_bench(tmp_path):
    """Start a mock bench with ``mock_bench(trace, *args)``; closed at the end of the test."""
    mocks: list[Mock] = []

    def start(trace: Path, *extra: str, **kw) -> Mock:
        m = Mock(trace, *extra, **kw)
        mocks.append(m)
        return m

    yield start
    for m in mocks:
        m.close()


@pytest.fixture
def run_mock(tmp_path):
    """Start runs with ``run_mock(out, sid, *args)``; every one still running is killed at the
    end of the test."""
    runs: list[Run] = []

    def start(out: Path, sid: str, *extra: str, **kw) -> Run:
        r = Run(out, sid, *extra, **kw)
        runs.append(r)
        return r

    yield start
    for r in runs:
        if r.proc.poll() is None:
            r.kill()


@pytest.fixture
def small_fs(tmp_path):
    """``small_fs(size)``: a tmpfs of ``size`` (e.g. "120k") mounted in the test's folder;
    ``ro=True`` mounts it read-only. Unmounted at the end of the test."""
    mounts: list[Path] = []

    def mount(size: str, ro: bool = False, name: str = "fs") -> Path:
        path = tmp_path / name
        path.mkdir()
        opts = f"size={size}" + (",ro" if ro else "")
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)],
                              capture_output=True, text=True)  # fmt: skip
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {proc.stderr.strip()}")
        mounts.append(path)
        return path

    yield mount
    for path in reversed(mounts):
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def rows_on_disk(folder: Path) -> int:
    """Whole sample rows in ``folder``'s samples.csv now."""
    with open(folder / "samples.csv", "rb") as fh:
        return sum(1 for line in fh if line.endswith(b"\n")) - 1


def assert_ends_aborted(rc: int, stderr: str, reason: str, warnings_from: str = "") -> None:
    """Exit 1, one line on stderr naming the reason, no traceback; ``warnings_from``: the
    logger prefix of the warnings allowed before that line (the driver saying what it saw)."""
    lines = stderr.strip().splitlines()
    assert rc == 1, (rc, stderr)
    assert "Traceback" not in stderr, stderr
    before = [ln for ln in lines[:-1] if not (warnings_from and ln.startswith(warnings_from))]
    assert lines and not before, stderr
    assert reason in lines[-1] and lines[-1].startswith("smabench run: aborted: "), stderr


def assert_wire_safe(trace: Path) -> None:
    """The plant's own trace ends with the current below 20 mA."""
    data = np.genfromtxt(trace, delimiter=",", names=True)
    assert data.size > 10, f"trace {trace} too short"
    current = data["current_A"] if "current_A" in data.dtype.names else data[data.dtype.names[1]]
    assert abs(current[-1]) < SAFE_CURRENT_A, current[-20:]
