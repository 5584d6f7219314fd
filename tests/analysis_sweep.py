"""How often ``smabench analyze`` names the right cause: many random draws, not one seed.

    .venv/bin/python tests/analysis_sweep.py [--n 10] [--sim independent|plant|third] [--seed 0]

For every effect (and no effect, and pulley friction or a dead band, outside the list; on the
third simulator also two effects at once) draws ``n`` magnitudes within the physical ranges of
``test_analysis_independent.CASES`` (the project plant: ``test_analysis.RANGES``; the third
simulator: ``test_analysis_third.CASES``), makes the sessions, runs the analysis and tallies the
verdicts: right, ``unexplained``/``none`` (honest misses), or a wrong name (the failure that
matters), with the median relative error of the headline parameter when named right. An
effect outside the list is right as ``unexplained`` or, within the floor, ``none``. One
effect is right when it is the cause and nothing else is in ``causes`` (a second cause that is
not there is a wrong name); two effects when ``causes`` holds both and nothing else. Not a
test (it takes minutes); its figures go into docs/analysis.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from smabench.analysis.candidates import REGISTRY  # noqa: E402
from smabench.analysis.core import analyse  # noqa: E402
from smabench.analysis.data import prepare_session  # noqa: E402
from smabench.analysis.report import summary  # noqa: E402
from smabench.sessions import load_session  # noqa: E402


def sessions_independent(tmp: Path, effect: str, value: float, loads, seed: int, n_cycles: int):
    import independent_sim as ind

    rng = np.random.default_rng(seed)
    fx = {effect: value} if effect != "none" else {}
    world = ind.WireWorld.draw(rng, **fx)
    out = []
    for j, load in enumerate(loads):
        ind.make(tmp / f"s{j}", fx, load, seed + j, n_cycles=n_cycles, world=world)
        out.append(prepare_session(load_session(tmp / f"s{j}")))
    return out


def sessions_plant(tmp: Path, effect: str, value: float, loads, seed: int, n_cycles: int):
    import test_analysis as ta

    fx = [f"{effect}={value:g}"] if effect != "none" else []
    out = []
    for j, load in enumerate(loads):
        ta.make_session(tmp / f"s{j}", fx, load, seed=seed + j, n_cycles=n_cycles)
        out.append(prepare_session(load_session(tmp / f"s{j}")))
    return out


def sessions_third(tmp: Path, effect: str, value: float, loads, seed: int, n_cycles: int):
    import third_sim as ts

    rng = np.random.default_rng(seed)
    if "+" in effect:  # two effects: stress shift at the drawn slope plus a fixed second one
        first, second = effect.split("+")
        fx = {first: value, second: TWO_EFFECTS[second]}
    else:
        fx = {effect: value} if effect != "none" else {}
    world = ts.World.draw(rng, **fx)
    out = []
    for j, load in enumerate(ts.loads_for(world, loads)):
        ts.make(tmp / f"s{j}", fx, load, seed + j, n_cycles=n_cycles, world=world)
        out.append(prepare_session(load_session(tmp / f"s{j}")))
    return out


TWO_EFFECTS = {"latent_heat": 25e3, "cycle_drift": 1e-3}
"""The second effect's value when two are hidden at once (third simulator)."""


def cases(sim: str) -> dict[str, tuple]:
    """effect → (low, high, loads, cycles, expected headline as a function of the value)."""
    if sim == "third":
        from test_analysis_third import CASES, OUTSIDE, expected

        out = {e: (lo, hi, st, nc, (lambda v, e=e: expected(e, v)) if tol else None)
               for e, (lo, hi, tol, st, nc) in CASES.items()}  # fmt: skip
        out["none"] = (0.0, 0.0, [170.0], 12, None)
        for e, (lo, hi, st, nc) in OUTSIDE.items():
            out[e] = (lo, hi, st, nc, None)
        for second in TWO_EFFECTS:
            out[f"stress_shift+{second}"] = (5.0, 12.0, [90.0, 250.0], 12, None)
        return out
    if sim == "independent":
        from test_analysis_independent import CASES, expected

        out = {e: (lo, hi, loads, nc, lambda v, e=e: expected(e, v))
               for e, (lo, hi, _tol, loads, nc) in CASES.items()}  # fmt: skip
    else:
        from test_analysis import RANGES

        out = {e: (lo, hi, loads, 9, lambda v: v) for e, (lo, hi, _tol, loads) in RANGES.items()}
    out["none"] = (0.0, 0.0, [2.0], 9, None)
    out["pulley_friction"] = (10.0, 20.0, [2.0], 9, None)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=10, help="draws per effect (10)")
    ap.add_argument("--sim", choices=["independent", "plant", "third"], default="independent")
    ap.add_argument("--workers", type=int, default=None, help="processes per analysis")
    ap.add_argument("--seed", type=int, default=0, help="first seed (0)")
    ap.add_argument("--only", help="comma-separated effects")
    ap.add_argument("--verbose", action="store_true", help="one line per draw: seed, verdict, why")
    args = ap.parse_args()
    make = {"independent": sessions_independent, "plant": sessions_plant,
            "third": sessions_third}[args.sim]  # fmt: skip
    table = cases(args.sim)
    if args.only:
        table = {k: v for k, v in table.items() if k in args.only.split(",")}
    print(f"{args.sim} simulator, {args.n} draws per effect")
    print(f"{'hidden effect':30s} {'right':>5s} {'unexpl.':>7s} {'none':>5s} {'wrong':>5s}  "
          f"{'param error (median, max)':26s} wrong names")  # fmt: skip
    total_wrong = 0
    for effect, (lo, hi, loads, n_cycles, want) in table.items():
        tally: Counter[str] = Counter()
        errors, wrong = [], []
        for k in range(args.n):
            seed = args.seed + 7919 * k + 31 * len(effect)
            rng = np.random.default_rng(seed)
            value = float(rng.uniform(lo, hi))
            if effect == "ambient_drift" and rng.random() < 0.5:
                value = -value
            with tempfile.TemporaryDirectory() as tmp:
                sess = make(Path(tmp), effect, value, loads, seed, n_cycles)
                doc = summary(analyse(sess, workers=args.workers))
            cause = doc["cause"]
            named = [c["cause"] for c in doc["causes"]]
            if args.verbose:
                print(f"  {effect} seed {seed} value {value:.4g}: {'+'.join(named) or cause} "
                      f"({doc['reason']})", flush=True)  # fmt: skip
            if "+" in effect:
                ok = set(named) == set(effect.split("+"))
                cause = "+".join(named) if named else cause
            else:
                # an effect outside the list: unexplained, or none when the baseline stays
                # within its floor (the "dead band → none under the stated floor")
                right = effect if effect in REGISTRY else (
                    "none" if effect == "none" else "unexplained")  # fmt: skip
                extra = [c for c in named if c != right]  # a second cause that is not there
                ok = (cause == right or (effect not in REGISTRY and effect != "none"
                                         and cause == "none")) and not extra  # fmt: skip
                if extra and cause == right:
                    cause = "+".join(named)
            if ok:
                tally["right"] += 1
                if want is not None:
                    got = doc["parameters"][REGISTRY[effect].headline]["value"]
                    errors.append(abs(got / want(value) - 1.0))
            elif "+" in effect and named and set(named) < set(effect.split("+")):
                tally["unexplained"] += 1  # one of the two named: a miss, not a wrong name
                wrong.append(f"only {cause}")
            elif cause in ("unexplained", "none"):
                tally[cause] += 1
            else:
                tally["wrong"] += 1
                wrong.append(f"{cause}@{value:.3g}")
        total_wrong += tally["wrong"]
        err = f"{np.median(errors):6.1%}, {np.max(errors):6.1%}" if errors else ""
        print(f"{effect:30s} {tally['right']:5d} {tally['unexplained']:7d} {tally['none']:5d} "
              f"{tally['wrong']:5d}  {err:26s} {' '.join(wrong)}", flush=True)  # fmt: skip
    return 1 if total_wrong else 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main()
    print(f"({time.perf_counter() - t0:.0f} s)")
    sys.exit(code)
