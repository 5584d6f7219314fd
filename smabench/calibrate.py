"""Calibration from the app: ``smabench calibrate current|wire|show`` and ``smabench sensor
tare|read`` (the ``calibration`` block of every session's ``session.json``:
:mod:`smabench.calibration_store`).

- **current**: the driver steps through a few currents (0.2, 1.0, 2.0 A by default), each held
  while the operator reads a multimeter in series with the wire (or given up front with
  ``--readings``); offset and gain are fitted by least squares against what the device measured,
  shown with their residuals, written to the device's EEPROM (SET_CALIBRATION, output off) and
  read back. The firmware computes ``I = (I_raw − offset)·gain`` and regulates that
  (``firmware/PROTOCOL.md``, "Calibration"), so after the write the setpoint is what the meter
  reads.
- **wire**: the cold resistance at a low current (0.2 A: the heating it causes is computed by the
  heat balance of :mod:`smabench.physics.thermal` and printed), from the Kelvin-sensed wire
  voltage and the shunt current, checked against length × martensite resistivity
  (:mod:`smabench.physics.wire`); an open circuit, shorted sense leads or a resistance off by
  more than the tolerance (30 %) end with a clear line and exit 2.
- **sensor tare**: the displacement sensor read for a second; the mean is the zero that
  positions are reported against (``smabench sensor read``) and that sessions record.

Results live in a small JSON file (:mod:`smabench.calibration_store`, :func:`store_path`:
``--calibration FILE``, else ``$SMABENCH_CALIBRATION``, else
``$XDG_CONFIG_HOME/smabench/calibration.json``, else ``~/.config/smabench/calibration.json``).
Units: A, V, Ω, mm, s, °C.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from smabench.argtypes import positive, sensor_map, sensor_spec, serial_port
from smabench.calibration_store import (  # the store and the session's block: a lower floor
    ENV_STORE,
    CalibrationError,
    _same_calibration,
    load_store,
    save_record,
    store_path,
)
from smabench.drivers import protocol as p

log = logging.getLogger(__name__)

EXIT_REFUSED = 2

DEFAULT_CURRENTS_A = (0.2, 1.0, 2.0)
READING_TOLERANCE = 0.20  # a meter reading more than 20 % off the set current is refused
WIRE_CURRENT_A = 0.2
WIRE_TOLERANCE = 0.30  # cold R more than 30 % off length × martensite resistivity: refused
SHORTED_SENSE_FRACTION = 0.1  # R below 10 % of the expected: the sense leads see no wire
OPEN_FRACTION = 0.5  # less than half the set current flows: open circuit
COMPLIANCE_FRACTION = 0.9  # less than 90 % flows: the driver runs out of voltage
LEASE_S = 0.5  # setpoint lease while holding a current (renewed every RENEW_S)
RENEW_S = 0.05
HEAT_BUDGET_MARGIN = 0.7  # hold at most 70 % of the time the device's energy budget allows
AMBIENT_FALLBACK_C = 40.0  # the firmware's ambient for its heat model when the NTC is faulty
GAIN_RANGE = p.CAL_GAIN_RANGE
OFFSET_MAX_A = 0.032767
VOLTAGE_OFFSET_MAX_V = 0.032767  # the wire-voltage offset the device stores (±32767 µV)
WIRE_FIT_FRACTION = 0.5  # the wire's offset fit: a hold at this fraction of the current, then at it
TARE_DURATION_S = 1.0
TARE_RATE_HZ = 100.0
TARE_MIN_SAMPLES = 5
TARE_MAX_STD_MM = 0.02  # a tare over a moving position is refused


def _now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


# ---------------------------------------------------------------------------- holding a current
@dataclass(frozen=True)
class Measurement:
    """What the device measured while a current was held (means over the settled frames)."""

    set_a: float
    current_a: float  # fast path, calibrated (what the firmware regulates)
    precise_current_a: float  # shunt by the external ADC, A (nan: not available)
    voltage_v: float  # Kelvin-sensed wire voltage, V (nan: not available)
    current_std_a: float
    frames: int
    span_s: float  # device time covered by the frames
    on_s: float  # device time from the output on at this setpoint to the last frame
    ambient_c: float
    faults: str  # latched faults/events seen while on ('' when none)
    fault_flags: int  # the same as flags (protocol.Flag)
    timed_out: bool  # the hold ended at its heat-budget limit

    @property
    def shunt_current_a(self) -> float:
        """The best current for a resistance: the precise shunt channel if there is one."""
        return self.precise_current_a if self.precise_current_a > 0 else self.current_a


class HeldCurrent:
    """Hold ``current_a`` on the output: setpoint, ENABLE, the setpoint renewed every
    :data:`RENEW_S` (it is leased), off on :meth:`stop` or after ``max_hold_s``.

    Telemetry frames from ``settle_s`` (device time) after the output came on at this setpoint
    are kept for :meth:`measurement`."""

    def __init__(
        self, cs: Any, current_a: float, *, settle_s: float = 0.3, max_hold_s: float = math.inf
    ) -> None:
        self.cs = cs
        self.current_a = current_a
        self.settle_ms = settle_s * 1e3
        self.max_hold_s = max_hold_s
        self.timed_out = False
        self._frames: list[p.Telemetry] = []
        self._faults = p.Flag(0)
        self._on_ms: float | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._unsubscribe: Callable[[], None] | None = None

    def __enter__(self) -> HeldCurrent:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        self._unsubscribe = self.cs.subscribe(self._on_frame)
        self.cs.set_current(self.current_a, wait=True)
        self.cs.enable(True)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._renew, name="calibrate-hold", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Output off (waits for the ACK; the emergency path if that fails)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        try:
            self.cs.enable(False)
        except Exception as exc:  # the device also turns off at its lease
            log.warning("ENABLE 0 not confirmed (%s): make_safe", exc)
            self.cs.make_safe()
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None

    def _renew(self) -> None:
        from smabench.bench.priority import realtime_loop_thread

        realtime_loop_thread()  # it renews the lease (LEASE_S): not held up by host load
        while not self._stop.wait(RENEW_S):
            if time.monotonic() - self._t0 >= self.max_hold_s:
                self.timed_out = True
                self.cs.make_safe()
                log.info("%.3f A held %.1f s: output off (heat budget)", self.current_a,
                         self.max_hold_s)  # fmt: skip
                break
            try:
                self.cs.set_current(self.current_a)
            except Exception as exc:  # the lease turns the device off: measurement() says so
                log.warning("setpoint renewal failed: %s", exc)

    def _on_frame(self, t: p.Telemetry) -> None:
        with self._cond:
            if t.enabled and abs(t.setpoint_a - self.current_a) < 0.0015:
                if self._on_ms is None:
                    self._on_ms = t.t_ms
                if t.t_ms - self._on_ms >= self.settle_ms:
                    self._frames.append(t)
            elif self._on_ms is not None and not self._stop.is_set():
                self._faults |= t.latched_faults | (t.flags & p.EVENTS)
            self._cond.notify_all()

    def remaining_s(self) -> float:
        """How long the current stays on at most from now, s (inf: until :meth:`stop`)."""
        return max(0.0, self.max_hold_s - (time.monotonic() - self._t0))

    def _span_ms(self) -> float:
        return self._frames[-1].t_ms - self._frames[0].t_ms if self._frames else -1.0

    def wait_span(self, span_s: float, timeout_s: float = 10.0) -> bool:
        """Wait until the kept frames cover ``span_s`` of device time; False when the output
        went off before (a fault, the heat budget) or after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._span_ms() < span_s * 1e3:
                left = deadline - time.monotonic()
                if left <= 0 or self._faults or self.timed_out:
                    return False
                self._cond.wait(min(left, 0.1))
        return True

    def measurement(self) -> Measurement:
        with self._cond:
            frames = list(self._frames)
            faults = self._faults
        nan = float("nan")

        def mean(values: list[float]) -> float:
            arr = np.asarray(values, dtype=float)
            return float(np.mean(arr)) if arr.size and np.all(np.isfinite(arr)) else nan

        currents = [t.current_a for t in frames]
        return Measurement(
            set_a=self.current_a,
            current_a=mean(currents),
            precise_current_a=mean([t.precise_current_a for t in frames]),
            voltage_v=mean([t.voltage_v for t in frames]),
            current_std_a=float(np.std(currents)) if currents else nan,
            frames=len(frames),
            span_s=max(0.0, self._span_ms()) / 1e3 if frames else 0.0,
            on_s=(frames[-1].t_ms - self._on_ms) / 1e3 if frames and self._on_ms else 0.0,
            ambient_c=mean([t.ambient_c for t in frames]),
            faults=p.fault_text(int(faults)) if faults else "",
            fault_flags=int(faults),
            timed_out=self.timed_out,
        )


def time_to_trip_s(
    model: p.HeatModel, current_a: float, start_c: float, ambient_c: float
) -> float:
    """How long the device's energy budget (``C·dT/dt = I²R − G·(T − T_amb)``, PROTOCOL.md)
    lets ``current_a`` flow from ``start_c`` before it trips at T_max, s (inf: never)."""
    if not math.isfinite(ambient_c):
        ambient_c = AMBIENT_FALLBACK_C
    g, c = model.conductance_w_per_k, model.heat_capacity_j_per_k
    t_inf = ambient_c + current_a**2 * model.resistance_ohm / g
    t_max = model.max_temperature_c
    if t_inf <= t_max:
        return math.inf
    if start_c >= t_max:
        return 0.0
    return c / g * math.log((t_inf - start_c) / (t_inf - t_max))


def _hold_limit_s(cs: Any, model: p.HeatModel, current_a: float, cap_s: float) -> float:
    t = cs.latest()
    start = t.wire_model_c if t is not None and math.isfinite(t.wire_model_c) else 22.0
    ambient = t.ambient_c if t is not None else float("nan")
    return min(cap_s, HEAT_BUDGET_MARGIN * time_to_trip_s(model, current_a, start, ambient))


def _wait_for_budget(
    cs: Any, model: p.HeatModel, current_a: float, need_s: float, out: Any
) -> None:
    """Wait (device telemetry) until the energy budget allows ``need_s`` at ``current_a``;
    CalibrationError when it never will (not even from a cold wire)."""
    if _hold_limit_s(cs, model, current_a, math.inf) >= need_s:
        return
    t = cs.latest()
    ambient = t.ambient_c if t is not None else float("nan")
    ambient = ambient if math.isfinite(ambient) else AMBIENT_FALLBACK_C
    cold = HEAT_BUDGET_MARGIN * time_to_trip_s(model, current_a, ambient, ambient)
    if cold < need_s:
        raise CalibrationError(
            f"the device's heat model (T_max {model.max_temperature_c:g} °C) allows only "
            f"{cold:.2f} s at {current_a:g} A, {need_s:.2f} s needed: lower --currents or "
            "--settle-s/--average-s"
        )
    print(f"  waiting for the wire to cool (the device's heat model allows less than "
          f"{need_s:.1f} s at {current_a:.3f} A now)", file=out, flush=True)  # fmt: skip

    def ok(t: p.Telemetry) -> bool:
        return time_to_trip_s(model, current_a, t.wire_model_c, t.ambient_c) * \
            HEAT_BUDGET_MARGIN >= need_s  # fmt: skip

    try:
        cs.wait_telemetry(ok, timeout_s=300.0)
    except p.ProtocolError as exc:  # pragma: no cover - decoding errors are logged by the driver
        raise CalibrationError(str(exc)) from None


# ---------------------------------------------------------------------------- current: the fit
@dataclass(frozen=True)
class CurrentFit:
    """Offset and gain fitted by least squares: after it the device reports what the meter
    read. ``residuals_a``: calibrated device reading − meter, A, per point."""

    offset_a: float
    gain: float
    residuals_a: tuple[float, ...]
    raw_a: tuple[float, ...]  # the device's uncalibrated readings, A

    def reported_a(self, raw_a: float) -> float:
        return (raw_a - self.offset_a) * self.gain


def check_readings(set_a: Sequence[float], meter_a: Sequence[float]) -> None:
    """Refuse readings that cannot be a meter in series with this output: a count that does not
    match, more than :data:`READING_TOLERANCE` off the set current, or not rising with it."""
    if len(meter_a) != len(set_a):
        raise CalibrationError(
            f"{len(meter_a)} meter reading(s) for {len(set_a)} currents "
            f"({', '.join(f'{i:g}' for i in set_a)} A): give one per current"
        )
    for i, m in zip(set_a, meter_a, strict=True):
        if not math.isfinite(m) or abs(m - i) > READING_TOLERANCE * i:
            raise CalibrationError(
                f"meter reading {m:g} A at {i:g} A set is more than "
                f"{READING_TOLERANCE:.0%} off: check the meter's range and that it is in "
                "series with the wire; nothing written"
            )
    for k in range(1, len(meter_a)):
        if not meter_a[k] > meter_a[k - 1]:
            raise CalibrationError(
                f"meter readings not rising with the current ({meter_a[k - 1]:g} A at "
                f"{set_a[k - 1]:g} A, then {meter_a[k]:g} A at {set_a[k]:g} A): nothing written"
            )


def fit_current(
    device_a: Sequence[float], meter_a: Sequence[float], old: p.Calibration
) -> CurrentFit:
    """Least-squares offset and gain: ``meter ≈ (raw − offset)·gain`` with the device's raw
    reading ``raw = device/old_gain + old_offset`` (what the fast path measured before the old
    calibration was applied). CalibrationError when the fit is outside what the device takes."""
    raw = np.asarray(device_a, dtype=float) / old.current_gain + old.current_offset_a
    meter = np.asarray(meter_a, dtype=float)
    if raw.size < 2 or np.ptp(raw) <= 0:
        raise CalibrationError("need at least two different currents to fit offset and gain")
    design = np.column_stack([raw, np.ones_like(raw)])
    (gain, intercept), *_ = np.linalg.lstsq(design, meter, rcond=None)
    gain = float(gain)
    offset = -float(intercept) / gain if gain else math.inf
    lo, hi = GAIN_RANGE
    if not lo <= gain <= hi:
        raise CalibrationError(
            f"the readings need a current gain of {gain:.4f}, outside the device's {lo} … {hi}: "
            "check the meter and the wiring; nothing written"
        )
    if abs(offset) > OFFSET_MAX_A:
        raise CalibrationError(
            f"the readings need a current offset of {offset * 1e3:+.1f} mA, beyond the device's "
            f"±{OFFSET_MAX_A * 1e3:.1f} mA: check the meter and the wiring; nothing written"
        )
    residuals = (raw - offset) * gain - meter
    return CurrentFit(offset, gain, tuple(map(float, residuals)), tuple(map(float, raw)))


MeterFn = Callable[[int, float, HeldCurrent], float]
"""``meter(step, set_a, held)`` → the meter's reading, A, taken while the current is held."""


@dataclass(frozen=True)
class CurrentCalibration:
    """The outcome of :func:`calibrate_current`."""

    before: p.Calibration
    written: p.Calibration
    read_back: p.Calibration
    fit: CurrentFit
    set_a: tuple[float, ...]
    device_a: tuple[float, ...]
    meter_a: tuple[float, ...]


def calibrate_current(
    cs: Any,
    set_a: Sequence[float],
    meter: MeterFn,
    *,
    settle_s: float = 0.3,
    average_s: float = 0.5,
    max_hold_s: float = 20.0,
    out: Any = None,
) -> CurrentCalibration:
    """Step ``cs`` (a connected :class:`~smabench.drivers.current_source.CurrentSource`)
    through ``set_a``, read the meter at each, fit, write (output off) and read back.

    Each reading is checked as it comes (:func:`check_readings`); a refusal turns the output
    off and writes nothing. Each hold lasts at most ``max_hold_s`` and at most 70 % of what the
    device's own energy budget allows at that current (the wire may be in series)."""
    out = out or sys.stdout
    set_a = tuple(float(i) for i in set_a)
    before = cs.get_calibration()
    model = cs.get_heat_model()
    cs.clear_faults()
    device_a: list[float] = []
    meter_a: list[float] = []
    need_s = settle_s + average_s
    for k, current in enumerate(set_a):
        _wait_for_budget(cs, model, current, need_s + 0.5, out)
        hold_s = _hold_limit_s(cs, model, current, max_hold_s)
        with HeldCurrent(cs, current, settle_s=settle_s, max_hold_s=hold_s) as held:
            if not held.wait_span(average_s, timeout_s=need_s + 10.0) and held.measurement().faults:
                raise CalibrationError(
                    f"the output went off at {current:g} A: {held.measurement().faults}"
                )
            if held.timed_out:  # a meter read now reads no current: do not blame the meter
                raise CalibrationError(
                    f"the output went off at its hold limit ({held.max_hold_s:.1f} s at "
                    f"{current:g} A: the device's heat budget or --max-hold-s) before "
                    f"{settle_s:g} s settling and {average_s:g} s of readings were in: shorten "
                    "--settle-s/--average-s or let the wire cool; nothing written"
                )
            reading = float(meter(k, current, held))
            check_readings(set_a[: k + 1], [*meter_a, reading])
        m = held.measurement()
        if m.frames == 0 or not math.isfinite(m.current_a):
            raise CalibrationError(
                f"no telemetry while {current:g} A was on ({m.faults or 'output off'}): "
                "nothing written"
            )
        if m.faults:
            raise CalibrationError(f"fault while {current:g} A was on: {m.faults}; nothing written")
        if m.timed_out:
            print(f"  (the output went off at its hold limit, {held.max_hold_s:.1f} s: "
                  "--max-hold-s or the device's heat budget; the device readings are from "
                  "before)", file=out)  # fmt: skip
        device_a.append(m.current_a)
        meter_a.append(reading)
        print(f"  device {m.current_a:.4f} A (± {m.current_std_a * 1e3:.1f} mA, "
              f"{m.frames} frames over {m.span_s:.2f} s), meter {reading:.4f} A",
              file=out, flush=True)  # fmt: skip
    fit = fit_current(device_a, meter_a, before)
    new = p.Calibration(fit.offset_a, fit.gain, before.voltage_gain, before.voltage_offset_v)
    new.to_data()  # range check before anything is sent
    cs.enable(False)  # the device refuses EEPROM writes while the output is on
    cs.set_calibration(new)
    back = cs.get_calibration()
    if not _same_calibration(back, new):
        raise CalibrationError(
            f"read back {back} after writing {new}: the EEPROM did not take it"
        )
    return CurrentCalibration(
        before, new, back, fit, set_a, tuple(device_a), tuple(meter_a)
    )


# ---------------------------------------------------------------------------- wire
@dataclass(frozen=True)
class WireCheck:
    """Cold resistance of the wire against length × martensite resistivity / area."""

    resistance_ohm: float
    expected_ohm: float
    length_mm: float
    diameter_mm: float
    current_a: float
    voltage_v: float
    heating_k: float  # wire temperature rise by the end of the measurement (heat balance)
    steady_heating_k: float  # rise if the current were held for ever
    ambient_c: float
    as_c: float

    @property
    def ohm_per_m(self) -> float:
        return self.resistance_ohm / (self.length_mm * 1e-3)

    @property
    def deviation(self) -> float:
        """(R − expected) / expected."""
        return self.resistance_ohm / self.expected_ohm - 1.0


def expected_wire(length_mm: float, diameter_mm: float, preset: str):
    """The wire of ``preset`` with this length and diameter (:class:`~smabench.physics.wire.
    Wire`)."""
    from smabench.physics.wire import PRESETS

    if not 1.0 <= length_mm <= 2000.0:
        raise CalibrationError(f"--wire-length-mm must be in 1 … 2000 mm, got {length_mm:g}")
    if not 0.01 <= diameter_mm <= 2.0:
        raise CalibrationError(f"--wire-diameter-mm must be in 0.01 … 2 mm, got {diameter_mm:g}")
    return PRESETS[preset].with_length_mm(length_mm).with_diameter_mm(diameter_mm)


def judge_wire(m: Measurement, wire: Any, tolerance: float = WIRE_TOLERANCE) -> WireCheck:
    """The wire's cold resistance from ``m``; CalibrationError naming what looks wrong: an
    open circuit, no Kelvin voltage, shorted sense leads, a driver out of voltage, or R more
    than ``tolerance`` off ``wire``'s length × martensite resistivity / area."""
    from smabench.physics.thermal import step_exact

    expected = float(wire.resistance_ohm(1.0))
    current = m.shunt_current_a
    if m.fault_flags & p.Flag.OPEN_WIRE or not current >= OPEN_FRACTION * m.set_a:
        shown = f"{current * 1e3:.1f} mA" if math.isfinite(current) else "no current"
        raise CalibrationError(
            f"open circuit: {shown} flows at {m.set_a:g} A set"
            f"{' (' + m.faults + ')' if m.faults else ''}: the wire is broken or a clamp or "
            "lead is off"
        )
    if m.faults:
        raise CalibrationError(f"the output went off during the measurement: {m.faults}")
    if current < COMPLIANCE_FRACTION * m.set_a:
        raise CalibrationError(
            f"only {current:.3f} A flows at {m.set_a:g} A set: the driver is out of voltage "
            "(resistance far too high: a loose clamp, a much longer wire)"
        )
    if not math.isfinite(m.voltage_v):
        raise CalibrationError(
            "no Kelvin wire voltage (the external ADC does not answer, VSENSE_FAULT): check "
            "the ADS1115 and its sense leads"
        )
    r = m.voltage_v / current
    if r < SHORTED_SENSE_FRACTION * expected:
        raise CalibrationError(
            f"the sense leads read {m.voltage_v * 1e3:.2f} mV at {current:.3f} A "
            f"(R {r * 1e3:.1f} mΩ, {expected * 1e3:.0f} mΩ expected): shorted Kelvin sense "
            "leads, or both on the same clamp"
        )
    hold_s = m.on_s  # the settling before the frames heated the wire too
    ambient = m.ambient_c if math.isfinite(m.ambient_c) else 22.0
    t_end = step_exact(ambient, current, hold_s, wire, ambient, resistance_ohm=r)
    t_inf = step_exact(ambient, current, math.inf, wire, ambient, resistance_ohm=r)
    check = WireCheck(
        resistance_ohm=r,
        expected_ohm=expected,
        length_mm=wire.length_mm,
        diameter_mm=wire.diameter_mm,
        current_a=current,
        voltage_v=m.voltage_v,
        heating_k=float(t_end - ambient),
        steady_heating_k=float(t_inf - ambient),
        ambient_c=ambient,
        as_c=wire.as_c,
    )
    if abs(check.deviation) > tolerance:
        hint = (
            "sense leads outside the clamps (the clamps' contact in the measurement), a loose "
            "clamp, or a longer/thinner wire than given"
            if check.deviation > 0
            else "part of the wire shorted (touching metal), sense leads closer than the "
            "clamps, or a shorter/thicker wire than given"
        )
        raise CalibrationError(
            f"R = {r:.4f} Ω is {check.deviation:+.0%} off the {expected:.4f} Ω of "
            f"{wire.length_mm:g} mm × {wire.diameter_mm:g} mm martensite "
            f"(tolerance ±{tolerance:.0%}): {hint}"
        )
    return check


def measure_wire(
    cs: Any, current_a: float = WIRE_CURRENT_A, *, settle_s: float = 0.3, average_s: float = 1.0
) -> Measurement:
    """Hold ``current_a`` and measure (output off afterwards)."""
    cs.clear_faults()
    with HeldCurrent(cs, current_a, settle_s=settle_s) as held:
        held.wait_span(average_s, timeout_s=settle_s + average_s + 10.0)
    return held.measurement()


@dataclass(frozen=True)
class WireOffset:
    """The wire-voltage amplifier's offset, fitted and written to the device's EEPROM.

    The device reads ``V = (raw − offset)·gain``; two holds (``points``: shunt current A, wire
    voltage V as read with the old calibration) give ``V = R·I + intercept``: the intercept is
    what the old offset left, so the new offset is ``old + intercept / gain``."""

    before: p.Calibration
    written: p.Calibration
    read_back: p.Calibration
    points: tuple[tuple[float, float], ...]
    slope_ohm: float
    intercept_v: float


def fit_wire_offset(lo: Measurement, hi: Measurement, before: p.Calibration
                    ) -> tuple[float, float, p.Calibration]:  # fmt: skip
    """``(slope Ω, intercept V, the calibration to write)`` from two holds on the cold wire;
    CalibrationError when the offset is beyond what the device stores."""
    i_lo, i_hi = lo.shunt_current_a, hi.shunt_current_a
    if not i_hi - i_lo > 0.2 * i_hi:
        raise CalibrationError(
            f"the two holds carried {i_lo * 1e3:.1f} and {i_hi * 1e3:.1f} mA: too close to fit "
            "the wire voltage's offset; nothing written"
        )
    slope = (hi.voltage_v - lo.voltage_v) / (i_hi - i_lo)
    intercept = hi.voltage_v - slope * i_hi
    offset = before.voltage_offset_v + intercept / before.voltage_gain
    if abs(offset) > VOLTAGE_OFFSET_MAX_V:
        raise CalibrationError(
            f"the wire voltage reads {intercept * 1e3:+.2f} mV at 0 A (offset "
            f"{offset * 1e3:+.2f} mV, the device stores ±{VOLTAGE_OFFSET_MAX_V * 1e3:.3f} mV): "
            "check the sense leads and the difference amplifier; nothing written"
        )
    new = dataclasses.replace(before, voltage_offset_v=offset)
    new.to_data()  # range check before anything is sent
    return slope, intercept, new


def calibrate_wire_offset(cs: Any, wire: Any, current_a: float, *, average_s: float = 1.0,
                          tolerance: float = WIRE_TOLERANCE) -> WireOffset:  # fmt: skip
    """Hold ``WIRE_FIT_FRACTION × current_a`` and ``current_a`` on the cold wire, fit the wire
    voltage's offset, write it (output off) and read it back. The wire is judged (open circuit,
    sense leads, R against ``wire``: :func:`judge_wire`) on the offset-free slope before
    anything is written."""
    before = cs.get_calibration()
    lo = measure_wire(cs, WIRE_FIT_FRACTION * current_a, average_s=average_s)
    judge_wire(lo, wire, math.inf)  # an open circuit or lost sense: said before anything else
    hi = measure_wire(cs, current_a, average_s=average_s)
    judge_wire(hi, wire, math.inf)
    slope, intercept, new = fit_wire_offset(lo, hi, before)
    judge_wire(dataclasses.replace(hi, voltage_v=hi.voltage_v - intercept), wire, tolerance)
    cs.enable(False)  # the device refuses EEPROM writes while the output is on
    cs.set_calibration(new)
    back = cs.get_calibration()
    if not _same_calibration(back, new):
        raise CalibrationError(f"read back {back} after writing {new}: the EEPROM did not take it")
    points = ((lo.shunt_current_a, lo.voltage_v), (hi.shunt_current_a, hi.voltage_v))
    return WireOffset(before, new, back, points, slope, intercept)


# ---------------------------------------------------------------------------- sensor tare
@dataclass(frozen=True)
class PositionStats:
    """Displacement readings over a while."""

    mean_mm: float
    std_mm: float
    samples: int
    invalid: int
    duration_s: float


def read_positions(sensor: Any, duration_s: float = TARE_DURATION_S) -> PositionStats:
    """Read ``sensor`` at up to :data:`TARE_RATE_HZ` for ``duration_s``; CalibrationError when
    fewer than :data:`TARE_MIN_SAMPLES` or than half of the readings are valid."""
    values: list[float] = []
    invalid = 0
    errors: list[str] = []
    t0 = time.monotonic()
    next_t = t0
    while True:
        now = time.monotonic()
        if now - t0 >= duration_s:
            break
        if now < next_t:
            time.sleep(next_t - now)  # pacing the requests, not waiting for a state
        next_t += 1.0 / TARE_RATE_HZ
        s = sensor.read_or_flag()
        if s.ok and math.isfinite(s.position_mm):
            values.append(s.position_mm)
        else:
            invalid += 1
            errors.append(s.error)
    n = len(values)
    if n < TARE_MIN_SAMPLES or n < invalid:
        last = errors[-1] if errors else "no reading"
        raise CalibrationError(
            f"only {n} valid reading(s) of {n + invalid} in {duration_s:g} s ({last}): "
            "nothing stored"
        )
    arr = np.asarray(values)
    return PositionStats(float(arr.mean()), float(arr.std()), n, invalid, duration_s)


# ---------------------------------------------------------------------------- CLI
def _float_list(text: str, what: str) -> list[float]:
    try:
        values = [float(x) for x in text.replace(";", ",").split(",") if x.strip()]
    except ValueError:
        raise CalibrationError(f"{what} {text!r}: give numbers separated by commas") from None
    if not values:
        raise CalibrationError(f"{what}: no numbers in {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise CalibrationError(f"{what} {text!r}: NaN and infinities are not readings")
    return values


def parse_reading(text: str) -> float:
    """A meter reading typed by the operator: ``1.003``, ``1.003 A`` or ``1003 mA``."""
    t = text.strip().lower().replace(",", ".")
    scale = 1.0
    if t.endswith("ma"):
        t, scale = t[:-2], 1e-3
    elif t.endswith("a"):
        t = t[:-1]
    value = float(t.strip()) * scale
    if not math.isfinite(value):
        raise ValueError(text)
    return value


def _prompt_meter(input_fn: Callable[[str], str], out: Any) -> MeterFn:
    def meter(step: int, set_a: float, held: HeldCurrent) -> float:
        left = held.remaining_s()
        limit = f" (on for {left:.0f} s more at most)" if math.isfinite(left) else ""
        for _ in range(3):
            try:
                text = input_fn(f"  {set_a:.3f} A is on{limit}: meter reading in A? ")
            except EOFError:
                raise CalibrationError(
                    "no meter reading given (end of input): nothing written"
                ) from None
            try:
                return parse_reading(text)
            except ValueError:
                print(f"  {text.strip()!r} is not a reading: type e.g. 1.003 or 1003 mA",
                      file=out, flush=True)  # fmt: skip
        raise CalibrationError("no meter reading understood: nothing written")

    return meter


def _connect(port: str) -> Any:
    from smabench.bench.priority import LINK_RT_PRIORITY, raise_priority
    from smabench.drivers.current_source import CurrentSource, CurrentSourceError

    raise_priority()  # it renews the lease while the operator reads the meter: as the bench loop
    cs = CurrentSource(port, lease_s=LEASE_S, owner_priority=LINK_RT_PRIORITY)
    try:
        cs.connect()
    except CurrentSourceError as exc:
        cs.close()
        raise CalibrationError(f"current driver on {port}: {exc}") from None
    return cs


def cmd_calibrate_current(args: argparse.Namespace, *, input_fn=input, out: Any = None) -> int:
    out = out or sys.stdout
    from smabench.drivers.current_source import CurrentSourceError

    currents = _float_list(args.currents, "--currents")
    if any(not 0.05 <= i <= 2.5 for i in currents) or sorted(set(currents)) != currents:
        raise CalibrationError(
            f"--currents {args.currents}: rising values in 0.05 … 2.5 A, each once"
        )
    if len(currents) < 2:
        raise CalibrationError("--currents: at least two currents to fit offset and gain")
    readings = None
    if args.readings is not None:
        readings = _float_list(args.readings, "--readings")
        check_readings(currents, readings)  # refused before the output is ever on
    store = store_path(args.calibration)
    load_store(store)  # a broken store is refused before anything is done
    cs = _connect(args.port)
    try:
        info = cs.info
        if max(currents) > info.hard_limit_a + 1e-9:
            raise CalibrationError(
                f"--currents up to {max(currents):g} A above the device's hard limit "
                f"{info.hard_limit_a:g} A"
            )
        before = cs.get_calibration()
        print(f"current driver {info.name} fw {info.firmware} on {args.port}: calibration now "
              f"offset {before.current_offset_a * 1e3:+.3f} mA, gain {before.current_gain:.5f}",
              file=out, flush=True)  # fmt: skip
        if readings is None:
            print("Put a multimeter (DC A range) in series with the wire. Each current is held "
                  "while you read it.", file=out, flush=True)  # fmt: skip
            meter = _prompt_meter(input_fn, out)
        else:

            def meter(step: int, set_a: float, held: HeldCurrent) -> float:
                return readings[step]

        result = calibrate_current(
            cs, currents, meter, settle_s=args.settle_s, average_s=args.average_s,
            max_hold_s=args.max_hold_s, out=out,
        )  # fmt: skip
    except CurrentSourceError as exc:
        raise CalibrationError(f"current driver: {exc}; nothing written") from None
    finally:
        cs.close()
    fit = result.fit
    print(f"fit (least squares, {len(currents)} points): offset {fit.offset_a * 1e3:+.3f} mA, "
          f"gain {fit.gain:.5f} (was {before.current_offset_a * 1e3:+.3f} mA, "
          f"{before.current_gain:.5f})", file=out)  # fmt: skip
    print("   set A   device A   meter A   residual mA (calibrated − meter)", file=out)
    for i, d, m, r in zip(currents, result.device_a, result.meter_a, fit.residuals_a,
                          strict=True):  # fmt: skip
        print(f"  {i:6.3f}   {d:8.4f}   {m:7.4f}   {r * 1e3:+8.2f}", file=out)
    back = result.read_back
    print(f"output off, written to EEPROM and read back: offset {back.current_offset_a * 1e3:+.3f}"
          f" mA, gain {back.current_gain:.5f}, voltage gain {back.voltage_gain:.5f}: as written",
          file=out)  # fmt: skip
    record = {
        "offset_a": back.current_offset_a,
        "gain": back.current_gain,
        "voltage_gain": back.voltage_gain,
        "written_at": _now_iso(),
        "device": info.name,
        "firmware": info.firmware,
        "port": args.port,
        "points": [
            {"set_a": i, "device_before_a": d, "meter_a": m, "residual_a": r}
            for i, d, m, r in zip(currents, result.device_a, result.meter_a, fit.residuals_a,
                                  strict=True)  # fmt: skip
        ],
        "before": asdict(result.before),
    }
    print(f"saved in {save_record('current', record, store)}", file=out)
    return 0


def cmd_calibrate_wire(args: argparse.Namespace, *, out: Any = None) -> int:
    out = out or sys.stdout
    from smabench.drivers.current_source import CurrentSourceError

    wire = expected_wire(args.wire_length_mm, args.wire_diameter_mm, args.wire_preset)
    if not 0.1 <= args.current_a <= 0.5:
        raise CalibrationError(f"--current-a must be in 0.1 … 0.5 A (low: no heating), got "
                               f"{args.current_a:g}")  # fmt: skip
    tolerance = args.tolerance_pct / 100.0
    store = store_path(args.calibration)
    load_store(store)
    cs = _connect(args.port)
    try:
        fitted = calibrate_wire_offset(cs, wire, args.current_a, average_s=args.average_s,
                                       tolerance=tolerance)  # fmt: skip
        m = measure_wire(cs, args.current_a, average_s=args.average_s)  # with the new offset
    except CurrentSourceError as exc:
        raise CalibrationError(f"current driver: {exc}") from None
    finally:
        cs.close()
    (i_lo, v_lo), (i_hi, v_hi) = fitted.points
    print(f"wire voltage at {i_lo:.4f} A: {v_lo * 1e3:.2f} mV, at {i_hi:.4f} A: "
          f"{v_hi * 1e3:.2f} mV (offset {fitted.before.voltage_offset_v * 1e3:+.3f} mV): "
          f"{fitted.intercept_v * 1e3:+.3f} mV at 0 A", file=out)  # fmt: skip
    print(f"wire-voltage offset written to EEPROM and read back: "
          f"{fitted.read_back.voltage_offset_v * 1e3:+.3f} mV", file=out)  # fmt: skip
    check = judge_wire(m, wire, tolerance)
    print(f"wire {check.length_mm:g} mm × {check.diameter_mm:g} mm at {check.current_a:.4f} A: "
          f"V {check.voltage_v * 1e3:.2f} mV (Kelvin), R {check.resistance_ohm:.4f} Ω, "
          f"{check.ohm_per_m:.3f} Ω/m", file=out)  # fmt: skip
    print(f"expected (martensite, {wire.resistivity_martensite_ohm_m * 1e8:.0f} µΩ·cm): "
          f"{check.expected_ohm:.4f} Ω; deviation {check.deviation:+.1%} (tolerance "
          f"±{tolerance:.0%})", file=out)  # fmt: skip
    print(f"heating by the heat balance: +{check.heating_k:.2f} K by the end of the "
          f"{m.on_s:.1f} s at {check.current_a:.2f} A (+{check.steady_heating_k:.1f} K "
          f"if held for ever), far below As {check.as_c:g} °C: the wire stays martensite",
          file=out)  # fmt: skip
    record = {
        "resistance_ohm": check.resistance_ohm,
        "ohm_per_m": check.ohm_per_m,
        "expected_ohm": check.expected_ohm,
        "deviation": check.deviation,
        "length_mm": check.length_mm,
        "diameter_mm": check.diameter_mm,
        "wire_preset": args.wire_preset,
        "current_a": check.current_a,
        "ambient_c": check.ambient_c,
        "heating_k": check.heating_k,
        "voltage_offset_v": fitted.read_back.voltage_offset_v,
        "voltage_offset_before_v": fitted.before.voltage_offset_v,
        "fit_points": [{"current_a": i, "voltage_v": v} for i, v in fitted.points],
        "measured_at": _now_iso(),
        "port": args.port,
    }
    print(f"saved in {save_record('wire', record, store)}", file=out)
    return 0


def cmd_calibrate_show(args: argparse.Namespace, *, out: Any = None) -> int:
    out = out or sys.stdout
    store = store_path(args.calibration)
    data = load_store(store)
    print(f"{store}{'' if data else ' (none yet)'}", file=out)
    if data:
        print(json.dumps(data, indent=2), file=out)
    if args.port:
        cs = _connect(args.port)
        try:
            cal = cs.get_calibration()
            t = cs.wait_telemetry(timeout_s=2.0)
        finally:
            cs.close()
        default = " (EEPROM invalid: defaults)" if t.flags & p.Flag.CAL_DEFAULT else ""
        print(f"device on {args.port}: offset {cal.current_offset_a * 1e3:+.3f} mA, gain "
              f"{cal.current_gain:.5f}, voltage gain {cal.voltage_gain:.5f}, wire-voltage "
              f"offset {cal.voltage_offset_v * 1e3:+.3f} mV{default}",
              file=out)  # fmt: skip
    return 0


def _open_sensor(args: argparse.Namespace) -> Any:
    from smabench.drivers.base import SensorError
    from smabench.drivers.displacement import DisplacementSensor

    try:
        sensor = DisplacementSensor(args.sensor_map, args.sensor)
        sensor.connect()
    except SensorError as exc:
        raise CalibrationError(f"sensor {args.sensor}: {exc}") from None
    return sensor


def cmd_sensor_tare(args: argparse.Namespace, *, out: Any = None) -> int:
    out = out or sys.stdout
    store = store_path(args.calibration)
    load_store(store)
    sensor = _open_sensor(args)
    try:
        stats = read_positions(sensor, args.duration_s)
    finally:
        sensor.close()
    if stats.std_mm > args.max_std_mm:
        raise CalibrationError(
            f"the position moves (± {stats.std_mm:.4f} mm over {stats.duration_s:g} s, more "
            f"than {args.max_std_mm:g} mm): wait until the wire is cold and the load still; "
            "nothing stored"
        )
    record = {
        "zero_mm": stats.mean_mm,
        "std_mm": stats.std_mm,
        "samples": stats.samples,
        "invalid": stats.invalid,
        "duration_s": stats.duration_s,
        "sensor": args.sensor,
        "map": sensor.map.name,
        "tared_at": _now_iso(),
    }
    print(f"zero {stats.mean_mm:.4f} mm (± {stats.std_mm:.4f} mm, {stats.samples} readings, "
          f"{stats.invalid} invalid, {stats.duration_s:g} s); positions are reported from it",
          file=out)  # fmt: skip
    print(f"saved in {save_record('sensor_tare', record, store)}", file=out)
    return 0


def cmd_sensor_read(args: argparse.Namespace, *, out: Any = None) -> int:
    out = out or sys.stdout
    tare = None if args.absolute else load_store(args.calibration).get("sensor_tare")
    sensor = _open_sensor(args)
    try:
        stats = read_positions(sensor, args.duration_s)
        name = sensor.map.name
    finally:
        sensor.close()
    if tare is None:
        print(f"position {stats.mean_mm:.4f} mm (absolute; ± {stats.std_mm:.4f} mm, "
              f"{stats.samples} readings)", file=out)  # fmt: skip
        return 0
    if tare.get("map") != name:
        print(f"warning: the tare was taken with map {tare.get('map')!r}, this sensor uses "
              f"{name!r}", file=sys.stderr)  # fmt: skip
    rel = stats.mean_mm - float(tare["zero_mm"])
    print(f"position {rel:+.4f} mm from the tare of {tare.get('tared_at')} (absolute "
          f"{stats.mean_mm:.4f} mm; ± {stats.std_mm:.4f} mm, {stats.samples} readings)",
          file=out)  # fmt: skip
    return 0


def _store_option(s: argparse.ArgumentParser) -> None:
    s.add_argument(
        "--calibration",
        metavar="FILE",
        help=f"calibration file (default ${ENV_STORE}, else ~/.config/smabench/calibration.json)",
    )


def add_commands(sub: Any) -> None:
    """Register ``calibrate`` and ``sensor`` on the CLI's subparsers."""
    from smabench.physics.wire import PRESETS
    from smabench.settings import default

    c = sub.add_parser("calibrate", help="calibrate the current driver and measure the wire")
    csub = c.add_subparsers(dest="what", required=True, metavar="WHAT")

    s = csub.add_parser(
        "current",
        help="offset and gain of the current measurement against a multimeter, into EEPROM",
    )
    s.add_argument("--port", type=serial_port, metavar="DEV", required=True,
                   help="current driver serial port")
    s.add_argument(
        "--currents",
        default=",".join(f"{i:g}" for i in DEFAULT_CURRENTS_A),
        help="currents to step through, A (0.2,1,2)",
    )
    s.add_argument(
        "--readings",
        help="the meter's readings at those currents, A (scripted; else asked for on stdin)",
    )
    s.add_argument("--settle-s", type=positive(), default=0.3, help="settling per step, s (0.3)")
    s.add_argument(
        "--average-s", type=positive(), default=0.5, help="device readings averaged, s (0.5)"
    )
    s.add_argument(
        "--max-hold-s",
        type=positive(),
        default=20.0,
        help="longest a current stays on while you read, s (20; less when the device's heat "
        "budget says so)",
    )
    _store_option(s)
    s.set_defaults(func=lambda a: _run(cmd_calibrate_current, a))

    s = csub.add_parser("wire", help="cold resistance of the wire (clamps, Kelvin sense leads)")
    s.add_argument("--port", type=serial_port, metavar="DEV", required=True,
                   help="current driver serial port")
    s.add_argument("--wire-length-mm", type=positive(), required=True, help="between the clamps")
    s.add_argument("--wire-diameter-mm", type=positive(), required=True, help="wire diameter")
    s.add_argument(
        "--wire-preset",
        choices=sorted(PRESETS),
        default=default("wire_preset"),
        help="material: resistivity, heat balance",
    )
    s.add_argument(
        "--current-a", type=positive(), default=WIRE_CURRENT_A, help="measuring current, A (0.2)"
    )
    s.add_argument("--average-s", type=positive(), default=1.0, help="averaged, s (1)")
    s.add_argument(
        "--tolerance-pct",
        type=positive(),
        default=WIRE_TOLERANCE * 100,
        help="refuse a resistance further off length x resistivity, %% (30)",
    )
    _store_option(s)
    s.set_defaults(func=lambda a: _run(cmd_calibrate_wire, a))

    s = csub.add_parser("show", help="print the stored results (and the device's calibration)")
    s.add_argument("--port", type=serial_port, metavar="DEV",
                   help="also read the calibration in this device's EEPROM")
    _store_option(s)
    s.set_defaults(func=lambda a: _run(cmd_calibrate_show, a))

    t = sub.add_parser("sensor", help="displacement sensor: tare, read")
    tsub = t.add_subparsers(dest="what", required=True, metavar="WHAT")
    for name, fn, text in (
        ("tare", cmd_sensor_tare, "store the mean reading over a second as the zero"),
        ("read", cmd_sensor_read, "read the position relative to the tare"),
    ):
        s = tsub.add_parser(name, help=text)
        s.add_argument("--sensor", type=sensor_spec, metavar="SPEC", required=True,
                       help="tcp:HOST:PORT or rtu:DEV[:BAUD]")
        s.add_argument("--sensor-map", type=sensor_map, default="generic-rs485-laser",
                       metavar="MAP",
                       help="register map: a shipped name or a map file")
        s.add_argument(
            "--duration-s", type=positive(), default=TARE_DURATION_S, help="reading time, s (1)"
        )
        if name == "read":
            s.add_argument("--absolute", action="store_true", help="without the tare")
        else:
            s.add_argument(
                "--max-std-mm",
                type=positive(),
                default=TARE_MAX_STD_MM,
                help=f"refuse when the readings scatter more, mm ({TARE_MAX_STD_MM:g})",
            )
        _store_option(s)
        s.set_defaults(func=lambda a, fn=fn: _run(fn, a))


def _run(fn: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """One line on stderr and exit 2 for a refusal (the CLI does the same for ValueError)."""
    from smabench.drivers.base import SensorError
    from smabench.drivers.link import LinkError

    try:
        return fn(args)
    except (LinkError, SensorError) as exc:
        raise CalibrationError(str(exc)) from None
