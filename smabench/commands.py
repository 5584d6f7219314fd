"""What the bench asks each tick for a current: the command-source seam and its one step type.

A command source is an open-loop experiment protocol (:class:`smabench.protocols.Protocol`) or
a position controller (:class:`smabench.control.Controller`). Both answer
``update(t_s, position_mm)`` with a :class:`CommandStep`; a controller also takes the tick's
temperature estimate through ``observe`` first (:class:`ObservingCommandSource`). The seam is
typed so that a renamed method fails at the type check and in the tests, not silently at run
time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class CommandStep:
    """One tick's command (units in names).

    ``current_set_a``: the current to drive, A (≥ 0); ``cycle``: 0-based cycle of the protocol or
    reference; ``phase``: what the source is doing (``heat``, ``cool``, ``track`` …);
    ``setpoint_mm``: position setpoint (closed loop only); ``mode``: the control law
    (``open_loop`` | ``pid`` | ``ff`` | ``ffpid``); ``done``: the source has finished;
    ``power_w``/``ff_power_w``: commanded and feed-forward heating power, W;
    ``reference_temperature_c``: the feed-forward's planned temperature, °C.
    """

    current_set_a: float
    cycle: int
    phase: str
    setpoint_mm: float | None = None
    mode: str = "open_loop"
    done: bool = False
    power_w: float = 0.0
    ff_power_w: float = 0.0
    reference_temperature_c: float | None = None


@runtime_checkable
class CommandSource(Protocol):
    """An open-loop source: a current from time and position."""

    def update(self, t_s: float, position_mm: float) -> CommandStep: ...


@runtime_checkable
class ObservingCommandSource(CommandSource, Protocol):
    """A closed-loop source: takes the tick's estimate before ``update``.

    ``observe(temperature_c, ambient_c, resistance_ohm, position_mm)``: the runtime's wire
    temperature estimate, °C; ambient, °C; measured wire resistance, Ω (None when the driver
    reports no voltage); position, mm (None when the sample is invalid)."""

    def observe(
        self,
        temperature_c: float,
        ambient_c: float,
        resistance_ohm: float | None,
        position_mm: float | None,
    ) -> None: ...
