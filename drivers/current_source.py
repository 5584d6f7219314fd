"""Host driver of the SMA current driver (``firmware/PROTOCOL.md``): the device on a framed link.

The link (:mod:`.link`: the owner thread, sequence numbers, ACK/retry, keepalive, reconnect,
packet dispatch) carries the frames; this class gives them meaning: the IDENTIFY handshake and
the configuration re-applied after every (re)connect, the commands with their units and local
checks, the telemetry store (latest, history, subscribers, waiting) and the fault text.

:meth:`CurrentSource.set_current` does not wait for its ACK: the control loop renews the setpoint
every tick and must not stall a round trip for it. The firmware turns the output off when no
SET_CURRENT came within its setpoint *lease* (:attr:`CurrentSource.lease_s`, 0.25 s by default;
``LEASE_EXPIRED`` in telemetry): the link's keepalive PINGs keep the link up but never renew the
lease, so a control loop that hangs in a live process stops heating. A setpoint still queued
when the next one comes is replaced by it; the ACKs are checked in
the background (:attr:`CurrentSource.setpoint_status`, counters, a log line when the device starts
or stops clamping). ``set_current(x, wait=True)`` waits and returns the ACK status.

Connecting survives an Arduino's auto-reset: opening the port pulses DTR, the board resets and
its bootloader waits about a second before it starts the firmware, so the handshake keeps
trying for :data:`CONNECT_WAIT_S` after the port was opened (and after every reopen).

Units: currents in A, voltages in V, times in s (device time ``t_ms`` in ms), duty 0 … 1.

Example::

    with CurrentSource("/dev/ttyUSB0") as cs:        # opens, IDENTIFY handshake
        cs.set_limits(1.5, 0.25)
        cs.set_current(0.8)
        cs.enable(True)
        t = cs.wait_telemetry(lambda t: abs(t.current_a - 0.8) < 0.04, timeout_s=0.5)
    # leaving the block: output off (best effort), thread stopped, port closed
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from smabench.drivers import protocol as p
from smabench.drivers.link import FramedLink, LinkError, LinkTimeout, Request, type_name

log = logging.getLogger(__name__)

MsgType = p.MsgType
Status = p.Status

CONNECT_WAIT_S = 2.5
"""How long the handshake keeps trying after the port was opened, s. Opening the serial port of
an Arduino pulses DTR and resets the board; optiboot then waits about 1 s for a programmer
before it starts the firmware (DESIGN.md §5), the old Nano bootloader a little longer."""

SETPOINT_SLOT = "setpoint"

__all__ = [
    "CONNECT_WAIT_S",
    "CommandRejected",
    "CurrentSource",
    "CurrentSourceError",
    "DeviceFault",
    "LinkCounters",
    "LinkTimeout",
    "VersionMismatch",
]


# ---------------------------------------------------------------------------- errors
CurrentSourceError = LinkError
"""Base class of the current-source driver errors (the link's errors included)."""


class CommandRejected(CurrentSourceError):  # noqa: N818 (names of the API)
    """The device answered with an ACK status other than OK (or CLAMPED)."""

    def __init__(self, command: int, status: int, message: str = "") -> None:
        self.command = command
        self.status = status
        try:
            status_name = Status(status).name
        except ValueError:
            status_name = f"status {status}"
        super().__init__(message or f"{type_name(command)} rejected: {status_name}")


class VersionMismatch(CurrentSourceError):  # noqa: N818 (names of the API)
    """The device speaks another protocol version."""


class DeviceFault(CommandRejected):
    """ENABLE refused because a fault is latched on the device (clear it with clear_faults)."""


@dataclass(frozen=True)
class LinkCounters:
    """Link statistics (host side, plus the device's own counters from the latest telemetry)."""

    tx_frames: int
    rx_packets: int
    crc_errors: int  # host receiver: frames with a bad CRC
    frame_errors: int  # host receiver: bad COBS / length
    retries: int  # command frames sent again after an ACK timeout
    timeouts: int  # commands that failed with LinkTimeout
    reconnects: int  # successful reopen + handshake after the first connect
    keepalives: int  # PINGs sent by the owner thread
    device_crc_errors: int  # device receiver, from telemetry (saturating u16)
    device_frame_errors: int
    setpoints_superseded: int = 0  # setpoints replaced by a newer one before they went out


class CurrentSource:
    """Client of the current driver firmware (satisfies ``smabench.drivers.base.
    CurrentSourceDevice``).

    Args:
        port: port name or pyserial URL (``/dev/ttyUSB0``, ``loop://``), or an already-constructed
            serial object (pyserial API: read, write, in_waiting, close; tests use a fake).
        ack_timeout_s: wait for one ACK, s. A command is sent ``1 + retries`` times at most.
        retries: resends after an ACK timeout (all commands are idempotent).
        telemetry_period_s: telemetry rate asked for at connect, s (0 = off).
        current_limit_a, host_timeout_s: limits sent at connect (``None`` = device defaults:
            hard limit, 0.25 s).
        keepalive: let the link PING to feed the device's host watchdog (PINGs keep the link
            alive; they never renew the setpoint lease: only :meth:`set_current` does).
        link_timeout_s: the link counts as lost when nothing valid was received for this long.
        max_reconnect_attempts: automatic reopen attempts after a port error before giving up.
        history: number of telemetry frames kept in :attr:`history`.
        protocol_version: version sent in IDENTIFY (only tests change it).
        connect_wait_s: keep trying the handshake this long after opening the port, s
            (:data:`CONNECT_WAIT_S`; 0: one try with its retries).
        lease_s: setpoint lease sent at connect, s (0.02 … 5; ``None`` = the device default,
            0.25 s): the output goes off when no :meth:`set_current` came for this long.
        owner_priority: SCHED_FIFO priority for the link's owner thread (keepalive, telemetry);
            ``None``: normal scheduling (see :class:`~smabench.drivers.link.FramedLink`).
    """

    def __init__(
        self,
        port: str | Any,
        *,
        ack_timeout_s: float = 0.1,
        retries: int = 2,
        telemetry_period_s: float = 0.01,
        current_limit_a: float | None = None,
        host_timeout_s: float | None = None,
        keepalive: bool = True,
        link_timeout_s: float = 0.3,
        max_reconnect_attempts: int = 8,
        history: int = 2000,
        protocol_version: int = p.PROTOCOL_VERSION,
        connect_wait_s: float = CONNECT_WAIT_S,
        lease_s: float | None = None,
        owner_priority: int | None = None,
    ) -> None:
        self._link = FramedLink(
            port,
            ack_timeout_s=ack_timeout_s,
            retries=retries,
            link_timeout_s=link_timeout_s,
            keepalive_interval_s=lambda: self.keepalive_interval_s,
            keepalive=keepalive,
            max_reopen_attempts=max_reconnect_attempts,
            handlers={MsgType.TELEMETRY: self._on_telemetry},
            on_resync=self._handshake,
            owner_priority=owner_priority,
        )
        self.port_name = self._link.port_name
        self.telemetry_period_s = telemetry_period_s
        self.protocol_version = protocol_version
        self.connect_wait_s = connect_wait_s
        # configuration re-applied after every handshake
        self._cfg_limit_a = current_limit_a
        self._cfg_host_timeout_s = host_timeout_s
        self._host_timeout_s = host_timeout_s or p.HOST_TIMEOUT_DEFAULT_S
        self._limit_a: float | None = current_limit_a
        if lease_s is not None:
            p.set_lease(lease_s)  # ValueError now, not at connect
        self._cfg_lease_s = lease_s
        self.info: p.DeviceInfo | None = None
        self.calibration: p.Calibration | None = None  # as last read back (get_calibration)

        self._lock = threading.RLock()
        self._tel_cond = threading.Condition(self._lock)
        self._latest: p.Telemetry | None = None
        self.history: collections.deque[p.Telemetry] = collections.deque(maxlen=history)
        self._subscribers: list[Callable[[p.Telemetry], None]] = []
        self._last_fault_flags = 0
        self.setpoint_status: Status | None = None  # ACK status of the latest answered setpoint
        self.setpoint_errors = 0  # setpoints rejected or unanswered

    # ------------------------------------------------------------------ link settings
    @property
    def ack_timeout_s(self) -> float:
        return self._link.ack_timeout_s

    @property
    def retries(self) -> int:
        return self._link.retries

    @property
    def link_timeout_s(self) -> float:
        return self._link.link_timeout_s

    @property
    def last_round_trip_s(self) -> float | None:
        """Round trip of the latest acknowledged command, s."""
        return self._link.last_round_trip_s

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the port and start the link (no handshake; see :meth:`connect`)."""
        self._link.open()

    def connect(self) -> p.DeviceInfo:
        """Open if needed and do the IDENTIFY handshake; apply limits and the telemetry rate.

        Keeps trying for ``connect_wait_s`` after the port was opened (an Arduino resets when
        its port opens). Returns the device info. Raises :class:`VersionMismatch` when the
        device speaks another protocol version, :class:`LinkTimeout` when it does not answer.
        """
        self.open()
        return self._handshake()

    def close(self) -> None:
        """Output off (best effort), stop the link, close the port. Idempotent."""
        if not self._link.usable and not self._link.running:
            self._link.close()
            return
        self.make_safe()
        self._link.close()

    def __enter__(self) -> CurrentSource:
        try:
            self.connect()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reconnect(self) -> p.DeviceInfo:
        """Close and reopen the port, then redo the handshake (limits and telemetry re-applied;
        waits for the bootloader like :meth:`connect`)."""
        if not self._link.running:
            return self.connect()
        self._link.reopen()
        info = self._handshake()
        self._link.count_reconnect()
        return info

    # ------------------------------------------------------------------ commands
    def identify(self) -> p.DeviceInfo:
        """IDENTIFY without changing any setting; returns the device info."""
        return self._handshake(configure=False, wait_s=0.0)

    def enable(self, on: bool) -> None:
        """Output on or off. On is refused with :class:`DeviceFault` while a fault is latched."""
        try:
            self._command(*p.enable(on))
        except CommandRejected as exc:
            if exc.status == Status.FAULT_ACTIVE:
                text = self.fault_text() or "fault latched"
                raise DeviceFault(exc.command, exc.status, f"ENABLE refused: {text}") from None
            raise

    def set_current(self, current_a: float, *, wait: bool = False) -> Status | None:
        """Current setpoint, A (sent in mA); also renews the device's setpoint lease.

        Refused locally (ValueError) outside 0 … the device's hard limit; above the active
        limit the device clamps it. Returns at once (None) and the ACK is checked in the
        background; with ``wait=True`` waits for it and returns its status (``OK`` or
        ``CLAMPED``; :class:`CommandRejected` / :class:`LinkTimeout` otherwise).
        """
        info = self._require_info()
        if not 0.0 <= current_a <= info.hard_limit_a + 1e-9:
            raise ValueError(
                f"current {current_a} A outside 0 … {info.hard_limit_a} A (device hard limit)"
            )
        type_, payload = p.set_current(current_a)
        if wait:
            ack = self._command(type_, payload)
            self._note_setpoint_status(Status(ack.status), current_a)
            return Status(ack.status)
        self._link.post(
            type_, payload, SETPOINT_SLOT, lambda req: self._on_setpoint_done(req, current_a)
        )
        return None

    def set_limits(self, current_limit_a: float, host_timeout_s: float) -> None:
        """Active current limit, A (≤ device hard limit), and host timeout, s (0.02 … 5)."""
        info = self._require_info()
        if current_limit_a > info.hard_limit_a + 1e-9:
            raise ValueError(
                f"limit {current_limit_a} A above the hard limit {info.hard_limit_a} A"
            )
        self._command(*p.set_limits(current_limit_a, host_timeout_s))
        with self._lock:
            self._cfg_limit_a, self._cfg_host_timeout_s = current_limit_a, host_timeout_s
            self._limit_a, self._host_timeout_s = current_limit_a, host_timeout_s

    def set_lease(self, lease_s: float) -> None:
        """Setpoint lease, s (0.02 … 5): the device turns the output off when no SET_CURRENT
        came for this long (PINGs do not count). Kept for every reconnect."""
        self._command(*p.set_lease(lease_s))
        with self._lock:
            self._cfg_lease_s = lease_s

    @property
    def lease_s(self) -> float:
        """The setpoint lease in force, s (the device default until :meth:`set_lease`)."""
        return p.LEASE_DEFAULT_S if self._cfg_lease_s is None else self._cfg_lease_s

    def set_probe_current(self, current_a: float) -> None:
        """Probe current, A (0 = off, else up to :data:`~smabench.drivers.protocol.PROBE_MAX_A`,
        0.1 A; sent in mA): while the output is enabled the device regulates the larger of the
        setpoint and the probe, so the wire's resistance is measured while it cools (setpoint 0).
        Waits for the ACK. Refused locally (ValueError, nothing sent) outside 0 … 0.1 A.

        Not leased (it is not a setpoint: the telemetry's setpoint stays the host's) and not
        stored: everything that turns the output off (``enable(False)``, :meth:`make_safe`, the
        host timeout, the lease, a latched fault, a reset) turns the probe off too, and it stays
        off until the next call; a reconnect does not re-apply it (PROTOCOL.md, SET_PROBE)."""
        type_, payload = p.set_probe(current_a)
        self._command(type_, payload)

    def get_calibration(self) -> p.Calibration:
        """The calibration the device uses (GET_CALIBRATION), also kept in :attr:`calibration`.
        Telemetry flag ``CAL_DEFAULT`` says when the EEPROM held none (defaults in use)."""
        cal = p.Calibration.from_data(self._command(*p.get_calibration()).data)
        self.calibration = cal
        return cal

    def set_calibration(self, cal: p.Calibration) -> None:
        """Write ``cal`` into the device's EEPROM (SET_CALIBRATION). The device refuses it while
        the output is on (:class:`CommandRejected`, status ``OUTPUT_ON``); read it back with
        :meth:`get_calibration` to check it stuck."""
        self.calibration = None  # unknown until read back
        self._command(*p.set_calibration(cal))

    def get_heat_model(self) -> p.HeatModel:
        """The wire heat model of the device's energy budget (GET_HEAT_MODEL)."""
        return p.HeatModel.from_data(self._command(*p.get_heat_model()).data)

    def set_heat_model(self, model: p.HeatModel) -> None:
        """Write the energy budget's heat model into EEPROM (SET_HEAT_MODEL); refused while the
        output is on (``OUTPUT_ON``), like :meth:`set_calibration`."""
        self._command(*p.set_heat_model(model))

    def set_telemetry(self, period_s: float) -> None:
        """Telemetry period, s (0 = off, else 0.005 … 1)."""
        self._command(*p.set_telemetry(period_s))
        self.telemetry_period_s = period_s

    def clear_faults(self) -> None:
        """Clear latched faults and events; the output stays off until :meth:`enable`."""
        self._command(*p.clear_faults())
        with self._lock:
            self._last_fault_flags = 0

    def ping(self) -> float:
        """PING; returns the round trip, s."""
        req = self._link.submit(*p.ping())
        self._link.wait(req)
        return req.round_trip_s

    def make_safe(self, timeout_s: float = 0.15) -> bool:
        """Output off: ENABLE 0 ahead of anything queued, best effort with a short timeout.
        Never raises; idempotent; any thread, any time (False before connect / after close).

        Returns True when the device acknowledged it. When the link is down the device turns
        itself off after its host timeout (and its setpoint lease) anyway.
        """
        if not self._link.usable or not self._link.port_up:
            return False
        try:
            self._link.cancel_slot(SETPOINT_SLOT)
            req = self._link.submit(
                *p.enable(False), ack_timeout_s=timeout_s / 2, retries=1, urgent=True
            )
            self._link.wait(req, total_timeout_s=timeout_s + 0.05)
            return True
        except Exception as exc:  # never raises: this is the emergency path
            log.warning("make_safe: ENABLE 0 not confirmed: %s", exc)
            return False

    # ------------------------------------------------------------------ telemetry
    def latest(self) -> p.Telemetry | None:
        """Latest telemetry frame, or None before the first one."""
        with self._lock:
            return self._latest

    @property
    def last_ack_host_time(self) -> float | None:
        """Host clock when the newest ACK was decoded, on the telemetry's ``host_time`` clock
        and in the byte stream's order with it (None before the first): a frame with a later
        ``host_time`` left the device after that command arrived."""
        return self._link.last_ack_at

    def telemetry_age_s(self) -> float | None:
        """Host time since the latest telemetry frame arrived, s (None before the first)."""
        t = self.latest()
        return None if t is None else time.monotonic() - t.host_time

    def telemetry_history(self) -> list[p.Telemetry]:
        """Copy of the kept telemetry frames, oldest first."""
        with self._lock:
            return list(self.history)

    def subscribe(self, callback: Callable[[p.Telemetry], None]) -> Callable[[], None]:
        """Call ``callback(telemetry)`` for every frame (from the owner thread: keep it short).
        Returns a function that unsubscribes."""
        with self._lock:
            self._subscribers.append(callback)

        def unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return unsubscribe

    def wait_telemetry(
        self, predicate: Callable[[p.Telemetry], bool] = lambda t: True, timeout_s: float = 1.0
    ) -> p.Telemetry:
        """Wait for the next telemetry frame satisfying ``predicate``; LinkTimeout after
        ``timeout_s``. Frames received before the call are not considered."""
        deadline = time.monotonic() + timeout_s
        with self._tel_cond:
            seen = self._latest
            while True:
                t = self._latest
                if t is not None and t is not seen:
                    seen = t
                    if predicate(t):
                        return t
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkTimeout(f"no matching telemetry within {timeout_s} s (latest: {t})")
                self._tel_cond.wait(left)

    def fault_text(self) -> str:
        """Human-readable latched faults and events of the latest telemetry, and a lost link;
        ``''`` when all is well."""
        parts = []
        t = self.latest()
        if t is not None:
            text = p.fault_text(t.flags)
            if text:
                parts.append(text)
        if self._link.running and self.info is not None and not self.link_ok:
            parts.append(f"link lost ({self._link.port_error or 'no answer'})")
        return "; ".join(parts)

    # ------------------------------------------------------------------ state
    @property
    def link_ok(self) -> bool:
        """Port open, handshake done, and a valid frame received within ``link_timeout_s`` (or
        bytes waiting: a held-up reader, not a silent device)."""
        return self._link.link_ok

    @property
    def host_timeout_s(self) -> float:
        return self._host_timeout_s

    @property
    def limit_a(self) -> float | None:
        """Active current limit, A (None before the handshake)."""
        if self._limit_a is not None:
            return self._limit_a
        return self.info.hard_limit_a if self.info else None

    @property
    def keepalive_interval_s(self) -> float:
        """PING after this long without any frame sent: host_timeout / 3, at most 0.1 s."""
        return min(self._host_timeout_s / 3.0, 0.1)

    def counters(self) -> LinkCounters:
        n = self._link.stats()
        t = self.latest()
        return LinkCounters(
            tx_frames=n["tx"],
            rx_packets=n["rx_packets"],
            crc_errors=n["crc_errors"],
            frame_errors=n["frame_errors"],
            retries=n["retries"],
            timeouts=n["timeouts"],
            reconnects=n["reconnects"],
            keepalives=n["keepalives"],
            device_crc_errors=t.crc_errors if t else 0,
            device_frame_errors=t.frame_errors if t else 0,
            setpoints_superseded=n["superseded"],
        )

    def pause_keepalive(self, paused: bool = True) -> None:
        """Test hook: stop (or resume) the automatic PINGs, to let the device's host timeout
        trip while the driver is alive."""
        self._link.pause_keepalive(paused)

    def send_raw(self, data: bytes) -> None:
        """Test/diagnostic hook: have the owner thread write ``data`` as is (e.g. a corrupted
        frame). Does not count as a sent frame for the keepalive."""
        self._link.send_raw(data)

    # ------------------------------------------------------------------ internals
    def _require_info(self) -> p.DeviceInfo:
        if self.info is None:
            raise CurrentSourceError("not connected: call connect() first")
        return self.info

    def _command(
        self,
        type_: MsgType | int,
        payload: bytes,
        *,
        accept: tuple[int, ...] = (Status.OK, Status.CLAMPED),
        check: bool = True,
    ) -> p.Ack:
        ack = self._link.call(type_, payload)
        if check and ack.status not in accept:
            raise CommandRejected(type_, ack.status)
        return ack

    def _identify_ack(self, wait_s: float | None) -> p.Ack:
        """IDENTIFY until answered; while the device may still be in its bootloader (up to
        ``connect_wait_s`` after the port opened, or ``wait_s`` from now) a silence is retried."""
        now = time.monotonic()
        deadline = (
            self._link.opened_at + self.connect_wait_s if wait_s is None else now + wait_s
        )
        told = False
        while True:
            try:
                return self._command(*p.identify(self.protocol_version), check=False)
            except LinkTimeout as exc:
                left = deadline - time.monotonic()
                if left <= 0 or not self._link.usable or not self._link.port_up:
                    raise
                if not told:
                    log.info(
                        "%s: no answer to IDENTIFY yet; trying %.1f s more: opening the port "
                        "resets an Arduino (DTR) and its bootloader waits about 1 s before "
                        "the firmware starts (%s)",
                        self.port_name,
                        left,
                        exc,
                    )
                    told = True

    def _handshake(self, configure: bool = True, wait_s: float | None = None) -> p.DeviceInfo:
        t0 = time.monotonic()
        ack = self._identify_ack(wait_s)
        info = p.DeviceInfo.from_data(ack.data) if len(ack.data) >= 6 else None
        if ack.status == Status.VERSION_MISMATCH or (
            info is not None and info.protocol_version != p.PROTOCOL_VERSION
        ):
            dev = info.protocol_version if info else "?"
            raise VersionMismatch(
                f"device {info.name if info else '?'} speaks protocol v{dev}, "
                f"host v{p.PROTOCOL_VERSION} (sent v{self.protocol_version})"
            )
        if ack.status != Status.OK or info is None:
            raise CommandRejected(MsgType.IDENTIFY, ack.status, "IDENTIFY: no device info")
        self.info = info
        if configure:
            with self._lock:
                limit, host_timeout = self._cfg_limit_a, self._cfg_host_timeout_s
            if limit is not None or host_timeout is not None:
                self._command(
                    *p.set_limits(
                        info.hard_limit_a if limit is None else limit,
                        p.HOST_TIMEOUT_DEFAULT_S if host_timeout is None else host_timeout,
                    )
                )
                self._host_timeout_s = host_timeout or p.HOST_TIMEOUT_DEFAULT_S
            if self._cfg_lease_s is not None:
                self._command(*p.set_lease(self._cfg_lease_s))
            self._command(*p.set_telemetry(self.telemetry_period_s))
        self._link.set_ready(True)
        log.info(
            "connected to %s fw %s on %s in %.2f s (hard limit %.3f A, protocol v%d)",
            info.name,
            info.firmware,
            self.port_name,
            time.monotonic() - t0,
            info.hard_limit_a,
            info.protocol_version,
        )
        return info

    def _note_setpoint_status(self, status: Status, current_a: float) -> None:
        previous, self.setpoint_status = self.setpoint_status, status
        if status == Status.CLAMPED and previous != Status.CLAMPED:
            log.warning(
                "setpoint %.3f A clamped to the active limit %s A", current_a, self._limit_a
            )
        elif previous == Status.CLAMPED and status == Status.OK:
            log.info("setpoint %.3f A no longer clamped", current_a)

    def _on_setpoint_done(self, req: Request, current_a: float) -> None:
        """Owner thread: the ACK (or the failure) of a posted setpoint."""
        if req.error is not None or req.ack is None:
            self.setpoint_errors += 1
            log.debug("setpoint %.3f A not acknowledged: %s", current_a, req.error)
            return
        if req.ack.status not in (Status.OK, Status.CLAMPED):
            self.setpoint_errors += 1
            log.warning("setpoint %.3f A rejected: %s", current_a, req.ack.status_name)
            return
        self._note_setpoint_status(Status(req.ack.status), current_a)

    def _on_telemetry(self, pkt: p.Packet, now: float) -> None:
        try:
            t = p.Telemetry.from_payload(pkt.payload, host_time=now)
        except p.ProtocolError as exc:
            log.warning("bad telemetry: %s", exc)
            return
        with self._tel_cond:
            self._latest = t
            self.history.append(t)
            subscribers = list(self._subscribers)
            new_faults = t.flags & ~self._last_fault_flags & ~(
                p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE | p.Flag.CUT_OPEN
            )
            self._last_fault_flags = int(t.flags)
            self._tel_cond.notify_all()
        text = p.fault_text(new_faults) if new_faults else ""
        if text:  # (status bits such as CAL_DEFAULT have no fault text: not worth a warning)
            log.warning("device fault/event: %s", text)
        for cb in subscribers:
            try:
                cb(t)
            except Exception:
                log.exception("telemetry subscriber failed")
