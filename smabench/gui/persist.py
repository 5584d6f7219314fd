"""What the operator entered, remembered between starts of the window (``QSettings``: on Linux
``~/.config/smabench/gui.ini``), and the way back to the defaults.

Remembered: every settings field's text as typed (a refused value stays refused), the protocol,
the control law, each gain set's choice (per-load table or the operator's gains), the device kind
and the connection's fields, the mock's options, the fit model. Saved when a session is started
and when the window closes; restored when it opens.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from PySide6 import QtCore, QtWidgets

log = logging.getLogger(__name__)

ORGANIZATION, APPLICATION = "smabench", "gui"


def store() -> QtCore.QSettings:
    """The settings file (INI, per user; tests point ``QSettings.setPath`` elsewhere)."""
    return QtCore.QSettings(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope,
                            ORGANIZATION, APPLICATION)  # fmt: skip


class Remembered:
    """Saves and restores a :class:`~smabench.gui.window.MainWindow`'s entries."""

    def __init__(self, win: Any, enabled: bool = True) -> None:
        self.win = win
        self.enabled = enabled  # False: neither read nor written (benchmarks, scripts)

    def _widgets(self) -> dict[str, QtWidgets.QWidget]:
        w = self.win
        return {"protocol": w.protocol, "fit_model": w.fit_model, "use_real": w.use_real,
                "mock_effect": w.mock_effect, "mock_thermocouple": w.mock_thermocouple,
                "mock_resistivity": w.mock_resistivity,
                "serial_port": w.serial_port, "sensor_kind": w.sensor_kind,
                "sensor_host": w.sensor_host, "sensor_rtu_port": w.sensor_rtu_port,
                "sensor_baud": w.sensor_baud, "sensor_map": w.sensor_map}  # fmt: skip

    def save(self) -> None:
        if not self.enabled:
            return
        w = self.win
        q = store()
        q.setValue("version", 1)
        for key, f in w.fields.items():
            q.setValue(f"field/{key}", _get(f))
        for name, wdg in self._widgets().items():
            q.setValue(f"entry/{name}", _get(wdg))
        q.setValue("mode", w.selected_mode())
        q.setValue("custom_gains", json.dumps(w.custom_gains))
        q.sync()

    def restore(self) -> None:
        """The remembered entries (nothing when there are none: the schema's defaults)."""
        if not self.enabled:
            return
        w = self.win
        q = store()
        if q.value("version") is None:
            return
        for name, wdg in self._widgets().items():
            v = q.value(f"entry/{name}")
            if v is not None and name != "use_real":
                _set(wdg, v)
        if _bool(q.value("entry/use_real")):
            w.use_real.setChecked(True)
        mode = q.value("mode")
        if mode in w.mode_buttons:
            w.mode_buttons[mode].setChecked(True)
        try:
            gains = json.loads(q.value("custom_gains") or "{}")
        except ValueError:
            gains = {}
        for key, f in w.fields.items():
            v = q.value(f"field/{key}")
            if v is not None:
                _set(f, v)
        for law, g in gains.items():
            if law in w.custom_gains and g is not None:
                w.custom_gains[law] = [float(x) for x in g]
                box = w.gain_table_boxes[law]
                box.blockSignals(True)
                box.setChecked(False)
                box.blockSignals(False)
                for f, x in zip(w._gain_fields(law), g, strict=True):
                    f.setReadOnly(False)
                    f.set_value(x)
        w._show_table_gains()

    def defaults(self) -> None:
        """Every run setting back to the schema's default; the gain sets back to the per-load
        table, the protocol and law to the first ones (the connection is left alone)."""
        w = self.win
        for law in w.custom_gains:
            w.custom_gains[law] = None
            box = w.gain_table_boxes[law]
            box.blockSignals(True)
            box.setChecked(True)
            box.blockSignals(False)
        from smabench import settings as schema

        w.protocol.setCurrentText(schema.get("protocol.name").default)
        w.mode_buttons["open_loop"].setChecked(True)
        for f in w.fields.values():
            if f.setting.group != "connection":
                f.set_value(f.setting.default)
        w._show_table_gains()


def _get(wdg: QtWidgets.QWidget) -> Any:
    if isinstance(wdg, QtWidgets.QLineEdit):
        return wdg.text()
    if isinstance(wdg, QtWidgets.QComboBox):
        return wdg.currentText()
    if isinstance(wdg, QtWidgets.QAbstractButton):
        return bool(wdg.isChecked())
    raise TypeError(wdg)


def _bool(v: Any) -> bool:
    return v is True or str(v).lower() == "true"


def _set(wdg: QtWidgets.QWidget, v: Any) -> None:
    if isinstance(wdg, QtWidgets.QLineEdit):
        wdg.setText(str(v))
    elif isinstance(wdg, QtWidgets.QComboBox):
        i = wdg.findText(str(v))
        if i >= 0:
            wdg.setCurrentIndex(i)
        elif wdg.isEditable():
            wdg.setCurrentText(str(v))
    elif isinstance(wdg, QtWidgets.QAbstractButton):
        wdg.setChecked(_bool(v))
