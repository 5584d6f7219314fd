"""The board's netlist (firmware/hardware/bench.cir) simulated in ngspice against electrical.toml.

electrical.toml repeats some part values of the netlist and derives the figures the firmware, the
emulator harness and the mock use (current per PWM count, filter poles, trips). These tests fail
when a copy differs from the netlist, or when the simulated circuit does not do what the toml's
figures say: the DC transfer at six points on two USB rails, the setpoint step, the sink loop's
phase margin, and the hardware cut opening on a shorted MOSFET, a wire shorted to ground, a hung
MCU (watchdog pin stuck high or low) and the e-stop.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from smabench.hardware import ELECTRICAL
from smabench.hardware.spice import (
    NETLIST_PATH,
    Deck,
    component_values,
    ngspice_available,
    pwm_pwl,
    run,
    spice_number,
)

needs_ngspice = pytest.mark.skipif(not ngspice_available(), reason="ngspice not installed "
                                   "(Debian package `ngspice`, in the Makefile's APT_PACKAGES)")

SUPPLY_V = float(ELECTRICAL["supply"]["wire_supply_v"])
PWM_PERIOD_S = 1.0 / ELECTRICAL["setpoint"]["pwm_frequency_hz"]
CLEAR_AT_S, ENABLE_AT_S = 3e-3, 4e-3  # the MCU clears the power-on trip, then enables
OFF_A = 0.02  # "current off": below 20 mA (the session's threshold)


def startup_pins(vusb: float, pwm: str) -> dict[str, str]:
    """The MCU's pins: watchdog toggled every 1 ms tick, trip cleared, enable low, the PWM."""
    return {
        "d7_wdi": f"PULSE(0 {vusb} 0 1u 1u 1m 2m)",
        "d4_clr_n": f"PWL(0 {vusb} {CLEAR_AT_S} {vusb} {CLEAR_AT_S + 1e-6} 0 "
                    f"{CLEAR_AT_S + 50e-6} 0 {CLEAR_AT_S + 51e-6} {vusb})",
        "d8_en_n": f"PWL(0 {vusb} {ENABLE_AT_S} {vusb} {ENABLE_AT_S + 1e-6} 0)",
        "d9_pwm": pwm,
    }


def sink_current(r: dict[str, np.ndarray]) -> np.ndarray:
    return (r["v(r1a)"] - r["v(r1b)"]) / ELECTRICAL.shunt_ohm


def parallel(jobs: list[Callable[[], dict[str, np.ndarray]]]) -> list[dict[str, np.ndarray]]:
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(lambda job: job(), jobs))


# ------------------------------------------------------------------ the netlist itself
def test_toml_copies_equal_the_netlist():
    values = component_values()
    for dotted, ref in ELECTRICAL["netlist"].items():
        section, key = dotted.split(".")
        assert ref in values, f"{ref} (for {dotted}) not in {NETLIST_PATH.name}"
        assert ELECTRICAL[section][key] == pytest.approx(values[ref], rel=1e-9), (
            f"electrical.toml {dotted} = {ELECTRICAL[section][key]} but {ref} = {values[ref]}")
    assert ELECTRICAL.shunt_ohm == pytest.approx(values["R1"])


def test_a_divider_without_its_series_resistors_is_caught(tmp_path):
    """The old mistake: a copy that leaves out a resistor of the netlist differs from it."""
    bad = tmp_path / "bench.cir"
    bad.write_text(NETLIST_PATH.read_text().replace("R20     sw_o sp1 15k", "R20     sw_o sp1 12k"))
    assert component_values(bad)["R20"] != ELECTRICAL["setpoint"]["divider_top_ohm"]


def _elements() -> list[list[str]]:
    rows, depth = [], 0
    for raw in NETLIST_PATH.read_text().splitlines():
        line = raw.split(";", 1)[0].strip().lower()
        if line.startswith(".subckt"):
            depth += 1
        elif line.startswith(".ends"):
            depth -= 1
        elif depth == 0 and line and line[0].isalpha():
            rows.append(line.split())
    return rows


def test_every_ic_on_the_logic_rail_has_its_decoupling_capacitor():
    rows = _elements()
    ics = {re.sub(r"[a-d]$", "", r[0]) for r in rows if r[0].startswith("xu") and "v5" in r[1:]}
    decoupling = [r for r in rows if r[0].startswith("c") and {r[1], r[2]} == {"v5", "0"}
                  and spice_number(r[3]) <= 10e-6]
    assert len(ics) >= 9
    assert len(decoupling) >= len(ics) + 1  # one per IC and the bulk capacitor


def test_kelvin_sense_is_not_ground():
    """SENSE− reaches the star only through the shunt's own sense pin; the setpoint divider, its
    filter and the fast amplifier return to SENSE−, so the force current's ground drop stays out."""
    rows = _elements()
    for r in rows:
        assert {r[1], r[2]} != {"sensem", "0"}, f"{r[0]} ties SENSE− to ground"
    on_sensem = {r[0] for r in rows if "sensem" in r[1:4]}
    assert {"r21", "c2", "c3", "r24", "r1s2"} <= on_sensem


# ------------------------------------------------------------------ DC transfer and step
@needs_ngspice
@pytest.mark.slow
def test_dc_transfer_and_step_match_electrical_toml():
    """Six PWM duties on two USB rails: the sink current within 1 % of electrical.toml's
    figure (and so of the firmware, the harness and the mock), independent of the rail; the
    fast path, the ADS1115 shunt channel and the wire-voltage amplifier read it within 1 %.
    The steps between segments rise and settle as documented (README, "Figures")."""
    seg_s, first_s = 15e-3, 5e-3
    plans = {4.65: (0.5, 0.1, 0.3), 5.0: (0.7, 0.85, 0.92)}
    rwire = 0.44
    vectors = ["v(r1a)", "v(r1b)", "v(a0_ifast)", "v(ain0)", "v(ain1)", "v(ain2)", "v(ain3)"]

    def job(vusb: float, duties: tuple[float, ...]) -> Callable[[], dict[str, np.ndarray]]:
        end = first_s + seg_s * len(duties)
        steps = [(0.0, 0.0)] + [(first_s + k * seg_s, d) for k, d in enumerate(duties)]
        pwm = pwm_pwl(steps, PWM_PERIOD_S, vusb, end)
        deck = Deck(params={"vpsu": SUPPLY_V, "vusb": vusb, "rwire": rwire},
                    pins=startup_pins(vusb, pwm), analysis=[f"tran 5u {end} uic"],
                    vectors=vectors)  # fmt: skip
        return lambda: run(deck)

    results = parallel([job(v, d) for v, d in plans.items()])
    top = ELECTRICAL["setpoint"]["pwm_top"]
    gain = ELECTRICAL.current_amplifier_gain
    for (vusb, duties), r in zip(plans.items(), results, strict=True):
        t, i = r["scale"], sink_current(r)
        for k, duty in enumerate(duties):
            window = (t > first_s + (k + 1) * seg_s - 2e-3) & (t < first_s + (k + 1) * seg_s)
            expected_a = duty * top * ELECTRICAL.setpoint_a_per_count
            got_a = float(np.mean(i[window]))
            assert got_a == pytest.approx(expected_a, rel=0.01), f"duty {duty} on {vusb} V USB"
            fast_a = float(np.mean(r["v(a0_ifast)"][window])) / (gain * ELECTRICAL.shunt_ohm)
            assert fast_a == pytest.approx(got_a, rel=0.01)
            ads_a = float(np.mean((r["v(ain2)"] - r["v(ain3)"])[window])) / ELECTRICAL.shunt_ohm
            assert ads_a == pytest.approx(got_a, rel=0.01)
            wire_v = float(np.mean((r["v(ain0)"] - r["v(ain1)"])[window]))
            assert wire_v / ELECTRICAL["precise_adc"]["wire_gain"] == pytest.approx(
                got_a * rwire, rel=0.01)  # fmt: skip
        # the step duties[1] → duties[2] (both on): 10–90 % rise and 0.1 % settling as documented
        t_step = first_s + 2 * seg_s
        start = float(np.mean(i[(t > t_step - 2e-3) & (t < t_step)]))
        final = float(np.mean(i[(t > t_step + seg_s - 2e-3) & (t < t_step + seg_s)]))
        seg = (t >= t_step) & (t < t_step + seg_s)
        ts, frac = t[seg] - t_step, (i[seg] - start) / (final - start)
        rise_s = ts[np.argmax(frac >= 0.9)] - ts[np.argmax(frac >= 0.1)]
        settle_s = ts[np.nonzero(np.abs(frac - 1.0) > 1e-3)[0][-1] + 1]
        print(f"step {duties[1]} → {duties[2]}: rise {rise_s * 1e3:.2f} ms, "
              f"settled to 0.1 % in {settle_s * 1e3:.2f} ms")
        assert rise_s == pytest.approx(ELECTRICAL.setpoint_rise_s, rel=0.05)
        assert settle_s == pytest.approx(ELECTRICAL.setpoint_settle_s, rel=0.05)
        # the step from 0 (the MOSFET off): the loop first charges the gate to its threshold, so
        # the current starts late and catches up; it settles no later than a linear step
        final0 = float(np.mean(i[(t > first_s + seg_s - 2e-3) & (t < first_s + seg_s)]))
        seg0 = (t >= first_s) & (t < first_s + seg_s)
        ts0, frac0 = t[seg0] - first_s, i[seg0] / final0
        t90_0 = ts0[np.argmax(frac0 >= 0.9)]
        settle0_s = ts0[np.nonzero(np.abs(frac0 - 1.0) > 1e-3)[0][-1] + 1]
        print(f"step 0 → {duties[0]}: 90 % at {t90_0 * 1e3:.2f} ms, "
              f"settled to 0.1 % in {settle0_s * 1e3:.2f} ms")
        assert t90_0 <= ELECTRICAL.setpoint_step_time_s(0.9) * 1.05
        assert settle0_s <= ELECTRICAL.setpoint_settle_s * 1.05


# ------------------------------------------------------------------ loop stability
# DC operating points with the cut closed: the latch, the NOR gates and the eFuse's soft start
# form a bistable loop that ngspice's DC solver does not settle; their outputs are held (through
# the gates' own 50 Ω) as D7's toggling and a cleared latch hold them. The cut's own behaviour is
# simulated in transient below.
CUT_CLOSED = ["V_wdfix wdt_h 0 DC 3.6", "V_enfix en 0 DC 4.8", "V_clfix clamp 0 DC 0"]


def op_fixture_ohm(current_a: float) -> float:
    """A resistor across R21 that sets the DC setpoint to ``current_a`` with D9 held high (the
    setpoint filter is outside the sink's loop, so the loop gain is the real one)."""
    sp = ELECTRICAL["setpoint"]
    top = sp["divider_top_ohm"] + sp["switch_ron_ohm"]
    v = current_a * ELECTRICAL.shunt_ohm
    r_eff = v * top / (sp["pwm_high_v"] - v)
    return 1.0 / (1.0 / r_eff - 1.0 / sp["divider_bottom_ohm"])


@needs_ngspice
@pytest.mark.parametrize(("current_a", "rwire"), [(0.1, 0.3), (1.0, 0.44), (2.5, 1.0)])
def test_sink_loop_phase_margin_is_45_degrees_or_more(current_a, rwire):
    """Loop gain by voltage injection at VLOOP (SENSE+ to R7): T = −V(SENSE+) / V(R7 side)."""
    vusb = 4.8
    deck = Deck(
        params={"vpsu": SUPPLY_V, "vusb": vusb, "rwire": rwire},
        pins={"d7_wdi": "DC 0", "d4_clr_n": "DC 0", "d8_en_n": "DC 0", "d9_pwm": f"DC {vusb}"},
        fixtures=[f"R_opfix sp1 sensem {op_fixture_ohm(current_a):.6g}", *CUT_CLOSED],
        analysis=["op"],
        vectors=["v(r1a)", "v(r1b)"],
    )
    op = run(deck)
    i_dc = float(op["v(r1a)"][0] - op["v(r1b)"][0]) / ELECTRICAL.shunt_ohm
    assert i_dc == pytest.approx(current_a, rel=0.02)  # the operating point the fixture sets
    deck.analysis = ["alter @vloop[acmag] = 1", "ac dec 40 10 20meg"]
    deck.vectors = ["v(sfb)", "v(sensep)"]
    r = run(deck)
    f = r["scale"]
    loop = -r["v(sensep)"] / r["v(sfb)"]
    mag = np.abs(loop)
    assert mag[0] > 100.0  # high loop gain at low frequency
    k = int(np.argmax(mag < 1.0))
    assert k > 0
    phase_deg = np.degrees(np.unwrap(np.angle(loop)))
    margin_deg = 180.0 + phase_deg[k]
    print(f"{current_a} A on {rwire} Ω: phase margin {margin_deg:.0f}° at {f[k]:.3g} Hz")
    assert margin_deg >= 45.0, f"{margin_deg:.0f}° at {f[k]:.3g} Hz"
    assert 1e3 < f[k] < 1e6  # crossover well above the setpoint filter, below the op-amp's GBW


# ------------------------------------------------------------------ wire voltage after calibration
WIRE_CORNER = {  # INA132 at its offset limit with a 0.1 % network mismatch; the 1:2 mismatched
    "XU4     wm_s wp_s ref125 ina_o v5 0 INA132":
        "XU4     wm_s wp_s ref125 ina_o v5 0 INA132 params: vos=250u mism=1m",
    "R66     ain0 0 10k": "R66     ain0 0 10.01k",
}


def wire_reading(current_a: float, rwire: float) -> tuple[float, float]:
    """(ADS1115 AIN0−AIN1 in V, true voltage between the sense clamps in V) at ``current_a``."""
    vusb = 4.8
    on = current_a > 0.0
    deck = Deck(params={"vpsu": SUPPLY_V, "vusb": vusb, "rwire": rwire},
                pins={"d7_wdi": "DC 0", "d4_clr_n": "DC 0", "d8_en_n": "DC 0",
                      "d9_pwm": f"DC {vusb if on else 0.0}"},
                fixtures=CUT_CLOSED
                + ([f"R_opfix sp1 sensem {op_fixture_ohm(current_a):.6g}"] if on else []),
                substitutions=WIRE_CORNER, analysis=["op"],
                vectors=["v(ain0)", "v(ain1)", "v(wp_s)", "v(wm_s)"])  # fmt: skip
    r = run(deck)
    return float(r["v(ain0)"][0] - r["v(ain1)"][0]), float(r["v(wp_s)"][0] - r["v(wm_s)"][0])


@needs_ngspice
def test_wire_resistance_within_0_1_percent_after_offset_and_gain_calibration():
    """Issue 25: ≤ 0.1 % of R after calibration at 0.2 A, on the shortest wire (the smallest
    voltage), with the difference amplifier at its offset limit and its network and the 1:2
    dividers mismatched. Offset at zero current (output enabled, setpoint 0: the common mode of
    operation), gain against a meter across the sense clamps at 1 A."""
    rwire = 0.3
    off_v, _ = wire_reading(0.0, rwire)
    assert abs(off_v) > 50e-6  # the corner does put an offset in (else this test proves nothing)
    ads_v, true_v = wire_reading(1.0, rwire)
    gain = true_v / (ads_v - off_v)
    assert abs(gain - 1.0 / ELECTRICAL["precise_adc"]["wire_gain"]) > 1e-4  # and a gain error
    for current_a in (0.2, 0.5, 2.0):
        ads_v, true_v = wire_reading(current_a, rwire)
        measured_v = (ads_v - off_v) * gain
        assert measured_v == pytest.approx(true_v, rel=1e-3), f"{current_a} A"
        # without calibration the same reading is several times further off at 0.2 A
        if current_a == 0.2:
            raw_v = ads_v / ELECTRICAL["precise_adc"]["wire_gain"]
            assert abs(raw_v / true_v - 1.0) > 2e-3


# ------------------------------------------------------------------ the cut
FAULT_AT_S = 20e-3


WATCHDOG_SLOW_CORNER = {  # the slowest decay: CW2 +10 %, RW1/RW2 +1 %, pumped from a 5.0 V pin
    "CW2     wdt_h 0 220n": "CW2     wdt_h 0 242n",
    "RW1     wdt_h wdt_div 49.9k": "RW1     wdt_h wdt_div 50.4k",
    "RW2     wdt_div 0 49.9k": "RW2     wdt_div 0 50.4k",
}


def fault_deck(kind: str, vusb: float = 4.8) -> Deck:
    """Full-scale PWM (2.73 A: the highest the MCU can ask, below the 2.99 A trip), a fault at
    20 ms; for the watchdog cases the D7 toggling stops there."""
    substitutions: dict[str, str] = {}
    if kind == "mcu-hang-high-slow-corner":
        substitutions, vusb, kind = WATCHDOG_SLOW_CORNER, 5.0, "mcu-hang-high"
    pins = startup_pins(vusb, f"DC {vusb}")
    fixtures: list[str] = [".model SW_FAULT SW(Vt=2.5 Vh=0.1 Ron=5m Roff=1e9)",
                           f"V_fault fault 0 PWL(0 0 {FAULT_AT_S} 0 {FAULT_AT_S + 1e-6} 5)"]
    estop = "DC 0"
    end = FAULT_AT_S + 12e-3
    if kind == "mosfet-short":
        fixtures.append("S_fault drain src fault 0 SW_FAULT")
    elif kind == "wire-to-ground":
        fixtures.append("S_fault wm_f 0 fault 0 SW_FAULT")
    elif kind in ("mcu-hang-high", "mcu-hang-low"):
        level = vusb if kind.endswith("high") else 0.0
        n = int(FAULT_AT_S / 1e-3)
        pts = [(0.0, 0.0)]
        for k in range(n):  # toggles every 1 ms until the fault, then stuck
            v = vusb if k % 2 == 0 else 0.0
            pts += [(k * 1e-3 + 1e-6, v), ((k + 1) * 1e-3, v)]
        pts.append((FAULT_AT_S + 1e-6, level))
        pins["d7_wdi"] = "PWL(" + " ".join(f"{t:.9g} {v:.4g}" for t, v in pts) + ")"
        end = FAULT_AT_S + 60e-3
    elif kind == "estop":
        estop = f"PWL(0 0 {FAULT_AT_S} 0 {FAULT_AT_S + 1e-6} 5)"
    else:
        raise ValueError(kind)
    if kind != "mosfet-short" and kind != "wire-to-ground":
        # the MCU tries to clear the latch while the cause is still there: it must stay tripped
        t_c = FAULT_AT_S + 40e-3 if kind.startswith("mcu") else FAULT_AT_S + 5e-3
        pins["d4_clr_n"] = (f"PWL(0 {vusb} {CLEAR_AT_S} {vusb} {CLEAR_AT_S + 1e-6} 0 "
                            f"{CLEAR_AT_S + 50e-6} 0 {CLEAR_AT_S + 51e-6} {vusb} "
                            f"{t_c} {vusb} {t_c + 1e-6} 0 {t_c + 50e-6} 0 {t_c + 51e-6} {vusb})")
    return Deck(params={"vpsu": SUPPLY_V, "vusb": vusb, "rwire": 0.44}, pins=pins,
                fixtures=fixtures, estop=estop, analysis=[f"tran 2u {end} uic"],
                substitutions=substitutions,
                vectors=["v(wp_s)", "v(wm_s)", "v(d6_trip)", "v(en)", "v(a1_vmon)"])  # fmt: skip


FAULT_LIMITS_S = {
    "mosfet-short": ELECTRICAL["cut"]["comparator_off_max_s"],
    "wire-to-ground": ELECTRICAL["cut"]["comparator_off_max_s"],
    "estop": ELECTRICAL["cut"]["comparator_off_max_s"],
    "mcu-hang-high": ELECTRICAL["cut"]["watchdog_off_max_s"],
    "mcu-hang-low": ELECTRICAL["cut"]["watchdog_off_max_s"],
    "mcu-hang-high-slow-corner": ELECTRICAL["cut"]["watchdog_off_max_s"],
}


@needs_ngspice
@pytest.mark.slow
def test_the_hardware_cut_ends_every_fault_in_time():
    kinds = list(FAULT_LIMITS_S)
    results = parallel([(lambda k=k: run(fault_deck(k))) for k in kinds])
    for kind, r in zip(kinds, results, strict=True):
        t = r["scale"]
        wire_a = (r["v(wp_s)"] - r["v(wm_s)"]) / 0.44
        before = (t > FAULT_AT_S - 1e-3) & (t < FAULT_AT_S)
        # before the fault: full scale flows and nothing has tripped (no false trip)
        assert np.mean(wire_a[before]) == pytest.approx(ELECTRICAL.setpoint_full_scale_a, rel=0.01)
        assert np.max(r["v(d6_trip)"][before]) < 0.5
        after = t > FAULT_AT_S
        on = np.nonzero(after & (np.abs(wire_a) >= OFF_A))[0]
        t_off = (t[on[-1]] if on.size else FAULT_AT_S) - FAULT_AT_S
        assert t_off <= FAULT_LIMITS_S[kind], f"{kind}: current off after {t_off * 1e3:.2f} ms"
        # and the cut is what did it: latched, EN low, the switched supply gone
        assert r["v(d6_trip)"][-1] > 4.0, kind
        assert r["v(en)"][-1] < 0.5, kind
        assert r["v(a1_vmon)"][-1] < 0.05, kind
        print(f"{kind}: current below {OFF_A * 1e3:.0f} mA {t_off * 1e3:.3f} ms after the fault")


@needs_ngspice
@pytest.mark.slow
def test_the_trip_is_cleared_only_by_the_mcu_once_the_cause_is_gone():
    """E-stop pressed at 20 ms, released at 26 ms: the current stays off (releasing restores
    nothing); a clear pulse while pressed (23 ms) does nothing; the clear at 30 ms, cause gone,
    brings the current back."""
    vusb = 4.8
    pins = startup_pins(vusb, f"DC {vusb}")
    pulses = " ".join(f"{t} {vusb} {t + 1e-6} 0 {t + 50e-6} 0 {t + 51e-6} {vusb}"
                      for t in (CLEAR_AT_S, 23e-3, 30e-3))
    pins["d4_clr_n"] = f"PWL(0 {vusb} {pulses})"
    deck = Deck(params={"vpsu": SUPPLY_V, "vusb": vusb, "rwire": 0.44}, pins=pins,
                estop="PWL(0 0 20m 0 20.001m 5 26m 5 26.001m 0)",
                analysis=["tran 2u 48m uic"], vectors=["v(wp_s)", "v(wm_s)", "v(d6_trip)"])
    r = run(deck)
    t, wire_a = r["scale"], (r["v(wp_s)"] - r["v(wm_s)"]) / 0.44
    assert np.max(np.abs(wire_a[(t > 20.5e-3) & (t < 30e-3)])) < OFF_A  # C12 drains ~0.2 ms
    assert np.all(r["v(d6_trip)"][(t > 20.1e-3) & (t < 30e-3)] > 4.0)
    assert np.all(r["v(d6_trip)"][t > 30.1e-3] < 0.5)
    assert np.mean(wire_a[t > 46e-3]) == pytest.approx(ELECTRICAL.setpoint_full_scale_a, rel=0.01)
