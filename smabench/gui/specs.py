"""The GUI's fields as :class:`~smabench.gui.fields.FieldSpec`: which settings exist, their range,
unit, help, which protocols use them and whether they may change while a session runs.

The settings schema (``smabench.settings``) is the one place for these facts; :func:`field_specs`
reads it when it is installed. Until then (the schema is being written at the same time) the
table below mirrors the checks in ``RunSettings.validate`` and ``ProtocolSettings.validate``.
"""

from __future__ import annotations

import logging

from smabench.gui.fields import FieldSpec
from smabench.physics.wire import PAPER_WIRE
from smabench.protocols import REFERENCE_NAMES

log = logging.getLogger(__name__)

THERMAL = ("cycles", "incomplete", "inner")
CYCLED = ("cycles", "incomplete", "inner", "ramp", *REFERENCE_NAMES)
GAIN_LAWS = (("pid", "PID", ("W/mm", "W/(mm·s)", "W·s/mm")),
             ("ffpid", "FF+PID tracking", ("mm/mm", "1/s", "s")),
             ("ffpid_hold", "FF+PID hold", ("mm/mm", "1/s", "s")))  # fmt: skip


def _fallback() -> list[FieldSpec]:
    wire_max_a = PAPER_WIRE.max_current_a * 1.25
    f = FieldSpec
    specs = [
        f("load_kg", "load", 2.0, 0.0, 10.0, "kg", "hanging mass on the wire", lo_open=True,
          group="experiment"),
        f("cycles", "cycles", 3, 1, 10000, "", "how many cycles (periods of a reference)",
          integer=True, protocols=CYCLED, group="experiment"),
        f("current_a", "current", 1.4, 0.0, wire_max_a, "A", "heating current",
          protocols=(*THERMAL, "ramp"), group="experiment"),
        f("heat_s", "heat time", 3.0, 0.0, 600.0, "s", "heating time of each cycle",
          lo_open=True, protocols=THERMAL, group="experiment"),
        f("cool_timeout_s", "max cool time", 15.0, 0.0, 3600.0, "s",
          "cooling ends when the position settles, at the latest after this", lo_open=True,
          protocols=THERMAL, group="experiment"),
        f("partial_cool_s", "incomplete: cool", 2.0, 0.0, 600.0, "s",
          "cooling time before reheating (incomplete cycles)", lo_open=True,
          protocols=("incomplete",), group="experiment"),
        f("inner_heat_s", "inner: heat", 0.4, 0.0, 60.0, "s", "heat pulse of an inner loop",
          lo_open=True, protocols=("inner",), group="experiment"),
        f("inner_cool_s", "inner: cool", 0.8, 0.0, 60.0, "s", "cool pause of an inner loop",
          lo_open=True, protocols=("inner",), group="experiment"),
        f("hold_s", "hold per level", 4.0, 0.0, 3600.0, "s", "time at each current level",
          lo_open=True, protocols=("step",), group="experiment"),
        f("ramp_s", "ramp time", 5.0, 0.0, 3600.0, "s", "time of each ramp up (and down)",
          lo_open=True, protocols=("ramp",), group="experiment"),
        f("amplitude_mm", "reference amplitude", 0.8, 0.0, 50.0, "mm",
          "half the peak-to-peak of the position reference", protocols=REFERENCE_NAMES,
          group="experiment"),
        f("offset_mm", "reference offset", None, 0.0, 60.0, "mm", "centre of the reference",
          optional=True, empty_text="middle of the stroke", protocols=REFERENCE_NAMES,
          group="experiment"),
        f("period_s", "reference period", 20.0, 0.5, 3600.0, "s", "one period of the reference",
          protocols=REFERENCE_NAMES, group="experiment"),
        f("lead_in_s", "lead-in hold", 8.0, 0.0, 600.0, "s",
          "hold at the start of the reference", protocols=REFERENCE_NAMES, group="experiment"),
        # limits: checked every tick by the runtime
        f("current_limit_a", "current limit", 2.0, 0.0, wire_max_a, "A",
          "the runtime stops the session when more current is asked for; the driver clamps to "
          "it", lo_open=True, group="limits"),
        f("temperature_limit_c", "temperature limit", 160.0, 40.0, 250.0, "°C",
          "estimated wire temperature that stops the session", group="limits"),
        f("position_min_mm", "lowest position", None, -100.0, 100.0, "mm",
          "the session stops below this position", optional=True, empty_text="no limit",
          group="limits"),
        f("position_max_mm", "highest position", None, -100.0, 100.0, "mm",
          "the session stops above this position", optional=True, empty_text="no limit",
          group="limits"),
        f("max_duration_s", "maximum duration", 3600.0, 1.0, 7 * 86400.0, "s",
          "the session stops after this long", group="limits"),
        # controller: may change live
        f("open_loop_current_a", "open-loop current", 0.0, 0.0, wire_max_a, "A",
          "current held when a running controller session is switched to Open loop",
          live=True, group="controller"),
    ]
    for law, title, units in GAIN_LAWS:
        for k, unit in zip(("kp", "ki", "kd"), units, strict=True):
            specs.append(f(f"{law}_{k}", f"{title} {k.capitalize()}", 0.0, 0.0, 100.0, unit,
                           f"{title}: {k} ({unit})", live=True, group=f"gains:{law}"))  # fmt: skip
    # connection (only while not connected)
    specs += [
        f("mock_speed", "mock speed", 1.0, 1.0, 10.0, "×",
          "the mock bench runs this much faster than real time", group="mock"),
        f("sensor_tcp_port", "TCP port", 502, 1, 65535, "", "Modbus TCP port of the sensor",
          integer=True, group="tcp"),
        f("sensor_unit", "unit id", 1, 1, 247, "", "Modbus unit (device) id of the sensor",
          integer=True, group="real"),
    ]
    return specs


def field_specs() -> dict[str, FieldSpec]:
    """Every field by name (from the settings schema when it is installed)."""
    try:
        from smabench import settings as schema  # noqa: F401
    except ImportError:
        return {s.name: s for s in _fallback()}
    return {s.name: s for s in _from_schema(schema)}


def _from_schema(schema) -> list[FieldSpec]:
    """Map the schema's declarations onto FieldSpec (unknown shapes: the fallback table)."""
    decls = getattr(schema, "SETTINGS", None) or getattr(schema, "FIELDS", None)
    if not decls:
        log.info("settings schema has no SETTINGS table yet; using the GUI's table")
        return _fallback()
    by_name = {s.name: s for s in _fallback()}
    items = decls.values() if isinstance(decls, dict) else decls
    for d in items:
        name = getattr(d, "name", None)
        key = name.split(".")[-1] if isinstance(name, str) else None
        if key not in by_name:
            continue
        old = by_name[key]
        lo, hi = getattr(d, "min", old.lo), getattr(d, "max", old.hi)
        by_name[key] = FieldSpec(
            name=key, label=old.label,
            default=getattr(d, "default", old.default), lo=lo, hi=hi,
            unit=getattr(d, "unit", old.unit) or old.unit, help=getattr(d, "help", old.help),
            integer=old.integer, optional=old.optional, empty_text=old.empty_text,
            lo_open=old.lo_open, live=bool(getattr(d, "live", old.live)),
            protocols=tuple(getattr(d, "protocols", old.protocols) or old.protocols),
            group=old.group,
        )  # fmt: skip
    return list(by_name.values())


def needs_high_stress_confirmation(load_kg: float) -> str:
    """'' or the sentence asking the operator to confirm a load above the wire's long-life
    stress (from the schema when it has the check)."""
    try:
        from smabench import settings as schema
    except ImportError:
        schema = None
    fn = getattr(schema, "needs_high_stress_confirmation", None) if schema else None
    if fn is not None:
        out = fn(load_kg)
        return out if isinstance(out, str) else ("high stress" if out else "")
    from smabench.physics.wire import stress_mpa

    stress = float(stress_mpa(load_kg, PAPER_WIRE))
    if stress > 172.0:
        return (f"{load_kg:g} kg puts {stress:.0f} MPa on the wire, above the 172 MPa it takes "
                "for a long life. Run with this load anyway?")  # fmt: skip
    return ""


def fields_for_protocol(specs: dict[str, FieldSpec], protocol: str) -> set[str]:
    """Names of the experiment fields the protocol reads."""
    return {n for n, s in specs.items() if s.group == "experiment"
            and (not s.protocols or protocol in s.protocols)}  # fmt: skip

