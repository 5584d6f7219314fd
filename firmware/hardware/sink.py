"""What the reference linear current sink delivers to the wire (a model for the mock and plant).

The sink regulates the shunt voltage to the filtered PWM setpoint with an analog loop far faster
than anything the plant sees, so the wire current is the setpoint after the two real poles of the
PWM filter ladder (``Electrical.setpoint_filter_poles_s``), except where the circuit cannot
deliver it:

- compliance: ``I ≤ (V_supply − V_DS,min) / (R_source + R_eFuse + R_wire + R_shunt)`` (a long or
  hot wire on a sagging supply);
- supply sag: the supply's source resistance drops ``I·R_source``;
- ripple: what is left of the 15.6 kHz PWM after the two poles (≈ 2e-5 of the fundamental), as
  peak-to-peak wire current;
- the MOSFET's dissipation ``(V_supply − I·(R_source + R_wire + R_shunt))·I`` and junction
  temperature through the heat-sink stack, for the firmware's dissipation limit to act on.

The current is smooth DC: heating is ``I²·R`` of this current, which is why a driver that chops
the supply straight onto the wire (mean of I² ≫ square of the mean) is caught by
``tests/test_hardware.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from smabench.hardware.electrical import ELECTRICAL, Electrical


@dataclass
class SinkState:
    """The two PWM-filter poles' outputs, expressed as sink current, A."""

    pole1_a: float = 0.0
    pole2_a: float = 0.0


@dataclass
class LinearSink:
    """The sink driving a wire of ``wire_ohm`` from a supply of ``supply_v`` (units in names)."""

    electrical: Electrical = ELECTRICAL
    supply_v: float | None = None  # None: the nominal wire supply
    state: SinkState = field(default_factory=SinkState)

    def __post_init__(self) -> None:
        if self.supply_v is None:
            self.supply_v = float(self.electrical["supply"]["wire_supply_v"])

    # --------------------------------------------------------------- static figures
    def compliance_a(self, wire_ohm: float) -> float:
        """The largest current the circuit can push through the wire, A."""
        e = self.electrical
        loop_ohm = e.loop_resistance_ohm + wire_ohm
        return max(0.0, (self.supply_v - e["sink"]["mosfet_vds_min_v"]) / loop_ohm)

    def mosfet_power_w(self, current_a: float, wire_ohm: float) -> float:
        e = self.electrical
        loop_ohm = e.loop_resistance_ohm + wire_ohm
        return max(0.0, (self.supply_v - current_a * loop_ohm) * current_a)

    def junction_temperature_c(self, current_a: float, wire_ohm: float, ambient_c: float) -> float:
        """Steady junction temperature of the MOSFET, °C."""
        power = self.mosfet_power_w(current_a, wire_ohm)
        return ambient_c + power * self.electrical.mosfet_rth_total_k_per_w

    def ripple_a_pp(self, duty: float) -> float:
        """Peak-to-peak wire current left of the PWM at duty 0 … 1 (fundamental), A."""
        e = self.electrical
        sp = e["setpoint"]
        if duty <= 0.0 or duty >= 1.0:
            return 0.0
        fundamental_v = 2.0 * sp["pwm_high_v"] / math.pi * math.sin(math.pi * duty)
        omega = sp["pwm_frequency_hz"] * 2.0 * math.pi
        attenuation = 1.0
        for tau in e.setpoint_filter_poles_s:  # two real poles
            attenuation /= math.hypot(1.0, omega * tau)
        return 2.0 * fundamental_v * attenuation * e.setpoint_divider / e.shunt_ohm

    def supply_at_terminals_v(self, current_a: float) -> float:
        return self.supply_v - current_a * self.electrical["supply"]["source_resistance_ohm"]

    # --------------------------------------------------------------- dynamics
    def step(self, duty_counts: float, wire_ohm: float, dt_s: float) -> float:
        """Advance by ``dt_s`` with PWM ``duty_counts`` (0 … pwm_top); the wire current, A.

        The two filter poles are integrated exactly for a constant input over the step; the
        delivered current is then limited by the compliance."""
        e = self.electrical
        target_a = max(0.0, duty_counts) * e.setpoint_a_per_count
        tau1, tau2 = e.setpoint_filter_poles_s
        k1, k2 = math.exp(-dt_s / tau1), math.exp(-dt_s / tau2)
        s = self.state
        # exact zero-order-hold solution of two cascaded first-order poles (τ1 ≠ τ2)
        p1_old = s.pole1_a
        s.pole1_a = target_a + (p1_old - target_a) * k1
        s.pole2_a = target_a + (s.pole2_a - target_a) * k2 + (p1_old - target_a) * (
            tau1 / (tau1 - tau2)) * (k1 - k2)  # fmt: skip
        return min(max(s.pole2_a, 0.0), self.compliance_a(wire_ohm))

    def duty_for_current(self, current_a: float) -> float:
        """The PWM counts that set ``current_a`` in steady state (before calibration)."""
        return current_a / self.electrical.setpoint_a_per_count
