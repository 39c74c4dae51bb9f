"""An always-on sensor: its plan (:class:`OnAir`: power-on, when the track goes out, how
long the machine stands after it), shared with the frame producer, and the standing machine
it sends before and after the track (a pose frozen in place, and a cycle of frames rendered
once and restamped)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from emulators.lidar import FrameResult


@dataclass
class OnAir:
    """An always-on sensor's plan, shared with the frame producer (a forked process): the
    sensor powers on at simulation time ``power_on_ns`` (whole frames before the track's
    start) and sends the machine standing at the track's start; once the run decides,
    from its frame ``step_at.value`` since power-on the clock has stepped onto the track's
    time line (the frames from there are recorded) and from frame ``track_at.value`` the
    track goes out (both -1 until decided; the track at the latest when the simulation
    reaches its start), then the machine stands where the track left it until the stream
    is stopped. Shared integers: ``multiprocessing.RawValue("q")`` made before the fork;
    ``step_at`` is set before ``track_at``."""

    power_on_ns: int
    track_at: Any
    step_at: Any
    # frames of the machine standing after the track at the most (-1: until stopped): a
    # run's sensor falls silent once the run could be over, so that a bench left hanging
    # does not go on sending to the ports the next run on the machine takes
    after_frames: int = -1
    # the track is over already (a sensor re-initialised after it): the machine stands
    # where the track left it from the first frame (frame_id from 0)
    track_over: bool = False


class StandingPose:
    """The track's sensor pose and IMU frozen at ``t_ns`` (a machine standing there)."""

    def __init__(self, track: Any, t_ns: int) -> None:
        self.track, self.t_ns = track, t_ns

    def sensor_pose(self, t_ns: Any) -> tuple[Any, Any]:
        return self.track.sensor_pose(np.full(len(np.atleast_1d(t_ns)), self.t_ns, np.int64))

    def imu(self, t_ns: Any) -> tuple[Any, Any]:
        n = len(np.atleast_1d(t_ns))
        acc, _ = self.track.imu(np.full(max(n, 1), self.t_ns, np.int64))
        return acc[:n], np.zeros((n, 3))  # standing: no rotation


class StandingEmulator:
    """Frames of a standing machine for any frame k of the simulation time line (``start_ns
    + k period``): one of a cycle of frames rendered once, its column times moved to frame
    k's (the packet headers and CRCs are the sensor's to finish, as the emulator's)."""

    def __init__(self, cycle: list[FrameResult], cycle_start_ns: int, start_ns: int,
                 period_ns: int, fmt: Any) -> None:
        self.cycle, self.cycle_start_ns = cycle, cycle_start_ns
        self.start_ns, self.period_ns, self.fmt = start_ns, period_ns, fmt
        self.from_store = False  # the cycle was read from the render store, not rendered

    def frame(self, k: int) -> FrameResult:
        t = self.start_ns + k * self.period_ns
        i = ((t - self.cycle_start_ns) // self.period_ns) % len(self.cycle)
        fr = self.cycle[i]
        # (added modulo 2^64: a move back in time wraps to the right, non-negative times)
        delta = np.uint64((t - (self.cycle_start_ns + i * self.period_ns)) % (1 << 64))
        arr = fr.packets.copy()
        self.fmt.column_timestamps(arr)[...] += delta
        return dataclasses.replace(fr, frame_index=k, timestamps_ns=fr.timestamps_ns + delta,
                                   packets=arr)
