"""Wire and material parameters (SI units inside, units in every name) and load → stress.

Presets:
- ``PAPER_WIRE``: Shibly & Söffker's NiTi wire, radius 0.19 mm, bench length 55 mm.
- ``FLEXINOL_038_70C`` / ``FLEXINOL_038_90C``: Dynalloy Flexinol, 0.38 mm diameter,
  70 °C (LT) and 90 °C (HT) activation grades.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

G_M_S2 = 9.80665


@dataclass(frozen=True)
class Wire:
    """Geometry and material of one SMA wire.

    Attributes:
        radius_m: wire radius, m (0.05e-3 … 0.5e-3).
        length_m: active length between clamps, m (0.01 … 2).
        density_kg_m3: mass density, kg/m³ (NiTi ≈ 6450).
        cp_j_kgk: specific heat, J/(kg·K) (NiTi ≈ 837).
        h_w_m2k: convection coefficient in still air, W/(m²·K) (≈ 40–200 for thin wires).
        resistivity_martensite_ohm_m: Ω·m (≈ 80e-8).
        resistivity_austenite_ohm_m: Ω·m (≈ 100e-8).
        latent_heat_j_kg: transformation enthalpy, J/kg (≈ 24e3).
        as_c, af_c, ms_c, mf_c: stress-free transformation temperatures, °C.
        stress_rate_mpa_per_k: Clausius–Clapeyron slope dσ/dT, MPa/K (≈ 7–8).
        max_strain: recoverable transformation strain (0.04 … 0.05).
        e_austenite_pa, e_martensite_pa: Young's moduli, Pa.
        alpha_per_k: linear thermal expansion of the austenite, 1/K (≈ 11e-6).
        max_current_a: rated current, A.
        hysteresis_shrink_k_per_mpa: thermal hysteresis width lost per MPa of stress, K/MPa
            (0 … 0.05; heating temperatures drop and cooling ones rise by half of it each):
            makes loops narrower under more load (paper Fig. 11).
        kinetics_tau_heating_s, kinetics_tau_cooling_s: first-order lag of the martensite
            fraction behind its equilibrium value on heating (A-forming) / cooling (M-forming,
            nucleation-limited, slower), s (0 … 2): widens the loop with the heating/cooling
            rate, so larger h widens and larger cp thins it (paper Fig. 11).
        long_life_stress_mpa: highest stress for a long cycle life, MPa. Flexinol: 172 MPa
            (≈ 25,000 psi; Dynalloy, "Technical Characteristics of Flexinol Actuator Wires",
            F1140 Rev I.2, whose curves are drawn at 172 MPa and whose pull forces are based on
            it): ≈ 2 kg on 0.38 mm. A heavier load needs the operator's confirmation.
    """

    radius_m: float = 0.19e-3
    length_m: float = 0.055
    density_kg_m3: float = 6450.0
    cp_j_kgk: float = 837.0
    h_w_m2k: float = 120.0
    resistivity_martensite_ohm_m: float = 80e-8
    resistivity_austenite_ohm_m: float = 100e-8
    latent_heat_j_kg: float = 24e3
    as_c: float = 68.0
    af_c: float = 78.0
    ms_c: float = 52.0
    mf_c: float = 42.0
    stress_rate_mpa_per_k: float = 7.5
    max_strain: float = 0.045
    e_austenite_pa: float = 75e9
    e_martensite_pa: float = 30e9
    alpha_per_k: float = 11e-6
    max_current_a: float = 2.0
    hysteresis_shrink_k_per_mpa: float = 0.03
    kinetics_tau_heating_s: float = 0.05
    kinetics_tau_cooling_s: float = 0.5
    long_life_stress_mpa: float = 172.0

    @property
    def area_m2(self) -> float:
        """Cross-section, m²."""
        return math.pi * self.radius_m**2

    @property
    def surface_m2(self) -> float:
        """Lateral surface exchanging heat, m²."""
        return 2.0 * math.pi * self.radius_m * self.length_m

    @property
    def mass_kg(self) -> float:
        """Wire mass, kg."""
        return self.density_kg_m3 * self.area_m2 * self.length_m

    @property
    def diameter_mm(self) -> float:
        return 2e3 * self.radius_m

    @property
    def length_mm(self) -> float:
        return 1e3 * self.length_m

    def resistance_ohm(self, martensite_fraction: float | np.ndarray = 0.5) -> float | np.ndarray:
        """Electrical resistance, Ω, for a martensite fraction in [0, 1]."""
        rho = self.resistivity_austenite_ohm_m + (
            self.resistivity_martensite_ohm_m - self.resistivity_austenite_ohm_m
        ) * np.asarray(martensite_fraction, dtype=float)
        r = rho * self.length_m / self.area_m2
        return float(r) if np.ndim(r) == 0 else r

    @property
    def resistance_mean_ohm(self) -> float:
        """Resistance at the mean of both phases' resistivities, Ω."""
        return float(self.resistance_ohm(0.5))

    def with_length_mm(self, length_mm: float) -> Wire:
        return replace(self, length_m=length_mm * 1e-3)

    def with_diameter_mm(self, diameter_mm: float) -> Wire:
        return replace(self, radius_m=diameter_mm * 0.5e-3)


def stress_mpa(load_kg: float | np.ndarray, wire: Wire) -> float | np.ndarray:
    """Axial stress, MPa, of a hanging mass ``load_kg`` (kg) on ``wire``."""
    s = np.asarray(load_kg, dtype=float) * G_M_S2 / wire.area_m2 * 1e-6
    return float(s) if np.ndim(s) == 0 else s


def load_kg_for_stress(stress: float, wire: Wire) -> float:
    """Hanging mass, kg, that gives ``stress`` MPa on ``wire``."""
    return stress * 1e6 * wire.area_m2 / G_M_S2


PAPER_WIRE = Wire()
"""Shibly & Söffker's NiTi wire: r = 0.19 mm, currents up to 2 A, loads 1–4 kg (3–4 kg are above
the long-life stress; the paper does not give one, so Flexinol's 172 MPa applies)."""

FLEXINOL_038_70C = Wire(
    radius_m=0.19e-3,
    h_w_m2k=90.0,
    as_c=68.0,
    af_c=78.0,
    ms_c=52.0,
    mf_c=42.0,
    max_current_a=2.25,
)
"""Flexinol 0.38 mm LT (70 °C activation): ≈ 8.3 Ω/m, ≈ 2.25 A recommended current."""

FLEXINOL_038_90C = Wire(
    radius_m=0.19e-3,
    h_w_m2k=90.0,
    as_c=88.0,
    af_c=98.0,
    ms_c=72.0,
    mf_c=62.0,
    max_current_a=2.25,
)
"""Flexinol 0.38 mm HT (90 °C activation)."""

PRESETS: dict[str, Wire] = {
    "paper": PAPER_WIRE,
    "flexinol-0.38-70c": FLEXINOL_038_70C,
    "flexinol-0.38-90c": FLEXINOL_038_90C,
}
