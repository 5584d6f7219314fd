"""In-process simulated bench devices backed by the plant, on a simulated clock.

No transports, no threads, no wall clock: a :class:`SimClock` says what time it is, and both
devices bring the shared :class:`SimPlant` up to that time whenever they are looked at (the
plant is stepped in sub-steps of ``substep_s``, 1 ms, with the current the simulated driver
drives). The owner of the clock — the offline closed loop, a test — advances it.

- :class:`SimCurrentSource` (a :class:`~smabench.drivers.base.CurrentSourceDevice`) behaves as
  the mock firmware (:mod:`smabench.drivers.mock.firmware`) on the reference driver: the
  current is what the linear sink delivers (:class:`smabench.hardware.LinearSink`: the clamped
  setpoint through the PWM filter's two poles, limited by the compliance); output off at start,
  on ``enable(False)``, on ``make_safe``, on a latched fault, when no command came within the
  host timeout and when no SET_CURRENT renewed the setpoint within the lease (0.25 s each, of
  simulated time); open wire latched as the firmware does. Telemetry every
  ``telemetry_period_s`` (10 ms, as the bench asks for): the mean current and Kelvin wire
  voltage over the frame (an oversampled measurement; the voltage from the plant's
  resistance), the plant's ambient, flags, the setpoint — packed and unpacked through the
  protocol's TELEMETRY payload, so it has the resolution of a real frame. Not modelled: the
  firmware's energy budget (``wire_model_c`` is reported empty), the thermocouple, the e-stop
  input.
- :class:`SimDisplacementSensor` (a :class:`~smabench.drivers.base.DisplacementDevice`): the
  plant's slider position with its sensor noise; flagged NaN samples while a failure is
  injected.

Fault injection for tests: :meth:`SimCurrentSource.inject_fault` (a latched device fault),
:meth:`SimCurrentSource.stall_telemetry` (a dead link: no frames), :meth:`SimDisplacementSensor.
fail` (flagged samples), :meth:`SimPlant.break_wire` (the load falls freely and the wire is an
open circuit: the driver latches OPEN_WIRE as the firmware does).
"""

from __future__ import annotations

import logging
import math
import threading

from smabench.drivers import protocol as p
from smabench.drivers.displacement import FLAG_SENSOR_STATUS, FLAG_TIMEOUT, Sample
from smabench.drivers.mock.firmware import (
    FW_VERSION,
    HARD_LIMIT_MA,
    OPEN_WIRE_MA,
    OPEN_WIRE_MS,
    OPEN_WIRE_SET_MA,
)
from smabench.hardware import ELECTRICAL, LinearSink
from smabench.physics.effects import Effects
from smabench.physics.plant import Plant, PlantState
from smabench.physics.wire import PAPER_WIRE, Wire

log = logging.getLogger(__name__)

__all__ = [
    "SimBench",
    "SimClock",
    "SimCurrentSource",
    "SimDeviceFaultError",
    "SimDisplacementSensor",
    "SimPlant",
]

DEVICE_NAME = "SMA-CD328-SIM"
G_MM_S2 = 9810.0  # free fall of a load whose wire broke, mm/s²
FALL_STOP_MM = 50.0  # the falling load stops this far below where it was (the frame's end stop)


class SimDeviceFaultError(RuntimeError):
    """ENABLE refused: a fault is latched (clear it first)."""


class SimClock:
    """A simulated clock, s. ``sleep`` advances it (so a loop scheduled on it runs at once)."""

    def __init__(self, t_s: float = 0.0) -> None:
        self._t = float(t_s)

    def now(self) -> float:
        return self._t

    def sleep(self, dt_s: float) -> None:
        if dt_s > 0:
            self._t += dt_s

    advance = sleep


class SimPlant:
    """A :class:`~smabench.physics.plant.Plant` stepped lazily up to a :class:`SimClock`.

    The driver attached with :meth:`attach` says which current flows in every sub-step.
    Thread-safe (an e-stop may come from another thread)."""

    def __init__(self, plant: Plant, clock: SimClock, substep_s: float = 1e-3) -> None:
        if not 0.0 < substep_s <= 0.01:
            raise ValueError(f"sub-step must be in (0, 10] ms, got {substep_s * 1e3} ms")
        self.plant = plant
        self.clock = clock
        self.substep_s = substep_s
        self.lock = threading.RLock()
        self.t_s = clock.now()
        self.state: PlantState = plant.state
        self.driver: SimCurrentSource | None = None
        self.broken_at: tuple[float, float] | None = None  # (t_s, position_mm) when it broke

    def attach(self, driver: SimCurrentSource) -> None:
        self.driver = driver

    def sync(self) -> PlantState:
        """Step the plant up to the clock's time; returns the state then."""
        with self.lock:
            now = self.clock.now()
            while now - self.t_s > 1e-12:
                h = min(self.substep_s, now - self.t_s)
                if self.driver is not None:
                    h = self.driver.limit_step(self.t_s, h)
                current_a = self.driver.advance(h) if self.driver is not None else 0.0
                self.state = self.plant.step(h, current_a)
                self.t_s += h
                if self.driver is not None:
                    self.driver.after_step(self.t_s, h, self.state)
            return self.state

    @property
    def broken(self) -> bool:
        return self.broken_at is not None

    def break_wire(self) -> None:
        """The wire breaks now: no current flows any more and the load falls freely."""
        with self.lock:
            state = self.sync()
            self.broken_at = (self.t_s, state.position_mm)
            log.info("simulated wire broke at %.3f s", self.t_s)

    def position_mm(self) -> float:
        """The sensor's view of the slider, mm (a falling load once the wire broke)."""
        with self.lock:
            state = self.sync()
            if self.broken_at is None:
                return float(state.position_mm)
            t_b, pos_b = self.broken_at
            fall = 0.5 * G_MM_S2 * (self.t_s - t_b) ** 2
            return pos_b + min(fall, FALL_STOP_MM)


class SimCurrentSource:
    """The current driver, simulated (see the module docstring). Units: A, s."""

    def __init__(
        self,
        plant: SimPlant,
        *,
        telemetry_period_s: float = 0.01,
        host_timeout_s: float = p.HOST_TIMEOUT_DEFAULT_S,
        lease_s: float = p.LEASE_DEFAULT_S,
        current_limit_a: float | None = None,
    ) -> None:
        lo, hi = p.TELEMETRY_PERIOD_RANGE_S
        if not lo <= telemetry_period_s <= hi:
            raise ValueError(f"telemetry period must be in {lo} … {hi} s")
        self.plant = plant
        self.clock = plant.clock
        self.sink = LinearSink()
        self.telemetry_period_s = telemetry_period_s
        self.host_timeout_s = host_timeout_s
        self.lease_s = lease_s
        self.hard_limit_a = HARD_LIMIT_MA / 1000.0
        self.limit_a = self.hard_limit_a if current_limit_a is None else float(current_limit_a)
        self.info = p.DeviceInfo(p.PROTOCOL_VERSION, FW_VERSION, self.hard_limit_a, DEVICE_NAME)
        self.enabled = False
        self.setpoint_a = 0.0
        self.current_a = 0.0  # flowing now
        self.flags = p.Flag(0)
        self.commands = 0  # commands received (each renews the host timeout)
        self._last_command_s = self.clock.now()
        self._lease_start_s = self.clock.now()
        self._open_s = 0.0
        self._stalled = False
        self._frame_t0 = plant.t_s
        self._next_frame_s = plant.t_s + telemetry_period_s
        self._sum_i = self._sum_v = 0.0
        self._latest: p.Telemetry | None = None
        plant.attach(self)

    # ------------------------------------------------------------------ device side (plant)
    def limit_step(self, t_s: float, h: float) -> float:
        """Shorten a plant sub-step so that it ends on the next telemetry frame."""
        return max(min(h, self._next_frame_s - t_s), 1e-9)

    def _off(self) -> None:
        self.enabled = False
        self.current_a = 0.0
        self.sink.state.pole1_a = self.sink.state.pole2_a = 0.0  # the enable line clamps

    def advance(self, h: float) -> float:
        """The current the sink delivers over the next ``h`` s, A."""
        if not self.enabled:
            self._off()
            return 0.0
        counts = min(self.setpoint_a, self.limit_a) / ELECTRICAL.setpoint_a_per_count
        r_wire = 1e9 if self.plant.broken else self.plant.state.resistance_ohm
        self.current_a = self.sink.step(counts, r_wire, h)
        return self.current_a

    def after_step(self, t_s: float, h: float, state: PlantState) -> None:
        """Device bookkeeping after a plant sub-step ending at ``t_s``: host timeout, lease,
        open-wire detection, telemetry frames."""
        if self.enabled and t_s - self._last_command_s >= self.host_timeout_s:
            log.info("simulated driver: host timeout at %.3f s, output off", t_s)
            self._off()
            self.flags |= p.Flag.HOST_TIMEOUT
        if self.enabled and self.setpoint_a > 0 and t_s - self._lease_start_s >= self.lease_s:
            log.info("simulated driver: setpoint lease expired at %.3f s, output off", t_s)
            self._off()
            self.setpoint_a = 0.0
            self.flags |= p.Flag.LEASE_EXPIRED
        set_ma = min(self.setpoint_a, self.limit_a) * 1000.0
        if self.enabled and set_ma >= OPEN_WIRE_SET_MA and self.current_a * 1000.0 < OPEN_WIRE_MA:
            self._open_s += h
            if self._open_s * 1000.0 >= OPEN_WIRE_MS:
                self._latch(p.Flag.OPEN_WIRE)
        else:
            self._open_s = 0.0
        self._sum_i += self.current_a * h
        self._sum_v += state.voltage_v * h
        if t_s >= self._next_frame_s - 1e-9:
            span = max(t_s - self._frame_t0, 1e-12)
            if not self._stalled:
                self._latest = self._frame(t_s, self._sum_i / span, self._sum_v / span, state)
            self._frame_t0 = t_s
            self._next_frame_s = t_s + self.telemetry_period_s
            self._sum_i = self._sum_v = 0.0

    def _frame(self, t_s: float, current_a: float, voltage_v: float, state: PlantState):
        flags = self.flags | (p.Flag.ENABLED if self.enabled else 0)
        if self.enabled and self.setpoint_a >= self.limit_a > 0:
            flags |= p.Flag.LIMIT_ACTIVE
        counts = min(self.setpoint_a, self.limit_a) / ELECTRICAL.setpoint_a_per_count
        current_a = max(current_a, 0.0)
        tel = p.Telemetry(
            t_ms=int(round(t_s * 1000.0)),
            current_a=current_a,
            voltage_v=max(voltage_v, 0.0),
            duty=min(1.0, counts / ELECTRICAL["setpoint"]["pwm_top"]) if self.enabled else 0.0,
            ambient_c=state.ambient_c,
            flags=p.Flag(flags),
            setpoint_a=self.setpoint_a,
            crc_errors=0,
            frame_errors=0,
            precise_current_a=current_a,
            supply_v=self.sink.supply_at_terminals_v(current_a),
        )  # through the frame's payload: the resolution a real frame has
        return p.Telemetry.from_payload(tel.to_payload(), host_time=t_s)

    def _latch(self, flag: p.Flag) -> None:
        log.warning("simulated driver: fault latched: %s", flag.name)
        self.flags |= flag
        self._off()

    # ------------------------------------------------------------------ host side
    def _command(self) -> None:
        self.plant.sync()  # the old state holds up to now
        self.commands += 1
        self._last_command_s = self.clock.now()

    def connect(self) -> p.DeviceInfo:
        return self.info

    def enable(self, on: bool) -> None:
        """Output on/off; on is refused while a fault is latched
        (:class:`SimDeviceFaultError`)."""
        with self.plant.lock:
            self._command()
            if on:
                if self.flags & p.LATCHED_FAULTS:
                    raise SimDeviceFaultError(f"ENABLE refused: {p.fault_text(self.flags)}")
                self.flags &= ~(p.Flag.HOST_TIMEOUT | p.Flag.LEASE_EXPIRED)
                self.enabled = True
            else:  # as the firmware: output off, the setpoint kept
                self._off()

    def set_current(self, current_a: float) -> p.Status:
        """Current setpoint, A; ValueError outside 0 … the hard limit; above the active limit
        the device clamps it (``Status.CLAMPED``). Renews the host timeout and the lease."""
        if not 0.0 <= current_a <= self.hard_limit_a + 1e-9:
            raise ValueError(
                f"current {current_a} A outside 0 … {self.hard_limit_a} A (device hard limit)"
            )
        with self.plant.lock:
            self._command()
            self._lease_start_s = self.clock.now()
            self.setpoint_a = min(round(float(current_a), 3), self.limit_a)  # mA on the wire
            return p.Status.CLAMPED if current_a > self.limit_a + 1e-9 else p.Status.OK

    def set_limits(self, current_limit_a: float, host_timeout_s: float) -> None:
        lo, hi = p.HOST_TIMEOUT_RANGE_S
        if current_limit_a > self.hard_limit_a + 1e-9 or not lo <= host_timeout_s <= hi:
            raise ValueError("limit above the hard limit or host timeout out of range")
        with self.plant.lock:
            self._command()
            self.limit_a, self.host_timeout_s = float(current_limit_a), float(host_timeout_s)

    def clear_faults(self) -> None:
        with self.plant.lock:
            self._command()
            self.flags = p.Flag(0)

    def latest(self) -> p.Telemetry | None:
        self.plant.sync()
        return self._latest

    def telemetry_age_s(self) -> float | None:
        t = self.latest()
        return None if t is None else self.clock.now() - t.host_time

    def fault_text(self) -> str:
        t = self.latest()
        return p.fault_text(t.flags) if t is not None else ""

    @property
    def link_ok(self) -> bool:
        return not self._stalled

    def make_safe(self) -> bool:
        """Output off now; idempotent, never raises; True (the simulated device always
        confirms)."""
        try:
            with self.plant.lock:
                self.plant.sync()
                self._off()
                self.setpoint_a = 0.0
            return True
        except Exception:  # never raises: this is the emergency path
            log.exception("simulated make_safe")
            self.enabled = False
            self.current_a = 0.0
            return True

    def close(self) -> None:
        self.make_safe()

    # ------------------------------------------------------------------ fault injection
    def inject_fault(self, flag: p.Flag = p.Flag.OVERCURRENT) -> None:
        """Latch a device fault now (output off, reported in the next frame)."""
        with self.plant.lock:
            self.plant.sync()
            self._latch(flag)

    def stall_telemetry(self, stalled: bool = True) -> None:
        """A dead link: no telemetry frames while stalled (the device itself keeps running)."""
        with self.plant.lock:
            self.plant.sync()
            self._stalled = stalled


class SimDisplacementSensor:
    """The displacement sensor, simulated: the plant's slider position, mm."""

    def __init__(self, plant: SimPlant) -> None:
        self.plant = plant
        self.clock = plant.clock
        self.reads = 0
        self._fail_left = 0.0
        self._fail_flag = FLAG_TIMEOUT

    def read_or_flag(self) -> Sample:
        """One reading at the clock's time; a flagged NaN sample while a failure is injected
        (a status-error failure keeps the position and sets ``FLAG_SENSOR_STATUS``)."""
        self.reads += 1
        position = self.plant.position_mm()
        t = self.clock.now()
        if self._fail_left > 0:
            self._fail_left -= 1
            if self._fail_flag == FLAG_SENSOR_STATUS:
                return Sample(position, t, flags=FLAG_SENSOR_STATUS, status=1)
            return Sample(math.nan, t, flags=self._fail_flag, error="injected failure")
        return Sample(position, t)

    def fail(self, count: float = math.inf, flag: int = FLAG_TIMEOUT) -> None:
        """The next ``count`` readings fail with ``flag`` (inf: until :meth:`recover`)."""
        self._fail_left, self._fail_flag = count, flag

    def recover(self) -> None:
        self._fail_left = 0

    def make_safe(self) -> bool:
        """Nothing to switch off on a passive sensor; never raises."""
        return True

    def close(self) -> None:
        pass


class SimBench:
    """Clock, plant, current source and sensor wired together (units in names)."""

    def __init__(
        self,
        load_kg: float = 2.0,
        wire: Wire = PAPER_WIRE,
        effects: Effects | None = None,
        *,
        ambient_c: float = 22.0,
        noise_mm: float = 0.002,
        seed: int = 0,
        substep_s: float = 1e-3,
        telemetry_period_s: float = 0.01,
        host_timeout_s: float = p.HOST_TIMEOUT_DEFAULT_S,
        lease_s: float = p.LEASE_DEFAULT_S,
        clock: SimClock | None = None,
    ) -> None:
        if not 0.0 < load_kg <= 10.0:
            raise ValueError(f"load must be in (0, 10] kg, got {load_kg}")
        self.clock = clock or SimClock()
        model = Plant(load_kg, wire, effects, ambient_c=ambient_c, noise_mm=noise_mm, seed=seed)
        self.plant = SimPlant(model, self.clock, substep_s)
        self.source = SimCurrentSource(
            self.plant,
            telemetry_period_s=telemetry_period_s,
            host_timeout_s=host_timeout_s,
            lease_s=lease_s,
        )
        self.sensor = SimDisplacementSensor(self.plant)

    @property
    def state(self) -> PlantState:
        """The plant's state at the clock's time."""
        return self.plant.sync()
