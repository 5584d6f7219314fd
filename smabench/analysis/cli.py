"""``smabench analyze SESSION [SESSION ...]``: where our simulation is wrong, and why.

Wire it in with ``add_commands(sub)``; ``python -m smabench.analysis.cli ...`` runs it alone.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence

from smabench.analysis.data import AnalysisError
from smabench.argtypes import OUTPUT_HELP, output_file, positive
from smabench.tasks import add_scheduler_timeout


def add_arguments(s: argparse.ArgumentParser) -> None:
    s.add_argument("sessions", nargs="+", metavar="SESSION", help="session folders or CSVs")
    s.add_argument("--json", metavar="OUT", type=output_file,
                   help="write the verdict, RMSEs and parameters here" + OUTPUT_HELP)
    s.add_argument("--report", metavar="DIR", help="write report.md and PNG plots here")
    s.add_argument("--predictions", metavar="OUT.csv", type=output_file,
                   help="write measured/baseline/extended" + OUTPUT_HELP)
    s.add_argument("--load-kg", type=positive(), help="hanging load, kg (overrides session.json)")
    s.add_argument("--wire-length-mm", type=positive(), help="wire length, mm (overrides)")
    s.add_argument("--wire-diameter-mm", type=positive(), help="wire diameter, mm (overrides)")
    s.add_argument(
        "--candidates",
        help="comma-separated candidate causes to try (default: all that apply); asking for "
        "stress_shift with one load is an error",
    )
    s.add_argument("--workers", type=int, help="processes for the candidate fits (default: CPUs)")
    s.add_argument(
        "--each",
        action="store_true",
        help="analyse every session on its own, one task per session (an archive), on local "
        "processes or on the Dask cluster of --scheduler; --json gets {'sessions': [...]}",
    )
    s.add_argument("--scheduler", help="Dask scheduler address tcp://HOST:PORT (with --each)")
    add_scheduler_timeout(s)
    s.add_argument("-q", "--quiet", action="store_true", help="print only the verdict")


def input_lines(s) -> list[str]:
    """What the analysis left out of a session: masked rows, cut rows (one line each)."""
    out = []
    if s.masked_rows:
        out.append(f"{s.name}: {s.masked_rows} row(s) with an invalid or empty position masked "
                   "(simulated through, not compared)")  # fmt: skip
    for what in (s.cut or {}).get("text", []):
        out.append(f"{s.name}: cut {what}")
    return out


def add_commands(sub) -> None:
    """Register ``analyze`` on an argparse subparsers object."""
    s = sub.add_parser(
        "analyze",
        help="find where the simulation is wrong and name the physical cause",
        description="Find where the simulation is wrong on recorded sessions, and name the "
        "physical cause.",
    )
    add_arguments(s)
    s.set_defaults(func=cmd_analyze)


def analyse_one(path: str, wire_length_mm: float | None, wire_diameter_mm: float | None,
                candidates: list[str] | None) -> dict:  # fmt: skip
    """One session's analysis document (a task of ``--each``: module level, picklable)."""
    from smabench.analysis.core import analyse
    from smabench.analysis.data import prepare_session
    from smabench.analysis.report import summary
    from smabench.sessions import load_session

    session = prepare_session(load_session(path), None, wire_length_mm, wire_diameter_mm)
    doc = summary(analyse([session], candidates, progress=lambda m: None, workers=1))
    doc.pop("timing_s", None)  # the same document wherever it ran: no wall-clock times
    for row in doc.get("candidates", {}).values():
        row.pop("fit_seconds", None)
    return {"session": path, "assumed": sorted(session.notes), **doc}


def cmd_analyze_each(args: argparse.Namespace) -> int:
    from smabench.analysis.report import write_json
    from smabench.sessions import load_session_meta_check
    from smabench.tasks import run_tasks

    if args.load_kg is not None:
        raise AnalysisError("--load-kg applies to one session only; give each its session.json")
    for p in args.sessions:
        load_session_meta_check(p)
    if not args.scheduler:  # a cluster's workers have memories of their own
        from smabench.analysis.data import require_memory
        from smabench.tasks import local_workers

        require_memory(args.sessions, local_workers(len(args.sessions), args.workers), each=True)
    cands = [c.strip() for c in args.candidates.split(",") if c.strip()] if args.candidates \
        else None  # fmt: skip
    tasks = [(str(p), args.wire_length_mm, args.wire_diameter_mm, cands) for p in args.sessions]
    docs = run_tasks(analyse_one, tasks, args.scheduler, args.workers, args.scheduler_timeout_s)
    for d in docs:
        print(f"{d['session']}: cause {d['cause']} (gain {d['gain']:.1%})")
    if args.json:
        write_json(args.json, {"sessions": docs})
        print(f"json written: {args.json}")
    return 0


def cmd_analyze(args: argparse.Namespace) -> int:
    if getattr(args, "each", False):
        return cmd_analyze_each(args)
    if getattr(args, "scheduler", None):
        raise AnalysisError("--scheduler needs --each (one task per session)")
    from smabench.analysis.core import analyse
    from smabench.analysis.data import prepare_session, require_memory
    from smabench.analysis.report import (
        summary,
        value_text,
        write_json,
        write_predictions,
        write_report,
    )
    from smabench.sessions import load_session

    t0 = time.perf_counter()
    say = (lambda m: None) if args.quiet else (lambda m: print(m, flush=True))
    if len(args.sessions) > 1 and args.load_kg is not None:
        raise AnalysisError("--load-kg applies to one session only; give each its session.json")
    require_memory(args.sessions)  # whole sessions are held: refused up front when they cannot
    sessions = [
        prepare_session(load_session(p), args.load_kg, args.wire_length_mm, args.wire_diameter_mm)
        for p in args.sessions
    ]
    t_load = time.perf_counter() - t0
    for note in sorted({n for s in sessions for n in s.notes}):
        print(f"smabench analyze: assumed: {note}", file=sys.stderr)
    n = sum(len(s.t) for s in sessions)
    say(f"{len(sessions)} session(s), {n} samples, loaded in {t_load:.2f} s")
    for s in sessions:
        for line in input_lines(s):
            print(line)
    cands = None
    if args.candidates:
        cands = [c.strip() for c in args.candidates.split(",") if c.strip()]
    an = analyse(sessions, cands, progress=say, workers=args.workers)
    doc = summary(an)
    doc["timing_s"]["load"] = t_load
    print(f"cause: {doc['cause']}   runner-up: {doc['runner_up']}   ({doc['reason']})")
    if len(doc["causes"]) > 1:
        print("causes: " + ", ".join(f"{c['cause']} (+{c['incremental_gain']:.1%} over "
                                     f"{c['over']})" for c in doc["causes"]))  # fmt: skip
    for flag in doc["flags"]:
        print(f"flag: {flag}")
    print(
        f"held-out RMSE: baseline {doc['baseline_heldout_rmse_mm']:.4g} mm, extended "
        f"({doc['extended_model']}) {doc['extended_heldout_rmse_mm']:.4g} mm, "
        f"gain {doc['gain']:.1%}"
    )
    if not args.quiet:
        for c, row in doc["candidates"].items():
            (pname, pv), = row["parameter"].items()
            print(f"  {c:22s} rmse {row['heldout_rmse_mm']:.4g} mm  gain {row['gain']:7.1%}  "
                  f"p {row['p_value']:.2g}  {pname} = {value_text(pv)}")  # fmt: skip
        for c, why in doc["skipped_candidates"].items():
            print(f"  {c:22s} not tried: {why}")
        ls = doc.get("loop_shift_check")
        if ls and ls.get("stress_rate_mpa_per_k"):
            fit = doc["candidates"].get("stress_shift", {}).get("parameter", {})
            fv = fit.get("stress_rate_mpa_per_k", {})
            print(f"stress rate: fitted {fv.get('value', float('nan')):.3g} ± "
                  f"{fv.get('uncertainty') or float('nan'):.2g} MPa/K; loops' own mid-"
                  f"transformation shift {ls['stress_rate_mpa_per_k']:.3g} MPa/K")  # fmt: skip
    if args.json:
        write_json(args.json, doc)
        say(f"json written: {args.json}")
    if args.predictions:
        write_predictions(args.predictions, an, doc["extended_model"])
        say(f"predictions written: {args.predictions}")
    if args.report:
        md = write_report(args.report, an, doc)
        say(f"report written: {md}")
    print(f"analysis time: {time.perf_counter() - t0:.1f} s for {n} samples")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="smabench analyze", description=__doc__)
    add_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(cmd_analyze(args) or 0)
    except (ValueError, OSError) as exc:
        print(f"smabench analyze: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
