"""The hardware cut of the reference driver, for the stand-in (firmware/hardware/README.md).

U10 (TPS25940L eFuse) in the wire supply conducts while EN = NOR(D8, TRIP) is high. The latch U8
(TRIP) is set by the LM339 comparators U7: the shunt current above :attr:`Electrical.trip_sink_a`
(2.99 A: a shorted MOSFET), the supply current on U10's IMON above
:attr:`Electrical.trip_supply_a` (3.26 A: the wire's low end to ground, which bypasses the shunt),
the e-stop contact, and the watchdog pump below its threshold (D7 stopped toggling). The MCU
clears it with a D4 pulse, which the host HAL applies at once unless a cause holds it
(``cut_hold``). Timings, all far below the 1 ms step of the stand-in: LM339 response time
1.3 µs typ (TI LM339 datasheet, 100 mV step with 5 mV overdrive; 0.3 µs for a TTL-level step)
behind the 1 µs input filters (R56/C65, R57/C67); TPS25940 EN turn-off ≈ 2 µs (README.md: the
netlist model's assumption, to check against the SLVSDJ0 timing table). The watchdog pump
(CW2, RW1 + RW2) decays with τ = R·C from its pumped level: the cut opens ≈ 17 ms after the
last edge (ngspice: 17.6 ms stuck low, 28.2 ms stuck high, 31.7 ms at the slow corner;
tests/test_circuit.py).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from smabench.hardware import ELECTRICAL

log = logging.getLogger(__name__)

_CUT = ELECTRICAL["cut"]
PUMP_TAU_S = float(_CUT["watchdog_r_ohm"]) * float(_CUT["watchdog_c_f"])
PUMPED_V = 3.6  # CW2 at 500 Hz of D7 edges (README.md "The cut", ngspice)
# U7D's threshold: VREF through R54/R55 (40.2 k / 10 k) = 0.816 V, against the pump through the
# RW1/RW2 halving divider: 1.63 V on CW2
PUMP_TRIP_V = 2.0 * float(ELECTRICAL["setpoint"]["pwm_high_v"]) * 10.0 / 50.2
PUMP_SHARE_PER_EDGE = 0.5  # an edge moves CW2 halfway to the pumped level (CW1 100 n vs 220 n)
FAULTS = ("mosfet-short", "wire-to-ground", "mcu-hang")


@dataclass
class CutEvent:
    """What opened the cut and when (device time, ms)."""

    cause: str  # "sink-comparator", "supply-comparator", "watchdog", "estop"
    t_ms: float


class HardwareCut:
    """The latch, the comparators and the watchdog pump; the switch's state follows from the
    enable line and the latch (the host HAL: ``io.cut_latch``, ``io.cut_hold``)."""

    def __init__(self) -> None:
        self.pump_v = 0.0  # power-on: empty, so the latch starts set
        self.feeds_seen = 0
        self.events: list[CutEvent] = []

    def feed(self, feeds: int) -> None:
        """D7 edges the MCU made since the last call (its ``cut_feeds`` counter)."""
        for _ in range(max(0, feeds - self.feeds_seen)):
            self.pump_v += (PUMPED_V - self.pump_v) * PUMP_SHARE_PER_EDGE
        self.feeds_seen = feeds

    def decay(self, dt_s: float) -> None:
        self.pump_v *= math.exp(-dt_s / PUMP_TAU_S)

    @property
    def pump_low(self) -> bool:
        return self.pump_v < PUMP_TRIP_V

    def comparators(self, sink_a: float, supply_a: float, estop: bool) -> str | None:
        """The first comparator that pulls OC_N low now, or None."""
        if sink_a > ELECTRICAL.trip_sink_a:
            return "sink-comparator"
        if supply_a > ELECTRICAL.trip_supply_a:
            return "supply-comparator"
        if estop:
            return "estop"
        if self.pump_low:
            return "watchdog"
        return None

    def record(self, cause: str, t_ms: float, was_closed: bool) -> None:
        if was_closed:
            log.info("hardware cut opened by the %s at %.1f ms", cause, t_ms)
            self.events.append(CutEvent(cause, t_ms))
