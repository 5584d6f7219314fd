"""The E-STOP key pressed on a real X server (Xvfb), run by :mod:`test_gui_xserver` in its own
pytest process (the platform of a process's QApplication is fixed once: xcb here, offscreen in
the other GUI tests). Not collected on its own (no ``test_`` file prefix).

The key press is injected through XTEST, so the X server stamps the event as it would a
keyboard's: the GUI takes the input time from the event itself, the runtime sends the
command, and events.jsonl holds both. Writes what it measured as JSON to
``$SMABENCH_XSERVER_OUT``.
"""

from __future__ import annotations

import ctypes
import json
import os
import time

import numpy as np
import pytest

pytest.importorskip("pytestqt")

from gui_support import dispose, measured_current_a, open_window, start_running  # noqa: E402
from PySide6 import QtCore  # noqa: E402

from smabench.sessions import read_events  # noqa: E402

Qt = QtCore.Qt
XK_ESCAPE = 0xFF1B


class XTest:
    """Key and pointer input through the X server's XTEST extension (libXtst), as hardware."""

    def __init__(self) -> None:
        self.x11 = ctypes.CDLL("libX11.so.6")
        self.xtst = ctypes.CDLL("libXtst.so.6")
        self.x11.XOpenDisplay.restype = ctypes.c_void_p
        self.x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
        self.x11.XKeysymToKeycode.restype = ctypes.c_ubyte
        self.x11.XKeysymToKeycode.argtypes = [ctypes.c_void_p, ctypes.c_ulong]
        self.x11.XFlush.argtypes = [ctypes.c_void_p]
        self.x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
        self.xtst.XTestFakeKeyEvent.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_int,
                                                ctypes.c_ulong]  # fmt: skip
        self.xtst.XTestFakeMotionEvent.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_int,
                                                   ctypes.c_int, ctypes.c_ulong]  # fmt: skip
        self.dpy = self.x11.XOpenDisplay(None)
        assert self.dpy, "no X display"

    def move(self, x: int, y: int) -> None:
        self.xtst.XTestFakeMotionEvent(self.dpy, -1, x, y, 0)
        self.x11.XFlush(self.dpy)

    def key(self, keysym: int) -> float:
        """Press and release ``keysym``; returns time.monotonic() just before the press."""
        code = self.x11.XKeysymToKeycode(self.dpy, keysym)
        t = time.monotonic()
        self.xtst.XTestFakeKeyEvent(self.dpy, code, 1, 0)
        self.x11.XFlush(self.dpy)
        self.xtst.XTestFakeKeyEvent(self.dpy, code, 0, 0)
        self.x11.XFlush(self.dpy)
        return t

    def close(self) -> None:
        self.x11.XCloseDisplay(self.dpy)


def test_estop_key_on_the_x_server(qtbot, tmp_path):
    assert os.environ.get("QT_QPA_PLATFORM") == "xcb", "run by test_gui_xserver"
    w = open_window(tmp_path / "sessions", 1.0)
    qtbot.waitExposed(w)
    x = XTest()
    try:
        w.tabs.setCurrentIndex(0)  # the Live plots, drawing while the wire heats
        w.protocol.setCurrentText("cycles")
        for key, value in (("protocol.cycles", 3), ("protocol.current_a", 1.4),
                           ("protocol.heat_s", 60.0)):  # fmt: skip
            w.fields[key].set_value(value)
        start_running(qtbot, w, w.start_button.click)
        qtbot.waitUntil(lambda: measured_current_a(w) > 1.2, timeout=30000)
        qtbot.waitUntil(lambda: w.buffer.n > 200, timeout=30000)  # the plots have drawn a while
        w.activateWindow()
        w.raise_()
        centre = w.mapToGlobal(w.rect().center())
        x.move(centre.x(), centre.y())
        qtbot.waitUntil(lambda: w.isActiveWindow(), timeout=5000)
        w.last_end = None
        handled: list[float] = []
        link_estop = w.link.estop

        def estop(*args, **kwargs):  # when the GUI thread sent it down the pipe
            handled.append(time.monotonic())
            return link_estop(*args, **kwargs)

        w.link.estop = estop
        pressed_t = x.key(XK_ESCAPE)
        qtbot.waitUntil(lambda: w.last_end is not None, timeout=15000)
        folder = w.last_end["folder"]
        events = read_events(folder)
        first = next(e for e in events if e["event"] == "estop_input")
        sent = next(e for e in events if e["event"] == "command_sent" and e["why"] == "e-stop")
        below = next(e for e in events if e["event"] == "current_below_threshold")
        current = np.asarray(w.buffer.column("current_A"), float)
        out = {
            "source": first["source"],
            "from_input_event": first["from_input_event"],
            "input_after_press_ms": 1e3 * (first["t_host_s"] - pressed_t),
            "input_to_command_ms": 1e3 * (sent["t_host_s"] - first["t_host_s"]),
            "input_to_gui_handler_ms": 1e3 * (handled[0] - first["t_host_s"]),
            "input_to_below_20ma_ms": 1e3 * (below["t_host_s"] - first["t_host_s"]),
            "acked": sent["acked"],
            "live_rows": int(len(current)),
        }
        with open(os.environ["SMABENCH_XSERVER_OUT"], "w") as f:
            json.dump(out, f)
    finally:
        x.close()
        dispose(w)
