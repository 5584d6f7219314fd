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
from dataclasses import dataclass, field
from typing import Any

from smabench.control.controller import Controller
from smabench.control.feedforward import FeedForward
from smabench.control.model import InverseLoop, identify_kinetic_lag, identify_loop_model
from smabench.control.observer import ObserverSettings, TemperatureObserver
from smabench.control.pid import PID, PIDGains, gains_for_load
from smabench.control.reference import Reference, natural_rise_rate_mm_s
from smabench.physics.wire import Wire
from smabench.protocols import ProtocolSettings
from smabench.settings import GAIN_COMPONENTS, GAIN_SETS, check_value, default

log = logging.getLogger(__name__)

MODEL_CACHE: dict[tuple, object] = {}


_C = "controller."


@dataclass
class ControllerSettings:
    """Closed-loop options of a session (units in names). Defaults, ranges and help:
    :mod:`smabench.settings` (keys ``controller.<field>``; a gain set ``None`` is the per-load
    table). ``mode`` defaults to FF+PID here; a session without a controller has none at all."""

    mode: str = "ffpid"
    gains: PIDGains | None = None  # PID law, W/mm …; None: the per-load table
    ffpid_gains: PIDGains | None = None  # FF+PID's PID, mm/mm …; None: the per-load table
    ffpid_limit_mm: float = default(_C + "ffpid_limit_mm")  # largest shift of FF+PID's PID
    ffpid_hold_gains: PIDGains | None = None  # FF+PID on setpoint holds; None: the table
    model: str = default(_C + "model")  # loop model of the feed-forward: sigmoid, 1, 2
    adapt: bool = default(_C + "adapt")
    lead_s: float | None = default(_C + "lead_s")  # None: each branch's identified lag
    horizon_s: float = default(_C + "horizon_s")  # heat-balance inverse horizon
    preview_slack_s: float = default(_C + "preview_slack_s")
    reversal_deadband_mm: float = default(_C + "reversal_deadband_mm")
    observer: ObserverSettings | None = field(default_factory=ObserverSettings)  # None: off
    t_ceiling_c: float = default(_C + "t_ceiling_c")
    switches: list[tuple[float, str]] = field(default_factory=list)
    cooling_limit: bool = default(_C + "cooling_limit")  # tell the reference the cooling rate

    def validate(self) -> None:
        """ValueError (:class:`smabench.settings.SettingError`) naming the first setting out of
        range."""
        for name, v in self.values().items():
            if GAIN_SET_KEYS.get(name.rsplit(".", 1)[0]) is None:
                check_value(name, v)
        for law, g in self.gain_sets().items():
            if g is not None:
                g.validate(law)

    def gain_sets(self) -> dict[str, PIDGains | None]:
        return {"pid": self.gains, "ffpid": self.ffpid_gains, "ffpid_hold": self.ffpid_hold_gains}

    def values(self) -> dict[str, Any]:
        """The settings as schema values (keys ``controller.…``; gain components ``None`` when
        a set comes from the per-load table)."""
        out: dict[str, Any] = {
            _C + "mode": self.mode,
            _C + "switches": tuple(tuple(x) for x in self.switches),
            _C + "observer": self.observer is not None,
        }
        for name in ("model", "adapt", "lead_s", "horizon_s", "preview_slack_s",
                     "reversal_deadband_mm", "ffpid_limit_mm", "t_ceiling_c", "cooling_limit"):
            out[_C + name] = getattr(self, name)  # fmt: skip
        for law, g in self.gain_sets().items():
            for key, comp in zip(GAIN_SETS[law].keys, GAIN_COMPONENTS, strict=True):
                out[key] = None if g is None else getattr(g, comp)
        return out

    @classmethod
    def from_values(cls, values: dict[str, Any], load_kg: float) -> ControllerSettings:
        """From schema values (:func:`smabench.settings.values_from_mapping` or the CLI); a gain
        component left ``None`` comes from the per-load table for ``load_kg``."""
        v = {k[len(_C):]: x for k, x in values.items() if k.startswith(_C)}
        observer = v.pop("observer", True)
        kw = {k: x for k, x in v.items() if "." not in k}
        sets = {law: gains_from_values(values, law, load_kg) for law in GAIN_SETS}
        kw["switches"] = [tuple(x) for x in kw.get("switches", ())]
        kw.setdefault("mode", "ffpid")
        if kw["mode"] is None:
            kw["mode"] = "ffpid"
        return cls(gains=sets["pid"], ffpid_gains=sets["ffpid"],
                   ffpid_hold_gains=sets["ffpid_hold"],
                   observer=ObserverSettings() if observer else None, **kw)  # fmt: skip


GAIN_SET_KEYS = {gs.key: law for law, gs in GAIN_SETS.items()}


def gains_from_values(values: dict[str, Any], law: str, load_kg: float) -> PIDGains | None:
    """``law``'s gains from schema values: None when no component is given (the per-load table
    then applies at build time), else the given components with the rest from the table."""
    keys = GAIN_SETS[law].keys
    given = [values.get(k) for k in keys]
    if all(x is None for x in given):
        return None
    table = gains_for_load(load_kg, law=law)
    comps = [x if x is not None else getattr(table, c)
             for x, c in zip(given, GAIN_COMPONENTS, strict=True)]  # fmt: skip
    return PIDGains(*comps)


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
