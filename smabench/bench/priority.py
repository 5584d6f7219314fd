"""Scheduling priority for the bench's processes: the control loop and the devices it stands in
for (the mock bench is a microcontroller and a sensor that no host load slows down) win the CPU
over drawing and other work where the system allows it (CAP_SYS_NICE: root); without it they
run at normal priority and this says so in the log.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

log = logging.getLogger(__name__)


LOOP_NICE = -10


AUTOGROUP = "/proc/self/autogroup"
"""The session's autogroup (sched(7), "The autogroup feature"): left as it is, see
:func:`raise_priority`."""


def raise_priority(nice: int = LOOP_NICE) -> bool:
    """Lower this process's nice value (children inherit it): the bench loop, and the mock
    bench standing in for devices, win the CPU over drawing and other processes of the session.

    The session's autogroup nice (:data:`AUTOGROUP`) is NOT lowered: that would lift every
    process of the session (a CPU-bound job started from the same terminal, the GUI's nice-19
    computation worker) above the kernel's workers (nice 0, in no autogroup), and a kernel
    worker carries every byte a serial port or pty receives; a thread reading the port waits
    for it in poll()/read(). Beside two CPU-bound processes in a session at autogroup nice
    -10, the pty's worker waited 0.34 s for a CPU while the link's SCHED_FIFO owner thread
    waited in poll() for it (ftrace): no keepalive went out and the device's 0.25 s host
    timeout turned the output off. What must not wait for other work runs SCHED_FIFO instead
    (:func:`realtime_loop_thread`, the link's owner thread, the stand-in devices), which no
    process of any session delays."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except OSError as exc:
        log.info("bench process stays at normal priority (%s)", exc)
        return False
    return True


LOOP_RT_PRIORITY = 20
LINK_RT_PRIORITY = LOOP_RT_PRIORITY
"""SCHED_FIFO priority of the current driver link's owner thread (its keepalive feeds the
device's host timeout, 0.25 s; the loop reads the telemetry it receives): as the loop's."""


def realtime_loop_thread(priority: int = LOOP_RT_PRIORITY) -> bool:
    """Real-time (SCHED_FIFO) scheduling for the calling thread, the control loop: it then
    preempts drawing at once on every tick instead of within the scheduler's wakeup granularity.
    The loop sleeps between ticks, and the kernel's RT throttling bounds it anyway. Needs
    CAP_SYS_NICE; without it the thread stays as it was."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return True
    except (OSError, AttributeError) as exc:
        log.info("control loop stays at normal scheduling (%s)", exc)
        return False


@contextmanager
def realtime_thread(priority: int = LOOP_RT_PRIORITY) -> Iterator[bool]:
    """:func:`realtime_loop_thread` for the calling thread while the block runs (yields whether
    it was raised), then its scheduling as it was: for a process that runs a session and then
    goes on computing (``bench control`` identifies the next case's model between sessions,
    which must not preempt its own mock)."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    raised = realtime_loop_thread(priority)
    try:
        yield raised
    finally:
        if raised:
            os.sched_setscheduler(0, policy, param)


def realtime_process(priority: int = LOOP_RT_PRIORITY // 2) -> int:
    """SCHED_FIFO for every thread of this process (threads started later inherit it): the
    loop shares the interpreter lock with the driver, status and stream threads, and one of
    them preempted by the GUI while holding the lock would hold up the loop (priority
    inversion). Returns how many threads were raised."""
    raised = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
            raised += 1
        except (OSError, AttributeError, ValueError) as exc:
            log.info("thread %s stays at normal scheduling (%s)", tid, exc)
    return raised


@contextmanager
def normal_thread() -> Iterator[bool]:
    """The calling thread at normal scheduling (SCHED_OTHER) while the block runs, then as it
    was; yields whether it was lowered. For CPU-bound work in a real-time process
    (:func:`realtime_process`): the GUI's runtime builds a controller's model (seconds of CPU)
    on its command thread, and a SCHED_FIFO thread computing that long starves the kernel's
    pty worker on its core (see :func:`raise_priority`): the driver's bytes stop arriving and
    the link is lost (seen: "device lost" at a PID session's start on a 2-core CI)."""
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    lowered = False
    if policy != os.SCHED_OTHER:
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            lowered = True
        except (OSError, AttributeError) as exc:
            log.info("thread stays at its scheduling (%s)", exc)
    try:
        yield lowered
    finally:
        if lowered:
            os.sched_setscheduler(0, policy, param)
