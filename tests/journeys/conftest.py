"""Fixtures of the journey tests (the harness is :mod:`journeys.harness`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from journeys.harness import Installed, Recordings, installed_once, shared_dir


@pytest.fixture(scope="session")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """smabench installed from this checkout into a fresh venv, once per test run."""
    return installed_once(tmp_path_factory)


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


