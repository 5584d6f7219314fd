"""Journey: record on the mock bench → export → pandas → fit with every model → plot, on a
recording with a real bench's flaws; and the command line's own basics (`--version`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from journeys.flaws import with_bench_flaws
from journeys.harness import Installed, Recordings, cycles_session

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

MODELS = ("1", "2", "preisach", "sigmoid")


@pytest.fixture(scope="module")
def flawed_2kg(recordings: Recordings, tmp_path_factory: pytest.TempPathFactory) -> Path:
    clean = cycles_session(recordings, 2.0)
    return with_bench_flaws(clean, tmp_path_factory.mktemp("flawed") / "s2kg", seed=3)


def test_version(installed: Installed, cwd: Path) -> None:
    proc = installed.ok("--version", cwd=cwd)
    assert proc.stdout.startswith("smabench ") and proc.stdout.split()[1][0].isdigit()


def test_export_then_pandas_keeps_integers(installed: Installed, flawed_2kg: Path, cwd: Path):
    installed.ok("export", flawed_2kg, "--out", "s.csv", cwd=cwd)
    dtypes = installed.py(
        "import pandas as pd, json; d = pd.read_csv('s.csv');"
        "print(json.dumps({c: str(t) for c, t in d.dtypes.items()}))",
        cwd=cwd,
    ).stdout
    kinds = json.loads(dtypes)
    assert kinds["t_s"] == "float64" and kinds["position_mm"] == "float64"
    assert kinds["cycle"] == "int64", kinds
    assert kinds["flags"] == "int64", kinds


@pytest.mark.parametrize("model", MODELS)
def test_fit_every_model_on_a_flawed_recording(
    installed: Installed, flawed_2kg: Path, cwd: Path, model: str
) -> None:
    proc = installed.ok(
        "fit", flawed_2kg, "--model", model, "--json", "fit.json", "--plot", "fit.png", cwd=cwd
    )
    result = json.loads((cwd / "fit.json").read_text())
    assert result["nrmse_percent"] < 15.0, result
    assert (cwd / "fit.png").stat().st_size > 10_000
    assert "invalid" in proc.stdout  # the masked sensor-invalid rows are counted, not hidden
