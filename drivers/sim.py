"""In-process simulated bench devices backed by the plant, on a simulated clock.

No transports, no threads, no wall clock: a :class:`SimClock` says what time it is, and both
devices bring the shared :class:`SimPlant` up to that time whenever they are looked at (the
plant is stepped in sub-steps of ``substep_s``, 1 ms, with the current the simulated driver
drives). The owner of the clock — the offline closed loop, a test — advances it.

- :class:`SimCurrentSource` (a :class:`~smabench.drivers.base.CurrentSourceDevice`) runs the
  REAL firmware core (``firmware/core/core.c`` built for the host, :mod:`smabench.drivers.mock.
  firmware`) on the simulated clock: every command is a frame into the core and its ACK comes
  back through the codec; the core's 1 ms control tick runs with the wire current the reference
  sink delivers (:class:`smabench.hardware.LinearSink`) into the plant's resistance, and its
  telemetry frames are decoded. So the lease, the host timeout (0.25 s each of simulated time),
  the latched faults (open wire, the energy budget's over-temperature, …), the clamps, the
  probe current (SET_PROBE) and the ACK codes are the firmware's own, not a re-implementation.
- :class:`SimDisplacementSensor` (a :class:`~smabench.drivers.base.DisplacementDevice`): the
  plant's slider position with its sensor noise; flagged NaN samples while a failure is
  injected.

Fault injection for tests: :meth:`SimCurrentSource.inject_fault` (a latched device fault, as an
external protection reports it to the core), :attr:`SimCurrentSource.electrical` (the e-stop
input, the NTC, the thermocouple, the external ADC),
:meth:`SimCurrentSource.stall_telemetry` (a dead link: no frames), :meth:`SimDisplacementSensor.
fail` (flagged samples), :meth:`SimPlant.break_wire` (the load falls freely and the wire is an
open circuit: the driver latches OPEN_WIRE as the firmware does).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading

import numpy as np

from smabench.drivers import protocol as p
from smabench.drivers.base import FLAG_SENSOR_STATUS, FLAG_TIMEOUT, Sample
from smabench.drivers.mock.firmware import Electrical, MockFirmware
from smabench.physics.effects import Effects
from smabench.physics.plant import Plant, PlantState
from smabench.physics.resistance import ResistivityModel
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

POWERED_BEFORE_S = 0.2  # the simulated driver runs this long before the plant's time 0
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
    """The current driver, simulated: the real firmware core on the simulated clock.

    Every command goes to the core as a frame and its ACK comes back through the frame codec;
    the core's control tick runs every 1 ms of simulated time (the plant's sub-steps end on the
    ticks) with the wire current the sink delivers; telemetry frames come out of the core and are
    decoded. Units: A, s."""

    def __init__(
        self,
        plant: SimPlant,
        *,
        telemetry_period_s: float = 0.01,
        host_timeout_s: float = p.HOST_TIMEOUT_DEFAULT_S,
        lease_s: float = p.LEASE_DEFAULT_S,
        current_limit_a: float | None = None,
        electrical: Electrical | None = None,
        powered_s: float = POWERED_BEFORE_S,
        wire_noise_v: float = 0.0,
        seed: int = 0,
    ) -> None:
        """``powered_s``: how long the device has been running when the clock reads the plant's
        time (a bench's driver is powered before a session: its NTC has been read, 100 ms).
        ``wire_noise_v``: Gaussian noise of the wire-voltage channel at the wire, V RMS, drawn
        per 1 ms core tick (about one ADS1115 conversion at 860 SPS; see
        :data:`smabench.physics.resistance.ADS1115_KELVIN_CHAIN`), ``seed`` its generator's."""
        lo, hi = p.TELEMETRY_PERIOD_RANGE_S
        if not lo <= telemetry_period_s <= hi:
            raise ValueError(f"telemetry period must be in {lo} … {hi} s")
        self.plant = plant
        self.clock = plant.clock
        self.telemetry_period_s = telemetry_period_s
        self.electrical = electrical or Electrical()  # the inputs besides the wire
        if not wire_noise_v >= 0.0:
            raise ValueError(f"wire_noise_v must be ≥ 0 V, got {wire_noise_v}")
        self.wire_noise_v = wire_noise_v
        self._noise_rng = np.random.default_rng(seed)
        self._t0_s = plant.t_s - powered_s  # device time 0 (the core's reset)
        self.fw = MockFirmware(0.0)
        state = plant.state
        self.fw.tick(
            powered_s * 1000.0,
            dataclasses.replace(
                self.electrical, resistance_ohm=state.resistance_ohm, ambient_c=state.ambient_c
            ),
        )
        self._rx = p.FrameReceiver()
        self._seq = 0
        self._latest: p.Telemetry | None = None
        self._stalled = False
        self.commands = 0  # host commands through the device API (each feeds the host timeout)
        self.last_ack_host_time: float | None = None  # plant clock of the newest ACK
        self.current_a = 0.0  # flowing now (device side)
        ack = self._call(*p.identify())
        self.info = p.DeviceInfo.from_data(ack.data)
        self.hard_limit_a = self.info.hard_limit_a
        limit_a = self.hard_limit_a if current_limit_a is None else float(current_limit_a)
        for cmd in (
            p.set_limits(limit_a, host_timeout_s),
            p.set_lease(lease_s),
            p.set_telemetry(telemetry_period_s),
        ):
            if self._call(*cmd).status != p.Status.OK:
                raise ValueError(f"the simulated driver refused {cmd[0].name}")
        self.host_timeout_s, self.lease_s, self.limit_a = host_timeout_s, lease_s, limit_a
        plant.attach(self)

    # ------------------------------------------------------------------ device side (plant)
    def _device_ms(self, t_s: float) -> float:
        return (t_s - self._t0_s) * 1000.0

    def limit_step(self, t_s: float, h: float) -> float:
        """Shorten a plant sub-step so that it ends on the core's next 1 ms tick."""
        next_tick_s = self._t0_s + (self.fw.core_ms + 1) / 1000.0
        return max(min(h, next_tick_s - t_s), 1e-9)

    def advance(self, h: float) -> float:
        """The current the sink delivers over the next ``h`` s, A (set at the last tick)."""
        self.current_a = self.fw.current_ma / 1000.0
        return self.current_a

    def after_step(self, t_s: float, h: float, state: PlantState) -> None:
        """A core tick when the sub-step ended on one: the plant's wire as the sink's load."""
        offset_v = self.electrical.wire_offset_v
        if self.wire_noise_v > 0.0:
            offset_v += self.wire_noise_v * float(self._noise_rng.standard_normal())
        wire = dataclasses.replace(
            self.electrical,
            resistance_ohm=state.resistance_ohm,
            ambient_c=state.ambient_c,
            open_wire=self.plant.broken or self.electrical.open_wire,
            wire_offset_v=offset_v,
        )
        self._frames(self.fw.tick(self._device_ms(t_s), wire), t_s)
        self.current_a = self.fw.current_ma / 1000.0

    def _frames(self, data: bytes, t_s: float) -> list[p.Packet]:
        """Decode what the core sent: telemetry is kept, the rest returned."""
        out = []
        for pkt in self._rx.feed(data):
            if pkt.type == p.MsgType.TELEMETRY:
                if not self._stalled:
                    self._latest = p.Telemetry.from_payload(pkt.payload, host_time=t_s)
            else:
                out.append(pkt)
        return out

    def _call(self, type_: int, payload: bytes) -> p.Ack:
        """One command through the core; its ACK."""
        seq = self._seq
        self._seq = (seq + 1) & 0xFF
        now = self.plant.t_s
        for pkt in self._frames(self.fw.receive(p.encode_frame(seq, type_, payload)), now):
            ack = p.Ack.from_payload(pkt.payload)
            if pkt.type == p.MsgType.ACK and ack.seq == seq:
                self.last_ack_host_time = now
                self.current_a = self.fw.current_ma / 1000.0
                return ack
        raise RuntimeError(f"the firmware core did not acknowledge {p.MsgType(type_).name}")

    # ------------------------------------------------------------------ host side
    def _command(self, type_: int, payload: bytes) -> p.Ack:
        self.plant.sync()  # the old state holds up to now
        self.commands += 1
        return self._call(type_, payload)

    @property
    def enabled(self) -> bool:
        return self.fw.enabled

    @property
    def flags(self) -> p.Flag:
        return self.fw.flags

    @property
    def setpoint_a(self) -> float:
        return self.fw.setpoint_ma / 1000.0

    def connect(self) -> p.DeviceInfo:
        return self.info

    def enable(self, on: bool) -> None:
        """Output on/off; on is refused while a fault is latched
        (:class:`SimDeviceFaultError`)."""
        with self.plant.lock:
            ack = self._command(*p.enable(on))
            if ack.status == p.Status.FAULT_ACTIVE:
                raise SimDeviceFaultError(f"ENABLE refused: {p.fault_text(self.fw.flags)}")

    def set_current(self, current_a: float) -> p.Status:
        """Current setpoint, A; ValueError outside 0 … the hard limit; above the active limit
        the device clamps it (``Status.CLAMPED``). Renews the host timeout and the lease."""
        if not 0.0 <= current_a <= self.hard_limit_a + 1e-9:
            raise ValueError(
                f"current {current_a} A outside 0 … {self.hard_limit_a} A (device hard limit)"
            )
        with self.plant.lock:
            return p.Status(self._command(*p.set_current(current_a)).status)

    def set_probe_current(self, current_a: float) -> None:
        """SET_PROBE: the probe current held while enabled, A (0 = off, at most 0.1 A;
        ValueError outside, nothing sent). The core's own behaviour (not a re-implementation):
        max(setpoint, probe), not leased, off with everything that turns the output off."""
        type_, payload = p.set_probe(current_a)
        with self.plant.lock:
            ack = self._command(type_, payload)
            if ack.status != p.Status.OK:
                raise ValueError(f"SET_PROBE {current_a} A refused: {ack.status_name}")

    def set_limits(self, current_limit_a: float, host_timeout_s: float) -> None:
        with self.plant.lock:
            ack = self._command(*p.set_limits(current_limit_a, host_timeout_s))
            if ack.status != p.Status.OK:
                raise ValueError(f"SET_LIMITS refused: {ack.status_name}")
            self.limit_a, self.host_timeout_s = float(current_limit_a), float(host_timeout_s)

    def set_lease(self, lease_s: float) -> None:
        """SET_LEASE: how long a setpoint holds without a SET_CURRENT, s (0.02 … 5)."""
        with self.plant.lock:
            if self._command(*p.set_lease(lease_s)).status != p.Status.OK:
                raise ValueError(f"lease {lease_s} s refused")
            self.lease_s = float(lease_s)

    def clear_faults(self) -> p.Status:
        """CLEAR_FAULTS: ``FAULT_ACTIVE`` while a cause is still there (that fault stays)."""
        with self.plant.lock:
            return p.Status(self._command(*p.clear_faults()).status)

    def ping(self) -> float:
        """PING: feeds the host timeout, never the lease; the round trip, s (0: in process)."""
        with self.plant.lock:
            self._command(*p.ping())
            return 0.0

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
        """Output off now (ENABLE 0, setpoint 0); idempotent, never raises; True when the core
        confirmed it."""
        try:
            with self.plant.lock:
                self.plant.sync()
                ok = self._call(*p.enable(False)).status == p.Status.OK
                self._call(*p.set_current(0.0))
                return ok and not self.fw.enabled
        except Exception:  # never raises: this is the emergency path
            log.exception("simulated make_safe")
            return False

    def close(self) -> None:
        self.make_safe()

    # ------------------------------------------------------------------ fault injection
    def inject_fault(self, flag: p.Flag = p.Flag.OVERCURRENT) -> None:
        """Latch a device fault now, as an external protection would report it to the core
        (output off at once, reported in the next frame)."""
        with self.plant.lock:
            self.plant.sync()
            self.fw.latch_fault(flag)
            self.current_a = 0.0

    def stall_telemetry(self, stalled: bool = True) -> None:
        """A dead link: no telemetry frames while stalled (the device itself keeps running)."""
        with self.plant.lock:
            self.plant.sync()
            self._stalled = stalled


class _SimPendingRead:
    """A simulated background reading: done once the clock reaches ``ready_s``."""

    def __init__(self, sample: Sample, clock: SimClock, ready_s: float) -> None:
        self._sample, self._clock, self._ready_s = sample, clock, ready_s

    def done(self) -> bool:
        return self._clock.now() >= self._ready_s

    def result(self, timeout: float | None = None) -> Sample:
        return self._sample


class SimDisplacementSensor:
    """The displacement sensor, simulated: the plant's slider position, mm."""

    def __init__(self, plant: SimPlant) -> None:
        self.plant = plant
        self.clock = plant.clock
        self.reads = 0
        self._fail_left = 0.0
        self._fail_until_s = -math.inf
        self._fail_flag = FLAG_TIMEOUT
        self.timeout_s = 0.0
        """How long a request that times out (``FLAG_TIMEOUT``) holds its caller, s: a real
        Modbus client waits its timeout; 0: the failure is returned at once."""

    def read_or_flag(self) -> Sample:
        """One reading at the clock's time; a flagged NaN sample while a failure is injected
        (a status-error failure keeps the position and sets ``FLAG_SENSOR_STATUS``)."""
        sample, wait_s = self._reading()
        if wait_s > 0:
            self.clock.sleep(wait_s)  # the request waited for its answer
            sample = dataclasses.replace(sample, t_s=self.clock.now())
        return sample

    def read_in_background(self) -> _SimPendingRead:
        """The reading, done once the clock has passed its wait (a timed-out request's
        ``timeout_s``); the clock is not held meanwhile."""
        sample, wait_s = self._reading()
        return _SimPendingRead(dataclasses.replace(sample, t_s=self.clock.now() + wait_s),
                               self.clock, self.clock.now() + wait_s)  # fmt: skip

    def _reading(self) -> tuple[Sample, float]:
        """(the reading now, how long its request waits, s)."""
        self.reads += 1
        position = self.plant.position_mm()
        t = self.clock.now()
        if self._fail_left > 0 or t < self._fail_until_s:
            self._fail_left = max(self._fail_left - 1, 0)
            if self._fail_flag == FLAG_TIMEOUT and self.timeout_s > 0:
                return Sample(math.nan, t, flags=FLAG_TIMEOUT, error="injected failure"), \
                    self.timeout_s  # fmt: skip
            if self._fail_flag == FLAG_SENSOR_STATUS:
                return Sample(position, t, flags=FLAG_SENSOR_STATUS, status=1), 0.0
            return Sample(math.nan, t, flags=self._fail_flag, error="injected failure"), 0.0
        return Sample(position, t), 0.0

    def fail(self, count: float = math.inf, flag: int = FLAG_TIMEOUT) -> None:
        """The next ``count`` readings fail with ``flag`` (inf: until :meth:`recover`)."""
        self._fail_left, self._fail_flag = count, flag

    def fail_for(self, seconds: float, flag: int = FLAG_TIMEOUT) -> None:
        """Every reading fails with ``flag`` for ``seconds`` of the clock from now."""
        self._fail_until_s, self._fail_flag = self.clock.now() + seconds, flag

    def recover(self) -> None:
        self._fail_left = 0
        self._fail_until_s = -math.inf

    def make_safe(self) -> bool:
        """Nothing to switch off on a passive sensor; never raises."""
        return True

    def close(self) -> None:
        pass


class SimBench:
    """Clock, plant, current source and sensor wired together (units in names);
    ``resistivity``: the plant's wire resistance from that model (:class:`Plant`);
    ``wire_noise_v``: the wire-voltage channel's noise (:class:`SimCurrentSource`)."""

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
        resistivity: ResistivityModel | None = None,
        wire_noise_v: float = 0.0,
    ) -> None:
        if not 0.0 < load_kg <= 10.0:
            raise ValueError(f"load must be in (0, 10] kg, got {load_kg}")
        self.clock = clock or SimClock()
        model = Plant(load_kg, wire, effects, ambient_c=ambient_c, noise_mm=noise_mm, seed=seed,
                      resistivity=resistivity)  # fmt: skip
        self.plant = SimPlant(model, self.clock, substep_s)
        self.source = SimCurrentSource(
            self.plant,
            telemetry_period_s=telemetry_period_s,
            host_timeout_s=host_timeout_s,
            lease_s=lease_s,
            wire_noise_v=wire_noise_v,
            seed=seed,
        )
        self.sensor = SimDisplacementSensor(self.plant)

    @property
    def state(self) -> PlantState:
        """The plant's state at the clock's time."""
        return self.plant.sync()
