"""When each event of a stream is due on the wall clock, and waiting for it: the one pacer of
the live lidar stream (:class:`emulators.lidar.PacedSender`) and of a recording sent again
(``tcf-hil replay``, ``run --replay``).

As python-can's player separates reading a log (``LogReader``), pacing it
(``MessageSync``) and sending (the bus), a stream here is read by its source, paced by a
:class:`Pacer` and sent by its socket or bus. The pacer sleeps until ``spin_ns`` before an
event's due time, then yields the rest (``time.sleep(0)``): the interval error stays at tens
of microseconds without a busy loop holding a core. Under SCHED_FIFO the sleep is needed as
well: a FIFO thread that never sleeps is throttled by the kernel for 50 ms of every second
(``/proc/sys/kernel/sched_rt_runtime_us``, 950,000 of 1,000,000 by default); spinning the
whole 781 us between packets, a bare pacer had about 60 wake-ups a second 1 ms or more late
and a p99 of 35-39 ms (2026-12-03), against a p99 of tens of microseconds with the sleep.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable
from typing import Protocol

__all__ = ["Pacer", "SimClockLike", "enter_fifo", "leave_fifo", "steal_s", "wake_floor"]


class SimClockLike(Protocol):
    """A shared simulation clock (:class:`emulators.harvester.SimClock`)."""

    speed: float

    def monotonic_at(self, t_sim_ns: int) -> int: ...


class Pacer:
    """Due times of simulation times ``t_ns`` (nanoseconds) and the waits for them.

    Args:
        speed: simulation seconds per wall second; 0: nothing waits (as fast as possible).
            The first event is due at once; the others keep their distance from it.
        clock: a simulation clock shared with the run's other emulators: events are due when
            it says (its speed wins over ``speed``).
        spin_ns: how long before a due time to stop sleeping and yield instead.
        idle_ns: with an ``idle`` task given to :meth:`wait`, how much time before a due
            time the task may still start (its own length: short work, tens of
            microseconds).
    """

    def __init__(self, speed: float = 1.0, *, clock: SimClockLike | None = None,
                 spin_ns: int = 300_000, idle_ns: int = 450_000) -> None:
        if speed < 0:
            raise ValueError(f"speed {speed}; expected >= 0")
        self.clock = clock
        self.speed = clock.speed if clock is not None else speed
        self.spin_ns = spin_ns
        self.idle_ns = idle_ns
        self._t0: tuple[int, int] | None = None  # (first simulation time, its wall time)
        self._mono_minus_perf = (time.monotonic_ns() - time.perf_counter_ns()
                                 if clock is not None else 0)

    def due(self, t_ns: int) -> int:
        """The wall time (``time.perf_counter_ns``) at which ``t_ns`` is due."""
        if self._t0 is None:
            self._t0 = (t_ns, time.perf_counter_ns())
        if self.speed == 0:
            return self._t0[1]
        if self.clock is not None:
            return self.clock.monotonic_at(t_ns) - self._mono_minus_perf
        return self._t0[1] + int((t_ns - self._t0[0]) / self.speed)

    def wait(self, t_ns: int, idle: Callable[[], bool] | None = None) -> int:
        """Wait until ``t_ns`` is due; how late it was (ns; negative: early, never here).
        ``idle``: housekeeping done while the wait is long enough (``idle_ns`` or more left):
        called until it returns False (nothing more to do now) or time runs short, so that
        it never runs just before a packet is due."""
        due = self.due(t_ns)
        if self.speed == 0:
            return 0
        now = time.perf_counter_ns()
        if idle is not None:
            while due - now > self.idle_ns and idle():
                now = time.perf_counter_ns()
        if due - now > self.spin_ns:
            time.sleep((due - now - self.spin_ns) / 1e9)
        while (now := time.perf_counter_ns()) < due:
            time.sleep(0)
        return now - due


def steal_s() -> float | None:
    """The CPU time the hypervisor withheld from this virtual machine so far, all CPUs
    together, seconds (the ``steal`` column of ``/proc/stat``: time a vCPU wanted to run
    and the host ran something else; see proc(5)); None where there is no such count.

    A vCPU the host does not run sends nothing, whatever its priority inside the guest: a
    difference of two readings over a stream says how much of its lateness the machine
    made."""
    try:
        with open("/proc/stat", "rb") as fh:
            fields = fh.readline().split()
    except OSError:
        return None
    if len(fields) < 9 or fields[0] != b"cpu":
        return None
    return int(fields[8]) / os.sysconf("SC_CLK_TCK")


def wake_floor(interval_ns: int, seconds: float, *, spin_ns: int = 200_000,
               realtime: bool = True) -> list[int]:
    """What the pacing alone gets from this machine now: a :class:`Pacer` waiting for an
    event every ``interval_ns`` for ``seconds``, sending nothing, under SCHED_FIFO where
    permitted (as the lidar sender); each wait's error in whole microseconds.

    The floor under any stream's pacing on this machine: a sender can be no more punctual
    than its own wake-ups (on a virtual machine, the host's scheduling shows here)."""
    old = enter_fifo() if realtime else None
    try:
        pacer = Pacer(1.0, spin_ns=spin_ns)
        n = max(1, int(seconds * 1e9 / interval_ns))
        pacer.due(0)  # the first event is due now; the others keep their distance
        return [abs(pacer.wait(k * interval_ns)) // 1000 for k in range(1, n + 1)]
    finally:
        leave_fifo(old)


def enter_fifo() -> tuple[int, int] | None:
    """This thread under SCHED_FIFO (priority 10 or the most allowed); its old policy and
    priority, or None where that is not permitted (nothing changed)."""
    if not hasattr(os, "SCHED_FIFO"):
        return None
    try:
        old = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(
            min(10, os.sched_get_priority_max(os.SCHED_FIFO))))
    except (OSError, AttributeError):
        return None
    return old


def leave_fifo(old: tuple[int, int] | None) -> None:
    """Back to the policy :func:`enter_fifo` returned (None: nothing to undo)."""
    if old is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, old[0], os.sched_param(old[1]))
