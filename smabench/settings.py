"""The run settings of a bench session, each declared once: type, default, range, unit, help.

Every front end is derived from this table: the ``smabench run`` options
(:func:`add_cli_options`, :func:`values_from_args`), the runtime's JSON messages
(:func:`values_from_mapping`, used by :mod:`smabench.bench.remote`) and the GUI's fields
(:func:`fields`). The session's dataclasses (``RunSettings``, ``ProtocolSettings``,
``ControllerSettings``, ``PIDGains``, ``RuntimeConfig``) take their defaults from here and validate
through :func:`check_value` and the cross-setting rules below, so a range exists in one place.

API for front ends (kept stable; the GUI builds its fields from it)
-------------------------------------------------------------------
- ``GROUPS``: group id → title, in display order: ``load_wire``, ``protocol``, ``controller``,
  ``gains``, ``limits``, ``loop``, ``session``.
- ``fields(group, protocol=None, closed_loop=None, mode=None) -> list[Setting]``: the settings of
  a group in display order; with ``protocol`` (and ``closed_loop``) only those that protocol
  uses; with ``mode`` only those that control law uses (gains of ``pid`` / ``ffpid``).
- ``GAIN_SETS``: the three gain sets (``pid``, ``ffpid``, ``ffpid_hold``) with their component
  keys; a gain component left ``None`` means "from the per-load table".
- ``Setting`` (frozen): ``key``, ``label``, ``unit``, ``kind`` (``float``, ``int``, ``bool``,
  ``choice``, ``floats``, ``switches``, ``text``), ``default``, ``choices``, ``decimals``, ``step``,
  ``live`` (may change during a run), ``optional`` + ``none_text`` (what ``None`` means, e.g.
  "per-load table"), ``tooltip`` (help, unit, range, default), ``range_text``,
  ``widget_range()`` → (lo, hi) for a spin box (open ends moved in by one display step),
  ``check(value)`` → the value, or :class:`SettingError` naming setting, value and range.
- ``error_for(key, value) -> str | None``: the message for a refused value (None when fine).
- ``values_from_mapping(dict) -> dict[key, value]``: the runtime's JSON (``{"load_kg": …,
  "protocol": {…}, "controller": {…, "gains": [kp, ki, kd] | {…} | null}}``), checked; unknown
  keys refused. ``to_mapping(values)`` is its inverse.
- ``stress_check(load_kg, wire_preset, long_life_stress_mpa=None) -> StressCheck``:
  ``.needs_confirmation``, ``.stress_mpa``, ``.limit_mpa``, ``.message`` (words for a dialog);
  a confirmed load is sent with ``allow_high_stress: true``.
- ``check_run(values, device_limit_a=None) -> StressCheck``: every rule across settings
  (load ≤ max load, currents ≤ the current limit, position min < max, the protocol against the
  loop, the stress), raising :class:`SettingError` (``.key``, ``.value``, ``.reason``).
- ``SETTINGS`` (key → Setting), ``get(key)``, ``GAIN_COMPONENTS``, ``PROTOCOL_NAMES``,
  ``REFERENCE_NAMES``, ``OPEN_LOOP_NAMES``, ``CONTROLLER_MODES``.

Nothing else is needed by a front end. Keys are the JSON paths: ``load_kg``,
``protocol.current_a``, ``controller.ffpid_hold_gains.ki``.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from smabench.drivers.protocol import HARD_LIMIT_A, PROBE_MAX_A
from smabench.physics.wire import PRESETS, Wire, load_kg_for_stress, stress_mpa

log = logging.getLogger(__name__)

GROUPS: dict[str, str] = {
    "load_wire": "Load & wire",
    "protocol": "Protocol",
    "controller": "Controller",
    "gains": "Gains",
    "limits": "Limits",
    "loop": "Loop",
    "session": "Session",
}

# choices that are facts of the schema (smabench.protocols and the controller use these)
PROTOCOL_NAMES = ("cycles", "incomplete", "inner", "step", "ramp", "staircase", "sine", "triangle")
REFERENCE_NAMES = ("step", "staircase", "sine", "triangle")
"""Protocols that are position references for a controller (``step`` is both)."""
OPEN_LOOP_NAMES = ("cycles", "incomplete", "inner", "step", "ramp")
CONTROLLER_MODES = ("open_loop", "pid", "ff", "ffpid")
FEEDBACK_SOURCES = ("laser", "resistance")
"""Where the command source's measured position comes from: the displacement sensor, or the
position estimated from the wire's resistance (issue 26)."""
FF_MODELS = ("sigmoid", "1", "2")

HEATING = ("cycles", "incomplete", "inner")
"""Protocols that heat at ``current_a`` and then cool until settled."""
CURRENT_MARGIN = 1.25
"""The current limit may exceed the wire's rated current by this factor (short heating pulses)."""
HIGH_STRESS_TOLERANCE = 0.01
"""A load within this fraction above the wire's long-life stress counts as at it: Dynalloy gives
the figure as a round "≈ 25,000 psi (172 MPa)", and the nominal diameter alone (0.015 in =
0.381 mm against the preset's 0.380 mm) moves the stress of a given load by 0.5 %. So 2 kg on
0.38 mm (172.9 MPa) runs without confirmation and 2.02 kg (174.6 MPa) asks for it."""


class SettingError(ValueError):
    """A refused setting: ``key``, the offending ``value`` and the reason (one line)."""

    def __init__(self, key: str, value: Any, reason: str) -> None:
        self.key, self.value, self.reason = key, value, reason
        super().__init__(self.naming(key))

    def naming(self, name: str) -> str:
        """The message naming the setting as ``name`` (``{name}`` in the reason, else at the
        end in parentheses)."""
        if "{name}" in self.reason:
            return self.reason.replace("{name}", name)
        return f"{self.reason} ({name})"

    def for_cli(self) -> str:
        """The message naming the command-line option instead of the key."""
        s = SETTINGS.get(self.key)
        return self.naming(s.cli_names()[0] if s is not None and s.cli_names() else self.key)


def _g(x: float) -> str:
    return f"{x:g}"


@dataclass(frozen=True)
class Setting:
    """One run setting (see the module docstring for the API front ends rely on)."""

    key: str
    label: str
    help: str
    group: str
    kind: str = "float"  # float, int, bool, choice, floats, switches, text
    default: Any = None
    unit: str = ""
    min: float | None = None
    max: float | str | None = None  # a key: bounded by that setting's value too
    min_open: bool = False
    max_open: bool = False
    choices: tuple[str, ...] = ()
    optional: bool = False  # None is a valid value, meaning ``none_text``
    none_text: str = ""
    required: bool = False  # must be given on the command line / in a start message
    protocols: tuple[str, ...] = ()  # open-loop protocols that use it (protocol group)
    references: tuple[str, ...] = ()  # position references that use it under a controller
    modes: tuple[str, ...] = ()  # control laws that use it (controller / gains groups)
    live: bool = False  # may change during a run
    decimals: int = 2
    step: float = 0.1
    cli: str | None = ""  # option name; "" derived from the key, None: no option
    cli_flag_value: bool = True  # bool options: the value the flag sets (False: --no-…)
    metavar: str | None = None

    # ------------------------------------------------------------------ description
    @property
    def max_value(self) -> float | None:
        """The static upper bound (a bound by another setting uses that setting's maximum)."""
        if isinstance(self.max, str):
            return SETTINGS[self.max].max_value
        return self.max

    @property
    def range_text(self) -> str:
        """E.g. ``(0, 10] kg``, ``0 … 100 W/mm``, ``≥ 1``; choices listed."""
        if self.kind == "choice":
            return "one of " + ", ".join(self.choices)
        lo, hi = self.min, self.max_value
        if lo is None and hi is None:
            return ""
        if hi is None:
            text = f"{'>' if self.min_open else '≥'} {_g(lo)}"
        elif lo is None:
            text = f"{'<' if self.max_open else '≤'} {_g(hi)}"
        elif not (self.min_open or self.max_open):
            text = f"{_g(lo)} … {_g(hi)}"
        else:
            text = (f"{'(' if self.min_open else '['}{_g(lo)}, {_g(hi)}"
                    f"{')' if self.max_open else ']'}")  # fmt: skip
        text = f"{text} {self.unit}".rstrip()
        if isinstance(self.max, str):
            text += f", and ≤ {SETTINGS[self.max].label}"
        return text

    @property
    def default_text(self) -> str:
        if self.default is None:
            return self.none_text or "none"
        if self.kind == "floats":
            return ",".join(_g(v) for v in self.default)
        if self.kind == "switches":
            return "none" if not self.default else " ".join(f"{_g(t)}:{m}" for t, m in self.default)
        if isinstance(self.default, bool):
            return "on" if self.default else "off"
        if isinstance(self.default, float):
            return f"{_g(self.default)} {self.unit}".rstrip()
        return str(self.default)

    @property
    def tooltip(self) -> str:
        """Help with unit, range and default, for a GUI tooltip."""
        parts = [self.help]
        if self.range_text:
            parts.append(f"Range: {self.range_text}.")
        parts.append(f"Default: {self.default_text}.")
        if self.live:
            parts.append("Can change during a run.")
        return " ".join(parts)

    def widget_range(self) -> tuple[float, float]:
        """(lo, hi) for a spin box at ``decimals``: open ends moved in by one display step."""
        q = 10.0**-self.decimals
        lo = -1e9 if self.min is None else self.min + (q if self.min_open else 0.0)
        hi_v = self.max_value
        hi = 1e9 if hi_v is None else hi_v - (q if self.max_open else 0.0)
        return lo, hi

    def cli_names(self) -> list[str]:
        if self.cli is None:
            return []
        if self.cli:
            return [self.cli]
        return ["--" + self.key.split(".")[-1].replace("_", "-")]

    @property
    def dest(self) -> str:
        return "setting__" + self.key.replace(".", "__")

    def uses(self, protocol: str | None, closed_loop: bool | None = None) -> bool:
        """Whether ``protocol`` (open loop, under a controller, or either when None) uses it."""
        if self.group != "protocol" or protocol is None or self.key == "protocol.name":
            return True
        open_use = protocol in self.protocols and protocol in OPEN_LOOP_NAMES
        ref_use = protocol in self.references and protocol in REFERENCE_NAMES
        if closed_loop is None:
            return open_use or ref_use
        return ref_use if closed_loop else open_use

    # ------------------------------------------------------------------ checking
    def _reason(self, value: Any, why: str = "") -> str:
        shown = value if isinstance(value, str) or value is None else _show(value, self.unit)
        if why:
            return f"{self.label} {why}, got {shown!s}"
        return f"{self.label} must be in {self.range_text}, got {shown!s}"

    def _number(self, value: Any) -> float:
        if isinstance(value, str):
            try:
                return float(value.strip().replace(",", "."))
            except ValueError:
                raise SettingError(self.key, value, self._reason(
                    repr(value), "must be a number")) from None  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingError(self.key, value, self._reason(repr(value), "must be a number"))
        return float(value)

    def _in_range(self, v: float, raw: Any = None) -> None:
        lo, hi = self.min, self.max_value
        bad = not math.isfinite(v)
        if lo is not None and (v < lo or (self.min_open and v == lo)):
            bad = True
        if hi is not None and (v > hi or (self.max_open and v == hi)):
            bad = True
        if bad:
            raise SettingError(self.key, v if raw is None else raw, self._reason(v))

    def check(self, value: Any) -> Any:
        """The value in its type (strings from a command line are parsed), or SettingError."""
        if value is None or (isinstance(value, str) and value.strip().lower() in ("", "none")
                             and self.optional):  # fmt: skip
            if self.optional:
                return None
            raise SettingError(self.key, value, self._reason(value, "must be given"))
        k = self.kind
        if k == "float":
            v = self._number(value)
            self._in_range(v)
            return v
        if k == "int":
            v = self._number(value)
            if not (math.isfinite(v) and v == int(v)):
                raise SettingError(self.key, value, self._reason(value, "must be a whole number"))
            self._in_range(v)
            return int(v)
        if k == "bool":
            if isinstance(value, bool):
                return value
            if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1"):
                return True
            if isinstance(value, str) and value.lower() in ("false", "no", "off", "0"):
                return False
            raise SettingError(self.key, value, self._reason(repr(value), "must be true or false"))
        if k == "choice":
            if not isinstance(value, str) or value not in self.choices:
                raise SettingError(self.key, value, f"unknown {self.label} {value!r}; choose from "
                                   f"{', '.join(self.choices)}")  # fmt: skip
            return value
        if k == "floats":
            items = value.replace(",", " ").split() if isinstance(value, str) else list(value)
            items = [p for x in items for p in (str(x).replace(",", " ").split()
                                                 if isinstance(x, str) else [x])]  # fmt: skip
            if not 1 <= len(items) <= 1000:
                raise SettingError(self.key, value,
                                   self._reason(len(items), "needs 1 … 1000 values"))  # fmt: skip
            out = []
            for x in items:
                v = self._number(x)
                self._in_range(v, value)
                out.append(v)
            return tuple(out)
        if k == "switches":
            items = [value] if isinstance(value, str) else list(value)
            return tuple(_parse_switch(self, x) for x in items)
        if k == "text":
            if not isinstance(value, str):
                raise SettingError(self.key, value, self._reason(repr(value), "must be text"))
            if self.key == "session_id" and (not value or "/" in value or value in (".", "..")):
                raise SettingError(self.key, value,
                                   self._reason(repr(value), "must be a plain folder name"))
            return value
        raise AssertionError(f"unknown kind {k}")  # a schema bug, not bad input


def _show(value: Any, unit: str) -> str:
    if isinstance(value, float):
        return f"{_g(value)} {unit}".rstrip()
    return f"{value} {unit}".rstrip()


def _parse_switch(s: Setting, item: Any) -> tuple[float, str]:
    """``S:MODE`` or (S, MODE) → (S, MODE): S ≥ 0 seconds of device time, MODE a control law."""
    if isinstance(item, str):
        t, sep, mode = item.partition(":")
    elif isinstance(item, (list, tuple)) and len(item) == 2:
        t, sep, mode = item[0], ":", item[1]
    else:
        raise SettingError(s.key, item, f"{s.label} wants S:MODE, got {item!r}")
    try:
        t_s = float(t)
    except (TypeError, ValueError):
        t_s = math.nan
    if not sep or not math.isfinite(t_s) or t_s < 0:
        raise SettingError(s.key, item, f"{s.label} wants S:MODE with S ≥ 0 s, got {item!r}")
    if mode not in CONTROLLER_MODES:
        raise SettingError(s.key, item, f"{s.label} {item!r}: unknown mode {mode!r}; choose "
                           f"from {', '.join(CONTROLLER_MODES)}")  # fmt: skip
    return t_s, str(mode)


# --------------------------------------------------------------------------- the table
_HEAT = HEATING
_REF = REFERENCE_NAMES
_FF = ("ff", "ffpid")


def _protocol(key: str, label: str, help: str, **kw: Any) -> Setting:
    return Setting(f"protocol.{key}", label, help, "protocol", **kw)


def _controller(key: str, label: str, help: str, **kw: Any) -> Setting:
    return Setting(f"controller.{key}", label, help, "controller", **kw)


@dataclass(frozen=True)
class GainSet:
    """One PID's gains: ``law`` (pid, ffpid, ffpid_hold), the JSON key, components' keys."""

    law: str
    key: str  # controller.gains, …
    label: str
    units: tuple[str, str, str]
    cli_triple: str | None  # "--ffpid-gains KP KI KD" style option, or None (one per gain)

    @property
    def keys(self) -> tuple[str, str, str, str]:
        return tuple(f"{self.key}.{c}" for c in GAIN_COMPONENTS)  # type: ignore[return-value]


GAIN_COMPONENTS = ("kp", "ki", "kd", "d_filter_s")
GAIN_SETS: dict[str, GainSet] = {
    "pid": GainSet("pid", "controller.gains", "PID", ("W/mm", "W/(mm·s)", "W·s/mm"), None),
    "ffpid": GainSet("ffpid", "controller.ffpid_gains", "FF+PID",
                     ("mm/mm", "1/s", "s"), "--ffpid-gains"),  # fmt: skip
    "ffpid_hold": GainSet("ffpid_hold", "controller.ffpid_hold_gains", "FF+PID hold",
                          ("mm/mm", "1/s", "s"), "--ffpid-hold-gains"),  # fmt: skip
}
_GAIN_HELP = {
    "pid": "the PID law's gain on position (output: heating power)",
    "ffpid": "FF+PID's gain while the setpoint moves (output: a setpoint shift)",
    "ffpid_hold": "FF+PID's gain while the setpoint holds still",
}


def _gain_settings(gs: GainSet) -> list[Setting]:
    out = []
    prefix = {"pid": "", "ffpid": "ffpid-", "ffpid_hold": "ffpid-hold-"}[gs.law]
    modes = ("pid",) if gs.law == "pid" else ("ffpid",)
    for comp, unit, what in zip(GAIN_COMPONENTS[:3], gs.units, ("proportional", "integral",
                                                                  "derivative"), strict=True):
        out.append(Setting(
            f"{gs.key}.{comp}", f"{gs.label} gain {comp}",
            f"{what.capitalize()} gain: {_GAIN_HELP[gs.law]}.", "gains", unit=unit, min=0.0,
            max=100.0, optional=True, none_text="per-load table", modes=modes, live=True,
            decimals=3, step=0.01, cli=f"--{comp}" if gs.cli_triple is None else None,
            metavar=comp.upper(),
        ))  # fmt: skip
    out.append(Setting(
        f"{gs.key}.d_filter_s", f"{gs.label} derivative filter",
        f"Time constant of the first-order filter on {gs.label}'s derivative term.", "gains",
        unit="s", min=0.0, max=10.0, min_open=True, optional=True, none_text="per-load table",
        modes=modes, decimals=3, step=0.01, cli=f"--{prefix}d-filter-s",
    ))  # fmt: skip
    return out


_TABLE: list[Setting] = [
    # ---------------------------------------------------------------- load & wire
    Setting("load_kg", "load", "Hanging mass on the wire (recorded in the session).",
            "load_wire", unit="kg", default=2.0, min=0.0, min_open=True, max="max_load_kg",
            required=True, step=0.5),  # fmt: skip
    Setting("wire_preset", "wire", "Wire preset: geometry, material and rated current.",
            "load_wire", kind="choice", default="paper", choices=tuple(PRESETS), cli="--wire"),
    Setting("long_life_stress_mpa", "long-life stress",
            "Highest stress for a long cycle life; a heavier load needs confirmation "
            "(--allow-high-stress).", "load_wire", unit="MPa", min=0.0, max=2000.0,
            min_open=True, optional=True, none_text="the wire preset's", decimals=0, step=1.0),
    Setting("allow_high_stress", "allow high stress",
            "Run a load above the wire's long-life stress (recorded in the session).",
            "load_wire", kind="bool", default=False),
    # ---------------------------------------------------------------- protocol
    _protocol("name", "protocol", "Experiment: heating cycles, steps, ramps, or a position "
              "reference for a controller (staircase, sine, triangle; step is both).",
              kind="choice", default="cycles", choices=PROTOCOL_NAMES, cli="--protocol"),
    _protocol("cycles", "cycles", "Number of cycles (periods of a position reference).",
              kind="int", default=5, min=1, max=10_000, protocols=(*_HEAT, "ramp"),
              references=_REF, decimals=0, step=1, metavar="N"),
    _protocol("current_a", "current", "Heating current.", unit="A", default=1.0, min=0.0,
              max=HARD_LIMIT_A, protocols=(*_HEAT, "ramp"), decimals=3, step=0.05),
    _protocol("heat_s", "heat time", "Heating time per cycle.", unit="s", default=3.0, min=0.0,
              min_open=True, max=600.0, protocols=_HEAT),
    _protocol("cool_timeout_s", "max cool time", "Longest cooling time per cycle.", unit="s",
              default=15.0, min=0.0, min_open=True, max=3600.0, protocols=_HEAT),
    _protocol("min_cool_s", "min cool time", "Shortest cooling time before settling counts.",
              unit="s", default=3.0, min=0.0, max=3600.0, protocols=_HEAT),
    _protocol("settle_mm", "settle tolerance",
              "Cooling ends once the wire has stretched back (half the heating's stroke) and its "
              "position drifts less than this across the settle window.",
              unit="mm", default=0.005, min=0.0, min_open=True, max=10.0, protocols=_HEAT,
              decimals=4, step=0.001),
    _protocol("settle_window_s", "settle window", "Window over which settling is judged.",
              unit="s", default=1.0, min=0.0, min_open=True, max=600.0, protocols=_HEAT),
    _protocol("partial_cool_s", "incomplete: cool", "Cooling time before reheating (incomplete).",
              unit="s", default=2.0, min=0.0, min_open=True, max=600.0,
              protocols=("incomplete",)),
    _protocol("inner_heat_s", "inner: heat", "Heating pulse inside the transformation (inner).",
              unit="s", default=0.4, min=0.0, min_open=True, max=60.0, protocols=("inner",),
              step=0.05),
    _protocol("inner_cool_s", "inner: cool", "Cooling pulse inside the transformation (inner).",
              unit="s", default=0.8, min=0.0, min_open=True, max=60.0, protocols=("inner",),
              step=0.05),
    _protocol("levels_a", "current levels", "Current steps, each held for the hold time (step "
              "without a controller).", kind="floats", unit="A",
              default=(0.4, 0.8, 1.2, 0.8, 0.4, 0.0), min=0.0, max=HARD_LIMIT_A,
              protocols=("step",), decimals=3, metavar="A"),
    _protocol("hold_s", "hold time", "Time each current level is held (step).", unit="s",
              default=4.0, min=0.0, min_open=True, max=3600.0, protocols=("step",)),
    _protocol("ramp_s", "ramp time", "Ramp time each way, 0 → current → 0 (ramp).", unit="s",
              default=5.0, min=0.0, min_open=True, max=3600.0, protocols=("ramp",)),
    _protocol("amplitude_mm", "reference amplitude", "Amplitude of the position reference.",
              unit="mm", default=0.8, min=0.0, max=50.0, references=_REF),
    _protocol("offset_mm", "reference offset", "Centre of the position reference.", unit="mm",
              min=-1000.0, max=1000.0, optional=True, none_text="middle of the reachable stroke",
              references=_REF, decimals=3),
    _protocol("period_s", "reference period", "Period of the position reference.", unit="s",
              default=20.0, min=0.5, max=3600.0, references=_REF, step=1.0),
    _protocol("lead_in_s", "lead-in", "Hold at the start before the first period.", unit="s",
              default=8.0, min=0.0, max=600.0, references=_REF, step=1.0),
    _protocol("max_rise_mm_s", "max rise rate",
              "Limit on how fast the reference may lengthen the wire (natural cooling).",
              unit="mm/s", min=0.0, min_open=True, max=100.0, optional=True,
              none_text="no limit", references=_REF, decimals=3),
    # ---------------------------------------------------------------- controller
    _controller("mode", "controller", "Control law on the position reference: open_loop, pid, "
                "ff (feed-forward) or ffpid (FF+PID).", kind="choice", choices=CONTROLLER_MODES,
                optional=True, none_text="no controller: the protocol sets the current",
                live=True, cli="--controller"),
    _controller("switches", "law switch", "Switch the control law at S s of device time, "
                "e.g. 30:ff (repeatable).", kind="switches", default=(), cli="--switch-at",
                metavar="S:MODE"),
    _controller("model", "feed-forward model", "Loop model the feed-forward inverts.",
                kind="choice", default="sigmoid", choices=FF_MODELS, modes=_FF,
                cli="--ff-model"),
    _controller("adapt", "adaptation", "Adapt the feed-forward's model online.", kind="bool",
                default=True, modes=_FF, cli="--no-adapt", cli_flag_value=False),
    _controller("observer", "temperature observer",
                "Correct the feed-forward's temperature from the measured position.",
                kind="bool", default=True, modes=_FF, cli="--no-observer",
                cli_flag_value=False),
    _controller("lead_s", "feed-forward lead", "Lead of the feed-forward.", unit="s", min=0.0,
                max=5.0, optional=True, none_text="each branch's identified kinetic lag",
                modes=_FF, decimals=3, cli="--ff-lead-s"),
    _controller("horizon_s", "feed-forward horizon", "Horizon of the heat-balance inverse.",
                unit="s", default=0.05, min=0.0, min_open=True, max=1.0, modes=_FF,
                decimals=3, step=0.01, cli="--ff-horizon-s"),
    _controller("preview_slack_s", "preview slack", "How far ahead the feed-forward previews "
                "the reference beyond its lead.", unit="s", default=0.5, min=0.0, max=10.0,
                modes=_FF, cli="--ff-preview-slack-s"),
    _controller("reversal_deadband_mm", "reversal deadband",
                "Setpoint move back that counts as a reversal.", unit="mm", default=0.02,
                min=0.0, max=1.0, modes=_FF, decimals=3, step=0.01),
    _controller("ffpid_limit_mm", "FF+PID shift limit",
                "Largest setpoint shift FF+PID's PID may add.", unit="mm", default=1.0,
                min=0.0, min_open=True, max=5.0, modes=("ffpid",)),
    _controller("t_ceiling_c", "temperature ceiling", "Highest wire temperature the "
                "feed-forward plans for (also 10 °C under the temperature limit).", unit="°C",
                default=120.0, min=40.0, max=200.0, modes=(*_FF, "pid"), decimals=0,
                step=1.0, cli="--t-ceiling-c"),
    _controller("cooling_limit", "cooling limit", "Limit the reference's rise to the wire's "
                "natural cooling rate.", kind="bool", default=False),
    # ---------------------------------------------------------------- gains
    *(s for gs in GAIN_SETS.values() for s in _gain_settings(gs)),
    # ---------------------------------------------------------------- limits
    Setting("current_limit_a", "current limit", "Interlock on the commanded current (also at "
            f"most {CURRENT_MARGIN:g} × the wire's rated current and the driver's own limit).",
            "limits", unit="A", default=2.0, min=0.0, min_open=True, max=HARD_LIMIT_A,
            decimals=3, step=0.05),  # fmt: skip
    Setting("temperature_limit_c", "max wire temperature",
            "Interlock on the estimated wire temperature.", "limits", unit="°C", default=160.0,
            min=40.0, max=250.0, decimals=0, step=1.0),
    Setting("position_min_mm", "position min", "Interlock: the position may not fall below.",
            "limits", unit="mm", min=-1000.0, max=1000.0, optional=True, none_text="no limit",
            decimals=3),
    Setting("position_max_mm", "position max", "Interlock: the position may not rise above.",
            "limits", unit="mm", min=-1000.0, max=1000.0, optional=True, none_text="no limit",
            decimals=3),
    Setting("max_load_kg", "max load", "Heaviest load this bench may carry; a heavier load "
            "setting is refused.", "limits", unit="kg", default=10.0, min=0.0, min_open=True,
            max=10.0, step=0.5),
    Setting("max_duration_s", "max duration", "The session is aborted after this long.",
            "limits", unit="s", default=3600.0, min=0.0, min_open=True, max=1e6, decimals=0,
            step=60.0),
    # ---------------------------------------------------------------- loop
    Setting("rate_hz", "loop rate", "Control loop rate.", "loop", unit="Hz", default=200.0,
            min=1.0, max=2000.0, decimals=0, step=10.0),
    Setting("time_scale", "time scale", "Device time per wall time: above 1 only against a mock "
            "bench run faster than real time (smabench run: set by --mock-speed).", "loop",
            default=1.0, min=0.1, max=100.0, decimals=1, step=1.0, cli=None),
    # resistance sensing (issue 26): optional, the session is as before without it
    Setting("probe_current_a", "probe current", "Current the driver holds while its output is "
            "enabled and the setpoint is lower (SET_PROBE), so the wire's resistance is measured "
            "while it cools; its heat is part of the session (0: off).", "loop", unit="A",
            default=0.0, min=0.0, max=PROBE_MAX_A, decimals=3, step=0.01),
    Setting("selfsense", "self-sense calibration", "Calibration JSON from `smabench selfsense "
            "calibrate`: every tick estimates the position from the wire's resistance (two more "
            "columns: the resistance in ohm and the estimated position in mm; the calibration "
            "goes into session.json).", "loop",
            kind="text", optional=True, none_text="none: no estimate", metavar="CAL.json"),
    Setting("feedback", "position feedback", "The controller's measured position: the laser's, "
            "or the one estimated from the wire's resistance (needs a self-sense calibration "
            "and a probe current).", "loop", kind="choice", default="laser",
            choices=FEEDBACK_SOURCES, live=True),
    Setting("fallback", "feedback fallback", "While the laser's reading is invalid or the "
            "sensor does not answer, control on the position estimated from the wire's "
            "resistance (flagged rows; needs a self-sense calibration and a probe current).",
            "loop", kind="choice", choices=("resistance",), optional=True,
            none_text="none: the session ends when the laser is lost"),
    # ---------------------------------------------------------------- session
    Setting("out_dir", "sessions folder", "Parent folder of the session.", "session",
            kind="text", default="sessions", cli="--out", metavar="DIR"),
    Setting("session_id", "session name", "Session folder name.", "session", kind="text",
            optional=True, none_text="time, protocol and load", metavar="NAME"),
]

SETTINGS: dict[str, Setting] = {s.key: s for s in _TABLE}
assert len(SETTINGS) == len(_TABLE), "duplicate setting key"


def get(key: str) -> Setting:
    """The setting ``key``; KeyError with the known keys otherwise."""
    try:
        return SETTINGS[key]
    except KeyError:
        raise KeyError(f"no setting {key!r}") from None


def default(key: str) -> Any:
    """The declared default of ``key`` (for the session dataclasses)."""
    return SETTINGS[key].default


def defaults(prefix: str = "") -> dict[str, Any]:
    """Defaults of every setting (under ``prefix``), keyed by the key without the prefix."""
    return {k[len(prefix):]: s.default for k, s in SETTINGS.items() if k.startswith(prefix)}


def fields(group: str, protocol: str | None = None, closed_loop: bool | None = None,
           mode: str | None = None) -> list[Setting]:  # fmt: skip
    """The settings of ``group`` in display order (see the module docstring)."""
    if group not in GROUPS:
        raise KeyError(f"no group {group!r}; groups: {', '.join(GROUPS)}")
    out = []
    for s in _TABLE:
        if s.group != group or not s.uses(protocol, closed_loop):
            continue
        if mode is not None and s.modes and mode not in s.modes:
            continue
        out.append(s)
    return out


def check_value(key: str, value: Any) -> Any:
    """``value`` of ``key`` in its type, or SettingError (naming setting, value, range)."""
    return get(key).check(value)


def error_for(key: str, value: Any) -> str | None:
    """The one-line reason ``value`` is refused for ``key``, or None when it is fine."""
    try:
        check_value(key, value)
    except SettingError as exc:
        return str(exc)
    return None


def check_values(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Each ``prefix + name`` checked; returns the parsed values (same keys)."""
    return {name: check_value(prefix + name, v) for name, v in values.items()}


# --------------------------------------------------------------------------- JSON
_GROUPED = ("protocol", "controller")


def values_from_mapping(cfg: Mapping[str, Any], complete: bool = True) -> dict[str, Any]:
    """The runtime's JSON start message → flat ``{key: value}``, each value checked.

    ``{"load_kg": 2, "protocol": {"name": "sine", …}, "controller": {"mode": "pid",
    "gains": [kp, ki, kd] | {"kp": …} | null, …} | null}``; unknown keys are refused. With
    ``complete`` the missing settings take their defaults (a required one missing is refused);
    the controller's only when a controller is given (its law then defaults to ``ffpid``)."""
    if not isinstance(cfg, Mapping):
        raise SettingError("settings", cfg, "settings must be a JSON object")
    flat: dict[str, Any] = {}
    for name, v in cfg.items():
        if name in _GROUPED and (v is None or isinstance(v, Mapping)):
            if v is None:
                continue
            for sub, sv in v.items():
                key = f"{name}.{sub}"
                gs = _gain_set_by_key(key)
                if gs is not None:
                    flat.update(_gain_values(gs, sv))
                elif key in SETTINGS:
                    flat[key] = sv
                else:
                    raise SettingError(key, sv, "unknown setting {name}")
        elif name in SETTINGS and name.split(".")[0] not in _GROUPED:
            flat[name] = v
        elif name in _GROUPED:
            raise SettingError(name, v, f"{name} must be an object of settings, got {v!r}")
        else:
            raise SettingError(name, v, "unknown setting {name}")
    values = {k: check_value(k, v) for k, v in flat.items()}
    if complete:
        with_controller = cfg.get("controller") is not None
        for k, s in SETTINGS.items():
            if k in values:
                continue
            if s.required:
                raise SettingError(k, None, f"{s.label} must be given")
            if k.startswith("controller.") and not with_controller:
                continue
            values[k] = s.default
        if with_controller and values.get("controller.mode") is None:
            values["controller.mode"] = "ffpid"
    return values


def _gain_set_by_key(key: str) -> GainSet | None:
    return next((g for g in GAIN_SETS.values() if g.key == key), None)


def _gain_values(gs: GainSet, v: Any) -> dict[str, Any]:
    """A gain set given as [kp, ki, kd(, d_filter_s)], {kp: …}, or null (per-load table)."""
    if v is None:
        return dict.fromkeys(gs.keys)
    if isinstance(v, Mapping):
        unknown = set(v) - set(GAIN_COMPONENTS)
        if unknown:
            raise SettingError(gs.key, v, f"unknown {gs.label} gain {sorted(unknown)[0]!r}")
        return {f"{gs.key}.{c}": v.get(c) for c in GAIN_COMPONENTS}
    if isinstance(v, (list, tuple)) and 2 <= len(v) <= 4:
        return {f"{gs.key}.{c}": (v[i] if i < len(v) else None)
                for i, c in enumerate(GAIN_COMPONENTS)}  # fmt: skip
    raise SettingError(gs.key, v, f"{gs.label} gains must be [kp, ki, kd] or an object, "
                       f"got {v!r}")  # fmt: skip


def to_mapping(values: Mapping[str, Any]) -> dict[str, Any]:
    """Flat values → the JSON shape :func:`values_from_mapping` reads (gain sets as objects,
    ``None`` for a set wholly from the per-load table; tuples as lists)."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        if isinstance(v, tuple):
            v = [list(x) if isinstance(x, tuple) else x for x in v]
        parts = k.split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = v
    ctl = out.get("controller")
    if isinstance(ctl, dict):
        for gs in GAIN_SETS.values():
            name = gs.key.split(".")[1]
            if name in ctl and all(x is None for x in ctl[name].values()):
                ctl[name] = None
    return out


# --------------------------------------------------------------------------- command line
def add_cli_options(parser: argparse.ArgumentParser,
                    groups: Iterable[str] = tuple(GROUPS)) -> None:  # fmt: skip
    """Add every setting of ``groups`` as an option, one argument group per settings group.

    Values arrive as text (``default=None`` = not given) and are parsed and checked by
    :func:`values_from_args`, so a bad value is one clear line, never an argparse usage dump."""
    for group in groups:
        g = parser.add_argument_group(GROUPS[group].lower())
        triples_done: set[str] = set()
        for s in _TABLE:
            if s.group != group:
                continue
            gs = _gain_set_of(s)
            if gs is not None and gs.cli_triple and s.key.rsplit(".", 1)[1] in ("kp", "ki", "kd"):
                if gs.law not in triples_done:
                    triples_done.add(gs.law)
                    kp = SETTINGS[gs.keys[0]]
                    g.add_argument(
                        gs.cli_triple, nargs=3, metavar=("KP", "KI", "KD"), default=None,
                        dest=f"setting__gains__{gs.law}",
                        help=f"{gs.label} gains: {', '.join(gs.units)} [each "
                        f"{_g(kp.min)} … {_g(kp.max_value)}; default {kp.none_text}]",
                    )  # fmt: skip
                continue
            for name in s.cli_names():
                g.add_argument(name, dest=s.dest, default=None, **_cli_kwargs(s))


def _gain_set_of(s: Setting) -> GainSet | None:
    return next((g for g in GAIN_SETS.values() if s.key.startswith(g.key + ".")), None)


def _cli_kwargs(s: Setting) -> dict[str, Any]:
    text = s.help.rstrip(".")
    bits = [b for b in (s.range_text if s.kind != "choice" else "",
                        "" if s.required else f"default {s.default_text}") if b]  # fmt: skip
    uses = s.protocols + tuple(p for p in s.references if p not in s.protocols)
    if s.group == "protocol" and uses:
        bits.append("for " + ", ".join(uses))
    if s.kind == "choice":
        text += f" {{{', '.join(s.choices)}}}"
    help_text = f"{text} [{'; '.join(bits)}]".replace("%", "%%")
    if s.required:
        help_text = "required: " + help_text
    if s.kind == "bool":
        if not s.cli_flag_value:
            help_text = f"switch off the {s.label}: " + help_text[0].lower() + help_text[1:]
        return {"action": "store_const", "const": s.cli_flag_value, "help": help_text}
    kw: dict[str, Any] = {"help": help_text, "metavar": s.metavar or _metavar(s)}
    if s.kind == "floats":
        kw["nargs"] = "+"
    elif s.kind == "switches":
        kw["action"] = "append"
    return kw


def _metavar(s: Setting) -> str:
    if s.kind == "choice":
        return "NAME"
    if s.kind == "int":
        return "N"
    unit = {"°C": "C", "mm/s": "MM_S", "": "X"}.get(s.unit, s.unit)
    return unit.upper().replace("/", "_").replace("(", "").replace(")", "").replace("·", "")


def values_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The options given on the command line (not the defaults), parsed and checked, keyed by
    setting key; a bad value or a required option missing raises SettingError (use
    :func:`cli_error` for the message)."""
    given: dict[str, Any] = {}
    for s in _TABLE:
        if s.required and s.cli_names() and getattr(args, s.dest, None) is None:
            raise SettingError(s.key, None, f"{s.label} must be given: {{name}} "
                               f"{s.metavar or _metavar(s)}")  # fmt: skip
    for s in _TABLE:
        v = getattr(args, s.dest, None)
        if v is not None:
            given[s.key] = s.check(v)
    for gs in GAIN_SETS.values():
        v = getattr(args, f"setting__gains__{gs.law}", None)
        if v is not None:
            for key, x in zip(gs.keys[:3], v, strict=True):
                given[key] = check_value(key, x)
    return given


def cli_error(exc: SettingError) -> str:
    """The message of a refused setting for the command line (names the option)."""
    s = SETTINGS.get(exc.key)
    gs = _gain_set_of(s) if s is not None else None
    if gs is not None and gs.cli_triple and exc.key.rsplit(".", 1)[1] != "d_filter_s":
        return exc.naming(gs.cli_triple)
    return exc.for_cli()


# --------------------------------------------------------------------------- cross-setting rules
def wire_of(values: Mapping[str, Any]) -> Wire:
    return PRESETS[values.get("wire_preset") or default("wire_preset")]


def long_life_stress(wire: Wire, override_mpa: float | None = None) -> float:
    """The long-life stress that applies, MPa: the setting when given, else the wire's."""
    return wire.long_life_stress_mpa if override_mpa is None else float(override_mpa)


@dataclass(frozen=True)
class StressCheck:
    """Whether a load needs the operator's confirmation (above the wire's long-life stress)."""

    load_kg: float
    stress_mpa: float
    limit_mpa: float
    limit_load_kg: float  # the load at the limit, kg
    needs_confirmation: bool
    message: str  # for a dialog: no command-line words


def stress_check(load_kg: float, wire_preset: str = "paper",
                 long_life_stress_mpa: float | None = None) -> StressCheck:  # fmt: skip
    """The load's stress against the wire's long-life stress (see HIGH_STRESS_TOLERANCE)."""
    wire = PRESETS[wire_preset]
    limit = long_life_stress(wire, long_life_stress_mpa)
    stress = float(stress_mpa(load_kg, wire))
    needs = stress > limit * (1.0 + HIGH_STRESS_TOLERANCE)
    limit_load = load_kg_for_stress(limit, wire)
    if needs:
        msg = (f"A load of {_g(load_kg)} kg puts {stress:.0f} MPa on the {wire.diameter_mm:.2f} mm "
               f"wire, above its long-life stress of {limit:.0f} MPa (about {limit_load:.2f} kg): "
               "the wire may fatigue or stretch for good. Run it anyway?")
    else:
        msg = (f"{_g(load_kg)} kg puts {stress:.0f} MPa on the wire, within its long-life stress "
               f"of {limit:.0f} MPa.")
    return StressCheck(float(load_kg), stress, limit, limit_load, needs, msg)


def check_stress(values: Mapping[str, Any]) -> StressCheck:
    """SettingError (key ``allow_high_stress``) when the load is above the long-life stress and
    not allowed; the check otherwise."""
    sc = stress_check(values["load_kg"], values.get("wire_preset") or default("wire_preset"),
                      values.get("long_life_stress_mpa"))  # fmt: skip
    if sc.needs_confirmation and not values.get("allow_high_stress"):
        raise SettingError(
            "allow_high_stress", False,
            f"load {_g(sc.load_kg)} kg puts {sc.stress_mpa:.0f} MPa on the "
            f"{PRESETS[values.get('wire_preset') or default('wire_preset')].diameter_mm:.2f} mm "
            "wire, above its "
            f"long-life stress of {sc.limit_mpa:.0f} MPa (about {sc.limit_load_kg:.2f} kg); "
            "to run it anyway, give {name}",
        )
    return sc


def effective_current_limit_a(
    values: Mapping[str, Any], device_limit_a: float | None = None
) -> tuple[float, str]:
    """The current the protocol may ask for, A, and what sets it: the current limit, the wire's
    rated current or the driver's limit, whichever is lowest."""
    options = [(values.get("current_limit_a", default("current_limit_a")), "the current limit"),
               (wire_of(values).max_current_a, "the wire's rated current")]  # fmt: skip
    if device_limit_a is not None:
        options.append((device_limit_a, "the driver's limit"))
    return min(options, key=lambda o: o[0])


def check_current_limit(current_limit_a: float, wire: Wire) -> None:
    """The current limit against its range and the wire's rated current × CURRENT_MARGIN."""
    check_value("current_limit_a", current_limit_a)
    ceiling = CURRENT_MARGIN * wire.max_current_a
    if current_limit_a > ceiling:
        raise SettingError("current_limit_a", current_limit_a,
                           f"current limit must be in (0, {_g(ceiling)}] A ({CURRENT_MARGIN:g} × "
                           f"the wire's rated {_g(wire.max_current_a)} A), got "
                           f"{_g(current_limit_a)} A")  # fmt: skip


def check_protocol(proto: Mapping[str, Any], max_current_a: float, closed_loop: bool = False,
                   limit_name: str = "the current limit") -> None:  # fmt: skip
    """A protocol's settings (names without ``protocol.``): ranges, the protocol against the
    loop (a controller needs a reference), and its currents against ``max_current_a``."""
    check_values(proto, "protocol.")
    name = proto.get("name", default("protocol.name"))
    if closed_loop and name not in REFERENCE_NAMES:
        raise SettingError("protocol.name", name,
                           f"protocol {name!r} is open loop; with a controller choose a "
                           f"reference: {', '.join(REFERENCE_NAMES)}")  # fmt: skip
    if not closed_loop and name not in OPEN_LOOP_NAMES:
        raise SettingError("protocol.name", name,
                           f"protocol {name!r} is a position reference: it needs a controller "
                           "(pid, ff or ffpid)")  # fmt: skip
    if closed_loop:
        return
    keys = ["current_a"] if name != "step" else ["levels_a"]
    for k in keys:
        vals = proto.get(k, default(f"protocol.{k}"))
        for c in vals if isinstance(vals, tuple | list) else (vals,):
            if c > max_current_a:
                s = SETTINGS[f"protocol.{k}"]
                raise SettingError(s.key, c, f"{s.label} {_g(c)} A is outside 0 … "
                                   f"{_g(max_current_a)} A, {limit_name}")  # fmt: skip


def check_run(values: Mapping[str, Any], device_limit_a: float | None = None) -> StressCheck:
    """Every rule across settings of a session (``values`` flat and complete, as from
    :func:`values_from_mapping`); returns the stress check. SettingError on the first refusal."""
    for k, v in values.items():
        check_value(k, v)
    if values["load_kg"] > values["max_load_kg"]:
        raise SettingError("load_kg", values["load_kg"],
                           f"load {_g(values['load_kg'])} kg is above the max load "
                           f"{_g(values['max_load_kg'])} kg")  # fmt: skip
    wire = wire_of(values)
    check_current_limit(values["current_limit_a"], wire)
    lo, hi = values.get("position_min_mm"), values.get("position_max_mm")
    if lo is not None and hi is not None and not lo < hi:
        raise SettingError("position_max_mm", hi, f"position max {_g(hi)} mm must be above "
                           f"position min {_g(lo)} mm")  # fmt: skip
    proto = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("protocol.")}
    closed = values.get("controller.mode") is not None
    limit_a, limit_name = effective_current_limit_a(values, device_limit_a)
    check_protocol(proto, limit_a, closed_loop=closed, limit_name=limit_name)
    return check_stress(values)


# --------------------------------------------------------------------------- device options
_DEVICE_OPTIONS: list[Setting] = [
    Setting("sensor_timeout_s", "sensor request timeout", "Per-request Modbus timeout in the "
            "loop; a later reading is flagged.", "devices", unit="s", default=0.05, min=0.001,
            max=5.0, decimals=3),  # fmt: skip
    Setting("mock.seed", "mock seed", "Seed of the mock sensor's noise.", "devices", kind="int",
            default=0, min=0, max=1e9, decimals=0),  # fmt: skip
    Setting("mock.adapter_latency_ms", "adapter latency", "The mock's sensor holds every answer "
            "this long, as an FTDI USB/RS-485 adapter's latency timer does.", "devices",
            unit="ms", default=0.0, min=0.0, max=1000.0),  # fmt: skip
    Setting("mock.wire_noise_v", "wire-voltage noise", "The mock driver's wire-voltage "
            "channel (the ADS1115 on the Kelvin leads) gets this Gaussian noise, RMS at the wire, "
            "drawn per 1 ms step (the emulated firmware: per conversion; 0: none).", "devices",
            unit="V",
            default=0.0, min=0.0, max=0.01, decimals=6),  # fmt: skip
    Setting("mock.tcp_port", "Modbus TCP port", "The mock sensor's TCP port (0: any free one).",
            "devices", kind="int", default=0, min=0, max=65535, decimals=0),  # fmt: skip
    Setting("mock.ready_timeout_s", "mock readiness timeout", "Longest wait for a started mock "
            "bench to print its ports (env SMABENCH_MOCK_READY_TIMEOUT_S).", "devices",
            unit="s", default=60.0, min=0.0, min_open=True, max=3600.0),  # fmt: skip
    Setting("sim.noise_mm", "sensor noise", "Standard deviation of the simulated sensor noise.",
            "devices", unit="mm", default=0.002, min=0.0, max=10.0, decimals=4),  # fmt: skip
    Setting("sim.seed", "noise seed", "Seed of the simulated noise.", "devices", kind="int",
            default=0, min=0, max=1e9, decimals=0),  # fmt: skip
]
DEVICE_OPTIONS: dict[str, Setting] = {s.key: s for s in _DEVICE_OPTIONS}
"""Options of the devices and simulations around a session (not run settings: neither the GUI's
fields nor the runtime's JSON carry them), declared here so that their ranges live in one place
too; command lines use them through :func:`arg_type`."""


def arg_type(key: str) -> Any:
    """An argparse ``type=`` for the setting or device option ``key``: the value in its type,
    or ``ArgumentTypeError`` with the one-line reason (NaN and infinities are never in range)."""
    s = DEVICE_OPTIONS.get(key) or get(key)

    def parse(text: str) -> Any:
        try:
            return s.check(text)
        except SettingError as exc:
            raise argparse.ArgumentTypeError(exc.reason) from None

    parse.__name__ = s.label
    return parse


def add_setting_option(parser: argparse.ArgumentParser, name: str, key: str,
                       default: Any = None, why: str = "") -> None:  # fmt: skip
    """``name`` (e.g. ``--current-a``) on a command outside a run's settings (``simulate``,
    ``demo``): its type, range, unit and help are the setting's (or device option's) ``key``;
    ``default``: this command's own, when it differs from the schema's, said with ``why``."""
    s = DEVICE_OPTIONS.get(key) or get(key)
    if default is None:
        default, own = s.default, ""
    else:
        default, own = s.check(default), f" here{': ' + why if why else ''}"
    shown = _show(default, s.unit) if s.kind != "choice" else str(default)
    text = s.help.rstrip(".")
    bits = [b for b in (s.range_text if s.kind != "choice" else "", f"default {shown}{own}") if b]
    parser.add_argument(name, type=arg_type(key), default=default, metavar=s.metavar or _metavar(s),
                        help=f"{text} [{'; '.join(bits)}]".replace("%", "%%"))  # fmt: skip
