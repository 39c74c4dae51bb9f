"""Paced UDP sending of lidar and IMU packets from the sensor's own address.

Real-time pacing (:class:`emulators.pacing.Pacer`, shared with replay) sleeps until shortly
before each packet's due time and then waits out the rest with short yields (``spin_us``), so
the interval error stays at tens of microseconds without burning a whole core. Where the
process may (root, or CAP_SYS_NICE / an RLIMIT_RTPRIO above 0), the sending thread runs under
SCHED_FIFO while it paces: a frame factory on the other core or any other process then cannot
delay a packet by a scheduler time slice (milliseconds); without it the p99 error is a few
hundred microseconds. A destination that refuses packets (ICMP port unreachable) does not stop
the stream: the error is counted and sending goes on.
"""

from __future__ import annotations

import errno
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from emulators.pacing import Pacer, SimClockLike, enter_fifo, leave_fifo, steal_s

__all__ = ["Datagram", "PacedSender", "Route", "SendStats"]


@dataclass(frozen=True, slots=True)
class Datagram:
    """One UDP payload due at simulation time ``t_ns`` to ``port`` on the destination."""

    t_ns: int
    port: int
    payload: bytes | memoryview


LATE_FRAMES_KEPT = 50  # late frames described one by one (the manifest's lidar section)
_HIST_US = 100_000  # pacing errors are kept as a 1 us histogram up to 100 ms (bounded memory)


@dataclass
class SendStats:
    sent: int = 0
    refused: int = 0
    errors: int = 0
    realtime: bool = False  # SCHED_FIFO was in effect
    cpu_s: float = 0.0  # CPU time of the sending thread while it sent
    wall_s: float = 0.0
    #: |actual - scheduled| send time: counts per whole microsecond (the last bin: beyond)
    late_hist: list[int] = field(default_factory=lambda: [0] * (_HIST_US + 1), repr=False)
    late_n: int = 0
    #: frames the sender got 1 ms or more after their first packet was due (the frame
    #: source, not the pacing, made those packets late)
    late_frames: int = 0
    #: the first of those (at most :data:`LATE_FRAMES_KEPT`): the frame's first packet's
    #: simulation time (ns), how late it was when the frame came (us), and the stream's phase
    late_frame_log: list[tuple[int, int, str]] = field(default_factory=list, repr=False)

    def add_late_frame(self, t_ns: int, late_ns: int, phase: str) -> None:
        """A frame that came ``late_ns`` after its first packet was due."""
        self.late_frames += 1
        if len(self.late_frame_log) < LATE_FRAMES_KEPT:
            self.late_frame_log.append((t_ns, late_ns // 1000, phase))

    #: while not None, a second histogram as ``late_hist`` (a window of the stream, such as
    #: an always-on sensor's track: :meth:`open_window`)
    window_hist: list[int] | None = field(default=None, repr=False)
    #: the hypervisor's steal over the window (ms per wall second, all CPUs together;
    #: :func:`emulators.pacing.steal_s`; None: not known), set by :meth:`close_window`
    steal_ms_per_s: float | None = None
    _window_t0: tuple[float | None, float] | None = field(default=None, repr=False)
    _window_ready: tuple[list[int], tuple[float | None, float]] | None = field(
        default=None, repr=False)
    _window_ended: list[int] | None = field(default=None, repr=False)

    def add_late(self, ns: int) -> None:
        b = min(abs(ns) // 1000, _HIST_US)
        self.late_hist[b] += 1
        self.late_n += 1
        if self.window_hist is not None:
            self.window_hist[b] += 1

    def ready_window(self) -> None:
        """What :meth:`open_window` needs, made ahead: a window opens between two packets,
        and the two frames' packets it falls between are 49 us apart at 2048x10, less than
        a histogram of 100,001 counts and a reading of ``/proc/stat`` take."""
        if self.window_hist is None and self._window_ready is None:
            self._window_ready = ([0] * (_HIST_US + 1), (steal_s(), time.monotonic()))

    def open_window(self) -> None:
        """Count the packets from here in :attr:`window_hist` too."""
        if self.window_hist is None:
            self.ready_window()
            assert self._window_ready is not None
            (self.window_hist, self._window_t0), self._window_ready = self._window_ready, None

    def end_window(self) -> None:
        """No more packets counted in the window, at once (between two packets);
        :meth:`close_window` reports it later (a sum of 100,001 counts and a reading of
        ``/proc/stat``)."""
        if self.window_hist is not None:
            self._window_ended, self.window_hist = self.window_hist, None

    def close_window(self) -> SendStats | None:
        """The window's packets (its own :class:`SendStats`, with the hypervisor's steal
        over it, until now; None if none was opened); no more are counted in it."""
        hist, self.window_hist = self.window_hist, None
        if hist is None:
            hist, self._window_ended = self._window_ended, None
        self._window_ready = None
        if hist is None:
            return None
        out = SendStats(late_hist=hist, late_n=sum(hist))
        t0, self._window_t0 = self._window_t0, None
        steal, wall = steal_s(), time.monotonic()
        if t0 is not None and t0[0] is not None and steal is not None and wall > t0[1]:
            out.steal_ms_per_s = 1000.0 * (steal - t0[0]) / (wall - t0[1])
        return out

    def pacing_us(self, since: list[int] | None = None) -> tuple[float, float]:
        """p50 and p99 of |actual - scheduled| send time, microseconds (1 us resolution:
        each is the upper edge of its bin); ``since``: of the packets sent after that
        :meth:`snapshot` only."""
        hist = self._hist(since)
        n = int(hist.sum())
        if not n:
            return 0.0, 0.0
        cum = np.cumsum(hist)
        p50, p99 = np.searchsorted(cum, [0.5 * n, 0.99 * n])
        return float(p50 + 1), float(p99 + 1)

    def late_over_us(self, us: int, since: list[int] | None = None) -> int:
        """Packets sent ``us`` microseconds or more from their due time (after the
        :meth:`snapshot` ``since``)."""
        return int(self._hist(since)[us:].sum())

    def snapshot(self) -> list[int]:
        """The histogram as it is now (for :meth:`pacing_us` of what follows)."""
        return list(self.late_hist)

    def _hist(self, since: list[int] | None) -> NDArray[np.int64]:
        h = np.asarray(self.late_hist, dtype=np.int64)
        return h - np.asarray(since, dtype=np.int64) if since is not None else h


class Route:
    """Where a sensor's datagrams go now: its ``udp_dest`` and the ports its configuration
    names. Datagrams carry the ports the stream was made with; a client's set_config (the
    sensor's HTTP API) moves them while the stream runs with :meth:`set`."""

    def __init__(self, dest_ip: str, lidar_port: int, imu_port: int) -> None:
        self.made = (lidar_port, imu_port)
        self._now: tuple[str, dict[int, int]] = (dest_ip, {})
        self.changes = 0
        # told of each set (a sender in another process keeps its own copy up to date)
        self.listeners: list[Callable[[str, int, int], None]] = []

    def set(self, dest_ip: str, lidar_port: int, imu_port: int) -> None:
        ports = {self.made[0]: lidar_port, self.made[1]: imu_port}
        self._now = (dest_ip, {k: v for k, v in ports.items() if k != v})  # one atomic swap
        self.changes += 1
        for fn in list(self.listeners):
            fn(dest_ip, lidar_port, imu_port)

    @property
    def dest_ip(self) -> str:
        return self._now[0]

    def port(self, made: int) -> int:
        """Where a datagram made for port ``made`` goes now."""
        return self._now[1].get(made, made)

    def address(self, made: int) -> tuple[str, int]:
        dest, ports = self._now
        return dest, ports.get(made, made)


class PacedSender:
    """Sends datagrams from ``sensor_ip`` (an ephemeral port) to ``dest_ip``.

    Args:
        sensor_ip: source address; ouster-sdk accepts a live packet only if it comes from the
            address the sensor's host name resolves to.
        dest_ip: where the packets go.
        speed: simulation seconds per wall second; 0 sends as fast as possible.
        spin_us: how long before a due time to stop sleeping and yield instead (default 200
            under SCHED_FIFO, whose wake-ups are punctual, else 300).
        realtime: try SCHED_FIFO for the sending thread while it paces (speed > 0 only).
        route: where datagrams go now (a client may move the stream while it runs); default:
            ``dest_ip`` and each datagram's own port.
        hold_realtime: keep SCHED_FIFO between :meth:`send` calls until :meth:`close` (a
            process that does nothing but send: leaving SCHED_FIFO after each frame lets the
            scheduler hand the core to another task for a time slice right then, and the
            next frame's first packets go out late).
    """

    def __init__(self, sensor_ip: str = "127.0.0.1", dest_ip: str = "127.0.0.1", *,
                 speed: float = 1.0, spin_us: int | None = None, realtime: bool = True,
                 clock: SimClockLike | None = None, route: Route | None = None,
                 hold_realtime: bool = False) -> None:
        if speed < 0:
            raise ValueError(f"speed {speed}; expected >= 0")
        self.dest_ip = dest_ip
        self.route = route
        self.speed = speed
        self._want_rt = realtime and speed > 0
        self._hold_rt = hold_realtime
        self._spin_us = spin_us
        self.spin_ns = (spin_us or 300) * 1000
        self._old_sched: tuple[int, int] | None = None
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        self.sock.bind((sensor_ip, 0))
        self.stats = SendStats()
        self.clock = clock  # one simulation clock with the other emulators of a run
        self.pacer = Pacer(speed, clock=clock, spin_ns=self.spin_ns)
        #: short housekeeping run between packets when there is time (:meth:`Pacer.wait`)
        self.idle: Callable[[], bool] | None = None
        self.speed = self.pacer.speed

    def _enter_realtime(self) -> None:
        if not self._want_rt or self._old_sched is not None:
            return
        old = enter_fifo()
        if old is None:
            return  # not permitted here: ordinary scheduling
        self._old_sched = old
        self.stats.realtime = True
        self.spin_ns = self.pacer.spin_ns = (self._spin_us or 200) * 1000

    def _leave_realtime(self) -> None:
        leave_fifo(self._old_sched)
        self._old_sched = None

    def close(self) -> None:
        self._leave_realtime()
        self.sock.close()

    def __enter__(self) -> PacedSender:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def send(self, datagrams: Iterable[Datagram]) -> None:
        """Send in order, each at its due time. Under SCHED_FIFO only while in here (unless
        ``hold_realtime``): the thread goes back to ordinary scheduling between calls."""
        self._enter_realtime()
        c0, w0 = time.thread_time(), time.perf_counter()
        try:
            self._send(datagrams)
        finally:
            self.stats.cpu_s += time.thread_time() - c0
            self.stats.wall_s += time.perf_counter() - w0
            if not self._hold_rt:
                self._leave_realtime()

    def _send(self, datagrams: Iterable[Datagram]) -> None:
        route, idle = self.route, self.idle
        for d in datagrams:
            late = self.pacer.wait(d.t_ns, idle)
            if self.speed > 0:
                self.stats.add_late(late)
            try:
                self.sock.sendto(d.payload, route.address(d.port) if route is not None
                                 else (self.dest_ip, d.port))
                self.stats.sent += 1
            except ConnectionRefusedError:
                self.stats.refused += 1
            except OSError as err:
                if err.errno in (errno.ENOBUFS, errno.EAGAIN, errno.EHOSTUNREACH,
                                 errno.ENETUNREACH):
                    self.stats.errors += 1
                else:
                    raise
