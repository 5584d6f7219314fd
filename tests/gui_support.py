"""What the GUI test files share: starting a session until it runs, on a loaded machine."""

from __future__ import annotations

from collections.abc import Callable

from smabench.gui.state import State

LINK_TROUBLE = ("did not answer", "stopped answering")
"""Words of the GUI's message when the mock bench missed the handshake or its link dropped."""


def start_until_running(qtbot, w, press_start: Callable[[], None]) -> None:
    """Press Start (``press_start``) until the session runs with the output on (the driver
    measures > 0.5 A): at most three presses, again only after link trouble, saying why.

    On a loaded machine the mock bench may miss the handshake (seen at load average 12 on two
    cores) or its link may drop (the kernel's tty worker that carries the pty's bytes waited
    0.2–0.8 s for a CPU, past the driver's 0.25 s host timeout: the output turns itself off, as
    it must). Neither is the state under test: an operator presses Start again, so does this."""
    for attempt in range(3):
        w.last_end = None
        press_start()
        # running, or stopped trying (refused, or the connection failed)
        qtbot.waitUntil(lambda: w.state in (State.RUNNING, State.ERROR) or w.last_end or (
            w.state == State.IDLE and "Not started" in w.message.text()), timeout=60000)
        if w.state == State.RUNNING:
            qtbot.waitUntil(lambda: (w.status.get("readout", {}).get("current_a") or 0) > 0.5
                            or w.state != State.RUNNING, timeout=30000)  # fmt: skip
            if w.state == State.RUNNING:
                return
        if attempt == 2 or not any(t in w.message.text() for t in LINK_TROUBLE):
            break
        print(f"\nstarting again after: {w.message.text()}")
        qtbot.waitUntil(lambda: w.state in (State.IDLE, State.ERROR, State.DISCONNECTED),
                        timeout=15000)  # fmt: skip
    raise AssertionError((w.state, w.message.text(), w.last_end, w.sm.history[-4:]))
