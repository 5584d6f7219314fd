"""The framed serial link to the current driver (``firmware/PROTOCOL.md``), without the device.

:class:`FramedLink` owns the port: ONE owner thread does all reading and writing. It numbers the
frames (sequence byte), sends one command at a time and matches its ACK (stop-and-wait, resent
with a new sequence number after an ACK timeout), keeps the device's host watchdog fed with PINGs
when nothing else was sent, watches for silence (link lost / back), reopens the port after an I/O
error (bounded, with backoff) and hands every other packet to the handler registered for its
type (telemetry). What the commands mean, the handshake and the telemetry store belong to the
device class (:mod:`.current_source`).

Two ways to send:

* :meth:`FramedLink.submit` / :meth:`FramedLink.call`: a command whose ACK the caller waits for;
* :meth:`FramedLink.post`: fire and forget into a *slot* (e.g. the current setpoint). The call
  returns at once; a posted command that is still queued when the next one for the same slot
  arrives is replaced by it (the newer value goes out, never a stale one), so a control loop that
  renews its setpoint every tick never waits for a round trip and never piles up a backlog.

Times in s (``time.monotonic``). Thread-safe unless a method says otherwise.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import serial

from smabench.drivers import protocol as p

log = logging.getLogger(__name__)

REOPEN_FIRST_DELAY_S = 0.05  # first reopen attempt after a port error
REOPEN_MAX_BACKOFF_S = 1.0
MAX_KEEPALIVES_TRACKED = 16
READ_TIMEOUT_S = 0.01  # the owner thread's longest blocking read (it is woken earlier on work)


class LinkError(Exception):
    """Base class of the link (and current-source driver) errors."""


class LinkTimeout(LinkError, TimeoutError):  # noqa: N818 (names of the API)
    """No ACK within the timeout and retries, or the port is down."""


BY_ID_DIR_ENV = "SMABENCH_SERIAL_BY_ID"
"""Environment variable naming the folder of stable serial names (default
``/dev/serial/by-id``, udev's: one symlink per USB adapter, named after its serial number)."""


PTY_GONE = (
    "the pseudo-terminal's other end closed (a mock bench or an emulator ended); its number "
    "goes to the next program that opens a pty, so it is not reopened"
)


def is_pseudo_terminal(port: str) -> bool:
    """Whether ``port`` is a Unix98 pseudo-terminal (``/dev/pts/N``: a mock bench, simavr's
    harness, socat), whose device never comes back once its other end closed."""
    return os.path.abspath(port).startswith("/dev/pts/")  # a stable name links to it: followed


def stable_port_name(port: str) -> str | None:
    """The stable name (a symlink in ``/dev/serial/by-id``) of the device ``port`` is now, so
    a reopen finds the adapter again when it comes back under another name (``/dev/ttyUSB0`` →
    ``/dev/ttyUSB1`` after a replug or a hub reset); None when there is none."""
    folder = os.environ.get(BY_ID_DIR_ENV, "/dev/serial/by-id")
    try:
        real = os.path.realpath(port)
        names = sorted(os.listdir(folder))
    except OSError:
        return None
    for name in names:
        path = os.path.join(folder, name)
        if os.path.realpath(path) == real and path != port:
            return path
    return None


def lock_holders(port: str) -> list[str]:
    """The processes holding an exclusive lock (``flock``, as pyserial's ``exclusive=True``
    takes) on the serial device ``port``, as "pid N (command line)", from ``/proc/locks``;
    empty when none is found (or not on Linux)."""
    try:
        st = os.stat(port)
        with open("/proc/locks", encoding="ascii") as fh:
            locks = fh.read().splitlines()
    except OSError:
        return []
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    holders = []
    for line in locks:
        words = line.split()
        if len(words) >= 6 and words[1] == "FLOCK" and words[5] == want:
            pid = words[4]
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as fh:
                    cmd = fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
            except OSError:
                cmd = "?"
            holders.append(f"pid {pid} ({cmd})")
    return holders


def _open_error(port: str, exc: BaseException) -> str:
    """Why ``port`` could not be opened, naming who holds it when it is locked."""
    if "exclusively lock" in str(exc):
        holders = lock_holders(port)
        who = ", ".join(holders) if holders else "another program"
        return f"cannot open {port}: in use by {who}"
    return f"cannot open {port}: {exc}"


def type_name(type_: int) -> str:
    """``IDENTIFY`` for a known message type, ``type 0x42`` otherwise."""
    try:
        return p.MsgType(type_).name
    except ValueError:
        return f"type 0x{type_:02x}"


@dataclass(eq=False)
class Request:
    """One command on its way: sent up to ``1 + retries`` times until its ACK arrives."""

    type: int
    payload: bytes
    ack_timeout_s: float
    retries: int
    slot: str | None = None  # posted commands: a newer one for the same slot replaces it
    on_done: Callable[[Request], None] | None = None  # called in the owner thread when done
    done: threading.Event = field(default_factory=threading.Event)
    seqs: list[int] = field(default_factory=list)
    attempts: int = 0
    deadline: float = 0.0
    sent_at: float = 0.0
    ack: p.Ack | None = None
    error: BaseException | None = None
    cancelled: bool = False
    round_trip_s: float = 0.0
    urgent: bool = False  # the safe state: no other urgent command gives it up

    def finish(self, ack: p.Ack | None = None, error: BaseException | None = None) -> None:
        if self.done.is_set():
            return
        self.ack, self.error = ack, error
        self.done.set()
        if self.on_done is not None:
            try:
                self.on_done(self)
            except Exception:  # a callback must not kill the owner thread
                log.exception("completion callback of %s failed", type_name(self.type))


PacketHandler = Callable[[p.Packet, float], None]


class FramedLink:
    """The port, its owner thread and the command/ACK machinery.

    Args:
        port: port name or pyserial URL, or an already-constructed serial object (pyserial API:
            read, write, in_waiting, close; tests use a fake).
        ack_timeout_s: wait for one ACK, s; a command is sent ``1 + retries`` times at most.
        retries: resends after an ACK timeout (the protocol's commands are idempotent).
        link_timeout_s: the link counts as lost when nothing valid arrived for this long.
        keepalive_interval_s: returns the current PING interval, s (asked at every check).
        keepalive: PING when nothing was sent for the keepalive interval (once :attr:`ready`).
        max_reopen_attempts: automatic reopen / resync attempts after an error before giving up.
        handlers: ``{message type: handler(packet, host_time_s)}`` for packets that are not ACKs
            (called in the owner thread: keep them short).
        on_resync: called in a helper thread after an automatic reopen, and when the device
            answers again after a silence; it redoes the handshake (through this link) and
            raises :class:`LinkTimeout` to be tried again, any other error to give up.
        owner_priority: SCHED_FIFO priority for the owner thread (the keepalive that feeds the
            device's host timeout, and the telemetry path), so host load cannot hold them past
            those timeouts; None (default) or no CAP_SYS_NICE: normal scheduling.
    """

    def __init__(
        self,
        port: str | Any,
        *,
        ack_timeout_s: float = 0.1,
        retries: int = 2,
        link_timeout_s: float = 0.3,
        keepalive_interval_s: Callable[[], float] = lambda: 0.1,
        keepalive: bool = True,
        max_reopen_attempts: int = 8,
        handlers: dict[int, PacketHandler] | None = None,
        on_resync: Callable[[], object] | None = None,
        owner_priority: int | None = None,
    ) -> None:
        self._stable_name: str | None = None  # /dev/serial/by-id: followed on a reopen
        if isinstance(port, str):
            self.port_name = port
            self._port_obj = None
        else:
            self.port_name = getattr(port, "port", None) or repr(port)
            self._port_obj = port
        self.ack_timeout_s = ack_timeout_s
        self.retries = retries
        self.link_timeout_s = link_timeout_s
        self.max_reopen_attempts = max_reopen_attempts
        self._keepalive_interval_s = keepalive_interval_s
        self._keepalive_enabled = keepalive
        self._keepalive_paused = False
        self._handlers = dict(handlers or {})
        self._on_resync = on_resync
        self.owner_priority = owner_priority

        self._ser: Any = None
        self._rx = p.FrameReceiver()
        self._lock = threading.RLock()
        self._queue: collections.deque[Request] = collections.deque()
        self._queued_slots: dict[str, Request] = {}
        self._current: Request | None = None
        self._preempt = False
        self._in_read = False  # the owner thread waits in a blocking read
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._seq = itertools.count()
        self._keepalive_seqs: dict[int, float] = {}
        self._raw_out: collections.deque[bytes] = collections.deque()
        self._last_tx = 0.0
        self._last_rx = 0.0
        self._ready = False  # the device's handshake is done on the current port
        self._lost = False
        self._port_error: str | None = None
        self._gave_up = False
        self._closing = False
        self._reopen_at: float | None = None
        self._reopen_attempts = 0
        self._reopen_request: tuple[threading.Event, list[BaseException | None]] | None = None
        self._resync_thread: threading.Thread | None = None
        self.opened_at = 0.0  # host time the port was last (re)opened, s
        self.last_round_trip_s: float | None = None
        self.last_ack_at: float | None = None  # host clock when the newest ACK was decoded
        self._n = dict.fromkeys(
            ("tx", "retries", "timeouts", "reconnects", "keepalives", "superseded"), 0
        )

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the port and start the owner thread (idempotent). :class:`LinkError` when the
        port cannot be opened."""
        if self.running:
            return
        self._stop.clear()
        self._closing = False
        self._gave_up = False
        try:
            self._ser = self._open_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(_open_error(self.port_name, exc)) from exc
        if self._port_obj is None and self._stable_name is None:
            self._stable_name = stable_port_name(self.port_name)
        self._thread = threading.Thread(
            target=self._run, name=f"FramedLink({self.port_name})", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stop the owner thread, fail what is pending, close the port. Idempotent."""
        if self._thread is None:
            return
        self._closing = True
        self._stop.set()
        self._wake_owner()
        self._thread.join(timeout=2.0)
        if self._thread.is_alive():
            log.error("owner thread did not stop")
        self._thread = None
        self._fail_all(LinkError("closed"))
        self._close_port()
        self._ready = False

    def reopen(self, timeout_s: float = 5.0) -> None:
        """Close and reopen the port from the owner thread (the handshake is the caller's)."""
        if not self.running:
            self.open()
            return
        done = threading.Event()
        result: list[BaseException | None] = [None]
        with self._lock:
            self._reopen_request = (done, result)
        self._wake_owner()
        if not done.wait(timeout_s):
            raise LinkTimeout("reopen did not complete")
        if result[0] is not None:
            raise LinkTimeout(f"reopen of {self.port_name} failed: {result[0]}") from result[0]

    # ------------------------------------------------------------------ state
    @property
    def running(self) -> bool:
        """The owner thread is alive (between :meth:`open` and :meth:`close`)."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def usable(self) -> bool:
        """Commands can be queued: running, not closing, not given up."""
        return self._thread is not None and not self._closing and not self._gave_up

    @property
    def port_up(self) -> bool:
        """The port is open right now (False between an I/O error and the reopen)."""
        return self._ser is not None

    @property
    def gave_up(self) -> bool:
        return self._gave_up

    @property
    def port_error(self) -> str | None:
        """The last port error, None after a successful (re)open."""
        return self._port_error

    @property
    def ready(self) -> bool:
        return self._ready

    def set_ready(self, ready: bool) -> None:
        """The device's handshake is done (True) or must be redone (False). While ready the
        link PINGs when idle and watches for silence."""
        with self._lock:
            self._ready = ready
            if ready:
                self._lost = False
                self._reopen_attempts = 0
        self._wake_owner()

    @property
    def link_ok(self) -> bool:
        """Port open, ready, not lost, and a valid frame received within ``link_timeout_s``
        or bytes waiting to be read."""
        with self._lock:
            ser = self._ser
            if ser is None or not self._ready or self._lost:
                return False
            if time.monotonic() - self._last_rx < self.link_timeout_s:
                return True
        # bytes waiting in the port: the device spoke and the owner thread was held up (a busy
        # host), as the owner's own loss rule says
        try:
            return ser.in_waiting > 0
        except (OSError, serial.SerialException, AttributeError, TypeError):
            return False

    def stats(self) -> dict[str, int]:
        """Host-side counters: tx (frames), retries, timeouts, reconnects, keepalives,
        superseded (posted commands replaced before they went out), rx_packets, crc_errors,
        frame_errors."""
        with self._lock:
            return {
                **self._n,
                "rx_packets": self._rx.packets,
                "crc_errors": self._rx.crc_errors,
                "frame_errors": self._rx.frame_errors,
            }

    def count_reconnect(self) -> None:
        with self._lock:
            self._n["reconnects"] += 1

    def pause_keepalive(self, paused: bool = True) -> None:
        """Test hook: stop (or resume) the automatic PINGs."""
        self._keepalive_paused = paused
        self._wake_owner()

    def send_raw(self, data: bytes) -> None:
        """Test/diagnostic hook: the owner thread writes ``data`` as is (not a sent frame for
        the keepalive)."""
        self._raw_out.append(bytes(data))
        self._wake_owner()

    # ------------------------------------------------------------------ commands
    def submit(
        self,
        type_: int,
        payload: bytes,
        *,
        ack_timeout_s: float | None = None,
        retries: int | None = None,
        urgent: bool = False,
    ) -> Request:
        """Queue a command; returns at once. ``urgent`` (the safe state): before everything
        queued, and the command in flight is given up (it fails with :class:`LinkError`) unless
        it is urgent too (two make_safe calls at once, an e-stop's and the session end's: the
        first one's ACK must not be lost to the second)."""
        req = self._new_request(type_, payload, ack_timeout_s, retries)
        req.urgent = urgent
        with self._lock:
            if urgent:
                self._queue.appendleft(req)
                self._preempt = True
            else:
                self._queue.append(req)
        self._wake_owner()
        return req

    def post(
        self,
        type_: int,
        payload: bytes,
        slot: str,
        on_done: Callable[[Request], None] | None = None,
    ) -> Request:
        """Queue a fire-and-forget command for ``slot``; returns at once. A command of the same
        slot that has not gone out yet is replaced by this one (its payload and callback)."""
        with self._lock:
            queued = self._queued_slots.get(slot)
            if queued is not None and not queued.cancelled:
                queued.type, queued.payload, queued.on_done = type_, payload, on_done
                self._n["superseded"] += 1
                return queued
            req = self._new_request(type_, payload, None, None)
            req.slot, req.on_done = slot, on_done
            self._queue.append(req)
            self._queued_slots[slot] = req
        self._wake_owner()
        return req

    def cancel_slot(self, slot: str) -> None:
        """Drop the queued (not yet sent) command of ``slot``, if any."""
        with self._lock:
            req = self._queued_slots.pop(slot, None)
            if req is not None:
                req.cancelled = True

    def wait(self, req: Request, total_timeout_s: float | None = None) -> p.Ack:
        """Wait for the ACK of ``req``; raises its error, or :class:`LinkTimeout` after
        ``total_timeout_s`` (default: all its tries plus 1 s)."""
        if total_timeout_s is None:
            total_timeout_s = (req.retries + 1) * req.ack_timeout_s + 1.0
        if not req.done.wait(total_timeout_s):
            req.cancelled = True
            with self._lock:
                self._n["timeouts"] += 1
            raise LinkTimeout(f"{type_name(req.type)}: no answer within {total_timeout_s:.2f} s")
        if req.error is not None:
            raise req.error
        assert req.ack is not None
        return req.ack

    def call(self, type_: int, payload: bytes, **kwargs: Any) -> p.Ack:
        """:meth:`submit` and :meth:`wait`: the ACK of the command (any status)."""
        total = kwargs.pop("total_timeout_s", None)
        return self.wait(self.submit(type_, payload, **kwargs), total)

    def _new_request(
        self, type_: int, payload: bytes, ack_timeout_s: float | None, retries: int | None
    ) -> Request:
        if self._thread is None or self._stop.is_set():
            raise LinkError("not open: call connect() first")
        if self._gave_up:
            raise LinkTimeout(f"port {self.port_name} down: {self._port_error}")
        return Request(
            type_,
            bytes(payload),
            self.ack_timeout_s if ack_timeout_s is None else ack_timeout_s,
            self.retries if retries is None else retries,
        )

    def _wake_owner(self) -> None:
        """Wake the owner thread: at once when it waits in a read. Only then: pyserial's
        ``cancel_read`` also aborts the next read, so cancelling at every call would starve the
        receiver when a control loop posts setpoints fast."""
        self._wake.set()
        with self._lock:
            blocked, self._in_read = self._in_read, False
        ser = self._ser
        if blocked and ser is not None and hasattr(ser, "cancel_read"):
            with contextlib.suppress(Exception):  # closed meanwhile: the owner is awake anyway
                ser.cancel_read()

    # ------------------------------------------------------------------ owner thread: port
    def _open_port(self) -> Any:
        if self._port_obj is not None:
            ser = self._port_obj
            if not getattr(ser, "is_open", True) and hasattr(ser, "open"):
                ser.open()
        else:
            if self._stable_name is not None:  # the adapter back under another device name
                if not os.path.exists(self._stable_name):
                    # unplugged (udev removed its name): whatever now has the old device name
                    # (another adapter, re-enumerated) is not this device; wait for the name
                    raise serial.SerialException(
                        f"{self._stable_name} is gone (the adapter unplugged); not opening "
                        f"{self.port_name} in its place"
                    )
                now_at = os.path.realpath(self._stable_name)
                if now_at != os.path.realpath(self.port_name):
                    log.warning("port %s is now %s (%s)", self.port_name, now_at,
                                self._stable_name)  # fmt: skip
                    self.port_name = now_at
            ser = serial.serial_for_url(
                self.port_name,
                baudrate=p.BAUDRATE,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=READ_TIMEOUT_S,
                write_timeout=0.5,
                exclusive=True,  # no second program (a GUI, a terminal) sends into a session
            )
        self._rx.reset()
        # a lone delimiter ends whatever partial frame the device may have buffered
        ser.write(p.DELIMITER)
        now = time.monotonic()
        self._last_rx = self.opened_at = now
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
        if self.owner_priority is not None:
            try:  # this thread only (Linux: 0 is the calling thread)
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.owner_priority))
            except (OSError, AttributeError) as exc:
                log.info("link owner thread stays at normal scheduling (%s)", exc)
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
            self._fail_all(LinkError("owner thread crashed"))
            with self._lock:
                self._ready = False
                self._gave_up = True
        finally:
            if self._current is not None:
                self._current.finish(error=LinkError("closed"))
                self._current = None
            log.debug("owner thread stopped")

    def _service(self) -> None:
        now = time.monotonic()
        while self._raw_out:
            self._ser.write(self._raw_out.popleft())
        cur = self._current
        with self._lock:
            preempt, self._preempt = self._preempt, False
        if cur is not None and preempt and not cur.urgent:
            cur.finish(error=LinkError(f"{type_name(cur.type)}: preempted by an urgent command"))
            cur = self._current = None
        if cur is not None and cur.cancelled:
            cur = self._current = None
        if cur is None:
            cur = self._next_request()
            if cur is not None:
                self._send_request(cur, now)
        elif now >= cur.deadline:
            self._on_ack_timeout(cur, now)
        if (
            self._keepalive_enabled
            and not self._keepalive_paused
            and self._ready
            and now - self._last_tx >= self._keepalive_interval_s()
        ):
            seq = self._send(p.MsgType.PING, b"", now)
            self._keepalive_seqs[seq] = now
            with self._lock:
                self._n["keepalives"] += 1
        data = b""
        waiting = self._ser.in_waiting
        # bytes already waiting: the device spoke and this thread was held up (a busy host),
        # not a silent link
        if (self._ready and not self._lost and not waiting
                and now - self._last_rx > self.link_timeout_s):
            with self._lock:
                self._lost = True
            log.warning("link lost: nothing received for %.0f ms", 1e3 * (now - self._last_rx))
        if waiting:
            data = self._ser.read(waiting)
        else:
            with self._lock:  # nothing to send (or waiting for an ACK): block until bytes come
                self._in_read = not self._queue or self._current is not None
            if self._in_read:
                data = self._ser.read(1)
                with self._lock:
                    self._in_read = False
                if data and self._ser.in_waiting:
                    data += self._ser.read(self._ser.in_waiting)
        if data:
            self._dispatch(self._rx.feed(data))

    def _on_ack_timeout(self, cur: Request, now: float) -> None:
        with self._lock:
            newer = cur.slot is not None and cur.slot in self._queued_slots
        if cur.attempts <= cur.retries and not newer:
            with self._lock:
                self._n["retries"] += 1
            log.debug("%s: no ACK, retry %d", type_name(cur.type), cur.attempts)
            self._send_request(cur, now)
            return
        self._current = None
        with self._lock:
            self._n["timeouts"] += 1
        reason = "a newer one is queued" if newer else f"after {cur.attempts} tries"
        cur.finish(error=LinkTimeout(f"{type_name(cur.type)}: no ACK ({reason})"))

    def _next_request(self) -> Request | None:
        with self._lock:
            while self._queue:
                req = self._queue.popleft()
                if req.slot is not None and self._queued_slots.get(req.slot) is req:
                    del self._queued_slots[req.slot]
                if not req.cancelled:
                    return req
        return None

    def _send(self, type_: int, payload: bytes, now: float) -> int:
        seq = next(self._seq) & 0xFF
        self._ser.write(p.encode_frame(seq, type_, payload))
        self._last_tx = now
        with self._lock:
            self._n["tx"] += 1
        return seq

    def _send_request(self, req: Request, now: float) -> None:
        self._current = req
        req.attempts += 1
        req.sent_at = now
        req.deadline = now + req.ack_timeout_s
        req.seqs.append(self._send(req.type, req.payload, now))

    # ------------------------------------------------------------------ owner thread: receive
    def _dispatch(self, packets: list[p.Packet]) -> None:
        if not packets:
            return
        now = time.monotonic()
        with self._lock:
            self._last_rx = now
            recovered = self._lost and self._ready
            self._lost = False
        if recovered:
            log.warning("link back: redoing the handshake")
            self._start_resync()
        for pkt in packets:
            try:
                if pkt.type == p.MsgType.ACK:
                    self._on_ack(pkt, now)
                elif pkt.type in self._handlers:
                    self._handlers[pkt.type](pkt, now)
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
            self.last_ack_at = now
            if ack.status not in (p.Status.OK, p.Status.CLAMPED):
                log.info("%s: %s", type_name(cur.type), ack.status_name)
            cur.finish(ack=ack)
            self._wake.set()  # the next command can go out at once
            return
        if self._keepalive_seqs.pop(ack.seq, None) is not None and ack.type == p.MsgType.PING:
            return
        if len(self._keepalive_seqs) > MAX_KEEPALIVES_TRACKED:  # forget unanswered keepalives
            oldest = sorted(self._keepalive_seqs, key=self._keepalive_seqs.get)
            for seq in oldest[:-MAX_KEEPALIVES_TRACKED]:
                del self._keepalive_seqs[seq]
        log.debug("stale ACK seq %d type 0x%02x", ack.seq, ack.type)

    def _fail_all(self, error: BaseException) -> None:
        cur, self._current = self._current, None
        if cur is not None:
            cur.finish(error=error)
        with self._lock:
            pending = list(self._queue)
            self._queue.clear()
            self._queued_slots.clear()
        for req in pending:
            req.finish(error=error)

    # ------------------------------------------------------------------ owner thread: reopen
    def _on_port_error(self, exc: BaseException) -> None:
        log.warning("port %s error: %s", self.port_name, exc)
        self._close_port()
        with self._lock:
            self._ready = False
            self._port_error = str(exc)
        self._fail_all(LinkTimeout(f"port {self.port_name} error: {exc}"))
        if self._stable_name is None and is_pseudo_terminal(self.port_name):
            # its other end (a mock bench, an emulator) closed: the kernel gives the number to
            # the next program asking for a pty, so a reopen would take a stranger's port
            log.error("port %s: %s", self.port_name, PTY_GONE)
            with self._lock:
                self._gave_up = True
                self._port_error = f"gave up: {PTY_GONE} ({exc})"
            self._reopen_at = None
            return
        self._reopen_at = time.monotonic() + REOPEN_FIRST_DELAY_S

    def _reopen_step(self) -> None:
        """Port closed after an error: reopen with backoff, bounded."""
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
            if self._reopen_attempts >= self.max_reopen_attempts:
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
            backoff = min(REOPEN_MAX_BACKOFF_S, REOPEN_FIRST_DELAY_S * 2**self._reopen_attempts)
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
            self._ready = False
            self._gave_up = False
        self._fail_all(LinkTimeout("port reopened"))
        try:
            self._ser = self._open_port()
        except Exception as exc:
            result[0] = exc
            with self._lock:
                self._port_error = str(exc)
            self._reopen_at = time.monotonic() + REOPEN_FIRST_DELAY_S
            self._reopen_attempts = 0
        done.set()

    def _start_resync(self, count_reconnect: bool = False) -> None:
        """Redo the handshake from a helper thread (the owner must keep serving the port)."""
        if self._on_resync is None:
            if count_reconnect:
                self.count_reconnect()
            return
        if self._resync_thread is not None and self._resync_thread.is_alive():
            return
        resync = self._on_resync

        def run() -> None:
            for attempt in range(1, self.max_reopen_attempts + 1):
                if self._stop.is_set() or self._closing:
                    return
                try:
                    resync()
                except LinkTimeout as exc:
                    log.warning("handshake after reconnect failed (try %d): %s", attempt, exc)
                    self._stop.wait(min(REOPEN_MAX_BACKOFF_S, REOPEN_FIRST_DELAY_S * 2**attempt))
                    continue
                except Exception as exc:
                    log.error("handshake after reconnect: %s", exc)
                    return
                if count_reconnect:
                    self.count_reconnect()
                return
            log.error("no handshake after %d tries: call reconnect()", self.max_reopen_attempts)

        self._resync_thread = threading.Thread(
            target=run, name=f"FramedLink-resync({self.port_name})", daemon=True
        )
        self._resync_thread.start()
