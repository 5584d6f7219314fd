"""The device seams the bench runtime drives: a current source and a displacement sensor.

Every implementation — the real clients over serial/Modbus (:mod:`.current_source`,
:mod:`.displacement`), the in-process simulated devices backed by the plant, the clients over
the emulated firmware — satisfies these protocols, and one device test suite runs against each
(``tests/test_devices.py``). The runtime depends on these types only, never on ``hasattr``.
A sensor's reading (:class:`Sample`), its flag bits and its typed link errors are declared here,
with the seam, not in one sensor's driver.

``make_safe`` is part of the contract (python-microscope's): it puts the device in its safe
state (output off, enable off), is idempotent, may be called from any thread and at any time
(also before connect and after close), and never raises — it returns False when it could not
confirm the safe state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from smabench.drivers.protocol import Telemetry

__all__ = ["CurrentSourceDevice", "DisplacementDevice", "Sample", "Telemetry", "FLAG_NAMES",
           "FLAGS_INVALID", "describe_flags", "SensorError"]  # fmt: skip

# --------------------------------------------------------------------------------------------
# a displacement sensor's errors and flags (every sensor implementation's)
# --------------------------------------------------------------------------------------------


class SensorError(Exception):
    """Base class of every displacement-sensor error."""

    flag = 0


class SensorTimeout(SensorError):  # noqa: N818 - public API name
    """The sensor did not answer within the timeout (after the configured retries)."""

    flag = 0x01


class SensorException(SensorError):  # noqa: N818 - public API name
    """The sensor answered with a Modbus exception response; ``code`` is the exception code."""

    flag = 0x02

    def __init__(self, code: int, message: str | None = None) -> None:
        self.code = int(code)
        name = EXCEPTION_NAMES.get(self.code, "unknown")
        super().__init__(message or f"Modbus exception {self.code} ({name})")


class SensorLinkLost(SensorError):  # noqa: N818 - public API name
    """No connection to the sensor (refused, closed, serial port gone); reconnects on next read."""

    flag = 0x04


class SensorFrameError(SensorError):
    """Bytes arrived but no valid frame (bad CRC, garbage, wrong length)."""

    flag = 0x08


FLAG_TIMEOUT = SensorTimeout.flag
FLAG_EXCEPTION = SensorException.flag
FLAG_LINK_LOST = SensorLinkLost.flag
FLAG_FRAMING = SensorFrameError.flag
FLAG_SENSOR_STATUS = 0x10  # the sensor's status says error (``error_mask`` / ``error_values``)
FLAG_RETRIED = 0x20  # the read succeeded, but only after a retry
FLAG_OUT_OF_RANGE = 0x40  # the position is a sentinel, NaN, or outside the map's ``valid_range``

FLAG_NAMES = {
    FLAG_TIMEOUT: "timeout",
    FLAG_EXCEPTION: "exception",
    FLAG_LINK_LOST: "link_lost",
    FLAG_FRAMING: "framing",
    FLAG_SENSOR_STATUS: "sensor_status",
    FLAG_RETRIED: "retried",
    FLAG_OUT_OF_RANGE: "out_of_range",
}
#: flags meaning "no valid position in this sample" (``position_mm`` is NaN: never fed to the
#: controller)
FLAGS_INVALID = (
    FLAG_TIMEOUT | FLAG_EXCEPTION | FLAG_LINK_LOST | FLAG_FRAMING | FLAG_SENSOR_STATUS
    | FLAG_OUT_OF_RANGE
)

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}


def describe_flags(flags: int) -> str:
    """``"timeout|retried"`` style text for a flags word ('' when 0)."""
    names = [name for bit, name in FLAG_NAMES.items() if flags & bit]
    rest = flags & ~sum(FLAG_NAMES)
    if rest:
        names.append(hex(rest))
    return "|".join(names)


@dataclass(frozen=True, slots=True)
class Sample:
    """One reading. ``t_s`` is ``time.monotonic()`` at the middle of the request."""

    position_mm: float
    t_s: float
    flags: int = 0
    latency_s: float = 0.0
    status: int | None = None
    temperature_c: float | None = None
    error: str = ""

    @property
    def ok(self) -> bool:
        """True when ``position_mm`` is a real measurement: no link problem, no status error,
        no out-of-range code (an invalid sample's ``position_mm`` is NaN)."""
        return not self.flags & FLAGS_INVALID



@runtime_checkable
class CurrentSourceDevice(Protocol):
    """A connected current driver for the wire (units: A, s)."""

    def enable(self, on: bool) -> None:
        """Output stage on/off (off: no current flows until the next enable(True))."""

    def set_current(self, current_a: float) -> object:
        """Command the wire current, A (0 … the device's limit)."""

    @property
    def last_ack_host_time(self) -> float | None:
        """Host clock (the telemetry's ``host_time`` clock) when the newest ACK arrived, in the
        byte stream's order with the frames (None before the first)."""

    def set_probe_current(self, current_a: float) -> None:
        """Hold a small probe current while the output is enabled, A (0 = off, at most 0.1 A;
        ValueError outside): the device drives the larger of the setpoint and the probe, so the
        wire's resistance is measured while it cools. Everything that turns the output off turns
        the probe off too (it stays off until set again)."""

    def latest(self) -> Telemetry | None:
        """The newest telemetry frame, or None before the first."""

    def telemetry_age_s(self) -> float | None:
        """Seconds since the newest telemetry frame arrived (host clock), None before any."""

    def fault_text(self) -> str:
        """A latched device fault in words, or '' when there is none."""

    def make_safe(self) -> bool:
        """Output off now (see the module docstring); True when confirmed."""


class PendingRead(Protocol):
    """A reading asked in the background (:meth:`DisplacementDevice.read_in_background`)."""

    def done(self) -> bool:
        """Whether its answer (or its timeout) has come."""

    def result(self, timeout: float | None = None) -> Sample:
        """The reading (flagged like :meth:`DisplacementDevice.read_or_flag`'s); waits for it
        up to ``timeout`` s when not done."""


@runtime_checkable
class DisplacementDevice(Protocol):
    """A connected displacement sensor (units: mm, s)."""

    def read_or_flag(self) -> Sample:
        """One reading; never raises for link problems: they come back as flagged samples."""

    def read_in_background(self) -> PendingRead:
        """:meth:`read_or_flag` without holding the caller: a silent sensor's request waits its
        timeout meanwhile. The caller does not use the sensor until it is done."""

    def make_safe(self) -> object:
        """Stop anything the sensor was asked to do (it is passive); never raises."""
