"""The hardware cut (firmware/hardware/README.md "The cut"), driven by the real firmware core.

Stand-in (the C core through ctypes, drivers/mock/firmware.py + cut.py) and, in
tests/test_cut_emulated.py, the AVR build in simavr: each injected fault ends with the wire
current off within 10 ms (comparators) or 50 ms (external watchdog) of the fault in DEVICE time,
the cut read back and the fault reported in telemetry. No wall-clock figures, no retries.
"""

from __future__ import annotations

import math
import queue
import subprocess
import sys
import threading
import time

import pytest

from smabench.drivers import protocol as p
from smabench.drivers.current_source import CurrentSource
from smabench.drivers.mock.bench import SIM_BIN, SIM_ELF
from smabench.drivers.mock.cut import PUMP_TAU_S, PUMP_TRIP_V, PUMPED_V
from smabench.drivers.mock.firmware import WDT_INTERRUPT_MS, Electrical, MockFirmware
from smabench.hardware import ELECTRICAL

pytestmark = pytest.mark.realtime_bench  # starts a real-time bench: see tests/conftest.py

F = p.Flag
S = p.Status
TELEMETRY_MS = 10  # the client's telemetry period below
OFF_MA = 20.0  # "off": below the open-wire threshold, as tests/test_circuit.py
COMPARATOR_S = ELECTRICAL["cut"]["comparator_off_max_s"]
WATCHDOG_S = ELECTRICAL["cut"]["watchdog_off_max_s"]


class Device:
    """A stand-in firmware driven in device time (1 ms ticks), frames decoded as sent."""

    def __init__(self, wire: Electrical | None = None) -> None:
        self.fw = MockFirmware()
        self.wire = wire or Electrical()
        self.rx = p.FrameReceiver()
        self.seq = 0
        self.t_ms = 0
        self.telemetry: list[p.Telemetry] = []

    def _take(self, data: bytes) -> list[p.Ack]:
        acks = []
        for pkt in self.rx.feed(data):
            if pkt.type == p.MsgType.TELEMETRY:
                self.telemetry.append(p.Telemetry.from_payload(pkt.payload))
            elif pkt.type == p.MsgType.ACK:
                acks.append(p.Ack.from_payload(pkt.payload))
        return acks

    def command(self, type_: int, payload: bytes = b"") -> S:
        seq, self.seq = self.seq, (self.seq + 1) & 0xFF
        acks = [a for a in self._take(self.fw.receive(p.encode_frame(seq, type_, payload)))
                if a.seq == seq]  # fmt: skip
        assert len(acks) == 1
        return S(acks[0].status)

    def run(self, ms: int, wire: Electrical | None = None) -> None:
        if wire is not None:
            self.wire = wire
        for _ in range(ms):
            self.t_ms += 1
            self._take(self.fw.tick(self.t_ms, self.wire))

    def run_until(self, pred, limit_ms: int, wire: Electrical | None = None) -> int:
        """Ticks until ``pred()`` holds (device ms); fails past ``limit_ms``."""
        for ms in range(1, limit_ms + 1):
            self.run(1, wire)
            if pred():
                return ms
        raise AssertionError(f"not within {limit_ms} ms of device time")

    def heating(self, current_a: float) -> None:
        assert self.command(*p.set_limits(2.5, 5.0)) == S.OK
        assert self.command(*p.set_lease(5.0)) == S.OK
        assert self.command(*p.set_telemetry(0.005)) == S.OK
        assert self.command(*p.set_current(current_a)) == S.OK
        assert self.command(*p.enable(True)) == S.OK
        self.run(60)
        assert self.fw.current_ma == pytest.approx(current_a * 1000, rel=0.01)
        assert self.fw.cut_closed
        last = self.telemetry[-1]
        assert last.flags & F.ENABLED and not last.flags & (F.CUT_OPEN | F.CUT_TRIP)


def test_power_on_clears_the_cut_once_the_watchdog_pump_is_charged():
    dev = Device()
    assert not dev.fw.cut_closed  # the pump starts empty: the latch is set at power-on
    dev.run(10)
    assert dev.fw._core.io.cut_clears == 1 and not dev.fw._core.io.cut_latch
    assert dev.fw._core.io.cut_feeds == 10  # one D7 edge per control tick
    t = dev.fw.telemetry()
    assert t.flags & F.CUT_OPEN and not t.flags & F.CUT_TRIP  # open because disabled: no fault


@pytest.mark.parametrize("fault,cause", [("mosfet-short", "sink-comparator"),
                                         ("wire-to-ground", "supply-comparator")])  # fmt: skip
@pytest.mark.parametrize("current_a", [0.6, 2.0])
def test_a_comparator_opens_the_cut_within_10_ms(fault, cause, current_a):
    dev = Device()
    dev.heating(current_a)
    fault_ms = dev.t_ms
    off_ms = dev.run_until(lambda: dev.fw.current_ma < OFF_MA, 50, Electrical(fault=fault))
    assert off_ms * 1e-3 <= COMPARATOR_S
    assert [e.cause for e in dev.fw.cut.events] == [cause]
    # the cut is read back and the fault reported: latched, switch open, switched supply gone
    t = dev.fw.telemetry()
    assert t.flags & F.CUT_TRIP and t.flags & F.CUT_OPEN and not t.enabled
    assert t.supply_v < 0.1
    print(f"\n{fault} at {current_a} A: current off {off_ms} ms after the fault "
          f"(device time, 1 ms steps; the comparator acts in µs)")
    # still shorted: a clear succeeds (the cut took the current away) but enabling trips again
    assert dev.command(*p.enable(True)) == S.FAULT_ACTIVE
    assert dev.command(*p.clear_faults()) == S.OK
    assert dev.command(*p.enable(True)) == S.OK
    dev.run_until(lambda: dev.fw.telemetry().flags & F.CUT_TRIP, 5)
    assert dev.fw.current_ma < OFF_MA
    # repaired: cleared, enabled, the current follows the setpoint again
    dev.run(5, Electrical())
    assert dev.command(*p.clear_faults()) == S.OK
    assert dev.command(*p.set_current(current_a)) == S.OK
    assert dev.command(*p.enable(True)) == S.OK
    dev.run(60)
    assert dev.fw.current_ma == pytest.approx(current_a * 1000, rel=0.01)
    assert fault_ms > 0


def test_a_hung_mcu_is_cut_by_the_external_watchdog_before_its_own():
    """The main loop stops (no control tick, no D7 edge); the AVR's watchdog would turn the
    output off after 32 ms and reset after 64 ms. The pump opens the cut first, within 50 ms."""
    dev = Device()
    dev.heating(2.0)
    fault_ms = dev.t_ms
    off_ms = dev.run_until(lambda: dev.fw.current_ma < OFF_MA, 100, Electrical(fault="mcu-hang"))
    assert off_ms * 1e-3 <= WATCHDOG_S
    assert off_ms < WDT_INTERRUPT_MS  # not the MCU's own watchdog
    [event] = dev.fw.cut.events
    assert event.cause == "watchdog" and event.t_ms - fault_ms == off_ms - 1
    # the pump's decay from its pumped level to U7D's threshold, τ = (RW1 + RW2)·CW2
    expected_ms = PUMP_TAU_S * 1e3 * math.log(PUMPED_V / PUMP_TRIP_V)
    assert abs(off_ms - expected_ms) <= 1.5
    print(f"\nMCU hang at 2 A: the external watchdog opened the cut {off_ms} ms after the last "
          f"D7 edge (device time; its RC: {expected_ms:.1f} ms; ngspice 17.6–31.7 ms)")
    # the hang ends with the AVR's own reset; the firmware then reports what happened
    dev.run_until(lambda: dev.fw.watchdog_resets == 1, 100)
    dev.run(20, Electrical())
    t = dev.fw.telemetry()
    assert t.flags & F.WATCHDOG_RESET and t.flags & F.CUT_TRIP and t.flags & F.CUT_OPEN
    assert dev.command(*p.clear_faults()) == S.OK
    assert not dev.fw.telemetry().flags & F.CUT_TRIP


def test_estop_holds_the_latch_and_the_firmware_does_not_pulse_it():
    dev = Device()
    dev.heating(1.0)
    dev.run_until(lambda: dev.fw.current_ma < OFF_MA, 2, Electrical(estop=True))
    assert dev.fw.telemetry().flags & (F.ESTOP | F.CUT_TRIP) == F.ESTOP | F.CUT_TRIP
    clears = dev.fw._core.io.cut_clears
    assert dev.command(*p.clear_faults()) == S.FAULT_ACTIVE
    assert dev.fw._core.io.cut_clears == clears  # no D4 pulse while the e-stop is pressed
    dev.run(5, Electrical())
    assert dev.command(*p.clear_faults()) == S.OK
    assert dev.command(*p.enable(True)) == S.OK


def test_avcc_is_measured_and_corrects_the_readings():
    """A weak USB port: AVcc 4.65 V instead of 5.0 V. Without the REF3040 on A3 the fast path
    would read 7.5 % high; measured, the telemetry stays within 1 % of the wire current."""
    dev = Device(Electrical(avcc_v=4.65))
    dev.heating(1.5)
    dev.run(100)
    t = dev.fw.telemetry()
    assert dev.fw.state.avcc_mv == pytest.approx(4650, abs=10)
    assert t.current_a == pytest.approx(dev.fw.current_ma / 1000, rel=0.01)
    supply_v = dev.fw.sink.supply_at_terminals_v(dev.fw.current_ma / 1000)
    assert t.supply_v == pytest.approx(supply_v, rel=0.01)


def trip_then_off(cs: CurrentSource) -> tuple[p.Telemetry, list[p.Telemetry]]:
    """The first frame flagging CUT_TRIP and the frames from it until one reads the current off."""
    t = cs.wait_telemetry(lambda u: u.flags & F.CUT_TRIP, timeout_s=10.0)
    cs.wait_telemetry(lambda u: u.current_a < OFF_MA / 1000, timeout_s=10.0)
    return t, [u for u in cs.telemetry_history() if u.t_ms >= t.t_ms]


@pytest.mark.slow
@pytest.mark.parametrize("firmware", ["python", "emulated"])
@pytest.mark.parametrize("fault,limit_s", [("mosfet-short", COMPARATOR_S),
                                           ("wire-to-ground", COMPARATOR_S),
                                           ("mcu-hang", WATCHDOG_S)])  # fmt: skip
def test_smabench_mock_fault_shows_the_cut_work(fault, limit_s, firmware):
    """`smabench mock --fault KIND`: a client heats at 1 A, the mock injects the fault and says
    what opened the cut and when (device time); the client sees CUT_TRIP."""
    if firmware == "emulated" and not (SIM_BIN.is_file() and SIM_ELF.is_file()):
        pytest.skip("make -C firmware elf sim")
    proc = subprocess.Popen(
        [sys.executable, "-m", "smabench.cli", "mock", "--control-stdin", "--fault", fault,
         "--firmware", firmware],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x.strip()) for x in proc.stdout])
    reader.daemon = True
    reader.start()

    def expect(prefix: str, timeout_s: float = 60.0) -> str:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = lines.get(timeout=left)
            except queue.Empty:
                break
            if line.startswith(prefix):
                return line
        raise AssertionError(f"mock never printed {prefix!r}")

    try:
        port = expect("driver: ").split(": ", 1)[1]
        expect("ready")
        with CurrentSource(port, telemetry_period_s=0.01, link_timeout_s=3.0) as cs:
            cs.set_lease(5.0)
            cs.set_current(1.0)
            cs.enable(True)
            injected = expect("fault: ")
            report = expect("cut: ")
            if fault != "mcu-hang":
                t, frames = trip_then_off(cs)
        if fault == "mcu-hang":  # its own watchdog resets it (telemetry off): connect afresh
            expect("mcu: reset")
            with CurrentSource(port, telemetry_period_s=0.01, link_timeout_s=3.0) as cs:
                t, frames = trip_then_off(cs)
            assert t.flags & F.WATCHDOG_RESET
        assert fault in injected and t.flags & F.CUT_OPEN
        # the frame carrying the trip may hold a current sampled while it fell; the wire
        # current reads off within two frames of it (device time)
        off = next(u for u in frames if u.current_a < OFF_MA / 1000)
        assert off.t_ms - t.t_ms <= 2 * TELEMETRY_MS and off.flags & F.CUT_OPEN, frames[:5]
        assert float(injected.split("wire current ")[1].split()[0]) >= 500  # it met a current
        after_ms = float(report.split(" ms after")[0].rsplit(" ", 1)[1])
        assert after_ms <= limit_s * 1e3
        print(f"\n{injected}\n{report}")
    finally:
        proc.stdin.close()
        proc.wait(15)
