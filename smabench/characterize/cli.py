"""``smabench characterize`` and ``smabench bench characterize``."""

from __future__ import annotations

import argparse
import csv
import logging
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from smabench.argtypes import OUTPUT_HELP, output_file
from smabench.characterize.e3097 import TEMPERATURE_KEYS
from smabench.characterize.run import Overrides, characterize_many, strip_private
from smabench.sessions import atomic_write, atomic_write_json
from smabench.tasks import add_scheduler_timeout

log = logging.getLogger(__name__)

CSV_COLUMNS = (
    "session", "load_MPa", "temperature_source", "cycle", "t_start_s", "t_end_s",
    "LCT_C", "UCT_C", "As_C", "Af_C", "Ms_C", "Mf_C", "actuation_strain",
    "heating_transformation_strain", "cooling_transformation_strain", "residual_strain",
    "accumulated_residual_strain", "residual_strain_austenite", "hysteresis_K",
    "heating_span_K", "cooling_span_K", "transformation_span_K", "temperature_uncertainty_K",
    "notes",
)  # fmt: skip


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(round(v, 9))
    if isinstance(v, list):
        return "; ".join(str(x) for x in v)
    return str(v)


def write_csv(doc: dict[str, Any], path: str | Path) -> None:
    """One row per cycle and session (the JSON's cycles, flattened)."""

    def write(fh: IO[str]) -> None:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(CSV_COLUMNS)
        for s in doc["sessions"]:
            for c in s["cycles"]:
                row = {**c, "session": s["session"], "load_MPa": s["load_MPa"],
                       "temperature_source": s["temperature_source"]}  # fmt: skip
                w.writerow([_cell(row.get(k)) for k in CSV_COLUMNS])

    atomic_write(path, write)


def _fmt(v: Any, spec: str = ".1f") -> str:
    return "n/a" if v is None else format(v, spec)


def summary_lines(doc: dict[str, Any]) -> list[str]:
    lines = []
    for s in doc["sessions"]:
        cyc = s["cycles"]
        med = {}
        for key in (*[f"{k}_C" for k in TEMPERATURE_KEYS], "actuation_strain", "hysteresis_K"):
            v = np.array([c[key] for c in cyc if c.get(key) is not None], dtype=float)
            med[key] = float(np.median(v)) if v.size else None
        lines.append(
            f"{s['session']}: {s['n_cycles']} cycle(s), {_fmt(s['load_MPa'], '.0f')} MPa, "
            f"temperature {s['temperature_source']}; median As {_fmt(med['As_C'])} "
            f"Af {_fmt(med['Af_C'])} Ms {_fmt(med['Ms_C'])} Mf {_fmt(med['Mf_C'])} °C, "
            f"actuation {_fmt(None if med['actuation_strain'] is None else med['actuation_strain'] * 100, '.2f')} %, "  # noqa: E501
            f"hysteresis {_fmt(med['hysteresis_K'])} K, accumulated residual "
            f"{_fmt(cyc[-1]['accumulated_residual_strain'] * 100, '.3f')} %"
            + (f"; {s['n_masked_rows']} row(s) masked (position flagged invalid or empty)"
               if s.get("n_masked_rows") else "")
        )
    pd = doc.get("phase_diagram")
    if pd:
        parts = [
            f"{k} {_fmt(pd[k]['slope_MPa_per_K'], '.2f')} ± {_fmt(pd[k]['uncertainty'], '.2f')}"
            + ("" if pd[k].get("clausius_clapeyron", True) else f" ({pd[k]['why_not']})")
            for k in TEMPERATURE_KEYS
        ]
        lines.append("phase diagram dσ/dT (MPa/K): " + ", ".join(parts))
        bad = [k for k in TEMPERATURE_KEYS if not pd[k].get("clausius_clapeyron", True)]
        if bad:
            lines.append(f"  warning: {', '.join(bad)}: not a Clausius–Clapeyron slope "
                         "(wrong sign, outside 3–20 MPa/K or no stress shift in the data)")
    return lines


CHUNK_MEMORY_PER_FILE_BYTE = 3.0
"""Memory to characterize a sample chunk file, per byte of it: its text, its parsed columns and
the cycle search's temporaries (measured: 107 MB more at peak for a 38 MB file)."""


def require_memory(sessions: list[str], workers: int | None) -> None:
    """Refuse up front (:class:`smabench.memlimit.NotEnoughMemoryError`) when the largest sample
    chunk file of ``sessions`` would not fit in each local worker: a session is read one chunk
    file at a time, so an archive of any size fits when its largest chunk does."""
    from smabench.memlimit import gb, require
    from smabench.sessions import sample_files
    from smabench.tasks import local_workers

    largest, where = 0, ""
    for s in sessions:
        p = Path(s)
        try:
            files = sample_files(p) if p.is_dir() else [p] if p.is_file() else []
        except (OSError, ValueError):
            continue  # characterize_many names what is wrong with it
        for f in files:
            size = f.stat().st_size
            if size > largest:
                largest, where = size, str(f)
    if largest:
        require(CHUNK_MEMORY_PER_FILE_BYTE * largest,
                f"characterizing {where} (a sample file of {gb(largest)}, read whole)",
                local_workers(len(sessions), workers))  # fmt: skip


def cmd_characterize(args: argparse.Namespace) -> int:
    overrides = Overrides(args.wire_length_mm, args.wire_diameter_mm, args.load_mpa)
    if not args.scheduler:  # a cluster's workers have memories of their own
        require_memory(args.sessions, args.workers)
    doc = characterize_many(
        args.sessions,
        overrides,
        keep_cycles="auto" if args.report else (),
        scheduler=args.scheduler,
        workers=args.workers,
        scheduler_timeout_s=args.scheduler_timeout_s,
        include_aborted=args.include_aborted,
    )
    for s in doc["skipped"]:
        print(f"smabench characterize: {s['session']}: skipped: {s['skipped']}", file=sys.stderr)
    for s in doc["sessions"]:
        for w in s["warnings"]:
            print(f"smabench characterize: {s['session']}: {w}", file=sys.stderr)
    for line in summary_lines(doc):
        print(line)
    atomic_write_json(args.json, strip_private(doc))
    print(f"json written: {args.json}")
    if args.csv:
        write_csv(doc, args.csv)
        print(f"csv written: {args.csv}")
    if args.report:
        from smabench.characterize.report import write_report

        for p in write_report(doc, args.report):
            print(f"plot written: {p}")
    return 0


def add_commands(sub) -> None:
    s = sub.add_parser(
        "characterize",
        help="ASTM E3097 per cycle (As, Af, Ms, Mf, strains, hysteresis) and the phase diagram",
        description="Split each session into thermal cycles and report the ASTM E3097 "
        "properties per cycle; with sessions at two loads or more, the Clausius–Clapeyron "
        "slopes. Prefers the measured temperature_C, else the estimate (marked 'estimated'). "
        "Aborted sessions and sessions with no complete thermal cycle are skipped with one line "
        "each (exit 2 when nothing is left).",
    )
    s.add_argument("sessions", nargs="+", help="session folders or CSVs")
    s.add_argument("--json", required=True, type=output_file,
                   help="write the results here (JSON)" + OUTPUT_HELP)
    s.add_argument("--csv", type=output_file,
                   help="also write one row per cycle here" + OUTPUT_HELP)
    s.add_argument("--report", help="folder for the report PNGs")
    s.add_argument("--wire-length-mm", type=float, help="wire length when a session lacks it")
    s.add_argument("--wire-diameter-mm", type=float, help="wire diameter when a session lacks it")
    s.add_argument("--load-mpa", type=float, help="stress of every session, MPa (overrides)")
    s.add_argument("--include-aborted", action="store_true",
                   help="characterize aborted sessions too (default: skipped with one line)")
    s.add_argument(
        "--scheduler",
        help="Dask scheduler address (tcp://HOST:PORT): one session per task on that cluster "
        "(default: local worker processes)",
    )
    add_scheduler_timeout(s)
    s.add_argument("--workers", type=int, help="local worker processes (default: one per CPU)")
    s.set_defaults(func=cmd_characterize)


# --------------------------------------------------------------------------- benchmark
def synthetic_session(folder: Path, cycles: int, rate_hz: float, period_s: float = 13.0) -> Path:
    """A session of ``cycles`` heating cycles written as the bench writes it (chunked files,
    cycles.csv): temperature estimate rising for 3 s then cooling, a smooth loop, noise."""
    from smabench.characterize.synth import Branches, cycle_record
    from smabench.sessions import SessionWriter

    br = Branches()
    n = int(round(period_s * rate_hz))
    rng = np.random.default_rng(1)
    w = SessionWriter(folder, {"load_kg": 2.0, "wire": {"length_mm": 55.0, "diameter_mm": 0.38},
                               "kind": "synthetic"}, chunk_rows=1_000_000)  # fmt: skip
    t1, e1 = cycle_record(br, n, heat_fraction=3.0 / period_s)
    pos1 = e1 * 55.0
    block = 50  # cycles per append_arrays call
    for c0 in range(0, cycles, block):
        m = min(block, cycles - c0)
        k = np.repeat(np.arange(c0, c0 + m), n)
        t_s = (np.arange(m * n) + c0 * n) / rate_hz
        w.append_arrays({
            "t_s": t_s,
            "current_A": np.tile(np.where(np.arange(n) < 3.0 / period_s * n, 1.4, 0.0), m),
            "position_mm": np.tile(pos1, m) + rng.normal(0, 2e-4, m * n),
            "temperature_est_C": np.tile(t1, m),
            "cycle": k,
            "flags": np.zeros(m * n, dtype=int),
        })  # fmt: skip
    w.close()
    return folder


def cmd_bench_characterize(args: argparse.Namespace) -> int:
    import resource

    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="smabench-char-"))
    folder = work / f"synthetic-{args.cycles}c-{args.rate_hz:g}hz"
    if not folder.exists():
        print(f"writing a {args.cycles}-cycle session at {args.rate_hz:g} Hz into {folder} …",
              flush=True)  # fmt: skip
        t0 = time.perf_counter()
        synthetic_session(folder, args.cycles, args.rate_hz)
        print(f"  written in {time.perf_counter() - t0:.1f} s", flush=True)
    files = sorted(folder.glob("samples*.csv"))
    size_mb = sum(f.stat().st_size for f in files) / 1e6
    t0 = time.perf_counter()
    c0 = time.process_time()
    doc = characterize_many([str(folder)], workers=1)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    s = doc["sessions"][0]
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    ok = sum(1 for c in s["cycles"] if c["As_C"] is not None and c["Mf_C"] is not None)
    print(f"session: {args.cycles} cycles at {args.rate_hz:g} Hz, {len(files)} chunk file(s), "
          f"{size_mb:.0f} MB")  # fmt: skip
    print(f"characterize: {dt:.1f} s for {s['n_cycles']} cycles ({ok} with all four "
          f"temperatures), {dt / max(1, s['n_cycles']) * 1e3:.2f} ms per cycle; "
          f"CPU time {cpu:.1f} s (load average {load:.1f} on {os.cpu_count()} CPUs)")
    print(f"peak memory of this process: {peak_mb:.0f} MB")
    return 0


def add_bench_characterize(bsub) -> None:
    b = bsub.add_parser("characterize", help="characterize speed on a long synthetic session")
    b.add_argument("--cycles", type=int, default=10_000, help="cycles (10000)")
    b.add_argument("--rate-hz", type=float, default=200.0, help="recording rate, Hz (200)")
    b.add_argument("--work-dir", help="keep the synthetic session here (reused when present)")
    b.set_defaults(func=cmd_bench_characterize)
