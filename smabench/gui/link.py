"""The GUI's side of the runtime process (``smabench.bench.remote``): no Qt here.

:class:`RuntimeLink` starts the process, parses what it prints on a reader thread and queues it;
the GUI drains :meth:`RuntimeLink.poll` from its timer. :class:`SampleBuffer` keeps the streamed
samples in growable numpy columns (one hour at 200 Hz is 720 000 rows, ~40 MB).
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

from smabench.sessions import COLUMNS

log = logging.getLogger(__name__)

PLOT_COLUMNS = (
    "t_s", "current_set_A", "current_A", "position_mm", "setpoint_mm", "temperature_est_C",
    "cycle",
)  # fmt: skip
_INDEX = {c: COLUMNS.index(c) for c in PLOT_COLUMNS}


class SampleBuffer:
    """Append-only float columns with amortised O(1) growth; read views with :meth:`column`."""

    def __init__(self, capacity: int = 4096) -> None:
        self._data = np.full((len(PLOT_COLUMNS), capacity), np.nan)
        self.n = 0

    def clear(self) -> None:
        self.n = 0

    def append_rows(self, rows: np.ndarray) -> None:
        """``rows``: (k, len(PLOT_COLUMNS)) array."""
        k = rows.shape[0]
        if self.n + k > self._data.shape[1]:
            grown = np.full((len(PLOT_COLUMNS), max(2 * self._data.shape[1], self.n + k)), np.nan)
            grown[:, : self.n] = self._data[:, : self.n]
            self._data = grown
        self._data[:, self.n : self.n + k] = rows.T
        self.n += k

    def append_columns(self, columns: dict[str, np.ndarray]) -> None:
        n = len(columns["t_s"])
        rows = np.full((n, len(PLOT_COLUMNS)), np.nan)
        for i, c in enumerate(PLOT_COLUMNS):
            if c in columns and columns[c] is not None:
                rows[:, i] = np.asarray(columns[c], dtype=float)
        self.append_rows(rows)

    def column(self, name: str) -> np.ndarray:
        return self._data[PLOT_COLUMNS.index(name), : self.n]


def parse_rows(lines: list[str]) -> np.ndarray:
    """``R`` lines (without the prefix) → (k, len(PLOT_COLUMNS)) floats; empty cells → NaN."""
    out = np.full((len(lines), len(PLOT_COLUMNS)), np.nan)
    for r, line in enumerate(lines):
        cells = line.split(",")
        for i, c in enumerate(PLOT_COLUMNS):
            text = cells[_INDEX[c]]
            if text:
                with contextlib.suppress(ValueError):
                    out[r, i] = float(text)
    return out


class RuntimeLink:
    """The runtime process: ``devices`` as for ``smabench.bench.remote``."""

    def __init__(self, devices: dict[str, Any]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "smabench.bench.remote", json.dumps(devices)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        self.events: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self._rows: list[str] = []
        self._lock = threading.Lock()
        self.ports: dict[str, Any] | None = None
        self.status: dict[str, Any] = {}
        self._reader = threading.Thread(target=self._read, name="runtime-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
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
        self.events.put(("Q", {"reason": f"runtime process exited ({self.proc.wait()})"}))

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

    def estop(self) -> bool:
        """``estop`` down the pipe in one system call (no Python buffering on the way; every
        other command is flushed whole, so lines never interleave). False when the process is
        gone or the pipe is closed."""
        if not self.alive:
            return False
        try:
            os.write(self.proc.stdin.fileno(), b"estop\n")
            return True
        except (OSError, ValueError):
            return False

    def close(self, timeout_s: float = 5.0) -> None:
        if self.alive:
            with contextlib.suppress(OSError, ValueError):
                self.send("quit")
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _json_default(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return str(obj)
