"""Host driver of the SMA current driver (``firmware/PROTOCOL.md``) over a serial port.

One owner thread does all reading and writing of the port; the public methods are thread-safe:
they enqueue a command, and wait for its ACK (retries on timeout, typed errors). The owner thread
also keeps the device's host watchdog fed (PING when no frame was sent for ``host_timeout / 3``),
collects telemetry, watches the link and reopens the port after an I/O error.

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
import contextlib
import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import serial
from smabench.drivers import protocol as p

log = logging.getLogger(__name__)

MsgType = p.MsgType
Status = p.Status


# ---------------------------------------------------------------------------- errors
class CurrentSourceError(Exception):
    """Base class of the current-source driver errors."""


class LinkTimeout(CurrentSourceError, TimeoutError):  # noqa: N818 (names of the API)
    """No ACK within the timeout and retries, or the port is down."""


class CommandRejected(CurrentSourceError):  # noqa: N818 (names of the API)
    """The device answered with an ACK status other than OK (or CLAMPED)."""

    def __init__(self, command: int, status: int, message: str = "") -> None:
        self.command = command
        self.status = status
        cmd_name = _type_name(command)
        try:
            status_name = Status(status).name
        except ValueError:
            status_name = f"status {status}"
        super().__init__(message or f"{cmd_name} rejected: {status_name}")


class VersionMismatch(CurrentSourceError):  # noqa: N818 (names of the API)
    """The device speaks another protocol version."""


class DeviceFault(CommandRejected):
    """ENABLE refused because a fault is latched on the device (clear it with clear_faults)."""


# ---------------------------------------------------------------------------- internals
def _type_name(type_: int) -> str:
    try:
        return MsgType(type_).name
    except ValueError:
        return f"type 0x{type_:02x}"


@dataclass(eq=False)
class _Request:
    type: MsgType
    payload: bytes
    ack_timeout_s: float
    retries: int
    done: threading.Event = field(default_factory=threading.Event)
    seqs: list[int] = field(default_factory=list)
    attempts: int = 0
    deadline: float = 0.0
    sent_at: float = 0.0
    ack: p.Ack | None = None
    error: BaseException | None = None
    cancelled: bool = False
    round_trip_s: float = 0.0

    def finish(self, ack: p.Ack | None = None, error: BaseException | None = None) -> None:
        self.ack, self.error = ack, error
        self.done.set()


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


class CurrentSource:
    """Client of the current driver firmware.

    Args:
        port: port name or pyserial URL (``/dev/ttyUSB0``, ``loop://``), or an already-constructed
            serial object (pyserial API: read, write, in_waiting, close; tests use a fake).
        ack_timeout_s: wait for one ACK, s. A command is sent ``1 + retries`` times at most.
        retries: resends after an ACK timeout (all commands are idempotent).
        telemetry_period_s: telemetry rate asked for at connect, s (0 = off).
        current_limit_a, host_timeout_s: limits sent at connect (``None`` = device defaults:
            hard limit, 0.25 s).
        keepalive: let the owner thread PING to feed the device's host watchdog.
        link_timeout_s: the link counts as lost when nothing valid was received for this long.
        max_reconnect_attempts: automatic reopen attempts after a port error before giving up.
        history: number of telemetry frames kept in :attr:`history`.
        protocol_version: version sent in IDENTIFY (only tests change it).
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
    ) -> None:
        if isinstance(port, str):
            self.port_name = port
            self._port_obj = None
        else:
            self.port_name = getattr(port, "port", None) or repr(port)
            self._port_obj = port
        self.ack_timeout_s = ack_timeout_s
        self.retries = retries
        self.telemetry_period_s = telemetry_period_s
        self.link_timeout_s = link_timeout_s
        self.max_reconnect_attempts = max_reconnect_attempts
        self.protocol_version = protocol_version
        self._keepalive_enabled = keepalive
        self._keepalive_paused = False
        # configuration re-applied after every handshake
        self._cfg_limit_a = current_limit_a
        self._cfg_host_timeout_s = host_timeout_s
        self._host_timeout_s = host_timeout_s or p.HOST_TIMEOUT_DEFAULT_S
        self._limit_a: float | None = current_limit_a
        self.info: p.DeviceInfo | None = None

        self._ser: Any = None
        self._rx = p.FrameReceiver()
        self._queue: queue.Queue[_Request] = queue.Queue()
        self._current: _Request | None = None
        self._lock = threading.RLock()
        self._tel_cond = threading.Condition(self._lock)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._seq = itertools.count()
        self._keepalive_seqs: dict[int, float] = {}
        self._raw_out: collections.deque[bytes] = collections.deque()
        self._last_tx = 0.0
        self._last_rx = 0.0
        self._connected = False  # handshake done on the current port
        self._lost = False
        self._port_error: str | None = None
        self._gave_up = False
        self._reopen_at: float | None = None
        self._reopen_attempts = 0
        self._reopen_request: tuple[threading.Event, list[BaseException | None]] | None = None
        self._resync_thread: threading.Thread | None = None
        self._closing = False

        self._latest: p.Telemetry | None = None
        self.history: collections.deque[p.Telemetry] = collections.deque(maxlen=history)
        self._subscribers: list[Callable[[p.Telemetry], None]] = []
        self._last_fault_flags = 0
        self._n = dict.fromkeys(
            ("tx", "retries", "timeouts", "reconnects", "keepalives", "handshakes"), 0
        )
        self.last_round_trip_s: float | None = None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the port and start the owner thread (no handshake; see :meth:`connect`)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._closing = False
        self._gave_up = False
        try:
            self._ser = self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CurrentSourceError(f"cannot open {self.port_name}: {exc}") from exc
        self._thread = threading.Thread(
            target=self._run, name=f"CurrentSource({self.port_name})", daemon=True
        )
        self._thread.start()

    def connect(self) -> p.DeviceInfo:
        """Open if needed and do the IDENTIFY handshake; apply limits and the telemetry rate.

        Returns the device info. Raises :class:`VersionMismatch` when the device speaks another
        protocol version, :class:`LinkTimeout` when it does not answer.
        """
        self.open()
        return self._handshake()

    def close(self) -> None:
        """Output off (best effort), stop the owner thread, close the port. Idempotent."""
        if self._thread is None:
            return
        self.make_safe()
        self._closing = True
        self._stop.set()
        self._wake_owner()
        self._thread.join(timeout=2.0)
        if self._thread.is_alive():
            log.error("owner thread did not stop")
        self._thread = None
        self._fail_all(CurrentSourceError("closed"))
        self._close_port()
        self._connected = False

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
        """Close and reopen the port, then redo the handshake (limits and telemetry re-applied)."""
        if self._thread is None:
            return self.connect()
        done = threading.Event()
        result: list[BaseException | None] = [None]
        with self._lock:
            self._reopen_request = (done, result)
        self._wake_owner()
        if not done.wait(5.0):
            raise LinkTimeout("reopen did not complete")
        if result[0] is not None:
            raise LinkTimeout(f"reopen of {self.port_name} failed: {result[0]}") from result[0]
        info = self._handshake()
        with self._lock:
            self._n["reconnects"] += 1
        return info

    # ------------------------------------------------------------------ commands
    def identify(self) -> p.DeviceInfo:
        """IDENTIFY without changing any setting; returns the device info."""
        return self._handshake(configure=False)

    def enable(self, on: bool) -> None:
        """Output on or off. On is refused with :class:`DeviceFault` while a fault is latched."""
        try:
            self._command(*p.enable(on))
        except CommandRejected as exc:
            if exc.status == Status.FAULT_ACTIVE:
                text = self.fault_text() or "fault latched"
                raise DeviceFault(exc.command, exc.status, f"ENABLE refused: {text}") from None
            raise

    def set_current(self, current_a: float) -> Status:
        """Current setpoint, A (sent in mA). Refused locally (ValueError) above the device's
        hard limit; above the active limit the device clamps it (returns ``Status.CLAMPED``)."""
        info = self._require_info()
        if not 0.0 <= current_a <= info.hard_limit_a + 1e-9:
            raise ValueError(
                f"current {current_a} A outside 0 … {info.hard_limit_a} A (device hard limit)"
            )
        ack = self._command(*p.set_current(current_a))
        if ack.status == Status.CLAMPED:
            log.warning(
                "setpoint %.3f A clamped to the active limit %s A", current_a, self._limit_a
            )
        return Status(ack.status)

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
        req = self._submit(*p.ping())
        self._wait(req)
        return req.round_trip_s

    def make_safe(self, timeout_s: float = 0.15) -> bool:
        """Output off: ENABLE 0, best effort with a short timeout. Never raises; idempotent.

        Returns True when the device acknowledged it. When the link is down the device turns
        itself off after its host timeout anyway.
        """
        if self._thread is None or self._closing or self._gave_up or self._ser is None:
            return False
        try:
            req = self._submit(*p.enable(False), ack_timeout_s=timeout_s / 2, retries=1)
            self._wait(req, total_timeout_s=timeout_s + 0.05)
            return True
        except Exception as exc:  # never raises: this is the emergency path
            log.warning("make_safe: ENABLE 0 not confirmed: %s", exc)
            return False

    # ------------------------------------------------------------------ telemetry
    def latest(self) -> p.Telemetry | None:
        """Latest telemetry frame, or None before the first one."""
        with self._lock:
            return self._latest

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
        if self._thread is not None and self.info is not None and not self.link_ok:
            parts.append(f"link lost ({self._port_error or 'no answer'})")
        return "; ".join(parts)

    # ------------------------------------------------------------------ state
    @property
    def link_ok(self) -> bool:
        """Port open, handshake done, and a valid frame received within ``link_timeout_s``."""
        with self._lock:
            return (
                self._ser is not None
                and self._connected
                and not self._lost
                and time.monotonic() - self._last_rx < self.link_timeout_s
            )

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
        with self._lock:
            t = self._latest
            return LinkCounters(
                tx_frames=self._n["tx"],
                rx_packets=self._rx.packets,
                crc_errors=self._rx.crc_errors,
                frame_errors=self._rx.frame_errors,
                retries=self._n["retries"],
                timeouts=self._n["timeouts"],
                reconnects=self._n["reconnects"],
                keepalives=self._n["keepalives"],
                device_crc_errors=t.crc_errors if t else 0,
                device_frame_errors=t.frame_errors if t else 0,
            )

    def pause_keepalive(self, paused: bool = True) -> None:
        """Test hook: stop (or resume) the automatic PINGs, to let the device's host timeout
        trip while the driver is alive."""
        self._keepalive_paused = paused
        self._wake_owner()

    def send_raw(self, data: bytes) -> None:
        """Test/diagnostic hook: have the owner thread write ``data`` as is (e.g. a corrupted
        frame). Does not count as a sent frame for the keepalive."""
        self._raw_out.append(bytes(data))
        self._wake_owner()

    # ------------------------------------------------------------------ internals: callers
    def _require_info(self) -> p.DeviceInfo:
        if self.info is None:
            raise CurrentSourceError("not connected: call connect() first")
        return self.info

    def _handshake(self, configure: bool = True) -> p.DeviceInfo:
        ack = self._command(*p.identify(self.protocol_version), check=False)
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
            self._command(*p.set_telemetry(self.telemetry_period_s))
        with self._lock:
            self._connected = True
            self._lost = False
            self._n["handshakes"] += 1
        log.info(
            "connected to %s fw %s on %s (hard limit %.3f A, protocol v%d)",
            info.name,
            info.firmware,
            self.port_name,
            info.hard_limit_a,
            info.protocol_version,
        )
        return info

    def _command(
        self,
        type_: MsgType,
        payload: bytes,
        *,
        accept: tuple[int, ...] = (Status.OK, Status.CLAMPED),
        check: bool = True,
    ) -> p.Ack:
        req = self._submit(type_, payload)
        ack = self._wait(req)
        if check and ack.status not in accept:
            raise CommandRejected(type_, ack.status)
        return ack

    def _submit(
        self,
        type_: MsgType,
        payload: bytes,
        ack_timeout_s: float | None = None,
        retries: int | None = None,
    ) -> _Request:
        if self._thread is None or self._stop.is_set():
            raise CurrentSourceError("not open: call connect() first")
        if self._gave_up:
            raise LinkTimeout(f"port {self.port_name} down: {self._port_error}")
        req = _Request(
            type_,
            payload,
            self.ack_timeout_s if ack_timeout_s is None else ack_timeout_s,
            self.retries if retries is None else retries,
        )
        self._queue.put(req)
        self._wake_owner()
        return req

    def _wait(self, req: _Request, total_timeout_s: float | None = None) -> p.Ack:
        if total_timeout_s is None:
            total_timeout_s = (req.retries + 1) * req.ack_timeout_s + 1.0
        if not req.done.wait(total_timeout_s):
            req.cancelled = True
            with self._lock:
                self._n["timeouts"] += 1
            raise LinkTimeout(f"{_type_name(req.type)}: no answer within {total_timeout_s:.2f} s")
        if req.error is not None:
            raise req.error
        assert req.ack is not None
        return req.ack

    def _wake_owner(self) -> None:
        self._wake.set()
        ser = self._ser
        if ser is not None and hasattr(ser, "cancel_read"):
            with contextlib.suppress(Exception):  # closed meanwhile: the owner is awake anyway
                ser.cancel_read()

    # ------------------------------------------------------------------ internals: owner thread
    def _open_port(self) -> Any:
        if self._port_obj is not None:
            ser = self._port_obj
            if not getattr(ser, "is_open", True) and hasattr(ser, "open"):
                ser.open()
        else:
            ser = serial.serial_for_url(
                self.port_name,
                baudrate=p.BAUDRATE,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=0.01,
                write_timeout=0.5,
            )
        self._rx.reset()
        # a lone delimiter ends whatever partial frame the device may have buffered
        ser.write(p.DELIMITER)
        self._last_rx = time.monotonic()
        self._port_error = None
        log.debug("port %s open", self.port_name)
        return ser

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception as exc:
                log.debug("close: %s", exc)

    def _run(self) -> None:
        log.debug("owner thread running")
        try:
            while not self._stop.is_set():
                self._wake.clear()
                self._handle_reopen_request()
                if self._ser is None:
                    self._reopen_step()
                    continue
                try:
                    self._service()
                except (serial.SerialException, OSError) as exc:
                    self._on_port_error(exc)
        except Exception:
            log.exception("owner thread crashed")
            self._fail_all(CurrentSourceError("owner thread crashed"))
            with self._lock:
                self._connected = False
                self._gave_up = True
        finally:
            if self._current is not None:
                self._current.finish(error=CurrentSourceError("closed"))
                self._current = None
            log.debug("owner thread stopped")

    def _service(self) -> None:
        now = time.monotonic()
        while self._raw_out:
            self._ser.write(self._raw_out.popleft())
        cur = self._current
        if cur is not None and cur.cancelled:
            cur = self._current = None
        if cur is None:
            cur = self._next_request()
            if cur is not None:
                self._send_request(cur, now)
        elif now >= cur.deadline:
            if cur.attempts <= cur.retries:
                with self._lock:
                    self._n["retries"] += 1
                log.debug("%s: no ACK, retry %d", _type_name(cur.type), cur.attempts)
                self._send_request(cur, now)
            else:
                self._current = None
                cur.finish(
                    error=LinkTimeout(f"{_type_name(cur.type)}: no ACK after {cur.attempts} tries")
                )
                with self._lock:
                    self._n["timeouts"] += 1
        if (
            self._keepalive_enabled
            and not self._keepalive_paused
            and self._connected
            and now - self._last_tx >= self.keepalive_interval_s
        ):
            seq = self._send(MsgType.PING, b"", now)
            self._keepalive_seqs[seq] = now
            with self._lock:
                self._n["keepalives"] += 1
        if self._connected and not self._lost and now - self._last_rx > self.link_timeout_s:
            with self._lock:
                self._lost = True
            log.warning("link lost: nothing received for %.0f ms", 1e3 * (now - self._last_rx))
        data = self._ser.read(1)
        if data:
            n = self._ser.in_waiting
            if n:
                data += self._ser.read(n)
            self._dispatch(self._rx.feed(data))

    def _next_request(self) -> _Request | None:
        while True:
            try:
                req = self._queue.get_nowait()
            except queue.Empty:
                return None
            if not req.cancelled:
                return req

    def _send(self, type_: int, payload: bytes, now: float) -> int:
        seq = next(self._seq) & 0xFF
        self._ser.write(p.encode_frame(seq, type_, payload))
        self._last_tx = now
        with self._lock:
            self._n["tx"] += 1
        return seq

    def _send_request(self, req: _Request, now: float) -> None:
        self._current = req
        req.attempts += 1
        req.sent_at = now
        req.deadline = now + req.ack_timeout_s
        req.seqs.append(self._send(req.type, req.payload, now))

    def _dispatch(self, packets: list[p.Packet]) -> None:
        if not packets:
            return
        now = time.monotonic()
        with self._lock:
            self._last_rx = now
            recovered = self._lost and self._connected
            self._lost = False
        if recovered:
            log.warning("link back: redoing the handshake")
            self._start_resync()
        for pkt in packets:
            try:
                if pkt.type == MsgType.ACK:
                    self._on_ack(pkt, now)
                elif pkt.type == MsgType.TELEMETRY:
                    self._on_telemetry(pkt, now)
                else:
                    log.debug("ignored packet type 0x%02x seq %d", pkt.type, pkt.seq)
            except Exception:  # a bad packet must not kill the owner thread
                log.exception("handling packet %s failed", pkt)

    def _on_ack(self, pkt: p.Packet, now: float) -> None:
        try:
            ack = p.Ack.from_payload(pkt.payload)
        except p.ProtocolError as exc:
            log.warning("bad ACK: %s", exc)
            return
        cur = self._current
        if cur is not None and ack.seq in cur.seqs and ack.type == cur.type:
            self._current = None
            cur.round_trip_s = now - cur.sent_at
            self.last_round_trip_s = cur.round_trip_s
            if ack.status not in (Status.OK, Status.CLAMPED):
                log.info("%s: %s", _type_name(cur.type), ack.status_name)
            cur.finish(ack=ack)
            return
        if self._keepalive_seqs.pop(ack.seq, None) is not None and ack.type == MsgType.PING:
            return
        if len(self._keepalive_seqs) > 16:  # forget unanswered keepalives
            for seq in sorted(self._keepalive_seqs, key=self._keepalive_seqs.get)[:-16]:
                del self._keepalive_seqs[seq]
        log.debug("stale ACK seq %d type 0x%02x", ack.seq, ack.type)

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
            new_faults = t.flags & ~self._last_fault_flags & ~(p.Flag.ENABLED | p.Flag.LIMIT_ACTIVE)
            self._last_fault_flags = int(t.flags)
            self._tel_cond.notify_all()
        if new_faults:
            log.warning("device fault/event: %s", p.fault_text(new_faults))
        for cb in subscribers:
            try:
                cb(t)
            except Exception:
                log.exception("telemetry subscriber failed")

    def _fail_all(self, error: BaseException) -> None:
        cur, self._current = self._current, None
        if cur is not None:
            cur.finish(error=error)
        while True:
            try:
                self._queue.get_nowait().finish(error=error)
            except queue.Empty:
                break

    def _on_port_error(self, exc: BaseException) -> None:
        log.warning("port %s error: %s", self.port_name, exc)
        self._close_port()
        with self._lock:
            self._connected = False
            self._port_error = str(exc)
        self._fail_all(LinkTimeout(f"port {self.port_name} error: {exc}"))
        self._reopen_at = time.monotonic() + 0.05

    def _reopen_step(self) -> None:
        """Owner thread, port closed after an error: reopen with backoff, bounded."""
        self._fail_all(LinkTimeout(f"port {self.port_name} down: {self._port_error}"))
        now = time.monotonic()
        if self._gave_up or self._reopen_at is None:
            self._wake.wait(0.05)
            return
        if now < self._reopen_at:
            self._wake.wait(self._reopen_at - now)
            return
        self._reopen_attempts += 1
        try:
            self._ser = self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            if self._reopen_attempts >= self.max_reconnect_attempts:
                log.error(
                    "port %s: giving up after %d reopen attempts: %s",
                    self.port_name,
                    self._reopen_attempts,
                    exc,
                )
                with self._lock:
                    self._gave_up = True
                    self._port_error = f"gave up after {self._reopen_attempts} attempts: {exc}"
                self._reopen_at = None
                return
            backoff = min(1.0, 0.05 * 2**self._reopen_attempts)
            log.info(
                "port %s: reopen failed (%s), next try in %.2f s", self.port_name, exc, backoff
            )
            self._reopen_at = now + backoff
            return
        log.warning("port %s reopened: redoing the handshake", self.port_name)
        self._reopen_at = None
        self._start_resync(count_reconnect=True)

    def _handle_reopen_request(self) -> None:
        with self._lock:
            request, self._reopen_request = self._reopen_request, None
        if request is None:
            return
        done, result = request
        self._close_port()
        with self._lock:
            self._connected = False
            self._gave_up = False
        self._fail_all(LinkTimeout("port reopened"))
        try:
            self._ser = self._open_port()
        except Exception as exc:
            result[0] = exc
            with self._lock:
                self._port_error = str(exc)
            self._reopen_at = time.monotonic() + 0.05
            self._reopen_attempts = 0
        done.set()

    def _start_resync(self, count_reconnect: bool = False) -> None:
        """Redo the handshake from a helper thread (the owner must keep serving the port)."""
        if self._resync_thread is not None and self._resync_thread.is_alive():
            return

        def resync() -> None:
            for attempt in range(1, self.max_reconnect_attempts + 1):
                if self._stop.is_set() or self._closing:
                    return
                try:
                    self._handshake()
                except VersionMismatch as exc:
                    log.error("handshake after reconnect: %s", exc)
                    return
                except CurrentSourceError as exc:
                    log.warning("handshake after reconnect failed (try %d): %s", attempt, exc)
                    self._stop.wait(min(1.0, 0.05 * 2**attempt))
                    continue
                self._reopen_attempts = 0
                if count_reconnect:
                    with self._lock:
                        self._n["reconnects"] += 1
                return
            log.error("no handshake after %d tries: call reconnect()", self.max_reconnect_attempts)

        self._resync_thread = threading.Thread(
            target=resync, name="CurrentSource-resync", daemon=True
        )
        self._resync_thread.start()
