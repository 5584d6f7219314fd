"""Session contract: writer, crash-safety, loader checks."""

from __future__ import annotations

import csv
import json
import math

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
    with open(folder / "samples.csv", "a", encoding="utf-8") as fh:
        fh.write("10.0,,1.0")
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


def test_export_all_and_chosen_columns(tmp_path, cli):
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
    cli("export", folder, "--out", out, check=True)
    lines = out.read_text().splitlines()
    assert lines[0] == ",".join(COLUMNS) and len(lines) == 3
    out2 = tmp_path / "some.csv"
    cli("export", folder, "--out", out2, "--columns", "position_mm,t_s,mode", check=True)
    assert out2.read_text().splitlines() == ["position_mm,t_s,mode", "1.5,0.0,pid", "1.25,0.5,ff"]
    proc = cli("export", folder, "--out", tmp_path / "bad.csv", "--columns", "nope")
    assert proc.returncode == 2 and "unknown column" in proc.stderr
    assert not (tmp_path / "bad.csv").exists()


# ---------------------------------------------------------------- issue 12 §8 / issue 15 pieces
def _mode(path) -> int:
    import os
    import stat

    return stat.S_IMODE(os.stat(path).st_mode)


def test_every_written_file_respects_the_umask(tmp_path, cli):
    """session.json, samples.csv, cycles.csv, exports and fit JSON all get 0666 & ~umask."""
    import os

    from smabench.sessions import atomic_write, atomic_write_json

    old = os.umask(0o022)
    try:
        folder = tmp_path / "s"
        with SessionWriter(folder, {"load_kg": 1.0}) as w:
            w.append({"t_s": 0.0, "current_A": 0.0, "position_mm": 1.0, "cycle": 0})
        for name in ("session.json", "samples.csv", "cycles.csv"):
            assert _mode(folder / name) == 0o644, name
        assert _mode(atomic_write_json(tmp_path / "a.json", {"x": 1})) == 0o644
        assert _mode(atomic_write(tmp_path / "b.bin", b"\x00\x01")) == 0o644
        os.umask(0o077)
        assert _mode(atomic_write(tmp_path / "c.txt", "private")) == 0o600
        os.umask(0o022)
        cli("export", folder, "--out", tmp_path / "e.csv", check=True)
        assert _mode(tmp_path / "e.csv") == 0o644
    finally:
        os.umask(old)
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_atomic_write_leaves_the_old_file_on_error(tmp_path):
    from smabench.sessions import atomic_write

    target = atomic_write(tmp_path / "x.txt", "old\n")

    def boom(fh):
        fh.write("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, boom)
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["x.txt"]


def test_flag_bits_are_defined_once_with_the_format():
    import smabench.sessions as sessions
    from smabench.drivers.base import FLAG_NAMES as SENSOR_BITS

    bits = list(sessions.FLAG_NAMES)
    assert len(bits) == len(set(bits)) == len(SENSOR_BITS) + 6
    assert sorted(sessions.RUNTIME_FLAG_NAMES) == [1 << k for k in range(8, 14)]  # bits 8-13
    assert all(b & sessions.SENSOR_FLAGS_MASK for b in SENSOR_BITS)
    assert not any(b & sessions.SENSOR_FLAGS_MASK for b in sessions.RUNTIME_FLAG_NAMES)
    assert sessions.describe_flags(sessions.FLAG_INTERLOCK | 0x01) == "timeout|interlock"
    from smabench.bench.session_run import SCHEMA_VERSION

    assert SCHEMA_VERSION == sessions.SCHEMA_VERSION == 2


def test_temperature_column_new_and_old_sessions(tmp_path):
    """Schema 2 carries temperature_C (empty without a thermocouple); schema-1 files still read."""
    folder = tmp_path / "new"
    with SessionWriter(folder, {}) as w:
        w.append({"t_s": 0.0, "current_A": 1.0, "position_mm": 1.0, "temperature_C": 41.5})
        w.append({"t_s": 0.1, "current_A": 1.0, "position_mm": 1.1})
    s = load_session(folder)
    assert s.columns[-1] == "temperature_C" and s.data["temperature_C"][0] == 41.5
    assert np.isnan(s.data["temperature_C"][1]) and not s.is_thermometer_loop
    assert json.loads((folder / "session.json").read_text())["schema_version"] == 2
    old = tmp_path / "old"
    old.mkdir()
    (old / "session.json").write_text('{"schema_version": 1, "load_kg": 2}')
    v1 = ",".join(COLUMNS[:-1])
    (old / "samples.csv").write_text(f"{v1}\n0.0,1,1,0.5,22,2.0,,30,open_loop,0,0\n")
    s1 = load_session(old)
    assert "temperature_C" not in s1.data and not s1.has("temperature_C")
    assert s1.data["position_mm"][0] == 2.0 and s1.meta["schema_version"] == 1


def test_long_session_rotates_chunks_at_cycle_boundaries_and_reads_as_one(tmp_path, cli):
    folder = tmp_path / "long"
    rows_per_cycle, cycles = 7, 40
    with SessionWriter(folder, {}, chunk_rows=50) as w:
        for k in range(cycles * rows_per_cycle):
            w.append({"t_s": k * 0.01, "current_A": 1.0, "position_mm": float(k),
                      "cycle": k // rows_per_cycle, "mode": "open_loop", "flags": k % 3 == 0})
    from smabench.sessions import iter_sample_chunks, sample_files

    files = sample_files(folder)
    assert files[0].name == "samples.csv" and files[1].name == "samples-00001.csv"
    assert len(files) == 5  # 50 rows per chunk, cut at the first cycle boundary after it
    per_file = [set(read_samples_csv(f)["cycle"].tolist()) for f in files]
    assert sum(len(c) for c in per_file) == cycles  # no cycle is split over two files
    assert all(50 <= len(read_samples_csv(f)["t_s"]) < 57 for f in files[:-1])
    s = load_session(folder)
    np.testing.assert_array_equal(s.data["position_mm"], np.arange(cycles * rows_per_cycle))
    assert sum(len(c["t_s"]) for c in iter_sample_chunks(folder, ["t_s"])) == len(s)
    out = tmp_path / "all.csv"
    cli("export", folder, "--out", out, check=True)
    assert len(out.read_text().splitlines()) == cycles * rows_per_cycle + 1
    summary = read_samples_csv(folder / "cycles.csv")
    np.testing.assert_array_equal(summary["cycle"], np.arange(cycles))
    np.testing.assert_array_equal(summary["rows"], rows_per_cycle)
    np.testing.assert_array_equal(summary["position_start_mm"], np.arange(cycles) * 7)
    np.testing.assert_array_equal(summary["position_max_mm"], np.arange(cycles) * 7 + 6)
    assert summary["flagged_rows"].sum() == np.count_nonzero(np.arange(280) % 3 == 0)
    meta = json.loads((folder / "session.json").read_text())
    assert meta["sample_files"] == [f.name for f in files]


def test_cycle_summary_is_live_while_recording(tmp_path):
    folder = tmp_path / "live"
    w = SessionWriter(folder, {})
    for k in range(30):
        w.append({"t_s": float(k), "current_A": 1.0, "position_mm": 1.0, "cycle": k // 10})
    lines = (folder / "cycles.csv").read_text().splitlines()
    assert len(lines) == 3  # header + cycles 0 and 1 done; cycle 2 still running
    w.close()
    assert len((folder / "cycles.csv").read_text().splitlines()) == 4


def test_write_session_arrays_chunk_and_summarise_like_rows(tmp_path):
    n = 1000
    data = {"t_s": np.arange(n) * 0.01, "current_A": np.ones(n),
            "position_mm": np.sin(np.arange(n) / 50), "cycle": np.arange(n) // 90,
            "mode": np.array(["open_loop"] * n, dtype=object)}
    from smabench.sessions import SessionWriter as W

    folder = tmp_path / "arr"
    w = W(folder, {}, chunk_rows=200)
    w.append_arrays(data)
    w.close()
    s = load_session(folder)
    np.testing.assert_allclose(s.data["position_mm"], data["position_mm"], atol=1e-9)
    summary = read_samples_csv(folder / "cycles.csv")
    assert summary["rows"].sum() == n and len(summary["rows"]) == 12
    assert (folder / "samples-00001.csv").exists()


def test_fast_and_strict_readers_agree(tmp_path):
    from smabench.sessions import _read_samples_fast, _read_samples_strict

    f = tmp_path / "x.csv"
    f.write_text("t_s,current_A,position_mm,mode,flags\n0,,1.5,pid,0\n1,2,,ff,\n,3,2.5,,1\n2,4")
    fast = _read_samples_fast(f, True, None)
    strict = _read_samples_strict(f, True, None)
    assert fast is not None and list(fast) == list(strict)
    for c in strict:
        if c == "mode":
            assert list(fast[c]) == list(strict[c]) == ["pid", "ff", ""]
        else:
            np.testing.assert_array_equal(fast[c], strict[c])


def test_compiled_reader_is_exact_on_what_the_writer_writes(tmp_path):
    """smabench.fastcsv against Python's float() on the writer's own formatting, plus the
    cells it must hand to the strict reader."""
    from smabench.fastcsv import parse_numeric

    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(0, 1, 3000) * 10.0 ** rng.integers(-8, 8, 3000),
                        [0.0, -0.0, 1e-9, 123456.789012345, -2.5e-7]])  # fmt: skip
    folder = tmp_path / "s"
    write_session(folder, {}, {"t_s": x, "current_A": -x, "position_mm": x * 3})
    text = (folder / "samples.csv").read_bytes()
    head, _, body = text.partition(b"\n")
    header = head.decode().split(",")
    got = parse_numeric(body, header, ["t_s", "position_mm", "voltage_V"])
    cells = [line.split(b",")[0] for line in body.splitlines()]
    ref = np.array([float(c) for c in cells])
    long = np.array([len(c.lstrip(b"-").replace(b".", b"").lstrip(b"0")) > 15 for c in cells])
    assert long.sum() > 2500  # most need the exact conversion of 16-17 digits
    np.testing.assert_array_equal(got["t_s"].view(np.int64), ref.view(np.int64))  # exact
    assert np.isnan(got["voltage_V"]).all()
    for bad in (b"1,2\n3\n", b"1,x\n", b"1,2,3\n", b"1e,2\n", b"1.5.2,3\n"):
        assert parse_numeric(bad, ["a", "b"], ["a", "b"]) is None, bad
    ok = parse_numeric(b"-1.5e-3,NaN\n+2,\ninf,-7", ["a", "b"], ["a", "b"])
    np.testing.assert_array_equal(ok["a"], [-1.5e-3, 2.0, np.inf])
    np.testing.assert_array_equal(ok["b"], [np.nan, np.nan, -7.0])


# ---------------------------------------------------------------- exact text (Hypothesis)
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True, width=64)
EDGE_FLOATS = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
               -1.7976931348623157e308, 1e-320, 0.1, 0.30000000000000004, 1e15, 1e16, 1e10,
               9999999999.0, 123456789.0, 2.0**53 + 2, 1e22, 1e23, 5e-7, 1.0, -3.0]  # fmt: skip
EXACT = settings(max_examples=60, deadline=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip


def _same_bits(got: np.ndarray, want: np.ndarray) -> None:
    """Bit-identical, except that every NaN (an empty cell) reads back as NaN."""
    want = np.asarray(want, dtype=float)
    assert got.shape == want.shape
    nan = np.isnan(want)
    assert np.isnan(got[nan]).all()
    np.testing.assert_array_equal(got[~nan].view(np.int64), want[~nan].view(np.int64))


@given(xs=st.lists(ANY_FLOAT, min_size=1, max_size=300), edges=st.booleans(),
       cycles=st.lists(st.integers(0, 2**40), min_size=1, max_size=300))  # fmt: skip
@EXACT
def test_every_float64_is_written_as_text_that_reads_back_bit_identical(
    tmp_path_factory, xs, edges, cycles
):
    """The session text of arbitrary float64 (subnormals, ±0, ±inf, the largest and smallest
    exponents) reads back bit-identical through the compiled reader, the strict reader, Python's
    float() and the export; integers stay integers; NaN is an empty cell."""
    from smabench.sessions import _read_samples_strict, export_csv

    x = np.array((EDGE_FLOATS if edges else []) + xs, dtype=float)
    n = len(x)
    cyc = np.resize(np.array(cycles, dtype=np.int64), n)
    flags = np.where(np.isfinite(x), np.abs(np.nan_to_num(x)) % 4096 // 1, np.nan)  # float ints
    data = {"t_s": x, "current_A": x[::-1].copy(), "position_mm": -x, "cycle": cyc,
            "flags": flags, "temperature_C": x * 0.5}  # fmt: skip
    tmp = tmp_path_factory.mktemp("exact")
    folder = write_session(tmp / "s", {}, data)
    back = load_session(folder)
    strict = _read_samples_strict(folder / "samples.csv", False, None)
    for name, col in data.items():
        _same_bits(back.data[name], col)
        _same_bits(strict[name], col)
    lines = (folder / "samples.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = [line.split(",") for line in lines[1:]]
    assert len(cells) == n  # never a row dropped or added
    for name in ("t_s", "position_mm", "temperature_C"):
        k = header.index(name)
        text = [row[k] for row in cells]
        _same_bits(np.array([float(c) if c else np.nan for c in text]), data[name])
        for c, v in zip(text, data[name], strict=True):
            if math.isfinite(v) and v == int(v) and abs(v) < 1e10:
                assert c.endswith(".0"), c  # a whole float stays a float for pandas
    for name in ("cycle", "flags"):
        k = header.index(name)
        assert [row[k] for row in cells] == [
            "" if math.isnan(v) else str(int(v)) for v in data[name].astype(float)
        ]
    assert export_csv(folder, tmp / "out.csv") == n
    with open(tmp / "out.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    for name in ("t_s", "position_mm", "temperature_C"):
        _same_bits(np.array([float(r[name]) if r[name] else np.nan for r in table]), data[name])


@given(xs=st.lists(ANY_FLOAT, min_size=1, max_size=40))
@EXACT
def test_rows_appended_one_at_a_time_read_back_bit_identical(tmp_path_factory, xs):
    tmp = tmp_path_factory.mktemp("rows")
    with SessionWriter(tmp / "s", {}) as w:
        for v in xs:
            w.append({"t_s": v, "current_A": 0.5, "position_mm": v, "cycle": 1, "flags": 0})
    back = load_session(tmp / "s")
    _same_bits(back.data["t_s"], np.array(xs))
    _same_bits(back.data["position_mm"], np.array(xs))


def test_compiled_reader_is_exact_on_long_and_extreme_numbers():
    """17 significant digits, exponents beyond ±22, subnormals: read as float() reads them."""
    from smabench.fastcsv import parse_numeric

    cells = [b"0.30000000000000004", b"1.7976931348623157e+308", b"5e-324", b"1e-320",
             b"2.2250738585072014e-308", b"9007199254740993", b"123456789012345678901234",
             b"0.1000000000000000055511151231257827", b"-4.9406564584124654e-324",
             b"1e23", b"8.98846567431158e307", b"-0", b"7e-10", b"1.5e+300", b"1e400"]  # fmt: skip
    got = parse_numeric(b"\n".join(cells), ["a"], ["a"])
    assert got is not None
    _same_bits(got["a"], np.array([float(c) for c in cells]))
