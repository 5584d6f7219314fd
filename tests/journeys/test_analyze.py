"""Journey: record on the mock bench (real transports) → ``smabench analyze``.

- nominal recordings (the shipped samples, fresh ones at 1, 2 and 4 kg with and without the
  thermocouple, and a copy with a real bench's flaws) come out ``none``: nothing is hidden in
  the mock, so any cause named is a wrong name and ``unexplained`` means our own model misses
  the plant;
- a hidden effect (``--mock-effect``) comes out under its name.

A tensile tester's raw exports imported as exported → ``smabench analyze`` (``stress_shift``, the
slope against the loops' own shift, what was cut) is the runnable block of
``docs/analysis-flexinol-raw.md``, which ``test_docs.py`` runs and checks: walked once, there.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from journeys.flaws import with_bench_flaws
from journeys.harness import REPO, Installed, Recordings, cycles_session

# minutes each on a loaded machine
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900), pytest.mark.realtime_bench]

CYCLES = 4  # as the other journeys record them (shared); the first trains every fold


def analyze(installed: Installed, cwd: Path, *sessions: Path, timeout_s: float = 600.0
            ) -> tuple[dict, str]:  # fmt: skip
    proc = installed.ok("analyze", *sessions, "--json", "a.json", "--workers", "1", cwd=cwd,
                        timeout_s=timeout_s)  # fmt: skip
    return json.loads((cwd / "a.json").read_text()), proc.stdout


def shipped(name: str, cwd: Path) -> Path:
    """A copy of a shipped sample session (the installed package has no sessions/)."""
    return Path(shutil.copytree(REPO / "sessions" / name, cwd / name))


@pytest.mark.parametrize("name", ["mock-cycles-1kg", "mock-cycles-4kg"])
def test_shipped_nominal_samples_come_out_none(installed: Installed, cwd: Path, name: str):
    doc, out = analyze(installed, cwd, shipped(name, cwd))
    assert doc["cause"] == "none", (doc["reason"], out)


@pytest.mark.parametrize(
    ("load_kg", "thermocouple"),
    [(1.0, False), (2.0, True), (2.0, False), (4.0, True)],
)
def test_fresh_nominal_recordings_come_out_none(
    installed: Installed, recordings: Recordings, cwd: Path, load_kg: float, thermocouple: bool
) -> None:
    session = cycles_session(recordings, load_kg, thermocouple=thermocouple, cycles=CYCLES)
    doc, out = analyze(installed, cwd, session)
    assert doc["cause"] == "none", (doc["reason"], out)


@pytest.mark.xfail(
    strict=True,
    reason="open: the flawed copy starts 0.8 s into the first heating (partial first cycle); the "
    "analysis's heat balance starts the wire at the room's temperature, fully martensitic, so "
    "the first cycle is mispredicted (baseline held-out 0.41 mm; 0.17 mm since that cycle only "
    "trains, TRAINING_ONLY: it still bends every fold's fit): the start state must be fitted "
    "from the first samples",
)
def test_flawed_nominal_recording_is_masked_and_comes_out_none(
    installed: Installed, recordings: Recordings, cwd: Path, tmp_path: Path
) -> None:
    clean = cycles_session(recordings, 2.0, thermocouple=True, cycles=CYCLES)
    flawed = with_bench_flaws(clean, tmp_path / "flawed", seed=5)
    doc, out = analyze(installed, cwd, flawed)
    masked = doc["sessions"][0]["masked_rows"]
    assert masked >= 3, doc["sessions"][0]
    assert f"{masked} row" in out and "masked" in out, out
    assert doc["cause"] == "none", (doc["reason"], out)


def test_a_hidden_effect_is_named(installed: Installed, recordings: Recordings, cwd: Path):
    session = recordings.mock(
        "cycles-2kg-latent", "--load-kg", 2.0, "--protocol", "cycles", "--cycles", 4,
        "--current-a", 1.4, "--mock-speed", 5, "--mock-seed", 1,
        "--mock-effect", "latent_heat=24000",
    )  # fmt: skip
    doc, out = analyze(installed, cwd, session)
    assert doc["cause"] == "latent_heat", (doc["reason"], out)


