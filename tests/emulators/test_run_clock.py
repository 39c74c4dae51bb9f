"""The run's clock that steps forward once (an always-on sensor's wait before the track):
before and after the step it is a plain simulation clock, a time the step jumped over is
never a time to wait for, and it never steps back."""

from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.harvester import RunClock, SimClock


@settings(max_examples=200, deadline=None)
@given(t0=st.integers(0, 10**12), speed=st.floats(0.1, 20.0), at=st.integers(1, 10**10),
       jump=st.integers(0, 10**11), probe=st.integers(-10**11, 10**12))
def test_each_segment_is_a_plain_clock(t0: int, speed: float, at: int, jump: int,
                                       probe: int) -> None:
    c = RunClock(t0, 0, speed)
    plain = SimClock(t0, 0, speed)
    before = t0 + round(at * speed)  # what the clock reads at monotonic ``at``
    c.step(at, before + jump)
    assert c.steps == [(before, before + jump)]
    t = t0 + probe
    if t < before:  # the first segment: as the clock that never stepped
        assert c.monotonic_at(t) == plain.monotonic_at(t)
    elif t >= before + jump:  # the second: ``at`` reads before + jump
        assert c.monotonic_at(t) == at + round((t - before - jump) / speed)
        assert c.monotonic_at(t) >= at - 1


def test_now_follows_the_step() -> None:
    c = RunClock.start(5_000_000_000, 1.0)
    now = time.monotonic_ns()
    c.step(now + 50_000_000, 60_000_000_000)  # 50 ms from now the clock reads 60 s
    assert 4_900_000_000 < c.now_ns() < 5_100_000_000
    time.sleep(0.08)
    assert 60_000_000_000 < c.now_ns() < 60_500_000_000
    assert c.t0_ns == 5_000_000_000  # the reference stays the first segment's


def test_it_never_steps_back_nor_out_of_order() -> None:
    c = RunClock(0, 0, 1.0)
    with pytest.raises(ValueError, match="forward"):
        c.step(1_000, 500)  # it would read 1000 then
    c.step(1_000, 5_000)
    with pytest.raises(ValueError, match="after the last"):
        c.step(1_000, 9_000)
    with pytest.raises(ValueError, match="speed"):
        RunClock(0, 0, 0.0)


@settings(max_examples=100, deadline=None)
@given(t0=st.integers(0, 10**12), speed=st.floats(0.1, 20.0),
       steps=st.lists(st.tuples(st.integers(1, 10**9), st.integers(0, 10**10)), max_size=4),
       probe=st.integers(-10**11, 10**13))
def test_a_clock_rebuilt_from_its_segments_is_the_same_clock(
        t0: int, speed: float, steps: list[tuple[int, int]], probe: int) -> None:
    """The lidar sender (a process of its own) rebuilds the run's clock from its segments."""
    c = RunClock(t0, 1000, speed)
    at = 1000
    for gap, jump in steps:
        at += gap
        c.step(at, c.segments[-1][0] + round((at - c.segments[-1][1]) * speed) + jump)
    copy = RunClock.from_segments(c.segments, speed)
    assert copy.segments == c.segments
    assert copy.monotonic_at(t0 + probe) == c.monotonic_at(t0 + probe)
    plain = SimClock(t0, 1000, speed)
    assert RunClock.from_segments(plain.segments, speed).monotonic_at(t0 + probe) == \
        plain.monotonic_at(t0 + probe)
