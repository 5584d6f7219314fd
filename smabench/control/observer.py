"""Temperature and heat-input observer: the wire temperature FF+PID plans from, corrected by
the measured position through the loop model.

The heat balance of the applied power predicts the wire temperature (the runtime's estimate
does only that). Whatever it does not model — the latent heat of the transformation, a wrong
convection coefficient or resistance, a drifting room — shows up as a position that differs
from what the loop model predicts. The observer runs

    C·dT/dt = −hA·(T − T_room) + P + d

with an unknown heat input ``d`` (W) and, each tick,

- predicts the position ``ŷ``: the loop model at its temperature, on its own branch (direction
  of its temperature with a ``deadband_k`` hysteresis, the first common point moved to the last
  reversal, as the wire does), through a first-order lag of each branch's kinetic lag (the
  martensite fraction lags its equilibrium; :func:`~smabench.control.model.identify_kinetic_lag`);
- turns the position error into a temperature error through the model's slope
  ``s = dy/dT``: ``e = (y − ŷ)·s/(s² + s0²)`` (K). Where the branch is steep that is the
  temperature offset the position stands for; where it is flat (inside the hysteresis gap, at
  the ends of the stroke) it goes to zero: there the position says nothing about the
  temperature. ``s0`` bounds the gain where the slope is small;
- corrects ``T += l_T·dt·e`` and ``d += C·ω_d²·dt·e``, with per-branch gains: the wire answers
  a temperature change after its kinetic lag, about ten times longer on cooling, so the cooling
  branch gets the lower gains.

A gate keeps it out of the way when the model is right. Corrections are scaled by a gate
(0 … 1) that opens as the RMS error (over ``gate_tau_s``) of the *open-loop* model — the loop
model at the heat balance's own temperature, the runtime's estimate — passes ``gate_mm`` and is
fully open at twice that. The open-loop model starts each branch at the wire's measured
position at the reversal, as the feed-forward's inverse does (the paper's adaptation): from the
model's own reversal point, its minor branches drift from the wire's by up to 1 mm after a few
staircase stairs at 4 kg, which opened the gate on the nominal plant and let the observer steer
by a model error. On the nominal plant that error stays within the model's accuracy
(≈ 0.05–0.1 mm RMS on the sines) and the observer, whose corrections of a right model only
add noise that the hysteresis turns into limit cycles at holds, stays shut: FF+PID is then the
feed-forward with its PID. An effect the heat balance does not know (latent heat moves the
wire's temperature by up to λ ≈ 29 K over a transformation) drives that error to 0.4–0.9 mm and
the observer takes over. The gate measures the open-loop model, not the observer's own
prediction, so it does not close again as soon as the observer has done its job.

Three rules keep it from explaining model errors as heat:

- a wire *ahead* of the model on its branch (further along than predicted) is only used while
  it moves along the branch: a wire that stopped sits in the hysteresis gap, where a position
  error cannot be resolved without a reversal;
- ``d`` relaxes to 0 within ``still_decay_s`` while the wire does not move (it cannot be
  observed then, and an unobservable heat input must not steer the temperature estimate);
- ``d`` does not integrate further in a direction the command cannot answer (power at its
  maximum or at 0 W).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

from smabench.control.model import common_points
from smabench.physics.memory import ReversalMemory, TurnDetector
from smabench.physics.thermal import thermal_constants
from smabench.physics.wire import Wire

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ObserverSettings:
    """Gains and guards of :class:`TemperatureObserver` (units in names; pairs are
    (heating branch, cooling branch))."""

    temperature_gain_per_s: tuple[float, float] = (80.0, 24.0)
    disturbance_bandwidth_rad_s: tuple[float, float] = (10.0, 6.7)
    slope_floor_mm_per_k: float = 0.1
    deadband_k: float = 1.0
    moving_mm_s: float = 0.05
    velocity_filter_s: float = 0.1
    still_decay_s: float = 0.1
    decay_s: float = 3.0
    max_disturbance_w: float = 1.0
    ahead_while_moving: bool = True  # use "ahead" errors while the wire moves along the branch
    gate_mm: float = 0.15  # corrections fade in as the open-loop RMS error passes 1 … 2 × this
    gate_tau_s: float = 3.0  # time constant of that RMS

    def as_dict(self) -> dict:
        return asdict(self)


class TemperatureObserver:
    """See module docstring. Temperatures °C, positions mm, powers W, times s."""

    def __init__(
        self,
        model,
        wire: Wire,
        lags_s: tuple[float, float],
        settings: ObserverSettings | None = None,
        ambient_c: float = 22.0,
    ) -> None:
        self.model = model
        self.lags_s = lags_s
        self.s = settings or ObserverSettings()
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.tau_s = self.heat_capacity / self.conductance
        self.ambient_c = ambient_c
        self.low, self.high = common_points(model)
        self.temperature_c = ambient_c
        self.disturbance_w = 0.0
        # the reversal point the branch leaves, from the model and (gate) at the measured
        # position; one point each (the paper's moved first common point)
        self.memory = ReversalMemory(self.low, self.high, True, depth=1)
        self.memory_open = ReversalMemory(self.low, self.high, True, depth=1)
        self.turns = TurnDetector(self.s.deadband_k, True, ambient_c)
        self._ext_y: float | None = None  # measured position at the temperature extreme
        self._y_meas: float | None = None
        self.predicted_mm = math.nan
        self._y_lag: float | None = None
        self._y_f: float | None = None
        self.velocity_mm_s = 0.0
        self.error_ms_mm2 = 0.0  # mean square error of the open-loop model, mm²
        self.gate = 0.0 if self.s.gate_mm > 0 else 1.0
        self._y_open: float | None = None

    def reset(self, temperature_c: float, heating: bool = True) -> None:
        """Start from ``temperature_c`` (the runtime's estimate) with no heat input."""
        self.temperature_c = float(temperature_c)
        self._ext_y = self._y_meas = None
        self.disturbance_w = 0.0
        self.memory.reset(heating)
        self.memory_open.reset(heating)
        self.turns.reset(heating)
        self.turns.extreme = self.temperature_c
        self._y_lag = self._y_f = self._y_open = None
        self.velocity_mm_s = 0.0
        self.error_ms_mm2 = 0.0
        self.gate = 0.0 if self.s.gate_mm > 0 else 1.0

    # ------------------------------------------------------------------ model
    @property
    def heating(self) -> bool:
        return self.memory.heating

    def _branch(self, t_c: float, open_loop: bool = False) -> float:
        """Model position (mm) at ``t_c`` on the current branch: from the observer's start
        point, or (``open_loop``) from the one at the measured position."""
        mem = self.memory_open if open_loop else self.memory
        return float(self.model.branch(t_c, mem.heating, *mem.start_target()))

    def _track_direction(self) -> None:
        t = self.temperature_c
        turns = self.turns
        if turns.update(t):
            t_rev = turns.turn_at
            y_model = self._branch(t_rev)
            y_meas = y_model if self._ext_y is None else self._ext_y
            self.memory.reverse((t_rev, y_model))
            self.memory_open.reverse((t_rev, y_meas))
        elif turns.extreme == t:
            self._ext_y = self._y_meas

    # ------------------------------------------------------------------ per tick
    def predict(self, dt_s: float, power_w: float) -> None:
        """Advance one step with ``power_w`` (W) applied plus the estimated heat input."""
        a = math.exp(-dt_s / self.tau_s)
        t_inf = self.ambient_c + (power_w + self.disturbance_w) / self.conductance
        self.temperature_c = t_inf + (self.temperature_c - t_inf) * a
        self._track_direction()
        y_eq = self._branch(self.temperature_c)
        tau = self.lags_s[0] if self.heating else self.lags_s[1]
        b = math.exp(-dt_s / tau) if tau > 0 else 0.0
        self._y_lag = y_eq if self._y_lag is None else y_eq + (self._y_lag - y_eq) * b

    def correct(self, dt_s: float, position_mm: float, saturated: int = 0,
                open_loop_c: float | None = None) -> None:  # fmt: skip
        """Correct temperature and heat input from the measured ``position_mm`` (mm).
        ``saturated``: +1 / −1 when the last command was at its maximum / at 0 W.
        ``open_loop_c``: the heat balance's own temperature (the runtime's estimate), °C; the
        loop model at it gives the open-loop error that opens the gate."""
        if self._y_lag is None:
            self._y_lag = self._branch(self.temperature_c)
        y_hat = self._y_lag
        self.predicted_mm = y_hat
        if not math.isfinite(position_mm):
            return
        self._y_meas = position_mm
        if self._y_f is None:
            self._y_f = position_mm
        a = dt_s / (self.s.velocity_filter_s + dt_s)
        y_new = self._y_f + a * (position_mm - self._y_f)
        self.velocity_mm_s = (y_new - self._y_f) / dt_s
        self._y_f = y_new
        still = abs(self.velocity_mm_s) < self.s.moving_mm_s
        decay_s = self.s.still_decay_s if still else self.s.decay_s
        self.disturbance_w *= math.exp(-dt_s / decay_s)
        t = self.temperature_c
        slope = self._branch(t + 0.5) - self._branch(t - 0.5)  # mm/K, over 1 K
        s0 = self.s.slope_floor_mm_per_k
        if open_loop_c is not None:
            self._update_gate(dt_s, position_mm, open_loop_c)
        err_mm = (position_mm - y_hat) * self.gate
        err_k = err_mm * slope / (slope * slope + s0 * s0)
        direction = 1.0 if self.heating else -1.0  # +1: the branch moves with heat
        moving_along = -self.velocity_mm_s * direction > self.s.moving_mm_s
        if err_k * direction > 0 and not (moving_along and self.s.ahead_while_moving):
            return  # ahead of the model and stopped: in the gap, nothing to learn
        branch = 0 if self.heating else 1
        step_k = self.s.temperature_gain_per_s[branch] * dt_s * err_k
        self.temperature_c += step_k
        self._y_lag += slope * step_k  # the offset held in the past as well
        step_w = self.heat_capacity * self.s.disturbance_bandwidth_rad_s[branch] ** 2 * dt_s * err_k
        if (saturated > 0 and step_w < 0) or (saturated < 0 and step_w > 0):
            step_w = 0.0  # the command cannot answer: do not wind the heat input up
        limit = self.s.max_disturbance_w
        self.disturbance_w = min(max(self.disturbance_w + step_w, -limit), limit)

    def _update_gate(self, dt_s: float, position_mm: float, open_loop_c: float) -> None:
        """The gate (0 … 1) from the RMS error (``gate_tau_s``) of the open-loop model: the loop
        model, kinetic lag included, at the heat balance's own temperature."""
        y_eq = self._branch(open_loop_c, open_loop=True)
        tau = self.lags_s[0] if self.heating else self.lags_s[1]
        b = math.exp(-dt_s / tau) if tau > 0 else 0.0
        self._y_open = y_eq if self._y_open is None else y_eq + (self._y_open - y_eq) * b
        e_open = position_mm - self._y_open
        w = dt_s / (self.s.gate_tau_s + dt_s)
        self.error_ms_mm2 += w * (e_open * e_open - self.error_ms_mm2)
        if self.s.gate_mm > 0:
            rms = math.sqrt(self.error_ms_mm2)
            self.gate = min(max(rms / self.s.gate_mm - 1.0, 0.0), 1.0)

    def state(self) -> dict:
        return {
            "temperature_c": self.temperature_c,
            "disturbance_w": self.disturbance_w,
            "heating": self.heating,
            "gate": self.gate,
            "settings": self.s.as_dict(),
        }
