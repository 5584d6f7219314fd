"""Electrical resistance of a NiTi wire, for using the wire as its own position sensor.

Model (SI inside, units in every name):

- Resistivity of each phase, linear in temperature about ``ref_c``:
  ``ρ_M(T) = ρ_M·(1 + α_M·(T - T_ref))``, ``ρ_A(T) = ρ_A·(1 + α_A·(T - T_ref))``, and, optional,
  the R-phase ``ρ_R(T) = ρ_R·(1 + α_A·(T - T_ref))`` (the austenite's coefficient).
- Phase mixture (series-parallel detail ignored, a rule of mixtures by volume):
  ``ρ = ξ·ρ_M(T) + (1 - ξ)·[(1 - r)·ρ_A(T) + r·ρ_R(T)]``, ξ the martensite fraction (1 = long,
  0 = short, as in ``smabench.physics.plant``), r the R-phase fraction of the non-martensite part
  (``rphase_fraction``).
- Geometry at constant volume: ``L = L0·(1 + ε)``, ``A = A0/(1 + ε)``, so
  ``R = ρ·L0·(1 + ε)²/A0``, ε the wire's total strain against its free length
  ``L0 = wire.length_m`` (transformation + elastic + thermal: what the plant computes).
- Measurement (``MeasurementChain``, ``measured_resistance_ohm``): the Kelvin wire voltage through
  gain error, offset, Gaussian noise and the ADC's quantization; R = V/I, NaN at small currents.

Not modelled: a resistivity of detwinned (loaded) martensite different from self-accommodated
martensite, the stress dependence of the R-phase temperatures, the R-phase on heating, the current
measurement's own error (the current is taken as exact).

Presets: ``FLEXINOL_RESISTIVITY`` (no R-phase), ``FLEXINOL_WITH_RPHASE`` (70 °C grade); sources
and assumptions at each number. ``ADS1115_KELVIN_CHAIN``: the bench's wire-voltage channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from smabench.physics.wire import Wire

__all__ = [
    "ADS1115_KELVIN_CHAIN",
    "FLEXINOL_RESISTIVITY",
    "FLEXINOL_WITH_RPHASE",
    "MeasurementChain",
    "RESISTIVITY_PRESETS",
    "ResistivityModel",
    "measured_resistance_ohm",
    "resistance_ohm",
    "resistivity_ohm_m",
    "rphase_fraction",
]


def _out(x: np.ndarray) -> float | np.ndarray:
    """0-d → float, else the array."""
    return float(x) if np.ndim(x) == 0 else x


def _check_fraction(name: str, x: np.ndarray) -> None:
    if np.any(x < 0.0) or np.any(x > 1.0):  # NaN passes: it propagates to R
        raise ValueError(f"{name} must lie in [0, 1]")


@dataclass(frozen=True)
class ResistivityModel:
    """Resistivities of the NiTi phases and their temperature coefficients.

    Attributes:
        rho_martensite_ohm_m: B19' martensite at ``ref_c``, Ω·m (NiTi ≈ 70e-8 … 100e-8).
        rho_austenite_ohm_m: B2 austenite at ``ref_c`` (extrapolated where austenite does not
            exist at ``ref_c``), Ω·m.
        tcr_martensite_per_k, tcr_austenite_per_k: linear temperature coefficients about
            ``ref_c``, 1/K (small and positive for NiTi: ≈ 1e-4 … 1e-3).
        ref_c: reference temperature of the resistivities, °C.
        rho_rphase_ohm_m: R-phase at ``ref_c``, Ω·m, above both phases' values (the resistance
            bump on cooling), or None for no R-phase; scaled with ``tcr_austenite_per_k``.
        rs_c, rf_c: R-phase start and finish on cooling, °C (rs_c > rf_c, both above the wire's
            Ms); None without an R-phase.
    """

    rho_martensite_ohm_m: float
    rho_austenite_ohm_m: float
    tcr_martensite_per_k: float = 0.0
    tcr_austenite_per_k: float = 0.0
    ref_c: float = 20.0
    rho_rphase_ohm_m: float | None = None
    rs_c: float | None = None
    rf_c: float | None = None

    def __post_init__(self) -> None:
        if self.rho_martensite_ohm_m <= 0 or self.rho_austenite_ohm_m <= 0:
            raise ValueError("resistivities must be positive")
        given = [v is not None for v in (self.rho_rphase_ohm_m, self.rs_c, self.rf_c)]
        if any(given) and not all(given):
            raise ValueError("an R-phase needs rho_rphase_ohm_m, rs_c and rf_c together")
        if all(given):
            if not self.rs_c > self.rf_c:  # type: ignore[operator]
                raise ValueError(f"R-phase needs rs_c > rf_c, got {self.rs_c} ≤ {self.rf_c}")
            top = max(self.rho_martensite_ohm_m, self.rho_austenite_ohm_m)
            if not self.rho_rphase_ohm_m > top:  # type: ignore[operator]
                raise ValueError("the R-phase resistivity must exceed both phases'")

    @property
    def has_rphase(self) -> bool:
        return self.rho_rphase_ohm_m is not None


def rphase_fraction(
    temp_c: float | np.ndarray, cooling: bool | np.ndarray, model: ResistivityModel
) -> float | np.ndarray:
    """R-phase fraction r (0 … 1) of the wire's non-martensite part at ``temp_c`` (°C).

    On cooling (``cooling`` True, broadcast against ``temp_c``) a cosine ramp like the plant's
    ξ_cool: 0 above Rs, ``0.5·(1 + cos(π·(T - Rf)/(Rs - Rf)))`` between, 1 below Rf, so what is
    left of the austenite below Rf is R-phase until the martensite takes it over (the wire's
    R-phase volume ``(1 - ξ)·r`` is non-zero between Rs and Mf only). On heating 0 (B19' → B2
    directly: no bump on heating), and 0 for a model without an R-phase. Memoryless: a reversal
    to heating inside Rf … Rs drops r to 0 at once, a simplification.
    """
    temp = np.asarray(temp_c, dtype=float)
    cool = np.asarray(cooling, dtype=bool)
    if not model.has_rphase:
        return _out(np.zeros(np.broadcast_shapes(temp.shape, cool.shape)))
    x = np.clip((temp - model.rf_c) / (model.rs_c - model.rf_c), 0.0, 1.0)  # type: ignore[operator]
    r = 0.5 * (1.0 + np.cos(np.pi * x))
    return _out(np.where(cool, r, 0.0 * r))


def resistivity_ohm_m(
    xi: float | np.ndarray,
    temp_c: float | np.ndarray,
    model: ResistivityModel,
    rphase: float | np.ndarray | None = None,
) -> float | np.ndarray:
    """Mixture resistivity, Ω·m, at martensite fraction ``xi`` (0 … 1), ``temp_c`` (°C) and
    R-phase fraction ``rphase`` of the non-martensite part (0 … 1, None = 0); broadcasts."""
    xi_a = np.asarray(xi, dtype=float)
    dt = np.asarray(temp_c, dtype=float) - model.ref_c
    _check_fraction("xi", xi_a)
    rho_m = model.rho_martensite_ohm_m * (1.0 + model.tcr_martensite_per_k * dt)
    rho_a = model.rho_austenite_ohm_m * (1.0 + model.tcr_austenite_per_k * dt)
    if rphase is None:
        rest = rho_a
    else:
        r = np.asarray(rphase, dtype=float)
        _check_fraction("rphase", r)
        if not model.has_rphase:
            if np.any(r > 0.0):
                raise ValueError("rphase > 0 given for a model without an R-phase")
            rest = rho_a + 0.0 * r
        else:
            rho_r = model.rho_rphase_ohm_m * (1.0 + model.tcr_austenite_per_k * dt)
            rest = (1.0 - r) * rho_a + r * rho_r
    return _out(xi_a * rho_m + (1.0 - xi_a) * rest)


def resistance_ohm(
    xi: float | np.ndarray,
    temp_c: float | np.ndarray,
    strain: float | np.ndarray,
    wire: Wire,
    model: ResistivityModel,
    rphase: float | np.ndarray | None = None,
) -> float | np.ndarray:
    """Wire resistance, Ω: ``ρ(ξ, T, r)·L0·(1 + ε)²/A0`` (volume conserved).

    ``xi``: martensite fraction (0 … 1); ``temp_c``: wire temperature, °C; ``strain``: total
    strain against the free length ``wire.length_m`` (> -1; ≈ 0 … 0.06 in use); ``rphase``: R-phase
    fraction of the non-martensite part (``rphase_fraction``), None = 0. All broadcast; scalars in,
    float out.
    """
    eps = np.asarray(strain, dtype=float)
    if np.any(eps <= -1.0):
        raise ValueError("strain must be above -1")
    rho = np.asarray(resistivity_ohm_m(xi, temp_c, model, rphase))
    return _out(rho * wire.length_m * (1.0 + eps) ** 2 / wire.area_m2)


@dataclass(frozen=True)
class MeasurementChain:
    """The wire-voltage channel, every figure referred to the wire (the Kelvin leads).

    Attributes:
        lsb_v: quantization step at the wire, V (ADC LSB / the gain from wire to ADC).
        noise_rms_v: input-referred Gaussian noise per reading, V.
        offset_v: offset added to the wire voltage, V (0 after ``smabench calibrate wire``).
        gain_error: relative gain error (0.001 = reads 0.1 % high).
        full_scale_v: the reading clips at ± this, V (codes -32768 … 32767 × LSB).
        min_current_a: |current| below this gives NaN resistance, A.
    """

    lsb_v: float
    noise_rms_v: float
    offset_v: float = 0.0
    gain_error: float = 0.0
    full_scale_v: float = math.inf
    min_current_a: float = 0.005

    def __post_init__(self) -> None:
        if not self.lsb_v > 0 or self.noise_rms_v < 0 or self.min_current_a < 0:
            raise ValueError("lsb_v must be > 0, noise_rms_v and min_current_a ≥ 0")


def measured_resistance_ohm(
    current_a: float | np.ndarray,
    voltage_true_v: float | np.ndarray,
    chain: MeasurementChain,
    rng: np.random.Generator | None = None,
) -> tuple[float | np.ndarray, float | np.ndarray]:
    """(voltage_measured_v, resistance_ohm) of one reading per sample.

    ``V = clip(round((V_true·(1 + gain_error) + offset + n)/LSB)·LSB)`` with n ~ N(0, noise_rms_v)
    drawn from ``rng`` (None: no noise); ``R = V/I`` (Ω), NaN where |I| < ``chain.min_current_a``.
    The current (A) is taken as exact. Broadcasts; scalars in, floats out.
    """
    cur, v_true = np.broadcast_arrays(
        np.asarray(current_a, dtype=float), np.asarray(voltage_true_v, dtype=float)
    )
    v = v_true * (1.0 + chain.gain_error) + chain.offset_v
    if rng is not None and chain.noise_rms_v > 0:
        v = v + rng.normal(0.0, chain.noise_rms_v, size=v.shape)
    codes = np.round(v / chain.lsb_v)
    if math.isfinite(chain.full_scale_v):
        top = math.floor(chain.full_scale_v / chain.lsb_v)
        codes = np.clip(codes, -top, top - 1)
    v_meas = codes * chain.lsb_v
    ok = np.abs(cur) >= chain.min_current_a
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(ok, v_meas / np.where(ok, cur, 1.0), np.nan)
    return _out(v_meas), _out(r)


# --- presets -------------------------------------------------------------------------------

FLEXINOL_RESISTIVITY = ResistivityModel(
    # Dynalloy, "Technical Characteristics of Flexinol Actuator Wires", F1140 Rev I.2: 0.015"
    # (0.38 mm) wire 8.3 Ω/m; × π·(0.19 mm)² = 94.1e-8 Ω·m, taken as the as-supplied (stress-free,
    # martensitic at room temperature) 70 °C-grade wire. The same sheet's generic "approx."
    # resistivities (martensite 80, austenite 100 µΩ·cm, also in wire.py) would give 7.05 Ω/m,
    # 15 % below its own table; the Nitinol handbook pair 76 / 82 µΩ·cm (Johnson Matthey,
    # "Nitinol technical properties"; Wikipedia "Nickel titanium") gives 6.70 Ω/m.
    rho_martensite_ohm_m=94e-8,
    # Assumption, calibrated: ρ_A(90 °C)/ρ_M(20 °C) = 95·1.035/94 = 1.046 makes a loaded wire's
    # full stroke (ξ 1 → 0, ε 4 % → 0, 20 → 90 °C) change R by -3.3 %, the ≈ -3 % quoted for
    # loaded wires by the hobby community (figure taken from the task brief: no primary source
    # was found). Its sign, R falling as the loaded wire contracts, is the basis of resistance
    # self-sensing (Ikuta, Tsukamoto & Hirose, IEEE ICRA 1988, pp. 427-430; Ma, Song & Lee,
    # Smart Mater. Struct. 13 (2004) 777-783). The stress-free handbook ratios above (100/80 and
    # 82/76) would give +16 % and -0.2 % over the same stroke.
    rho_austenite_ohm_m=95e-8,
    # Assumption: 5e-4 /K for both phases, inside the 1e-4 … 1e-3 /K usually quoted for NiTi; no
    # Flexinol figure found. Over a 70 K stroke it moves R by 3.5 %, as much as the phase and
    # geometry signal: calibrate on the bench wire before trusting R as a position.
    tcr_martensite_per_k=5e-4,
    tcr_austenite_per_k=5e-4,
    ref_c=20.0,
)
"""Flexinol 0.38 mm, 70 °C grade, without R-phase: 8.29 Ω/m cold and free; sources above."""

FLEXINOL_WITH_RPHASE = replace(
    FLEXINOL_RESISTIVITY,
    # Assumption: ρ_R 15 % above ρ_A. The B2 → R transformation raises the resistivity on cooling
    # (the classic resistance peak; Otsuka & Ren, "Physical metallurgy of Ti-Ni-based shape memory
    # alloys", Prog. Mater. Sci. 50 (2005) 511-678); the height depends on composition and heat
    # treatment, and no Flexinol measurement was found.
    rho_rphase_ohm_m=109e-8,
    # Assumption: Rs 62 °C, Rf 56 °C, between Ms 52 °C and As 68 °C of FLEXINOL_038_70C. The
    # 20 … 40 °C often quoted for the R-phase of binary NiTi (e.g. Ni-rich 50.8 at.% aged) lies
    # below this wire's Ms and cannot apply; stress-free values, not shifted with the load.
    rs_c=62.0,
    rf_c=56.0,
)
"""Flexinol 0.38 mm, 70 °C grade, with an R-phase bump of ≈ +15 % on cooling (assumed)."""

RESISTIVITY_PRESETS: dict[str, ResistivityModel] = {
    "flexinol": FLEXINOL_RESISTIVITY,
    "flexinol-rphase": FLEXINOL_WITH_RPHASE,
}
"""The presets by the names command lines use (``smabench mock --resistivity NAME``)."""

ADS1115_KELVIN_CHAIN = MeasurementChain(
    # firmware/hardware/electrical.toml [precise_adc]: AIN0-AIN1 at ±2.048 V (wire_fsr_v, PGA 2,
    # LSB 2.048 V/2^15 = 62.5 µV, TI SBAS444E Table 7-1) behind wire_gain = 0.5 (INA132 gain 1,
    # then a 1:2 divider): 125 µV per LSB at the wire, ±4.096 V range.
    lsb_v=125e-6,
    # TI ADS1115 datasheet SBAS444E (2024), Table 6-1: 62.5 µV RMS (118.63 µV pp) at 860 SPS and
    # ±2.048 V, inputs shorted; ÷ 0.5 → 125 µV RMS at the wire. The RMS entry equals one LSB
    # (effective resolution 16 bits, Table 6-2), so it is an upper bound (Fig. 5-15 plots the
    # 860 SPS noise below one LSB). One conversion: the firmware's 4-reading mean
    # (firmware/PROTOCOL.md) is not modelled; Kelvin leads: no lead resistance in the reading.
    noise_rms_v=125e-6,
    # offset and gain error: 0, i.e. after `smabench calibrate wire`. Uncalibrated, the ADS1115
    # alone has ±1 LSB (max ±3) offset and 0.01 % (max 0.15 %) gain error (SBAS444E §5.5,
    # differential, ±2.048 V); firmware/PROTOCOL.md cites ±2-3 mV amplifier offset on the mock.
    offset_v=0.0,
    gain_error=0.0,
    full_scale_v=4.096,
    min_current_a=0.005,
)
"""The bench's Kelvin wire-voltage channel (ADS1115 at 860 SPS, ±2.048 V, gain 0.5 to the ADC)."""
