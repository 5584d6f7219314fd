"""The operator's prompt when a campaign (``smabench plan run/resume``) needs the load changed:
a dialog on the screen when there is one, the terminal prompt otherwise.

:func:`ask_load_dialog` has the signature of :func:`smabench.plan.ask_load` (the plan's ``ask``
hook): True when the operator confirms the new load hangs, False to stop the plan there (it is
resumed later with ``smabench plan resume``). The bench's output is off while it waits: steps run
one session at a time and each session ends with the output made safe.
"""

from __future__ import annotations

import logging
import os
import sys

log = logging.getLogger(__name__)


def display_available() -> bool:
    """Whether a window can be shown (an X11/Wayland display, or Windows/macOS)."""
    if os.environ.get("QT_QPA_PLATFORM", "") == "offscreen":
        return False
    if sys.platform in ("win32", "darwin"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def load_change_text(load_kg: float, previous: float | None, step: str) -> str:
    before = "the current load" if previous is None else f"{previous:g} kg"
    return (f"Step {step} needs a different load: change it from {before} to {load_kg:g} kg "
            "(the output is off).\n\nPress Continue when the new load hangs still, or Stop to "
            "stop the plan here (`smabench plan resume` continues it later).")  # fmt: skip


def ask_load_dialog(load_kg: float, previous: float | None, step: str) -> bool:
    """Ask in a dialog (modal, on top); True: continue with the new load, False: stop."""
    from PySide6 import QtCore, QtWidgets

    from smabench.gui.app import make_app

    make_app()
    text = load_change_text(load_kg, previous, step)
    print(f"\n>>> {text.splitlines()[0]} (answer in the dialog)", flush=True)
    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Question,
                                "smabench plan: change the load", text)  # fmt: skip
    go = box.addButton("Continue", QtWidgets.QMessageBox.ButtonRole.AcceptRole)
    stop = box.addButton("Stop here", QtWidgets.QMessageBox.ButtonRole.RejectRole)
    box.setDefaultButton(stop)  # Enter by accident does not start the next step
    box.setEscapeButton(stop)
    box.setWindowFlag(QtCore.Qt.WindowType.WindowStaysOnTopHint, True)
    box.exec()
    ok = box.clickedButton() is go
    log.info("load change to %g kg for step %s: %s", load_kg, step, "confirmed" if ok else "stop")
    return ok
