"""The live sender's count of frames late from the producer (``send_frames``): a frame
counts when it reached the sender late, not when the sender, held up on the frame before,
reached it late. Real packets over loopback; the ring is a stand-in producer whose frames
come at set times."""

from __future__ import annotations

import collections
import socket
import threading
import time
from typing import Any

import numpy as np

from emulators.lidar import Datagram, PacedSender
from tcf_hil.devices._sender import send_frames

PERIOD_NS = 20_000_000  # a frame every 20 ms of simulation time, 4 packets each


class _Run:
    def __init__(self, port: int, frames: int) -> None:
        self.frames = frames
        self.meta = type("Meta", (), {"udp_port_lidar": port})()


class _Ring:
    """Frames ``0..n-1`` (all track), each handed over (put in the pipe) at ``come(k)``
    (perf_counter_ns), as the frame producer stamps them."""

    def __init__(self, n: int, port: int, come: Any) -> None:
        self.n, self.port, self.come, self.k = n, port, come, 0

    def receive(self, timeout: float) -> tuple[str, Any] | None:
        if self.k >= self.n:
            return ("done", None)
        wait = (self.come(self.k) - time.perf_counter_ns()) / 1e9
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        k, self.k = self.k, self.k + 1
        t = k * PERIOD_NS + np.arange(4) * (PERIOD_NS // 4)
        meta = np.stack([t, np.full(4, self.port)], axis=1)
        return ("frame", (k, meta, [], "track", self.come(k)))  # in the pipe since

    def frame_stream(self, slot: int, meta: np.ndarray) -> list[Datagram]:
        return [Datagram(int(t), int(p), b"x" * 32) for t, p in meta]

    def sent(self) -> None:
        pass


def _send(come: Any, progress: Any, n: int = 6) -> PacedSender:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    port = rx.getsockname()[1]
    try:
        sender = PacedSender(realtime=False)
        err, _, handled, _ = send_frames(_Run(port, n), _Ring(n, port, come),
                                         collections.deque(), sender, threading.Event(),
                                         None, progress)
        assert err is None and handled == n
        return sender
    finally:
        rx.close()


def test_a_frame_the_producer_hands_over_late_counts() -> None:
    t0 = time.perf_counter_ns()
    # frame 3 comes 60 ms after the stream began, 0 about 20 ms before it was due: 3 was due
    # 60 ms after 0, so it comes about 20 ms late; the others are early
    sender = _send(lambda k: t0 + (80_000_000 if k == 3 else 0), None)
    assert sender.stats.late_frames == 1
    (t_ns, late_us, phase), = sender.stats.late_frame_log
    assert t_ns == 3 * PERIOD_NS and phase == "track" and late_us >= 1000


def test_a_sender_held_up_does_not_blame_the_producer() -> None:
    # every frame in the ring from the start; the bookkeeping after frame 1 holds the sender
    # up for 60 ms (as a hypervisor that runs another guest would): frames 2 and 3, long in
    # hand, go out late, and that is the packets' lateness, not the producer's
    def progress(done: int, n: int) -> None:
        if done == 2:
            time.sleep(0.06)

    t0 = time.perf_counter_ns()
    sender = _send(lambda k: t0, progress)
    assert sender.stats.late_frames == 0
    hist = sender.stats.late_hist
    assert sum(hist[1000:]) >= 1  # packets did leave 1 ms or more late


def test_the_ring_holds_a_second_of_wall_time_at_any_speed() -> None:
    """A stall of the frame producer is wall time: at ``--speed 2`` the ring holds twice the
    frames (a second of them at 1x was half a second at 2x); never less than a second of the
    sensor's frames (slower speeds, 0: as fast as possible); within its memory cap."""
    from tcf_hil.devices._ring import RING_MAX_BYTES, ring_slots, slot_bytes
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.scenario import load_scenario

    run = LidarRun(load_scenario("forest-ii"), mode="512x10")
    assert [ring_slots(run, s) for s in (1.0, 2.0, 0.5, 0.0, 2.5)] == [10, 20, 10, 10, 25]
    big = LidarRun(load_scenario("forest-ii"), mode="2048x10")
    assert ring_slots(big, 20.0) * slot_bytes(big) <= RING_MAX_BYTES < 200 * slot_bytes(big)


def test_the_next_frame_is_made_ready_before_the_last_packet_and_a_slot_goes_back_after_it(
        ) -> None:
    """Between a frame's last packet and the next frame's first there are 49 us at 2048x10:
    the next frame is taken and its first datagram made before the current frame's last
    packet leaves (it was after, and on a loaded machine that packet left 100-300 us late
    every frame); a frame's slot goes back to the producer only after its last packet left."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    port = rx.getsockname()[1]
    t0 = time.perf_counter_ns()
    made: list[tuple[int, int, int]] = []  # (frame, datagram, packets sent then)
    slots_back: list[int] = []  # packets sent when each slot went back
    sender = PacedSender(realtime=False)

    class Ring(_Ring):
        def frame_stream(self, slot: int, meta: np.ndarray) -> Any:
            def views() -> Any:
                for i, (t, p) in enumerate(meta):
                    made.append((slot, i, sender.stats.sent))
                    yield Datagram(int(t), int(p), b"x" * 32)
            return views()

        def sent(self) -> None:
            slots_back.append(sender.stats.sent)

    ring = Ring(5, port, lambda k: t0)
    ready = collections.deque(ring.receive(0) for _ in range(6))  # primed: 5 frames, done
    try:
        err, _, handled, _ = send_frames(_Run(port, 5), ring, ready, sender,
                                         threading.Event(), None, None)
    finally:
        rx.close()
        sender.close()
    assert err is None and handled == 5 and sender.stats.sent == 20
    firsts = {k: sent for k, i, sent in made if i == 0}
    for k in range(1, 5):  # frame k's first datagram made before frame k-1's last (4k-1) left
        assert firsts[k] <= 4 * k - 1, (k, firsts[k])
    assert slots_back == sorted(slots_back) and len(slots_back) == 5
    assert all(back >= 4 * (k + 1) for k, back in enumerate(slots_back)), slots_back
