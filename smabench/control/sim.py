"""Closed loop in one process, without transports: the controller against ``Plant.step``.

Mimics one runtime tick (temperature estimate from the commanded current, observe, update,
apply the current for one period) for unit tests and for tuning; the benchmark
(``smabench bench control``) runs the same controller against the mock bench over the real
transports instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smabench.physics.effects import Effects
from smabench.physics.plant import Plant
from smabench.physics.thermal import TemperatureEstimator
from smabench.physics.wire import PAPER_WIRE, Wire


@dataclass
class LoopTrace:
    t_s: np.ndarray
    current_a: np.ndarray
    position_mm: np.ndarray
    setpoint_mm: np.ndarray
    temperature_c: np.ndarray
    estimate_c: np.ndarray
    mode: list[str]


def run_closed_loop(
    controller,
    load_kg: float,
    duration_s: float,
    dt_s: float = 0.01,
    wire: Wire = PAPER_WIRE,
    effects: Effects | None = None,
    noise_mm: float = 0.002,
    on_tick=None,
) -> LoopTrace:
    """Run ``controller`` (a command source with ``observe``) for ``duration_s`` or until done.

    ``on_tick(k, t_s)`` is called before each tick (e.g. to switch modes)."""
    plant = Plant(load_kg, wire, effects or Effects(), noise_mm=noise_mm, seed=3)
    est = TemperatureEstimator(wire)
    rows = []
    modes = []
    current = 0.0
    n = int(round(duration_s / dt_s))
    pos = plant.state.position_mm
    for k in range(n):
        t = k * dt_s
        if on_tick is not None:
            on_tick(k, t)
        temp_est = est.update(dt_s, current)
        if hasattr(controller, "observe"):
            controller.observe(temp_est, 22.0, None, pos)
        step = controller.update(t, pos)
        current = float(step.current_set_a)
        sp = getattr(step, "setpoint_mm", None)
        rows.append((t, current, pos, np.nan if sp is None else sp, plant.state.temperature_c,
                     temp_est))  # fmt: skip
        modes.append(getattr(step, "mode", "open_loop"))
        if step.done:
            break
        s = plant.step(dt_s, current)
        pos = s.position_mm
    a = np.array(rows)
    return LoopTrace(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5], modes)
