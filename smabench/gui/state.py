"""The operator window's state machine (no Qt here): which state the bench is in and which
events move it on. The window enables its controls from :func:`controls_for` alone.

States: ``disconnected``, ``connecting``, ``idle`` (connected, nothing running), ``starting`` (a
start sent, not yet accepted), ``running``, ``paused``, ``estopped`` (latched until acknowledged),
``error`` (not connected, with a message: a failed connection, a lost device, a dead runtime).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import StrEnum

log = logging.getLogger(__name__)


class State(StrEnum):
    DISCONNECTED = "disconnected"
    CONNECTING = "connecting"
    IDLE = "idle"
    STARTING = "starting"
    RUNNING = "running"
    PAUSED = "paused"
    ESTOPPED = "estopped"
    ERROR = "error"


S = State
NOT_CONNECTED = (S.DISCONNECTED, S.ERROR)
IN_SESSION = (S.STARTING, S.RUNNING, S.PAUSED)

# event -> {from state: to state}; an event not listed for a state is ignored (logged)
TRANSITIONS: dict[str, dict[State, State]] = {
    "connect": {S.DISCONNECTED: S.CONNECTING, S.ERROR: S.CONNECTING},
    "connected": {S.CONNECTING: S.IDLE},
    "connect_failed": {S.CONNECTING: S.ERROR},
    "disconnect": {s: S.DISCONNECTED for s in (S.CONNECTING, S.IDLE, S.ERROR)},
    "start": {S.IDLE: S.STARTING},
    "started": {S.STARTING: S.RUNNING},
    "refused": {S.STARTING: S.IDLE, S.CONNECTING: S.ERROR},
    "pause": {S.RUNNING: S.PAUSED},
    "resume": {S.PAUSED: S.RUNNING},
    "ended": {S.STARTING: S.IDLE, S.RUNNING: S.IDLE, S.PAUSED: S.IDLE},
    "lost": {s: S.ERROR for s in (S.CONNECTING, S.IDLE, S.STARTING, S.RUNNING, S.PAUSED)},
    "estop": {s: S.ESTOPPED for s in State},
    "acknowledge_connected": {S.ESTOPPED: S.IDLE},
    "acknowledge_disconnected": {S.ESTOPPED: S.DISCONNECTED},
}


@dataclass(frozen=True)
class Controls:
    """What the operator may press or edit in a state."""

    connect: bool  # the Connect/Disconnect button
    connect_label: str
    start: bool
    pause: bool
    stop: bool
    acknowledge: bool
    connection_fields: bool  # device kind, ports, mock speed
    session_fields: bool  # settings that cannot change mid-run
    live_fields: bool  # settings a running session takes (mode, gains, open-loop current)


def controls_for(state: State) -> Controls:
    running = state in (S.RUNNING, S.PAUSED)
    return Controls(
        connect=state in (S.DISCONNECTED, S.ERROR, S.CONNECTING, S.IDLE),
        connect_label="Connect" if state in NOT_CONNECTED else "Disconnect",
        start=state in (S.IDLE, S.DISCONNECTED, S.ERROR),  # not connected: connects first
        pause=running,
        stop=running or state == S.STARTING,
        acknowledge=state == S.ESTOPPED,
        connection_fields=state in NOT_CONNECTED,
        session_fields=state not in (*IN_SESSION,),
        live_fields=True,
    )


class StateMachine:
    """The current state, moved only by :meth:`fire`."""

    def __init__(self) -> None:
        self.state = S.DISCONNECTED
        self.history: list[tuple[str, State, State]] = []

    def fire(self, event: str) -> State:
        """Apply ``event``; returns the (possibly unchanged) state."""
        table = TRANSITIONS[event]
        new = table.get(self.state)
        if new is None:
            log.debug("event %s ignored in state %s", event, self.state.value)
            return self.state
        self.history.append((event, self.state, new))
        self.state = new
        return new
