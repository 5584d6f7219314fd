"""``smabench bench import``: the import of a large tensile-tester style CSV, timed as a user runs
it (``smabench import`` in a child process), with its peak memory.

The file is made here: a metadata line, a header and a units line, then ``t_s``,
``temperature_C`` and ``strain`` rows of a slow thermal cycle (≈ 25 bytes a row, so 200 MB is
≈ 8 M rows), with a few empty cells as real exports have them. Besides the wall time and the
peak memory it prints the import's CPU time (user + system, all threads) and the load average:
on a shared machine the wall time is the CPU time stretched by the other work.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from smabench.argtypes import positive

ROWS_PER_BLOCK = 1_000_000
EMPTY_EVERY = 100_003
"""One strain cell in this many rows is empty (a sensor dropout)."""


def make_csv(path: Path, mb: float, seed: int = 0) -> int:
    """Write a CSV of about ``mb`` MB at ``path``; returns its data rows."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    rng = np.random.default_rng(seed)
    target = int(mb * 1e6)
    rows = 0
    with open(path, "wb") as fh:
        fh.write(b"Test : Start of hold value,100.0,MPa\n\nTime,Temperature,Strain\n(s),(C),(-)\n")
        while fh.tell() < target:
            t_s = (rows + np.arange(ROWS_PER_BLOCK)) * 0.01
            temp_c = 60.0 + 35.0 * np.sin(2 * np.pi * t_s / 600.0)
            strain = 0.04 / (1.0 + np.exp(-(temp_c - 60.0) / 4.0))
            strain += rng.normal(0.0, 1e-5, ROWS_PER_BLOCK)
            dropout = (rows + np.arange(ROWS_PER_BLOCK)) % EMPTY_EVERY == 7  # an empty cell
            table = pa.table({
                "t": np.round(t_s, 2), "T": np.round(temp_c, 3),
                "e": pa.array(np.round(strain, 6), mask=dropout),
            })  # fmt: skip
            buf = pa.BufferOutputStream()
            pacsv.write_csv(table, buf, pacsv.WriteOptions(include_header=False))
            block = buf.getvalue().to_pybytes()
            room = target - fh.tell()
            last = len(block) >= room
            if last:
                block = block[: block.rfind(b"\n", 0, room) + 1]
            fh.write(block)
            rows += block.count(b"\n")
            if last:
                break
    return rows


def cmd_bench_import(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="smabench-bench-import-") as tmp:
        src = Path(tmp) / "export.csv"
        rows = make_csv(src, args.mb)
        size_mb = src.stat().st_size / 1e6
        print(f"bench import: {size_mb:.0f} MB, {rows / 1e6:.2f} M rows …", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-P", "-m", "smabench.cli", "import", str(src), "--columns",
             "t_s,temperature_C,strain", "--wire-length-mm", "100", "--out", str(Path(tmp) / "s")],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        wall_s = time.perf_counter() - t0
        if proc.returncode != 0:
            print(proc.stdout, end="")
            return proc.returncode
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        peak_mb = usage.ru_maxrss / 1024.0
        cpu_s = usage.ru_utime + usage.ru_stime
        load = os.getloadavg()[0]
        print(proc.stdout, end="")
        print(f"{rows / wall_s / 1e6:.2f} M rows/s, {wall_s:.1f} s, peak RSS {peak_mb:.0f} MB "
              f"({size_mb:.0f} MB file); CPU {cpu_s:.1f} s on {os.cpu_count()} CPUs, "
              f"load average {load:.1f}")  # fmt: skip
    return 0


def add_bench_import(bsub) -> None:
    b = bsub.add_parser("import", help="import a large CSV as `smabench import` does: time, memory")
    b.add_argument("--mb", type=positive(), default=200.0, help="file size, MB (200)")
    b.set_defaults(func=cmd_bench_import)
