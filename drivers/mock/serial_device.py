"""The mock current driver on a pseudo-terminal: :class:`MockFirmware` (the real firmware core,
built for the host, with the electrical side in Python) behind a real tty.

The host driver opens :attr:`SerialDevice.port_name` (``/dev/pts/N``) like a USB serial port.
A thread steps the firmware model in real time (1 ms device steps, catching up on the wall clock,
optionally ``speed`` × faster), hands it the bytes the host wrote and writes back its ACKs and
telemetry. The electrical state of the wire is set with :meth:`set_resistance` /
:meth:`set_open_wire`, or by an ``on_step`` hook called every step, e.g. to couple the mock to a
plant simulation::

    link = PlantLink(load_kg=2.0)

    def couple(t_ms, dt_s, fw):
        state = link.step(dt_s, fw.current_ma / 1000.0)
        return Electrical(resistance_ohm=state.resistance_ohm, ambient_c=state.ambient_c)

    with SerialDevice(on_step=couple) as dev, CurrentSource(dev.port_name) as cs:
        ...

Test hooks: :meth:`inject_to_host` / :meth:`inject_to_device` put raw bytes (noise) on the line,
:meth:`pause` freezes the device (a hung MCU: no stepping, no reading), :meth:`stop` makes it
disappear (the host's port then reports an I/O error).

``boot_delay_s`` emulates an Arduino's auto-reset: every time the host opens the port (DTR) the
MCU resets into its bootloader, which swallows what the host sends and stays silent for
``boot_delay_s`` (optiboot: about 1 s) before the firmware starts afresh (output off, default
limits). Every open of the pty by the host is seen through inotify (``IN_OPEN``, Linux).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import errno
import logging
import os
import select
import struct
import threading
import time
import tty
from collections.abc import Callable

from smabench.drivers.mock.firmware import Electrical, MockFirmware

log = logging.getLogger(__name__)

StepHook = Callable[[float, float, MockFirmware], Electrical | None]

_IN_OPEN, _IN_CLOSE = 0x20, 0x08 | 0x10  # <sys/inotify.h>
_INOTIFY_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (no name for a file watch)


def _watch_opens(path: str) -> int:
    """A non-blocking inotify fd reporting opens and closes of ``path`` (closes too, so that
    two opens in a row are not merged into one event)."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
    if fd < 0 or libc.inotify_add_watch(fd, path.encode(), _IN_OPEN | _IN_CLOSE) < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"inotify on {path}: {os.strerror(err)}")
    return fd


WAKE_S = 0.002
"""Shortest idle wait of the device thread, s (wall): the steps due meanwhile run in one burst at
the next wake (each with its own device time), and host bytes wake it at once. Waking for every
1 ms step cost the thread 79 % of a core at 5× (5000 wakes a second; a step's own work is 21 µs):
at SCHED_FIFO that, beside a second such mock, ran past the kernel's real-time budget (RT
throttling: every real-time thread of the CPU stopped for up to 50 ms, the kernel's pty worker
starved) and telemetry was lost for 0.26 s in a GUI session on CI."""


class SerialDevice:
    """Serve a :class:`MockFirmware` on a pty, stepped in real time by a thread.

    Args:
        firmware: the device model (a fresh one by default).
        speed: device time / wall time (1 = real time). The device's host timeout runs in device
            time: above 1, give the host a longer host timeout (``set_limits``) to match.
        step_ms: device time step, ms.
        electrical: initial electrical state of the wire.
        on_step: ``hook(t_ms, dt_s, firmware) -> Electrical | None`` called before every step;
            a returned :class:`Electrical` becomes the state used for that step and after.
        max_catch_up_ms: when the thread falls further behind than this (a long GC pause, an
            overloaded machine), device time skips ahead instead of running a burst of steps.
        boot_delay_s: None (default): no auto-reset. A number: every open of the port resets
            the device, silent for this long (device time, s) before a fresh firmware starts.
        thread_priority: SCHED_FIFO priority for the device thread where allowed (a
            microcontroller is not slowed by host load); None: normal scheduling.
    """

    def __init__(
        self,
        firmware: MockFirmware | None = None,
        *,
        speed: float = 1.0,
        step_ms: float = 1.0,
        electrical: Electrical | None = None,
        on_step: StepHook | None = None,
        max_catch_up_ms: float = 100.0,
        boot_delay_s: float | None = None,
        thread_priority: int | None = None,
    ) -> None:
        if speed <= 0 or step_ms <= 0:
            raise ValueError("speed and step_ms must be > 0")
        self.firmware = firmware or MockFirmware(0.0)
        self.speed = speed
        self.step_ms = step_ms
        self.on_step = on_step
        self.max_catch_up_ms = max_catch_up_ms
        self._electrical = electrical or Electrical()
        self._lock = threading.RLock()
        self._master: int | None = None
        self._slave: int | None = None
        self._port_name: str | None = None
        self._thread: threading.Thread | None = None
        self._running = threading.Event()
        self._paused = threading.Event()
        self._to_host = bytearray()
        self._to_device = bytearray()
        self.device_ms = self.firmware.last_tick_ms
        self.rx_bytes = 0  # host -> device
        self.tx_bytes = 0  # device -> host
        self.dropped_bytes = 0  # device -> host, lost because nobody read the port
        self.skipped_ms = 0.0
        self.boot_delay_s = boot_delay_s
        self.thread_priority = thread_priority
        self.resets = 0  # auto-resets (port opened by the host)
        self.boot_end_ms: float | None = None  # device time the firmware (re)starts, while booting
        self._inotify: int | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def port_name(self) -> str:
        """Path of the pty the host opens (``/dev/pts/N``); valid after :meth:`start`."""
        if self._port_name is None:
            raise RuntimeError("SerialDevice not started")
        return self._port_name

    def start(self) -> SerialDevice:
        if self._thread is not None:
            return self
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._port_name = os.ttyname(slave)
        if self.boot_delay_s is not None:
            self._inotify = _watch_opens(self._port_name)
        self._running.set()
        self._thread = threading.Thread(target=self._run, name="SerialDevice", daemon=True)
        self._thread.start()
        log.debug("mock current driver on %s (speed %.1f)", self._port_name, self.speed)
        return self

    def stop(self) -> None:
        """Stop the device and close the pty: the host sees the port disappear."""
        self._running.clear()
        self._paused.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave, self._inotify):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = self._inotify = None

    def __enter__(self) -> SerialDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ electrical state
    @property
    def electrical(self) -> Electrical:
        with self._lock:
            return self._electrical

    @electrical.setter
    def electrical(self, value: Electrical) -> None:
        with self._lock:
            self._electrical = value

    def set_resistance(self, ohm: float) -> None:
        """Wire resistance, Ω (a huge value looks like an open wire to the controller)."""
        with self._lock:
            self._electrical = dataclasses.replace(self._electrical, resistance_ohm=ohm)

    def set_open_wire(self, open_wire: bool = True) -> None:
        with self._lock:
            self._electrical = dataclasses.replace(self._electrical, open_wire=open_wire)

    # ------------------------------------------------------------------ test hooks
    def inject_to_host(self, data: bytes) -> None:
        """Raw bytes from the device to the host (line noise), sent at the next step."""
        with self._lock:
            self._to_host += data

    def inject_to_device(self, data: bytes) -> None:
        """Raw bytes into the device's receiver as if the host had sent them (line noise)."""
        with self._lock:
            self._to_device += data

    def pause(self) -> None:
        """Freeze the device (hung MCU): it neither steps nor reads until :meth:`resume`."""
        self._paused.set()

    def resume(self) -> None:
        self._paused.clear()

    def call(self, fn: Callable[[MockFirmware], object]) -> object:
        """Run ``fn(firmware)`` between two steps (thread-safe access to the model)."""
        with self._lock:
            return fn(self.firmware)

    # ------------------------------------------------------------------ device thread
    def _watch_host(self) -> None:
        """Auto-reset: the host opened the port (DTR) → reset into the bootloader."""
        try:
            events = os.read(self._inotify, 4096)
        except BlockingIOError:
            return
        opens = sum(
            1
            for off in range(0, len(events), _INOTIFY_EVENT.size)
            if _INOTIFY_EVENT.unpack_from(events, off)[1] & _IN_OPEN
        )
        if opens:
            self.resets += opens
            self.boot_end_ms = self.device_ms + 1e3 * self.boot_delay_s
            log.debug("port opened: reset, firmware starts at t=%.0f ms", self.boot_end_ms)

    def _boot(self) -> bool:
        """While in the bootloader: swallow the host's bytes; True until the firmware runs."""
        if self.boot_end_ms is None:
            return False
        with contextlib.suppress(OSError):
            while os.read(self._master, 4096):
                pass
        self._to_device.clear()
        if self.device_ms < self.boot_end_ms:
            return True
        self.firmware = MockFirmware(self.device_ms, eeprom=self.firmware.eeprom)  # EEPROM kept
        self.boot_end_ms = None
        log.debug("firmware started at t=%.0f ms", self.device_ms)
        return False

    def _run(self) -> None:
        if self.thread_priority is not None:
            try:  # this thread only
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.thread_priority))
            except (OSError, AttributeError) as exc:
                log.info("mock device thread stays at normal scheduling (%s)", exc)
        wall0 = time.monotonic()
        dev0 = self.device_ms
        paused_at: float | None = None
        try:
            while self._running.is_set():
                if self._paused.is_set():
                    paused_at = paused_at or time.monotonic()
                    time.sleep(0.002)
                    continue
                if paused_at is not None:  # device time does not advance while frozen
                    wall0 += time.monotonic() - paused_at
                    paused_at = None
                target = dev0 + (time.monotonic() - wall0) * 1e3 * self.speed
                if target - self.device_ms > self.max_catch_up_ms:
                    skip = target - self.device_ms - self.step_ms
                    self.skipped_ms += skip
                    dev0 -= skip
                    target -= skip
                    log.debug("device thread late: skipped %.1f ms of device time", skip)
                if self._inotify is not None:
                    self._watch_host()
                with self._lock:
                    while self._boot() and self.device_ms + self.step_ms <= target:
                        self.device_ms += self.step_ms
                    fw = self.firmware
                    if self.boot_end_ms is None:
                        # host bytes once per wake (select wakes on them), the burst's output in
                        # one write: a syscall per 1 ms step, each a release and re-take of the
                        # interpreter lock, cost more than the steps themselves
                        self._receive(fw)
                        out = bytearray()
                        while self.boot_end_ms is None and self.device_ms + self.step_ms <= target:
                            out += self._step(fw)
                        self._write(bytes(out))
                next_ms = self.device_ms + self.step_ms
                wait_s = (next_ms - dev0) / (1e3 * self.speed) - (time.monotonic() - wall0)
                if wait_s > 0:  # caught up: idle until the next step is due, WAKE_S at least
                    select.select([self._master], [], [], max(wait_s, WAKE_S))
        except Exception:
            log.exception("mock device thread crashed")
        finally:
            log.debug("mock device thread stopped at t=%.0f ms", self.device_ms)

    def _receive(self, fw: MockFirmware) -> None:
        data = bytearray(self._to_device)
        self._to_device.clear()
        while True:
            try:
                chunk = os.read(self._master, 4096)
            except BlockingIOError:
                break
            except OSError as exc:  # EIO: no process has the slave open (cannot happen here)
                if exc.errno != errno.EIO:
                    raise
                break
            if not chunk:
                break
            self.rx_bytes += len(chunk)
            data += chunk
        if data and self._inotify is not None:
            self._watch_host()  # opened before these bytes were written: the bootloader eats them
            if self.boot_end_ms is not None:
                return
        if data:
            self._write(fw.receive(bytes(data), self.device_ms))

    def _step(self, fw: MockFirmware) -> bytes:
        """One step of device time; returns what the device sent in it."""
        t = self.device_ms + self.step_ms
        if self.on_step is not None:
            wire = self.on_step(t, self.step_ms / 1e3, fw)
            if wire is not None:
                self._electrical = wire
        self.device_ms = t
        return fw.tick(t, self._electrical)

    def _write(self, data: bytes) -> None:
        if not data and not self._to_host:
            return
        if self._to_host:
            data = bytes(self._to_host) + data
            self._to_host.clear()
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except BlockingIOError:  # nobody reads the port: a UART would drop it too
                self.dropped_bytes += len(view)
                return
            self.tx_bytes += n
            view = view[n:]
