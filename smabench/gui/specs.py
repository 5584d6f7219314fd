"""What the GUI shows of the settings schema (:mod:`smabench.settings`), and the few fields that
are not run settings (how to reach the devices), declared the same way.

The schema is the one place for ranges, units, help, which protocol or control law uses a
setting and whether it may change during a run; this module only chooses which of them the
operator's window shows, and in which tab.
"""

from __future__ import annotations

from smabench import settings as schema
from smabench.settings import GAIN_SETS, Setting

EXPERIMENT_GROUPS = ("load_wire", "protocol")
HIDDEN = {
    "allow_high_stress",  # asked in a dialog when the load needs it
    "protocol.name",  # the protocol drop-down
    "controller.mode",  # the mode buttons
    "controller.switches",  # switching is done live with the mode buttons
    "time_scale",  # follows the mock bench's speed
    "out_dir",  # the Sessions tab's folder
    "session_id",  # named by time, protocol and load
}
SELFSENSE_KEYS = ("probe_current_a", "selfsense", "feedback", "fallback")
"""Resistance sensing (issue 26, schema group ``loop``): shown under their own heading; the
calibration file with a button to choose it; ``feedback`` switches live in a session with a
calibration."""
GAIN_LAWS = tuple((law, gs.label, gs.units) for law, gs in GAIN_SETS.items())

# not run settings: how the devices are reached (shown only while not connected)
CONNECTION: dict[str, Setting] = {
    s.key: s
    for s in (
        Setting("mock_speed", "mock speed", "The mock bench runs this much faster than real "
                "time (device time per wall time).", "connection", unit="×", default=1.0,
                min=1.0, max=10.0, decimals=0, step=1.0),
        Setting("sensor_tcp_port", "TCP port", "Modbus TCP port of the displacement sensor.",
                "connection", kind="int", default=502, min=1, max=65535, decimals=0),
        Setting("sensor_unit", "unit id", "Modbus unit (device) id of the displacement sensor.",
                "connection", kind="int", default=1, min=1, max=247, decimals=0),
    )
}  # fmt: skip
OPEN_LOOP_CURRENT = Setting(
    "open_loop_current_a", "open-loop current", "Current held when a running controller session "
    "is switched to Open loop (at most the current limit).", "controller", unit="A",
    default=0.0, min=0.0, max="current_limit_a", decimals=3, step=0.05, live=True,
)  # fmt: skip
FIT_CYCLE = Setting("fit_cycle", "cycle", "Cycle to fit, counted from 1.", "fit", kind="int",
                    min=1, max=1_000_000, optional=True, none_text="last", decimals=0)


def shown(group: str) -> list[Setting]:
    """The settings of a schema group the window shows (display order)."""
    return [s for s in schema.fields(group) if s.key not in HIDDEN]


def protocol_uses(setting: Setting, protocol: str, closed_loop: bool) -> bool:
    """Whether the field belongs on screen for this protocol (and loop)."""
    return setting.uses(protocol, closed_loop)


def mode_uses(setting: Setting, mode: str) -> bool:
    """Whether a controller setting matters for this control law."""
    return not setting.modes or mode in setting.modes


def stress_question(load_kg: float, wire_preset: str, long_life_mpa: float | None) -> str:
    """'' or the schema's sentence asking to confirm a load above the long-life stress."""
    sc = schema.stress_check(load_kg, wire_preset, long_life_mpa)
    return sc.message if sc.needs_confirmation else ""
