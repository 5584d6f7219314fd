"""``smabench bench control``: tracking of PID, FF and FF+PID on the mock bench.

Every case is a recorded session against its own ``smabench mock`` process over the real
transports (current driver on a pty, laser sensor on Modbus TCP), the mock running ``speed`` ×
faster than real time (the runtime records device time). References: a square-wave ``step``, a
``staircase``, a slow ``sine`` (period 20 s) and a faster one (10 s), each ``offset ± 0.8 mm``
about the middle of the reachable stroke, under 1, 2 and 4 kg; once on the nominal plant and once
with latent heat switched on in the mock (``latent_heat=24000`` J/kg), which the controller's
loop model (identified from the nominal plant) does not know.

Figures, over the samples after the lead-in: RMS and maximum of position − setpoint (mm and % of
the wire's stroke, the model's cold − hot position), and for steps the mean settling time after
each setpoint edge (error inside ±2 % of the stroke from then until the next edge), with the
number of edges that settled.

``--offline`` runs the same cases in-process instead (:mod:`smabench.bench.offline`: the
runtime's tick on a simulated clock against the simulated devices), at the loop period the mock
run would have in device time (``speed / rate_hz``, 12.5 ms by default, or ``--periods-ms``):
no transports and no wall clock, so its figures do not depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from smabench.argtypes import OUTPUT_HELP, output_file
from smabench.control.reference import BENCHMARK_REFERENCES

if TYPE_CHECKING:
    from smabench.protocols import ProtocolSettings

log = logging.getLogger(__name__)

LOADS_KG = (1.0, 2.0, 4.0)
CONTROLLERS = ("pid", "ff", "ffpid")
EFFECTS = ("", "latent_heat=24000")


@dataclass(frozen=True)
class Case:
    ref: str  # label
    kind: str
    period_s: float
    cycles: int
    load_kg: float
    controller: str
    effect: str = ""
    lead_in_s: float | None = None  # hold before the first period, s (None: the protocol's 8 s)


def all_cases(
    loads=LOADS_KG, refs=tuple(BENCHMARK_REFERENCES), effects=EFFECTS, controllers=CONTROLLERS
):
    return [
        Case(r, *BENCHMARK_REFERENCES[r], load, c, e)
        for e in effects
        for r in refs
        for load in loads
        for c in controllers
    ]


def protocol_settings(case: Case) -> ProtocolSettings:
    """The case's reference: ``offset ± 0.8 mm`` about the middle of the reachable stroke."""
    from smabench.protocols import ProtocolSettings

    lead_in = {} if case.lead_in_s is None else {"lead_in_s": case.lead_in_s}
    return ProtocolSettings(
        name=case.kind, cycles=case.cycles, period_s=case.period_s, amplitude_mm=0.8, **lead_in
    )


def run_case(case: Case, speed: float = 5.0, rate_hz: float = 400.0) -> dict:
    """One session on its own mock; returns the figures."""
    from smabench.bench.headless import MockProcess, open_devices
    from smabench.bench.session_run import RunSettings, run_session
    from smabench.control import ControllerSettings
    from smabench.sessions import load_session

    proto = protocol_settings(case)
    with tempfile.TemporaryDirectory(prefix="smabench-bench-control-") as tmp:
        settings = RunSettings(
            load_kg=case.load_kg,
            protocol=proto,
            rate_hz=rate_hz,
            out_dir=Path(tmp),
            session_id="case",
            time_scale=speed,
            max_duration_s=600.0,
            controller=ControllerSettings(mode=case.controller),
            allow_high_stress=True,  # the paper's loads (4 kg: 346 MPa), on the mock only
        )
        settings.validate()
        controller = settings.build_controller()
        mock_args = ["--load-kg", f"{case.load_kg:g}", "--speed", f"{speed:g}"]
        if case.effect:
            mock_args += ["--effect", case.effect]
        with MockProcess(mock_args) as mock:
            source, sensor = open_devices(mock.ports.driver, mock.ports.sensor_tcp, settings)
            try:
                # (the loop real-time while it runs: run_session's own, then as before)
                folder, result = run_session(settings, source, sensor, command=controller)
            finally:
                source.close()
                sensor.close()
        data = load_session(folder).data
    if result.status != "completed":
        raise RuntimeError(f"{case}: session ended {result.status}: {result.reason}")
    lo, hi = controller.ff.inverse.reachable_mm(0.0)
    return {**case.__dict__, **figures(data, controller.reference, hi - lo),
            "missed": result.missed_deadlines, "samples": result.samples}  # fmt: skip


def run_case_offline(case: Case, period_s: float = 0.0125) -> dict:
    """One case on the offline closed loop at loop period ``period_s`` (device time)."""
    from smabench.bench.offline import run_closed_loop
    from smabench.control import ControllerSettings, build_controller
    from smabench.physics.effects import Effects
    from smabench.physics.wire import PAPER_WIRE

    proto = protocol_settings(case)
    controller = build_controller(
        proto, ControllerSettings(mode=case.controller), case.load_kg, PAPER_WIRE, 2.0
    )
    effects = Effects.from_strings([case.effect]) if case.effect else None
    duration_s = controller.reference.duration_s + period_s
    tr = run_closed_loop(controller, case.load_kg, duration_s, dt_s=period_s, effects=effects)
    if tr.status != "completed":
        raise RuntimeError(f"{case}: offline session ended {tr.status}: {tr.reason}")
    data = {"t_s": tr.t_s, "position_mm": tr.position_mm, "setpoint_mm": tr.setpoint_mm}
    lo, hi = controller.ff.inverse.reachable_mm(0.0)
    return {**case.__dict__, **figures(data, controller.reference, hi - lo),
            "missed": 0, "samples": int(tr.t_s.size), "period_ms": period_s * 1e3}  # fmt: skip


def figures(data: dict, reference, stroke_mm: float) -> dict:
    """RMS/max error and step settling from a recorded session."""
    t = np.asarray(data["t_s"], dtype=float)
    y = np.asarray(data["position_mm"], dtype=float)
    sp = np.asarray(data["setpoint_mm"], dtype=float)
    t0 = t[0]
    m = (t - t0 >= reference.s.lead_in_s) & np.isfinite(y) & np.isfinite(sp)
    e = y[m] - sp[m]
    out = {
        "stroke_mm": stroke_mm,
        "rms_mm": float(np.sqrt(np.mean(e**2))),
        "max_mm": float(np.max(np.abs(e))),
    }
    out["rms_pct"] = 100.0 * out["rms_mm"] / stroke_mm
    out["max_pct"] = 100.0 * out["max_mm"] / stroke_mm
    edges = reference.edges_s()
    if edges:
        band = 0.02 * stroke_mm
        times = []
        for k, te in enumerate(edges):
            t_end = edges[k + 1] if k + 1 < len(edges) else reference.duration_s
            w = (t - t0 >= te) & (t - t0 < t_end) & np.isfinite(y)
            if w.sum() < 3:
                continue
            err = np.abs(y[w] - sp[w])
            outside = np.nonzero(err > band)[0]
            if outside.size == 0:
                times.append(0.0)
            elif outside[-1] < err.size - 1:
                times.append(float(t[w][outside[-1] + 1] - t0 - te))
            else:
                times.append(math.nan)
        ok = [x for x in times if math.isfinite(x)]
        out["settle_s"] = float(np.mean(ok)) if ok else math.nan
        out["settled"] = f"{len(ok)}/{len(times)}"
    return out


def format_table(rows: list[dict]) -> str:
    head = (
        f"{'reference':10s} {'load':>4s} {'plant':9s} {'ctrl':6s} {'RMS mm':>7s} {'RMS %':>6s} "
        f"{'max mm':>7s} {'max %':>6s} {'settle s':>8s} {'settled':>7s}"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        settle = (
            f"{r['settle_s']:8.2f} {r['settled']:>7s}" if "settle_s" in r else f"{'':8s} {'':7s}"
        )
        lines.append(
            f"{r['ref']:10s} {r['load_kg']:4.0f} {'latent' if r['effect'] else 'nominal':9s} "
            f"{r['controller']:6s} {r['rms_mm']:7.3f} {r['rms_pct']:6.1f} {r['max_mm']:7.3f} "
            f"{r['max_pct']:6.1f} {settle}"
        )
    lines.append("")
    lines.append("FF+PID RMS / PID RMS (target ≤ 0.5 on the sines, ≤ 1 on steps):")
    by = {(r["ref"], r["load_kg"], r["effect"], r["controller"]): r for r in rows}
    met = total = 0
    for (ref, load, eff, c), r in by.items():
        if c != "ffpid" or (ref, load, eff, "pid") not in by:
            continue
        ratio = r["rms_mm"] / by[(ref, load, eff, "pid")]["rms_mm"]
        target = 0.5 if ref.startswith("sine") else 1.0
        total += 1
        met += ratio <= target
        lines.append(
            f"  {ref:10s} {load:4.0f} kg {'latent' if eff else 'nominal':8s} {ratio:5.2f}"
            f"  {'met' if ratio <= target else 'NOT met'}"
        )
    lines.append(f"{met} of {total} targets met")
    return "\n".join(lines)


def _run(args_case):
    case, speed, rate, offline_period_s = args_case
    try:
        if offline_period_s:
            return run_case_offline(case, offline_period_s)
        return run_case(case, speed, rate)
    except Exception as exc:  # keep the other cases going; report the failure
        log.exception("case %s failed", case)
        return {**case.__dict__, "error": f"{type(exc).__name__}: {exc}"}


def bench_control(
    cases: list[Case], speed: float = 5.0, rate_hz: float = 400.0, jobs: int = 1,
    progress: Path | None = None, table_out: Path | None = None,
    offline_period_s: float | None = None,
) -> list[dict]:  # fmt: skip
    """Run the cases (``jobs`` at a time, each with its own mock, or offline at
    ``offline_period_s``); rows in case order."""
    from smabench.sessions import atomic_write, writes_in_place

    rows: list[dict] = []
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        args = [(c, speed, rate_hz, offline_period_s) for c in cases]
        for row in pool.map(_run, args):
            rows.append(row)
            if "error" in row:
                print(f"  {row['ref']} {row['load_kg']:g} kg {row['controller']}: {row['error']}",
                      flush=True)  # fmt: skip
            else:
                print(f"  {row['ref']:10s} {row['load_kg']:g} kg {row['effect'] or 'nominal':18s} "
                      f"{row['controller']:6s} RMS {row['rms_mm']:.3f} mm", flush=True)  # fmt: skip
            if progress is not None and not writes_in_place(progress):
                atomic_write(progress, json.dumps(rows, indent=1))
            if table_out is not None and not writes_in_place(table_out):  # partial results
                done = [r for r in rows if "error" not in r]  # survive an interruption
                atomic_write(table_out, format_table(done) + "\n")
    return rows


def cmd_bench_control(args: argparse.Namespace) -> int:
    loads = tuple(args.loads) if args.loads else LOADS_KG
    refs = tuple(args.refs) if args.refs else tuple(BENCHMARK_REFERENCES)
    effects = ("",) if args.nominal_only else EFFECTS
    cases = all_cases(loads, refs, effects)
    if not args.offline:
        print(f"bench control: {len(cases)} sessions on the mock at {args.speed:g}×, "
              f"{args.rate_hz:g} Hz loop, {args.jobs} at a time", flush=True)  # fmt: skip
        periods: list[float | None] = [None]
    else:
        periods = [p / 1e3 for p in args.periods_ms] if args.periods_ms else [
            args.speed / args.rate_hz]
        if not all(0.0005 <= p <= 1.0 for p in periods):
            raise ValueError("offline loop periods must be in 0.5 … 1000 ms")
    from smabench.sessions import atomic_write, writes_in_place

    ok = True
    tables = []
    for period in periods:
        if period is not None:
            print(f"bench control --offline: {len(cases)} sessions in-process, loop period "
                  f"{period * 1e3:g} ms (device time), {args.jobs} at a time", flush=True)
        rows = bench_control(cases, args.speed, args.rate_hz, args.jobs,
                             Path(args.json) if args.json else None,
                             Path(args.out) if args.out else None, period)  # fmt: skip
        good = [r for r in rows if "error" not in r]
        table = format_table(good)
        if period is not None:
            table = f"offline, loop period {period * 1e3:g} ms\n" + table
        print(table)
        tables.append(table)
        ok = ok and len(good) == len(rows)
        if args.json and writes_in_place(args.json):  # a stream gets the rows once, at the end
            atomic_write(args.json, json.dumps(rows, indent=1))
    if args.out:
        atomic_write(args.out, "\n\n".join(tables) + "\n")
    return 0 if ok else 1


def add_bench_control(bsub) -> None:
    """Register ``control`` on the ``smabench bench`` subparsers."""
    b = bsub.add_parser(
        "control", help="tracking of PID, FF and FF+PID on the mock bench (real transports)"
    )
    b.add_argument("--speed", type=float, default=5.0, help="mock speed (5×)")
    b.add_argument("--rate-hz", type=float, default=400.0, help="loop rate, wall Hz (400)")
    b.add_argument("--jobs", type=int, default=1, help="sessions at a time (1)")
    b.add_argument("--loads", type=float, nargs="+", help="loads, kg (1 2 4)")
    b.add_argument("--refs", nargs="+", choices=list(BENCHMARK_REFERENCES), help="references (all)")
    b.add_argument("--nominal-only", action="store_true", help="skip the latent-heat plant")
    b.add_argument(
        "--offline", action="store_true",
        help="in-process on a simulated clock (the runtime's tick, simulated devices), no mock",
    )  # fmt: skip
    b.add_argument(
        "--periods-ms", type=float, nargs="+",
        help="--offline: loop periods, ms of device time (default speed / rate, 12.5)",
    )  # fmt: skip
    b.add_argument("--out", type=output_file,
                   help="also write the table to this file" + OUTPUT_HELP)
    b.add_argument("--json", type=output_file,
                   help="write the rows as JSON (updated after every case)" + OUTPUT_HELP)
    b.set_defaults(func=cmd_bench_control)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="smabench bench")
    add_bench_control(p.add_subparsers(dest="cmd", required=True))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
