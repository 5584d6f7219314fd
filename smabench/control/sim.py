"""Closed loop in one process, without transports: the controller against ``Plant.step``.

Mimics one runtime tick (temperature estimate from the measured current, observe, update,
apply the current for one period) for unit tests and for tuning; the benchmark
(``smabench bench control``) runs the same controller against the mock bench over the real
transports instead. Like the mock bench, the plant is stepped in sub-steps of ``substep_s``
(1 ms) and the driver's current follows the command with the firmware's first-order settling
(``current_tau_s``, 8 ms; the mock firmware's ``CURRENT_TAU_MS``), so the loop sees the same
actuator lag as on the bench.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from smabench.physics.effects import Effects
from smabench.physics.plant import Plant
from smabench.physics.thermal import TemperatureEstimator
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)

CURRENT_TAU_S = 0.008
"""Settling time constant of the driver's current loop, s (the mock firmware's)."""


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
    dt_s: float = 0.0125,
    wire: Wire = PAPER_WIRE,
    effects: Effects | None = None,
    noise_mm: float = 0.002,
    on_tick=None,
    substep_s: float = 1e-3,
    current_tau_s: float = CURRENT_TAU_S,
    seed: int = 3,
) -> LoopTrace:
    """Run ``controller`` (a command source with ``observe``) for ``duration_s`` s or until done.

    ``dt_s`` is the loop period, s (12.5 ms: the benchmark's 400 Hz at 5× speed);
    ``on_tick(k, t_s)`` is called before each tick (e.g. to switch modes). The recorded current
    is the commanded one."""
    plant = Plant(load_kg, wire, effects or Effects(), noise_mm=noise_mm, seed=seed)
    est = TemperatureEstimator(wire)
    rows = []
    modes = []
    command_a = 0.0
    flowing_a = 0.0  # the driver's current, lagging the command
    mean_a = 0.0  # mean current over the last period (what the estimator integrates)
    n_sub = max(1, int(round(dt_s / substep_s)))
    h = dt_s / n_sub
    lag = math.exp(-h / current_tau_s) if current_tau_s > 0 else 0.0
    n = int(round(duration_s / dt_s))
    pos = plant.state.position_mm
    for k in range(n):
        t = k * dt_s
        if on_tick is not None:
            on_tick(k, t)
        temp_est = est.update(dt_s, mean_a)
        if hasattr(controller, "observe"):
            controller.observe(temp_est, 22.0, None, pos)
        step = controller.update(t, pos)
        command_a = float(step.current_set_a)
        sp = getattr(step, "setpoint_mm", None)
        rows.append((t, command_a, pos, np.nan if sp is None else sp, plant.state.temperature_c,
                     temp_est))  # fmt: skip
        modes.append(getattr(step, "mode", "open_loop"))
        if step.done:
            break
        p_sum = 0.0
        for _ in range(n_sub):
            flowing_a = command_a + (flowing_a - command_a) * lag
            s = plant.step(h, flowing_a)
            p_sum += flowing_a * flowing_a
        mean_a = math.sqrt(p_sum / n_sub)  # same heating as the flowing current
        pos = s.position_mm
    a = np.array(rows)
    return LoopTrace(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5], modes)
