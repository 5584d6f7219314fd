"""The hardware cut with the REAL firmware (ATmega328P build) in simavr (firmware/sim/cut.c).

Each injected fault ends with the wire current off within 10 ms (comparators) or 50 ms (the
external watchdog) of the fault, in the harness's AVR time (its ``fault_ms`` / ``off_ms``: the
same clock, whatever the host's load); the cut is read back by the firmware (D5/D6, A1) and
reported in telemetry. A hung main loop is an endless loop the harness sends the CPU into with
interrupts still running: the AVR's own watchdog would act after 32 ms; the external one must
open the cut first, while the firmware still drives its enable line (``d8_at_trip``).
"""

from __future__ import annotations

import pytest
from test_firmware_emulated import (  # noqa: E402 - the emulator fixtures and clients
    ELF,
    SIM,
    WAIT_S,
    Harness,
    RawDevice,
    raw,  # noqa: F401 - fixture
    sim,  # noqa: F401 - fixture
)

from smabench.drivers import protocol as p
from smabench.hardware import ELECTRICAL

F = p.Flag
S = p.Status
COMPARATOR_MS = ELECTRICAL["cut"]["comparator_off_max_s"] * 1e3
WATCHDOG_MS = ELECTRICAL["cut"]["watchdog_off_max_s"] * 1e3
AVR_WDT_INTERRUPT_MS = 32.0  # firmware/avr/hal_avr.c: the AVR's own watchdog, first stage
CAUSE = {"sink": 1, "supply": 2, "estop": 3, "watchdog": 4}

pytestmark = [
    pytest.mark.emulator,
    pytest.mark.slow,
    pytest.mark.timeout(120),
    pytest.mark.skipif(not (SIM.is_file() and ELF.is_file()), reason="make -C firmware elf sim"),
    pytest.mark.realtime_bench,
]


def heat(raw: RawDevice, sim: Harness, current_a: float) -> p.Telemetry:  # noqa: F811
    sim.set_resistance(0.44)
    assert raw.status(*p.set_lease(5.0)) == S.OK
    assert raw.status(*p.set_current(current_a)) == S.OK
    assert raw.status(*p.enable(True)) == S.OK
    on = raw.telemetry(lambda t: t.current_a > 0.97 * current_a)
    assert not on.flags & (F.CUT_TRIP | F.CUT_OPEN)
    st = sim.state()
    assert st["cut_closed"] == 1 and st["cut_trip"] == 0
    return on


def test_power_on_clears_the_cut_and_the_firmware_feeds_it(raw, sim):  # noqa: F811
    st = sim.state()
    assert st["cut_trip"] == 0 and st["cut_clears"] >= 1  # the power-on clear
    feeds = st["cut_feeds"]
    sim.wait_device_ms(st["t_ms"] + 50)
    st2 = sim.state()
    # one D7 edge per 1 ms control tick
    edges_per_ms = (st2["cut_feeds"] - feeds) / (st2["t_ms"] - st["t_ms"])
    assert 0.9 <= edges_per_ms <= 1.1
    t = raw.telemetry()
    assert t.flags & F.CUT_OPEN and not t.flags & F.CUT_TRIP  # disabled: open, no fault


@pytest.mark.parametrize("fault,cause", [("MOSFET", "sink"), ("GROUND", "supply")])
def test_a_comparator_opens_the_cut_within_10_ms(raw, sim, fault, cause):  # noqa: F811
    on = heat(raw, sim, 1.5)
    sim.send(f"FAULT {fault}")
    t = raw.telemetry(lambda t: t.flags & F.CUT_TRIP)
    st = sim.state()
    off_after_ms = st["off_ms"] - st["fault_ms"]
    print(f"\n{fault}: the {cause} comparator tripped {st['trip_ms'] - st['fault_ms']:.3f} ms and "
          f"the current was off {off_after_ms:.3f} ms after the fault (AVR time)")
    assert st["cut_cause"] == CAUSE[cause] and st["d8_at_trip"] == 1
    assert 0.0 <= off_after_ms <= COMPARATOR_MS
    assert st["current_a"] == 0.0 and st["cut_closed"] == 0 and st["cut_trip"] == 1
    # read back and reported: latched, the switch open, the switched supply gone
    assert t.flags & F.CUT_OPEN and not t.enabled and t.t_ms > on.t_ms
    later = raw.telemetry(lambda x: x.t_ms > t.t_ms + 10)
    assert later.supply_v < 0.1 and later.current_a < 0.02
    # still faulty: clearing works (no current, no cause) but the next enable trips at once
    assert raw.status(*p.enable(True)) == S.FAULT_ACTIVE
    assert raw.status(*p.clear_faults()) == S.OK
    assert raw.status(*p.enable(True)) == S.OK
    raw.telemetry(lambda t: t.flags & F.CUT_TRIP)
    assert sim.state()["current_a"] == 0.0
    # repaired: the current follows the setpoint again
    sim.send("FAULT NONE")
    assert raw.status(*p.clear_faults()) == S.OK
    assert raw.status(*p.set_current(1.5)) == S.OK
    assert raw.status(*p.enable(True)) == S.OK
    raw.telemetry(lambda t: t.current_a > 1.45)


def test_a_hung_mcu_is_cut_by_the_external_watchdog_not_its_own(raw, sim):  # noqa: F811
    heat(raw, sim, 1.5)
    mark = len(sim.stderr)
    sim.send("FAULT HANG")
    reset = sim.wait_stderr("watchdog", mark)  # the AVR's own watchdog resets it, later
    st = sim.state()
    off_after_ms = st["off_ms"] - st["fault_ms"]
    print(f"\nMCU hang: the external watchdog tripped {st['trip_ms'] - st['fault_ms']:.2f} ms "
          f"after the loop stopped, current off {off_after_ms:.2f} ms after (AVR time)")
    assert st["cut_cause"] == CAUSE["watchdog"]
    assert 0.0 < off_after_ms <= WATCHDOG_MS
    # before the AVR's own watchdog (32 ms), with the firmware's enable line still on: the
    # external watchdog opened the cut, not the MCU
    assert st["trip_ms"] - st["fault_ms"] < AVR_WDT_INTERRUPT_MS and st["d8_at_trip"] == 1
    # after its reset (and once it listens) the firmware reports the watchdog reset and the
    # trip (not cleared)
    sim.wait_ready_after_reset(reset)
    assert raw.status(*p.set_telemetry(0.005)) == S.OK
    t = raw.telemetry(lambda t: t.flags & F.WATCHDOG_RESET and t.t_ms > p.CUT_STARTUP_S * 1e3,
                      timeout_s=WAIT_S)
    assert t.flags & F.CUT_TRIP and t.flags & F.CUT_OPEN and not t.enabled
    assert sim.state()["cut_trip"] == 1
    assert raw.status(*p.clear_faults()) == S.OK
    assert sim.state()["cut_trip"] == 0


def test_avcc_on_a_weak_usb_port_is_measured(raw, sim):  # noqa: F811
    """AVcc 4.65 V: uncorrected the fast path would read 7.5 % high; measured on A3, < 1 %."""
    sim.send("AVCC 4.65")
    sim.wait_device_ms(sim.state()["t_ms"] + 500)  # the firmware's 64 ms mean of AVcc settles
    heat(raw, sim, 1.5)
    t = raw.telemetry(lambda x: True)
    t = raw.telemetry(lambda x: x.t_ms > t.t_ms + 100)
    wire_a = sim.state()["current_a"]
    print(f"\nAVcc 4.65 V: telemetry {t.current_a:.4f} A, wire {wire_a:.4f} A")
    assert t.current_a == pytest.approx(wire_a, rel=0.01)
    assert wire_a == pytest.approx(1.5, rel=0.01)
