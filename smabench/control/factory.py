"""Build a :class:`~smabench.control.controller.Controller` from the session's settings.

:class:`ControllerSettings` is what the operator chooses (law, gains or the per-load tables,
feed-forward model, adaptation, scripted switches); :func:`build_controller` identifies the loop
model of the configured wire under the configured load and its kinetic lags (simulated nominal
identification cycles, see :mod:`smabench.control.model`; it never knows the plant effects the
mock may run with), checks the reference against the reachable stroke and wires everything
together.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from smabench.control.controller import MODES, Controller
from smabench.control.feedforward import FeedForward
from smabench.control.model import InverseLoop, identify_kinetic_lag, identify_loop_model
from smabench.control.observer import ObserverSettings, TemperatureObserver
from smabench.control.pid import PID, PIDGains, gains_for_load
from smabench.control.reference import Reference, natural_rise_rate_mm_s
from smabench.physics.wire import Wire
from smabench.protocols import ProtocolSettings

log = logging.getLogger(__name__)

MODEL_CACHE: dict[tuple, object] = {}


@dataclass
class ControllerSettings:
    """Closed-loop options of a session (units in names)."""

    mode: str = "ffpid"
    gains: PIDGains | None = None  # PID law, W/mm …; None: the per-load table
    ffpid_gains: PIDGains | None = None  # FF+PID's PID, mm/mm …; None: the per-load table
    ffpid_limit_mm: float = 1.0  # largest setpoint shift of FF+PID's PID
    ffpid_hold_gains: PIDGains | None = None  # FF+PID on setpoint holds; None: the table
    model: str = "sigmoid"  # loop model of the feed-forward: sigmoid, 1, 2
    adapt: bool = True
    lead_s: float | None = None  # None: each branch's identified kinetic lag
    horizon_s: float = 0.05  # heat-balance inverse horizon (see feedforward)
    preview_slack_s: float = 0.5
    reversal_deadband_mm: float = 0.02  # setpoint move back that counts as a reversal
    observer: ObserverSettings | None = field(default_factory=ObserverSettings)  # None: off
    t_ceiling_c: float = 120.0
    switches: list[tuple[float, str]] = field(default_factory=list)
    cooling_limit: bool = False  # tell the reference the natural cooling rate (max_rise_mm_s)

    def validate(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"unknown controller {self.mode!r}; choose from {', '.join(MODES)}")
        for g in (self.gains, self.ffpid_gains, self.ffpid_hold_gains):
            if g is not None:
                g.validate()
        if self.model not in ("sigmoid", "1", "2"):
            raise ValueError(f"feed-forward model must be sigmoid, 1 or 2, got {self.model!r}")
        if self.lead_s is not None and not 0.0 <= self.lead_s <= 5.0:
            raise ValueError(f"feed-forward lead must be in 0 … 5 s, got {self.lead_s}")
        if not 0.0 < self.horizon_s <= 1.0:
            raise ValueError(f"feed-forward horizon must be in (0, 1] s, got {self.horizon_s}")
        if not 0.0 < self.ffpid_limit_mm <= 5.0:
            raise ValueError(f"FF+PID shift limit must be in (0, 5] mm, got {self.ffpid_limit_mm}")
        if not 40.0 <= self.t_ceiling_c <= 200.0:
            raise ValueError(f"temperature ceiling must be in 40 … 200 °C, got {self.t_ceiling_c}")
        for t, m in self.switches:
            if m not in MODES or not (math.isfinite(t) and t >= 0):
                raise ValueError(f"bad switch {t}:{m}")


def loop_model_for(load_kg: float, wire: Wire, model: str, ambient_c: float = 22.0):
    """Identified model (cached per wire, load, model)."""
    key = (wire, float(load_kg), model, float(ambient_c))
    if key not in MODEL_CACHE:
        MODEL_CACHE[key] = identify_loop_model(load_kg, wire, model, ambient_c)
    return MODEL_CACHE[key]


def kinetic_lag_for(load_kg: float, wire: Wire, model: str, ambient_c: float = 22.0):
    """(heating, cooling) kinetic lag, s, of the identified model (cached)."""
    key = ("lag", wire, float(load_kg), model, float(ambient_c))
    if key not in MODEL_CACHE:
        fit = loop_model_for(load_kg, wire, model, ambient_c)
        MODEL_CACHE[key] = identify_kinetic_lag(fit, load_kg, wire, ambient_c)
    return MODEL_CACHE[key]


def build_controller(
    protocol: ProtocolSettings,
    ctrl: ControllerSettings,
    load_kg: float,
    wire: Wire,
    current_limit_a: float,
    temperature_limit_c: float = 160.0,
    ambient_c: float = 22.0,
) -> Controller:
    """A controller for one session; ValueError (clear message) when a setting is refused,
    e.g. setpoints outside the reachable stroke."""
    ctrl.validate()
    t_ceiling = min(ctrl.t_ceiling_c, temperature_limit_c - 10.0)
    fit = loop_model_for(load_kg, wire, ctrl.model, ambient_c)
    inverse = InverseLoop(fit.loop_model, ambient_c, t_ceiling, adapt=ctrl.adapt,
                          deadband_mm=ctrl.reversal_deadband_mm)  # fmt: skip
    stroke = inverse.reachable_mm()
    offset = protocol.offset_mm if protocol.offset_mm is not None else 0.5 * sum(stroke)
    if ctrl.cooling_limit and protocol.max_rise_mm_s is None:
        rate = natural_rise_rate_mm_s(inverse, wire, ambient_c)
        protocol = ProtocolSettings(**{**protocol.__dict__, "max_rise_mm_s": rate})
    reference = Reference(protocol, offset)
    lags = kinetic_lag_for(load_kg, wire, ctrl.model, ambient_c)
    lead = lags if ctrl.lead_s is None else ctrl.lead_s
    ff = FeedForward(inverse, wire, ambient_c, t_ceiling, lead, horizon_s=ctrl.horizon_s,
                     preview_slack_s=ctrl.preview_slack_s)  # fmt: skip
    gains = ctrl.gains or gains_for_load(load_kg)
    ffpid_gains = ctrl.ffpid_gains or gains_for_load(load_kg, law="ffpid")
    ffpid_hold_gains = ctrl.ffpid_hold_gains or gains_for_load(load_kg, law="ffpid_hold")
    observer = None
    if ctrl.observer is not None:
        observer = TemperatureObserver(fit.loop_model, wire, lags, ctrl.observer, ambient_c)
    info = {
        "load_kg": load_kg,
        "reference": {
            "kind": protocol.name,
            "amplitude_mm": protocol.amplitude_mm,
            "offset_mm": offset,
            "period_s": protocol.period_s,
            "cycles": protocol.cycles,
            "lead_in_s": protocol.lead_in_s,
            "max_rise_mm_s": protocol.max_rise_mm_s,
        },
        "model": {
            "kind": ctrl.model,
            "identified_from": "simulate_plant, nominal plant (no effects), slow ramp cycle",
            "nrmse_percent": fit.nrmse_percent,
            "kinetic_lag_s": {"heating": lags[0], "cooling": lags[1]},
            "parameters": fit.parameters,
        },
        "gains_source": "settings" if ctrl.gains else f"per-load table ({load_kg:g} kg)",
        "ffpid_gains_source": "settings" if ctrl.ffpid_gains else
                              f"per-load table ({load_kg:g} kg)",  # fmt: skip
        "ffpid_hold_gains_source": "settings" if ctrl.ffpid_hold_gains else
                                   f"per-load table ({load_kg:g} kg)",  # fmt: skip
        "switches": [[t, m] for t, m in ctrl.switches],
    }
    return Controller(
        wire,
        current_limit_a,
        reference=reference,
        pid=PID(gains),
        feedforward=ff,
        mode=ctrl.mode,
        t_ceiling_c=t_ceiling,
        ambient_c=ambient_c,
        switches=list(ctrl.switches),
        stroke_mm=stroke,
        info=info,
        ffpid=PID(ffpid_gains),
        observer=observer,
        ffpid_limit_mm=ctrl.ffpid_limit_mm,
        ffpid_hold_gains=ffpid_hold_gains,
    )
