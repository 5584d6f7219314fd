"""Property tests (Hypothesis) of the session files: ``import`` of text tables, ``export`` and
the session reader. Random valid inputs round-trip exactly; random invalid ones give one line,
exit 2 and leave nothing behind."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smabench.importer import read_table
from smabench.sessions import COLUMNS, atomic_write, load_session, write_session

FAST = settings(max_examples=25, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
CLI = settings(FAST, max_examples=10)  # each example runs the command line in-process

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
# numbers as a lab instrument prints them: a fixed number of decimals
decimals = st.integers(min_value=0, max_value=6)


@st.composite
def tables(draw):
    n = draw(st.integers(min_value=2, max_value=40))
    places = draw(decimals)
    rows = [[round(draw(finite), places), round(draw(finite), places)] for _ in range(n)]
    empty = draw(st.sets(st.tuples(st.integers(0, n - 1), st.integers(0, 1)), max_size=n))
    # a row keeps at least one number (a wholly empty line is a blank line, not a row)
    empty = {(r, c) for r, c in empty if (r, 1 - c) not in empty}
    return rows, places, empty


@given(t=tables(), sep=st.sampled_from([",", ";", "\t"]), comma=st.booleans(),
       header=st.booleans(), meta=st.lists(st.sampled_from(["Operator: A. Lab", "Rate : 5 K/min",
                                                            "Sample 3"]), max_size=3))  # fmt: skip
@FAST
def test_import_keeps_every_row_and_value(tmp_path_factory, t, sep, comma, header, meta):
    rows, places, empty = t
    if comma and sep == ",":
        sep = ";"  # decimal commas with comma separators need --decimal (tested elsewhere)

    def cell(v: float) -> str:
        s = f"{v:.{places}f}"
        return s.replace(".", ",") if comma else s

    lines = list(meta) + (["Temperature" + sep + "Position"] if header else [])
    for i, (a, b) in enumerate(rows):
        cells = ["" if (i, k) in empty else cell(v) for k, v in enumerate((a, b))]
        lines.append(sep.join(cells))
    src = tmp_path_factory.mktemp("imp") / "loop.txt"
    src.write_text("\n".join(lines) + "\n")
    data, layout = read_table(src, ["temperature_C", "position_mm"])
    assert layout.rows == len(rows)
    for k, name in enumerate(("temperature_C", "position_mm")):
        want = [math.nan if (i, k) in empty else float(f"{r[k]:.{places}f}")
                for i, r in enumerate(rows)]  # fmt: skip
        np.testing.assert_array_equal(data[name], np.array(want))
    assert sum(layout.empty_cells.values()) == len(empty)


@given(garbage=st.sampled_from(["abc", "1.2.3", "--", "inf", "1e", "0x10"]),
       where=st.integers(min_value=0, max_value=9))  # fmt: skip
@CLI
def test_import_of_a_bad_cell_is_one_line_exit_2_and_nothing_written(tmp_path_factory,
                                                                     cli_in_process, garbage,
                                                                     where):  # fmt: skip
    tmp = tmp_path_factory.mktemp("bad")
    lines = ["T,x"] + [f"{20 + i}.5,{i / 100}" for i in range(10)]
    lines[1 + where] = f"{garbage},0.5" if where % 2 else f"30.0,{garbage}"
    if where == 0:
        lines[2] = lines[1]  # the first data line is good so the table starts there
        lines[1] = "20.5,0.0"
        lines[5] = f"30.0,{garbage}"
    (tmp / "bad.csv").write_text("\n".join(lines) + "\n")
    proc = cli_in_process("import", tmp / "bad.csv", "--columns", "temperature_C,position_mm",
                          "--out", tmp / "s")  # fmt: skip
    assert proc.returncode == 2, proc
    assert len(proc.stderr.strip().splitlines()) == 1 and "line" in proc.stderr
    assert sorted(p.name for p in tmp.iterdir()) == ["bad.csv"]


samples = st.lists(
    st.tuples(finite, finite, st.integers(0, 50), st.integers(0, 4095),
              st.one_of(st.none(), finite)),
    min_size=1, max_size=30,
)  # fmt: skip


@given(rows=samples)
@CLI
def test_session_written_read_and_exported_round_trips(tmp_path_factory, cli_in_process, rows):
    tmp = tmp_path_factory.mktemp("rt")
    t = np.cumsum([1e-3 + abs(r[0]) % 1.0 for r in rows])
    data = {
        "t_s": t,  # not rounded: every float64 is written as text that reads back exactly
        "current_A": np.array([r[1] % 3.0 for r in rows]),
        "position_mm": np.array([r[0] for r in rows]),
        "cycle": np.array([r[2] for r in rows]),
        "flags": np.array([r[3] for r in rows]),
        "temperature_C": np.array([math.nan if r[4] is None else r[4] for r in rows]),
        "mode": np.array(["open_loop"] * len(rows), dtype=object),
    }
    folder = write_session(tmp / "s", {"status": "completed"}, data)
    back = load_session(folder)
    for name, col in data.items():
        if name == "mode":
            assert list(back.data[name]) == list(col)
        else:
            np.testing.assert_array_equal(back.data[name], col.astype(float))
    proc = cli_in_process("export", folder, "--out", tmp / "out.csv")
    assert proc.returncode == 0, proc.stderr
    with open(tmp / "out.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert list(table[0]) == [c for c in COLUMNS if c in back.columns]
    for name in ("cycle", "flags"):  # integers stay integers
        assert [r[name] for r in table] == [str(int(v)) for v in data[name]]
    for name in ("t_s", "position_mm", "temperature_C"):
        got = [math.nan if r[name] == "" else float(r[name]) for r in table]
        np.testing.assert_array_equal(np.array(got), data[name])


@given(junk=st.binary(min_size=1, max_size=200))
@CLI
def test_session_reader_refuses_junk_in_one_line(tmp_path_factory, cli_in_process, junk):
    tmp = tmp_path_factory.mktemp("junk")
    (tmp / "s").mkdir()
    (tmp / "s" / "samples.csv").write_bytes(junk)
    proc = cli_in_process("export", tmp / "s", "--out", tmp / "out.csv")
    assert proc.returncode == 2, proc
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp / "out.csv").exists()
    assert [p.name for p in tmp.iterdir()] == ["s"]


@given(body=st.text(max_size=300))
@FAST
def test_atomic_write_through_a_symlink_keeps_the_link(tmp_path_factory, body):
    tmp = tmp_path_factory.mktemp("link")
    (tmp / "target.txt").write_text("old")
    (tmp / "link.txt").symlink_to(tmp / "target.txt")
    atomic_write(tmp / "link.txt", body)
    assert (tmp / "link.txt").is_symlink()
    assert (tmp / "target.txt").read_bytes() == body.encode("utf-8")
    assert sorted(os.listdir(tmp)) == ["link.txt", "target.txt"]


def test_dash_writes_stdout_and_no_file(tmp_path, cli_in_process, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = write_session(tmp_path / "s", {"status": "completed"},
                           {"t_s": np.arange(3.0), "current_A": np.ones(3),
                            "position_mm": np.array([1.0, 2.0, 3.5]), "cycle": np.zeros(3, int),
                            "flags": np.array([0, 256, 0])})  # fmt: skip
    proc = cli_in_process("export", folder, "--out", "-", "--columns", "t_s,position_mm,flags")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "t_s,position_mm,flags\n0.0,1.0,0\n1.0,2.0,256\n2.0,3.5,0\n"
    assert "3 rows written" in proc.stderr
    assert not Path("-").exists()
    proc = cli_in_process("fit", folder, "--model", "1", "--json", "-", "--plot", "-")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1


def test_a_fifo_is_written_in_place(tmp_path):
    import threading

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    atomic_write(fifo, "a,b\n1,2\n")
    reader.join(timeout=30)
    assert got == [b"a,b\n1,2\n"] and fifo.is_fifo()
