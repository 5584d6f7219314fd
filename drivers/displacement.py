"""Modbus (RTU or TCP) laser displacement sensor driver.

A sensor is described by a register map (``drivers/sensors/*.toml``, see the README there) and
reached through a transport spec:

* ``tcp:HOST[:PORT]`` (port defaults to 502; IPv6 hosts in brackets, ``tcp:[::1]:502``)
* ``rtu:/dev/ttyUSB0[:BAUD[:FORMAT]]`` (FORMAT like ``8N1`` / ``8E1``; defaults from the map)

:class:`DisplacementSensor` is synchronous and meant for ONE owner thread (the bench runtime's
device thread); pymodbus clients are not thread-safe. Every call is bounded in time: a read takes
at most about ``(retries + 1) * timeout_s`` per register block plus one connect timeout.

Errors on the link are typed (:class:`SensorTimeout`, :class:`SensorException`,
:class:`SensorFrameError`, :class:`SensorLinkLost`); :meth:`DisplacementSensor.read_or_flag`
turns them into a :class:`Sample` with ``position_mm = nan`` and ``FLAG_*`` bits so the runtime can
record the sample and carry on. After a lost link the next read reconnects.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import struct
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SENSORS_DIR = Path(__file__).resolve().parent / "sensors"

# pymodbus logs every timeout at ERROR level with a packet dump; this driver reports link problems
# itself (typed errors, sample flags). A NullHandler keeps those messages off stderr when the
# application has not configured logging, and still lets them through when it has.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

# --------------------------------------------------------------------------------------------
# errors and flags
# --------------------------------------------------------------------------------------------


class SensorError(Exception):
    """Base class of every displacement-sensor error."""

    flag = 0


class SensorMapError(SensorError, ValueError):
    """A register map file is missing, malformed or inconsistent (message names file and key)."""


class SensorTimeout(SensorError):  # noqa: N818 - public API name
    """The sensor did not answer within the timeout (after the configured retries)."""

    flag = 0x01


class SensorException(SensorError):  # noqa: N818 - public API name
    """The sensor answered with a Modbus exception response; ``code`` is the exception code."""

    flag = 0x02

    def __init__(self, code: int, message: str | None = None) -> None:
        self.code = int(code)
        name = EXCEPTION_NAMES.get(self.code, "unknown")
        super().__init__(message or f"Modbus exception {self.code} ({name})")


class SensorLinkLost(SensorError):  # noqa: N818 - public API name
    """No connection to the sensor (refused, closed, serial port gone); reconnects on next read."""

    flag = 0x04


class SensorFrameError(SensorError):
    """Bytes arrived but no valid frame (bad CRC, garbage, wrong length)."""

    flag = 0x08


FLAG_TIMEOUT = SensorTimeout.flag
FLAG_EXCEPTION = SensorException.flag
FLAG_LINK_LOST = SensorLinkLost.flag
FLAG_FRAMING = SensorFrameError.flag
FLAG_SENSOR_STATUS = 0x10  # the sensor's status word has an error bit set (see ``error_mask``)
FLAG_RETRIED = 0x20  # the read succeeded, but only after a retry

FLAG_NAMES = {
    FLAG_TIMEOUT: "timeout",
    FLAG_EXCEPTION: "exception",
    FLAG_LINK_LOST: "link_lost",
    FLAG_FRAMING: "framing",
    FLAG_SENSOR_STATUS: "sensor_status",
    FLAG_RETRIED: "retried",
}
#: flags meaning "no valid position in this sample"
FLAGS_INVALID = FLAG_TIMEOUT | FLAG_EXCEPTION | FLAG_LINK_LOST | FLAG_FRAMING

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "device failure",
    5: "acknowledge",
    6: "device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target failed to respond",
}


def describe_flags(flags: int) -> str:
    """``"timeout|retried"`` style text for a flags word ('' when 0)."""
    names = [name for bit, name in FLAG_NAMES.items() if flags & bit]
    rest = flags & ~sum(FLAG_NAMES)
    if rest:
        names.append(hex(rest))
    return "|".join(names)


# --------------------------------------------------------------------------------------------
# register encoding
# --------------------------------------------------------------------------------------------

#: data type -> (registers, struct format of the big-endian byte string)
DATA_TYPES: dict[str, tuple[int, str]] = {
    "int16": (1, ">h"),
    "uint16": (1, ">H"),
    "int32": (2, ">i"),
    "uint32": (2, ">I"),
    "float32": (2, ">f"),
}
WORD_ORDERS = ("big", "little")


def encode_registers(raw: int | float, dtype: str, word_order: str = "big") -> list[int]:
    """Encode one raw (device-unit) value into 16-bit registers.

    Bytes inside a register are always big-endian (Modbus); ``word_order`` says whether the
    most significant register comes first (``big``) or last (``little``). Integers are rounded
    and must fit the type (``ValueError`` otherwise).
    """
    n_regs, fmt = _dtype(dtype)
    if word_order not in WORD_ORDERS:
        raise ValueError(f"word order {word_order!r} is not one of {', '.join(WORD_ORDERS)}")
    value: int | float = float(raw) if dtype == "float32" else int(round(raw))
    try:
        data = struct.pack(fmt, value)
    except (struct.error, OverflowError) as exc:
        raise ValueError(f"{raw!r} does not fit {dtype}") from exc
    regs = [int.from_bytes(data[i : i + 2], "big") for i in range(0, 2 * n_regs, 2)]
    if word_order == "little":
        regs.reverse()
    return regs


def decode_registers(regs: list[int] | tuple[int, ...], dtype: str, word_order: str = "big"):
    """Decode 16-bit registers into one raw value (inverse of :func:`encode_registers`)."""
    n_regs, fmt = _dtype(dtype)
    if len(regs) != n_regs:
        raise ValueError(f"{dtype} needs {n_regs} register(s), got {len(regs)}")
    if word_order not in WORD_ORDERS:
        raise ValueError(f"word order {word_order!r} is not one of {', '.join(WORD_ORDERS)}")
    ordered = list(regs) if word_order == "big" else list(reversed(regs))
    data = b"".join(int(r & 0xFFFF).to_bytes(2, "big") for r in ordered)
    return struct.unpack(fmt, data)[0]


def _dtype(dtype: str) -> tuple[int, str]:
    try:
        return DATA_TYPES[dtype]
    except KeyError:
        raise ValueError(
            f"unknown data type {dtype!r} (expected one of {', '.join(DATA_TYPES)})"
        ) from None


# --------------------------------------------------------------------------------------------
# register maps
# --------------------------------------------------------------------------------------------

QUANTITIES = {"position": "mm", "temperature": "degC", "status": ""}
_ENTRY_KEYS = {"address", "type", "word_order", "scale", "offset", "units", "error_mask",
               "description"}
_SENSOR_KEYS = {"name", "description", "unit_id", "function"}
_LINE_KEYS = {"baudrate", "parity", "stopbits", "bytesize", "timeout_s", "retries"}


@dataclass(frozen=True)
class Quantity:
    """One measured quantity: ``physical = raw * scale + offset`` (in ``units``)."""

    name: str
    address: int
    dtype: str
    word_order: str = "big"
    scale: float = 1.0
    offset: float = 0.0
    units: str = ""
    error_mask: int = 0
    description: str = ""

    @property
    def count(self) -> int:
        return DATA_TYPES[self.dtype][0]

    def decode(self, regs: list[int]) -> float | int:
        raw = decode_registers(regs, self.dtype, self.word_order)
        if self.name == "status":
            return int(raw)
        return raw * self.scale + self.offset

    def encode(self, value: float) -> list[int]:
        """Registers a device would serve for the physical ``value``."""
        if self.name == "status":
            return encode_registers(int(value), self.dtype, self.word_order)
        return encode_registers((value - self.offset) / self.scale, self.dtype, self.word_order)


@dataclass(frozen=True)
class LineSettings:
    """Serial line defaults (RTU) and request timing (both transports)."""

    baudrate: int = 19200
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8
    timeout_s: float = 0.1
    retries: int = 1


@dataclass(frozen=True)
class SensorMap:
    """A parsed, validated register map."""

    name: str
    unit_id: int
    function: int
    quantities: dict[str, Quantity]
    line: LineSettings = field(default_factory=LineSettings)
    source: str = "<memory>"
    description: str = ""

    @property
    def position(self) -> Quantity:
        return self.quantities["position"]

    def blocks(self) -> list[tuple[int, int, list[Quantity]]]:
        """Contiguous register runs ``(start, count, quantities)``: one request each."""
        out: list[tuple[int, int, list[Quantity]]] = []
        for q in sorted(self.quantities.values(), key=lambda q: q.address):
            if out and out[-1][0] + out[-1][1] == q.address and out[-1][1] + q.count <= 125:
                start, count, qs = out[-1]
                out[-1] = (start, count + q.count, [*qs, q])
            else:
                out.append((q.address, q.count, [q]))
        return out

    def encode(self, name: str, value: float) -> dict[int, int]:
        """``{address: register}`` a device serves for quantity ``name`` at ``value``."""
        q = self.quantities[name]
        return {q.address + i: r for i, r in enumerate(q.encode(value))}


def available_maps() -> list[str]:
    """Names of the register maps shipped in ``drivers/sensors``."""
    return sorted(p.stem for p in SENSORS_DIR.glob("*.toml"))


def load_map(name_or_path: str | Path) -> SensorMap:
    """Load a map by file path or by the name of a shipped map (``generic-rs485-laser``)."""
    path = Path(name_or_path)
    if not path.exists() and not path.suffix and (SENSORS_DIR / f"{path}.toml").exists():
        path = SENSORS_DIR / f"{path}.toml"
    if not path.is_file():
        raise SensorMapError(
            f"{name_or_path}: no such register map (shipped: {', '.join(available_maps())})"
        )
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SensorMapError(f"{path}: not valid TOML: {exc}") from None
    return parse_map(data, source=str(path), default_name=path.stem)


def parse_map(data: dict[str, Any], *, source: str = "<memory>",
              default_name: str = "sensor") -> SensorMap:
    """Validate a map already parsed from TOML; errors name ``source`` and the offending key."""

    def fail(key: str, msg: str) -> SensorMapError:
        return SensorMapError(f"{source}: {key}: {msg}")

    def check_keys(table: dict, allowed: set[str], where: str) -> None:
        for key in table:
            if key not in allowed:
                raise fail(f"{where}.{key}",
                           f"unknown key (allowed: {', '.join(sorted(allowed))})")

    def get_int(table: dict, key: str, where: str, lo: int, hi: int,
                default: int | None = None) -> int:
        if key not in table:
            if default is None:
                raise fail(f"{where}.{key}", "missing (required)")
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise fail(f"{where}.{key}", f"must be an integer in {lo}..{hi}, got {value!r}")
        return value

    def get_float(table: dict, key: str, where: str, default: float) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
            value
        ):
            raise fail(f"{where}.{key}", f"must be a finite number, got {value!r}")
        return float(value)

    def get_str(table: dict, key: str, where: str, default: str) -> str:
        value = table.get(key, default)
        if not isinstance(value, str):
            raise fail(f"{where}.{key}", f"must be a string, got {value!r}")
        return value

    if not isinstance(data, dict):
        raise SensorMapError(f"{source}: expected a TOML table")
    check_keys(data, {"sensor", "line", "registers"}, "(top level)")
    for table_name in ("sensor", "line", "registers"):
        if table_name in data and not isinstance(data[table_name], dict):
            raise fail(f"[{table_name}]", "must be a table")

    sensor = data.get("sensor", {})
    check_keys(sensor, _SENSOR_KEYS, "[sensor]")
    name = get_str(sensor, "name", "[sensor]", default_name)
    description = get_str(sensor, "description", "[sensor]", "")
    unit_id = get_int(sensor, "unit_id", "[sensor]", 0, 247, default=1)
    function = get_int(sensor, "function", "[sensor]", 0, 255, default=3)
    if function not in (3, 4):
        raise fail("[sensor].function",
                   f"must be 3 (holding registers) or 4 (input registers), got {function}")

    line_t = data.get("line", {})
    check_keys(line_t, _LINE_KEYS, "[line]")
    parity = get_str(line_t, "parity", "[line]", "N").upper()
    if parity not in ("N", "E", "O"):
        raise fail("[line].parity", f"must be 'N', 'E' or 'O', got {parity!r}")
    stopbits = get_int(line_t, "stopbits", "[line]", 1, 2, default=1)
    bytesize = get_int(line_t, "bytesize", "[line]", 7, 8, default=8)
    timeout_s = get_float(line_t, "timeout_s", "[line]", 0.1)
    if not 0 < timeout_s <= 10:
        raise fail("[line].timeout_s", f"must be in (0, 10] s, got {timeout_s}")
    line = LineSettings(
        baudrate=get_int(line_t, "baudrate", "[line]", 300, 4_000_000, default=19200),
        parity=parity, stopbits=stopbits, bytesize=bytesize, timeout_s=timeout_s,
        retries=get_int(line_t, "retries", "[line]", 0, 5, default=1),
    )

    regs_t = data.get("registers")
    if regs_t is None:
        raise fail("[registers]", "missing (required, with at least [registers.position])")
    quantities: dict[str, Quantity] = {}
    for qname, entry in regs_t.items():
        where = f"[registers.{qname}]"
        if qname not in QUANTITIES:
            raise fail(where, f"unknown quantity (allowed: {', '.join(QUANTITIES)})")
        if not isinstance(entry, dict):
            raise fail(where, "must be a table")
        check_keys(entry, _ENTRY_KEYS, where)
        if "type" not in entry:
            raise fail(f"{where}.type", f"missing (required; one of {', '.join(DATA_TYPES)})")
        dtype = entry["type"]
        if dtype not in DATA_TYPES:
            raise fail(f"{where}.type",
                       f"unknown data type {dtype!r} (expected one of {', '.join(DATA_TYPES)})")
        word_order = entry.get("word_order", "big")
        if word_order not in WORD_ORDERS:
            raise fail(f"{where}.word_order",
                       f"bad word order {word_order!r} (expected 'big' or 'little')")
        n_regs = DATA_TYPES[dtype][0]
        address = get_int(entry, "address", where, 0, 65536 - n_regs)
        scale = get_float(entry, "scale", where, 1.0)
        if scale == 0:
            raise fail(f"{where}.scale", "must not be 0")
        units = get_str(entry, "units", where, QUANTITIES[qname])
        if qname == "position" and units != "mm":
            raise fail(f"{where}.units",
                       f"position must be scaled to 'mm' (set scale), got {units!r}")
        if qname == "status":
            if dtype not in ("uint16", "int16", "uint32"):
                raise fail(f"{where}.type", f"status must be an integer word, got {dtype!r}")
            if "scale" in entry or "offset" in entry:
                raise fail(where, "status takes no scale/offset (it is a bit field)")
        elif "error_mask" in entry:
            raise fail(f"{where}.error_mask", "only [registers.status] takes error_mask")
        quantities[qname] = Quantity(
            name=qname, address=address, dtype=dtype, word_order=word_order, scale=scale,
            offset=get_float(entry, "offset", where, 0.0), units=units,
            error_mask=get_int(entry, "error_mask", where, 0, 0xFFFFFFFF, default=0),
            description=get_str(entry, "description", where, ""),
        )
    if "position" not in quantities:
        raise fail("[registers.position]", "missing (every map needs a position entry)")

    used: dict[int, str] = {}
    for q in quantities.values():
        for a in range(q.address, q.address + q.count):
            if a in used:
                raise fail(f"[registers.{q.name}].address",
                           f"register {a} overlaps [registers.{used[a]}]")
            used[a] = q.name
    return SensorMap(name=name, unit_id=unit_id, function=function, quantities=quantities,
                     line=line, source=source, description=description)


# --------------------------------------------------------------------------------------------
# transport spec
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TransportSpec:
    """Parsed ``tcp:HOST:PORT`` or ``rtu:DEVICE[:BAUD[:FORMAT]]``."""

    kind: str  # "tcp" | "rtu"
    host: str = ""
    port: int = 502
    device: str = ""
    baudrate: int | None = None
    bytesize: int | None = None
    parity: str | None = None
    stopbits: int | None = None

    def __str__(self) -> str:
        if self.kind == "tcp":
            host = f"[{self.host}]" if ":" in self.host else self.host
            return f"tcp:{host}:{self.port}"
        out = f"rtu:{self.device}"
        if self.baudrate:
            out += f":{self.baudrate}"
        return out


_FORMAT_RE = re.compile(r"^([78])([NEO])([12])$", re.IGNORECASE)


def parse_sensor_spec(spec: str) -> TransportSpec:
    """Parse a transport spec; ``ValueError`` with a readable message when malformed."""
    if not isinstance(spec, str) or ":" not in spec:
        raise ValueError(f"sensor spec {spec!r}: expected tcp:HOST:PORT or rtu:DEVICE[:BAUD]")
    kind, rest = spec.split(":", 1)
    kind = kind.lower()
    if kind == "tcp":
        if rest.startswith("["):
            host, _, tail = rest[1:].partition("]")
            port_s = tail[1:] if tail.startswith(":") else tail
        elif rest.count(":") == 1:
            host, port_s = rest.split(":")
        elif ":" not in rest:
            host, port_s = rest, ""
        else:
            raise ValueError(f"sensor spec {spec!r}: put IPv6 hosts in brackets, tcp:[::1]:502")
        if not host:
            raise ValueError(f"sensor spec {spec!r}: missing host")
        port = 502
        if port_s:
            if not port_s.isdigit() or not 0 < int(port_s) < 65536:
                raise ValueError(f"sensor spec {spec!r}: bad port {port_s!r}")
            port = int(port_s)
        return TransportSpec("tcp", host=host, port=port)
    if kind == "rtu":
        parts = rest.split(":")
        fmt = None
        if len(parts) > 1 and _FORMAT_RE.match(parts[-1]):
            fmt = _FORMAT_RE.match(parts.pop())
        baud = None
        if len(parts) > 1 and parts[-1].isdigit():
            baud = int(parts.pop())
            if baud <= 0:
                raise ValueError(f"sensor spec {spec!r}: bad baud rate")
        device = ":".join(parts)
        if not device:
            raise ValueError(f"sensor spec {spec!r}: missing serial device")
        return TransportSpec(
            "rtu", device=device, baudrate=baud,
            bytesize=int(fmt.group(1)) if fmt else None,
            parity=fmt.group(2).upper() if fmt else None,
            stopbits=int(fmt.group(3)) if fmt else None,
        )
    raise ValueError(f"sensor spec {spec!r}: unknown transport {kind!r} (use tcp: or rtu:)")


# --------------------------------------------------------------------------------------------
# the driver
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sample:
    """One reading. ``t_s`` is ``time.monotonic()`` at the middle of the request."""

    position_mm: float
    t_s: float
    flags: int = 0
    latency_s: float = 0.0
    status: int | None = None
    temperature_c: float | None = None
    error: str = ""

    @property
    def ok(self) -> bool:
        """True when ``position_mm`` is a real measurement (no link-problem flag)."""
        return not self.flags & FLAGS_INVALID


class DisplacementSensor:
    """Synchronous Modbus displacement sensor client (one owner thread).

    ``sensor_map``: a :class:`SensorMap`, a map file path or a shipped map name.
    ``spec``: a transport spec string or :class:`TransportSpec`.
    ``timeout_s`` / ``retries`` override the map's ``[line]`` values; ``reconnect_interval_s`` is
    the minimum time between reconnect attempts after a failed one (reads in between raise
    :class:`SensorLinkLost` at once).
    """

    def __init__(
        self,
        sensor_map: SensorMap | str | Path,
        spec: str | TransportSpec,
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
        unit_id: int | None = None,
        reconnect_interval_s: float = 0.2,
    ) -> None:
        self.map = sensor_map if isinstance(sensor_map, SensorMap) else load_map(sensor_map)
        self.spec = spec if isinstance(spec, TransportSpec) else parse_sensor_spec(spec)
        self.timeout_s = float(timeout_s if timeout_s is not None else self.map.line.timeout_s)
        if not self.timeout_s > 0:
            raise ValueError("timeout_s must be > 0")
        self.retries = int(retries if retries is not None else self.map.line.retries)
        if self.retries < 0:
            raise ValueError("retries must be >= 0")
        self.unit_id = self.map.unit_id if unit_id is None else int(unit_id)
        self.reconnect_interval_s = float(reconnect_interval_s)
        self._blocks = self.map.blocks()
        self._client: Any = None
        self._last_connect_fail = -math.inf
        self._rx_seen = False
        self.stats = {"reads": 0, "ok": 0, "timeouts": 0, "exceptions": 0, "link_lost": 0,
                      "framing": 0, "retries": 0, "connects": 0}

    # -- lifecycle ------------------------------------------------------------------------

    def __repr__(self) -> str:
        return f"DisplacementSensor({self.map.name!r}, {str(self.spec)!r})"

    def __enter__(self) -> DisplacementSensor:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._client is not None and bool(self._client.connected)

    def connect(self) -> None:
        """Open the link; :class:`SensorLinkLost` if the sensor cannot be reached."""
        if self.connected:
            return
        self._drop_client()
        client = self._make_client()
        try:
            ok = client.connect()
        except Exception as exc:  # pyserial/termios raise assorted types
            ok = False
            err = exc
        else:
            err = None
        if not ok:
            self._last_connect_fail = time.monotonic()
            _quiet_close(client)
            detail = f": {err}" if err else ""
            raise SensorLinkLost(f"cannot connect to {self.spec}{detail}")
        self._client = client
        self.stats["connects"] += 1

    def close(self) -> None:
        """Close the link (idempotent)."""
        self._drop_client()

    def make_safe(self) -> None:
        """Nothing to switch off on a sensor: close cleanly. Never raises."""
        try:
            self.close()
        except Exception:  # make_safe must never raise
            self._client = None

    # -- reading --------------------------------------------------------------------------

    def read(self) -> Sample:
        """Read every quantity of the map (one request per contiguous block).

        Raises :class:`SensorTimeout`, :class:`SensorException`, :class:`SensorFrameError` or
        :class:`SensorLinkLost`; a sensor status word with ``error_mask`` bits set is not an error
        but sets ``FLAG_SENSOR_STATUS``.
        """
        self.stats["reads"] += 1
        t0 = time.monotonic()
        values: dict[str, float | int] = {}
        flags = 0
        try:
            for start, count, quantities in self._blocks:
                regs, retried = self._read_block(start, count)
                if retried:
                    flags |= FLAG_RETRIED
                for q in quantities:
                    off = q.address - start
                    values[q.name] = q.decode(regs[off : off + q.count])
        except SensorError as exc:
            key = {FLAG_TIMEOUT: "timeouts", FLAG_EXCEPTION: "exceptions",
                   FLAG_LINK_LOST: "link_lost", FLAG_FRAMING: "framing"}.get(exc.flag)
            if key:
                self.stats[key] += 1
            raise
        t1 = time.monotonic()
        status = values.get("status")
        if status is not None and status & self.map.quantities["status"].error_mask:
            flags |= FLAG_SENSOR_STATUS
        temp = values.get("temperature")
        self.stats["ok"] += 1
        return Sample(
            position_mm=float(values["position"]), t_s=0.5 * (t0 + t1), flags=flags,
            latency_s=t1 - t0, status=None if status is None else int(status),
            temperature_c=None if temp is None else float(temp),
        )

    def read_or_flag(self) -> Sample:
        """Like :meth:`read` but never raises on link problems: returns a flagged NaN sample."""
        t0 = time.monotonic()
        try:
            return self.read()
        except SensorError as exc:
            t1 = time.monotonic()
            return Sample(position_mm=math.nan, t_s=0.5 * (t0 + t1),
                          flags=exc.flag or FLAG_LINK_LOST, latency_s=t1 - t0, error=str(exc))

    def read_registers(self, address: int, count: int) -> list[int]:
        """Raw read of ``count`` registers with the map's function code (diagnostics)."""
        regs, _ = self._read_block(address, count)
        return regs

    # -- internals ------------------------------------------------------------------------

    def _make_client(self):
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        if self.spec.kind == "tcp":
            return ModbusTcpClient(
                self.spec.host, port=self.spec.port, timeout=self.timeout_s, retries=0,
                reconnect_delay=0, trace_packet=self._trace_packet,
            )
        line = self.map.line
        return ModbusSerialClient(
            self.spec.device,
            baudrate=self.spec.baudrate or line.baudrate,
            bytesize=self.spec.bytesize or line.bytesize,
            parity=self.spec.parity or line.parity,
            stopbits=self.spec.stopbits or line.stopbits,
            timeout=self.timeout_s, retries=0, reconnect_delay=0,
            trace_packet=self._trace_packet,
        )

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending and data:
            self._rx_seen = True
        return data

    def _drop_client(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            _quiet_close(client)

    def _ensure_connected(self) -> None:
        if self.connected:
            return
        if time.monotonic() - self._last_connect_fail < self.reconnect_interval_s:
            raise SensorLinkLost(f"link to {self.spec} is down (retrying shortly)")
        self.connect()

    def _read_block(self, address: int, count: int) -> tuple[list[int], bool]:
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        last: SensorError | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats["retries"] += 1
            self._ensure_connected()
            self._rx_seen = False
            try:
                if self.map.function == 3:
                    rr = self._client.read_holding_registers(
                        address, count=count, device_id=self.unit_id)
                else:
                    rr = self._client.read_input_registers(
                        address, count=count, device_id=self.unit_id)
            except ConnectionException as exc:
                self._drop_client()
                last = SensorLinkLost(f"{self.spec}: link lost ({_short(exc)})")
                continue
            except ModbusIOException as exc:
                # No valid answer in time. TCP: drop the connection so a late answer to this
                # request cannot be taken for the answer to the next one. RTU: keep the port
                # open (reopening real adapters is slow and may toggle DTR/RTS); the client
                # discards whatever is waiting in the input buffer before it sends again.
                if self.spec.kind == "tcp":
                    self._drop_client()
                if self._rx_seen:
                    last = SensorFrameError(f"{self.spec}: invalid response ({_short(exc)})")
                else:
                    last = SensorTimeout(f"{self.spec}: no response within {self.timeout_s} s")
                continue
            except OSError as exc:
                self._drop_client()
                last = SensorLinkLost(f"{self.spec}: link lost ({exc})")
                continue
            except Exception as exc:  # any other pymodbus failure: treat as a broken frame
                self._drop_client()
                last = SensorFrameError(f"{self.spec}: {type(exc).__name__}: {exc}")
                continue
            if rr.isError():
                code = int(getattr(rr, "exception_code", 0))
                raise SensorException(
                    code,
                    f"{self.spec}: Modbus exception {code} "
                    f"({EXCEPTION_NAMES.get(code, 'unknown')}) "
                    f"reading {count} register(s) at {address}",
                )
            regs = list(getattr(rr, "registers", []) or [])
            if len(regs) < count:
                if self.spec.kind == "tcp":
                    self._drop_client()
                last = SensorFrameError(
                    f"{self.spec}: asked for {count} registers, got {len(regs)}")
                continue
            return regs[:count], attempt > 0
        assert last is not None
        raise last


def _short(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def _quiet_close(client: Any) -> None:
    with contextlib.suppress(Exception):  # closing a broken link may raise anything
        client.close()
