"""The plant simulation as the mock devices see it: one thread-safe, real-time stepped wire.

The serial mock (current driver) steps it with the current it drives through the wire and reads
back the wire's resistance and the ambient temperature; the Modbus sensor server reads the
slider position from it. Time is the driver's device time (ms), so a mock run at ``speed`` × real
time stays consistent between both devices.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from smabench.physics.effects import Effects
from smabench.physics.plant import Plant, PlantState
from smabench.physics.resistance import ResistivityModel
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)


TRACE_COLUMNS = ("t_s", "current_A", "temperature_C", "position_mm")


class PlantTrace:
    """What the plant really got, as CSV: one row per step of the link (device time, the current
    that flowed, the wire's temperature, the slider position), flushed at least once a second,
    so safety and accuracy can be checked from outside the host code (``smabench mock --trace``).
    """

    def __init__(self, path: str | Path, flush_s: float = 1.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "w", encoding="utf-8", newline="")  # noqa: SIM115
        self._fh.write(",".join(TRACE_COLUMNS) + "\n")
        self._flush_s = flush_s
        self._last_flush = time.monotonic()

    def write(self, t_s: float, current_a: float, temperature_c: float, position_mm: float) -> None:
        self._fh.write(f"{t_s:.6f},{current_a:.6f},{temperature_c:.4f},{position_mm:.6f}\n")
        now = time.monotonic()
        if now - self._last_flush >= self._flush_s:
            self._fh.flush()
            self._last_flush = now

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()


class PlantLink:
    """A :class:`~smabench.physics.plant.Plant` shared between mock devices (thread-safe).

    ``resistivity``: the wire's resistance from that model, R(ξ, T, ε)
    (:mod:`smabench.physics.resistance`), which the driver's wire voltage then reads; None: the
    plant's default two-phase resistance."""

    def __init__(
        self,
        load_kg: float = 2.0,
        wire: Wire = PAPER_WIRE,
        effects: Effects | None = None,
        *,
        ambient_c: float = 22.0,
        noise_mm: float = 0.002,
        seed: int = 0,
        max_step_s: float = 1e-3,
        trace: str | Path | None = None,
        resistivity: ResistivityModel | None = None,
    ) -> None:
        if not 0.0 < load_kg <= 10.0:
            raise ValueError(f"load must be in (0, 10] kg, got {load_kg}")
        self.plant = Plant(
            load_kg, wire, effects, ambient_c=ambient_c, noise_mm=noise_mm, seed=seed,
            resistivity=resistivity,
        )  # fmt: skip
        self.max_step_s = max_step_s
        self._lock = threading.Lock()
        self._state: PlantState = self.plant.state
        self.t_s = 0.0  # device time the plant has been stepped through, s
        self.trace = PlantTrace(trace) if trace is not None else None

    def step(self, dt_s: float, current_a: float) -> PlantState:
        """Advance by ``dt_s`` (s) with ``current_a`` (A) flowing; sub-steps of ≤ max_step_s."""
        with self._lock:
            remaining = max(dt_s, 0.0)
            state = self._state
            while remaining > 1e-12:
                h = min(self.max_step_s, remaining)
                state = self.plant.step(h, max(current_a, 0.0))
                remaining -= h
                self.t_s += h
                if self.trace is not None:
                    self.trace.write(
                        self.t_s, max(current_a, 0.0), state.temperature_c, state.position_mm
                    )
            self._state = state
            return state

    def close(self) -> None:
        """Flush and close the trace (idempotent)."""
        with self._lock:
            if self.trace is not None:
                self.trace.close()

    @property
    def state(self) -> PlantState:
        with self._lock:
            return self._state

    def position_mm(self) -> float:
        """Sensor reading of the slider position, mm (source for the Modbus server)."""
        return float(self.state.position_mm)

    def resistance_ohm(self) -> float:
        return float(self.state.resistance_ohm)

    def ambient_c(self) -> float:
        return float(self.state.ambient_c)
