"""A small reusable Modbus server that serves a displacement-sensor register map.

:class:`SensorServer` runs pymodbus servers (TCP and/or RTU on a serial port path, e.g. one end of
a socat pty pair or ``os.ttyname`` of an ``os.openpty()`` slave) in a background thread with its
own asyncio loop. The owner updates values with :meth:`SensorServer.set_position_mm` /
:meth:`SensorServer.set_value` (encoded per the map) from any thread, or registers a callable with
:meth:`SensorServer.set_source` that is asked for the value at every request (e.g. the plant
simulation in the mock bench). Fault injection for tests: :meth:`delay_responses`,
:meth:`fail_with_exception`, :meth:`corrupt_responses`, and what a real sensor reports when it
cannot measure: :meth:`serve_status_error` (the map's error status) and :meth:`serve_sentinel`
(its "no measurement" position code). ``adapter_latency_s`` delays every response, as an FTDI
USB/RS-485 adapter's latency timer does (16 ms by default: drivers/sensors/README.md).

Only the map's registers exist: its quantities (read with the map's function only), its
``[[check]]`` registers (holding the expected values) and its ``[[on_connect]]`` registers
(writable, every write logged in :attr:`SensorServer.writes`); any other address answers with
exception 2 (illegal data address). The simulator keeps one register space for both functions.

Usage::

    with SensorServer("generic-rs485-laser", tcp_port=0) as srv:
        srv.set_position_mm(12.345)
        sensor = DisplacementSensor(srv.sensor_map, srv.tcp_spec)
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

from smabench.drivers.displacement import SensorMap, load_map

DROP_HOLD_S = 1.0
"""A dropped sensor's held-back answers go out this long after the drop ends, s."""


class SensorServer:
    """Serve ``sensor_map`` over TCP (``tcp_port``; 0 = pick a free port) and/or RTU
    (``serial_port``). Either may be None. ``start()``/``stop()`` may be repeated: a restarted
    TCP server reuses the port it got the first time."""

    def __init__(
        self,
        sensor_map: SensorMap | str | Path,
        *,
        tcp_port: int | None = 0,
        host: str = "127.0.0.1",
        serial_port: str | None = None,
        baudrate: int | None = None,
        unit_id: int | None = None,
        adapter_latency_s: float = 0.0,
        parity: str | None = None,
    ) -> None:
        self.sensor_map = sensor_map if isinstance(sensor_map, SensorMap) else load_map(sensor_map)
        self.host = host
        self.tcp_port = tcp_port
        self.serial_port = serial_port
        self.baudrate = baudrate or self.sensor_map.line.baudrate
        # a pty refuses parity (EINVAL): serve an 8E1 map as 8N1 there (``parity="N"``)
        self.parity = parity or self.sensor_map.line.parity
        self.unit_id = self.sensor_map.unit_id if unit_id is None else unit_id
        self._lock = threading.Lock()
        if not 0.0 <= adapter_latency_s <= 1.0:
            raise ValueError(f"adapter latency {adapter_latency_s} s outside 0 … 1 s")
        self.adapter_latency_s = adapter_latency_s
        self._regs: dict[int, int] = {}
        for q in self.sensor_map.quantities.values():
            self._regs.update(self.sensor_map.encode(q.name, 0))
        for start, count in self.sensor_map.read_blocks:  # the unmapped rest of a record: 0
            for a in range(start, start + count):
                self._regs.setdefault(a, 0)
        self._read_function = dict.fromkeys(self._regs, self.sensor_map.function)
        for c in self.sensor_map.checks:
            self._claim(c.address, c.function, "[[check]]")
            self._regs[c.address] = c.expect
        self._writable: set[int] = set()
        for w in self.sensor_map.on_connect:
            for a in range(w.address, w.address + len(w.values)):
                self._claim(a, 3, "[[on_connect]]")
                self._regs.setdefault(a, 0)
                self._writable.add(a)
        self.writes: list[tuple[int, list[int]]] = []  # (address, values) of every write
        self._raw_override: dict[str, tuple[float, int | None]] = {}
        self._frozen_count: int | None = 0
        self._frozen_regs: dict[int, int] | None = None
        self._sources: dict[str, Callable[[], float]] = {}
        self._delay_s = 0.0
        self._delay_count: int | None = 0
        self._exc_code = 0
        self._exc_count: int | None = 0
        self._corrupt_count: int | None = 0
        self._drop_until = -math.inf  # time.monotonic() until which no request is answered
        self.requests = 0  # register requests that reached the datastore
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._servers: list = []

    def _claim(self, address: int, function: int, what: str) -> None:
        seen = self._read_function.get(address)
        if seen is not None and seen != function:
            raise ValueError(
                f"{self.sensor_map.source}: {what} register {address} is also read with "
                f"function {seen}: this simulator keeps one register space"
            )
        self._read_function[address] = function

    # -- values ---------------------------------------------------------------------------

    def set_position_mm(self, position_mm: float) -> None:
        self.set_value("position", position_mm)

    def set_status(self, word: int) -> None:
        self.set_value("status", word)

    def set_value(self, name: str, value: float) -> None:
        """Set quantity ``name`` (physical units, encoded per the map)."""
        regs = self.sensor_map.encode(name, value)
        with self._lock:
            self._regs.update(regs)

    def set_source(self, name: str, source: Callable[[], float] | None) -> None:
        """Compute quantity ``name`` at every request by calling ``source()`` (in the server
        thread; keep it quick and thread-safe). ``None`` removes it. If it raises, the request is
        answered with exception 4 (device failure)."""
        self.sensor_map.quantities[name]  # KeyError for a quantity the map does not have
        with self._lock:
            if source is None:
                self._sources.pop(name, None)
            else:
                self._sources[name] = source

    def _set_from_source(self, name: str, value: float) -> None:
        """A value the registers cannot hold (a position outside a sensor's range) is served as
        the map's "no measurement" code, as the real sensor would report it."""
        try:
            self.set_value(name, value)
        except ValueError:
            q = self.sensor_map.quantities[name]
            regs = self.sensor_map.encode_raw(name, q.invalid_raw)  # ValueError: no such code
            with self._lock:
                self._regs.update(regs)

    def set_registers(self, address: int, values: list[int]) -> None:
        """Overwrite raw registers (must be inside the map)."""
        with self._lock:
            for i, v in enumerate(values):
                if address + i not in self._regs:
                    raise KeyError(f"register {address + i} is not in the map")
                self._regs[address + i] = int(v) & 0xFFFF

    # -- faults ---------------------------------------------------------------------------

    def delay_responses(self, delay_s: float, count: int | None = None) -> None:
        """Delay the next ``count`` responses (None: all, until :meth:`clear_faults`)."""
        with self._lock:
            self._delay_s, self._delay_count = float(delay_s), count

    def fail_with_exception(self, code: int = 4, count: int | None = None) -> None:
        """Answer the next ``count`` requests with Modbus exception ``code``."""
        with self._lock:
            self._exc_code, self._exc_count = int(code), count

    def corrupt_responses(self, count: int | None = None) -> None:
        """Damage the next ``count`` response frames (RTU: bad CRC; TCP: bad protocol id)."""
        with self._lock:
            self._corrupt_count = count

    def serve_status_error(self, count: int | None = None, word: int | None = None) -> None:
        """Serve a status word that says error (default: the map's first error bit/value) for
        the next ``count`` requests (None: until :meth:`clear_faults`)."""
        q = self.sensor_map.quantities["status"]  # KeyError: the map has no status word
        self._override("status", q.error_word if word is None else word, count)

    def serve_sentinel(self, count: int | None = None, raw: float | None = None) -> None:
        """Serve a position the map calls "no measurement" (default: its first sentinel, NaN
        for a float, or just outside its valid range) for the next ``count`` requests."""
        q = self.sensor_map.position
        self._override("position", q.invalid_raw if raw is None else raw, count)

    def _override(self, name: str, raw: float, count: int | None) -> None:
        self.sensor_map.quantities[name].encode_raw(raw)  # ValueError now, not in the server
        with self._lock:
            self._raw_override[name] = (raw, count)

    def freeze(self, count: int | None = None) -> None:
        """Serve the same registers (those of the next request) for the next ``count``
        requests (None: until :meth:`clear_faults`): a sensor whose output froze, still
        answering, every reading valid."""
        with self._lock:
            self._frozen_regs, self._frozen_count = None, count

    def drop_for(self, seconds: float) -> None:
        """Answer nothing for ``seconds`` (wall time) from now: a sensor that stopped answering
        (every request times out at the client; the answers held back are sent after the drop
        and :data:`DROP_HOLD_S`, when the client has long given up on them)."""
        if not 0.0 <= seconds <= 3600.0:
            raise ValueError(f"drop time must be in 0 … 3600 s, got {seconds}")
        with self._lock:
            self._drop_until = time.monotonic() + seconds

    def clear_faults(self) -> None:
        with self._lock:
            self._drop_until = -math.inf
            self._delay_count = self._exc_count = self._corrupt_count = 0
            self._frozen_count, self._frozen_regs = 0, None
            self._raw_override.clear()

    @staticmethod
    def _take(count: int | None) -> tuple[bool, int | None]:
        if count is None:
            return True, None
        if count > 0:
            return True, count - 1
        return False, 0

    # -- lifecycle ------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def tcp_spec(self) -> str:
        return f"tcp:{self.host}:{self.tcp_port}"

    @property
    def rtu_spec(self) -> str:
        line = self.sensor_map.line
        return f"rtu:{self.serial_port}:{self.baudrate}:{line.bytesize}{self.parity}{line.stopbits}"

    def __enter__(self) -> SensorServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, timeout_s: float = 5.0) -> SensorServer:
        """Start serving; returns once listening (``RuntimeError`` if it cannot listen)."""
        if self.running:
            return self
        ready = threading.Event()
        errors: list[BaseException] = []
        loop = asyncio.new_event_loop()
        self._loop = loop

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(self._start_servers())
            except BaseException as exc:  # noqa: BLE001 - reported to start()
                errors.append(exc)
                ready.set()
                loop.run_until_complete(self._shutdown())
                loop.close()
                return
            ready.set()
            try:
                loop.run_forever()
            finally:
                loop.run_until_complete(self._shutdown())
                loop.close()

        self._thread = threading.Thread(target=run, name="modbus-sim", daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            self.stop()
            raise RuntimeError("Modbus simulator did not start in time")
        if errors:
            self._thread.join(timeout_s)
            self._thread = None
            raise RuntimeError(f"Modbus simulator could not start: {errors[0]}") from errors[0]
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving and join the thread (closes client connections)."""
        thread, loop = self._thread, self._loop
        if thread is None or loop is None:
            return
        if thread.is_alive():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(loop.stop)
            thread.join(timeout_s)
        if thread.is_alive():
            raise RuntimeError("Modbus simulator thread did not stop")
        self._thread = None
        self._loop = None

    async def _start_servers(self) -> None:
        from pymodbus import FramerType
        from pymodbus.server import ModbusSerialServer, ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        with self._lock:
            addresses = sorted(self._read_function)
        simdata = [SimData(a, count=1, values=0, datatype=DataType.REGISTERS) for a in addresses]
        self._servers = []
        if self.tcp_port is not None:
            device = SimDevice(self.unit_id, simdata=list(simdata), action=self._action)
            srv = ModbusTcpServer(device, address=(self.host, self.tcp_port),
                                  trace_packet=self._trace_tcp)
            self._servers.append(srv)
            await srv.serve_forever(background=True)
            self.tcp_port = srv.transport.sockets[0].getsockname()[1]
        if self.serial_port is not None:
            self._check_serial_port()
            device = SimDevice(self.unit_id, simdata=list(simdata), action=self._action)
            line = self.sensor_map.line
            srv = ModbusSerialServer(
                device, framer=FramerType.RTU, port=self.serial_port, baudrate=self.baudrate,
                parity=self.parity, stopbits=line.stopbits, bytesize=line.bytesize,
                trace_packet=self._trace_rtu,
            )
            self._servers.append(srv)
            await srv.serve_forever(background=True)

    def _check_serial_port(self) -> None:
        """Open and close the RTU port as pymodbus will (exclusively): pymodbus turns an OSError
        there into "Could not start listen, please check address." and logs the cause at a level
        nobody sees; this raises it with its errno (seen once on a busy CI, cause unknown)."""
        import serial

        try:
            serial.serial_for_url(self.serial_port, exclusive=True, baudrate=self.baudrate).close()
        except (OSError, serial.SerialException) as exc:
            raise OSError(f"RTU port {self.serial_port}: {exc}") from exc

    async def _shutdown(self) -> None:
        for srv in self._servers:
            with contextlib.suppress(Exception):
                await srv.shutdown()
        self._servers = []
        current = asyncio.current_task()
        tasks = [t for t in asyncio.all_tasks() if t is not current]
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=1.0)

    async def _action(self, function_code, start_address, address, count, registers,
                      set_values):
        from pymodbus.constants import ExcCodes

        with self._lock:
            sources = list(self._sources.items())
        try:
            for name, source in sources:
                self._set_from_source(name, source())
        except Exception:  # a broken source looks like a failing device
            return ExcCodes.DEVICE_FAILURE
        with self._lock:
            self.requests += 1
            served = dict(self._regs)
            for name, (raw, n) in list(self._raw_override.items()):
                served.update(self.sensor_map.encode_raw(name, raw))
                if n is not None:
                    if n <= 1:
                        del self._raw_override[name]
                    else:
                        self._raw_override[name] = (raw, n - 1)
            frozen, self._frozen_count = self._take(self._frozen_count)
            if frozen and self._frozen_regs is None:
                self._frozen_regs = served
            elif frozen:
                served = self._frozen_regs
            else:
                self._frozen_regs = None
            for a, v in served.items():
                registers[a - start_address] = v
            delay, self._delay_count = self._take(self._delay_count)
            delay_s = self._delay_s
            fail, self._exc_count = self._take(self._exc_count)
            code = self._exc_code
            drop_s = self._drop_until - time.monotonic()
        latency_s = self.adapter_latency_s + (delay_s if delay else 0.0)
        if drop_s > 0:  # a dropped sensor: the answer comes long after the client gave up
            latency_s += drop_s + DROP_HOLD_S
        if latency_s > 0:
            await asyncio.sleep(latency_s)
        if fail:
            return ExcCodes(code)
        span = range(address, address + count)
        if set_values is not None:
            if function_code not in (6, 16) or any(a not in self._writable for a in span):
                return ExcCodes.ILLEGAL_ADDRESS  # only the map's configuration is writable
            with self._lock:
                self._regs.update(zip(span, (int(v) & 0xFFFF for v in set_values), strict=True))
                self.writes.append((address, [int(v) for v in set_values]))
            return None
        if function_code in (6, 16):  # pymodbus reads a written register back for the answer
            return None if all(a in self._writable for a in span) else ExcCodes.ILLEGAL_ADDRESS
        if any(self._read_function.get(a) != function_code for a in span):
            return ExcCodes.ILLEGAL_FUNCTION
        return None

    def _corrupt_now(self) -> bool:
        with self._lock:
            corrupt, self._corrupt_count = self._take(self._corrupt_count)
        return corrupt

    def _trace_rtu(self, sending: bool, data: bytes) -> bytes:
        if sending and data and self._corrupt_now():
            return data[:-1] + bytes([data[-1] ^ 0xFF])
        return data

    def _trace_tcp(self, sending: bool, data: bytes) -> bytes:
        if sending and len(data) > 4 and self._corrupt_now():
            return data[:2] + b"\xde\xad" + data[4:]
        return data
