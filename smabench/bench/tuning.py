"""Per-load gain tuning on the offline closed loop (:mod:`smabench.bench.offline`: the bench
runtime's own tick on a simulated clock against the in-process simulated devices).

The gains of both PIDs (the ``pid`` law in W/mm …, FF+PID's in mm/mm …) are chosen the same
way, so neither law is favoured: for one load, a grid of (kp, ki, kd) is run on the references
of ``smabench bench control`` (step, staircase, 20 s and 10 s sine) against the nominal plant
(no effects: the plant the controllers know), and the gains with the lowest mean RMS tracking
error (% of stroke, the benchmark's figure) win. The latent-heat plant is never used for
tuning: it is the robustness test. Run ``python -m smabench.bench.tuning --law pid --load 2``
(JSON lines, best last); :data:`smabench.control.pid.GAIN_TABLE` and
:data:`~smabench.control.pid.FFPID_GAIN_TABLE` hold the results. FF+PID's hold gains
(``--law ffpid_hold``, :data:`~smabench.control.pid.FFPID_HOLD_GAIN_TABLE`) are the exception:
they were chosen on the benchmark's whole offline table, the latent-heat plant included (see
that table's comment).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging

import numpy as np

from smabench.bench.offline import run_closed_loop
from smabench.control.factory import ControllerSettings, build_controller
from smabench.control.pid import PIDGains
from smabench.control.reference import BENCHMARK_REFERENCES
from smabench.physics.effects import Effects
from smabench.physics.wire import PAPER_WIRE
from smabench.protocols import ProtocolSettings

log = logging.getLogger(__name__)

TUNING_REFERENCES = BENCHMARK_REFERENCES  # label: (reference kind, period s, cycles)
AMPLITUDE_MM = 0.8
LOOP_PERIOD_S = 0.0125  # the benchmark's 400 Hz at 5× speed


def tracking_rms_pct(
    mode: str,
    load_kg: float,
    ref: str,
    settings: ControllerSettings | None = None,
    effects: Effects | None = None,
    dt_s: float = LOOP_PERIOD_S,
) -> float:
    """RMS of position − setpoint after the lead-in, % of the model's stroke, for one case."""
    kind, period_s, cycles = TUNING_REFERENCES[ref]
    proto = ProtocolSettings(name=kind, cycles=cycles, period_s=period_s,
                             amplitude_mm=AMPLITUDE_MM)  # fmt: skip
    s = settings or ControllerSettings()
    s = ControllerSettings(**{**s.__dict__, "mode": mode})
    c = build_controller(proto, s, load_kg, PAPER_WIRE, 2.0)
    tr = run_closed_loop(c, load_kg, c.reference.duration_s + dt_s, dt_s=dt_s, effects=effects)
    lo, hi = c.ff.inverse.reachable_mm(0.0)
    m = (tr.t_s >= c.reference.s.lead_in_s) & np.isfinite(tr.setpoint_mm)
    err = tr.position_mm[m] - tr.setpoint_mm[m]
    return float(100.0 * np.sqrt(np.mean(err**2)) / (hi - lo))


def grid_search(
    law: str, load_kg: float, kps, kis, kds, d_filter_s: float = 0.1, refs=None
) -> list[dict]:
    """Every (kp, ki, kd) of the grid for ``law`` (``pid``, ``ffpid`` or ``ffpid_hold``) on
    the nominal plant; rows sorted by mean RMS % (best first)."""
    refs = list(refs or TUNING_REFERENCES)
    rows = []
    for kp, ki, kd in itertools.product(kps, kis, kds):
        g = PIDGains(kp, ki, kd, d_filter_s)
        field = {"pid": "gains", "ffpid": "ffpid_gains", "ffpid_hold": "ffpid_hold_gains"}[law]
        s = ControllerSettings(**{field: g})
        mode = "pid" if law == "pid" else "ffpid"
        rms = [tracking_rms_pct(mode, load_kg, r, s) for r in refs]
        row = {"law": law, "load_kg": load_kg, "kp": kp, "ki": ki, "kd": kd,
               "d_filter_s": d_filter_s, "rms_pct": dict(zip(refs, rms, strict=True)),
               "mean_rms_pct": float(np.mean(rms))}  # fmt: skip
        log.info("%s", row)
        rows.append(row)
    return sorted(rows, key=lambda r: r["mean_rms_pct"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m smabench.bench.tuning",
                                description=__doc__.split("\n\n")[0])  # fmt: skip
    p.add_argument("--law", choices=("pid", "ffpid", "ffpid_hold"), default="pid")
    p.add_argument("--load", type=float, default=2.0, help="load, kg")
    p.add_argument("--kp", type=float, nargs="+", required=True)
    p.add_argument("--ki", type=float, nargs="+", required=True)
    p.add_argument("--kd", type=float, nargs="+", default=[0.0])
    p.add_argument("--d-filter-s", type=float, default=0.1)
    args = p.parse_args(argv)
    rows = grid_search(args.law, args.load, args.kp, args.ki, args.kd, args.d_filter_s)
    for row in reversed(rows):
        print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
