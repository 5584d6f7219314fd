"""Input fields that never change a value by accident and never alter what was typed.

- :class:`NumberField`: a line edit for a number with a range and unit. Text outside the range
  (or not a number) is kept as typed, marked red, and :meth:`NumberField.error` says the allowed
  range; nothing is clamped or rounded ("-5" kg stays "-5" and is refused). The mouse wheel does
  nothing to it. Optional fields may be left empty (``None``: "automatic" / "no limit").
- :class:`NoWheelCombo`: a drop-down whose choice the wheel changes only when it has the focus
  (otherwise the wheel scrolls the panel as the operator meant).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from PySide6 import QtCore, QtGui, QtWidgets

Qt = QtCore.Qt
INVALID_STYLE = "QLineEdit { background: #ffd7d7; border: 1px solid #c62828; }"


@dataclass(frozen=True)
class FieldSpec:
    """One setting as the GUI shows it (from the settings schema)."""

    name: str
    label: str
    default: float | int | None
    lo: float | None = None  # inclusive unless lo_open
    hi: float | None = None
    unit: str = ""
    help: str = ""
    integer: bool = False
    optional: bool = False  # empty allowed: None
    empty_text: str = ""  # what empty means ("middle of the stroke", "no limit")
    lo_open: bool = False
    live: bool = False  # may change while a session runs
    protocols: tuple[str, ...] = field(default_factory=tuple)  # empty: every protocol
    group: str = ""


def _fmt(v: float | None) -> str:
    if v is None:
        return ""
    return f"{v:g}" if abs(v) < 1e6 else f"{v:.6g}"


class NumberField(QtWidgets.QLineEdit):
    """A number in a range; see the module docstring."""

    changed = QtCore.Signal()

    def __init__(self, spec: FieldSpec, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.spec = spec
        self.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        self.setPlaceholderText(spec.empty_text)
        tip = f"{spec.label}: {self.range_text()}"
        if spec.help:
            tip += f"\n{spec.help}"
        self.base_tip = tip
        self.setToolTip(tip)
        self.set_value(spec.default)
        self.textChanged.connect(self._check)

    def range_text(self) -> str:
        s = self.spec
        unit = f" {s.unit}" if s.unit else ""
        if s.lo is not None and s.hi is not None:
            left = "above" if s.lo_open else "from"
            text = f"{left} {_fmt(s.lo)} to {_fmt(s.hi)}{unit}"
        elif s.lo is not None:
            text = f"{'above' if s.lo_open else 'at least'} {_fmt(s.lo)}{unit}"
        elif s.hi is not None:
            text = f"at most {_fmt(s.hi)}{unit}"
        else:
            text = "any number" + unit
        if s.integer:
            text += ", whole numbers"
        if s.optional:
            text += f"; empty: {s.empty_text or 'automatic'}"
        return text

    def set_value(self, value: float | int | None) -> None:
        self.setText("" if value is None else (str(int(value)) if self.spec.integer
                                               else _fmt(float(value))))  # fmt: skip

    def error(self) -> str:
        """'' when the text is a valid value, else the sentence the operator reads."""
        s = self.spec
        text = self.text().strip()
        if not text:
            return "" if s.optional else f"{s.label}: enter a value ({self.range_text()})"
        try:
            v = float(text)
        except ValueError:
            return f"{s.label}: “{self.text()}” is not a number ({self.range_text()})"
        bad = not math.isfinite(v)
        bad |= s.integer and v != int(v)
        bad |= s.lo is not None and (v <= s.lo if s.lo_open else v < s.lo)
        bad |= s.hi is not None and v > s.hi
        if bad:
            return f"{s.label}: {text} is outside the allowed range ({self.range_text()})"
        return ""

    def value(self) -> float | int | None:
        """The value; ValueError (with :meth:`error`'s sentence) when the text is not valid."""
        err = self.error()
        if err:
            raise ValueError(err)
        text = self.text().strip()
        if not text:
            return None
        return int(float(text)) if self.spec.integer else float(text)

    def _check(self) -> None:
        err = self.error()
        self.setStyleSheet(INVALID_STYLE if err else "")
        self.setToolTip(err if err else self.base_tip)
        self.changed.emit()

    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:  # noqa: N802 (Qt name)
        event.ignore()  # never a value change: the panel scrolls instead


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
