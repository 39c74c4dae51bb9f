"""One simulation clock for every emulator in a run: simulation nanoseconds tied to the
monotonic clock (system-wide on Linux, so processes that share ``origin_monotonic_ns`` share the
clock)."""

from __future__ import annotations

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
