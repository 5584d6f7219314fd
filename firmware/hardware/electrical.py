"""Load ``electrical.toml`` and derive the figures every consumer needs (units in names)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

TOML_PATH = Path(__file__).resolve().parent / "electrical.toml"


@dataclass(frozen=True)
class Electrical:
    """The parsed parameter file, with derived figures as properties."""

    raw: dict[str, Any]

    def __getitem__(self, section: str) -> dict[str, Any]:
        return self.raw[section]

    # --------------------------------------------------------------- sink and setpoint
    @cached_property
    def shunt_ohm(self) -> float:
        return float(self["sink"]["shunt_ohm"])

    @property
    def current_max_a(self) -> float:
        return float(self["sink"]["current_max_a"])

    @cached_property
    def setpoint_divider(self) -> float:
        """DC ratio from the switched VREF to the op-amp's + input (R21 / (R20 + R_on + R21))."""
        sp = self["setpoint"]
        top = sp["divider_top_ohm"] + sp["switch_ron_ohm"]
        return sp["divider_bottom_ohm"] / (top + sp["divider_bottom_ohm"])

    @cached_property
    def setpoint_a_per_count(self) -> float:
        """Sink current per PWM count (duty 0 … ``pwm_top``), A."""
        sp = self["setpoint"]
        return sp["pwm_high_v"] * self.setpoint_divider / self.shunt_ohm / sp["pwm_top"]

    @property
    def setpoint_full_scale_a(self) -> float:
        return self.setpoint_a_per_count * self["setpoint"]["pwm_top"]

    @cached_property
    def setpoint_filter_poles_s(self) -> tuple[float, float]:
        """The two time constants of the R20/R21/C2 – R3/C3 ladder, s (slower first).

        The ladder's denominator is ``1 + s·(τa + τb + τc) + s²·τa·τb`` with ``τa = (R20+R_on)∥R21
        · C2``, ``τb = R3·C3`` and the loading term ``τc = (R20+R_on)∥R21 · C3``; its roots are
        real and distinct (a passive RC ladder cannot have two equal poles)."""
        sp = self["setpoint"]
        top = sp["divider_top_ohm"] + sp["switch_ron_ohm"]
        r_th = top * sp["divider_bottom_ohm"] / (top + sp["divider_bottom_ohm"])
        tau_a = r_th * sp["filter1_c_f"]
        tau_b = sp["filter2_r_ohm"] * sp["filter2_c_f"]
        tau_c = r_th * sp["filter2_c_f"]
        total, product = tau_a + tau_b + tau_c, tau_a * tau_b
        root = math.sqrt(total * total - 4.0 * product)
        return ((total + root) / 2.0, (total - root) / 2.0)

    @property
    def setpoint_filter_tau_s(self) -> float:
        """The equal-pole equivalent with the same mean delay ((τ1 + τ2) / 2), s: what the
        firmware's reference model uses (``ELEC_SETPOINT_FILTER_TAU_US``)."""
        t1, t2 = self.setpoint_filter_poles_s
        return (t1 + t2) / 2.0

    def setpoint_step_fraction(self, t_s: float) -> float:
        """Fraction of a setpoint step reached ``t_s`` after it (the two ladder poles)."""
        t1, t2 = self.setpoint_filter_poles_s
        if t_s <= 0.0:
            return 0.0
        return 1.0 - (t1 * math.exp(-t_s / t1) - t2 * math.exp(-t_s / t2)) / (t1 - t2)

    def setpoint_step_time_s(self, fraction: float) -> float:
        """Time for a setpoint step to reach ``fraction`` (0 … 1) of its size, s (bisection)."""
        lo, hi = 0.0, 100.0 * self.setpoint_filter_poles_s[0]
        for _ in range(100):
            mid = (lo + hi) / 2.0
            if self.setpoint_step_fraction(mid) < fraction:
                lo = mid
            else:
                hi = mid
        return hi

    @property
    def setpoint_rise_s(self) -> float:
        """10–90 % rise time of a setpoint step, s."""
        return self.setpoint_step_time_s(0.9) - self.setpoint_step_time_s(0.1)

    @property
    def setpoint_settle_s(self) -> float:
        """Time for a setpoint step to settle within 0.1 %, s."""
        return self.setpoint_step_time_s(0.999)

    # --------------------------------------------------------------- measurement
    @property
    def current_amplifier_gain(self) -> float:
        """Fast path: U1B's non-inverting gain 1 + R23/R24."""
        cs = self["current_sense"]
        return 1.0 + cs["amplifier_rf_ohm"] / cs["amplifier_rg_ohm"]

    @property
    def current_adc_a_per_count(self) -> float:
        """Fast path: wire current per internal ADC count, A."""
        cs = self["current_sense"]
        return cs["adc_reference_v"] / 2 ** cs["adc_bits"] / (
            self.current_amplifier_gain * self.shunt_ohm)  # fmt: skip

    @property
    def current_adc_full_scale_a(self) -> float:
        """Fast path: the current at which ADC0 saturates on the lowest AVcc, A."""
        cs = self["current_sense"]
        return cs["adc_reference_min_v"] / (self.current_amplifier_gain * self.shunt_ohm)

    @property
    def precise_current_a_per_lsb(self) -> float:
        """ADS1115 shunt channel: current per LSB, A."""
        pa = self["precise_adc"]
        return pa["shunt_fsr_v"] / 2 ** (pa["lsb_bits"] - 1) / self.shunt_ohm

    @property
    def precise_current_full_scale_a(self) -> float:
        return self["precise_adc"]["shunt_fsr_v"] / self.shunt_ohm

    @property
    def precise_wire_v_per_lsb(self) -> float:
        """ADS1115 wire channel: wire voltage per LSB (through the difference amplifier), V."""
        pa = self["precise_adc"]
        return pa["wire_fsr_v"] / 2 ** (pa["lsb_bits"] - 1) / pa["wire_gain"]

    @property
    def precise_wire_v_max(self) -> float:
        pa = self["precise_adc"]
        return pa["wire_fsr_v"] / pa["wire_gain"]

    def resistance_resolution(self, wire_ohm: float, current_a: float) -> float:
        """Relative resolution of R = V/I from one ADS1115 LSB of each channel (0.001 = 0.1 %)."""
        dv = self.precise_wire_v_per_lsb / (wire_ohm * current_a)
        di = self.precise_current_a_per_lsb / current_a
        return math.hypot(dv, di)

    # --------------------------------------------------------------- the cut
    @property
    def loop_resistance_ohm(self) -> float:
        """Everything in the wire's loop except the wire and the MOSFET: supply, leads, fuse,
        clamps, the eFuse and the shunt, Ω."""
        return (self["supply"]["source_resistance_ohm"] + self["cut"]["switch_ron_ohm"]
                + self.shunt_ohm)  # fmt: skip

    @property
    def trip_sink_a(self) -> float:
        """Comparator U7A's threshold on the shunt current, A."""
        c = self["cut"]
        ratio = c["trip_sink_bottom_ohm"] / (c["trip_sink_top_ohm"] + c["trip_sink_bottom_ohm"])
        return self["setpoint"]["pwm_high_v"] * ratio / self.shunt_ohm

    @property
    def trip_supply_a(self) -> float:
        """Comparator U7B's threshold on the supply current (U10's IMON), A."""
        c = self["cut"]
        ratio = c["trip_supply_bottom_ohm"] / (
            c["trip_supply_top_ohm"] + c["trip_supply_bottom_ohm"])  # fmt: skip
        return self["setpoint"]["pwm_high_v"] * ratio / (c["imon_gain_a_per_a"] * c["imon_r_ohm"])

    # --------------------------------------------------------------- thermal
    @property
    def mosfet_rth_total_k_per_w(self) -> float:
        sk = self["sink"]
        return (sk["mosfet_rth_jc_k_per_w"] + sk["mosfet_rth_cs_k_per_w"]
                + sk["insulator_rth_k_per_w"] + sk["heatsink_rth_k_per_w"])  # fmt: skip


def load_electrical(path: Path | str = TOML_PATH) -> Electrical:
    """Parse a parameter file (ValueError naming the file when it is broken)."""
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: {exc}") from None
    for section in ("supply", "sink", "setpoint", "current_sense", "precise_adc", "cut", "ntc",
                    "pins", "netlist"):
        if section not in raw:
            raise ValueError(f"{path}: section [{section}] missing")
    return Electrical(raw)


ELECTRICAL = load_electrical()
