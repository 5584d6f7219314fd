"""One device test suite (python-microscope's testsuite pattern): the contract of the device seams
(:mod:`smabench.drivers.base`) checked on every implementation.

Implementations (the ``rig`` fixture):

- ``sim``: the in-process simulated devices (:mod:`smabench.drivers.sim`) on a simulated clock;
- ``mock``: the real clients (:class:`~smabench.drivers.current_source.CurrentSource` over a pty,
  :class:`~smabench.drivers.displacement.DisplacementSensor` over Modbus TCP) against the mock
  bench (the Python firmware model) served from threads in this process;
- ``emulated``: the same clients against the real AVR firmware in simavr (skipped when the
  firmware is not built, except under CI).

Contract: the setpoint lease expires while other frames keep the link alive (output off,
``LEASE_EXPIRED``, setpoint 0, no host timeout); the host timeout turns the output off when the
host falls silent; a latched fault (the e-stop input) turns the output off, refuses ENABLE and
survives CLEAR_FAULTS while its cause is there, and clears once it is gone. Timings from the
device's own telemetry clock (``t_ms``), bounded from the side a late host read cannot move.
Since the stand-ins run the real firmware core, these are the firmware's behaviour on every rig.
``make_safe`` is idempotent, never raises (also before connect and after close) and
the output is off afterwards — checked on the device side, the current the plant receives;
``set_current`` is reflected in the telemetry and on the device side; ``enable(False)`` turns
the output off; out-of-range setpoints are refused; a probe current (``set_probe_current``) is
held at setpoint 0 past the lease and goes off with the output; sensor samples carry a finite
position or invalid flags, and an injected sensor failure comes back as a flagged sample, never
an exception. Waits poll a condition against a generous deadline (simulated time for ``sim``), so
the suite holds on a busy machine.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from smabench.drivers import protocol as p
from smabench.drivers.base import (
    FLAG_EXCEPTION,
    FLAGS_INVALID,
    CurrentSourceDevice,
    DisplacementDevice,
)

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

IMPLEMENTATIONS = ("sim", "mock", "emulated")
SETPOINT_A = 0.8
TOLERANCE_A = 0.04  # 5 %: the firmware settles within 5 % in 50 ms (PROTOCOL.md)


@dataclass
class Rig:
    """One implementation's devices plus the test's view of the device side."""

    name: str
    source: CurrentSourceDevice
    sensor: DisplacementDevice
    wire_current_a: Callable[[], float]  # the current the plant receives now, A
    fail_next_read: Callable[[], None]  # the next sensor reading fails
    unconnected_source: Callable[[], CurrentSourceDevice]
    wait_s: float  # deadline for a condition (simulated s for sim, wall s otherwise)
    poll: Callable[[], None]  # let time pass a little
    estop: Callable[[bool], None]  # the device's e-stop input (a latched fault's cause)
    silence: Callable[[bool], None]  # the host sends nothing at all (no keepalive) while True
    keepalive: Callable[[], None]  # a frame that is not SET_CURRENT (the link thread's PING)
    clear_faults: Callable[[], bool]  # CLEAR_FAULTS; False: refused, a cause is still there
    refused: type[Exception]  # what enable(True) raises while a fault is latched

    def wait(self, condition: Callable[[], bool]) -> bool:
        """Poll ``condition`` until it holds or the deadline passes; returns whether it held."""
        deadline = self.elapsed() + self.wait_s
        while not condition():
            if self.elapsed() > deadline:
                return condition()
            self.poll()
        return True

    elapsed: Callable[[], float] = time.monotonic


def _sim_rig() -> Iterator[Rig]:
    from smabench.drivers.sim import SimBench, SimCurrentSource, SimDeviceFaultError, SimPlant
    from smabench.physics.plant import Plant

    bench = SimBench(2.0)
    clock = bench.clock
    src = bench.source

    def unconnected():
        return SimCurrentSource(SimPlant(Plant(2.0), clock))

    def estop(on: bool) -> None:
        src.electrical.estop = on

    silent = [False]

    def keepalive() -> None:
        if not silent[0]:
            src.ping()

    # 0.2 s of simulated time: inside the device's 0.25 s host timeout (no keepalive here)
    yield Rig(
        "sim", src, bench.sensor, lambda: bench.state.current_a,
        lambda: bench.sensor.fail(1), unconnected, 0.2, lambda: clock.sleep(0.005),
        estop, lambda on: silent.__setitem__(0, on), keepalive,
        lambda: src.clear_faults() == p.Status.OK,
        SimDeviceFaultError, clock.now,
    )  # fmt: skip


def _mock_rig(firmware: str) -> Iterator[Rig]:
    from smabench.drivers.current_source import CommandRejected, CurrentSource, DeviceFault
    from smabench.drivers.displacement import DisplacementSensor
    from smabench.drivers.mock.bench import SENSOR_MAP, SIM_BIN, SIM_ELF, MockBench

    if firmware == "emulated" and not (SIM_BIN.is_file() and SIM_ELF.is_file()):
        if os.environ.get("CI"):
            pytest.fail("firmware build missing under CI (`make -C firmware elf sim`)")
        pytest.skip("firmware build missing (`make -C firmware elf sim`)")
    bench = MockBench(2.0, firmware=firmware, rtu=False)
    ports = bench.start()
    source = CurrentSource(ports.driver)
    sensor = DisplacementSensor(SENSOR_MAP, ports.sensor_tcp, timeout_s=0.5, retries=0)
    estop_on = [False]
    if bench.device is not None:  # the Python stand-in: the plant's wire plus the e-stop input
        couple = bench.device.on_step

        def on_step(t_ms, dt_s, fw):
            return dataclasses.replace(couple(t_ms, dt_s, fw), estop=estop_on[0])

        bench.device.on_step = on_step

    def estop(on: bool) -> None:
        estop_on[0] = on
        if bench.emulated is not None:
            bench.emulated._send(f"ESTOP {int(on)}")  # the harness's e-stop pin

    def clear_faults() -> bool:
        try:
            source.clear_faults()
        except CommandRejected as exc:
            assert exc.status == p.Status.FAULT_ACTIVE, exc
            return False
        return True

    try:
        source.connect()
        source.clear_faults()
        sensor.connect()
        yield Rig(
            firmware, source, sensor, lambda: bench.link.state.current_a,
            lambda: bench.server.fail_with_exception(4, 1),
            lambda: CurrentSource(ports.driver), 3.0, lambda: time.sleep(0.005),
            estop, source.pause_keepalive, lambda: None, clear_faults, DeviceFault,
        )  # fmt: skip
    finally:
        source.close()
        sensor.close()
        bench.stop()


@pytest.fixture(params=IMPLEMENTATIONS)
def rig(request) -> Iterator[Rig]:
    if request.param == "sim":
        yield from _sim_rig()
    else:
        yield from _mock_rig("python" if request.param == "mock" else "emulated")


def _heat(rig: Rig, current_a: float = SETPOINT_A) -> None:
    rig.source.enable(True)
    rig.source.set_current(current_a)
    assert rig.wait(lambda: abs(rig.wire_current_a() - current_a) < TOLERANCE_A), (
        f"{rig.name}: the wire never got {current_a} A (it gets {rig.wire_current_a():.3f} A)"
    )


# ----------------------------------------------------------------------------- the contract
def test_devices_implement_the_protocols(rig):
    assert isinstance(rig.source, CurrentSourceDevice)
    assert isinstance(rig.sensor, DisplacementDevice)


def test_make_safe_turns_the_output_off_on_the_device_side_and_is_idempotent(rig):
    _heat(rig)
    first = rig.source.make_safe()
    second = rig.source.make_safe()  # idempotent: a second call is harmless
    assert isinstance(first, bool) and isinstance(second, bool)
    assert rig.wait(lambda: rig.wire_current_a() == 0.0), (
        f"{rig.name}: the wire still gets {rig.wire_current_a():.3f} A after make_safe"
    )
    rig.sensor.make_safe()  # the sensor's never raises either
    # the device stays off: no later telemetry reports the output enabled
    assert rig.wait(
        lambda: (t := rig.source.latest()) is not None and not t.flags & p.Flag.ENABLED
    )


def test_make_safe_never_raises_before_connect_or_after_close(rig):
    fresh = rig.unconnected_source()
    assert fresh.make_safe() in (True, False)  # nothing to talk to: no exception either
    fresh.close()
    assert rig.source.make_safe() in (True, False)
    rig.source.close()
    assert rig.source.make_safe() in (True, False)
    rig.source.make_safe()
    rig.sensor.close()
    rig.sensor.make_safe()


def test_set_current_is_reflected_in_the_telemetry_and_on_the_device_side(rig):
    _heat(rig)

    def reported() -> bool:
        t = rig.source.latest()
        # the Kelvin wire voltage, when the device has one, is the current through the
        # plant's resistance (0.3 … 1 Ω)
        return (
            t is not None
            and t.setpoint_a == pytest.approx(SETPOINT_A, abs=1e-3)
            and abs(t.current_a - SETPOINT_A) < TOLERANCE_A
            and bool(t.flags & p.Flag.ENABLED)
            and (math.isnan(t.voltage_v) or 0.3 * SETPOINT_A < t.voltage_v < 1.0 * SETPOINT_A)
        )

    assert rig.wait(reported), f"{rig.name}: telemetry {rig.source.latest()}"
    age = rig.source.telemetry_age_s()
    assert age is not None and 0.0 <= age < rig.wait_s
    t = rig.source.latest()
    assert not t.flags & p.LATCHED_FAULTS, rig.source.fault_text()
    rig.source.enable(False)  # output off: reported, and on the device side
    assert rig.wait(
        lambda: not (t := rig.source.latest()).flags & p.Flag.ENABLED and t.current_a < 0.005
    )
    assert rig.wait(lambda: rig.wire_current_a() == 0.0)  # and on the device side


def test_out_of_range_setpoints_are_refused(rig):
    rig.source.enable(True)
    for bad in (-0.1, 2.6, math.inf):
        with pytest.raises(ValueError):
            rig.source.set_current(bad)
    rig.source.make_safe()


def test_sensor_samples_carry_finite_positions_or_invalid_flags(rig):
    samples = []
    for _ in range(20):
        samples.append(rig.sensor.read_or_flag())
        rig.poll()
    for s in samples:
        if math.isfinite(s.position_mm):
            assert not s.flags & FLAGS_INVALID, s
            assert 0.0 < s.position_mm < 10.0, s  # the slider of a 55 mm wire, mm
        else:
            assert s.flags & FLAGS_INVALID, s
    assert sum(math.isfinite(s.position_mm) for s in samples) >= 10  # mostly real readings
    rig.fail_next_read()
    failed = rig.sensor.read_or_flag()  # never raises: a flagged sample
    assert math.isnan(failed.position_mm) and failed.flags & FLAGS_INVALID, failed
    if rig.name != "sim":
        assert failed.flags & FLAG_EXCEPTION
    assert rig.wait(lambda: math.isfinite(rig.sensor.read_or_flag().position_mm))


# ----------------------------------------------------------------------------- safety contract
LEASE_S = p.LEASE_DEFAULT_S  # every rig runs the device's default lease and host timeout
HOST_TIMEOUT_S = p.HOST_TIMEOUT_DEFAULT_S
FRAME_S = 0.01  # the telemetry period every rig asks for


def _frame(rig: Rig, pred) -> p.Telemetry:
    """The first telemetry frame seen that satisfies ``pred`` (keeping the link as it is)."""
    seen: list[p.Telemetry] = []

    def check() -> bool:
        rig.keepalive()
        t = rig.source.latest()
        if t is not None and pred(t):
            seen.append(t)
        return bool(seen)

    assert rig.wait(check), f"{rig.name}: no such frame; latest {rig.source.latest()}"
    return seen[0]


def test_the_lease_expires_while_the_link_is_kept_alive(rig):
    rig.source.enable(True)
    before = _frame(rig, lambda t: True)  # device time no later than the SET_CURRENT
    rig.source.set_current(SETPOINT_A)
    first = _frame(rig, lambda t: t.setpoint_a > 0)  # no earlier than the SET_CURRENT
    rig.wait_s = max(rig.wait_s, 2 * LEASE_S)
    off = _frame(rig, lambda t: bool(t.flags & p.Flag.LEASE_EXPIRED))
    assert not off.flags & p.Flag.ENABLED and not off.flags & p.Flag.HOST_TIMEOUT, off
    assert off.setpoint_a == 0.0, off
    # the frame that says so may carry a current sampled as the sink's filter (≈1 ms poles)
    # was still falling; the next reading is off
    settled = _frame(rig, lambda t: t.t_ms > off.t_ms and t.current_a < 0.005)
    assert settled.setpoint_a == 0.0 and not settled.flags & p.Flag.ENABLED, settled
    # device clock: off one lease after the SET_CURRENT, though other frames went on
    assert off.t_ms - before.t_ms >= LEASE_S * 1e3 - 1, (before.t_ms, off.t_ms)
    assert off.t_ms - first.t_ms <= (LEASE_S + FRAME_S) * 1e3 + 1, (first.t_ms, off.t_ms)
    assert rig.wait(lambda: rig.wire_current_a() == 0.0)  # and on the device side
    rig.source.enable(True)  # no fault: ENABLE is accepted, the event is cleared
    assert _frame(rig, lambda t: bool(t.flags & p.Flag.ENABLED)).flags & p.Flag.LEASE_EXPIRED == 0


PROBE_A = 0.05


def test_the_probe_current_is_held_at_setpoint_0_and_goes_off_with_the_output(rig):
    """set_probe_current (protocol 4): at setpoint 0 the wire gets the probe current, also past
    the setpoint lease (the probe is not leased); enable(False) ends it and ENABLE alone does not
    bring it back; out of range is refused on the host."""
    for bad in (-0.01, 0.101, math.nan):
        with pytest.raises(ValueError):
            rig.source.set_probe_current(bad)
    rig.source.set_current(0.0)
    rig.source.set_probe_current(PROBE_A)
    rig.source.enable(True)
    on = _frame(rig, lambda t: t.enabled and abs(t.current_a - PROBE_A) < 0.005)
    assert rig.wait(lambda: abs(rig.wire_current_a() - PROBE_A) < 0.005), rig.wire_current_a()
    rig.wait_s = max(rig.wait_s, 4 * LEASE_S)
    later = _frame(rig, lambda t: t.t_ms >= on.t_ms + 2 * LEASE_S * 1e3)
    assert later.enabled and not later.flags & p.Flag.LEASE_EXPIRED, later
    assert later.setpoint_a == 0.0 and abs(later.current_a - PROBE_A) < 0.005, later
    rig.source.enable(False)
    assert rig.wait(lambda: rig.wire_current_a() == 0.0)  # on the device side
    rig.source.enable(True)
    back = _frame(rig, lambda t: bool(t.flags & p.Flag.ENABLED))
    still = _frame(rig, lambda t: t.t_ms >= back.t_ms + 30)
    assert still.enabled and still.current_a < 0.005 and rig.wire_current_a() == 0.0, still
    rig.source.make_safe()


def test_the_host_timeout_turns_the_output_off_when_the_host_falls_silent(rig):
    rig.source.set_lease(5.0)  # the lease would end it too: here only the host timeout may
    _heat(rig)
    rig.silence(True)
    try:
        rig.source.ping()  # the host's last frame: once its ACK is back, nothing else goes out
        acked = rig.source.last_ack_host_time
        # one byte stream, in order: the first frame decoded after that ACK left the device
        # after the PING arrived, and within one frame period of it. (The first frame seen after
        # the silence began is no such anchor: with the host's reader behind, it was sent 40 ms
        # before the device's last byte from the host, 290 against 260 ms on a busy CI; nor is
        # the host's clock when ping() returned: the reader may have decoded frames after the
        # ACK by then, 230 against 239 ms beside a mock control table.)
        start = _frame(rig, lambda t: t.host_time > acked)
        rig.wait_s = max(rig.wait_s, 2 * HOST_TIMEOUT_S)
        off = _frame(rig, lambda t: bool(t.flags & p.Flag.HOST_TIMEOUT))
    finally:
        rig.silence(False)
    assert not off.flags & p.Flag.ENABLED, off
    settled = _frame(rig, lambda t: t.t_ms > off.t_ms and t.current_a < 0.005)  # as above
    assert not settled.flags & p.Flag.ENABLED, settled
    # the trip 250 ms after the last byte, reported in the next frame (≤ 10 ms); start within a
    # frame period after that byte: not early, not late
    since_ms = off.t_ms - start.t_ms
    lo_ms, hi_ms = (HOST_TIMEOUT_S - FRAME_S) * 1e3 - 1, (HOST_TIMEOUT_S + FRAME_S) * 1e3 + 1
    assert lo_ms <= since_ms <= hi_ms, (start.t_ms, off.t_ms)
    assert rig.wait(lambda: rig.wire_current_a() == 0.0)
    rig.source.enable(True)  # an event, not a latched fault: ENABLE is accepted again
    rig.source.make_safe()


def test_a_latched_fault_holds_until_its_cause_is_gone_and_it_is_cleared(rig):
    _heat(rig)
    rig.estop(True)
    try:
        t = _frame(rig, lambda t: bool(t.flags & p.Flag.ESTOP))
        assert not t.flags & p.Flag.ENABLED, t
        assert rig.wait(lambda: rig.wire_current_a() == 0.0)
        with pytest.raises(rig.refused):
            rig.source.enable(True)
        assert rig.clear_faults() is False  # the cause is still there: the fault stays
        assert _frame(rig, lambda t: True).flags & p.Flag.ESTOP
    finally:
        rig.estop(False)
    # the cause is gone but nothing was cleared: still latched, still refused
    assert rig.wait(lambda: rig.source.latest().flags & p.Flag.ESTOP)
    with pytest.raises(rig.refused):
        rig.source.enable(True)
    assert rig.wait(rig.clear_faults)
    assert not _frame(rig, lambda t: not t.flags & p.Flag.ESTOP).flags & p.LATCHED_FAULTS
    _heat(rig)  # and the output works again
    rig.source.make_safe()
