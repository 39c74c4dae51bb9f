"""The one pacer (:class:`emulators.pacing.Pacer`) of the live stream and of replay: due
times keep the simulation's distances scaled by the speed, a shared clock decides them when
there is one, speed 0 never waits, and a wait never ends before its due time."""

from __future__ import annotations

import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from emulators.harvester import SimClock
from emulators.pacing import Pacer


@given(st.lists(st.integers(0, 10**12), min_size=1, max_size=30),
       st.floats(0.01, 100.0))
def test_due_times_keep_the_distances_scaled_by_the_speed(ts: list[int], speed: float) -> None:
    ts = sorted(ts)
    p = Pacer(speed)
    first = p.due(ts[0])
    for t in ts[1:]:
        assert abs((p.due(t) - first) - (t - ts[0]) / speed) <= 1


def test_speed_zero_never_waits() -> None:
    p = Pacer(0)
    t0 = time.perf_counter_ns()
    for t in range(0, 10**12, 10**10):  # 100 events a simulated 10 s apart
        assert p.wait(t) == 0
    assert time.perf_counter_ns() - t0 < 1e9


def test_a_wait_never_ends_early() -> None:
    p = Pacer(1.0, spin_ns=100_000)
    p.wait(0)
    for k in range(1, 6):
        due = p.due(k * 2_000_000)
        late = p.wait(k * 2_000_000)
        assert late >= 0 and time.perf_counter_ns() >= due


def test_a_shared_clock_decides() -> None:
    clock = SimClock.start(5_000_000_000, 2.0)
    p = Pacer(1.0, clock=clock)
    assert p.speed == 2.0
    mono_minus_perf = time.monotonic_ns() - time.perf_counter_ns()
    assert abs(p.due(6_000_000_000) - (clock.monotonic_at(6_000_000_000) - mono_minus_perf)) \
        < 1_000_000


def test_a_negative_speed_is_refused() -> None:
    with pytest.raises(ValueError, match="speed"):
        Pacer(-1.0)


def test_idle_work_runs_only_while_a_wait_is_long_enough() -> None:
    """Housekeeping between packets never starts with less than ``idle_ns`` to go, and a
    wait with it still ends on time."""
    p = Pacer(1.0, spin_ns=200_000, idle_ns=2_000_000)
    left: list[int] = []
    t0 = 1_000_000_000
    p.due(t0)

    def idle() -> bool:
        left.append(p.due(t0 + 10_000_000) - time.perf_counter_ns())
        time.sleep(0.001)
        return True

    late = p.wait(t0 + 10_000_000, idle)
    assert left and min(left) > 2_000_000
    assert 3 <= len(left) <= 9
    assert late >= 0
    assert p.wait(t0 + 10_000_001, lambda: pytest.fail("no time to spare: not called")) >= 0
