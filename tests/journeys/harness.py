"""Journey tests: each test is one path a lab engineer walks, through the *installed* console
script only.

Once per test run (shared by the pytest-xdist workers through a lock file) the checkout's files
are copied to a clean folder and installed with ``pip install`` into a fresh virtual environment,
as a new user would (`pip install .`). Its third-party dependencies (and pandas, what a user
reads our CSV with) are not downloaded again: a ``.pth`` line puts the interpreter's own
site-packages (the project venv's, which ``make`` filled from ``pyproject.toml``) after the fresh
venv's; smabench itself, its package data and its console script come only from the fresh
install (the project venv's editable ``.pth`` hooks are not run from a path added that way).
Every command then runs as ``VENV/bin/smabench ...`` in a subprocess whose working
directory is a temporary folder, with no ``PYTHONPATH``: the checkout's modules cannot be
imported by accident (:func:`installed` checks where ``smabench`` comes from).

``SMABENCH_JOURNEY_VENV=/path``: use (and, when empty, create) that venv instead of a new one per
run; a developer's shortcut while writing a journey, never set in CI.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTALL_TIMEOUT_S = 900.0
COMMAND_TIMEOUT_S = 300.0


def source_files(repo: Path) -> list[Path]:
    """The files a clone of the checkout has (tracked, plus new files not ignored)."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-co", "--exclude-standard", "-z"],
            cwd=repo, capture_output=True, check=True, timeout=60,
        ).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        files = (p for p in repo.rglob("*") if p.is_file() and ".venv" not in p.parts)
        return [p.relative_to(repo) for p in files]
    return [Path(name) for name in out.decode().split("\0") if name and (repo / name).is_file()]


def install(venv: Path, work: Path) -> None:
    """``pip install`` a clean copy of the checkout into a fresh venv at ``venv``."""
    src = work / "src"
    shutil.rmtree(src, ignore_errors=True)
    for rel in source_files(REPO):
        dest = src / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, dest)
    shutil.rmtree(venv, ignore_errors=True)
    # no pip of its own: the project venv's pip and setuptools (through the .pth) install into it
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)  # fmt: skip
    python = str(venv / "bin" / "python")
    purelib = "import sysconfig; print(sysconfig.get_path('purelib'))"
    fresh = subprocess.run([python, "-c", purelib], capture_output=True, text=True, check=True,
                           timeout=60).stdout.strip()  # fmt: skip
    deps = sysconfig.get_path("purelib")  # this interpreter's: the project venv's dependencies
    (Path(fresh) / "zz-project-dependencies.pth").write_text(deps + "\n")
    proc = subprocess.run(
        [python, "-m", "pip", "install", "-q", "--disable-pip-version-check", "--no-deps",
         "--no-build-isolation", str(src)],
        capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S,
    )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"pip install of the checkout failed:\n{proc.stdout}\n{proc.stderr}")
    (venv / ".journey-ok").write_text("installed\n")


@dataclass(frozen=True)
class Installed:
    """The installed smabench: run its console script like a user at a shell."""

    venv: Path
    home: Path  # a scratch folder shared by the run; each test gets its own cwd under tmp_path

    @property
    def script(self) -> Path:
        return self.venv / "bin" / "smabench"

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    def env(self, extra: dict[str, str] | None = None) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "SMABENCH_"))}
        env.update(QT_QPA_PLATFORM="offscreen", HOME=str(self.home), PATH=f"{self.venv / 'bin'}"
                   f":{os.environ.get('PATH', '/usr/bin:/bin')}", MPLBACKEND="Agg")  # fmt: skip
        env.update(extra or {})
        return env

    def run(
        self,
        *args: object,
        cwd: Path,
        timeout_s: float = COMMAND_TIMEOUT_S,
        input_text: str | None = None,
        env: dict[str, str] | None = None,
    ) -> subprocess.CompletedProcess:
        """``smabench ARGS`` in ``cwd``; output as text, never raises on a non-zero exit."""
        return subprocess.run(
            [str(self.script), *map(str, args)], cwd=cwd, capture_output=True, text=True,
            timeout=timeout_s, input=input_text, env=self.env(env),
            stdin=None if input_text is not None else subprocess.DEVNULL,
        )  # fmt: skip

    def ok(self, *args: object, cwd: Path, **kw) -> subprocess.CompletedProcess:
        """``smabench ARGS`` that must succeed (exit 0, no traceback)."""
        proc = self.run(*args, cwd=cwd, **kw)
        assert proc.returncode == 0, (
            f"smabench {' '.join(map(str, args))} -> exit {proc.returncode}\n"
            f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
        )
        assert "Traceback" not in proc.stderr, proc.stderr
        return proc

    def usage_error(self, *args: object, cwd: Path, **kw) -> str:
        """``smabench ARGS`` that must be refused as bad input: exit 2 and one line on stderr,
        no traceback. Returns that line."""
        proc = self.run(*args, cwd=cwd, **kw)
        lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert proc.returncode == 2, (
            f"smabench {' '.join(map(str, args))} -> exit {proc.returncode}, want 2\n"
            f"stdout:\n{proc.stdout[-2000:]}\nstderr:\n{proc.stderr[-3000:]}"
        )
        assert len(lines) == 1 and "Traceback" not in proc.stderr, (
            f"want one line on stderr, got {len(lines)}:\n{proc.stderr[-3000:]}"
        )
        return lines[0]

    def py(self, code: str, *args: object, cwd: Path) -> subprocess.CompletedProcess:
        """The venv's python (a user's own script, e.g. pandas on an export)."""
        proc = subprocess.run(
            [str(self.python), "-c", code, *map(str, args)], cwd=cwd, capture_output=True,
            text=True, timeout=COMMAND_TIMEOUT_S, env=self.env(),
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        return proc


@dataclass(frozen=True)
class Recordings:
    """Sessions recorded once per test run through the installed ``smabench run --mock`` (shared
    by the xdist workers: the first to ask records, the others wait and reuse)."""

    installed: Installed
    root: Path

    def mock(self, name: str, *run_args: object, timeout_s: float = 600.0) -> Path:
        """``smabench run --mock RUN_ARGS --out ROOT --session-id NAME``, once; returns the
        session folder (completed, checked)."""
        folder = self.root / name
        with open(self.root / f"{name}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (folder / ".journey-ok").exists():
                shutil.rmtree(folder, ignore_errors=True)
                self.installed.ok(
                    "run", "--mock", *run_args, "--out", self.root, "--session-id", name,
                    "--quiet", cwd=self.root, timeout_s=timeout_s,
                )  # fmt: skip
                (folder / ".journey-ok").write_text("recorded\n")
        return folder


def installed_once(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """smabench installed from a clean copy of this checkout into a fresh venv, once per test
    run: every xdist worker and both folders that use it (journeys, faults) share it through a
    lock. ``SMABENCH_JOURNEY_VENV`` names a venv to reuse while developing."""
    chosen = os.environ.get("SMABENCH_JOURNEY_VENV")
    shared = shared_dir(tmp_path_factory)
    venv = Path(chosen) if chosen else shared / "journey-venv"
    with open(shared / "journey-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one install; the other workers wait for it
        if not (venv / ".journey-ok").exists():
            install(venv, shared / "journey-build")
    home = shared / "journey-home"
    home.mkdir(exist_ok=True)
    inst = Installed(venv=venv, home=home)
    where = inst.py("import smabench; print(smabench.__file__)", cwd=home).stdout.strip()
    assert Path(where).resolve().is_relative_to(venv.resolve()), (
        f"smabench imported from {where}, not from the journey venv"
    )
    return inst


def cycles_session(recordings: Recordings, load_kg: float, *, thermocouple: bool = False,
                   cycles: int = 4, seed: int = 0) -> Path:  # fmt: skip
    """A nominal heating-cycles session at ``load_kg`` from the mock bench (1.4 A, 5× speed)."""
    name = f"cycles-{load_kg:g}kg{'-tc' if thermocouple else ''}-{cycles}c-s{seed}"
    extra = ["--mock-thermocouple"] if thermocouple else []
    allow = ["--allow-high-stress"] if load_kg > 2.0 else []
    return recordings.mock(
        name, "--load-kg", load_kg, "--protocol", "cycles", "--cycles", cycles, "--current-a",
        1.4, "--mock-speed", 5, "--mock-seed", seed, *extra, *allow,
    )  # fmt: skip


def shared_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder shared by every xdist worker of this run (the parent of each worker's temp)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
