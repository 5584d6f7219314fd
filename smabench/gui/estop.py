"""The E-STOP keys, application-wide: Esc, F12 or Ctrl+E stop the output from anywhere.

:class:`EStopGuard` is an event filter on the QApplication, so it sees every key press before
any widget does: in the main window, in an open drop-down or menu (popups grab the keyboard, and
a plain shortcut never fires there), in a modal dialog (a file dialog, a confirmation), whatever
has the focus. It calls the e-stop first, then closes the popup or dialog the key was meant for.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from PySide6 import QtCore, QtWidgets

log = logging.getLogger(__name__)

Qt = QtCore.Qt
ESTOP_KEYS = ((Qt.Key.Key_Escape, Qt.KeyboardModifier.NoModifier),
              (Qt.Key.Key_F12, Qt.KeyboardModifier.NoModifier),
              (Qt.Key.Key_E, Qt.KeyboardModifier.ControlModifier))  # fmt: skip
KEY_NAMES = "Esc, F12 or Ctrl+E"


def is_estop_key(event) -> bool:
    mods = event.modifiers() & ~Qt.KeyboardModifier.KeypadModifier
    return any(event.key() == k and mods == m for k, m in ESTOP_KEYS)


class EStopGuard(QtCore.QObject):
    """Calls ``on_estop()`` on an e-stop key anywhere in the application (installed on
    construction; :meth:`remove` takes it off). ``last_key_t`` is the ``time.monotonic()`` of the
    last key press it acted on."""

    def __init__(self, on_estop: Callable[[], None], parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self.on_estop = on_estop
        self.last_key_t: float | None = None
        self.app = QtWidgets.QApplication.instance()
        self.app.installEventFilter(self)

    def remove(self) -> None:
        self.app.removeEventFilter(self)

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        kind = event.type()
        if kind == QtCore.QEvent.Type.ShortcutOverride and is_estop_key(event):
            event.accept()  # no shortcut elsewhere may take the key: the press comes to us
            return True
        if kind != QtCore.QEvent.Type.KeyPress or not is_estop_key(event):
            return False
        if event.isAutoRepeat():
            return True
        self.last_key_t = time.monotonic()
        try:
            self.on_estop()
        except Exception:  # the e-stop path must not be broken by a display error
            log.exception("e-stop handler failed")
        self._close_overlays()
        return True  # consumed: the e-stop was the key's job

    def _close_overlays(self) -> None:
        """Close the popup or modal dialog the key would have closed (after the e-stop)."""
        popup = QtWidgets.QApplication.activePopupWidget()
        if popup is not None:
            popup.close()
        modal = QtWidgets.QApplication.activeModalWidget()
        if isinstance(modal, QtWidgets.QDialog):
            modal.reject()
