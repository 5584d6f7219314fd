"""PID on position, gains per load, relay auto-tune.

Sign: heating shortens the wire and ``position_mm`` grows with the wire length, so the control
error is ``e = position − setpoint`` (mm): a wire that is too long (e > 0) needs more heat.

The same discrete PID serves two laws (units follow the output):

- ``pid``: output the electrical power P (W) put into the wire; the caller turns it into a
  current with ``I = sqrt(P/R)``. The plant from power to temperature is linear (heat balance),
  so the loop is much closer to linear in P than in I (the wire heats with I²). Gains in W/mm,
  W/(mm·s), W·s/mm.
- ``ffpid``: output a shift (mm) of the setpoint the feed-forward inverts (FF+PID, see
  :mod:`smabench.control.controller`). Gains in mm/mm, 1/s, s.

- Output limits ``[out_min_w, out_max_w]`` per call (the maximum moves with the temperature
  ceiling; the minimum is 0: cooling is passive).
- Anti-windup: conditional integration (no integration while the output is saturated and the
  error pushes further into saturation) plus clamping of the integral to the output range left
  by the feed-forward, so neither a saturated current nor passive cooling winds it up.
- Derivative on the measurement (no kick on setpoint steps), through a first-order filter with
  time constant ``d_filter_s``.
- Bumpless transfer: :meth:`PID.track` sets the integral so that the output equals the current
  command at the switch.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from smabench.commands import CommandStep
from smabench.settings import GAIN_SETS, check_value

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PIDGains:
    """Gains in power units: kp W/mm, ki W/(mm·s), kd W·s/mm; d_filter_s the derivative filter
    time constant, s."""

    kp: float
    ki: float
    kd: float = 0.0
    d_filter_s: float = 0.3

    def validate(self, law: str = "pid") -> None:
        """ValueError naming the gain, its value and range (:mod:`smabench.settings`; the
        ranges of ``law``'s gain set: ``pid``, ``ffpid`` or ``ffpid_hold``)."""
        gain_set = GAIN_SETS[law]
        for key, v in zip(gain_set.keys, (self.kp, self.ki, self.kd, self.d_filter_s),
                          strict=True):  # fmt: skip
            check_value(key, v)

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


# Gains per load for the paper wire (55 mm, Ø 0.38 mm): grid searches on the offline closed
# loop (``smabench.bench.tuning``: the benchmark's four references on the nominal plant, the
# lowest mean RMS error; each grid extended until its best point was inside it). The cost is
# flat near the optimum (within ≈ 3 % for kd/kp ≈ 0.3–0.5 s at 2 kg), so neighbouring loads
# can differ more than the physics does. Interpolated in load.
GAIN_TABLE: dict[float, PIDGains] = {  # W/mm, W/(mm·s), W·s/mm, s
    1.0: PIDGains(2.5, 0.4, 1.2, 0.1),
    2.0: PIDGains(6.0, 0.4, 3.0, 0.1),
    4.0: PIDGains(2.5, 0.4, 0.8, 0.1),
}
FFPID_GAIN_TABLE: dict[float, PIDGains] = {  # mm/mm, 1/s, s, s
    1.0: PIDGains(0.1, 0.5, 0.0, 0.05),
    2.0: PIDGains(0.3, 2.0, 0.0, 0.05),
    4.0: PIDGains(0.2, 1.0, 0.0, 0.05),
}
# FF+PID while the setpoint holds still (steps, staircases, the lead-in): integral only, slow.
# On a hold, any overshoot the feedback corrects costs a trip across the hysteresis gap, which
# overshoots the other way; the feed-forward alone lands within ≈ 0.05 mm, so the feedback only
# trims a steady offset. Chosen on the benchmark's 24 cases offline (nominal and latent-heat
# plants, 3 loop periods; FF+PID / PID RMS): hold ki 0 (no feedback on holds) fails the latent
# steps, 0.02 /s meets all 24, 0.03–0.15 /s meet 18–21 at the worst period; the tracking gains
# on holds meet 16. (Swept before the observer gate took measured reversal points; with it,
# 0.02 /s meets all 24 at six loop periods.)
FFPID_HOLD_GAIN_TABLE: dict[float, PIDGains] = {  # mm/mm, 1/s, s, s
    1.0: PIDGains(0.0, 0.02, 0.0, 0.05),
    2.0: PIDGains(0.0, 0.02, 0.0, 0.05),
    4.0: PIDGains(0.0, 0.02, 0.0, 0.05),
}
LAW_TABLES = {"pid": GAIN_TABLE, "ffpid": FFPID_GAIN_TABLE, "ffpid_hold": FFPID_HOLD_GAIN_TABLE}


def gains_for_load(
    load_kg: float, table: dict[float, PIDGains] | None = None, law: str = "pid"
) -> PIDGains:
    """Gains of ``law`` (``pid``, ``ffpid`` or ``ffpid_hold``) for ``load_kg`` kg, interpolated
    linearly in the table (held beyond its ends)."""
    table = table or LAW_TABLES[law]
    loads = sorted(table)
    x = min(max(load_kg, loads[0]), loads[-1])
    vals = np.array([[table[k].kp, table[k].ki, table[k].kd, table[k].d_filter_s] for k in loads])
    kp, ki, kd, tf = (float(np.interp(x, loads, vals[:, j])) for j in range(4))
    return PIDGains(kp, ki, kd, tf)


class PID:
    """Discrete PID (see module docstring). Not thread-safe by itself: the controller owns it."""

    def __init__(self, gains: PIDGains) -> None:
        gains.validate()
        self.gains = gains
        self.integral_w = 0.0
        self._y_f: float | None = None  # filtered measurement
        self._dy_f = 0.0  # filtered derivative, mm/s
        self.last_output_w = 0.0
        self.saturated = False
        self.branch_integrals = {True: 0.0, False: 0.0}  # kept per branch by the controller

    def set_gains(self, gains: PIDGains) -> None:
        """New gains; the integral is kept (in power units it does not jump with ki)."""
        gains.validate()
        self.gains = gains

    def reset(self) -> None:
        """Forget the integrals, the derivative filter and the last output."""
        self.integral_w = 0.0
        self.branch_integrals = {True: 0.0, False: 0.0}
        self._y_f, self._dy_f = None, 0.0
        self.last_output_w = 0.0
        self.saturated = False

    def _terms(self, setpoint: float, measurement: float) -> tuple[float, float]:
        e = measurement - setpoint
        return self.gains.kp * e, self.gains.kd * self._dy_f

    def track(
        self, setpoint: float, measurement: float, output_w: float, feedforward_w: float = 0.0
    ) -> None:
        """Bumpless transfer: make the next output (same inputs) equal ``output_w``."""
        self._y_f, self._dy_f = measurement, 0.0  # a stale filter state would kick the D term
        p, d = self._terms(setpoint, measurement)
        self.integral_w = output_w - feedforward_w - p - d
        self.last_output_w = output_w

    def update(
        self,
        dt_s: float,
        setpoint: float,
        measurement: float,
        out_min_w: float,
        out_max_w: float,
        feedforward_w: float = 0.0,
        freeze: int = 0,
        hold_up: bool = False,
        hold_down: bool = False,
    ) -> float:
        """One step; returns the total output (feed-forward + PID), clipped to the limits.
        ``freeze`` = +1/−1: a later stage saturated, do not integrate positive/negative errors;
        ``hold_up`` / ``hold_down``: do not integrate positive / negative errors (both may
        hold at once)."""
        g = self.gains
        if not math.isfinite(measurement):
            return self.last_output_w  # hold on an invalid reading
        if self._y_f is None:
            self._y_f, self._dy_f = measurement, 0.0
        else:  # derivative on the measurement through a first-order filter
            a = dt_s / (g.d_filter_s + dt_s)
            y_new = self._y_f + a * (measurement - self._y_f)
            self._dy_f = (y_new - self._y_f) / dt_s if dt_s > 0 else 0.0
            self._y_f = y_new
        e = measurement - setpoint
        p, d = self._terms(setpoint, measurement)
        unsat = feedforward_w + p + self.integral_w + d
        pushes_up = e > 0 and (unsat >= out_max_w or freeze > 0 or hold_up)
        pushes_down = e < 0 and (unsat <= out_min_w or freeze < 0 or hold_down)
        if not (pushes_up or pushes_down):
            self.integral_w += g.ki * e * dt_s
        # the integral alone never holds more than the output range left by the feed-forward
        self.integral_w = min(max(self.integral_w, out_min_w - feedforward_w),
                              out_max_w - feedforward_w)  # fmt: skip
        out = feedforward_w + p + self.integral_w + d
        self.saturated = not out_min_w <= out <= out_max_w
        out = min(max(out, out_min_w), out_max_w)
        self.last_output_w = out
        return out


# --------------------------------------------------------------------------- relay auto-tune
@dataclass
class RelayResult:
    """Relay oscillation figures and the gains proposed from them."""

    amplitude_mm: float
    period_s: float
    ultimate_gain_w_per_mm: float
    gains: PIDGains


class RelayTuner:
    """Relay feedback (Åström–Hägglund) on position: a command source for the bench runtime.

    Power ``bias ± step`` (W) switches whenever the position crosses ``setpoint_mm`` (with a
    hysteresis of ``hysteresis_mm``); after ``cycles`` full oscillations (the first one dropped)
    :attr:`result` has the amplitude ``a`` and period ``Tu`` and the proposed gains from the
    ultimate gain ``Ku = 4·step/(π·a)``: Kp = 0.45·Ku, Ti = Tu/1.2 … in the conservative
    Tyreus–Luyben form (Kp = Ku/3.2, Ti = 2.2·Tu, Td = Tu/6.3, d filter Td/2).

    On the SMA wire this is a rough guide only: the oscillation is set by the hysteresis gap
    (the wire sits in the gap for most of each half cycle and moves ≈ 0.02 mm), not by a linear
    phase crossover, so on the offline loop the proposals change by 1.5–2× with the relay step
    and come out 2–3× above the grid-search gains of :mod:`smabench.bench.tuning`, which
    are the ones in the per-load tables.
    """

    def __init__(
        self,
        setpoint_mm: float,
        bias_w: float,
        step_w: float,
        cycles: int = 4,
        hysteresis_mm: float = 0.01,
        resistance_ohm: float = 0.436,
        max_duration_s: float = 300.0,
    ) -> None:
        if not 0.0 < step_w <= bias_w:
            raise ValueError("relay step must be in (0, bias] W (the output cannot go negative)")
        self.setpoint_mm, self.bias_w, self.step_w = setpoint_mm, bias_w, step_w
        self.cycles, self.hyst = cycles, hysteresis_mm
        self.resistance_ohm = resistance_ohm
        self.max_duration_s = max_duration_s
        self.high = True
        self.switch_t: list[float] = []
        self.extremes: list[float] = []
        self._ext: float | None = None
        self.result: RelayResult | None = None
        self.t0: float | None = None

    def update(self, t_s: float, position_mm: float):

        if self.t0 is None:
            self.t0 = t_s
        y = position_mm
        if math.isfinite(y):
            if self._ext is None:
                self._ext = y
            self._ext = min(self._ext, y) if self.high else max(self._ext, y)
            # heating (high) shortens the wire: switch off once it is below the setpoint
            if (self.high and y < self.setpoint_mm - self.hyst) or (
                not self.high and y > self.setpoint_mm + self.hyst
            ):
                self._switch(t_s)
        done = self.result is not None or t_s - self.t0 > self.max_duration_s
        p = self.bias_w + (self.step_w if self.high else -self.step_w)
        cur = math.sqrt(max(p, 0.0) / self.resistance_ohm)
        return CommandStep(0.0 if done else cur, len(self.switch_t) // 2, "relay",
                           self.setpoint_mm, "relay", done)  # fmt: skip

    def _switch(self, t_s: float) -> None:
        self.high = not self.high
        self.switch_t.append(t_s)
        if self._ext is not None:
            self.extremes.append(self._ext)
        self._ext = None
        n = len(self.switch_t)
        if n >= 2 * self.cycles + 1:
            sw = np.array(self.switch_t[2:])  # drop the first oscillation
            ex = np.array(self.extremes[2:])
            period = float(np.mean(np.diff(sw[::2])))
            amp = float(0.5 * (np.mean(ex[1::2]) - np.mean(ex[0::2]))) if ex.size >= 2 else 0.0
            amp = abs(amp)
            if amp > 0:
                self.result = relay_gains(amp, period, self.step_w)


def relay_gains(amplitude_mm: float, period_s: float, step_w: float) -> RelayResult:
    """Tyreus–Luyben PID gains from a relay oscillation (amplitude a, period Tu, relay step d)."""
    ku = 4.0 * step_w / (math.pi * amplitude_mm)
    kp = ku / 3.2
    ti = 2.2 * period_s
    td = period_s / 6.3
    gains = PIDGains(kp, kp / ti, kp * td, max(td / 2.0, 0.05))
    return RelayResult(amplitude_mm, period_s, ku, gains)
