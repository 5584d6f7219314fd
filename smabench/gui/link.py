"""The GUI's side of the runtime process (``smabench.bench.remote``): no Qt here.

:class:`RuntimeLink` starts the process, parses what it prints on a reader thread and queues it;
the GUI drains :meth:`RuntimeLink.poll` from its timer. :class:`SampleBuffer` keeps the streamed
samples in bounded numpy columns: the newest 0.5–1 h at 200 Hz at full resolution, everything
older as a min–max envelope (memory bounded whatever the session's length). A session with a
self-sense calibration (issue 26) has three more columns, :data:`SELFSENSE_PLOT_COLUMNS`; the
others keep the eight columns of :data:`PLOT_COLUMNS` and their memory.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import queue
import subprocess
import sys
import threading
from typing import Any

import numpy as np

from smabench.sessions import FLAG_FEEDBACK_RESISTANCE, session_columns

log = logging.getLogger(__name__)

PLOT_COLUMNS = (
    "t_s", "current_set_A", "current_A", "position_mm", "setpoint_mm", "temperature_est_C",
    "cycle", "temperature_C",
)  # fmt: skip
SELFSENSE_PLOT_COLUMNS = ("resistance_ohm", "position_est_mm", "feedback_resistance")
"""A self-sensing session's further columns: the wire's resistance (Ω), the position estimated
from it (mm), and 1 on rows the controller ran on that estimate (the ``flags`` column's
``FLAG_FEEDBACK_RESISTANCE``), else 0."""
LINK_COLUMNS = PLOT_COLUMNS + SELFSENSE_PLOT_COLUMNS
"""The columns :func:`parse_rows` gives (NaN where a row has none)."""
STREAM_COLUMNS = session_columns(selfsense=True)
"""The cells of a streamed row (``R`` line): ``samples.csv``'s columns with the self-sensing
ones after them (empty without a calibration)."""
FULL_ROWS = 720_000
"""Rows kept at full resolution by :class:`SampleBuffer` (1 h at 200 Hz)."""
ENVELOPE_ROWS = 400_000
"""Envelope rows (older data, min–max) before the envelope is folded 2:1."""
FOLD = 16
"""Full-resolution rows per envelope pair when the older half is folded."""
_INDEX = {c: STREAM_COLUMNS.index(c) for c in LINK_COLUMNS if c in STREAM_COLUMNS}
_FLAGS = STREAM_COLUMNS.index("flags")


class SampleBuffer:
    """Streamed samples in numpy columns, bounded: the newest ``full_rows`` at full resolution,
    everything older as a min–max envelope.

    Storage is one array, ``[envelope | full resolution]``; :meth:`column` is a view of both,
    in time order. When the full-resolution part is full, its older half is folded into the
    envelope: each block of ``fold`` rows becomes two rows holding, per column, the block's
    minimum and maximum in the order they occurred (``t_s`` at the block's first and last
    sample), which keeps every peak a time plot shows. When the envelope passes
    ``envelope_rows`` it is folded 2:1 the same way. Memory is then at most
    ``(full_rows + envelope_rows) × len(columns) × 8`` bytes whatever the length (defaults, the
    eight :data:`PLOT_COLUMNS`: ≈ 72 MB: between half an hour and an hour at 200 Hz whole, plus
    the envelope of everything older; with :data:`SELFSENSE_PLOT_COLUMNS` ≈ 99 MB).
    """

    def __init__(self, capacity: int = 4096, full_rows: int = FULL_ROWS,
                 envelope_rows: int = ENVELOPE_ROWS, fold: int = FOLD,
                 columns: tuple[str, ...] = PLOT_COLUMNS) -> None:  # fmt: skip
        self.columns = tuple(columns)
        self._capacity = int(capacity)
        self._data = np.full((len(self.columns), capacity), np.nan)
        self.full_rows = int(full_rows)
        self.envelope_rows = int(envelope_rows)
        self.fold = int(fold)
        self.n = 0  # rows stored (envelope + full resolution)
        self.full_start = 0  # index of the first full-resolution row
        self.total = 0  # rows appended since the last clear

    def clear(self, columns: tuple[str, ...] | None = None) -> None:
        """Empty; with ``columns`` (other than the buffer's) the storage is made anew for them."""
        self.n = self.full_start = self.total = 0
        if columns is not None and tuple(columns) != self.columns:
            self.columns = tuple(columns)
            self._data = np.full((len(self.columns), self._capacity), np.nan)

    def has(self, name: str) -> bool:
        return name in self.columns

    @property
    def full_start_abs(self) -> int:
        """The first full-resolution row, counted in rows appended since the last clear."""
        return self.total - (self.n - self.full_start)

    def index_of(self, abs_row: int) -> int:
        """Storage index of an appended row (counted since clear), clamped to full resolution."""
        return self.full_start + max(0, abs_row - self.full_start_abs)

    @property
    def nbytes(self) -> int:
        return int(self._data.nbytes)

    def append_rows(self, rows: np.ndarray) -> None:
        """``rows``: (k, len(columns)) array (a long one, a replay, in bounded pieces)."""
        k = rows.shape[0]
        step = max(1, self.full_rows // 4)
        if k > step:
            for a in range(0, k, step):
                self.append_rows(rows[a : a + step])
            return
        if self.n - self.full_start + k > self.full_rows:
            self._fold_full()
        if self.n + k > self._data.shape[1]:
            size = max(2 * self._data.shape[1], self.n + k)
            size = min(size, max(self.n + k, self.full_rows + self.envelope_rows + k))
            grown = np.full((len(self.columns), size), np.nan)
            grown[:, : self.n] = self._data[:, : self.n]
            self._data = grown
        self._data[:, self.n : self.n + k] = rows.T
        self.n += k
        self.total += k

    def _fold_full(self) -> None:
        """The older half of the full-resolution rows → envelope (then the envelope 2:1 if it
        is over its size)."""
        d = self._data
        n_full = self.n - self.full_start
        take = (n_full // 2) // self.fold * self.fold
        if take == 0:
            return
        t = self.columns.index("t_s")
        env = _min_max(d[:, self.full_start : self.full_start + take], self.fold, t)
        e0 = self.full_start
        d[:, e0 : e0 + env.shape[1]] = env
        e1 = e0 + env.shape[1]
        rest = self.n - (self.full_start + take)
        d[:, e1 : e1 + rest] = d[:, self.full_start + take : self.n]
        self.full_start, self.n = e1, e1 + rest
        if self.full_start > self.envelope_rows:
            env = _min_max(d[:, : self.full_start - self.full_start % 4], 4, t)
            tail = self.full_start % 4
            keep = np.concatenate([env, d[:, self.full_start - tail : self.n]], axis=1)
            d[:, : keep.shape[1]] = keep
            self.full_start = env.shape[1] + tail
            self.n = keep.shape[1]

    def append_columns(self, columns: dict[str, np.ndarray]) -> None:
        n = len(columns["t_s"])
        rows = np.full((n, len(self.columns)), np.nan)
        for i, c in enumerate(self.columns):
            if c in columns and columns[c] is not None:
                rows[:, i] = np.asarray(columns[c], dtype=float)
        self.append_rows(rows)

    def column(self, name: str) -> np.ndarray:
        return self._data[self.columns.index(name), : self.n]


def select(rows: np.ndarray, columns: tuple[str, ...]) -> np.ndarray:
    """(k, len(LINK_COLUMNS)) rows of :func:`parse_rows` → their ``columns`` (a buffer's)."""
    if tuple(columns) == LINK_COLUMNS:
        return rows
    return rows[:, [LINK_COLUMNS.index(c) for c in columns]]


def _min_max(block: np.ndarray, fold: int, t: int) -> np.ndarray:
    """(columns, m·fold) → (columns, 2m): per block of ``fold`` rows and per column, the
    minimum and the maximum in the order they occurred (NaN-aware; an all-NaN block stays
    NaN); the time column (row ``t``) gets the block's first and last time."""
    c, n = block.shape
    b = block.reshape(c, n // fold, fold)
    out = np.empty((c, n // fold, 2))
    nan = np.isnan(b)
    lo_i = np.argmin(np.where(nan, np.inf, b), axis=2)
    hi_i = np.argmax(np.where(nan, -np.inf, b), axis=2)
    lo = np.take_along_axis(b, lo_i[..., None], axis=2)[..., 0]
    hi = np.take_along_axis(b, hi_i[..., None], axis=2)[..., 0]
    first_lo = lo_i <= hi_i
    out[..., 0] = np.where(first_lo, lo, hi)
    out[..., 1] = np.where(first_lo, hi, lo)
    out[t, :, 0], out[t, :, 1] = b[t, :, 0], b[t, :, -1]
    return out.reshape(c, -1)


def parse_rows(lines: list[str]) -> np.ndarray:
    """``R`` lines (without the prefix, cells as :data:`STREAM_COLUMNS`) → (k,
    len(LINK_COLUMNS)) floats; empty or missing cells → NaN; ``feedback_resistance`` from the
    row's flags (NaN without them)."""
    out = np.full((len(lines), len(LINK_COLUMNS)), np.nan)
    fb = LINK_COLUMNS.index("feedback_resistance")
    for r, line in enumerate(lines):
        cells = line.split(",")
        for i, c in enumerate(LINK_COLUMNS):
            j = _INDEX.get(c)
            text = cells[j] if j is not None and j < len(cells) else ""
            if text:
                with contextlib.suppress(ValueError):
                    out[r, i] = float(text)
        if len(cells) > _FLAGS and cells[_FLAGS]:
            with contextlib.suppress(ValueError):
                out[r, fb] = 1.0 if int(cells[_FLAGS]) & FLAG_FEEDBACK_RESISTANCE else 0.0
    return out


class RuntimeLink:
    """The runtime process: ``devices`` as for ``smabench.bench.remote``."""

    def __init__(self, devices: dict[str, Any]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-P", "-m", "smabench.bench.remote", json.dumps(devices)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self.stderr_lines: list[str] = []  # what the runtime wrote on stderr (the last 200)
        self._stderr = threading.Thread(target=self._read_stderr, name="runtime-stderr",
                                        daemon=True)  # fmt: skip
        self._stderr.start()
        self.events: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._rows: list[str] = []
        self._lock = threading.Lock()
        self.ports: dict[str, Any] | None = None
        self.status: dict[str, Any] = {}
        self._reader = threading.Thread(target=self._read, name="runtime-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        with contextlib.suppress(ValueError, OSError):  # our end closed (the window closing)
            self._read_lines()
        self.events.put(("Q", {"reason": f"runtime process exited ({self.proc.wait()})"}))

    def _read_lines(self) -> None:
        for line in self.proc.stdout:
            kind, _, rest = line.rstrip("\n").partition(" ")
            if kind == "R":
                with self._lock:
                    self._rows.append(rest)
                continue
            try:
                payload = json.loads(rest)
            except json.JSONDecodeError:
                log.warning("runtime printed %r", line)
                continue
            self.events.put((kind, payload))

    def _read_stderr(self) -> None:
        """The runtime's warnings and errors into this process's log (never lost, never on the
        operator's terminal as a stray traceback)."""
        with contextlib.suppress(ValueError, OSError):
            self._read_stderr_lines()

    def _read_stderr_lines(self) -> None:
        for line in self.proc.stderr:
            line = line.rstrip("\n")
            self.stderr_lines.append(line)
            del self.stderr_lines[:-200]
            log.info("runtime: %s", line)

    def take_rows(self) -> np.ndarray:
        with self._lock:
            rows, self._rows = self._rows, []
        return parse_rows(rows)

    def poll(self) -> list[tuple[str, Any]]:
        out = []
        while True:
            try:
                out.append(self.events.get_nowait())
            except queue.Empty:
                return out

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def send(self, command: str) -> None:
        if not self.alive:
            raise ConnectionError("the runtime process is not running")
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def start(self, settings: dict[str, Any]) -> None:
        self.send("start " + json.dumps(settings, default=_json_default))

    def estop(self, input_t: float | None = None, source: str = "") -> bool:
        """``estop [INPUT_T SOURCE]`` down the pipe in one system call (no Python buffering on
        the way; every other command is flushed whole, so lines never interleave): the input
        event's ``time.monotonic()`` and what it was, for the session's event log. False when
        the process is gone or the pipe is closed."""
        if not self.alive:
            return False
        words = ["estop"]
        if input_t is not None or source:
            words.append("nan" if input_t is None else f"{input_t:.6f}")
            words.append(" ".join(source.split()))
        try:
            os.write(self.proc.stdin.fileno(), (" ".join(words).rstrip() + "\n").encode())
            return True
        except (OSError, ValueError):
            return False

    def close(self, timeout_s: float = 10.0) -> None:
        if self.alive:
            with contextlib.suppress(OSError, ValueError):
                self.send("quit")
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(2.0)
        self._stderr.join(2.0)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return str(obj)
