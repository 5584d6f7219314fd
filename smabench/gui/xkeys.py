"""The E-STOP keys' fast path on X11: a thread with its own X connection takes the keys.

Qt delivers a key press on the GUI thread, after whatever that thread is doing: with the Live
plots drawing on a loaded 2-core machine an Esc reached the handler 50–256 ms after the press
(Xvfb, XTEST; ``tests/test_gui_xserver.py``). Here a thread of its own holds a passive grab
(``XGrabKey``) of Esc, F12 and Ctrl+E on each of the application's top-level windows: while
one of them (or a widget in it) has the focus, the X server sends those keys to this thread's
connection instead of Qt's, and the thread hands the press, with the X server's own timestamp,
to ``on_key`` at once. Where Qt holds the keyboard itself (an open drop-down or menu) or on
another platform, Qt's own event (:class:`smabench.gui.estop.EStopGuard`) still does it.

libX11 is called through ctypes (no binding to install); the connection is used by this
thread alone.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import queue
import select
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

KEY_PRESS, KEY_RELEASE = 2, 3  # X event types
SHIFT_LOCK_MASK, CONTROL_MASK, MOD2_MASK = 1 << 1, 1 << 2, 1 << 4  # Caps Lock, Ctrl, Num Lock
GRAB_MODE_ASYNC = 1
ESTOP_KEYSYMS = ((0xFF1B, 0, "Esc"), (0xFFC9, 0, "F12"), (0x0065, CONTROL_MASK, "Ctrl+E"))
"""(keysym, modifiers, name) of the e-stop keys, as :data:`smabench.gui.estop.ESTOP_KEYS`."""
LOCKS = (0, SHIFT_LOCK_MASK, MOD2_MASK, SHIFT_LOCK_MASK | MOD2_MASK)
"""Caps Lock and Num Lock do not change a key: each grab is made with every combination."""


class _XKeyEvent(ctypes.Structure):
    _fields_ = [("type", ctypes.c_int), ("serial", ctypes.c_ulong),
                ("send_event", ctypes.c_int), ("display", ctypes.c_void_p),
                ("window", ctypes.c_ulong), ("root", ctypes.c_ulong),
                ("subwindow", ctypes.c_ulong), ("time", ctypes.c_ulong),
                ("x", ctypes.c_int), ("y", ctypes.c_int), ("x_root", ctypes.c_int),
                ("y_root", ctypes.c_int), ("state", ctypes.c_uint), ("keycode", ctypes.c_uint),
                ("same_screen", ctypes.c_int)]  # fmt: skip


class _XEvent(ctypes.Union):
    _fields_ = [("type", ctypes.c_int), ("xkey", _XKeyEvent), ("pad", ctypes.c_long * 24)]


_ERROR_HANDLER = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p)


@_ERROR_HANDLER
def _ignore_x_error(display, error) -> int:  # a window gone before its grab: nothing to do
    return 0


def _libx11() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("X11") or "libX11.so.6"
    try:
        x = ctypes.CDLL(name)
    except OSError:
        return None
    x.XOpenDisplay.restype = ctypes.c_void_p
    x.XOpenDisplay.argtypes = [ctypes.c_char_p]
    for fn in ("XCloseDisplay", "XFlush", "XPending", "XConnectionNumber"):
        getattr(x, fn).argtypes = [ctypes.c_void_p]
    x.XNextEvent.argtypes = [ctypes.c_void_p, ctypes.POINTER(_XEvent)]
    x.XKeysymToKeycode.restype = ctypes.c_ubyte
    x.XKeysymToKeycode.argtypes = [ctypes.c_void_p, ctypes.c_ulong]
    x.XGrabKey.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_ulong,
                           ctypes.c_int, ctypes.c_int, ctypes.c_int]  # fmt: skip
    x.XkbSetDetectableAutoRepeat.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
    x.XSetErrorHandler.argtypes = [_ERROR_HANDLER]
    x.XSetErrorHandler.restype = ctypes.c_void_p
    return x


class EStopKeyGrab:
    """The e-stop keys taken from the X server by a thread of their own.

    ``on_key(stamp_ms, name)`` runs on that thread for each press (not its auto-repeats), with
    the X server's time of the press (ms of the monotonic clock, modulo 2³²) and the key's name
    (``Esc``, ``F12``, ``Ctrl+E``); it must be thread-safe and quick. :meth:`grab` adds a
    top-level window (its X id); :meth:`close` ends the thread and the connection.
    :meth:`start` returns None where there is no X display or no libX11."""

    def __init__(self, x11: ctypes.CDLL, display: int, on_key: Callable[[int, str], None]):
        self._x, self._dpy, self._on_key = x11, display, on_key
        self._codes: dict[tuple[int, int], str] = {}
        for keysym, mods, name in ESTOP_KEYSYMS:
            code = x11.XKeysymToKeycode(display, keysym)
            if code:
                self._codes[(code, mods)] = name
        self._grabbed: set[int] = set()
        self._todo: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._wake_r, self._wake_w = os.pipe()
        self._down: set[int] = set()
        self.presses = 0
        self._thread = threading.Thread(target=self._run, name="estop-keys", daemon=True)
        self._thread.start()

    @classmethod
    def start(cls, on_key: Callable[[int, str], None]) -> EStopKeyGrab | None:
        if not os.environ.get("DISPLAY"):
            return None
        x11 = _libx11()
        if x11 is None:
            log.info("no libX11: the e-stop keys go through Qt's events only")
            return None
        display = x11.XOpenDisplay(None)
        if not display:
            log.info("X display not opened: the e-stop keys go through Qt's events only")
            return None
        x11.XSetErrorHandler(_ignore_x_error)
        x11.XkbSetDetectableAutoRepeat(display, 1, None)  # repeats: presses with no release
        return cls(x11, display, on_key)

    def grab(self, window_id: int) -> None:
        """Take the e-stop keys while ``window_id`` (a top-level) or a child has the focus."""
        if window_id and window_id not in self._grabbed:
            self._grabbed.add(window_id)
            self._todo.put(window_id)
            os.write(self._wake_w, b"g")

    def close(self) -> None:
        if self._thread.is_alive():
            self._todo.put(None)
            os.write(self._wake_w, b"q")
            self._thread.join(2.0)

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        from smabench.bench.priority import realtime_loop_thread

        realtime_loop_thread()  # the key before drawing and other work, where allowed
        x, dpy = self._x, self._dpy
        fd = x.XConnectionNumber(dpy)
        event = _XEvent()
        try:
            while True:
                while not self._todo.empty():
                    window = self._todo.get()
                    if window is None:
                        return
                    for code, mods in self._codes:
                        for lock in LOCKS:
                            x.XGrabKey(dpy, code, mods | lock, window, 0, GRAB_MODE_ASYNC,
                                       GRAB_MODE_ASYNC)  # fmt: skip
                    x.XFlush(dpy)
                    log.debug("e-stop keys grabbed on window 0x%x", window)
                while x.XPending(dpy):
                    x.XNextEvent(dpy, ctypes.byref(event))
                    self._handle(event)
                ready, _, _ = select.select([fd, self._wake_r], [], [])
                if self._wake_r in ready:
                    os.read(self._wake_r, 64)
        except Exception:  # Qt's own path still stops the output
            log.exception("e-stop key thread failed")
        finally:
            x.XCloseDisplay(dpy)
            os.close(self._wake_r)
            os.close(self._wake_w)

    def _handle(self, event: _XEvent) -> None:
        if event.type not in (KEY_PRESS, KEY_RELEASE):
            return
        key = event.xkey
        code = key.keycode
        if event.type == KEY_RELEASE:
            self._down.discard(code)
            return
        if code in self._down:  # auto-repeat
            return
        self._down.add(code)
        mods = key.state & CONTROL_MASK
        name = self._codes.get((code, mods))
        if name is None:
            return
        self.presses += 1
        try:
            self._on_key(int(key.time), name)
        except Exception:
            log.exception("e-stop key handler failed")
