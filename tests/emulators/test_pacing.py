"""The one pacer (:class:`emulators.pacing.Pacer`) of the live stream and of replay: due
times keep the simulation's distances scaled by the speed, a shared clock decides them when
there is one, speed 0 never waits, and a wait never ends before its due time."""

from __future__ import annotations

import os
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from emulators.harvester import SimClock
from emulators.lidar import SendStats
from emulators.pacing import Pacer, steal_s, wake_floor


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


def test_the_hypervisors_steal_is_read_and_never_goes_back() -> None:
    a = steal_s()
    if a is None:  # not Linux, or a /proc without the column
        pytest.skip("no steal count on this machine")
    time.sleep(0.05)
    b = steal_s()
    assert b is not None and 0.0 <= a <= b


def test_a_window_of_the_stream_reports_the_steal_over_it() -> None:
    s = SendStats()
    s.open_window()
    s.add_late(5_000)
    time.sleep(0.05)
    w = s.close_window()
    assert w is not None and w.late_n == 1 and w.late_over_us(5) == 1
    if steal_s() is None:
        assert w.steal_ms_per_s is None
    else:  # both CPUs together: never more than a second a second per CPU
        assert w.steal_ms_per_s is not None
        assert 0.0 <= w.steal_ms_per_s <= 1000.0 * (os.cpu_count() or 1)
    assert s.close_window() is None  # closed: nothing more counted in it


def test_a_window_made_ready_ahead_counts_only_from_its_opening() -> None:
    s = SendStats()
    s.ready_window()  # (ahead: a window opens between two packets 49 us apart)
    s.add_late(7_000)  # before the window opens: not in it
    assert s.window_hist is None
    s.open_window()
    s.add_late(3_000)
    w = s.close_window()
    assert w is not None and w.late_n == 1 and w.late_over_us(3) == 1
    assert w.late_over_us(7) == 0 and s.late_n == 2


def test_a_window_ended_between_packets_is_reported_later() -> None:
    s = SendStats()
    s.open_window()
    s.add_late(2_000)
    s.end_window()  # (between two packets: nothing but a swap)
    s.add_late(9_000)  # after the window: not in it
    w = s.close_window()
    assert w is not None and w.late_n == 1 and w.late_over_us(2) == 1
    assert w.late_over_us(9) == 0 and s.close_window() is None


def test_the_bare_pacers_floor_is_one_error_per_wake_up() -> None:
    t0 = time.perf_counter()
    errs = wake_floor(2_000_000, 0.1, realtime=False)  # every 2 ms for 0.1 s
    assert len(errs) == 50 and all(e >= 0 for e in errs)
    assert time.perf_counter() - t0 >= 0.1  # it waited for each: never early


def test_late_frames_are_counted_and_the_first_ones_described() -> None:
    from emulators.lidar._stream import LATE_FRAMES_KEPT

    s = SendStats()
    for k in range(LATE_FRAMES_KEPT + 5):
        s.add_late_frame(k * 100_000_000, 2_500_000 + k, "track" if k else "before")
    assert s.late_frames == LATE_FRAMES_KEPT + 5
    assert len(s.late_frame_log) == LATE_FRAMES_KEPT
    assert s.late_frame_log[0] == (0, 2500, "before") and s.late_frame_log[1][2] == "track"
