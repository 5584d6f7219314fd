"""The offline closed loop: the bench runtime itself, on a simulated clock, in-process devices.

:func:`run_closed_loop` runs :class:`~smabench.bench.runtime.BenchRuntime` — the same
:class:`~smabench.bench.tick.ControlTick` as on the bench: interlocks, the temperature estimate
from the driver's telemetry (measured current, wire voltage so V/I, ambient), the controller's
observe/update, the command every tick — against the simulated devices of
:mod:`smabench.drivers.sim` (the plant in 1 ms sub-steps, the reference driver's current with
its setpoint lease, telemetry frames every 10 ms) with the loop scheduled on their simulated
clock. Nothing here waits on the wall clock, so its figures do not depend on how busy the
machine is.

Used by the unit tests, gain tuning (:mod:`smabench.bench.tuning`) and ``smabench bench control
--offline``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from smabench.bench.runtime import BenchRuntime
from smabench.bench.tick import RuntimeConfig
from smabench.commands import CommandSource
from smabench.drivers.sim import SimBench
from smabench.physics.effects import Effects
from smabench.physics.wire import PAPER_WIRE, Wire
from smabench.sessions import FLAG_AFTER_END

log = logging.getLogger(__name__)

@dataclass
class LoopTrace:
    """One offline session, one entry per recorded tick (units in names).

    ``current_a``: the commanded current; ``temperature_c``: the plant's true wire temperature
    at the tick; ``estimate_c``: the tick's estimate; ``status`` / ``reason``: how it ended."""

    t_s: np.ndarray
    current_a: np.ndarray
    position_mm: np.ndarray
    setpoint_mm: np.ndarray
    temperature_c: np.ndarray
    estimate_c: np.ndarray
    mode: list[str]
    status: str = "completed"
    reason: str = ""
    rows: list[dict] = field(default_factory=list, repr=False)


def run_closed_loop(
    controller: CommandSource,
    load_kg: float,
    duration_s: float,
    dt_s: float = 0.0125,
    wire: Wire = PAPER_WIRE,
    effects: Effects | None = None,
    noise_mm: float = 0.002,
    on_tick: Callable[[int, float], None] | None = None,
    substep_s: float = 1e-3,
    seed: int = 3,
    *,
    config: RuntimeConfig | None = None,
    bench: SimBench | None = None,
    keep_rows: bool = False,
) -> LoopTrace:
    """Run ``controller`` (a protocol or a controller) for ``duration_s`` s of simulated time
    (ticks at 0, dt_s, … below duration_s) or until it is done.

    ``dt_s``: the loop period, s (12.5 ms: the benchmark's 400 Hz at 5× speed); ``on_tick(k,
    t_s)`` is called before each tick (e.g. to switch modes); ``config``: the runtime's limits
    (default: the bench's, at this period, wire and duration); ``bench``: simulated devices to
    use (e.g. with a fault to inject from ``on_tick``); ``keep_rows``: keep the recorded rows.
    """
    if bench is None:
        bench = SimBench(
            load_kg, wire, effects, noise_mm=noise_mm, seed=seed, substep_s=substep_s
        )
    if config is None:
        n = int(round(duration_s / dt_s))
        config = RuntimeConfig(rate_hz=1.0 / dt_s, wire=wire, max_duration_s=(n - 0.5) * dt_s)
    rows: list[dict] = []
    true_c: list[float] = []

    def record(row: dict) -> None:
        if int(row["flags"] or 0) & FLAG_AFTER_END:  # the proof that the output went off,
            return  # after the session's end: not part of the closed loop's trace
        rows.append(row)
        true_c.append(bench.plant.state.temperature_c)

    def before_tick(k: int, t_s: float) -> None:  # not for the tick that ends at the duration
        if on_tick is not None and t_s <= config.max_duration_s * config.time_scale:
            on_tick(k, t_s)

    rt = BenchRuntime(
        bench.source, bench.sensor, controller, record, config, on_tick=before_tick,
        clock=bench.clock.now, sleep=bench.clock.sleep,
    )  # fmt: skip
    result = rt.run()
    if result.status == "aborted" and not result.reason.startswith("maximum duration"):
        log.warning("offline loop ended early: %s", result.reason)

    def col(name: str) -> np.ndarray:
        return np.array([np.nan if r[name] is None else r[name] for r in rows], dtype=float)

    return LoopTrace(
        col("t_s"), col("current_set_A"), col("position_mm"), col("setpoint_mm"),
        np.asarray(true_c, dtype=float), col("temperature_est_C"), [r["mode"] for r in rows],
        "completed" if result.reason.startswith("maximum duration") else result.status,
        result.reason, rows if keep_rows else [],
    )  # fmt: skip
