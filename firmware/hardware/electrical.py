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
        sp = self["setpoint"]
        return sp["divider_bottom_ohm"] / (sp["divider_top_ohm"] + sp["divider_bottom_ohm"])

    @cached_property
    def setpoint_a_per_count(self) -> float:
        """Sink current per PWM count (duty 0 … ``pwm_top``), A."""
        sp = self["setpoint"]
        return sp["pwm_high_v"] * self.setpoint_divider / self.shunt_ohm / sp["pwm_top"]

    @property
    def setpoint_full_scale_a(self) -> float:
        return self.setpoint_a_per_count * self["setpoint"]["pwm_top"]

    @cached_property
    def setpoint_filter_tau_s(self) -> float:
        """Time constant of each of the two RC poles of the PWM filter, s."""
        sp = self["setpoint"]
        return sp["filter_r_ohm"] * sp["filter_c_f"]

    # --------------------------------------------------------------- measurement
    @property
    def current_adc_a_per_count(self) -> float:
        """Fast path: wire current per internal ADC count, A."""
        cs = self["current_sense"]
        return cs["adc_reference_v"] / 2 ** cs["adc_bits"] / (cs["amplifier_gain"] * self.shunt_ohm)

    @property
    def precise_current_a_per_lsb(self) -> float:
        """ADS1115 shunt channel: current per LSB, A."""
        pa = self["precise_adc"]
        return pa["shunt_fsr_v"] / 2 ** (pa["lsb_bits"] - 1) / self.shunt_ohm

    @property
    def precise_wire_v_per_lsb(self) -> float:
        """ADS1115 wire channel: wire voltage per LSB (through the 1:2 dividers), V."""
        pa = self["precise_adc"]
        return pa["wire_fsr_v"] / 2 ** (pa["lsb_bits"] - 1) / pa["wire_divider"]

    @property
    def precise_wire_v_max(self) -> float:
        pa = self["precise_adc"]
        return pa["wire_fsr_v"] / pa["wire_divider"]

    def resistance_resolution(self, wire_ohm: float, current_a: float) -> float:
        """Relative resolution of R = V/I from one ADS1115 LSB of each channel (0.001 = 0.1 %)."""
        dv = self.precise_wire_v_per_lsb / (wire_ohm * current_a)
        di = self.precise_current_a_per_lsb / current_a
        return math.hypot(dv, di)

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
    for section in ("supply", "sink", "setpoint", "current_sense", "precise_adc", "ntc", "pins"):
        if section not in raw:
            raise ValueError(f"{path}: section [{section}] missing")
    return Electrical(raw)


ELECTRICAL = load_electrical()
