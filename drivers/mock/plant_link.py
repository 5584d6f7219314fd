"""The plant simulation as the mock devices see it: one thread-safe, real-time stepped wire.

The serial mock (current driver) steps it with the current it drives through the wire and reads
back the wire's resistance and the ambient temperature; the Modbus sensor server reads the
slider position from it. Time is the driver's device time (ms), so a mock run at ``speed`` × real
time stays consistent between both devices.
"""

from __future__ import annotations

import logging
import threading

from smabench.physics.effects import Effects
from smabench.physics.plant import Plant, PlantState
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)


class PlantLink:
    """A :class:`~smabench.physics.plant.Plant` shared between mock devices (thread-safe)."""

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
    ) -> None:
        if not 0.0 < load_kg <= 10.0:
            raise ValueError(f"load must be in (0, 10] kg, got {load_kg}")
        self.plant = Plant(
            load_kg, wire, effects, ambient_c=ambient_c, noise_mm=noise_mm, seed=seed
        )
        self.max_step_s = max_step_s
        self._lock = threading.Lock()
        self._state: PlantState = self.plant.state

    def step(self, dt_s: float, current_a: float) -> PlantState:
        """Advance by ``dt_s`` (s) with ``current_a`` (A) flowing; sub-steps of ≤ max_step_s."""
        with self._lock:
            remaining = max(dt_s, 0.0)
            state = self._state
            while remaining > 1e-12:
                h = min(self.max_step_s, remaining)
                state = self.plant.step(h, max(current_a, 0.0))
                remaining -= h
            self._state = state
            return state

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
