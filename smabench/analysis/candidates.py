"""The one registry of the analysis: the baseline's parameters and every candidate cause.

Each cause is declared once here: its parameters (unit, scale, bounds, start), the extra starts
its fit needs, whether it feeds back into the heat balance (coupled), what data it needs, the
sentence that says what it means, and its headline parameter. Fitting (``core._spec``,
``core.fit_model``), the verdict (``core.make_problem``) and the report (``report.summary``) all
read this table; nothing about a candidate is written anywhere else.

Physical constants come from :mod:`smabench.physics.wire` (the paper's wire defaults).
"""

from __future__ import annotations

from dataclasses import dataclass

from smabench.physics.wire import G_M_S2, PAPER_WIRE

RHO_KG_M3 = PAPER_WIRE.density_kg_m3
CP_J_KGK = PAPER_WIRE.cp_j_kgk
RESISTIVITY_MEAN_OHM_M = 0.5 * (
    PAPER_WIRE.resistivity_martensite_ohm_m + PAPER_WIRE.resistivity_austenite_ohm_m
)
DCOMPLIANCE_PER_MPA = 1e6 * (1.0 / PAPER_WIRE.e_martensite_pa - 1.0 / PAPER_WIRE.e_austenite_pa)
"""Compliance difference martensite − austenite, 1/MPa (the elastic part of the stroke)."""

__all__ = ["BASELINE", "CANDIDATES", "CP_J_KGK", "G_M_S2", "Candidate", "Param", "REGISTRY"]


@dataclass(frozen=True)
class Param:
    """One fitted parameter: ``scale`` is its typical size (the optimiser works in units of
    it), ``lo``/``hi`` its physical bounds, ``start`` where fits begin."""

    name: str
    unit: str
    scale: float
    lo: float
    hi: float
    start: float


@dataclass(frozen=True)
class Candidate:
    """A cause: a physical extension of the baseline, 0 = off.

    ``needs``: "heat_balance" (current-driven sessions), "loads" (two loads or more),
    "cycles" (``min_cycles`` complete cycles in one session) or "" (any session).
    ``fresh_starts``: values of the first parameter for extra starts from the data (coupled
    effects bend the baseline's thermal parameters); ``second_start``: one more start from the
    baseline's fit with the first parameter at this value. ``many_cycles``: parameters fitted
    only from 20 complete cycles on (else held at their start). ``magnitude``: the parameters
    whose 0 turns the cause off (empty: the first)."""

    name: str
    params: tuple[Param, ...]
    headline: str
    text: str
    needs: str = ""
    min_cycles: int = 0
    coupled: bool = False
    fresh_starts: tuple[float, ...] = ()
    second_start: float | None = None
    many_cycles: tuple[str, ...] = ()
    magnitude: tuple[str, ...] = ()

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def off_params(self) -> tuple[str, ...]:
        """The parameters that are all 0 when the cause is off."""
        return self.magnitude or (self.params[0].name,)


BASELINE: tuple[Param, ...] = (
    Param("tau_s", "s", 4.0, 0.2, 120.0, 4.0),
    Param("h_mid", "°C", 10.0, -50.0, 250.0, 70.0),
    Param("h_w", "K", 10.0, 2.0, 80.0, 10.0),
    Param("hyst_k", "K (heating centre − cooling centre, ≥ 0)", 10.0, 0.0, 150.0, 20.0),
    Param("c_w", "K", 10.0, 2.0, 80.0, 10.0),
    Param("h_shape", "1 (-1 Tanaka exponential … 0 cosine … 1 logistic)", 0.3, -1.0, 1.0, 0.3),
    Param("c_shape", "1 (-1 Tanaka exponential … 0 cosine … 1 logistic)", 0.3, -1.0, 1.0, 0.3),
    Param("memory", "1 (0 scaled branch … 1 wiping-out)", 0.3, 0.0, 1.0, 0.0),
    Param("heat_lag_ratio", "1 (τ_heat/τ_cool ≤ 0.5: the reverse transformation needs no "
          "nucleation; equal lags on both branches are a sensor's)", 0.1, 0.0, 0.5, 0.1),
    Param("tau_cool_s", "s", 0.5, 0.0, 5.0, 0.2),
    Param("shrink_k_per_mpa", "K/MPa", 0.03, 0.0, 0.1, 0.0),
)
"""The baseline's nonlinear parameters (which of them a problem uses: ``core._spec``). The loop's
direction is built in: the cooling centre is ``h_mid − hyst_k`` with ``hyst_k ≥ 0``."""

DERIVED_UNITS = {
    "c_mid": "°C",
    "eps_l": "strain",
    "alpha_per_k": "1/K",
    "eps_mix": "strain (× ξ(1-ξ))",
    "eps_l_per_mpa": "strain/MPa (× ξ·(σ − σ_ref): the stroke's growth with stress)",
    "stress_rate_mpa_per_k": "MPa/K",
    "resistivity_difference_uohm_cm": "µΩ·cm",
    "latent_heat_j_kg": "J/kg",
    "sensor_delay_s": "s",
    "drift_per_cycle": "strain/cycle (mean over the first 10 cycles)",
}
"""Units of quantities derived from the fitted parameters (reported, not fitted)."""

_LIST = (
    Candidate(
        "phase_resistance",
        (Param("beta", "1 (ΔR/R_mean)", 0.2, -0.8, 0.8, 0.05),),
        headline="resistivity_difference_uohm_cm",
        text="the wire's resistance depends on its phase (austenite and martensite "
        "resistivities differ), so the heating power I²R changes as it transforms",
        needs="heat_balance", coupled=True, fresh_starts=(-0.2, 0.2),
    ),  # fmt: skip
    Candidate(
        "latent_heat",
        (Param("lat_k", "K per unit ξ", 20.0, 0.0, 80.0, 10.0),),
        headline="latent_heat_j_kg",
        text="the transformation absorbs heat on heating and releases it on cooling "
        "(its enthalpy is missing from the heat balance)",
        needs="heat_balance", coupled=True, fresh_starts=(15.0, 30.0),
    ),  # fmt: skip
    Candidate(
        "stress_shift",
        (Param("ss_k_per_mpa", "K/MPa", 0.1, -0.3, 1.0, 0.1),),
        headline="stress_rate_mpa_per_k",
        text="the transformation temperatures rise with stress (Clausius–Clapeyron): "
        "the loops of different loads sit at different temperatures",
        needs="loads", second_start=0.0,
    ),  # fmt: skip
    Candidate(
        "convection_nonlinear",
        (Param("conv_k", "1/K", 0.005, 0.0, 0.1, 0.003),),
        headline="conv_k",
        text="heat loss grows faster than linearly with the wire's overtemperature "
        "(natural convection and radiation)",
        needs="heat_balance", coupled=True, fresh_starts=(0.008, 0.02), second_start=0.015,
    ),  # fmt: skip
    Candidate(
        "sensor_lag",
        (Param("lag_s", "s", 0.2, 0.0, 10.0, 0.2), Param("delay_s", "s", 0.2, 0.0, 10.0, 0.0)),
        headline="sensor_delay_s",
        text="the displacement reading lags the wire (sensor filter or transport delay): "
        "every motion is late by the same time, the transformation on both branches, the "
        "thermal expansion and the rests alike",
        magnitude=("lag_s", "delay_s"),
    ),  # fmt: skip
    Candidate(
        "ambient_drift",
        (Param("drift_k_h", "K/h", 5.0, -60.0, 60.0, 0.0),),
        headline="drift_k_h",
        text="the room temperature drifts during the session and is not measured",
        needs="heat_balance",
    ),  # fmt: skip
    Candidate(
        "cycle_drift",
        (Param("cyc_rate", "strain/cycle (at the first cycle)", 2e-4, -3e-3, 3e-3, 0.0),
         Param("cyc_n0", "cycles", 20.0, 0.3, 1000.0, 30.0),
         Param("cyc_q", "1 (decay exponent of the rate)", 0.5, 0.0, 3.0, 1.0)),
        headline="drift_per_cycle",
        text="residual strain grows with the number of transformation cycles (functional "
        "fatigue, training), at a rate that may fall as cycles accumulate",
        needs="cycles", min_cycles=3, many_cycles=("cyc_q",),
    ),  # fmt: skip
)

REGISTRY: dict[str, Candidate] = {c.name: c for c in _LIST}
"""Candidate name → its declaration."""

CANDIDATES: tuple[str, ...] = tuple(REGISTRY)
COUPLED = frozenset(c.name for c in _LIST if c.coupled)

VERDICT_TEXT = {
    "none": "the baseline explains the held-out data to within its accuracy floor",
    "unexplained": "structure remains that none of the candidate causes removes (or two "
    "cannot be told apart)",
}

RIVAL: tuple[Param, ...] = (
    Param("xi_delay_s", "s (dead time of ξ only)", 0.2, 0.0, 10.0, 0.0),
)
"""Extra parameter of the kinetic rival of ``sensor_lag`` (``core.KINETIC_RIVAL``): the
transformation late by a dead time, the thermal expansion not."""

RATE_KINETICS: tuple[Param, ...] = (
    Param("rate_shift_k", "K per √(K/s) (the transformation starts k·√|dT/dt| late: As "
          "higher on heating, Ms lower on cooling)", 0.5, 0.0, 5.0, 0.8),
)
"""Extra parameter of the baseline's rate-dependent kinetics (``core.RATE_KINETICS``): the wire's
own physics, not a hidden effect; tried only when no candidate is named (see there)."""

PARAMS: dict[str, Param] = {p.name: p for p in (*BASELINE, *RIVAL, *RATE_KINETICS)}
for _c in _LIST:
    PARAMS.update({p.name: p for p in _c.params})


def cause_text(name: str) -> str:
    """What a verdict (a cause, ``a+b`` of several, ``none``, ``unexplained``) means."""
    if name in VERDICT_TEXT:
        return VERDICT_TEXT[name]
    parts = [REGISTRY[n].text for n in name.split("+") if n in REGISTRY]
    return "; and ".join(parts)


def unit_of(name: str) -> str:
    """Unit of a fitted or derived parameter ("" when unknown)."""
    if name in PARAMS:
        return PARAMS[name].unit
    return DERIVED_UNITS.get(name, "")


def members(model: str) -> list[str]:
    """The candidates of a model name: "baseline" → [], "a+b" → ["a", "b"]."""
    return [m for m in model.split("+") if m in REGISTRY]
