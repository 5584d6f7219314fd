"""Shared fixtures: paths to the measured Flexinol loops, a CLI runner and the GUI tests' one
window per module on the mock bench."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
FLEXINOL_DIR = Path(
    os.environ.get("SMABENCH_FLEXINOL_DIR", REPO / "sessions" / "samples" / "flexinol-isobaric")
)
# where the workplace keeps the measured loops (more loads of the same wire may appear there)
SHARED_FLEXINOL_DIR = REPO.parent / "shared" / "data" / "flexinol-isobaric"


REALTIME_GROUP = "realtime-bench"
"""The xdist group (``--dist loadgroup``, Makefile) of every test marked ``realtime_bench``: they
run one after another in one worker, never two real-time benches at once. A mock bench at 5×
with its session holds about 75 % of a core at SCHED_FIFO (the device thread 40 %, the Modbus
server 11 %, the loop 15 %, the link 9 %: measured from /proc); two on this 2-core machine left
the kernel's pty workers and the rest a fraction of the CPU, and a device thread that fell
behind recorded a session that was not the plant's (telemetry stale, a cycle 0.3 mm too long;
"telemetry lost for 0.25 s" on CI). One bench per machine is also what a lab runs."""


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Group by file (as ``--dist loadfile``: a module's fixtures are built once), except that
    every ``realtime_bench`` test joins :data:`REALTIME_GROUP`."""
    for item in items:
        realtime = item.get_closest_marker("realtime_bench") is not None
        group = REALTIME_GROUP if realtime else item.nodeid.split("::", 1)[0]
        item.add_marker(pytest.mark.xdist_group(group))


@pytest.hookimpl(trylast=True)  # after xdist's hook, which puts the group into the node id
def pytest_collection_finish(session: pytest.Session) -> None:
    """Refuse to run when ``--dist loadgroup`` lost the groups: pytest 9.2 ignores what
    xdist 3.8 writes (pytest-xdist#1386), and the real-time tests would then run two at once
    without a word (the pin in pyproject.toml's dev extra keeps it from happening)."""
    lost = not all("@" in item.nodeid for item in session.items)
    if getattr(session.config.option, "loadgroup", False) and lost:  # set in xdist's workers
        raise pytest.UsageError("pytest-xdist's --dist loadgroup lost the test groups "
                                "(pytest-xdist#1386): pytest < 9.2 is needed")  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def bench_priority(request: pytest.FixtureRequest):
    """A module that starts real-time benches (``realtime_bench``) runs at the bench's own
    priority (smabench.bench.priority, as `smabench run`, `smabench mock` and the GUI's runtime
    do): tests that host a mock bench in-process, or start one, then see the devices they stand
    in for unslowed by unrelated load, as real devices are. Every other module runs at normal
    priority, as the analysis does on a user's machine: its minutes of CPU must not outrank the
    kernel's workers that carry a bench's bytes (nice -10 did, beside the real-time group).
    Where the system refuses (no CAP_SYS_NICE), the tests run at normal priority."""
    from smabench.bench.priority import raise_priority

    if any(True for _ in request.node.iter_markers("realtime_bench")):
        raise_priority()
    else:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, 0)
    yield


def flexinol_files() -> list[Path]:
    """The shipped measured loops plus any other load of the same wire in the shared folder."""
    files = {f.name: f for f in FLEXINOL_DIR.glob("filtered_data_*.txt")}
    if "SMABENCH_FLEXINOL_DIR" not in os.environ:
        files.update({f.name: f for f in SHARED_FLEXINOL_DIR.glob("filtered_data_*.txt")})
    assert files, f"no measured loops in {FLEXINOL_DIR} (set SMABENCH_FLEXINOL_DIR)"
    return [files[name] for name in sorted(files)]


@pytest.fixture
def run_cli():
    """Run ``smabench ARGS`` in a subprocess; returns CompletedProcess with text output."""

    def run(*args: str, check: bool = False) -> subprocess.CompletedProcess:
        proc = subprocess.run(
            [sys.executable, "-m", "smabench.cli", *map(str, args)],
            capture_output=True,
            text=True,
            cwd=REPO,
            timeout=300,
        )
        if check and proc.returncode != 0:
            raise AssertionError(f"smabench {' '.join(map(str, args))} failed:\n{proc.stderr}")
        return proc

    return run


@pytest.fixture
def cli_in_process(capsys):
    """Run ``smabench ARGS`` through ``smabench.cli.main`` in this process (no interpreter start,
    no imports again: for the unit tier); returns a CompletedProcess like :func:`run_cli`.
    An exception main does not turn into exit 2 propagates (a traceback fails the test)."""
    from smabench.cli import main

    def run(*args: str, check: bool = False) -> subprocess.CompletedProcess:
        capsys.readouterr()
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:  # argparse: --help, usage errors
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
        out = capsys.readouterr()
        proc = subprocess.CompletedProcess(list(args), code, out.out, out.err)
        if check and code != 0:
            raise AssertionError(f"smabench {' '.join(map(str, args))} failed:\n{out.err}")
        return proc

    return run


@pytest.fixture
def cli(cli_in_process):
    """``smabench`` in this process (the subprocess fixture costs seconds on a busy machine)."""
    return cli_in_process


@pytest.fixture(scope="module")
def shared_bench(qapp, tmp_path_factory, request):
    """The GUI test module's one window on the mock bench at the module's ``MOCK_SPEED``
    (:class:`gui_support.SharedBench`): a runtime and a mock started once, not per test."""
    from gui_support import SharedBench

    bench = SharedBench(tmp_path_factory.mktemp("bench") / "sessions", request.module.MOCK_SPEED)
    yield bench
    bench.close()


@pytest.fixture
def bench_win(request, qtbot, shared_bench, tmp_path):
    """That window as a fresh one for this test; closed after the module's last test using it."""
    from gui_support import last_to_use

    qtbot.waitExposed(shared_bench.w)
    yield shared_bench.for_test(qtbot, tmp_path / "sessions")
    if last_to_use(request, "bench_win"):
        shared_bench.close()


@pytest.fixture(autouse=True)
def gui_settings_store(request, tmp_path_factory):
    """GUI tests: the window's remembered entries (QSettings) in a folder of the test's own,
    never the user's ~/.config, and none left from another test."""
    if not request.module.__name__.startswith("test_gui"):
        yield None
        return
    from PySide6 import QtCore

    where = tmp_path_factory.mktemp("qsettings")
    QtCore.QSettings.setPath(QtCore.QSettings.Format.IniFormat,
                             QtCore.QSettings.Scope.UserScope, str(where))  # fmt: skip
    yield where

