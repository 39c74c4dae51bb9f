"""One simulation clock for every emulator in a run: simulation nanoseconds tied to the
monotonic clock (system-wide on Linux, so processes that share ``origin_monotonic_ns`` share the
clock)."""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class SimClock:
    """``now_ns() = t0_ns + (monotonic_ns() - origin_monotonic_ns) * speed``."""

    t0_ns: int
    origin_monotonic_ns: int
    speed: float = 1.0

    @classmethod
    def start(cls, t0_ns: int, speed: float = 1.0, *, lead_ns: int = 0) -> SimClock:
        """A clock that reads ``t0_ns`` ``lead_ns`` from now."""
        if not speed > 0:
            raise ValueError(f"clock speed: expected > 0, got {speed}")
        return cls(t0_ns, time.monotonic_ns() + lead_ns, speed)

    def now_ns(self) -> int:
        return self.t0_ns + round((time.monotonic_ns() - self.origin_monotonic_ns) * self.speed)

    def monotonic_at(self, t_sim_ns: int) -> int:
        """The monotonic time at which the simulation reaches ``t_sim_ns``."""
        return self.origin_monotonic_ns + round((t_sim_ns - self.t0_ns) / self.speed)

    def sleep_until(self, t_sim_ns: int) -> None:
        d = self.monotonic_at(t_sim_ns) - time.monotonic_ns()
        if d > 0:
            time.sleep(d / 1e9)

    @property
    def segments(self) -> tuple[tuple[int, int], ...]:
        """The clock as :class:`RunClock`'s segments (one: it never steps)."""
        return ((self.t0_ns, self.origin_monotonic_ns),)


class RunClock:
    """A run's simulation clock that may step forward: sim time runs at ``speed`` from
    ``t0_ns`` at ``origin_monotonic_ns`` until a :meth:`step`, which makes the simulation
    jump forward (never back) at a chosen monotonic time. An always-on sensor stands at the
    track's start from power-on; once its program is ready the clock steps to the track's
    start, so the track keeps its own time line (and its bytes) however long the wait.

    ``now_ns``/``monotonic_at``/``sleep_until`` as :class:`SimClock`'s, each by the segment
    that holds the time asked about; ``t0_ns`` and ``origin_monotonic_ns`` stay the first
    segment's (the reference a CAN TIME object counts from)."""

    def __init__(self, t0_ns: int, origin_monotonic_ns: int, speed: float = 1.0) -> None:
        if not speed > 0:
            raise ValueError(f"clock speed: expected > 0, got {speed}")
        self.t0_ns, self.origin_monotonic_ns, self.speed = t0_ns, origin_monotonic_ns, speed
        # (sim start, monotonic start) of each segment, in order; swapped whole (atomic)
        self._segments: tuple[tuple[int, int], ...] = ((t0_ns, origin_monotonic_ns),)

    @classmethod
    def start(cls, t0_ns: int, speed: float = 1.0, *, lead_ns: int = 0) -> RunClock:
        """A clock that reads ``t0_ns`` ``lead_ns`` from now."""
        return cls(t0_ns, time.monotonic_ns() + lead_ns, speed)

    @property
    def segments(self) -> tuple[tuple[int, int], ...]:
        """(sim start, monotonic start) of each segment, in order (a snapshot: another
        process rebuilds the clock from it with :meth:`from_segments`)."""
        return self._segments

    @classmethod
    def from_segments(cls, segments: tuple[tuple[int, int], ...], speed: float) -> RunClock:
        """The clock that :attr:`segments` and ``speed`` describe."""
        clock = cls(segments[0][0], segments[0][1], speed)
        clock._segments = tuple((int(s), int(m)) for s, m in segments)
        return clock

    @property
    def steps(self) -> list[tuple[int, int]]:
        """Each step as (the sim time the clock would have read, the sim time it jumped to)."""
        out = []
        segs = self._segments
        for (s0, m0), (s1, m1) in itertools.pairwise(segs):
            out.append((s0 + round((m1 - m0) * self.speed), s1))
        return out

    def step(self, at_monotonic_ns: int, to_sim_ns: int) -> None:
        """From ``at_monotonic_ns`` (later than the last step) the clock reads
        ``to_sim_ns`` (no earlier than it would have read then)."""
        segs = self._segments
        s0, m0 = segs[-1]
        if at_monotonic_ns <= m0:
            raise ValueError("a step must come after the last one")
        if to_sim_ns < s0 + round((at_monotonic_ns - m0) * self.speed):
            raise ValueError("the clock steps forward only")
        self._segments = (*segs, (to_sim_ns, at_monotonic_ns))

    def now_ns(self) -> int:
        now = time.monotonic_ns()
        s, m = next((seg for seg in reversed(self._segments) if seg[1] <= now),
                    self._segments[0])
        return s + round((now - m) * self.speed)

    def monotonic_at(self, t_sim_ns: int) -> int:
        """The monotonic time at which the simulation reaches ``t_sim_ns`` (a time a step
        jumped over: when it would have, had the clock not stepped)."""
        s, m = next((seg for seg in reversed(self._segments) if seg[0] <= t_sim_ns),
                    self._segments[0])
        return m + round((t_sim_ns - s) / self.speed)

    def sleep_until(self, t_sim_ns: int) -> None:
        d = self.monotonic_at(t_sim_ns) - time.monotonic_ns()
        if d > 0:
            time.sleep(d / 1e9)
