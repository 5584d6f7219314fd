"""``smabench bench analyze``: how long ``smabench analyze`` takes on a long session.

Makes a session with the plant simulation (default: one hour at 100 Hz, 2 kg, heating cycles at
three currents and three pulse lengths, latent heat switched on: a coupled effect, the slowest
kind to fit), writes it as a real session folder, then times the whole command as a user runs
it (load the CSV, fit the baseline and every candidate, verdict, JSON) and prints the figures.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def long_profile(duration_s: float, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Heating pulses (1.1/1.3/1.5 A for 3/4/5 s) each followed by 9 s off, for ``duration_s``."""
    pattern = []
    for k in range(9):
        pattern.append(([3.0, 4.0, 5.0][(k // 3) % 3], [1.1, 1.3, 1.5][k % 3]))
        pattern.append((9.0, 0.0))
    cur: list[np.ndarray] = []
    total = 0
    n_total = int(round(duration_s / dt_s))
    while total < n_total:
        for d, c in pattern:
            n = int(round(d / dt_s))
            cur.append(np.full(n, c))
            total += n
    current = np.concatenate(cur)[:n_total]
    return np.arange(n_total) * dt_s, current


def make_long_session(folder: Path, duration_s: float, rate_hz: float, load_kg: float,
                      effects: list[str]) -> Path:  # fmt: skip
    """Simulate and write the session (the plant stepped at the recording rate)."""
    from smabench.physics.plant import Effects, simulate_plant
    from smabench.sessions import write_session

    t, cur = long_profile(duration_s, 1.0 / rate_hz)
    tr = simulate_plant(
        t, cur, load_kg=load_kg, effects=Effects.from_strings(effects), noise_mm=0.002, seed=1
    )
    n = len(t)
    data = {
        "t_s": tr.t_s, "current_set_A": tr.current_a, "current_A": tr.current_a,
        "voltage_V": tr.voltage_v, "ambient_C": np.full(n, 22.0), "position_mm": tr.position_mm,
    }  # fmt: skip
    meta = {"load_kg": load_kg, "wire": {"length_mm": 55.0, "diameter_mm": 0.38},
            "source": "smabench bench analyze", "effects": effects}  # fmt: skip
    return write_session(folder, meta, data)


def cmd_bench_analyze(args: argparse.Namespace) -> int:
    from smabench.analysis.cli import main as analyze_main

    effects = ["latent_heat=24000"] if args.effect is None else args.effect
    if not (args.duration_s >= 60.0 and args.rate_hz > 0 and 0 < args.load_kg <= 10):
        raise ValueError("bench analyze needs --duration-s ≥ 60, --rate-hz > 0, --load-kg 0…10")
    with tempfile.TemporaryDirectory(prefix="smabench-bench-analyze-") as tmp:
        t0 = time.perf_counter()
        folder = make_long_session(
            Path(tmp) / "long", args.duration_s, args.rate_hz, args.load_kg, effects
        )
        t_make = time.perf_counter() - t0
        size_mb = (folder / "samples.csv").stat().st_size / 1e6
        print(f"session: {args.duration_s:g} s at {args.rate_hz:g} Hz, {args.load_kg:g} kg, "
              f"effects {', '.join(effects) or 'none'}; {size_mb:.1f} MB CSV, made in "
              f"{t_make:.1f} s", flush=True)  # fmt: skip
        out = Path(tmp) / "a.json"
        argv = [str(folder), "--json", str(out), "-q"]
        if args.workers:
            argv += ["--workers", str(args.workers)]
        t0 = time.perf_counter()
        code = analyze_main(argv)
        wall = time.perf_counter() - t0
        if code != 0:
            return code
        doc = json.loads(out.read_text())
    timing = doc["timing_s"]
    print("\nsmabench analyze, wall time by part (fits in the worker processes overlap):")
    print(f"  {'load + validate':24s} {timing.get('load', float('nan')):7.2f} s")
    for k, v in timing.items():
        if k not in ("load", "total"):
            print(f"  {'fit ' + k:24s} {v:7.2f} s")
    print(f"  {'analysis (all fits)':24s} {timing['total']:7.2f} s")
    print(f"  {'whole command':24s} {wall:7.2f} s   (target ≤ 60 s)")
    print(f"verdict: {doc['cause']} (gain {doc['gain']:.1%}), runner-up {doc['runner_up']}")
    return 0


def add_bench_analyze(bsub) -> None:
    """Register ``bench analyze`` on the ``smabench bench`` subparsers."""
    b = bsub.add_parser("analyze", help="time smabench analyze on a one-hour 100 Hz session")
    b.add_argument("--duration-s", type=float, default=3600.0, help="session length, s (3600)")
    b.add_argument("--rate-hz", type=float, default=100.0, help="recording rate, Hz (100)")
    b.add_argument("--load-kg", type=float, default=2.0, help="load, kg (2)")
    b.add_argument("--effect", action="append", default=None, metavar="NAME=VALUE",
                   help="plant effect to hide (default latent_heat=24000; repeatable)")  # fmt: skip
    b.add_argument("--workers", type=int, help="processes for the candidate fits (default: CPUs)")
    b.set_defaults(func=cmd_bench_analyze)
