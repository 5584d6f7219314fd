"""Fixtures of the journey tests (the harness is :mod:`journeys.harness`)."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

import pytest

from journeys.harness import Installed, Recordings, install, shared_dir


@pytest.fixture(scope="session")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """smabench installed from this checkout into a fresh venv, once per test run."""
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
    where = inst.py("import smabench, sys; print(smabench.__file__)", cwd=home).stdout.strip()
    assert Path(where).resolve().is_relative_to(venv.resolve()), (
        f"smabench imported from {where}, not from the journey venv"
    )
    return inst


@pytest.fixture
def cwd(tmp_path: Path) -> Path:
    """The folder a journey's commands run in (its relative paths land there)."""
    work = tmp_path / "work"
    work.mkdir()
    return work


@pytest.fixture(scope="session")
def recordings(installed: Installed, tmp_path_factory: pytest.TempPathFactory) -> Recordings:
    root = shared_dir(tmp_path_factory) / "journey-recordings"
    root.mkdir(exist_ok=True)
    return Recordings(installed=installed, root=root)


