"""The calibration store (a small JSON file of what ``smabench calibrate`` and ``smabench sensor
tare`` measured) and the ``calibration`` block every session's ``session.json`` carries.

On a low floor: the session runner reads it at each start, the calibration commands
(:mod:`smabench.calibrate`) write it. Where the file lives: :func:`store_path`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from smabench.drivers import protocol as p

log = logging.getLogger(__name__)

ENV_STORE = "SMABENCH_CALIBRATION"
STORE_VERSION = 1


class CalibrationError(ValueError):
    """A calibration refused: one line for the operator, exit code 2, nothing written."""


# ---------------------------------------------------------------------------- the store
def store_path(path: str | Path | None = None) -> Path:
    """Where calibration results are kept: ``path``, ``$SMABENCH_CALIBRATION``, the user's
    config folder (``$XDG_CONFIG_HOME`` or ``~/.config``) ``/smabench/calibration.json``."""
    if path:
        return Path(path).expanduser()
    if os.environ.get(ENV_STORE):
        return Path(os.environ[ENV_STORE]).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config"
    return Path(base) / "smabench" / "calibration.json"


def load_store(path: str | Path | None = None) -> dict[str, Any]:
    """The stored results (``{}`` when there is no file); CalibrationError when it is broken."""
    where = store_path(path)
    try:
        text = where.read_text()
    except FileNotFoundError:
        return {}
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"calibration file {where} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"calibration file {where} does not hold a JSON object")
    return data


def save_record(key: str, record: dict[str, Any], path: str | Path | None = None) -> Path:
    """Put ``record`` under ``key`` (``current``, ``wire``, ``sensor_tare``), atomically."""
    from smabench.sessions import atomic_write_json

    where = store_path(path)
    data = load_store(where)
    data["version"] = STORE_VERSION
    data[key] = record
    return atomic_write_json(where, data)


def _same_calibration(a: p.Calibration, b: p.Calibration) -> bool:
    """Equal as the device stores them (1 µA, Q15 gains)."""
    return a.to_data() == b.to_data()


# ---------------------------------------------------------------------------- session metadata
def session_block(source: Any, path: str | Path | None = None) -> dict[str, Any]:
    """The ``calibration`` block of ``session.json``: the current driver's calibration as read
    back from the device at connect (``source.calibration``) with when it was written (from
    the store, when it matches), the wire's cold resistance and the sensor tare from the
    store. Never raises: a broken store is logged and left out."""
    where = store_path(path)
    try:
        store = load_store(where)
    except (CalibrationError, OSError) as exc:
        log.warning("calibration store left out of the session: %s", exc)
        store = {}
    cal = getattr(source, "calibration", None)
    current = None
    if isinstance(cal, p.Calibration):
        rec = store.get("current") or {}
        written = None
        try:
            stored = p.Calibration(  # the wire-voltage offset is `calibrate wire`'s
                rec["offset_a"], rec["gain"], rec.get("voltage_gain", cal.voltage_gain),
                cal.voltage_offset_v,
            )
            if _same_calibration(stored, cal):
                written = rec.get("written_at")
        except (KeyError, TypeError, ValueError):
            pass
        latest = source.latest() if hasattr(source, "latest") else None
        if latest is None and hasattr(source, "wait_telemetry"):
            # just connected on a busy host: the first frame (10 ms period) may not be in yet
            with contextlib.suppress(Exception):  # none within 1 s: unknown (null)
                latest = source.wait_telemetry(timeout_s=1.0)
        current = {
            "current_offset_a": cal.current_offset_a,
            "current_gain": cal.current_gain,
            "voltage_gain": cal.voltage_gain,
            "voltage_offset_v": cal.voltage_offset_v,
            # CAL_DEFAULT: the calibration or the heat model in EEPROM invalid, defaults in use
            "eeprom_defaults": None if latest is None else bool(latest.flags & p.Flag.CAL_DEFAULT),
            "written_at": written,  # null: not written by `smabench calibrate` with this store
        }
    return {
        "store": str(where),
        "current_driver": current,
        "wire": store.get("wire"),
        "sensor_tare": store.get("sensor_tare"),
    }
