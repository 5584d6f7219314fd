"""Python's cyclic garbage collected on the GUI thread only, while a window is open.

Automatic collection runs in whatever thread happens to allocate: a job thread, the runtime's
reader or the computation worker's reader. When the garbage holds Qt objects (a closed window,
a dialog, their lambdas), their destructors then run in that thread; a destructor takes a Qt
lock and waits for the interpreter lock while the GUI thread, holding the interpreter lock,
waits for the same Qt lock: the GUI freezes (seen in the walkthrough tests: the GUI thread in
``QObject::~QObject`` of a menu, a job thread in ``~QObject`` of the previous test's window).
A frozen GUI thread would not see the E-STOP key. So automatic collection is off while the
window lives, and a timer on the GUI thread collects with the interpreter's own thresholds.
"""

from __future__ import annotations

import gc

from PySide6 import QtCore

INTERVAL_MS = 500
_active: list[GuiThreadCollector] = []  # the collectors running (one per open window)
_enabled_before = True  # automatic collection before the first of them started


class GuiThreadCollector(QtCore.QObject):
    """Collects on the GUI thread every :data:`INTERVAL_MS` when the interpreter would have;
    :meth:`stop` of the last one running gives collection back to the interpreter (if it had
    it)."""

    def __init__(self, parent: QtCore.QObject | None = None) -> None:
        global _enabled_before
        super().__init__(parent)
        if not _active:
            _enabled_before = gc.isenabled()
        _active.append(self)
        self._threshold = gc.get_threshold()
        gc.disable()
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.check)
        self.timer.start(INTERVAL_MS)

    def check(self) -> None:
        """The generations over their thresholds, as automatic collection would."""
        counts = gc.get_count()
        for gen in range(3):
            if counts[gen] <= self._threshold[gen]:
                break
            gc.collect(gen)

    def stop(self) -> None:
        self.timer.stop()
        gc.collect()  # here, on the GUI thread
        if self in _active:
            _active.remove(self)
            if not _active and _enabled_before:
                gc.enable()
