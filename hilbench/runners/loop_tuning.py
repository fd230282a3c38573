"""What the operating system can do for the fixed-rate loop's thread, asked for and undone per run.

Set in the rig config's ``[rig]`` table (a property of the bench PC, so every command that runs the
rig gets it):

* ``lock_memory`` (default true): ``mlockall(MCL_CURRENT | MCL_ONFAULT)``: the pages the process
  has are kept in RAM, so the loop never waits for one to come back from swap. ``MCL_ONFAULT``
  locks pages as they are touched instead of faulting in every mapped page at once (a Python
  process with numba maps gigabytes it never touches).
* ``loop_priority`` (default 0: the normal scheduler): 1-99 runs the loop's thread under
  ``SCHED_FIFO`` at that priority, ahead of every ordinary process. The loop spins before each
  deadline, so give it a core of its own (``loop_cpu``) on a machine with few cores.
* ``loop_cpu`` (default -1: any): the core the loop's thread runs on (``sched_setaffinity``); the
  watchdog thread and the recording's writer process stay free to run elsewhere.

Always, on Linux: the loop thread's timer slack is set to 1 ns (``prctl(PR_SET_TIMERSLACK)``; the
default 50 us is added to every sleep of an ordinary thread), so that its sleeps end when asked.

Under SCHED_FIFO the loop must still sleep a little every period: the kernel throttles real-time
threads that use more than 95 % of a second (``sched_rt_runtime_us``), a stall of 50 ms every
second for a thread that spins through every period. :func:`spin_for` keeps the spin before each
deadline under three quarters of a period there (the rest of the period, less the
per-sample work, is slept).

Each is tried, and what happened goes into the run's ``loop_tuning`` attribute and the command's
output: permission is often missing (real-time priority and memory locking need root, the
``CAP_SYS_NICE``/``CAP_IPC_LOCK`` capabilities or ``ulimit -r``/``-l``), and that is said, not
fatal. Everything is undone after the run. Linux only; elsewhere each says it is not available.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
from collections.abc import Callable
from dataclasses import dataclass, field

_MCL_CURRENT, _MCL_ONFAULT = 1, 4
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30


@dataclass
class LoopTuning:
    lock_memory: bool = True
    priority: int = 0
    cpu: int = -1
    #: what was done or refused, one phrase each (filled by :func:`apply_tuning`)
    notes: list[str] = field(default_factory=list)
    #: the loop's thread runs under SCHED_FIFO (set by :func:`apply_tuning`)
    realtime: bool = False

    def summary(self) -> str:
        return "; ".join(self.notes) if self.notes else "none asked"


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name, use_errno=True)
    except OSError:
        return None


def _why(err: int) -> str:
    if err in (errno.EPERM, errno.EACCES):
        return "not permitted (root, or the capability / ulimit for it)"
    if err in (errno.ENOMEM, errno.EAGAIN):
        return "over the locked-memory limit (ulimit -l)"
    return os.strerror(err)


def apply_tuning(tuning: LoopTuning) -> Callable[[], None]:
    """Apply ``tuning`` to the calling thread (and the process's memory); returns the undo."""
    undo: list[Callable[[], None]] = []
    notes = tuning.notes
    notes.clear()
    tuning.realtime = False
    libc = _libc()
    if libc is not None and hasattr(libc, "prctl"):
        slack = libc.prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0)
        if slack >= 0 and libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0:
            undo.append(lambda: libc.prctl(_PR_SET_TIMERSLACK, slack, 0, 0, 0))
    if tuning.lock_memory:
        if libc is None or not hasattr(libc, "mlockall"):
            notes.append("memory not locked: mlockall not available here")
        elif libc.mlockall(_MCL_CURRENT | _MCL_ONFAULT) != 0:
            notes.append(f"memory not locked: {_why(ctypes.get_errno())}")
        else:
            notes.append("memory locked")
            undo.append(lambda: libc.munlockall())
    if tuning.cpu >= 0:
        if not hasattr(os, "sched_setaffinity"):
            notes.append(f"not pinned to CPU {tuning.cpu}: affinity not available here")
        else:
            before = os.sched_getaffinity(0)
            try:
                os.sched_setaffinity(0, {tuning.cpu})  # 0: the calling thread on Linux
                notes.append(f"loop thread pinned to CPU {tuning.cpu}")
                undo.append(lambda: os.sched_setaffinity(0, before))
            except OSError as exc:
                notes.append(f"not pinned to CPU {tuning.cpu}: {_why(exc.errno or 0)} "
                             f"(this machine has CPUs {sorted(before)})")
    if tuning.priority > 0:
        if not hasattr(os, "sched_setscheduler"):
            notes.append("real-time priority not available here")
        else:
            policy = os.sched_getscheduler(0)
            param = os.sched_getparam(0)
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(tuning.priority))
                notes.append(f"loop thread at SCHED_FIFO priority {tuning.priority}")
                tuning.realtime = True
                undo.append(lambda: os.sched_setscheduler(0, policy, param))
            except OSError as exc:
                notes.append(f"real-time priority {tuning.priority} refused: {_why(exc.errno or 0)}")

    def restore() -> None:
        for step in reversed(undo):
            try:
                step()
            except OSError:
                pass

    return restore


def spin_for(period_s: float, spin_s: float, realtime: bool) -> float:
    """The spin before each deadline: ``spin_s``, and under SCHED_FIFO at most 3/4 of a period (see the
    module docstring)."""
    return min(spin_s, 0.75 * period_s) if realtime else spin_s
