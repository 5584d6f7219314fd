"""The E-STOP keys, application-wide: Esc, F12 or Ctrl+E stop the output from anywhere.

On X11 the keys first take a fast path that does not wait for the GUI thread
(:mod:`smabench.gui.xkeys`: a thread of its own sends the e-stop down the runtime's pipe at
once, then the display follows here); what it cannot see comes through Qt as below.

:class:`EStopGuard` is an event filter on the QApplication, so it sees every key press before
any widget does: in the main window, in an open drop-down or menu (popups grab the keyboard, and
a plain shortcut never fires there), in a modal dialog (a file dialog, a confirmation), whatever
has the focus. It calls the e-stop first, then closes the popup or dialog the key was meant for.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from PySide6 import QtCore, QtGui, QtWidgets

log = logging.getLogger(__name__)

Qt = QtCore.Qt
ESTOP_KEYS = ((Qt.Key.Key_Escape, Qt.KeyboardModifier.NoModifier),
              (Qt.Key.Key_F12, Qt.KeyboardModifier.NoModifier),
              (Qt.Key.Key_E, Qt.KeyboardModifier.ControlModifier))  # fmt: skip
KEY_NAMES = "Esc, F12 or Ctrl+E"


MAX_INPUT_AGE_S = 2.0
"""An input event older than this by its own timestamp is taken to be on another clock."""


def input_time(event) -> tuple[float, bool]:
    """When an input event happened on ``time.monotonic()``'s clock, s, and whether that came
    from the event itself. On X11 (xcb, also Xvfb) an event's ``timestamp()`` is the X server's
    time: milliseconds of the system's monotonic clock modulo 2³², the clock of
    ``time.monotonic()``. An age outside 0 … :data:`MAX_INPUT_AGE_S` means another clock (the
    offscreen platform, a synthetic test event): then the handler's own time, said so."""
    try:
        stamp_ms = int(event.timestamp())
    except (AttributeError, TypeError, ValueError):
        return time.monotonic(), False
    return stamp_time(stamp_ms)


def stamp_time(stamp_ms: int) -> tuple[float, bool]:
    """An X server timestamp (ms of the monotonic clock, modulo 2³²) on ``time.monotonic()``'s
    clock, s, and whether it is one (see :func:`input_time`)."""
    now = time.monotonic()
    age_ms = (int(now * 1000.0) - stamp_ms) % (1 << 32)
    if stamp_ms and age_ms <= MAX_INPUT_AGE_S * 1000.0:
        return now - age_ms / 1000.0, True
    return now, False


def key_name(event) -> str:
    """``Esc``, ``F12`` or ``Ctrl+E``: the e-stop key of ``event``."""
    return {Qt.Key.Key_Escape: "Esc", Qt.Key.Key_F12: "F12", Qt.Key.Key_E: "Ctrl+E"}.get(
        event.key(), str(event.key())
    )


def is_estop_key(event) -> bool:
    mods = event.modifiers() & ~Qt.KeyboardModifier.KeypadModifier
    return any(event.key() == k and mods == m for k, m in ESTOP_KEYS)


class EStopGuard(QtCore.QObject):
    """Calls ``on_estop(input_t, source)`` on an e-stop key anywhere in the application
    (installed on construction; :meth:`remove` takes it off): ``input_t`` is the key press's own
    time on ``time.monotonic()``'s clock (None when the event's clock is not that one, see
    :func:`input_time`), ``source`` e.g. ``key Esc``. ``last_key_t`` is the time of the last key
    press it acted on; ``press_t`` the time of the last mouse press on ``button`` (the E-STOP
    button, whose ``pressed`` signal carries no event).

    With ``send_now(input_t, source) -> sent`` (thread-safe) the X11 fast path
    (:class:`~smabench.gui.xkeys.EStopKeyGrab`) is used where there is one: the key's thread
    calls ``send_now`` at once, then ``on_estop(input_t, source, sent)`` runs here."""

    _fast_key = QtCore.Signal(object, str, bool)  # input_t, source, sent: to the GUI thread

    def __init__(
        self,
        on_estop: Callable[..., None],
        parent: QtCore.QObject | None = None,
        button: QtWidgets.QAbstractButton | None = None,
        send_now: Callable[[float | None, str], bool] | None = None,
    ) -> None:
        super().__init__(parent)
        self.on_estop = on_estop
        self.button = button
        self.last_key_t: float | None = None
        self.press_t: tuple[float, bool] | None = None
        self.app = QtWidgets.QApplication.instance()
        self.app.installEventFilter(self)
        self.send_now = send_now
        self.keys = None  # the X11 fast path's thread, where there is one
        if send_now is not None and QtGui.QGuiApplication.platformName() == "xcb":
            from smabench.gui.xkeys import EStopKeyGrab

            self.keys = EStopKeyGrab.start(self._on_fast_key)
        if self.keys is not None:
            self._fast_key.connect(self._after_fast_key, Qt.ConnectionType.QueuedConnection)
            self.app.focusWindowChanged.connect(self._grab_window)
            for window in self.app.topLevelWindows():
                self._grab_window(window)

    def remove(self) -> None:
        self.app.removeEventFilter(self)
        if self.keys is not None:
            self.app.focusWindowChanged.disconnect(self._grab_window)
            self.keys.close()
            self.keys = None

    def _grab_window(self, window: QtGui.QWindow | None) -> None:
        if window is not None and self.keys is not None:
            self.keys.grab(int(window.winId()))

    def _on_fast_key(self, stamp_ms: int, name: str) -> None:
        """On the key's thread: the e-stop down the pipe now, the display on the GUI thread."""
        t, own = stamp_time(stamp_ms)
        source = f"key {name}"
        try:
            sent = bool(self.send_now(t if own else None, source))
        except Exception:
            log.exception("e-stop fast path failed")
            sent = False
        self._fast_key.emit(t if own else None, source, sent)

    def _after_fast_key(self, input_t: float | None, source: str, sent: bool) -> None:
        self.last_key_t = input_t
        try:
            self.on_estop(input_t, source, sent=sent)
        except Exception:
            log.exception("e-stop handler failed")
        self._close_overlays()

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        kind = event.type()
        if kind == QtCore.QEvent.Type.MouseButtonPress and obj is self.button:
            self.press_t = input_time(event)  # the button's pressed signal follows
            return False
        if kind == QtCore.QEvent.Type.ShortcutOverride and is_estop_key(event):
            event.accept()  # no shortcut elsewhere may take the key: the press comes to us
            return True
        if kind != QtCore.QEvent.Type.KeyPress or not is_estop_key(event):
            return False
        if event.isAutoRepeat():
            return True
        t, own = input_time(event)
        self.last_key_t = t
        try:
            self.on_estop(t if own else None, f"key {key_name(event)}")
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
