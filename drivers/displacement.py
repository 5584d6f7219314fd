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

import concurrent.futures
import contextlib
import functools
import json
import logging
import math
import os
import re
import struct
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from smabench.drivers.base import (  # the sensor's errors, flags and Sample: the seam's own
    EXCEPTION_NAMES,
    FLAG_EXCEPTION,
    FLAG_FRAMING,
    FLAG_LINK_LOST,
    FLAG_OUT_OF_RANGE,
    FLAG_RETRIED,
    FLAG_SENSOR_STATUS,
    FLAG_TIMEOUT,
    Sample,
    SensorError,
    SensorException,
    SensorFrameError,
    SensorLinkLost,
    SensorTimeout,
)


class SensorMapError(SensorError, ValueError):
    """A register map file is missing, malformed or inconsistent (message names file and key)."""


SENSORS_DIR = Path(__file__).resolve().parent / "sensors"
log = logging.getLogger(__name__)
#: where Linux's ftdi_sio driver shows an adapter's latency timer, ms (16 by default)
LATENCY_TIMER_SYSFS = "/sys/bus/usb-serial/devices/{tty}/latency_timer"

# pymodbus logs every timeout at ERROR level with a packet dump; this driver reports link problems
# itself (typed errors, sample flags). A NullHandler keeps those messages off stderr when the
# application has not configured logging, and still lets them through when it has.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

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
ORDERS = ("big", "little")
WORD_ORDERS = ORDERS


def _check_order(order: str, what: str) -> None:
    if order not in ORDERS:
        raise ValueError(f"{what} {order!r} is not one of {', '.join(ORDERS)}")


def _swap(reg: int) -> int:
    return ((reg & 0xFF) << 8) | ((reg >> 8) & 0xFF)


def encode_registers(raw: int | float, dtype: str, word_order: str = "big",
                     byte_order: str = "big") -> list[int]:
    """Encode one raw (device-unit) value into 16-bit registers.

    ``word_order``: whether the most significant register comes first (``big``) or last
    (``little``); ``byte_order``: bytes inside each register as Modbus sends them (``big``) or
    swapped (``little``). Integers are rounded and must fit the type (``ValueError`` otherwise).
    """
    n_regs, fmt = _dtype(dtype)
    _check_order(word_order, "word order")
    _check_order(byte_order, "byte order")
    value: int | float = float(raw) if dtype == "float32" else int(round(raw))
    try:
        data = struct.pack(fmt, value)
    except (struct.error, OverflowError) as exc:
        raise ValueError(f"{raw!r} does not fit {dtype}") from exc
    regs = [int.from_bytes(data[i : i + 2], "big") for i in range(0, 2 * n_regs, 2)]
    if word_order == "little":
        regs.reverse()
    if byte_order == "little":
        regs = [_swap(r) for r in regs]
    return regs


def decode_registers(regs: list[int] | tuple[int, ...], dtype: str, word_order: str = "big",
                     byte_order: str = "big"):
    """Decode 16-bit registers into one raw value (inverse of :func:`encode_registers`)."""
    n_regs, fmt = _dtype(dtype)
    if len(regs) != n_regs:
        raise ValueError(f"{dtype} needs {n_regs} register(s), got {len(regs)}")
    _check_order(word_order, "word order")
    _check_order(byte_order, "byte order")
    ordered = [int(r) & 0xFFFF for r in regs]
    if byte_order == "little":
        ordered = [_swap(r) for r in ordered]
    if word_order == "little":
        ordered.reverse()
    data = b"".join(r.to_bytes(2, "big") for r in ordered)
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
SCHEMA_PATH = SENSORS_DIR / "map.schema.json"


@dataclass(frozen=True)
class Quantity:
    """One measured quantity: ``physical = raw * scale + offset`` (in ``units``).

    A raw value that is NaN/infinite, one of ``sentinels`` or outside ``valid_range`` means
    "no measurement" (:meth:`invalid_reason`); a status word is an error when it has an
    ``error_mask`` bit set or is one of ``error_values``.
    """

    name: str
    address: int
    dtype: str
    word_order: str = "big"
    scale: float = 1.0
    offset: float = 0.0
    units: str = ""
    error_mask: int = 0
    description: str = ""
    byte_order: str = "big"
    valid_range: tuple[float, float] | None = None
    sentinels: tuple[float, ...] = ()
    error_values: tuple[int, ...] = ()

    @property
    def count(self) -> int:
        return DATA_TYPES[self.dtype][0]

    def raw(self, regs: list[int]) -> float | int:
        """The raw (device-unit) value of the registers."""
        return decode_registers(regs, self.dtype, self.word_order, self.byte_order)

    def decode(self, regs: list[int]) -> float | int:
        raw = self.raw(regs)
        if self.name == "status":
            return int(raw)
        return raw * self.scale + self.offset

    def encode(self, value: float) -> list[int]:
        """Registers a device would serve for the physical ``value``."""
        if self.name == "status":
            return self.encode_raw(int(value))
        return self.encode_raw((value - self.offset) / self.scale)

    def encode_raw(self, raw: float) -> list[int]:
        """Registers a device would serve for the raw (device-unit) value."""
        return encode_registers(raw, self.dtype, self.word_order, self.byte_order)

    def invalid_reason(self, raw: float | int) -> str:
        """Why a raw position/temperature is no measurement ('' when it is one)."""
        if not math.isfinite(raw):
            return f"raw value {raw} (no measurement)"
        if raw in self.sentinels:
            return f"raw value {raw:g} is the sensor's 'no measurement' code"
        if self.valid_range is not None and not self.valid_range[0] <= raw <= self.valid_range[1]:
            lo, hi = self.valid_range
            return f"raw value {raw:g} outside the valid range {lo:g} … {hi:g}"
        return ""

    def status_error(self, word: int) -> bool:
        return bool(word & self.error_mask) or word in self.error_values

    @property
    def invalid_raw(self) -> float:
        """A raw value that :meth:`invalid_reason` rejects (for simulators and tests)."""
        if self.sentinels:
            return self.sentinels[0]
        if self.dtype == "float32":
            return math.nan
        if self.valid_range is not None:
            lo, hi = self.valid_range
            top = {"int16": 0x7FFF, "uint16": 0xFFFF, "int32": 0x7FFFFFFF,
                   "uint32": 0xFFFFFFFF}[self.dtype]
            return hi + 1 if hi < top else lo - 1
        raise ValueError(f"[registers.{self.name}] has no invalid value (no sentinels/range)")

    @property
    def error_word(self) -> int:
        """A status word :meth:`status_error` flags (for simulators and tests)."""
        if self.error_values:
            return self.error_values[0]
        if self.error_mask:
            return self.error_mask & -self.error_mask  # its lowest bit
        raise ValueError("[registers.status] has neither error_mask nor error_values")


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
class RegisterWrite:
    """Holding registers written on every connect (function 6 for one, 16 for several)."""

    address: int
    values: tuple[int, ...]
    description: str


@dataclass(frozen=True)
class RegisterCheck:
    """A register read on connect that must hold ``expect`` (else the map is wrong for it)."""

    address: int
    function: int
    expect: int
    description: str


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
    document: str = ""
    section: str = ""
    example: bool = False
    read_blocks: tuple[tuple[int, int], ...] = ()
    on_connect: tuple[RegisterWrite, ...] = ()
    checks: tuple[RegisterCheck, ...] = ()

    @property
    def position(self) -> Quantity:
        return self.quantities["position"]

    def blocks(self) -> list[tuple[int, int, list[Quantity]]]:
        """The read requests ``(start, count, quantities)``: the map's ``[[block]]`` list, or
        else one request per contiguous run of quantities."""
        qs = sorted(self.quantities.values(), key=lambda q: q.address)
        if self.read_blocks:
            return [(a, n, [q for q in qs if a <= q.address < a + n])
                    for a, n in self.read_blocks]
        out: list[tuple[int, int, list[Quantity]]] = []
        for q in qs:
            if out and out[-1][0] + out[-1][1] == q.address and out[-1][1] + q.count <= 125:
                start, count, block = out[-1]
                out[-1] = (start, count + q.count, [*block, q])
            else:
                out.append((q.address, q.count, [q]))
        return out

    def encode(self, name: str, value: float) -> dict[int, int]:
        """``{address: register}`` a device serves for quantity ``name`` at ``value``."""
        q = self.quantities[name]
        return {q.address + i: r for i, r in enumerate(q.encode(value))}

    def encode_raw(self, name: str, raw: float) -> dict[int, int]:
        """``{address: register}`` for a raw (device-unit) value of quantity ``name``."""
        q = self.quantities[name]
        return {q.address + i: r for i, r in enumerate(q.encode_raw(raw))}


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


@functools.cache
def _validator():
    import jsonschema

    schema = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)
    return cls(schema)


def _where(path: list) -> str:
    """``[registers.position].type`` from a JSON path (as the TOML file spells it)."""
    tables = [str(p) for p in path if not isinstance(p, int)]
    index = next((p for p in path if isinstance(p, int)), None)
    if not tables:
        return "(top level)"
    if tables[0] in ("block", "on_connect", "check"):
        head = f"[[{tables[0]}]]" + (f" #{index + 1}" if index is not None else "")
        return head + "".join(f".{t}" for t in tables[1:])
    n_table = 2 if tables[0] == "registers" and len(tables) > 1 else 1
    head = "[" + ".".join(tables[:n_table]) + "]"
    return head + "".join(f".{t}" for t in tables[n_table:])


def _schema_message(error) -> tuple[list, str]:
    """(path, words) of a jsonschema error, in the map's terms."""
    path, v, inst, sch = list(error.absolute_path), error.validator, error.instance, error.schema
    if v == "required":
        missing = error.message.split("'")[1]
        return [*path, missing], "missing (required)"
    if v in ("additionalProperties", "unevaluatedProperties"):
        allowed = sorted(sch.get("properties", {}))
        extra = [k for k in inst if k not in allowed] if isinstance(inst, dict) else []
        where = [*path, extra[0]] if extra else path
        what = "unknown quantity" if path == ["registers"] else "unknown key"
        return where, f"{what}" + (f" (allowed: {', '.join(allowed)})" if allowed else "")
    if v == "enum":
        choices = ", ".join(repr(c) for c in error.validator_value)
        label = "unknown data type" if path and path[-1] == "type" else "bad value"
        return path, f"{label} {inst!r} (expected one of {choices})"
    if v == "const":
        return path, f"must be {error.validator_value!r}, got {inst!r}"
    if v == "type":
        return path, f"must be of type {error.validator_value}, got {inst!r}"
    if v in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        lo = sch.get("minimum", sch.get("exclusiveMinimum", "-inf"))
        hi = sch.get("maximum", sch.get("exclusiveMaximum", "inf"))
        return path, f"must be in {lo}..{hi}, got {inst!r}"
    if v == "not":
        return path, f"must not be {inst!r}"
    return path, error.message


def parse_map(data: dict[str, Any], *, source: str = "<memory>",
              default_name: str = "sensor") -> SensorMap:
    """Validate a map already parsed from TOML against the declared schema
    (``drivers/sensors/map.schema.json``) plus the register layout (overlaps, blocks);
    errors name ``source`` and the offending key."""
    import jsonschema

    def fail(where: str, msg: str) -> SensorMapError:
        return SensorMapError(f"{source}: {_printable(where)}: {_printable(msg)}")

    if not isinstance(data, dict):
        raise SensorMapError(f"{source}: expected a TOML table")
    bad_number = _first_non_finite(data, [])
    if bad_number is not None:
        raise fail(_where(bad_number[0]), f"must be a finite number, got {bad_number[1]!r}")
    error = jsonschema.exceptions.best_match(_validator().iter_errors(data))
    if error is not None:
        path, words = _schema_message(error)
        raise fail(_where(path), words)

    sensor, line_t = data.get("sensor", {}), data.get("line", {})
    line = LineSettings(**{k: line_t[k] for k in line_t})
    quantities: dict[str, Quantity] = {}
    for qname, e in data["registers"].items():
        vr = e.get("valid_range")
        if vr is not None and vr[0] > vr[1]:
            raise fail(f"[registers.{qname}].valid_range", f"low end above high end: {vr}")
        quantities[qname] = Quantity(
            name=qname, address=e["address"], dtype=e["type"],
            word_order=e.get("word_order", "big"), byte_order=e.get("byte_order", "big"),
            scale=float(e.get("scale", 1.0)), offset=float(e.get("offset", 0.0)),
            units=e.get("units", QUANTITIES[qname]), error_mask=e.get("error_mask", 0),
            description=e.get("description", ""),
            valid_range=None if vr is None else (float(vr[0]), float(vr[1])),
            sentinels=tuple(e.get("sentinels", ())), error_values=tuple(e.get("error_values", ())),
        )
    used: dict[int, str] = {}
    for q in quantities.values():
        if q.address + q.count > 65536:
            raise fail(f"[registers.{q.name}].address", "runs past register 65535")
        for a in range(q.address, q.address + q.count):
            if a in used:
                raise fail(f"[registers.{q.name}].address",
                           f"register {a} overlaps [registers.{used[a]}]")
            used[a] = q.name
    blocks = tuple((b["address"], b["count"]) for b in data.get("block", ()))
    for q in quantities.values() if blocks else ():
        if not any(a <= q.address and q.address + q.count <= a + n for a, n in blocks):
            raise fail(f"[registers.{q.name}].address", "not inside any [[block]]")
    return SensorMap(
        name=sensor.get("name", default_name), unit_id=sensor.get("unit_id", 1),
        function=sensor.get("function", 3), quantities=quantities, line=line, source=source,
        description=sensor.get("description", ""), document=sensor.get("document", ""),
        section=sensor.get("section", ""), example=sensor.get("example", False),
        read_blocks=blocks,
        on_connect=tuple(RegisterWrite(w["address"], tuple(w["values"]), w["description"])
                         for w in data.get("on_connect", ())),
        checks=tuple(RegisterCheck(c["address"], c.get("function", 3), c["expect"],
                                   c["description"]) for c in data.get("check", ())),
    )


def _printable(text: str) -> str:
    """``text`` on one line: a control character from the file (a key ``"a\nb"``) escaped."""
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii")
                   for c in text)  # fmt: skip


def _first_non_finite(node: Any, path: list) -> tuple[list, float] | None:
    if isinstance(node, float) and not math.isfinite(node):
        return path, node
    items = node.items() if isinstance(node, dict) else enumerate(node) \
        if isinstance(node, list) else ()
    for key, value in items:
        found = _first_non_finite(value, [*path, key])
        if found is not None:
            return found
    return None


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
        self._latency_checked = False
        self.stats = {"reads": 0, "ok": 0, "timeouts": 0, "exceptions": 0, "link_lost": 0,
                      "framing": 0, "retries": 0, "connects": 0, "invalid": 0}

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
        """Open the link, check the map's ``[[check]]`` registers and write its
        ``[[on_connect]]`` registers (every connect: a power-cycled sensor forgets them).

        :class:`SensorLinkLost` if the sensor cannot be reached; :class:`SensorMapError` when a
        check register holds another value (the map does not fit this sensor); the Modbus
        errors of :meth:`read` when a check or write fails on the link.
        """
        if self.connected:
            return
        if self.spec.kind == "rtu" and not self._latency_checked:
            self._latency_checked = True
            latency = adapter_latency_ms(self.spec.device)
            if latency is not None and latency > 1:
                log.warning(
                    "%s: the USB adapter's latency timer is %d ms: every sensor answer can wait "
                    "that long; set it to 1 ms (drivers/sensors/README.md, 'USB adapters')",
                    self.spec.device, latency,
                )
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
        try:
            self._setup()
        except BaseException:
            self._drop_client()
            raise
        self.stats["connects"] += 1

    def _setup(self) -> None:
        for check in self.map.checks:
            (value,), _ = self._read_block(check.address, 1, check.function)
            if value != check.expect:
                raise SensorMapError(
                    f"{self.spec}: register {check.address} reads {value}, the map "
                    f"{self.map.source} expects {check.expect} ({check.description}): "
                    "wrong map for this sensor"
                )
        for w in self.map.on_connect:
            self._write(w.address, list(w.values), w.description)
            log.info("%s: wrote %s to register %d (%s)", self.spec, list(w.values), w.address,
                     w.description)

    def _write(self, address: int, values: list[int], what: str) -> None:
        from pymodbus.exceptions import ModbusException

        try:
            if len(values) == 1:
                rr = self._client.write_register(address, values[0], device_id=self.unit_id)
            else:
                rr = self._client.write_registers(address, values, device_id=self.unit_id)
        except (ModbusException, OSError) as exc:
            raise SensorLinkLost(f"{self.spec}: writing register {address}: {_short(exc)}") \
                from None
        if rr.isError():
            code = int(getattr(rr, "exception_code", 0))
            raise SensorException(code, f"{self.spec}: Modbus exception {code} "
                                        f"({EXCEPTION_NAMES.get(code, 'unknown')}) writing "
                                        f"register {address} ({what})")

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
        :class:`SensorLinkLost`. What the sensor itself reports as no measurement is not raised
        but makes the sample invalid (``position_mm`` NaN, the reason in ``error``): a status
        error (``FLAG_SENSOR_STATUS``), a sentinel, NaN or out-of-range position
        (``FLAG_OUT_OF_RANGE``).
        """
        self.stats["reads"] += 1
        t0 = time.monotonic()
        values: dict[str, float | int] = {}
        raws: dict[str, float | int] = {}
        flags = 0
        try:
            for start, count, quantities in self._blocks:
                regs, retried = self._read_block(start, count)
                if retried:
                    flags |= FLAG_RETRIED
                for q in quantities:
                    off = q.address - start
                    raws[q.name] = q.raw(regs[off : off + q.count])
                    values[q.name] = q.decode(regs[off : off + q.count])
        except SensorError as exc:
            key = {FLAG_TIMEOUT: "timeouts", FLAG_EXCEPTION: "exceptions",
                   FLAG_LINK_LOST: "link_lost", FLAG_FRAMING: "framing"}.get(exc.flag)
            if key:
                self.stats[key] += 1
            raise
        t1 = time.monotonic()
        position_mm = float(values["position"])
        errors = []
        status = values.get("status")
        if status is not None and self.map.quantities["status"].status_error(int(status)):
            flags |= FLAG_SENSOR_STATUS
            errors.append(f"sensor status 0x{int(status):04x} says error")
        reason = self.map.position.invalid_reason(raws["position"])
        if reason:
            flags |= FLAG_OUT_OF_RANGE
            errors.append(f"position {reason}")
        if errors:
            position_mm = math.nan
            self.stats["invalid"] += 1
        temp = values.get("temperature")
        if temp is not None and self.map.quantities["temperature"].invalid_reason(
            raws["temperature"]
        ):
            temp = None
        self.stats["ok"] += 1
        return Sample(
            position_mm=position_mm, t_s=0.5 * (t0 + t1), flags=flags,
            latency_s=t1 - t0, status=None if status is None else int(status),
            temperature_c=None if temp is None else float(temp), error="; ".join(errors),
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

    def read_in_background(self) -> concurrent.futures.Future[Sample]:
        """:meth:`read_or_flag` on a thread of its own (the caller leaves the client alone until
        the future is done)."""
        fut: concurrent.futures.Future[Sample] = concurrent.futures.Future()

        def run() -> None:
            try:
                fut.set_result(self.read_or_flag())
            except BaseException as exc:  # a closed client: the caller gets it from result()
                fut.set_exception(exc)

        threading.Thread(target=run, name="sensor-read", daemon=True).start()
        return fut

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

    def _read_block(self, address: int, count: int,
                    function: int | None = None) -> tuple[list[int], bool]:
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        function = self.map.function if function is None else function
        last: SensorError | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                self.stats["retries"] += 1
            if self._client is None or not self._client.connected:
                self._ensure_connected()
            self._rx_seen = False
            try:
                if function == 3:
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


def adapter_latency_ms(device: str) -> int | None:
    """The latency timer of the FTDI USB adapter behind serial ``device``, ms (symlinks such as
    ``/dev/serial/by-id/…`` are followed); None when it has none (not FTDI, a pty, not Linux).
    The adapter holds received bytes up to this long before it sends them to the host."""
    tty = os.path.basename(os.path.realpath(device))
    try:
        return int(Path(LATENCY_TIMER_SYSFS.format(tty=tty)).read_text().strip())
    except (OSError, ValueError):
        return None


def _short(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text[:160]


def _quiet_close(client: Any) -> None:
    with contextlib.suppress(Exception):  # closing a broken link may raise anything
        client.close()
