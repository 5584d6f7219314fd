"""The memory a command may still use, and a refusal up front when its data needs more (issue 29:
an archive larger than the memory given to the analysis is streamed or refused with what it
needs, never killed by the kernel half-way).

Three limits apply to a process, the tightest wins: its address space (``RLIMIT_AS``,
``ulimit -v``, ``prlimit --as``: mapped memory, libraries included), its control group's memory
(cgroup v2 ``memory.max`` or v1 ``memory.limit_in_bytes``, less what the group already uses) and
the machine's available memory (``MemAvailable`` in ``/proc/meminfo``).
"""

from __future__ import annotations

import logging
import resource
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

CODE_ADDRESS_SPACE_BYTES = 512 * 2**20
"""Address space the interpreter and its libraries (numpy, scipy, numba/llvmlite) map before any
data: measured VmPeak 463 MB for ``smabench characterize`` of a 56 000-row session, 510 MB after
importing the analysis. Counted against ``RLIMIT_AS`` only (most of it is never resident)."""


@dataclass(frozen=True)
class Headroom:
    """Bytes still free for data (``bytes_free``) and the limit that sets it, in words."""

    bytes_free: int
    what: str


def gb(n_bytes: float) -> str:
    """``n_bytes`` as a short text in GB or MB."""
    return f"{n_bytes / 1e9:.1f} GB" if n_bytes >= 1e9 else f"{n_bytes / 1e6:.0f} MB"


def _proc_kb_bytes(path: str, key: str) -> int | None:
    """A ``key:  N kB`` line of a /proc file in bytes (None when absent or unreadable)."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _vm_size_bytes() -> int:
    return _proc_kb_bytes("/proc/self/status", "VmSize") or 0


def _cgroup_free() -> int | None:
    """The control group's memory limit less its usage (None: no limit, or not readable)."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, rel = line.split(":", 2)
        if controllers == "":  # v2
            base = Path("/sys/fs/cgroup") / rel.lstrip("/")
            limit_f, usage_f = base / "memory.max", base / "memory.current"
        elif "memory" in controllers.split(","):  # v1
            base = Path("/sys/fs/cgroup/memory") / rel.lstrip("/")
            limit_f, usage_f = base / "memory.limit_in_bytes", base / "memory.usage_in_bytes"
        else:
            continue
        try:
            limit_text = limit_f.read_text().strip()
            if limit_text == "max" or int(limit_text) >= 2**60:
                continue
            return max(0, int(limit_text) - int(usage_f.read_text().strip()))
        except (OSError, ValueError):
            continue
    return None


def _mem_available() -> int | None:
    return _proc_kb_bytes("/proc/meminfo", "MemAvailable")


def headroom(processes: int = 1) -> Headroom:
    """The memory free for data in each of ``processes`` worker processes: the address-space
    limit is per process; the control group's and the machine's memory are shared by them."""
    found: list[Headroom] = []
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        used = max(_vm_size_bytes(), CODE_ADDRESS_SPACE_BYTES)
        found.append(Headroom(max(0, soft - used), f"address-space limit {gb(soft)} (ulimit -v), "
                              f"{gb(used)} of it the program's own"))  # fmt: skip
    shared_by = f" for {processes} processes" if processes > 1 else ""
    for free, what in ((_cgroup_free(), "control group memory limit, {} free"),
                       (_mem_available(), "{} of memory available")):  # fmt: skip
        if free is not None:  # shared by the processes
            found.append(Headroom(free // processes, what.format(gb(free)) + shared_by))
    if not found:
        return Headroom(2**62, "no limit known")
    return min(found, key=lambda h: h.bytes_free)


class NotEnoughMemoryError(ValueError):
    """The data needs more memory than the process may use (a usage error: exit 2)."""


def require(need_bytes: float, what: str, processes: int = 1) -> None:
    """Raise :class:`NotEnoughMemoryError` (one line: what needs how much, what is free, the limit)
    when ``need_bytes`` (per process) exceeds the headroom."""
    room = headroom(processes)
    log.debug("memory: %s needs %s, %s free (%s)", what, gb(need_bytes), gb(room.bytes_free),
              room.what)  # fmt: skip
    if need_bytes > room.bytes_free:
        raise NotEnoughMemoryError(f"{what} needs about {gb(need_bytes)} of memory; "
                              f"{gb(room.bytes_free)} free ({room.what})")  # fmt: skip
