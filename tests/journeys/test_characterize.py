"""Journeys: `characterize` on a campaign's folder of sessions as the README writes it (aborted and
incomplete steps among them), and the phase diagram from two mock loads."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from journeys.flaws import with_bench_flaws
from journeys.harness import Installed, Recordings, cycles_session

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

NOT_CC = "not a Clausius–Clapeyron slope"


def _first_heating_only(session: Path, out: Path) -> Path:
    """A copy of ``session`` cut after its first heating: no complete thermal cycle."""
    shutil.copytree(session, out)
    samples = out / "samples.csv"
    rows = list(csv.reader(samples.open(newline="")))
    col = rows[0].index("current_A")
    on = [k for k in range(1, len(rows)) if float(rows[k][col] or 0) > 0.2]
    cut = on[-1] if on else len(rows)
    first_off = next(k for k in range(on[0], len(rows)) if float(rows[k][col] or 0) <= 0.2)
    cut = min(cut, first_off + 20)
    with samples.open("w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows[:cut])
    (out / "cycles.csv").unlink(missing_ok=True)
    return out


@pytest.fixture(scope="module")
def campaign(recordings: Recordings, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A plan's output folder: two good steps, an aborted try of a step, an incomplete step."""
    root = tmp_path_factory.mktemp("plans-out") / "example"
    root.mkdir()
    s1, s2 = cycles_session(recordings, 1.0), cycles_session(recordings, 2.0)
    shutil.copytree(s1, root / "01-cycles-1kg")
    with_bench_flaws(s2, root / "02-cycles-2kg-try1", seed=2, abort_fraction=0.2)
    shutil.copytree(s2, root / "02-cycles-2kg-try2")
    _first_heating_only(s2, root / "03-incomplete-2kg")
    return root


@pytest.mark.slow
def test_characterize_a_campaign_folder_skips_aborted_and_incomplete(
    installed: Installed, campaign: Path, cwd: Path
) -> None:
    paths = sorted(campaign.glob("0*"))
    proc = installed.ok("characterize", *paths, "--json", "c.json", cwd=cwd)
    skipped = [ln for ln in proc.stderr.splitlines() if "skipped" in ln]
    assert len(skipped) == 2, proc.stderr
    assert any("02-cycles-2kg-try1" in ln and "aborted" in ln for ln in skipped), skipped
    assert any("03-incomplete-2kg" in ln and "no complete thermal cycle" in ln for ln in skipped)
    doc = json.loads((cwd / "c.json").read_text())
    done = [Path(s["session"]).name for s in doc["sessions"]]
    assert done == ["01-cycles-1kg", "02-cycles-2kg-try2"]
    assert {Path(s["session"]).name for s in doc["skipped"]} == {
        "02-cycles-2kg-try1", "03-incomplete-2kg"}  # fmt: skip


@pytest.mark.slow
def test_characterize_refuses_when_every_session_is_skipped(
    installed: Installed, campaign: Path, cwd: Path
) -> None:
    line = installed.usage_error("characterize", campaign / "03-incomplete-2kg", "--json", "c.json",
                                 cwd=cwd)  # fmt: skip
    assert "no complete thermal cycle" in line
    assert not (cwd / "c.json").exists()


@pytest.mark.slow
def test_phase_diagram_from_two_mock_loads_is_judged(
    installed: Installed, recordings: Recordings, cwd: Path
) -> None:
    s1, s2 = cycles_session(recordings, 1.0), cycles_session(recordings, 2.0)
    proc = installed.ok("characterize", s1, s2, "--json", "c.json", cwd=cwd)
    pd = json.loads((cwd / "c.json").read_text())["phase_diagram"]
    judged = 0
    for key in ("As", "Af", "Ms", "Mf"):
        entry = pd[key]
        slope = entry["slope_MPa_per_K"]
        assert "clausius_clapeyron" in entry, entry
        if slope is None or not 3.0 <= slope <= 20.0:
            assert entry["clausius_clapeyron"] is False, entry
            assert entry["why_not"], entry
            judged += 1
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("phase diagram"))
    if judged:
        assert NOT_CC in proc.stdout, proc.stdout
    for key in ("As", "Af", "Ms", "Mf"):
        if pd[key]["clausius_clapeyron"] is False:
            assert f"{key} " in line


REPO = Path(__file__).resolve().parents[2]
LOOPS = REPO / "sessions" / "samples" / "flexinol-isobaric"


def test_phase_diagram_of_real_loops_is_a_clausius_clapeyron_slope(installed: Installed,
                                                                    cwd: Path) -> None:
    """The shipped Flexinol loops at 100 and 172 MPa: about 8 MPa/K, no warning."""
    for mpa in (100, 172):
        installed.ok("import", LOOPS / f"filtered_data_{mpa}MPa.txt", "--columns",
                     "temperature_C,strain,stress_MPa", "--wire-length-mm", 55, "--out",
                     f"f{mpa}", cwd=cwd)  # fmt: skip
    proc = installed.ok("characterize", "f100", "f172", "--json", "c.json", cwd=cwd)
    pd = json.loads((cwd / "c.json").read_text())["phase_diagram"]
    for key in ("As", "Af", "Ms", "Mf"):
        assert 7.0 < pd[key]["slope_MPa_per_K"] < 9.0, pd[key]
        assert pd[key]["clausius_clapeyron"] is True, pd[key]
    assert NOT_CC not in proc.stdout
