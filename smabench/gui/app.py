"""``smabench gui``: start the operator window (and, for documentation, a scripted demo)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

log = logging.getLogger(__name__)


def make_app():
    """The QApplication (offscreen when there is no display)."""
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import pyqtgraph as pg
    from PySide6 import QtWidgets

    pg.setConfigOptions(useOpenGL=False, antialias=False, background="w", foreground="k")
    return QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])


def cmd_gui(args: argparse.Namespace) -> int:
    from PySide6 import QtCore

    from smabench.gui.window import MainWindow

    app = make_app()
    win = MainWindow(args.sessions, mock_speed=args.mock_speed)
    if args.port:
        win.use_real.setChecked(True)
        win.serial_port.setCurrentText(args.port)
    win.show()
    previous_hook = sys.excepthook

    def on_crash(*exc_info) -> None:  # a GUI bug must not leave the wire heating
        win.estop()
        previous_hook(*exc_info)

    sys.excepthook = on_crash
    if args.mock and not args.run_demo:
        win.connect_devices()
    if args.run_demo:
        win.fields["load_kg"].set_value(2.0)
        win.fields["protocol.cycles"].set_value(3)
        win.fields["protocol.current_a"].set_value(1.4)
        QtCore.QTimer.singleShot(100, win.start_experiment)
    started = time.monotonic()
    if args.screenshot or args.quit_after:
        quit_after_s = args.quit_after or 10.0

        def finish() -> None:
            if args.screenshot:
                Path(args.screenshot).parent.mkdir(parents=True, exist_ok=True)
                win.grab().save(str(args.screenshot))
                print(f"screenshot: {args.screenshot}")
            win.close()
            app.quit()

        QtCore.QTimer.singleShot(int(quit_after_s * 1000), finish)
    code = app.exec()
    log.info("GUI ran %.1f s", time.monotonic() - started)
    return int(code)


def add_commands(sub) -> None:
    s = sub.add_parser("gui", help="the operator GUI (PySide6 + pyqtgraph)")
    s.add_argument("--mock", action="store_true", help="connect to the built-in mock bench")
    s.add_argument("--mock-speed", type=float, default=None,
                   help="mock bench speed, × (the remembered one; 1 the first time)")
    s.add_argument("--port", help="current driver serial port (real devices)")
    s.add_argument("--sessions", default="sessions", help="sessions folder (sessions/)")
    s.add_argument("--run-demo", action="store_true", help="start 3 heating cycles at once")
    s.add_argument("--screenshot", help="save a PNG of the window before quitting")
    s.add_argument("--quit-after", type=float, help="quit after this many seconds")
    s.set_defaults(func=cmd_gui)
