"""Feed-forward: inverse loop model → temperature trajectory → inverse heat balance → power.

Each tick the position setpoint goes through :class:`~smabench.control.model.InverseLoop` (the
branch the motion needs, reversal memory, online adaptation) to a reference temperature. The
power that takes the feed-forward's temperature ``T_ff`` to the reference temperature at the end
of a short horizon ``h`` (``horizon_s``, held constant over it) is the exact inverse of the heat
balance step (``smabench.physics.thermal``, zero-order hold):

    T_inf = (T_ref(t + h + lead) − a·T_ff)/(1 − a),  a = exp(−h/τ),  P = h·A·(T_inf − T_room) − d

clipped to ``0 … P_max``. ``d`` is a heat input the wire gets besides the current (W; 0 unless
FF+PID's observer estimates one). A horizon of a few loop periods (50 ms) rather than one
(deadbeat) keeps the command from overshooting through the driver's current lag (8 ms) and
keeps the gain from temperature to power at C/h instead of C/dt.

- ``lead``: each branch's kinetic lag (the wire transforms that much behind its temperature),
  so the temperature is planned that far ahead of the setpoint.
- Cooling is passive: never a negative command. Where the reference falls faster than natural
  cooling, P = 0 and ``T_ff`` follows the natural cooling curve. Because the reference is known
  ahead, the target is also lowered to the latest temperature from which natural cooling still
  reaches the previewed reference temperatures over the next ``preview_s`` (the preview runs
  the inverse through the coming reversals), each ``preview_slack_s`` late at most: the wire
  starts cooling early enough to cross the hysteresis gap at a heating → cooling reversal, and
  the unavoidable miss is shared between the last stretch before the reversal and the first
  after it instead of being taken entirely before it (0.5 s: about a quarter of the time
  natural cooling needs to cross the gap from 70 °C).
- ``T_ff`` advances with the power applied (:meth:`advance`); it is synchronised to the
  runtime's estimate when a feed-forward law is switched on (bumpless start).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from smabench.control.model import InverseLoop
from smabench.physics.thermal import thermal_constants
from smabench.physics.wire import Wire

log = logging.getLogger(__name__)


class FeedForward:
    """Power feed-forward for a position setpoint (see module docstring)."""

    def __init__(
        self,
        inverse: InverseLoop,
        wire: Wire,
        ambient_c: float = 22.0,
        t_ceiling_c: float = 120.0,
        lead_s: float | tuple[float, float] = 0.15,
        horizon_s: float = 0.05,
        preview_s: float = 6.0,
        preview_step_s: float = 0.25,
        preview_slack_s: float = 0.5,
    ) -> None:
        self.inverse = inverse
        self.wire = wire
        self.ambient_c = ambient_c
        self.t_ceiling_c = t_ceiling_c
        # (heating, cooling) lead, s: each branch's kinetic lag
        self.lead_s = (lead_s, lead_s) if isinstance(lead_s, (int, float)) else tuple(lead_s)
        self.horizon_s = horizon_s
        self.heat_capacity, self.conductance = thermal_constants(wire)
        self.tau_s = self.heat_capacity / self.conductance
        self.preview_s, self.preview_step_s = preview_s, preview_step_s
        self.preview_slack_s = preview_slack_s
        self.t_ff_c = ambient_c
        self.t_ref_c = ambient_c
        self.power_w = 0.0

    def sync(self, temperature_c: float) -> None:
        """Start the feed-forward's temperature from ``temperature_c`` (°C)."""
        if math.isfinite(temperature_c):
            self.t_ff_c = float(temperature_c)

    def reference_temperature(self, setpoint_mm: float, deadband_mm: float | None = None) -> float:
        """Commit this tick's setpoint to the inverse (direction, reversals); returns T_ref."""
        t = self.inverse.temperature(setpoint_mm, commit=True, deadband_mm=deadband_mm)
        self.t_ref_c = min(max(t, self.ambient_c), self.t_ceiling_c)
        return self.t_ref_c

    def target_temperature(self, t_s: float, reference, offset_mm: float = 0.0) -> float:
        """Temperature (°C) for the end of the horizon: :meth:`follow_temperature`, lowered to
        :meth:`cooling_bound` (see module docstring)."""
        t_next = min(self.follow_temperature(t_s, reference, offset_mm),
                     self.cooling_bound(t_s, reference, offset_mm))  # fmt: skip
        return min(max(t_next, self.ambient_c), self.t_ceiling_c)

    def _ahead_s(self, t_s: float) -> float:
        lead = self.lead_s[0] if self.inverse.heating else self.lead_s[1]
        return t_s + self.horizon_s + lead

    def follow_temperature(self, t_s: float, reference, offset_mm: float = 0.0) -> float:
        """The reference (shifted by ``offset_mm``) ``h + lead`` s ahead of ``t_s`` through the
        inverse, on the current branch (°C)."""
        y = reference.peek(self._ahead_s(t_s)) + offset_mm
        return self.inverse.temperature(y, commit=False)

    def cooling_bound(self, t_s: float, reference, offset_mm: float = 0.0) -> float:
        """Latest temperature (°C) from which natural cooling still reaches every previewed
        reference temperature, each ``preview_slack_s`` late at most (inf: no preview)."""
        if self.preview_s <= 0:
            return math.inf
        ahead = self._ahead_s(t_s)
        hs = np.arange(1, int(self.preview_s / self.preview_step_s) + 1) * self.preview_step_s
        ys = [reference.peek(ahead + h) + offset_mm for h in hs]
        temps = np.asarray(self.inverse.preview(ys))
        reach = np.exp((hs + self.preview_slack_s) / self.tau_s)
        return float((self.ambient_c + (temps - self.ambient_c) * reach).min())

    def power(self, t_next_c: float, p_max_w: float, disturbance_w: float = 0.0) -> float:
        """Power (W), clipped to 0 … ``p_max_w``, that takes ``T_ff`` to ``t_next_c`` within the
        horizon, given a heat input ``disturbance_w`` (W) besides the current."""
        a = math.exp(-self.horizon_s / self.tau_s)
        t_inf = (t_next_c - a * self.t_ff_c) / (1.0 - a)
        p = (t_inf - self.ambient_c) * self.conductance - disturbance_w
        self.power_w = min(max(p, 0.0), max(p_max_w, 0.0))
        return self.power_w

    def advance(self, dt_s: float, power_w: float) -> None:
        """Advance ``T_ff`` over one loop period with ``power_w`` (W) applied."""
        a = math.exp(-dt_s / self.tau_s)
        t_inf = self.ambient_c + max(power_w, 0.0) / self.conductance
        self.t_ff_c = t_inf + (self.t_ff_c - t_inf) * a

    def steady_power_w(self, temperature_c: float) -> float:
        """Power (W) that holds the wire at ``temperature_c`` (the feed-forward's steady state)."""
        return max(0.0, (temperature_c - self.ambient_c) * self.conductance)
