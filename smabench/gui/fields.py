"""Input fields built from the settings schema (:mod:`smabench.settings`) that never change a
value by accident and never alter what was typed.

- :class:`ValueField`: a line edit for a number, a list of numbers or text. The schema's
  ``Setting.check`` parses and checks it; text it refuses is kept as typed, marked red, and
  :meth:`ValueField.error` gives the schema's sentence with the allowed range (nothing is clamped
  or rounded: "-5" kg stays "-5" and Start refuses it). The mouse wheel does nothing to it.
  Optional settings may be left empty (``None``: the schema's ``none_text``).
- :class:`ChoiceField`: a drop-down for a choice; :class:`BoolField`: a check box.
- :class:`NoWheelCombo`: a drop-down whose choice the wheel changes only while it has the focus
  (otherwise the wheel scrolls the panel, as the operator meant).

Every field has ``setting``, ``value()``, ``set_value(v)``, ``error()`` and a ``changed`` signal.
"""

from __future__ import annotations

from typing import Any

from PySide6 import QtCore, QtGui, QtWidgets

from smabench.gui import words
from smabench.settings import Setting, SettingError

Qt = QtCore.Qt
INVALID_STYLE = "QLineEdit { background: #ffd7d7; border: 1px solid #c62828; }"


def _show(setting: Setting, v: Any) -> str:
    if v is None:
        return ""
    if setting.kind == "floats":
        return ", ".join(f"{x:g}" for x in v)
    if setting.kind == "int":
        return str(int(v))
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


def label_for(setting: Setting) -> str:
    return f"{setting.label} ({setting.unit})" if setting.unit else setting.label


class NoWheelCombo(QtWidgets.QComboBox):
    """A drop-down the wheel changes only while it has the keyboard focus."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)

    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:  # noqa: N802 (Qt name)
        if self.hasFocus():
            super().wheelEvent(event)
        else:
            event.ignore()


class ValueField(QtWidgets.QLineEdit):
    """A number, numbers or text checked by the schema; see the module docstring."""

    changed = QtCore.Signal()

    def __init__(self, setting: Setting, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setting = setting
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.setPlaceholderText(setting.none_text if setting.optional else "")
        self.base_tip = words.tooltip(setting)
        self.setToolTip(self.base_tip)
        self.set_value(setting.default)
        self.textChanged.connect(self._check)

    def set_value(self, value: Any) -> None:
        self.setText(_show(self.setting, value))

    def error(self) -> str:
        """'' when the text is valid, else the sentence the operator reads (with the range)."""
        s = self.setting
        text = self.text().strip()
        if not text and not s.optional:
            rng = words.range_words(s)
            return f"{s.label}: enter a value" + (f" ({rng})" if rng else "")
        if s.kind in ("float", "int") and text and "," in text:
            return f"{s.label}: “{text}” is not a number (use a point: 1.5)"
        try:
            s.check(text if text else None)
        except SettingError as exc:
            return words.setting_problem(s, exc)
        return ""

    def value(self) -> Any:
        """The checked value; ValueError (the :meth:`error` sentence) when the text is refused."""
        err = self.error()
        if err:
            raise ValueError(err)
        text = self.text().strip()
        return self.setting.check(text) if text else None

    def _check(self) -> None:
        err = self.error()
        self.setStyleSheet(INVALID_STYLE if err else "")
        self.setToolTip(err if err else self.base_tip)
        self.changed.emit()

    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:  # noqa: N802 (Qt name)
        event.ignore()  # never a value change: the panel scrolls instead


class ChoiceField(NoWheelCombo):
    """One of the setting's choices (or its ``none_text`` when optional)."""

    changed = QtCore.Signal()

    def __init__(self, setting: Setting, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setting = setting
        if setting.optional:
            self.addItem(setting.none_text or "none", None)
        for c in setting.choices:
            self.addItem(c, c)
        self.setToolTip(words.tooltip(setting))
        self.set_value(setting.default)
        self.currentIndexChanged.connect(lambda *_: self.changed.emit())

    def set_value(self, value: Any) -> None:
        i = self.findData(value)
        if i >= 0:
            self.setCurrentIndex(i)

    def value(self) -> Any:
        return self.currentData()

    def error(self) -> str:
        return ""


class BoolField(QtWidgets.QCheckBox):
    changed = QtCore.Signal()

    def __init__(self, setting: Setting, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(setting.label, parent)
        self.setting = setting
        self.setToolTip(words.tooltip(setting))
        self.setChecked(bool(setting.default))
        self.toggled.connect(lambda *_: self.changed.emit())

    def set_value(self, value: Any) -> None:
        self.setChecked(bool(value))

    def value(self) -> bool:
        return self.isChecked()

    def error(self) -> str:
        return ""


Field = ValueField | ChoiceField | BoolField


def make_field(setting: Setting) -> Field:
    if setting.kind == "choice":
        return ChoiceField(setting)
    if setting.kind == "bool":
        return BoolField(setting)
    return ValueField(setting)
