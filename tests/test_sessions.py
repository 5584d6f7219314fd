"""Session contract: writer, crash-safety, loader checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from smabench.sessions import (
    COLUMNS,
    SessionError,
    SessionWriter,
    load_session,
    read_samples_csv,
    write_session,
)


def test_writer_header_order_and_roundtrip(tmp_path):
    folder = tmp_path / "s1"
    with SessionWriter(folder, {"load_kg": 2.0}) as w:
        for i in range(5):
            w.append(
                {
                    "t_s": i * 0.005,
                    "current_A": 0.5,
                    "position_mm": 1.0 + i,
                    "mode": "pid",
                    "cycle": 0,
                    "flags": 0,
                }
            )
    header = (folder / "samples.csv").read_text().splitlines()[0]
    assert header == ",".join(COLUMNS)
    s = load_session(folder)
    assert len(s) == 5
    np.testing.assert_allclose(s.data["position_mm"], [1, 2, 3, 4, 5])
    assert np.isnan(s.data["voltage_V"]).all()
    assert list(s.data["mode"]) == ["pid"] * 5
    meta = json.loads((folder / "session.json").read_text())
    assert meta["status"] == "completed" and meta["rows"] == 5 and meta["load_kg"] == 2.0


def test_writer_records_abort_reason(tmp_path):
    folder = tmp_path / "s2"
    with pytest.raises(RuntimeError), SessionWriter(folder, {}) as w:
        w.append({"t_s": 0.0, "current_A": 0.0, "position_mm": 0.0})
        raise RuntimeError("sensor lost")
    meta = json.loads((folder / "session.json").read_text())
    assert meta["status"] == "aborted" and "sensor lost" in meta["end_reason"]
    assert len(load_session(folder)) == 1


def test_unclosed_session_is_readable_and_truncated_tail_dropped(tmp_path):
    folder = tmp_path / "s3"
    w = SessionWriter(folder, {}, flush_s=0.0)
    for i in range(10):
        w.append({"t_s": float(i), "current_A": 1.0, "position_mm": float(i)})
    # simulate a crash in the middle of writing a row
    w._fh.write("10.0,,1.0")
    w._fh.flush()
    s = load_session(folder)
    assert len(s) == 10
    assert json.loads((folder / "session.json").read_text())["status"] == "running"


def test_write_session_refuses_existing_and_leaves_nothing_on_error(tmp_path):
    out = tmp_path / "s4"
    write_session(out, {}, {"t_s": [0.0, 1.0], "current_A": [0, 1], "position_mm": [1.0, 2.0]})
    with pytest.raises(SessionError, match="already exists"):
        write_session(out, {}, {"t_s": [0.0], "current_A": [0], "position_mm": [1.0]})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s4"]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("t_s,current_A\n0,1\n", "no position_mm"),
        ("t_s,position_mm\n0,1\n", "needs t_s and current_A"),
        ("t_s,current_A,position_mm\n0,1,abc\n", "line 2.*'abc'"),
        ("t_s,current_A,position_mm\n0,1\n0,1,2\n", "line 2 has 2 cells"),
        ("", "empty file"),
    ],
)
def test_loader_rejects_bad_csv(tmp_path, text, match):
    f = tmp_path / "x.csv"
    f.write_text(text)
    with pytest.raises(SessionError, match=match):
        load_session(f)


def test_thermometer_csv_without_time_gets_row_index(tmp_path):
    f = tmp_path / "loop.csv"
    f.write_text("temperature_C,position_mm\n30,2.0\n40,2.1\n50,1.0\n")
    s = load_session(f)
    assert s.is_thermometer_loop
    np.testing.assert_array_equal(s.data["t_s"], [0, 1, 2])
    assert s.meta["t_s_is_row_index"] is True
    assert read_samples_csv(f)["position_mm"][2] == 1.0


def test_export_all_and_chosen_columns(tmp_path, run_cli):
    folder = tmp_path / "s"
    write_session(
        folder,
        {},
        {
            "t_s": [0.0, 0.5],
            "current_A": [0.1, 0.2],
            "position_mm": [1.5, 1.25],
            "mode": ["pid", "ff"],
        },
    )
    out = tmp_path / "all.csv"
    run_cli("export", folder, "--out", out, check=True)
    lines = out.read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and len(lines) == 3
    out2 = tmp_path / "some.csv"
    run_cli("export", folder, "--out", out2, "--columns", "position_mm,t_s,mode", check=True)
    assert out2.read_text().splitlines() == ["position_mm,t_s,mode", "1.5,0.0,pid", "1.25,0.5,ff"]
    proc = run_cli("export", folder, "--out", tmp_path / "bad.csv", "--columns", "nope")
    assert proc.returncode == 2 and "unknown column" in proc.stderr
    assert not (tmp_path / "bad.csv").exists()
