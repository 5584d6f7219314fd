"""The device seams the bench runtime drives: a current source and a displacement sensor.

Every implementation — the real clients over serial/Modbus (:mod:`.current_source`,
:mod:`.displacement`), the in-process simulated devices backed by the plant, the clients over
the emulated firmware — satisfies these protocols, and one device test suite runs against each
(``tests/test_devices.py``). The runtime depends on these types only, never on ``hasattr``.

``make_safe`` is part of the contract (python-microscope's): it puts the device in its safe
state (output off, enable off), is idempotent, may be called from any thread and at any time
(also before connect and after close), and never raises — it returns False when it could not
confirm the safe state.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from smabench.drivers.displacement import Sample
from smabench.drivers.protocol import Telemetry

__all__ = ["CurrentSourceDevice", "DisplacementDevice", "Sample", "Telemetry"]


@runtime_checkable
class CurrentSourceDevice(Protocol):
    """A connected current driver for the wire (units: A, s)."""

    def enable(self, on: bool) -> None:
        """Output stage on/off (off: no current flows until the next enable(True))."""

    def set_current(self, current_a: float) -> object:
        """Command the wire current, A (0 … the device's limit)."""

    def latest(self) -> Telemetry | None:
        """The newest telemetry frame, or None before the first."""

    def telemetry_age_s(self) -> float | None:
        """Seconds since the newest telemetry frame arrived (host clock), None before any."""

    def fault_text(self) -> str:
        """A latched device fault in words, or '' when there is none."""

    def make_safe(self) -> bool:
        """Output off now (see the module docstring); True when confirmed."""


@runtime_checkable
class DisplacementDevice(Protocol):
    """A connected displacement sensor (units: mm, s)."""

    def read_or_flag(self) -> Sample:
        """One reading; never raises for link problems: they come back as flagged samples."""

    def make_safe(self) -> object:
        """Stop anything the sensor was asked to do (it is passive); never raises."""
