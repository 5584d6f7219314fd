"""fit --holdout/--test and predict: a fitted model tested where it was not fitted, and applied
to another session from its JSON."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from smabench.physics.identify import FitError, fit_from_document, fit_loop, model_document
from smabench.physics.model_bench import excitation_c

REPO = Path(__file__).resolve().parent.parent
S2 = REPO / "sessions" / "mock-cycles-2kg-latent-heat"
S1 = REPO / "sessions" / "mock-cycles-1kg"


@pytest.fixture(scope="module")
def loop():
    d = np.loadtxt(REPO / "sessions/samples/flexinol-isobaric/filtered_data_100MPa.txt")
    return d[:, 0], d[:, 1] * 55.0


@pytest.mark.parametrize(
    "model", ["1", "2", "sigmoid", pytest.param("preisach", marks=pytest.mark.slow)]  # ~2 s fit
)
def test_document_rebuilds_the_same_model(loop, model):
    t, y = loop
    fit = fit_loop(t, y, model)
    doc = json.loads(json.dumps(model_document(fit)))  # through JSON text
    again = fit_from_document(doc)
    seq = excitation_c(float(t.min()), float(t.max()), 3000)  # reversals: the memory path too
    assert np.allclose(again.predict(seq), fit.predict(seq), atol=1e-9)


def test_broken_documents_are_refused():
    with pytest.raises(FitError, match="not a fitted model"):
        fit_from_document({"model": "1"})
    with pytest.raises(FitError, match="broken"):
        fit_from_document({"document": "smabench fitted loop model", "version": 1,
                           "model": "sigmoid", "state": {"ym_mm": 1.0}})  # fmt: skip


@pytest.mark.slow  # three `smabench` commands (in this process), each fits
def test_fit_holdout_and_test_then_predict(tmp_path, cli):
    run_cli = cli
    js = tmp_path / "fit.json"
    proc = run_cli("fit", S2, "--model", "sigmoid", "--holdout", "0.3", "--json", js)
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(js.read_text())
    assert rep["holdout"]["fraction"] == 0.3
    assert rep["holdout"]["n_points"] > 100
    # held out is honest: not better than where it was fitted by more than noise, and usable
    assert 0.2 < rep["holdout"]["nrmse_percent"] < 25.0
    proc = run_cli("fit", S2, "--model", "1", "--test", S1, "--json", tmp_path / "t.json")
    assert proc.returncode == 0, proc.stderr
    assert "nrmse_percent" in json.loads((tmp_path / "t.json").read_text())["test"]
    out = tmp_path / "pred.csv"
    proc = run_cli("predict", "--model", js, S1, "--out", out)
    assert proc.returncode == 0, proc.stderr
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t_s", "position_mm", "model_mm"]
    vals = np.array([[float(x) if x else np.nan for x in r] for r in rows[1:]])
    assert np.isfinite(vals[:, 2]).mean() > 0.95


def test_fit_and_predict_bad_input(tmp_path, cli_in_process):
    run_cli = cli_in_process  # refusals: the CLI's logic, in this process
    proc = run_cli("fit", S2, "--holdout", "0.95")
    assert proc.returncode == 2 and "0.05" in proc.stderr
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    proc = run_cli("predict", "--model", bad, S1, "--out", tmp_path / "p.csv")
    assert proc.returncode == 2 and "not JSON" in proc.stderr
    assert not (tmp_path / "p.csv").exists()


def test_fit_masks_rows_flagged_invalid_and_counts_them(tmp_path, cli_in_process):
    """Issue 24: a row the sensor flagged invalid is masked by its flag even when a (stale)
    position is still in it; the masked rows are counted, printed and in --json."""
    import shutil

    from smabench.sessions import FLAG_SENSOR_INVALID

    s = shutil.copytree(S1, tmp_path / "s")
    with open(s / "samples.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    fl, pos = rows[0].index("flags"), rows[0].index("position_mm")
    for k in (50, 51, 52, len(rows) // 2, len(rows) - 10):
        rows[k][fl] = str(int(rows[k][fl] or 0) | FLAG_SENSOR_INVALID)
    with open(s / "samples.csv", "w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    want = sum(1 for r in rows[1:] if not r[pos] or int(r[fl] or 0) & FLAG_SENSOR_INVALID)
    proc = cli_in_process("fit", s, "--model", "sigmoid", "--json", tmp_path / "f.json")
    assert proc.returncode == 0, proc.stderr
    rep = json.loads((tmp_path / "f.json").read_text())
    assert rep["n_masked"] == want >= 5
    assert rep["n_points"] == len(rows) - 1 - want
    assert f"{want} row(s) masked" in proc.stdout
