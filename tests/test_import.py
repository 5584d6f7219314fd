"""Import of real exports: metadata, units, quoted numbers, separators, decimal commas, voltage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smabench.importer import TextImportError, import_text, sniff_layout
from smabench.sessions import load_session

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "flexinol-instron-raw"

RAW_EXPORT = """Test : Start of hold value,"100.00000",MPa

Time,Extension,Load,Temperature: Chamber 3119-600 1 1,Tensile strain (Extension),Tensile stress
(s),(mm),(N),(C),(mm/mm),(MPa)
"0.00000","1.20676","0.46379","29.11588","0.00000","4.06799"
"0.10000","1.20670","0.46804","29.11588","0.00000","4.10529"
"0.20000","1.20674","0.48410","29.21588","0.00000","4.24617"
"""


def test_raw_testing_machine_export_layout():
    lay = sniff_layout(RAW_EXPORT)
    assert lay.separator == "comma" and lay.decimal == "." and lay.quoted
    assert lay.first_data_line == 5 and lay.n_fields == 6
    assert lay.header[0] == "Time" and lay.header[3].startswith("Temperature")
    assert lay.units == ["(s)", "(mm)", "(N)", "(C)", "(mm/mm)", "(MPa)"]
    assert lay.metadata == ['Test : Start of hold value,"100.00000",MPa']


def test_raw_export_imports(tmp_path):
    src = tmp_path / "raw.csv"
    src.write_text(RAW_EXPORT)
    out = import_text(src, "t_s,position_mm,skip,temperature_C,skip,stress_MPa", tmp_path / "s")
    s = load_session(out)
    assert np.allclose(s.data["t_s"], [0.0, 0.1, 0.2])
    assert np.allclose(s.data["temperature_C"], [29.11588, 29.11588, 29.21588])
    meta = json.loads((out / "session.json").read_text())
    assert meta["source_layout"]["units"][1] == "(mm)"
    assert meta["source_layout"]["metadata"]


@pytest.mark.parametrize(
    ("text", "separator"),
    [
        ("T;x\n30,5;0,0125\n31,0;0,0130\n31,5;0,0140\n", "semicolon"),
        ("T\tx\n30,5\t0,0125\n31,0\t0,0130\n31,5\t0,0140\n", "tab"),
        ("# a comment\n30,5 0,0125\n31,0 0,0130\n31,5 0,0140\n", "whitespace"),
    ],
)
def test_decimal_commas_are_found(tmp_path, text, separator):
    assert sniff_layout(text).separator == separator
    assert sniff_layout(text).decimal == ","
    src = tmp_path / "dc.txt"
    src.write_text(text)
    out = import_text(src, "temperature_C,strain", tmp_path / "s", wire_length_mm=100.0)
    s = load_session(out)
    assert np.allclose(s.data["temperature_C"], [30.5, 31.0, 31.5])
    assert np.allclose(s.data["position_mm"], [1.25, 1.30, 1.40])


def test_comma_separated_decimal_commas_need_the_flag(tmp_path):
    # "30,5,0,0125" is ambiguous; with quotes and --decimal , it is not
    text = '"30,5","0,0125"\n"31,0","0,0130"\n"31,5","0,0140"\n'
    src = tmp_path / "q.csv"
    src.write_text(text)
    out = import_text(src, "temperature_C,strain", tmp_path / "s", wire_length_mm=100.0,
                      decimal=",")  # fmt: skip
    assert np.allclose(load_session(out).data["temperature_C"], [30.5, 31.0, 31.5])


def test_voltage_driven_data_imports(tmp_path):
    src = tmp_path / "v.csv"
    t = np.arange(0, 5, 0.1)
    v = np.where(t < 2.5, 0.6, 0.0)
    pos = 0.5 * np.exp(-t)
    src.write_text("t_s,voltage_V,position_mm\n" + "\n".join(
        f"{a:.2f},{b:.3f},{c:.5f}" for a, b, c in zip(t, v, pos, strict=True)))  # fmt: skip
    out = import_text(src, "t_s,voltage_V,position_mm", tmp_path / "s")
    meta = json.loads((out / "session.json").read_text())
    assert meta["kind"] == "voltage_driven"
    assert np.allclose(load_session(out).data["voltage_V"], v)


def test_bad_files_are_one_clear_error(tmp_path, cli_in_process):
    run_cli = cli_in_process
    src = tmp_path / "bad.csv"
    src.write_text("a,b\n1,2\nthree,4\n")
    with pytest.raises(TextImportError, match="no table|line 3"):
        import_text(src, "temperature_C,position_mm", tmp_path / "s")
    src.write_text("1,2,3\n4,5,6\n7,8,9\n")
    with pytest.raises(TextImportError, match="3 columns"):
        import_text(src, "temperature_C,position_mm", tmp_path / "s2")
    (tmp_path / "bin").write_bytes(b"\0\1\2")
    proc = run_cli("import", str(tmp_path / "bin"), "--columns", "temperature_C,position_mm",
                   "--out", str(tmp_path / "s3"))  # fmt: skip
    assert proc.returncode == 2 and "not a text file" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "s3").exists()


def test_preview_prints_the_layout(tmp_path, cli_in_process):
    run_cli = cli_in_process
    src = tmp_path / "raw.csv"
    src.write_text(RAW_EXPORT)
    proc = run_cli("import", str(src), "--preview")
    assert proc.returncode == 0
    assert "separator: comma" in proc.stdout and "(mm/mm)" in proc.stdout
    assert "data from line 5" in proc.stdout


@pytest.mark.slow  # two exports of > 30 000 rows
@pytest.mark.skipif(not SHARED.is_dir(), reason="shared measured data not beside the repo")
def test_the_measured_raw_exports_import(tmp_path):
    """Another lab's raw exports as the testing machine wrote them (shared/data)."""
    for mpa in (100, 172):
        src = SHARED / f"flexinol_isobaric_trained_{mpa}MPa.csv"
        out = import_text(src, "t_s,position_mm,skip,temperature_C,skip,stress_MPa",
                          tmp_path / f"s{mpa}")  # fmt: skip
        s = load_session(out)
        assert len(s.data["t_s"]) > 30_000
        assert np.min(s.data["temperature_C"]) > 20.0 and np.max(s.data["temperature_C"]) < 140.0
        held = s.data["stress_MPa"][s.data["t_s"] > 600.0]
        assert abs(np.median(held) - mpa) < 0.05 * mpa


def test_a_large_import_streams_with_progress_and_keeps_every_value(tmp_path, monkeypatch):
    """The reading and the writing of the session both report their progress; every row and
    every value arrives (the written text reads back bit-identical to what was parsed)."""
    import smabench.importer as importer
    import smabench.sessions as sessions

    monkeypatch.setattr(importer, "PROGRESS_MIN_BYTES", 0)
    monkeypatch.setattr(importer, "PROGRESS_S", 0.0)
    monkeypatch.setattr(importer, "WRITE_PROGRESS_MIN_ROWS", 0)
    monkeypatch.setattr(sessions, "PROGRESS_S", 0.0)
    monkeypatch.setattr(sessions, "WRITE_BLOCK_ROWS", 5_000)
    n = 40_000
    rng = np.random.default_rng(3)
    temp_c = np.round(rng.uniform(20, 90, n), 3)
    strain = rng.uniform(0, 0.05, n)  # 17 significant digits: × wire length is not tidy either
    src = tmp_path / "big.csv"
    rows = zip(temp_c.tolist(), strain.tolist(), strict=True)
    src.write_text("Time,Temperature,Strain\n"
                   + "".join(f"{k * 0.01:.2f},{t!r},{e!r}\n" for k, (t, e) in enumerate(rows)))
    read: list[tuple[int, int, int]] = []
    written: list[tuple[int, int]] = []
    out = import_text(src, "t_s,temperature_C,strain", tmp_path / "s", wire_length_mm=100.0,
                      progress=lambda *a: read.append(a),
                      write_progress=lambda *a: written.append(a))  # fmt: skip
    assert read and read[-1][0] == n and read[-1][1] == read[-1][2] == src.stat().st_size
    assert len(written) >= n // 5_000 - 1 and all(total == n for _, total in written)
    assert [done for done, _ in written] == sorted({done for done, _ in written})
    s = load_session(out)
    np.testing.assert_array_equal(s.data["temperature_C"], temp_c)
    np.testing.assert_array_equal(s.data["position_mm"].view(np.int64),
                                  (strain * 100.0).view(np.int64))  # fmt: skip
