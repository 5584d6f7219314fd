"""Feed-forward: inverse loop model → temperature trajectory → inverse heat balance → power.

Each tick the position setpoint goes through :class:`~smabench.control.model.InverseLoop` (the
branch the motion needs, reversal memory, online adaptation) to a reference temperature. The
power that takes the feed-forward's own model of the wire temperature ``T_ff`` to the reference
temperature ``lead_s`` ahead within one step is the exact inverse of the heat balance step
(``smabench.physics.thermal``, zero-order hold):

    T_inf = (T_ref(t + dt + lead) − a·T_ff)/(1 − a),  a = exp(−dt/τ),  P = h·A·(T_inf − T_room)

clipped to ``0 … P_max``: cooling is passive (never a negative command: where the reference
falls faster than natural cooling, P = 0 and ``T_ff`` follows the natural cooling curve, so
``T_ff`` never runs ahead of what the wire can do) and the maximum comes from the current limit
and the temperature ceiling. Because the reference is known ahead, the target is also lowered
to the latest temperature from which natural cooling still reaches the previewed reference
temperatures over the next ``preview_s`` (the preview runs the inverse through the coming
reversals): the wire starts cooling early enough to cross the hysteresis gap at a
heating → cooling reversal. ``T_ff`` advances with the power the feed-forward stands for. It is the
feed-forward's own open-loop state, not the runtime's estimate, so a PID adding power on top is
not cancelled by the feed-forward; it is synchronised to the runtime's estimate when the
feed-forward is switched on (bumpless start). ``lead_s`` makes up for the lag of the
transformation kinetics behind the temperature.
"""

from __future__ import annotations

import math

import numpy as np

from smabench.control.model import InverseLoop
from smabench.physics.thermal import thermal_constants
from smabench.physics.wire import Wire


class FeedForward:
    """Power feed-forward for a position setpoint (see module docstring)."""

    def __init__(
        self,
        inverse: InverseLoop,
        wire: Wire,
        ambient_c: float = 22.0,
        t_ceiling_c: float = 120.0,
        lead_s: float = 0.15,
        preview_s: float = 6.0,
        preview_step_s: float = 0.25,
    ) -> None:
        self.inverse = inverse
        self.wire = wire
        self.ambient_c = ambient_c
        self.t_ceiling_c = t_ceiling_c
        self.lead_s = lead_s
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.tau_s = self.heat_capacity / self.conductance
        self.preview_s, self.preview_step_s = preview_s, preview_step_s
        self.t_ff_c = ambient_c
        self.t_ref_c = ambient_c
        self.power_w = 0.0

    def sync(self, temperature_c: float) -> None:
        """Start the feed-forward's temperature from the runtime's estimate."""
        if math.isfinite(temperature_c):
            self.t_ff_c = float(temperature_c)

    def reference_temperature(self, setpoint_mm: float) -> float:
        """Commit this tick's setpoint to the inverse (direction, reversals); returns T_ref."""
        t = self.inverse.temperature(setpoint_mm, commit=True)
        self.t_ref_c = min(max(t, self.ambient_c), self.t_ceiling_c)
        return self.t_ref_c

    def target_temperature(self, t_s: float, dt_s: float, reference) -> float:
        """Temperature for the end of this step: the reference ``dt + lead`` s ahead, lowered
        where the reference further ahead falls faster than natural cooling can follow (the
        latest temperature from which passive cooling still reaches every previewed point)."""
        t_next = self.inverse.temperature(reference.peek(t_s + dt_s + self.lead_s), commit=False)
        if self.preview_s > 0:
            hs = np.arange(1, int(self.preview_s / self.preview_step_s) + 1) * self.preview_step_s
            ys = [reference.peek(t_s + dt_s + self.lead_s + h) for h in hs]
            temps = np.asarray(self.inverse.preview(ys))
            bound = self.ambient_c + (temps - self.ambient_c) * np.exp(hs / self.tau_s)
            t_next = min(t_next, float(bound.min()))
        return min(max(t_next, self.ambient_c), self.t_ceiling_c)

    def power(self, dt_s: float, t_next_c: float, p_max_w: float) -> float:
        """Power (W), clipped to 0 … ``p_max_w``, that takes ``T_ff`` to ``t_next_c`` in
        ``dt_s`` s (exact inverse of the heat-balance step)."""
        if dt_s <= 0:
            return self.power_w
        a = math.exp(-dt_s / self.tau_s)
        t_inf = (t_next_c - a * self.t_ff_c) / (1.0 - a)
        p = (t_inf - self.ambient_c) * self.conductance
        self.power_w = min(max(p, 0.0), max(p_max_w, 0.0))
        return self.power_w

    def advance(self, dt_s: float, power_w: float) -> None:
        """Advance ``T_ff`` over the step with the power the feed-forward stands for."""
        a = math.exp(-dt_s / self.tau_s)
        t_inf = self.ambient_c + max(power_w, 0.0) / self.conductance
        self.t_ff_c = t_inf + (self.t_ff_c - t_inf) * a

    def steady_power_w(self, temperature_c: float) -> float:
        """Power that holds the wire at ``temperature_c`` (the feed-forward's steady state)."""
        return max(0.0, (temperature_c - self.ambient_c) * self.conductance)
