"""One task per session, on local worker processes or on a Dask cluster (``--scheduler``).

Used by ``smabench characterize`` and ``smabench analyze --each`` over archives of sessions.
A task is a plain module-level function of picklable arguments, so a Dask worker on another
machine runs exactly what a local process runs (it needs the same smabench installed and the
session paths readable); the results come back in the order of the arguments, so the output is
the same either way.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from smabench.argtypes import positive

log = logging.getLogger(__name__)


SCHEDULER_TIMEOUT_S = 10.0
"""How long to keep trying to reach a Dask scheduler before giving up, s
(``--scheduler-timeout-s``): the Dask client's connect timeout, during which it retries a
refused or silent address. A scheduler across a slow network may need more."""


def add_scheduler_timeout(parser: argparse.ArgumentParser) -> None:
    """``--scheduler-timeout-s`` (> 0 s, default :data:`SCHEDULER_TIMEOUT_S`) on a command that
    takes ``--scheduler``."""
    parser.add_argument(
        "--scheduler-timeout-s",
        type=positive(),
        default=SCHEDULER_TIMEOUT_S,
        metavar="S",
        help=f"with --scheduler: give up reaching the scheduler after S seconds "
        f"(default {SCHEDULER_TIMEOUT_S:g})",
    )


class SchedulerError(ValueError):
    """The Dask scheduler cannot be used (message says why; the CLI exits 2)."""


def local_workers(n_tasks: int, workers: int | None = None) -> int:
    """Processes to use: ``workers`` or one per CPU this process may run on, at most one per
    task."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(n_tasks, workers or cpus or 1))


def run_tasks(
    func: Callable[..., Any],
    args: Sequence[tuple],
    scheduler: str | None = None,
    workers: int | None = None,
    scheduler_timeout_s: float = SCHEDULER_TIMEOUT_S,
) -> list[Any]:
    """``[func(*a) for a in args]``, one task per item: on the Dask cluster at ``scheduler``
    (``tcp://host:port``) when given, else on local worker processes (in this process when
    there is one task or ``workers == 1``). Results in the order of ``args``; the first task
    error (in that order) is raised here; a scheduler not reached within
    ``scheduler_timeout_s`` raises :class:`SchedulerError`."""
    if not scheduler_timeout_s > 0:
        raise SchedulerError(f"scheduler timeout must be > 0 s, not {scheduler_timeout_s:g}")
    if scheduler:
        try:
            from distributed import Client
        except ImportError as exc:  # pragma: no cover - a declared dependency
            raise SchedulerError(
                f"--scheduler needs dask[distributed] ({exc}); pip install 'dask[distributed]'"
            ) from None
        try:
            client = Client(scheduler, timeout=f"{scheduler_timeout_s:g}s", set_as_default=False)
        except OSError as exc:
            raise SchedulerError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
        with client:
            futures = [client.submit(func, *a, pure=False) for a in args]
            return client.gather(futures)
    n = local_workers(len(args), workers)
    if n == 1:
        return [func(*a) for a in args]
    with ProcessPoolExecutor(max_workers=n) as pool:
        futures = [pool.submit(func, *a) for a in args]
        return [f.result() for f in futures]
