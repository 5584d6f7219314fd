"""The GUI's computation process: fits run there, at the lowest priority, started once and kept.

Why not a ``ProcessPoolExecutor``: its spawned worker imports the GUI's ``__main__`` and the
job function's module (Qt, pyqtgraph) before any initializer can lower its priority, and its
manager and feeder threads live in the GUI process; lowering those threads' priority (so the
worker spawned from them inherits it) puts the GUI's interpreter lock in the hands of
lowest-priority threads, and a GUI thread waiting for that lock waits as long as the scheduler
keeps them off the CPU (a priority inversion on the E-STOP's path).

Here no thread of the GUI process is ever lowered. The worker is a new interpreter whose first
statement sets its own nice value to :data:`WORKER_NICE`; only then does it import anything
(numpy, scipy, the models, :data:`PRELOAD`), and it does so when the GUI starts
(:meth:`ComputeWorker.start`), not when the operator presses Fit during a run. Jobs go down a
pipe one at a time (a module-level function and its arguments, pickled); the worker answers
``begin`` (the job is computing, with its ``time.monotonic()``, one clock for every process on
Linux) and ``done`` or ``failed`` (with the end time). A reader thread of the GUI process, at
the GUI's priority, resolves the :class:`concurrent.futures.Future` of each job. Nothing here
imports Qt.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import importlib
import logging
import os
import pickle
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO

log = logging.getLogger(__name__)

WORKER_NICE = 19
"""The worker's nice value (the lowest): a fit never takes the CPU from the bench or the GUI."""
PRELOAD = ("numpy", "scipy.optimize", "smabench.physics.identify", "smabench.sessions")
"""Imported by the worker as soon as it starts (at its low priority), before any job."""
_HEADER = struct.Struct("!Q")
# the worker's command: lower the priority first, import after
_BOOT = (
    "import os\n"
    f"os.setpriority(os.PRIO_PROCESS, 0, {WORKER_NICE})\n"
    "from smabench.gui.worker import worker_main\n"
    "worker_main()\n"
)


def _send(f: BinaryIO, message: Any) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    f.write(_HEADER.pack(len(data)) + data)
    f.flush()


def _receive(f: BinaryIO) -> Any:
    """One message, or None at the end of the stream."""
    head = f.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    n = _HEADER.unpack(head)[0]
    data = f.read(n)
    if len(data) < n:
        return None
    return pickle.loads(data)


def _picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def worker_main() -> None:
    """The worker process (started by :class:`ComputeWorker`; stdin: jobs, stdout: answers)."""
    jobs, answers = sys.stdin.buffer, os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    sys.stdout = sys.stderr  # a print in a job must not break the answers' framing
    for name in PRELOAD:
        with contextlib.suppress(ImportError):
            importlib.import_module(name)
    _send(answers, ("ready", os.getpid(), time.monotonic()))
    while (job := _receive(jobs)) is not None:
        job_id, module, name, args = job
        _send(answers, ("begin", job_id, time.monotonic()))
        try:
            result = getattr(importlib.import_module(module), name)(*args)
            answer = ("done", job_id, time.monotonic(), result)
        except Exception as exc:
            answer = ("failed", job_id, time.monotonic(), _picklable(exc))
        try:
            _send(answers, answer)
        except (pickle.PicklingError, TypeError, AttributeError) as exc:
            _send(answers, ("failed", job_id, time.monotonic(), RuntimeError(str(exc))))


@dataclass
class JobTimes:
    """When a job computed in the worker, ``time.monotonic()`` (``end_t`` None while it runs)."""

    job_id: int
    begin_t: float
    end_t: float | None = None


class ComputeWorker:
    """The worker process and its jobs, one at a time in submission order; thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._proc: subprocess.Popen | None = None
        # job id → (its future, the process it was sent to)
        self._futures: dict[int, tuple[concurrent.futures.Future, subprocess.Popen]] = {}
        self._next_id = 0
        self.ready = threading.Event()
        self.current: JobTimes | None = None  # the job computing now
        self.finished: list[JobTimes] = []  # the jobs that ended, newest last (at most 100)

    def start(self) -> None:
        """Start the worker now (it then imports :data:`PRELOAD` at its low priority); a job
        submitted later finds it ready. Does nothing when it is running."""
        with self._lock:
            self._start_locked()

    def _start_locked(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            return
        self.ready.clear()
        self.current = None
        # started from the calling (GUI) thread: only the child lowers its priority
        proc = subprocess.Popen([sys.executable, "-P", "-c", _BOOT], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, close_fds=True)  # fmt: skip
        self._proc = proc
        threading.Thread(target=self._read, args=(proc,), name="compute-reader",
                         daemon=True).start()  # fmt: skip

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def computing(self) -> bool:
        """A job is computing in the worker now (it said ``begin`` and has not answered)."""
        return self.current is not None

    def submit(self, fn: Callable[..., Any], args: tuple = ()) -> concurrent.futures.Future:
        """``fn(*args)`` in the worker: ``fn`` a module-level function, ``args`` picklable.
        The worker is (re)started when it is not running."""
        module, name = fn.__module__, fn.__qualname__
        if module == "__main__" or "." in name:
            raise ValueError(f"{fn!r} is not a module-level function the worker can import")
        fut: concurrent.futures.Future = concurrent.futures.Future()
        with self._lock:
            self._start_locked()
            job_id = self._next_id
            self._next_id += 1
            self._futures[job_id] = (fut, self._proc)
            try:
                _send(self._proc.stdin, (job_id, module, name, tuple(args)))
            except (OSError, ValueError) as exc:  # the worker died just now
                self._futures.pop(job_id, None)
                fut.set_exception(RuntimeError(f"the computation process is gone ({exc})"))
        return fut

    def _read(self, proc: subprocess.Popen) -> None:
        while (msg := _receive(proc.stdout)) is not None:
            kind = msg[0]
            if kind == "ready":
                self.ready.set()
            elif kind == "begin":
                self.current = JobTimes(msg[1], msg[2])
            else:
                job_id, end_t = msg[1], msg[2]
                times = self.current if self.current and self.current.job_id == job_id else \
                    JobTimes(job_id, end_t)  # fmt: skip
                times.end_t = end_t
                self.finished = [*self.finished[-99:], times]
                self.current = None
                with self._lock:
                    fut, _ = self._futures.pop(job_id, (None, None))
                if fut is not None:
                    fut.set_result(msg[3]) if kind == "done" else fut.set_exception(msg[3])
        code = proc.wait()
        with self._lock:  # the jobs sent to this process are lost
            lost = [job for job, (_, to) in self._futures.items() if to is proc]
            futures = [self._futures.pop(job)[0] for job in lost]
            if self._proc is proc:
                self.current = None
        for fut in futures:
            fut.set_exception(RuntimeError(f"the computation process stopped (exit {code})"))

    def close(self, timeout_s: float = 2.0) -> None:
        """End the worker (a job in progress is not waited for)."""
        with self._lock:
            proc, self._proc = self._proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            proc.stdin.close()
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        with self._lock:
            lost, self._futures = self._futures, {}
        for fut, _ in lost.values():
            if not fut.done():
                fut.set_exception(RuntimeError("the computation process was closed"))
