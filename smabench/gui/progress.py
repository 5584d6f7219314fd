"""Progress and remaining time of a running open-loop protocol, estimated from its settings
from the first second (no Qt here).

The runtime's own progress counts finished cycles (0 through the whole first cycle). Here a
cycle's planned length comes from the protocol's settings (heat + the cooling's timeout, or the
fixed phases of ``incomplete``, ``inner``, ``ramp`` and ``step``); once cycles have finished,
their measured mean length replaces the plan for the cycles still to come (cooling usually ends
on the settle criterion, before its timeout). Times are device time (the session's ``t_s``);
divide by the mock's speed for wall time.
"""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger(__name__)


def planned_cycles_s(protocol: dict[str, Any]) -> list[float]:
    """Planned length of each cycle, s (device time), from the protocol's settings (schema
    defaults for those left out)."""
    from smabench.settings import default

    def g(key: str) -> Any:
        return protocol.get(key, default("protocol." + key))

    name = g("name")
    n = int(g("cycles"))
    if name == "step":
        return [float(g("hold_s"))] * len(g("levels_a"))
    if name == "ramp":
        return [2.0 * float(g("ramp_s"))] * n
    heat, cool = float(g("heat_s")), float(g("cool_timeout_s"))
    out = []
    for k in range(n):
        last = k == n - 1
        if name == "incomplete" and not last:
            out.append(heat + float(g("partial_cool_s")))
        elif name == "inner":
            h = heat if k == 0 else float(g("inner_heat_s"))
            out.append(h + (cool if last else float(g("inner_cool_s"))))
        else:
            out.append(heat + cool)
    return out


def estimate(plan_s: list[float], t_s: float, cycle: int, cycle_start_s: float,
             done: bool = False) -> tuple[float, float]:  # fmt: skip
    """(fraction done 0 … 1, remaining s) at session time ``t_s`` in cycle ``cycle`` (from 0)
    that began at ``cycle_start_s``. Finished cycles count as they ran; the current one as
    planned (at least as long as it has run); later ones as planned, scaled by how the finished
    ones compared with their plan."""
    if done or not plan_s:
        return 1.0, 0.0
    k = min(max(0, int(cycle)), len(plan_s) - 1)
    scale = 1.0
    if k > 0 and sum(plan_s[:k]) > 0:  # the cycles that finished, against their plan
        scale = min(1.0, cycle_start_s / sum(plan_s[:k]))
    in_cycle = max(0.0, t_s - cycle_start_s)
    current_left = max(0.0, plan_s[k] * scale - in_cycle)
    remaining = current_left + scale * sum(plan_s[k + 1:])
    total = t_s + remaining
    return (min(1.0, t_s / total) if total > 0 else 0.0), remaining
