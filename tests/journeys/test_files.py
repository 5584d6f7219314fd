"""Journeys through smabench's file interfaces, as a user at a shell walks them: exports to
whatever a shell hands as a file name (``-``, ``/dev/stdout``, a FIFO another process reads, a
symlink to a regular file), and imports of what instruments write (an empty cell in the data,
a European file with decimal commas and semicolons)."""

from __future__ import annotations

import csv
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from test_sensor_maps import invalid_maps

from journeys.harness import Installed, Recordings, cycles_session

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py


@pytest.fixture(scope="module")
def session_1kg(recordings: Recordings) -> Path:
    return cycles_session(recordings, 1.0)


@pytest.fixture(scope="module")
def reference_csv(installed: Installed, session_1kg: Path, tmp_path_factory) -> bytes:
    """The export written to a regular file: what every other target must receive."""
    where = tmp_path_factory.mktemp("reference")
    installed.ok("export", session_1kg, "--out", "ref.csv", cwd=where)
    data = (where / "ref.csv").read_bytes()
    assert data.startswith(b"t_s,") and data.count(b"\n") > 100
    return data


def test_export_to_dash_writes_stdout(installed: Installed, session_1kg: Path, cwd: Path,
                                      reference_csv: bytes) -> None:  # fmt: skip
    proc = installed.ok("export", session_1kg, "--out", "-", cwd=cwd)
    assert proc.stdout.encode() == reference_csv  # the CSV only: the status line is on stderr
    assert "rows written" in proc.stderr
    assert not (cwd / "-").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can replace /dev/stdout")
def test_export_to_dev_stdout_as_root_keeps_the_symlink(
    installed: Installed, session_1kg: Path, cwd: Path, reference_csv: bytes
) -> None:
    before = os.readlink("/dev/stdout")
    try:
        proc = installed.ok("export", session_1kg, "--out", "/dev/stdout", cwd=cwd)
    finally:
        replaced = not os.path.islink("/dev/stdout")
        if replaced:  # put the system back before failing
            os.unlink("/dev/stdout")
            os.symlink(before, "/dev/stdout")
    assert not replaced, "export replaced the /dev/stdout symlink with a file"
    assert proc.stdout.encode() == reference_csv


def test_export_to_a_fifo_another_process_reads(
    installed: Installed, session_1kg: Path, cwd: Path, reference_csv: bytes
) -> None:
    fifo = cwd / "pipe.csv"
    os.mkfifo(fifo)
    reader = subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.stdout.buffer.write(open(sys.argv[1], 'rb')"
         ".read())", str(fifo)], stdout=subprocess.PIPE,
    )  # fmt: skip
    try:
        installed.ok("export", session_1kg, "--out", fifo, cwd=cwd, timeout_s=120)
        got, _ = reader.communicate(timeout=120)
    finally:
        reader.kill()
    assert got == reference_csv
    assert fifo.is_fifo()  # still the FIFO, not a file renamed over it


def test_export_through_a_symlink_writes_its_target(
    installed: Installed, session_1kg: Path, cwd: Path, reference_csv: bytes
) -> None:
    (cwd / "results").mkdir()
    target = cwd / "results" / "run.csv"
    target.write_text("old\n")
    link = cwd / "latest.csv"
    link.symlink_to(target)
    installed.ok("export", session_1kg, "--out", link, cwd=cwd)
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_bytes() == reference_csv
    assert sorted(p.name for p in target.parent.iterdir()) == ["run.csv"]  # no temp file left


def _loop_rows(n: int) -> list[tuple[float, float]]:
    half = n // 2
    temps = [25.0 + 60.0 * k / half for k in range(half)]
    temps += [85.0 - 60.0 * k / (n - half) for k in range(n - half)]
    return [(t, round(0.04 / (1.0 + 2.718281828 ** (-(t - 55.0) / 4.0)), 6)) for t in temps]


def test_import_keeps_every_row_with_an_empty_cell(installed: Installed, cwd: Path) -> None:
    rows = _loop_rows(400)
    lines = ["temperature_C,strain"] + [f"{t:.3f},{s}" for t, s in rows]
    lines[9] = f"{rows[8][0]:.3f},"  # data row 9: its strain cell is empty
    (cwd / "loop.csv").write_text("\n".join(lines) + "\n")
    proc = installed.ok("import", "loop.csv", "--columns", "temperature_C,strain",
                        "--wire-length-mm", "100", "--out", "s", cwd=cwd)  # fmt: skip
    assert "400 rows" in proc.stdout, proc.stdout
    assert "1 empty" in proc.stdout, proc.stdout  # the empty cell is counted, not hidden
    with open(cwd / "s" / "samples.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 400
    assert table[8]["position_mm"] == "" and float(table[8]["temperature_C"]) == rows[8][0]
    assert float(table[0]["temperature_C"]) == rows[0][0]


def test_import_a_european_file(installed: Installed, cwd: Path) -> None:
    rows = _loop_rows(200)
    buf = io.StringIO()
    buf.write("Prüfung: Zugversuch NiTi 0,38 mm;Datum: 03.02.2024\n")
    buf.write("Vorspannung;150,0;MPa\n\n")
    buf.write("Temperatur;Dehnung\n(°C);(-)\n")
    for t, s in rows:
        buf.write(f"{t:.3f};{s}\n".replace(".", ","))
    (cwd / "messung.csv").write_bytes(buf.getvalue().encode("cp1252"))
    proc = installed.ok("import", "messung.csv", "--columns", "temperature_C,strain",
                        "--wire-length-mm", "100", "--out", "s", cwd=cwd)  # fmt: skip
    assert "200 rows" in proc.stdout, proc.stdout
    with open(cwd / "s" / "samples.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 200
    assert [float(r["temperature_C"]) for r in table] == [round(t, 3) for t, _ in rows]
    assert [float(r["position_mm"]) for r in table] == pytest.approx([100 * s for _, s in rows])


@given(broken=invalid_maps())
@example(broken=({"registers": {"position": {"address": 0, "type": "int16"}}, "gain\nx": 1},
                 "unknown key"))  # a quoted TOML key holding a line end
@settings(max_examples=6, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
def test_run_refuses_a_broken_sensor_map_in_one_line(installed: Installed, tmp_path_factory,
                                                     broken) -> None:  # fmt: skip
    """A register map generated from the schema and broken one way (an unknown key, a wrong
    type, a value outside the schema's bounds, a zero scale, overlapping registers …), given
    to ``smabench run``: one line naming the file, exit 2, before any device or session."""
    import tomli_w

    data, how = broken
    cwd = tmp_path_factory.mktemp("badmap")
    (cwd / "my-sensor.toml").write_text(tomli_w.dumps(data), encoding="utf-8")
    line = installed.usage_error("run", "--mock", "--load-kg", "2", "--cycles", "1",
                                 "--sensor-map", "my-sensor.toml", cwd=cwd)  # fmt: skip
    assert "my-sensor.toml" in line and "--sensor-map" in line, (how, line)
    assert line.isprintable(), (how, line)
    assert sorted(p.name for p in cwd.iterdir()) == ["my-sensor.toml"]  # no session, no mock
