"""Journey: every real file we hold, imported as its instrument wrote it → fit → analyze →
characterize: the filtered Flexinol loops (shipped), the raw tensile-tester exports with their
loading ramp (``../shared/data``, beside the clone in CI; skipped when absent; their analyze is
``docs/analysis-flexinol-raw.md``'s block, run by ``test_docs.py``), a European file
(decimal commas and semicolons, made here from a filtered loop) and a thermocouple loop (a mock
recording with ``--mock-thermocouple``). `analyze` costs ~25 s of CPU per pair of loops: slow."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from journeys.harness import Installed, Recordings, cycles_session

REPO = Path(__file__).resolve().parents[2]
LOOPS = REPO / "sessions" / "samples" / "flexinol-isobaric"
SHARED = next((p for p in (REPO.parent / "shared" / "data", REPO.parents[1] / "shared" / "data")
               if p.is_dir()), None)  # fmt: skip
RAW = SHARED / "flexinol-instron-raw" if SHARED else None
needs_shared = pytest.mark.skipif(RAW is None or not RAW.is_dir(),
                                  reason="../shared/data is not beside this clone")  # fmt: skip
FILTERED_COLUMNS = "temperature_C,strain,stress_MPa"
RAW_COLUMNS = "t_s,position_mm,skip,temperature_C,skip,stress_MPa"  # Time, Extension, Load, ...


def _fit_and_characterize(installed: Installed, sessions: list[str], cwd: Path) -> dict:
    for s in sessions:
        fit = installed.ok("fit", s, "--model", "sigmoid", "--json", f"{s}-fit.json", cwd=cwd)
        assert json.loads((cwd / f"{s}-fit.json").read_text())["nrmse_percent"] < 10.0, fit.stdout
    installed.ok("characterize", *sessions, "--json", "c.json", cwd=cwd)
    return json.loads((cwd / "c.json").read_text())


@pytest.mark.slow
@pytest.mark.timeout(1200)  # analyze: ~25 s of CPU, minutes of wall time on a loaded machine
def test_filtered_flexinol_loops(installed: Installed, cwd: Path) -> None:
    for mpa in (100, 172):
        installed.ok("import", LOOPS / f"filtered_data_{mpa}MPa.txt", "--columns",
                     FILTERED_COLUMNS, "--wire-length-mm", 55, "--out", f"f{mpa}",
                     cwd=cwd)  # fmt: skip
    doc = _fit_and_characterize(installed, ["f100", "f172"], cwd)
    assert all(doc["phase_diagram"][k]["clausius_clapeyron"] for k in ("As", "Af", "Ms", "Mf"))
    proc = installed.ok("analyze", "f100", "f172", cwd=cwd, timeout_s=900)
    assert "stress" in proc.stdout


@pytest.fixture(scope="module")
def raw_sessions(installed: Installed, tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("raw")
    for mpa in (100, 172):
        installed.ok("import", RAW / f"flexinol_isobaric_trained_{mpa}MPa.csv", "--columns",
                     RAW_COLUMNS, "--out", f"r{mpa}", cwd=where)  # fmt: skip
    return where


@needs_shared
@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_raw_tensile_exports_import_fit_characterize(
    installed: Installed, raw_sessions: Path
) -> None:
    doc = _fit_and_characterize(installed, ["r100", "r172"], raw_sessions)
    assert [s["n_cycles"] for s in doc["sessions"]] and all(
        s["n_cycles"] >= 1 for s in doc["sessions"])  # fmt: skip
    # analyze on these exports (stress_shift, its slope, what was cut): the runnable block of
    # docs/analysis-flexinol-raw.md, run by test_docs.py (a minute of CPU: walked once, there)


def test_european_file(installed: Installed, cwd: Path) -> None:
    """Decimal commas and semicolons, a German header line, as a European lab's software writes."""
    rows = [ln.split() for ln in (LOOPS / "filtered_data_100MPa.txt").read_text().splitlines()
            if ln.strip()]  # fmt: skip
    text = "Temperatur;Dehnung;Spannung\n" + "".join(
        ";".join(v.replace(".", ",") for v in r) + "\n" for r in rows)  # fmt: skip
    (cwd / "eu.csv").write_text(text, encoding="utf-8")
    installed.ok("import", "eu.csv", "--columns", FILTERED_COLUMNS, "--wire-length-mm", 55,
                 "--out", "eu", cwd=cwd)  # fmt: skip
    installed.ok("fit", "eu", "--model", "sigmoid", "--json", "eu.json", cwd=cwd)
    doc = json.loads((cwd / "eu.json").read_text())
    assert doc["n_points"] == len(rows) and doc["nrmse_percent"] < 2.0, doc
    installed.ok("characterize", "eu", "--json", "c.json", cwd=cwd)
    cyc = json.loads((cwd / "c.json").read_text())["sessions"][0]["cycles"][0]
    assert 80.0 < cyc["As_C"] < 90.0, cyc


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_thermocouple_loop(installed: Installed, recordings: Recordings, cwd: Path) -> None:
    tc = cycles_session(recordings, 2.0, thermocouple=True)
    _fit_and_characterize(installed, [str(tc)], cwd)
    doc = json.loads((cwd / "c.json").read_text())
    assert doc["sessions"][0]["temperature_source"] == "measured"
    installed.ok("analyze", tc, cwd=cwd, timeout_s=900)
