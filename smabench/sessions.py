"""The session contract (DESIGN.md §3): a folder with ``session.json`` and ``samples.csv``.

Writing: :class:`SessionWriter` appends rows and flushes at least once a second, writes
``session.json`` at the start and rewrites it atomically at the end, so a crashed run leaves a
readable session. :func:`write_session` writes a whole session at once into a temporary folder and
renames it into place, so a failed write leaves nothing half-written.

Reading: :func:`load_session` accepts a session folder or a bare CSV that has ``t_s``,
``current_A`` and ``position_mm`` (current-driven sessions) or ``temperature_C`` and
``position_mm`` (loops measured with a thermometer; ``t_s`` optional, row order then).

Long sessions (a campaign of 10 000 cycles): the writer keeps no rows in memory and rotates the
samples into chunk files ``samples.csv``, ``samples-00001.csv``, … (each with the header; a new
chunk starts at a cycle boundary once ``chunk_rows`` rows are written), so no file grows without
bound. Readers (:func:`load_session`, :func:`iter_sample_chunks`, ``smabench export``) see one
table. The writer also keeps ``cycles.csv`` live: one summary row per finished cycle
(:data:`CYCLE_COLUMNS`), appended and flushed when the next cycle starts.

This module is the one place for the session format's facts: the schema version, the column
order, the file names, the ``flags`` bits (:data:`FLAG_SENSOR_INVALID` …; the low byte is the
displacement sensor's own bits, defined by its driver) and the one atomic write
(:func:`atomic_write`) that every writer of a result file uses.

Schema history: 1 = the contract columns up to ``flags``; 2 = adds ``temperature_C`` (measured
wire temperature from an optional thermocouple, empty when absent), chunk files and
``cycles.csv``. Version-1 sessions read unchanged (a missing column is simply absent). Schema 2
was later extended without a new version, as nothing a reader relies on changed: the optional
self-sensing columns :data:`SELFSENSE_COLUMNS` (``resistance_ohm``, ``position_est_mm``; only in
sessions run with a self-sense calibration, after the contract columns) and the flag bit
:data:`FLAG_FEEDBACK_RESISTANCE` (issue 26).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import json
import logging
import math
import os
import re
import secrets
import shutil
import stat
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from smabench.drivers.base import FLAG_NAMES as SENSOR_FLAG_NAMES
from smabench.drivers.base import FLAGS_INVALID as SENSOR_FLAGS_INVALID

log = logging.getLogger(__name__)

SCHEMA_VERSION = 2
"""Version written into every ``session.json`` (see the schema history above)."""

# ``flags`` column: one integer per sample. Bits 0-7 are the displacement sensor's own flags
# (timeout, exception, link lost, framing, status, retried: smabench.drivers.displacement
# FLAG_*), copied as the sensor reported them; bits 8-13 are the bench runtime's.
SENSOR_FLAGS_MASK = 0x00FF
FLAG_SENSOR_INVALID = 1 << 8  # the sample's position is invalid (no value fed to the controller)
FLAG_TELEMETRY_STALE = 1 << 9  # the current driver's telemetry was older than the link timeout
FLAG_DEADLINE_MISSED = 1 << 10  # the loop tick came late
FLAG_INTERLOCK = 1 << 11  # an interlock tripped on this sample (the session ends)
FLAG_AFTER_END = 1 << 12  # recorded after the session ended, until the driver showed 0 A
FLAG_FEEDBACK_RESISTANCE = 1 << 13  # the controller's position was position_est_mm (from the
# wire's resistance), not the laser's: --feedback resistance, or the fallback while the laser's
# reading was invalid (position_mm still holds the laser's, empty when invalid)
RUNTIME_FLAG_NAMES: dict[int, str] = {
    FLAG_SENSOR_INVALID: "sensor_invalid",
    FLAG_TELEMETRY_STALE: "telemetry_stale",
    FLAG_DEADLINE_MISSED: "deadline_missed",
    FLAG_INTERLOCK: "interlock",
    FLAG_AFTER_END: "after_end",
    FLAG_FEEDBACK_RESISTANCE: "feedback_resistance",
}
FLAG_NAMES: dict[int, str] = {**SENSOR_FLAG_NAMES, **RUNTIME_FLAG_NAMES}
"""Every bit of the ``flags`` column and its name."""
FLAGS_POSITION_INVALID = FLAG_SENSOR_INVALID | SENSOR_FLAGS_INVALID


def describe_flags(flags: int) -> str:
    """``"timeout|sensor_invalid"`` style text of a ``flags`` value ('' when 0)."""
    names = [name for bit, name in FLAG_NAMES.items() if flags & bit]
    rest = int(flags) & ~sum(FLAG_NAMES)
    if rest:
        names.append(hex(rest))
    return "|".join(names)

COLUMNS: tuple[str, ...] = (
    "t_s",
    "current_set_A",
    "current_A",
    "voltage_V",
    "ambient_C",
    "position_mm",
    "setpoint_mm",
    "temperature_est_C",
    "mode",
    "cycle",
    "flags",
    "temperature_C",
)
"""Contract columns, in this order (``temperature_C``: measured wire temperature from an
optional thermocouple, °C, empty when absent; since schema 2)."""
SELFSENSE_COLUMNS: tuple[str, ...] = ("resistance_ohm", "position_est_mm")
"""Optional columns after :data:`COLUMNS`, only in sessions run with a self-sense calibration
(``smabench run --selfsense CAL.json``, issue 26): ``resistance_ohm``, the wire's resistance
``voltage_V / current_A`` of the row, Ω (empty below the calibration's ``min_current_a``);
``position_est_mm``, the position estimated from it online (:class:`smabench.selfsense.
SelfSenseEstimator`, the same floats ``smabench selfsense estimate`` gives on the session), mm.
Sessions without them read as before: a reader that wants them checks for the column."""


def session_columns(selfsense: bool = False) -> tuple[str, ...]:
    """The columns a bench session records: :data:`COLUMNS`, and :data:`SELFSENSE_COLUMNS` after
    them when it estimates the position from the wire's resistance."""
    return COLUMNS + SELFSENSE_COLUMNS if selfsense else COLUMNS


EXTRA_COLUMNS: tuple[str, ...] = ("temperature_C", "stress_MPa")
"""Columns that thermometer loops (imported data) may carry (those not in :data:`COLUMNS` go
after the contract columns)."""
TEXT_COLUMNS = frozenset({"mode"})
INTEGER_COLUMNS = frozenset({"cycle", "flags", "rows", "flagged_rows"})
"""Columns of samples and ``cycles.csv`` that hold integers: written without a decimal point
(``3``, not ``3.0``) whatever type the values arrive in, so that a CSV reader sees integers."""
SAMPLES_FILE = "samples.csv"
META_FILE = "session.json"
CYCLES_FILE = "cycles.csv"
EVENTS_FILE = "events.jsonl"  # the safety chain's events, one JSON object a line (EventLog)
WRITE_BLOCK_ROWS = 65_536
"""Rows formatted and written at once by :meth:`SessionWriter.append_arrays` (≈ 10 MB of text)."""
PROGRESS_S = 1.0
"""Seconds between two progress reports of a large write (:func:`write_session`)."""
CHUNK_ROWS = 1_000_000
"""Rows per samples chunk file before the writer rotates (≈ 80 MB, 83 min at 200 Hz)."""
_CHUNK_RE = re.compile(r"^samples-(\d{5})\.csv$")
CYCLE_COLUMNS: tuple[str, ...] = (
    "cycle",
    "t_start_s",
    "t_end_s",
    "rows",
    "flagged_rows",
    "current_max_A",
    "temperature_est_min_C",
    "temperature_est_max_C",
    "temperature_min_C",
    "temperature_max_C",
    "position_start_mm",
    "position_end_mm",
    "position_min_mm",
    "position_max_mm",
)
"""``cycles.csv``: one row per finished cycle, written live by :class:`SessionWriter`."""


class SessionError(ValueError):
    """A session folder or CSV that does not follow the contract (message says what and where)."""


@dataclass
class Session:
    """A loaded session: metadata from ``session.json`` and one numpy array per column."""

    path: Path
    meta: dict[str, Any]
    data: dict[str, np.ndarray]
    columns: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.data["position_mm"])

    def has(self, column: str) -> bool:
        """True when the column exists and holds at least one value."""
        col = self.data.get(column)
        if col is None:
            return False
        if col.dtype.kind == "f":
            return bool(np.isfinite(col).any())
        return bool(len(col))

    @property
    def is_thermometer_loop(self) -> bool:
        return self.has("temperature_C") and not self.has("current_A")

    @property
    def load_kg(self) -> float | None:
        v = self.meta.get("load_kg")
        return None if v is None else float(v)


def _format_cell(value: Any, integer: bool = False) -> str:
    """One cell as the session contract writes it: the shortest text that reads back as the
    same float64 (``repr``), integers (and, in an ``integer`` column, whole-number floats) as
    integers, NaN and None as an empty cell, text as it is."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return str(int(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    f = float(value)
    if math.isnan(f):
        return ""
    if integer and f.is_integer():
        return str(int(f))
    return repr(f)


_WHOLE_AS_FLOAT_MAX = 1e10
"""Whole-number floats below this magnitude are written ``3.0``, not ``3`` (a float column stays
a float column for a CSV reader such as pandas); larger ones are written with an exponent."""


def _arrow_array(x: np.ndarray, null: np.ndarray | None = None) -> Any:
    """A numeric or boolean numpy array as a pyarrow array over the same bytes, ``null`` the
    cells to leave empty. ``pa.array(ndarray)`` would import pandas to check the argument's
    type: 0.3–0.5 s the first time a session is written (a stall at a run's first rows)."""
    import pyarrow as pa

    x = np.ascontiguousarray(x)
    if x.dtype == np.bool_:
        kind, data = pa.bool_(), np.packbits(x, bitorder="little")
    else:
        kind, data = pa.from_numpy_dtype(x.dtype), x
    nulls = int(null.sum()) if null is not None else 0
    validity = pa.py_buffer(np.packbits(~null, bitorder="little")) if nulls else None
    return pa.Array.from_buffers(kind, len(x), [validity, pa.py_buffer(data)], null_count=nulls)


def _arrow_strings(values: Sequence[str]) -> Any:
    """A pyarrow string array of ``values`` built from its buffers (``pa.array(list)`` and
    ``pa.scalar(str)`` import pandas too, see :func:`_arrow_array`)."""
    import pyarrow as pa

    data = [v.encode("utf-8") for v in values]
    offsets = np.cumsum([0, *map(len, data)]).astype(np.int32)
    buffers = [None, pa.py_buffer(offsets), pa.py_buffer(b"".join(data))]
    return pa.Array.from_buffers(pa.string(), len(data), buffers)


def _float_text(x: np.ndarray) -> Any:
    """A float64 array as a pyarrow string array, one shortest round-trip text per value
    (pyarrow's compiled formatter, ≈ 4× ``repr``: ``2.5e-7``, ``1e+20``, ``inf``); a whole
    number below :data:`_WHOLE_AS_FLOAT_MAX` ends in ``.0``; NaN is null (an empty cell)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    x = np.ascontiguousarray(x, dtype=np.float64)
    nan = np.isnan(x)
    text = pc.cast(_arrow_array(x, nan), pa.string())
    with np.errstate(invalid="ignore"):
        whole = (np.trunc(x) == x) & (np.abs(x) < _WHOLE_AS_FLOAT_MAX)
    if whole.any():
        floats = pc.cast(_arrow_array(x[whole].astype(np.int64)), pa.string())
        dot0, empty = _arrow_strings([".0", ""])
        text = pc.replace_with_mask(text, _arrow_array(whole),
                                    pc.binary_join_element_wise(floats, dot0, empty))  # fmt: skip
        minus0 = (x == 0) & np.signbit(x)  # -0.0: the int64 lost its sign
        if minus0.any():
            text = pc.replace_with_mask(text, _arrow_array(minus0),
                                        _arrow_strings(["-0.0"] * int(minus0.sum())))
    return text


def _integer_text(x: np.ndarray) -> Any | None:
    """An integer column given as floats as a pyarrow int64 array (NaN null); None when a value
    is not a whole number or beyond int64 (the caller then formats cell by cell)."""

    nan = np.isnan(x)
    ok = x[~nan]
    if ok.size and not ((np.trunc(ok) == ok).all() and (np.abs(ok) < 2.0**63).all()):
        return None
    return _arrow_array(np.where(nan, 0, x).astype(np.int64), nan)


def _arrow_column(col: Any, i: int, j: int, integer: bool) -> Any:
    """Cells ``i:j`` of one column as a pyarrow array whose CSV text is the contract's."""
    import pyarrow as pa

    if col is None:
        return pa.nulls(j - i, pa.string())
    if isinstance(col, np.ndarray) and col.dtype.kind in "iub":
        return _arrow_array(col[i:j].astype(np.int64))
    if isinstance(col, np.ndarray) and col.dtype.kind == "f":
        x = col[i:j]
        if integer:
            arr = _integer_text(x)
            if arr is not None:
                return arr
            return _arrow_strings([_format_cell(v, True) for v in x.tolist()])
        return _float_text(x)
    return _arrow_strings([_format_cell(col[k], integer) for k in range(i, j)])


_FORMAT_PART_ROWS = 16_384
"""Rows from which :func:`format_block` formats the parts of a block on parallel threads."""
_format_pool: list[Any] = []
"""[pid, ThreadPoolExecutor] of :func:`format_block` (a forked child makes its own)."""


def format_block(cols: Sequence[Any], columns: Sequence[str], i: int, j: int) -> bytes:
    """Rows ``i:j`` of ``cols`` (one array or None per name of ``columns``) as CSV lines, each
    cell as :func:`_format_cell` writes it (exponents spelled ``1e-7``, not ``1e-07``): the
    table is formatted by pyarrow's compiled CSV writer, a large block in as many parts as
    there are CPUs, on parallel threads (pyarrow's work runs without the GIL)."""
    workers = min(os.cpu_count() or 1, (j - i) // _FORMAT_PART_ROWS)
    if workers < 2:
        return _format_part(cols, columns, i, j)
    if not _format_pool or _format_pool[0] != os.getpid():  # none yet, or a forked child's
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(os.cpu_count(), thread_name_prefix="session-format")
        _format_pool[:] = [os.getpid(), pool]
    cuts = np.linspace(i, j, workers + 1).astype(int).tolist()
    parts = _format_pool[1].map(lambda a, b: _format_part(cols, columns, a, b),
                                cuts[:-1], cuts[1:])  # fmt: skip
    return b"".join(parts)


def _format_part(cols: Sequence[Any], columns: Sequence[str], i: int, j: int) -> bytes:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    arrays = [_arrow_column(col, i, j, c in INTEGER_COLUMNS)
              for c, col in zip(columns, cols, strict=True)]  # fmt: skip
    table = pa.Table.from_arrays(arrays, names=[f"c{k}" for k in range(len(arrays))])
    sink = pa.BufferOutputStream()
    try:
        pacsv.write_csv(table, sink, pacsv.WriteOptions(include_header=False,
                                                       quoting_style="none"))  # fmt: skip
    except pa.ArrowInvalid:  # a text cell holding a comma or quote: written as it is
        cells = [a.to_pylist() for a in arrays]
        text = "\n".join(",".join("" if v is None else str(v) for v in row)
                          for row in zip(*cells, strict=True))  # fmt: skip
        return (text + "\n").encode() if j > i else b""
    return sink.getvalue().to_pybytes()


def _format_column(col: Any, i: int, j: int, integer: bool = False) -> list[str]:
    """Cells ``i:j`` of one column as :func:`format_block` writes them, as Python strings."""
    return ["" if v is None else str(v) for v in _arrow_column(col, i, j, integer).to_pylist()]


def format_row(row: Mapping[str, Any], columns: Sequence[str] = COLUMNS) -> str:
    """One CSV line (no newline) of ``row`` in ``columns`` order; missing values are empty."""
    return ",".join(_format_cell(row.get(c), c in INTEGER_COLUMNS) for c in columns)


STDOUT_NAME = "-"
"""The output file name that means standard output (every ``--out``/``--json``/``--csv``)."""
_data_stdout: list[IO[Any]] = []
"""Where ``-`` writes while a command's own messages are redirected to stderr (see
:func:`data_to_stdout`); standard output when empty."""


@contextlib.contextmanager
def data_to_stdout() -> Iterator[None]:
    """While active, files named ``-`` go to the current standard output and everything else the
    command prints goes to stderr, so a ``--out -`` pipe gets the data only."""
    _data_stdout.append(sys.stdout)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        _data_stdout.pop()


def is_stdout(path: str | Path) -> bool:
    """True for ``-`` and for a path that is this process's standard output (``/dev/stdout``,
    ``/dev/fd/1``, the file or pipe that file descriptor 1 is)."""
    if str(path) == STDOUT_NAME:
        return True
    try:
        return os.path.samestat(os.stat(path), os.fstat(1))
    except (OSError, ValueError):
        return False


def writes_in_place(path: str | Path) -> bool:
    """True when ``path`` is a stream rather than a file to replace: ``-`` (standard output), a
    character device, a FIFO or a socket (after following symlinks), or anything under /dev or
    /proc (``/dev/stdout`` redirected to a file must not be renamed over)."""
    if str(path) == STDOUT_NAME:
        return True
    try:
        st = os.stat(path)
    except OSError:
        return False
    if not stat.S_ISREG(st.st_mode):
        return not stat.S_ISDIR(st.st_mode)
    absolute = os.path.abspath(path)
    return absolute.startswith(("/dev/", "/proc/"))


def _write_stream(path: str | Path, content: Any, binary: bool) -> None:
    if str(path) == STDOUT_NAME:
        out = _data_stdout[-1] if _data_stdout else sys.stdout
        out.flush()
        if binary:
            fh: IO[Any] = out.buffer
            close = False
        else:
            fh, close = out, False
    else:  # a device, FIFO or /dev path: opened as it is, never created, renamed or truncated
        flags = os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
        fd = os.open(path, flags)
        fh = os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")
        close = True
    try:
        if callable(content):
            content(fh)
        else:
            fh.write(content)
        fh.flush()
    finally:
        if close:
            fh.close()


def atomic_write(
    path: str | Path,
    content: str | bytes | Callable[[IO[Any]], Any],
    *,
    binary: bool | None = None,
    fsync: bool = True,
) -> Path:
    """Write a file all-or-nothing, with the permissions any new file gets (0666 less the umask).

    ``content`` is text, bytes, or a callable that writes into the open file object (binary when
    ``binary`` is true, e.g. ``fig.savefig``; text with ``newline=""`` otherwise). The data go
    to a hidden temporary file in the same folder, are flushed (and fsynced) and renamed over
    ``path``; on any error the temporary file is removed and ``path`` is untouched. The
    temporary file is created with mode 0666 so the kernel applies the umask, as it does for
    ``open(path, "w")`` (``mkstemp`` would make it 0600 and never read the umask). Returns
    ``path``; the parent folder is created when missing.

    Only regular files are replaced that way. ``-`` is standard output; a character device, a
    FIFO (another process reads it) and ``/dev/...`` paths are written in place
    (:func:`writes_in_place`); a symlink is followed and its target replaced, the link kept.
    """
    if binary is None:
        binary = isinstance(content, bytes)
    if writes_in_place(path):
        _write_stream(path, content, binary)
        return Path(path)
    given = path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))  # write the target; the link stays a link
    path.parent.mkdir(parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:
            continue
    else:  # pragma: no cover - 100 collisions of 32 random bits
        raise OSError(f"cannot create a temporary file beside {path}")
    try:
        fh = os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")
        with fh:
            if callable(content):
                content(fh)
            else:
                fh.write(content)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return given


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    """``obj`` as JSON (one trailing newline) through :func:`atomic_write`."""
    return atomic_write(path, json.dumps(obj, indent=indent) + "\n")


def _atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, text)


def write_meta(folder: Path, meta: Mapping[str, Any]) -> None:
    """Write ``session.json`` atomically (temp file + rename)."""
    body = {"schema_version": SCHEMA_VERSION}
    body.update((k, v) for k, v in meta.items() if k != "schema_version")
    atomic_write(Path(folder) / META_FILE, json.dumps(body, indent=2, sort_keys=False) + "\n")


def chunk_name(index: int) -> str:
    """File name of samples chunk ``index`` (0 is ``samples.csv``)."""
    return SAMPLES_FILE if index == 0 else f"samples-{index:05d}.csv"


def sample_files(folder: str | Path) -> list[Path]:
    """The samples chunk files of a session folder, in order (``samples.csv`` first)."""
    folder = Path(folder)
    first = folder / SAMPLES_FILE
    if not first.exists():
        return []
    more = sorted(
        (int(m.group(1)), p)
        for p in folder.iterdir()
        if (m := _CHUNK_RE.match(p.name)) is not None
    )
    return [first, *(p for _, p in more)]


class _CycleSummary:
    """Running per-cycle aggregates (constant memory) for ``cycles.csv``."""

    def __init__(self) -> None:
        self.cycle: Any = None
        self.reset(None)

    def reset(self, cycle: Any) -> None:
        self.cycle = cycle
        self.rows = 0
        self.flagged = 0
        self.t_start = self.t_end = math.nan
        self.pos_start = self.pos_end = math.nan
        self.mins: dict[str, float] = {}
        self.maxs: dict[str, float] = {}

    def add(self, row: Mapping[str, Any]) -> None:
        t = _num(row.get("t_s"))
        if self.rows == 0:
            self.t_start = t
        self.t_end = t
        self.rows += 1
        if _num(row.get("flags"), 0.0):
            self.flagged += 1
        pos = _num(row.get("position_mm"))
        if math.isfinite(pos):
            if not math.isfinite(self.pos_start):
                self.pos_start = pos
            self.pos_end = pos
        for col in ("current_A", "temperature_est_C", "temperature_C", "position_mm"):
            v = _num(row.get(col))
            if math.isfinite(v):
                self.mins[col] = min(self.mins.get(col, v), v)
                self.maxs[col] = max(self.maxs.get(col, v), v)

    def add_block(self, data: Mapping[str, Any], i0: int, i1: int) -> None:
        """Rows ``i0:i1`` of column arrays (all of one cycle) at once."""
        if i1 <= i0:
            return
        t = data.get("t_s")
        if t is not None:
            if self.rows == 0:
                self.t_start = _num(t[i0])
            self.t_end = _num(t[i1 - 1])
        self.rows += i1 - i0
        flags = data.get("flags")
        if flags is not None:
            f = _floats(flags[i0:i1])
            self.flagged += int(np.count_nonzero(np.nan_to_num(f)))
        for col in ("current_A", "temperature_est_C", "temperature_C", "position_mm"):
            raw = data.get(col)
            if raw is None:
                continue
            v = _floats(raw[i0:i1])
            ok = v[np.isfinite(v)]
            if not ok.size:
                continue
            lo, hi = float(ok.min()), float(ok.max())
            self.mins[col] = min(self.mins.get(col, lo), lo)
            self.maxs[col] = max(self.maxs.get(col, hi), hi)
            if col == "position_mm":
                if not math.isfinite(self.pos_start):
                    self.pos_start = float(ok[0])
                self.pos_end = float(ok[-1])

    def line(self) -> str:
        nan = math.nan
        mn, mx = self.mins, self.maxs
        return format_row(
            {
                "cycle": self.cycle,
                "t_start_s": self.t_start,
                "t_end_s": self.t_end,
                "rows": self.rows,
                "flagged_rows": self.flagged,
                "current_max_A": mx.get("current_A", nan),
                "temperature_est_min_C": mn.get("temperature_est_C", nan),
                "temperature_est_max_C": mx.get("temperature_est_C", nan),
                "temperature_min_C": mn.get("temperature_C", nan),
                "temperature_max_C": mx.get("temperature_C", nan),
                "position_start_mm": self.pos_start,
                "position_end_mm": self.pos_end,
                "position_min_mm": mn.get("position_mm", nan),
                "position_max_mm": mx.get("position_mm", nan),
            },
            CYCLE_COLUMNS,
        )


def _floats(seq: Any) -> np.ndarray:
    try:
        return np.asarray(seq, dtype=float)
    except (TypeError, ValueError):
        return np.array([_num(x) for x in seq], dtype=float)


def _num(value: Any, default: float = math.nan) -> float:
    if value is None or isinstance(value, str):
        return default
    try:
        return float(value)
    except (TypeError, ValueError):
        return default


class DiskFullError(OSError):
    """The session folder's file system filled up: the samples end at the last whole row
    (``lost_lines``: lines of the failed write that were not kept)."""

    lost_lines: int = 0
    reason: str = "disk full"


RESERVE_FILE = ".close-reserve"
EVENTS_RESERVE_BYTES = 4096  # of the reserve, given back for events.jsonl when the disk fills
"""A few kB the writer sets aside at the start and frees to close a session on a full disk."""
LOCK_FILE = ".recording.lock"
"""Held (``flock``) by the recording process while a session is running; gone at its end."""
RECORDER_DIED = "the recording process died"
"""``end_reason`` readers give a ``running`` session whose recording process is gone."""
ROW_BYTES_BUDGET = 160
"""Bytes a samples row takes at most in the contract columns (measured ≈ 75–110)."""
WALL_CLOCK_STEP_S = 2.0
"""A wall clock that moved this much more (or less) than the monotonic clock during a session
was stepped (NTP, an operator): ``session.json`` says by how much (``wall_clock_stepped_s``)."""
RESERVE_BYTES = 16384
"""Set aside for the closing (cycles.csv's last row, session.json twice during its rewrite)."""


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def _recorder_alive(folder: Path) -> bool:
    """Whether a live process holds ``folder``'s recording lock (False: none, or no lock)."""
    import fcntl

    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        return False
    except OSError:
        return True  # unreadable: do not pretend to know
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def session_status(folder: str | Path, meta: Mapping[str, Any] | None = None) -> tuple[str, str]:
    """``(status, end_reason)`` of a session as every reader shows it (the session list, the
    GUI, ``plan resume``): ``session.json``'s, except that a ``running`` session whose
    recording process is gone (killed with kill -9, a power cut) is ``aborted`` with the reason
    :data:`RECORDER_DIED`. ``meta``: ``session.json`` already read (read here when None)."""
    folder = Path(folder)
    meta_path = folder / META_FILE

    def read() -> Mapping[str, Any]:
        try:
            return json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}

    if meta is None:
        meta = read()
    status = str(meta.get("status", ""))
    if status != "running" or _recorder_alive(folder):
        return status, str(meta.get("end_reason", ""))
    meta = read()  # it may have closed between the two reads
    if meta.get("status") != "running":
        return str(meta.get("status", "")), str(meta.get("end_reason", ""))
    return "aborted", RECORDER_DIED


def close_dead_session(folder: str | Path) -> tuple[str, str]:
    """Write into ``session.json`` what :func:`session_status` tells of a ``running`` session
    whose recording process died (``aborted``, :data:`RECORDER_DIED`, the rows on disk), so
    every tool reads it so; a live or closed session is left alone. Returns its status and
    reason."""
    folder = Path(folder)
    status, reason = session_status(folder)
    if status != "aborted" or reason != RECORDER_DIED:
        return status, reason
    meta = json.loads((folder / META_FILE).read_text(encoding="utf-8"))
    rows = 0
    for path in sample_files(folder):
        with open(path, "rb") as fh:
            rows += max(0, sum(1 for line in fh if line.endswith(b"\n")) - 1)
    meta.update(status=status, end_reason=reason, rows=rows)
    write_meta(folder, meta)
    (folder / RESERVE_FILE).unlink(missing_ok=True)
    (folder / LOCK_FILE).unlink(missing_ok=True)
    return status, reason


def space_needed_bytes(rows: int) -> int:
    """Free space a session of ``rows`` samples needs (rows, cycles.csv, the closing reserve)."""
    return int(rows * ROW_BYTES_BUDGET * 1.05) + 2 * RESERVE_BYTES


def check_free_space(out_dir: str | Path, rows: int, what: str) -> None:
    """Raise :class:`SessionError` when the file system holding ``out_dir`` (or its nearest
    existing parent) cannot take a session of ``rows`` samples (``what``: the plan in words,
    e.g. "120 s at 200 Hz"), or cannot be written at all (read-only, no permission)."""
    path = Path(out_dir).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    need = space_needed_bytes(rows)
    try:
        st = os.statvfs(path)
    except OSError as exc:
        raise SessionError(f"{out_dir}: cannot check free space ({exc.strerror})") from None
    if st.f_flag & os.ST_RDONLY:
        raise SessionError(f"{out_dir}: read-only file system; choose another --out")
    if not os.access(path, os.W_OK):
        raise SessionError(f"{out_dir}: not writable; choose another --out")
    free = st.f_bavail * st.f_frsize
    if free < need:
        raise SessionError(
            f"{out_dir}: not enough free space for the session: {what} need "
            f"{_size(need)}, {_size(free)} free"
        )


def _size(n_bytes: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n_bytes < 1000 or unit == "GB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1000
    return f"{n_bytes:.1f} GB"  # pragma: no cover


class SessionWriter:
    """Appends sample rows to ``samples.csv``; hands them to the OS at least every ``flush_s``.

    ``append`` only adds the row to a buffer and, when due, writes the buffer to the file
    (cheap, and enough for a killed process: the rows are in the page cache). The ``fsync`` to
    the disk runs on a background thread so that it never stalls the control loop. Use as a
    context manager or call :meth:`close` with the end status and reason.

    Memory stays bounded whatever the length: rows go straight to the file, a new chunk file
    starts (at the next cycle boundary) once ``chunk_rows`` rows are in the current one (at
    ``2 × chunk_rows`` whatever the cycle), and ``cycles.csv`` gets one summary row per finished
    cycle (when the columns include ``cycle``).

    Faults: while running the writer holds :data:`LOCK_FILE` (``flock``), so a reader tells a
    live session from a dead one (:func:`session_status`); it sets :data:`RESERVE_FILE` aside;
    a full file system raises :class:`DiskFullError` from :meth:`append` with the samples cut
    back to the last whole row, and :meth:`close` frees the reserve first so the closing fits.
    """

    def __init__(
        self,
        folder: str | Path,
        meta: Mapping[str, Any],
        columns: Sequence[str] = COLUMNS,
        flush_s: float = 0.5,
        chunk_rows: int = CHUNK_ROWS,
    ) -> None:
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=False)
        self.columns = list(columns)
        self.meta: dict[str, Any] = {
            **meta,
            "status": "running",
            "columns": self.columns,
            "recorder": {"pid": os.getpid(), "host": os.uname().nodename, "boot_id": _boot_id()},
        }
        self.flush_s = flush_s
        self.chunk_rows = chunk_rows
        self._lock_fd = self._hold_lock()  # before session.json says "running"
        try:
            self._set_reserve_aside()
            write_meta(self.folder, self.meta)
        except BaseException:
            self._release_lock()
            raise
        self._header = ",".join(self.columns) + "\n"
        self._lock = threading.Lock()  # the fsync thread vs a rotation
        self._buf: list[str] = []
        self.full = ""  # why rows can no longer be written ("disk full"), "" while they can
        self.chunk = 0
        self._chunk_n = 0
        self._fh = self._open_chunk(0)
        self._cycles_fh = None
        self._summary: _CycleSummary | None = None
        if "cycle" in self.columns:
            self._cycles_fh = open(self.folder / CYCLES_FILE, "wb", buffering=0)  # noqa: SIM115
            self._write_whole(self._cycles_fh, (",".join(CYCLE_COLUMNS) + "\n").encode())
            self._summary = _CycleSummary()
        self._last_flush = time.monotonic()
        self._started_wall_s, self._started_mono_s = time.time(), time.monotonic()
        self.rows_written = 0
        self._sync_due = threading.Event()
        self._closing = False
        self._syncer = threading.Thread(target=self._sync_loop, name="session-fsync", daemon=True)
        self._syncer.start()

    # ------------------------------------------------------------------ faults
    def _hold_lock(self) -> int:
        import fcntl

        fd = os.open(self.folder / LOCK_FILE, os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC, 0o666)
        fcntl.flock(fd, fcntl.LOCK_EX)
        return fd

    def _release_lock(self) -> None:
        if self._lock_fd >= 0:
            with contextlib.suppress(OSError):
                (self.folder / LOCK_FILE).unlink()
            os.close(self._lock_fd)  # closing the last descriptor releases the flock
            self._lock_fd = -1

    def _set_reserve_aside(self) -> None:
        path = self.folder / RESERVE_FILE
        try:
            with open(path, "wb") as fh:
                fh.write(b"\0" * RESERVE_BYTES)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            path.unlink(missing_ok=True)
            msg = f"{self.folder}: no room for a session ({exc.strerror})"
            raise DiskFullError(exc.errno, msg) from None

    def _shrink_reserve_for_events(self) -> None:
        """On a full disk, give :data:`EVENTS_RESERVE_BYTES` of the reserve back at once, so the
        safety chain's events (the end, the output off: ``events.jsonl``), written before the
        closing, still fit; the rest stays for the closing."""
        with contextlib.suppress(OSError):
            path = self.folder / RESERVE_FILE
            os.truncate(path, min(path.stat().st_size, RESERVE_BYTES - EVENTS_RESERVE_BYTES))

    def _free_reserve(self) -> None:
        (self.folder / RESERVE_FILE).unlink(missing_ok=True)

    def _write_whole(self, fh: IO[bytes], data: bytes) -> None:
        """Write ``data`` (whole lines); on a full disk keep only the whole lines that fit,
        cut the file back to them, and raise :class:`DiskFullError` (``lost_lines``: how many
        lines did not fit)."""
        start = fh.tell()
        done = 0
        try:
            while done < len(data):
                n = fh.write(data[done:])
                if not n:
                    raise OSError(28, os.strerror(28))
                done += n
        except OSError as exc:
            keep = data.rfind(b"\n", 0, done) + 1
            with contextlib.suppress(OSError):
                os.ftruncate(fh.fileno(), start + keep)
                fh.seek(start + keep)
            full = DiskFullError(exc.errno, exc.strerror)
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                full.reason = f"session folder not writable ({exc.strerror})"
            self.full = full.reason
            full.lost_lines = data.count(b"\n") - data.count(b"\n", 0, keep)
            self._shrink_reserve_for_events()
            raise full from exc

    # ------------------------------------------------------------------ rows
    def _open_chunk(self, index: int):
        fh = open(self.folder / chunk_name(index), "wb", buffering=0)  # noqa: SIM115
        try:
            self._write_whole(fh, self._header.encode())
        except BaseException:
            fh.close()
            raise
        return fh

    def _write_buffer(self) -> None:
        """The buffered rows to the OS (whole rows only; :class:`DiskFullError` on a full disk)."""
        if not self._buf:
            return
        data = "".join(self._buf).encode()
        self._buf = []
        self._write_rows(data)

    def _write_rows(self, data: bytes) -> None:
        """Whole formatted rows to the OS (the counters lose the rows a full disk refused)."""
        try:
            self._write_whole(self._fh, data)
        except DiskFullError as exc:
            self.rows_written -= exc.lost_lines
            self._chunk_n -= exc.lost_lines
            raise

    def _rotate(self) -> None:
        self._write_buffer()
        new = self._open_chunk(self.chunk + 1)
        with self._lock:
            old, self._fh = self._fh, new
            self.chunk += 1
            self._chunk_n = 0
        os.fsync(old.fileno())
        old.close()
        log.info("%s: samples continue in %s", self.folder, chunk_name(self.chunk))

    def _cycle_done(self) -> None:
        summary = self._summary
        if summary is not None and summary.rows and self._cycles_fh is not None:
            self._write_whole(self._cycles_fh, (summary.line() + "\n").encode())

    def append(self, row: Mapping[str, Any]) -> None:
        """Append one sample; missing columns become empty cells. :class:`DiskFullError` when the
        file system is full (the session must end: :meth:`close` still fits)."""
        if self.full:
            full = DiskFullError(errno.ENOSPC, self.full)
            full.reason = self.full
            raise full
        summary = self._summary
        new_cycle = summary is not None and row.get("cycle") != summary.cycle
        if self._chunk_n >= self.chunk_rows and (
            new_cycle or summary is None or self._chunk_n >= 2 * self.chunk_rows
        ):
            self._rotate()
        if new_cycle:
            self._cycle_done()
            summary.reset(row.get("cycle"))
        if summary is not None:
            summary.add(row)
        self._buf.append(format_row(row, self.columns) + "\n")
        self._chunk_n += 1
        self.rows_written += 1
        now = time.monotonic()
        if now - self._last_flush >= self.flush_s:
            self._last_flush = now
            self._write_buffer()
            self._sync_due.set()

    def _sync_loop(self) -> None:
        while not self._closing:
            self._sync_due.wait()
            self._sync_due.clear()
            with self._lock, contextlib.suppress(OSError, ValueError):  # closed: close() syncs
                os.fsync(self._fh.fileno())

    def append_arrays(
        self, data: Mapping[str, Sequence[Any] | np.ndarray],
        progress: Callable[[int, int], None] | None = None,
    ) -> None:  # fmt: skip
        """Append many rows given as equally long columns (cycles and chunks as :meth:`append`);
        ``progress(rows_done, rows)`` is called about every :data:`PROGRESS_S` seconds."""
        n = len(next(iter(data.values())))
        last_progress_s = time.monotonic()
        cols = [data.get(c) for c in self.columns]
        cycle = data.get("cycle") if self._summary is not None else None
        if cycle is not None:
            cyc = np.asarray(cycle)
            starts = [0, *(np.flatnonzero(cyc[1:] != cyc[:-1]) + 1).tolist()] if n else []
        else:
            starts = [0] if n else []
        bounds = [*starts, n]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            summary = self._summary
            new_cycle = summary is not None and (
                (cycle[a] if cycle is not None else None) != summary.cycle
            )
            i = a
            while i < b:
                if summary is None:
                    if self._chunk_n >= self.chunk_rows:
                        self._rotate()
                    room = self.chunk_rows - self._chunk_n
                else:
                    if self._chunk_n >= 2 * self.chunk_rows or (
                        new_cycle and i == a and self._chunk_n >= self.chunk_rows
                    ):
                        self._rotate()
                    room = 2 * self.chunk_rows - self._chunk_n
                j = min(b, i + room, i + WRITE_BLOCK_ROWS)  # memory: one block's text
                if new_cycle and i == a:
                    self._cycle_done()
                    summary.reset(cycle[a])
                if summary is not None:
                    summary.add_block(data, i, j)
                block = format_block(cols, self.columns, i, j)
                self._write_buffer()
                self._chunk_n += j - i
                self.rows_written += j - i
                i = j
                self._write_rows(block)
                if progress is not None and time.monotonic() - last_progress_s >= PROGRESS_S:
                    progress(i, n)
                    last_progress_s = time.monotonic()
        self.flush()

    def flush(self) -> None:
        """Rows to the disk now (blocking)."""
        self._write_buffer()
        os.fsync(self._fh.fileno())

    def close(self, status: str = "completed", reason: str = "", **extra: Any) -> None:
        """Write the rows left and rewrite ``session.json`` with the end status and reason.

        On a full disk (:attr:`full`, or filling up now) the reserve is freed first, the rows
        that do not fit are dropped at a whole row, and the session ends ``aborted`` with the
        reason "disk full" (added to ``reason`` when it says something else)."""
        if self._fh.closed:
            return
        self._closing = True
        self._sync_due.set()
        self._syncer.join()
        if self.full:
            self._free_reserve()
        try:
            self.flush()
        except DiskFullError:
            self._free_reserve()
        with contextlib.suppress(OSError):
            os.fsync(self._fh.fileno())
        self._fh.close()
        if self._cycles_fh is not None:
            with contextlib.suppress(DiskFullError):
                self._cycle_done()
            with contextlib.suppress(OSError):
                os.fsync(self._cycles_fh.fileno())
            self._cycles_fh.close()
        self._free_reserve()
        if self.full and self.full not in reason:
            status, reason = "aborted", f"{self.full}; {reason}" if reason else self.full
        self.meta.update(status=status, end_reason=reason, rows=self.rows_written, **extra)
        self.meta["ended_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        # all timing is monotonic; the wall-clock stamps say when the host's clock was stepped
        step_s = (time.time() - self._started_wall_s) - (time.monotonic() - self._started_mono_s)
        if abs(step_s) > WALL_CLOCK_STEP_S:
            self.meta["wall_clock_stepped_s"] = round(step_s, 1)
        if self.chunk:
            self.meta["sample_files"] = [chunk_name(i) for i in range(self.chunk + 1)]
        try:
            write_meta(self.folder, self.meta)
        finally:
            self._release_lock()

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close()
        else:
            self.close(status="aborted", reason=f"{exc_type.__name__}: {exc}")


def write_session(
    folder: str | Path,
    meta: Mapping[str, Any],
    data: Mapping[str, Sequence[Any] | np.ndarray],
    columns: Sequence[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Write a complete session into ``folder`` (must not exist) all-or-nothing.

    ``columns`` defaults to the contract columns followed by any extra or self-sensing columns
    present in ``data``; ``progress(rows_done, rows)``: see :meth:`SessionWriter.append_arrays`.
    """
    folder = Path(folder)
    if folder.exists():
        raise SessionError(f"{folder} already exists; choose another --out")
    if columns is None:
        columns = list(COLUMNS) + [c for c in (*EXTRA_COLUMNS, *SELFSENSE_COLUMNS)
                                   if c in data and c not in COLUMNS]  # fmt: skip
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        w = SessionWriter(tmp / "s", meta, columns=columns)
        w.append_arrays(data, progress)
        w.close(status=str(meta.get("status", "completed")), reason=str(meta.get("end_reason", "")))
        os.replace(tmp / "s", folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def _parse_column(name: str, cells: list[str], source: Path) -> np.ndarray:
    if name in TEXT_COLUMNS:
        return np.array(cells, dtype=object)
    out = np.empty(len(cells), dtype=float)
    for i, cell in enumerate(cells):
        cell = cell.strip()
        if not cell:
            out[i] = np.nan
            continue
        try:
            out[i] = float(cell)
        except ValueError:
            raise SessionError(
                f"{source}: line {i + 2}: column {name!r} holds {cell!r}, not a number"
            ) from None
    return out


def _read_samples_strict(
    path: Path, tolerate_truncated_tail: bool, columns: Sequence[str] | None
) -> dict[str, np.ndarray]:
    try:
        with open(path, encoding="utf-8", newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise SessionError(f"{path}: not a CSV text file ({exc})") from None
    if not rows:
        raise SessionError(f"{path}: empty file, expected a header line")
    header = [h.strip() for h in rows[0]]
    if len(set(header)) != len(header):
        raise SessionError(f"{path}: duplicate column names in header {header}")
    body = rows[1:]
    while body and not any(c.strip() for c in body[-1]):
        body.pop()
    if body and tolerate_truncated_tail and len(body[-1]) != len(header):
        log.warning("%s: dropping a truncated last line (crashed run?)", path)
        body.pop()
    for i, row in enumerate(body):
        if len(row) != len(header):
            raise SessionError(
                f"{path}: line {i + 2} has {len(row)} cells, the header has {len(header)}"
            )
    cols = list(zip(*body, strict=True)) if body else [() for _ in header]
    return {
        name: _parse_column(name, list(cells), path)
        for name, cells in zip(header, cols, strict=True)
        if columns is None or name in columns
    }


def _read_samples_fast(
    path: Path, tolerate_truncated_tail: bool, columns: Sequence[str] | None
) -> dict[str, np.ndarray] | None:
    """The compiled reader (:mod:`smabench.fastcsv`, ≈ 4 M rows/s) on a plain contract CSV; None
    when the file needs the strict reader (quotes, ragged lines, bad cells: it names the line)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SessionError(f"cannot read {path}: {exc.strerror}") from None
    if b'"' in raw or b"\r" in raw:
        return None
    head, sep, body = raw.partition(b"\n")
    try:
        header = [h.strip() for h in head.decode("utf-8").split(",")]
    except UnicodeDecodeError:
        return None
    if not sep or len(set(header)) != len(header) or not header[0]:
        return None
    body = body.rstrip(b"\n")
    if body:
        last_nl = body.rfind(b"\n")
        last = body[last_nl + 1 :]
        if last.count(b",") != len(header) - 1:
            if not tolerate_truncated_tail:
                return None
            log.warning("%s: dropping a truncated last line (crashed run?)", path)
            body = body[: max(last_nl, 0)]
    want = [c for c in header if columns is None or c in columns]
    out: dict[str, np.ndarray] = {}
    if not body:
        for c in want:
            out[c] = np.zeros(0, dtype=object if c in TEXT_COLUMNS else float)
        return out
    numeric = [c for c in want if c not in TEXT_COLUMNS]
    text = [i for i, c in enumerate(header) if c in want and c in TEXT_COLUMNS]
    if numeric:
        from smabench.fastcsv import parse_numeric  # numba: imported (compiled) on first use

        parsed = parse_numeric(body, header, numeric)
        if parsed is None:
            return None
        out.update(parsed)
    try:
        for i in text:
            cells = np.loadtxt(
                io.BytesIO(body), delimiter=",", usecols=[i], dtype=str, ndmin=1, comments=None
            )
            out[header[i]] = cells.astype(object)
    except ValueError:
        return None
    return {c: out[c] for c in want}


def read_samples_csv(
    path: str | Path,
    tolerate_truncated_tail: bool = True,
    columns: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """Read a contract CSV into column arrays (only ``columns`` when given).

    A last line cut short by a crash (fewer cells than the header) is dropped with a warning when
    ``tolerate_truncated_tail``; any other ragged line is an error naming the line. Plain files
    go through numpy's parser; anything unusual through the strict reader.
    """
    path = Path(path)
    fast = _read_samples_fast(path, tolerate_truncated_tail, columns)
    if fast is not None:
        return fast
    return _read_samples_strict(path, tolerate_truncated_tail, columns)


def iter_sample_chunks(
    path: str | Path, columns: Sequence[str] | None = None
) -> Iterator[dict[str, np.ndarray]]:
    """The samples of a session folder (or a bare CSV) one chunk file at a time: memory stays
    that of one chunk. A truncated tail is tolerated only in the last chunk."""
    path = Path(path)
    files = sample_files(path) if path.is_dir() else [path]
    if not files:
        raise SessionError(f"{path}: no {SAMPLES_FILE} in this folder")
    for k, f in enumerate(files):
        yield read_samples_csv(f, tolerate_truncated_tail=k == len(files) - 1, columns=columns)


def _concat(chunks: list[dict[str, np.ndarray]], source: Path) -> dict[str, np.ndarray]:
    if len(chunks) == 1:
        return chunks[0]
    names = list(chunks[0])
    for c in chunks[1:]:
        if list(c) != names:
            raise SessionError(f"{source}: sample chunk files have different columns")
    return {n: np.concatenate([c[n] for c in chunks]) for n in names}


def load_session(path: str | Path) -> Session:
    """Load a session folder (or a bare CSV) and check it has what readers need."""
    path = Path(path)
    if path.is_dir():
        csv_path = path / SAMPLES_FILE
        if not csv_path.exists():
            raise SessionError(f"{path}: no {SAMPLES_FILE} in this folder")
        meta_path = path / META_FILE
        meta: dict[str, Any] = {}
        if meta_path.exists():
            try:
                meta = json.loads(meta_path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise SessionError(
                    f"{meta_path}: invalid JSON ({exc.msg}, line {exc.lineno})"
                ) from None
    elif path.is_file():
        csv_path, meta = path, {}
    else:
        raise SessionError(f"{path}: no such session folder or file")
    data = _concat(list(iter_sample_chunks(path)), path)
    header = list(data)
    if "position_mm" not in data:
        raise SessionError(f"{csv_path}: no position_mm column (columns: {', '.join(header)})")
    has_current = "current_A" in data and "t_s" in data
    has_thermo = "temperature_C" in data
    if not (has_current or has_thermo):
        raise SessionError(
            f"{csv_path}: needs t_s and current_A, or temperature_C, besides position_mm "
            f"(columns: {', '.join(header)})"
        )
    if "t_s" not in data:
        data["t_s"] = np.arange(len(data["position_mm"]), dtype=float)
        meta.setdefault("t_s_is_row_index", True)
    return Session(path=path, meta=meta, data=data, columns=header)


def rows_from_arrays(data: Mapping[str, np.ndarray], columns: Iterable[str]) -> Iterable[list[str]]:
    """Yield formatted CSV cells row by row for the chosen columns."""
    cols = [data[c] for c in columns]
    n = len(cols[0]) if cols else 0
    for i in range(0, n, 65536):  # a block of rows at a time, each column formatted at once
        j = min(n, i + 65536)
        cells = [_format_column(col, i, j, c in INTEGER_COLUMNS)
                 for c, col in zip(columns, cols, strict=True)]
        yield from map(list, zip(*cells, strict=True))


def export_csv(
    session: Session | str | Path, out: str | Path, columns: Sequence[str] | None = None
) -> int:
    """Write the session's samples (all columns, or ``columns`` in that order) to ``out``.

    ``session`` is a loaded :class:`Session` or a session folder/CSV path; a path is streamed
    one chunk file at a time (a 10 000-cycle session exports in the memory of one chunk) and
    its chunks come out as one table. Written through :func:`atomic_write`, so a failed export
    leaves nothing behind. Returns the number of rows written.
    """
    if isinstance(session, Session):
        have = list(session.columns)
        chunks: Iterable[Mapping[str, np.ndarray]] = [session.data]
    else:
        path = Path(session)
        load_session_meta_check(path)
        first = sample_files(path)[0] if path.is_dir() else path
        have = read_header(first)
        chunks = iter_sample_chunks(path)
    columns = list(columns) if columns else have
    unknown = [c for c in columns if c not in have]
    if unknown:
        raise SessionError(
            f"unknown column(s) {', '.join(unknown)}; this session has {', '.join(have)}"
        )
    count = [0]

    def write(fh: IO[str]) -> None:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(columns)
        for data in chunks:
            for row in rows_from_arrays(data, columns):
                writer.writerow(row)
                count[0] += 1

    atomic_write(out, write)
    return count[0]


def read_header(csv_path: str | Path) -> list[str]:
    """The column names of a samples CSV (its first line)."""
    try:
        with open(csv_path, encoding="utf-8", newline="") as fh:
            first = fh.readline()
    except OSError as exc:
        raise SessionError(f"cannot read {csv_path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise SessionError(f"{csv_path}: not a CSV text file ({exc})") from None
    if not first.strip():
        raise SessionError(f"{csv_path}: empty file, expected a header line")
    return [h.strip() for h in next(csv.reader([first]))]


def load_session_meta_check(path: str | Path) -> dict[str, Any]:
    """Check a session folder/CSV has what readers need without loading its samples; returns
    its metadata (``{}`` for a bare CSV). Raises :class:`SessionError` naming the problem."""
    path = Path(path)
    meta: dict[str, Any] = {}
    if path.is_dir():
        files = sample_files(path)
        if not files:
            raise SessionError(f"{path}: no {SAMPLES_FILE} in this folder")
        csv_path = files[0]
        meta_path = path / META_FILE
        if meta_path.exists():
            try:
                meta = json.loads(meta_path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise SessionError(
                    f"{meta_path}: invalid JSON ({exc.msg}, line {exc.lineno})"
                ) from None
    elif path.is_file():
        csv_path = path
    else:
        raise SessionError(f"{path}: no such session folder or file")
    header = read_header(csv_path)
    if "position_mm" not in header:
        raise SessionError(f"{csv_path}: no position_mm column (columns: {', '.join(header)})")
    if not (("current_A" in header and "t_s" in header) or "temperature_C" in header):
        raise SessionError(
            f"{csv_path}: needs t_s and current_A, or temperature_C, besides position_mm "
            f"(columns: {', '.join(header)})"
        )
    return meta


class EventLog:
    """``events.jsonl`` of a session: one JSON object a line, appended, flushed and synced at
    once (a handful of lines a session; each must survive the process dying right after it).

    Each line has ``event`` (what happened), ``t_host_s`` (``time.monotonic()``, s: one clock
    for every process on the host, so the GUI's input events and the runtime's frames compare)
    and ``wall`` (ISO 8601 with the UTC offset), then the event's own fields (``t_device_ms``:
    the current driver's clock, ms since its reset). Thread-safe."""

    def __init__(self, folder: str | Path) -> None:
        self.path = Path(folder) / EVENTS_FILE
        self._lock = threading.Lock()

    def write(self, event: str, t_host_s: float | None = None, **fields: Any) -> dict[str, Any]:
        """Append one event (``t_host_s`` defaults to now); returns what was written. An
        unwritable file is logged, never raised: the safety path must not stop on it."""
        finite = {k: None if isinstance(v, float) and not math.isfinite(v) else v
                  for k, v in fields.items()}  # fmt: skip
        line = {"event": event, "t_host_s": time.monotonic() if t_host_s is None else t_host_s,
                "wall": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **finite}  # fmt: skip
        text = json.dumps(line, allow_nan=False, default=str) + "\n"
        with self._lock:
            try:
                with open(self.path, "a", encoding="utf-8") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
            except OSError as exc:
                log.error("%s: event %s not written: %s", self.path, event, exc)
        return line


def read_events(folder: str | Path) -> list[dict[str, Any]]:
    """The events of a session folder in the order written ([] when it has none)."""
    path = Path(folder) / EVENTS_FILE
    if not path.exists():
        return []
    out = []
    for k, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not text.strip():
            continue
        try:
            out.append(json.loads(text))
        except json.JSONDecodeError as exc:
            raise SessionError(f"{path}:{k}: not a JSON event line: {exc}") from None
    return out
