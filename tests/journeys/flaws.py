"""What a real bench puts into a recording, applied to a copy of a recorded session.

A recording from the mock bench is clean apart from the few rows its sensor flags; a lab's is not.
:func:`with_bench_flaws` copies a session folder and gives it, in the contract's own terms
(DESIGN.md §3: empty cells for missing values, the ``flags`` bits of ``smabench.sessions``):

- sensor-invalid rows: ``position_mm`` empty and ``flags`` with the sensor-invalid bit, scattered
  and in short bursts;
- a dropout: a stretch of rows missing entirely (the loop stalled or the sensor stopped answering);
- missed deadlines: the deadline bit on rows whose period came late, with the late period;
- time jitter: every period moved by a little (strictly increasing time kept);
- a partial first cycle: the recording starts part-way through the first heating;
- an aborted end: cut part-way through the last cycle, ``status`` aborted with a reason.

Only the standard library: the journey must not depend on the code under test to make its input.
"""

from __future__ import annotations

import csv
import json
import random
import shutil
from pathlib import Path

FLAG_SENSOR_INVALID = 1 << 8  # smabench.sessions (the session contract's flag bits)
FLAG_DEADLINE_MISSED = 1 << 10


def with_bench_flaws(
    session: Path,
    out: Path,
    *,
    seed: int = 0,
    invalid_fraction: float = 0.004,
    dropout_s: float = 0.6,
    jitter_fraction: float = 0.15,
    partial_first_s: float = 0.8,
    abort_fraction: float = 0.93,
) -> Path:
    """Copy ``session`` to ``out`` with a real bench's flaws (see the module doc); returns
    ``out``. ``abort_fraction`` < 1 cuts the recording there and marks it aborted; 1 keeps it
    whole and completed."""
    rng = random.Random(seed)
    shutil.copytree(session, out)
    samples = out / "samples.csv"
    with samples.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader)
        rows = list(reader)
    col = {name: k for k, name in enumerate(header)}
    t0 = float(rows[0][col["t_s"]])
    # partial first cycle: start after the first heating began
    heat_start = next(
        (k for k, r in enumerate(rows) if float(r[col["current_A"]] or 0) > 0.2), 0
    )
    t_cut = float(rows[heat_start][col["t_s"]]) + partial_first_s
    rows = [r for r in rows if float(r[col["t_s"]]) >= t_cut]
    # aborted end
    if abort_fraction < 1.0:
        rows = rows[: int(len(rows) * abort_fraction)]
    # a dropout in the middle third
    t = [float(r[col["t_s"]]) for r in rows]
    mid = len(rows) // 2 + rng.randrange(-len(rows) // 6, len(rows) // 6)
    drop_end = next((k for k in range(mid, len(rows)) if t[k] - t[mid] >= dropout_s), mid)
    rows = rows[:mid] + rows[drop_end:]
    # jitter (keeps time strictly increasing: each period scaled within ±jitter_fraction)
    t = [float(r[col["t_s"]]) for r in rows]
    new_t = [t[0]]
    for k in range(1, len(t)):
        period = (t[k] - t[k - 1]) * (1.0 + rng.uniform(-jitter_fraction, jitter_fraction))
        new_t.append(new_t[-1] + max(period, 1e-6))
    for r, tk in zip(rows, new_t, strict=True):
        r[col["t_s"]] = f"{tk:.6f}"
    # sensor-invalid rows, single and in bursts of up to 5
    n_invalid = max(3, int(len(rows) * invalid_fraction))
    k = 0
    while k < n_invalid:
        start = rng.randrange(1, len(rows) - 6)
        for j in range(start, start + rng.choice((1, 1, 2, 5))):
            rows[j][col["position_mm"]] = ""
            rows[j][col["flags"]] = str(int(rows[j][col["flags"]] or 0) | FLAG_SENSOR_INVALID)
            k += 1
    # missed deadlines: a late period, flagged
    for _ in range(max(2, len(rows) // 2000)):
        j = rng.randrange(1, len(rows))
        rows[j][col["flags"]] = str(int(rows[j][col["flags"]] or 0) | FLAG_DEADLINE_MISSED)
    with samples.open("w", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)
    meta_path = out / "session.json"
    meta = json.loads(meta_path.read_text())
    if abort_fraction < 1.0:
        meta["status"] = "aborted"
        meta["end_reason"] = "interrupted by the operator"
    meta["journey_flaws"] = {"seed": seed, "t0_s": t0, "partial_first_cut_s": t_cut}
    meta_path.write_text(json.dumps(meta, indent=2))
    (out / "cycles.csv").unlink(missing_ok=True)  # its rows no longer match the samples
    return out
