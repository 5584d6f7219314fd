"""Switchable physical effects of the plant simulation (all off by default).

Each effect is one number; 0 means off. ``Effects.from_strings(["latent_heat=24000"])`` parses
the CLI's ``--effect NAME=VALUE`` (a bare ``NAME`` takes the typical value of ``EFFECT_DOCS``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace

log = logging.getLogger(__name__)

REFERENCE_STRESS_MPA = 100.0
"""Stress, MPa, at which the Wire's transformation temperatures hold (stress_shift on)."""

CYCLE_DRIFT_TAU_CYCLES = 20.0
"""Saturation constant, cycles, of cycle_drift: residual strain = rate·tau·(1 - exp(-N/tau))."""

# name: (unit, min, max, typical, description)
_SPECS: dict[str, tuple[str, float, float, float, str]] = {
    "phase_resistance": (
        "µΩ·cm",
        -50.0,
        50.0,
        20.0,
        "resistivity difference austenite - martensite about the wire's mean "
        "(20 → 80/100 µΩ·cm): R and V/I depend on the martensite fraction; off: constant "
        "mean resistivity",
    ),
    "latent_heat": (
        "J/kg",
        0.0,
        40e3,
        24e3,
        "transformation enthalpy in the heat balance: + m·L·dξ/dt (heating absorbs, cooling "
        "releases) — slows heating between As and Af and cooling between Ms and Mf",
    ),
    "stress_shift": (
        "MPa/K",
        3.0,
        15.0,
        7.5,
        "Clausius–Clapeyron slope: transformation temperatures move by "
        f"(σ - {REFERENCE_STRESS_MPA:g} MPa)/slope; off: stress-free temperatures at any load",
    ),
    "convection_nonlinear": (
        "1/K",
        0.0,
        0.05,
        0.005,
        "convection grows with the overtemperature: h = h0·(1 + k·(T - T_room)); lowers the "
        "steady temperature at high current",
    ),
    "sensor_lag": (
        "s",
        0.0,
        2.0,
        0.1,
        "first-order lag time constant of the displacement reading (position delayed by ≈ τ)",
    ),
    "ambient_drift": (
        "K/h",
        -10.0,
        10.0,
        2.0,
        "unmeasured linear drift of the room temperature (the recorded ambient stays nominal)",
    ),
    "ambient_sine": (
        "K",
        0.0,
        5.0,
        1.0,
        "unmeasured sinusoidal room-temperature swing, amplitude (period: ambient_sine_period)",
    ),
    "ambient_sine_period": (
        "s",
        10.0,
        86400.0,
        1800.0,
        "period of ambient_sine (a parameter, not an effect by itself; default 1800 s)",
    ),
    "cycle_drift": (
        "strain/cycle",
        0.0,
        1e-3,
        2e-4,
        "residual strain grows by this per transformation cycle (cycle = 2 units of |Δξ|) "
        f"and saturates at rate·{CYCLE_DRIFT_TAU_CYCLES:g} cycles: the cold position creeps up",
    ),
    "pulley_friction": (
        "N",
        0.0,
        20.0,
        3.0,
        "Coulomb friction at the pulley: the wire tension is Mg ± F, so the length shows a "
        "deadband of 2·F·L0/(E·A) on every reversal (stick, then slip). Not in the paper's "
        "models: an analysis should report it as unexplained",
    ),
}

EFFECT_DOCS: dict[str, str] = {
    name: f"[{unit}] range {lo:g}…{hi:g}, typical {typ:g}: {text}"
    for name, (unit, lo, hi, typ, text) in _SPECS.items()
}
"""Effect name → parameter unit, physical range, typical value, what it does."""


@dataclass(frozen=True)
class Effects:
    """Effect switches of the plant; 0 = off. Units and ranges: see ``EFFECT_DOCS``."""

    phase_resistance: float = 0.0
    latent_heat: float = 0.0
    stress_shift: float = 0.0
    convection_nonlinear: float = 0.0
    sensor_lag: float = 0.0
    ambient_drift: float = 0.0
    ambient_sine: float = 0.0
    ambient_sine_period: float = 1800.0
    cycle_drift: float = 0.0
    pulley_friction: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            unit, lo, hi, _, _ = _SPECS[f.name]
            off_ok = value == 0.0 and f.name != "ambient_sine_period"
            if not off_ok and not lo <= value <= hi:
                raise ValueError(
                    f"effect {f.name}={value:g} out of range {lo:g}…{hi:g} {unit} (0 = off)"
                )

    @property
    def coupled(self) -> bool:
        """True when an effect feeds ξ or T back into the heat balance (sequential simulation)."""
        return bool(self.latent_heat or self.phase_resistance or self.convection_nonlinear)

    def active(self) -> list[str]:
        """Names of the effects switched on."""
        return [
            f.name
            for f in fields(self)
            if f.name != "ambient_sine_period" and getattr(self, f.name) != 0.0
        ]

    @classmethod
    def from_strings(cls, items: list[str] | tuple[str, ...]) -> Effects:
        """Parse ``["NAME=VALUE", "NAME", ...]``; ValueError on unknown names or bad values."""
        values: dict[str, float] = {}
        for item in items:
            name, sep, text = item.partition("=")
            name = name.strip().replace("-", "_")
            if name not in _SPECS:
                raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(_SPECS))}")
            if sep:
                try:
                    values[name] = float(text)
                except ValueError:
                    raise ValueError(f"effect {name}: {text!r} is not a number") from None
            else:
                values[name] = _SPECS[name][3]
        return replace(cls(), **values)
