"""The session contract (DESIGN.md §3): a folder with ``session.json`` and ``samples.csv``.

Writing: :class:`SessionWriter` appends rows and flushes at least once a second, writes
``session.json`` at the start and rewrites it atomically at the end, so a crashed run leaves a
readable session. :func:`write_session` writes a whole session at once into a temporary folder and
renames it into place, so a failed write leaves nothing half-written.

Reading: :func:`load_session` accepts a session folder or a bare CSV that has ``t_s``,
``current_A`` and ``position_mm`` (current-driven sessions) or ``temperature_C`` and
``position_mm`` (loops measured with a thermometer; ``t_s`` optional, row order then).
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
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
)
"""Contract columns, in this order."""
EXTRA_COLUMNS: tuple[str, ...] = ("temperature_C", "stress_MPa")
"""Columns that thermometer loops (imported data) carry after the contract columns."""
TEXT_COLUMNS = frozenset({"mode"})
SAMPLES_FILE = "samples.csv"
META_FILE = "session.json"


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


def _format_cell(value: Any) -> str:
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
    return repr(round(f, 9)) if abs(f) < 1e15 else repr(f)


def format_row(row: Mapping[str, Any], columns: Sequence[str] = COLUMNS) -> str:
    """One CSV line (no newline) of ``row`` in ``columns`` order; missing values are empty."""
    return ",".join(_format_cell(row.get(c)) for c in columns)


def _atomic_write_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_meta(folder: Path, meta: Mapping[str, Any]) -> None:
    """Write ``session.json`` atomically (temp file + rename)."""
    body = {"schema_version": SCHEMA_VERSION, **meta}
    _atomic_write_text(Path(folder) / META_FILE, json.dumps(body, indent=2, sort_keys=False) + "\n")


class SessionWriter:
    """Appends sample rows to ``samples.csv``; hands them to the OS at least every ``flush_s``.

    ``append`` only writes to the file and, when due, flushes Python's buffer to the OS (cheap,
    and enough for a killed process: the rows are in the page cache). The ``fsync`` to the disk
    runs on a background thread so that it never stalls the control loop. Use as a context
    manager or call :meth:`close` with the end status and reason.
    """

    def __init__(
        self,
        folder: str | Path,
        meta: Mapping[str, Any],
        columns: Sequence[str] = COLUMNS,
        flush_s: float = 0.5,
    ) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=False)
        self.columns = list(columns)
        self.meta: dict[str, Any] = {**meta, "status": "running", "columns": self.columns}
        self.flush_s = flush_s
        write_meta(self.folder, self.meta)
        self._fh = open(self.folder / SAMPLES_FILE, "w", encoding="utf-8", newline="")  # noqa: SIM115
        self._fh.write(",".join(self.columns) + "\n")
        self._fh.flush()
        self._last_flush = time.monotonic()
        self.rows_written = 0
        self._sync_due = threading.Event()
        self._closing = False
        self._syncer = threading.Thread(target=self._sync_loop, name="session-fsync", daemon=True)
        self._syncer.start()

    def append(self, row: Mapping[str, Any]) -> None:
        """Append one sample; missing columns become empty cells."""
        self._fh.write(format_row(row, self.columns) + "\n")
        self.rows_written += 1
        now = time.monotonic()
        if now - self._last_flush >= self.flush_s:
            self._fh.flush()
            self._sync_due.set()
            self._last_flush = now

    def _sync_loop(self) -> None:
        fd = self._fh.fileno()
        while not self._closing:
            self._sync_due.wait()
            self._sync_due.clear()
            with contextlib.suppress(OSError, ValueError):  # closed under us: close() syncs
                os.fsync(fd)

    def append_arrays(self, data: Mapping[str, Sequence[Any] | np.ndarray]) -> None:
        """Append many rows given as equally long columns."""
        n = len(next(iter(data.values())))
        cols = [data.get(c) for c in self.columns]
        lines = []
        for i in range(n):
            lines.append(",".join("" if col is None else _format_cell(col[i]) for col in cols))
        if lines:
            self._fh.write("\n".join(lines) + "\n")
        self.rows_written += n
        self.flush()

    def flush(self) -> None:
        """Rows to the disk now (blocking)."""
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self, status: str = "completed", reason: str = "", **extra: Any) -> None:
        """Flush rows and rewrite ``session.json`` with the end status and reason."""
        if self._fh.closed:
            return
        self._closing = True
        self._sync_due.set()
        self._syncer.join()
        self.flush()
        self._fh.close()
        self.meta.update(status=status, end_reason=reason, rows=self.rows_written, **extra)
        write_meta(self.folder, self.meta)

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
) -> Path:
    """Write a complete session into ``folder`` (must not exist) all-or-nothing.

    ``columns`` defaults to the contract columns followed by any extra columns present in
    ``data``.
    """
    folder = Path(folder)
    if folder.exists():
        raise SessionError(f"{folder} already exists; choose another --out")
    if columns is None:
        columns = list(COLUMNS) + [c for c in EXTRA_COLUMNS if c in data]
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder.parent, prefix=f".{folder.name}."))
    try:
        w = SessionWriter(tmp / "s", meta, columns=columns)
        w.append_arrays(data)
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


def read_samples_csv(
    path: str | Path, tolerate_truncated_tail: bool = True
) -> dict[str, np.ndarray]:
    """Read a contract CSV into column arrays.

    A last line cut short by a crash (fewer cells than the header) is dropped with a warning when
    ``tolerate_truncated_tail``; any other ragged line is an error naming the line.
    """
    path = Path(path)
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
    }


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
    data = read_samples_csv(csv_path)
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
    for i in range(n):
        yield [_format_cell(col[i]) for col in cols]


def export_csv(session: Session, out: str | Path, columns: Sequence[str] | None = None) -> int:
    """Write the session's samples (all columns, or ``columns`` in that order) to ``out``.

    Written to a temporary file and renamed, so a failed export leaves nothing behind.
    Returns the number of rows written.
    """
    columns = list(columns) if columns else list(session.columns)
    unknown = [c for c in columns if c not in session.data]
    if unknown:
        raise SessionError(
            f"unknown column(s) {', '.join(unknown)}; this session has {', '.join(session.columns)}"
        )
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(columns)
            n = 0
            for row in rows_from_arrays(session.data, columns):
                writer.writerow(row)
                n += 1
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return n
