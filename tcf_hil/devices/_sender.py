"""The live stream's sender: a process of its own that takes each frame from the frame ring
(:mod:`tcf_hil.devices._ring`), waits for its packets' due times and sends them.

Why a process: in the run's process the pacing loop shared one interpreter lock with the CAN
node, the sensor's HTTP API, the recorder and the progress line; a thread that held the lock
delayed a packet by up to the switch interval, and on two cores shared with the program
under test the lidar fell behind by milliseconds hundreds of times a minute. Forked from the
run's process (it shares the built run, the ring and the socket's source address), the
sender has the interpreter to itself and, where it may, runs under SCHED_FIFO.

What crosses between the two, and how:

- **to the sender** (a control pipe and a shared counter, checked before each packet: one
  shared-memory read): where the packets go now (the HTTP API's ``set_config`` moves the
  :class:`~emulators.lidar.Route`; it takes effect on the next packet) and the run's clock
  (known only after power-on; it steps once when the program under test is ready);
- **from the sender** (a pipe, a few messages per frame at most): fault events as the frame
  they struck goes out, track frames sent with the counters of the live
  :class:`~emulators.lidar.SendStats`, the first frame after the track, and at the end the
  pacing histogram, the bookkeeping of exactly the frames sent and any error.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import gc
import itertools
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from emulators.harvester import RunClock
from emulators.lidar import Datagram, PacedSender, Route, SendStats
from tcf_hil._io import name_process, settle_heap

__all__ = ["SenderProcess", "send_frames"]

_JOIN_S = 10.0  # how long a finished sender may take to exit before it is killed
# how often the run's process looks for a new clock to pass on: a step is placed six frames
# ahead (25 ms at --speed 20), and a sender that learns of it late waits on the old clock
_RELAY_POLL_S = 0.005


_LATE_NS = 1_000_000  # a packet this late is late (the figure: late packets > 1 ms)
_POLL_NS = 5_000_000  # between packets, the ring is asked for the next frame this often


def send_frames(run: Any, ring: Any, ready: collections.deque[tuple[str, Any]],
                sender: PacedSender, stop: Any,
                on_fault: Callable[[dict[str, Any]], None] | None,
                progress: Callable[[int, int], None] | None,
                on_track_end: Callable[[], None] | None = None
                ) -> tuple[str | None, int, int, SendStats | None]:
    """The pacing loop: each frame from the ring sent at its time until the producer is
    done, fails, or ``stop``. The error (or None), the track's frames that left with lidar
    packets, the track's frames handled, and the track's own pacing (None: no frame of the
    track went out; :meth:`~emulators.lidar.SendStats.open_window`).

    The frames go out as one stream of datagrams: a frame's last packet and the next one's
    first are 49 us apart at 2048x10, too close for anything else. The next frames are taken
    from the ring ahead, and a frame's bookkeeping (its slot handed back, its fault events
    and progress reported as it goes out) waits in a queue of short tasks; both run between
    packets when the next one is far enough off (:meth:`emulators.pacing.Pacer.wait`'s
    ``idle``). A frame the producer handed over 1 ms or more after its first packet was due
    counts in ``late_frames`` (the producer, not the pacing, made it late). The hand-over
    time, not the moment the stream reaches the frame: a sender held up before it (by the
    hypervisor, say) reaches a frame long in hand late, and that is the pacing's lateness,
    counted in the packets' histogram."""
    tasks: collections.deque[Callable[[], Any]] = collections.deque()
    staged: collections.deque[tuple[str, Any]] = collections.deque()  # frames with views
    last_poll = [0]
    closed = [False]  # the producer said done or failed
    counts = {"on_wire": 0, "track": 0}
    opened = [False]  # the track's window (its own pacing) opened
    out: dict[str, Any] = {"error": None, "window": None}
    stats = sender.stats

    def stage(item: tuple[str, Any]) -> None:
        if item[0] == "frame":
            slot, meta, events, phase, handed = item[1]
            item = ("frame", (ring.frame_stream(slot, meta), meta, events, phase, handed))
        else:
            closed[0] = True
        staged.append(item)

    def idle() -> bool:
        if tasks:
            tasks.popleft()()
            return True
        if ready:  # (primed before the stream started)
            stage(ready.popleft())
            return True
        now = time.perf_counter_ns()
        if closed[0] or len(staged) >= 2 or now - last_poll[0] < _POLL_NS:
            return False
        last_poll[0] = now
        item = ring.receive(0)
        if item is None:
            return False
        stage(item)
        return True

    def prepare(item: tuple[str, Any]) -> tuple[str, Any]:
        """A staged frame made ready to go out: its lateness from the producer judged, its
        fault events' reports queued for when it goes out, its first datagram made."""
        if item[0] != "frame":
            return item
        dgs, meta, events, phase, handed = item[1]
        dgs, n = iter(dgs), len(meta)
        late = None  # (counted when the frame goes out: a stop may keep it back)
        if n and sender.speed > 0:
            late_ns = handed - sender.pacer.due(int(meta[0, 0]))
            if late_ns >= _LATE_NS:
                late = (int(meta[0, 0]), late_ns, phase)
        reports = [functools.partial(on_fault, ev) for ev in events] \
            if on_fault is not None else []
        reinit = [ev["init_id"] for ev in events if ev["kind"] == "lidar_reinit"]
        on_wire = bool(n) and bool((meta[:, 1] == run.meta.udp_port_lidar).any())
        if phase == "track" and not opened[0]:
            stats.ready_window()
        # the frame's datagram maker (and with it its list of 138 packets) is let go in
        # gone(), between packets: freed where the stream moves to the next frame, it made
        # that frame's first packet tens of microseconds late
        return "frame", (dgs, next(dgs) if n else None, n, phase, (late, reports, reinit),
                         functools.partial(gone, phase == "track", on_wire, [dgs]))

    def gone(track: bool, on_wire: bool, maker: list[Any]) -> None:
        """A frame's last datagram went out: its slot back, its count and progress."""
        maker.clear()
        ring.sent()
        if track:
            counts["on_wire"] += on_wire
            counts["track"] += 1
            if progress:
                progress(counts["track"], run.frames)

    def close_window() -> None:
        out["window"] = stats.close_window()

    def take(block: bool) -> tuple[str, Any] | None:
        """The next frame (or the producer's end) made ready; None: stopped, or (``block``
        False) no frame in hand."""
        while not stop.is_set():
            if staged:
                return prepare(staged.popleft())
            if ready:  # (primed before the stream started)
                stage(ready.popleft())
                continue
            if not block:
                return None
            while tasks:  # nothing in hand: the bookkeeping, then wait for a frame
                tasks.popleft()()
            item = ring.receive(1.0)
            if item is not None:
                stage(item)
        return None

    def stream() -> Iterator[Datagram]:
        # Between a frame's last packet and the next frame's first there are 49 us at
        # 2048x10, and on a loaded machine the sender wakes with the SIC's data in its
        # caches: taking and preparing the next frame there made that packet 100-300 us late
        # once a frame (a trace of every packet: 300 of the 346 packets 100 us or more late
        # in a 30 s track). So the next frame is made ready before the current frame's last
        # packet, in the 781 us before it; only the phase's edges and a few appends are left
        # between the frames.
        ended = False
        nxt = take(block=True)
        while nxt is not None:
            kind, body = nxt
            if kind == "error":
                out["error"] = body
                return
            if kind == "done":
                break
            dgs, first, n, phase, (late, reports, reinit), done = body
            if phase == "track" and not opened[0]:
                opened[0] = True
                stats.open_window()
            if phase == "after" and not ended:
                ended = True
                stats.end_window()
                tasks.append(close_window)
                if on_track_end is not None:
                    tasks.append(on_track_end)
            if late is not None:
                stats.add_late_frame(*late)
            if reports:
                tasks.extend(reports)  # reported as the frame they struck goes out
            for init_id in reinit:  # the sidecars: the new identity
                run.meta = run.meta.with_changes(init_id=init_id)
            nxt = None
            if n:
                if n > 1:
                    yield first
                    yield from itertools.islice(dgs, n - 2)
                    first = next(dgs)
                nxt = take(block=False)  # (stop set: None, and the loop ends below)
                yield first  # the frame's last datagram
            tasks.append(done)
            if nxt is None:
                nxt = take(block=True)
            elif stop.is_set():
                break
        if not ended and on_track_end is not None:
            tasks.append(on_track_end)

    sender.idle = idle
    sender.send(stream())
    while tasks:
        tasks.popleft()()
    window = stats.close_window() or out["window"]
    return out["error"], counts["on_wire"], counts["track"], window


def _clock_state(clock: Any) -> tuple[tuple[int, int], ...] | None:
    """A clock as segments another process can rebuild (None: not known yet). ``clock``: a
    :class:`~emulators.harvester.RunClock` or ``SimClock``, or a holder with a ``clock``
    attribute that is None until power-on."""
    inner = getattr(clock, "clock", clock)
    return None if inner is None else tuple(inner.segments)


class _Control:
    """The sender's side of the control channel: applies what the run's process sent, in
    order, once the shared counter says it is there (one shared-memory read when nothing
    changed)."""

    def __init__(self, conn: Any, count: Any, route: Route | None, speed: float,
                 clock: tuple[tuple[int, int], ...] | None) -> None:
        self.conn, self.count, self.seen = conn, count, 0
        self.route, self.speed = route, speed
        self.clock = None if clock is None else RunClock.from_segments(clock, speed)

    def poll(self) -> None:
        if self.count.value == self.seen:
            return
        while self.seen < self.count.value:
            kind, body = self.conn.recv()  # written before the counter moved: never waits
            self.seen += 1
            if kind == "route" and self.route is not None:
                self.route.set(*body)
            elif kind == "clock":
                self.clock = RunClock.from_segments(body, self.speed)


class _MirrorClock:
    """The run's clock as the sender sees it (from the control channel). Until the run's
    process has one (power-on), the first packet's due time waits for it."""

    def __init__(self, ctl: _Control, stop: Any) -> None:
        self.ctl, self.stop, self.speed = ctl, stop, ctl.speed

    def monotonic_at(self, t_sim_ns: int) -> int:
        self.ctl.poll()
        while self.ctl.clock is None:
            if self.stop.is_set():
                return time.monotonic_ns()
            self.ctl.conn.poll(0.05)
            self.ctl.poll()
        return self.ctl.clock.monotonic_at(t_sim_ns)


class _MirrorRoute:
    """The run's :class:`~emulators.lidar.Route` as the sender sees it."""

    def __init__(self, ctl: _Control, route: Route) -> None:
        self.ctl, self.route = ctl, route

    def address(self, made: int) -> tuple[str, int]:
        self.ctl.poll()
        return self.route.address(made)


class _Stop:
    """Set by the run's process (a shared flag: one memory read, no lock), or by its death
    (a sender must not outlive its run)."""

    def __init__(self, flag: Any, parent: int) -> None:
        self.flag, self.parent = flag, parent

    def is_set(self) -> bool:
        return bool(self.flag.value) or os.getppid() != self.parent

    def set(self) -> None:
        self.flag.value = 1


def _sender_main(proc: SenderProcess, conn: Any, ctl_rx: Any, parent_ends: list[Any]) -> None:
    """The sender process: the pacing loop (:func:`send_frames`) with its callbacks sent up
    the pipe, then the end report."""
    name_process("tcf-lidar-send")
    settle_heap()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the run's process decides when to stop
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    for end in parent_ends:  # the fork's copies of the run's ends: a dead run breaks pipes
        end.close()
    with contextlib.suppress(OSError):  # ahead of the program under test where SCHED_FIFO
        os.setpriority(os.PRIO_PROCESS, 0, -10)  # is not allowed (PacedSender tries it)
    run, ring = proc.run, proc.ring
    if proc.route is not None:
        proc.route.listeners.clear()  # (the run's listener, copied by the fork)
    stop = _Stop(proc.stop, proc.parent)
    ctl = _Control(ctl_rx, proc.count, proc.route, proc.speed, proc.clock0)
    clock = _MirrorClock(ctl, stop) if proc.has_clock else None
    route = _MirrorRoute(ctl, proc.route) if proc.route is not None else None
    report: dict[str, Any] = {"error": None}

    def up(kind: str, body: Any) -> None:
        with contextlib.suppress(OSError):
            conn.send((kind, body))

    try:
        ready = ring.prime(stop)
        gc.collect()  # a full collection walks the whole scene: none while sending
        gc.freeze()
        with PacedSender(proc.sensor_ip, proc.dest, speed=proc.speed,
                         realtime=proc.realtime, clock=clock,
                         route=route,  # type: ignore[arg-type]
                         hold_realtime=True) as sender:
            st = sender.stats
            up("on_air", None)  # the first frame is ready and the sockets are open

            def progress(track: int, _total: int) -> None:
                up("track", (track, st.sent, st.refused, st.errors))

            error, on_wire, track, window = send_frames(
                run, ring, ready, sender, stop, lambda ev: up("fault", ev), progress,
                lambda: up("track_end", None))
        error = ring.finish(error)
        report.update(error=error, on_wire=on_wire, track=track, final=ring.final,
                      stats=st, window=window)
    except BaseException as err:  # reported to the run's process
        report["error"] = f"{type(err).__name__}: {err}"
    finally:
        ring.release_held()
        up("end", report)


class SenderProcess:
    """Forks the sender (:func:`_sender_main`) for ``ring``'s frames; :meth:`relay` (in the
    run's process) turns its messages into the stream's callbacks and keeps it told of the
    route and the clock."""

    def __init__(self, run: Any, ring: Any, sensor_ip: str, dest: str, *, speed: float,
                 realtime: bool, clock: Any, route: Route | None) -> None:
        ctx = mp.get_context("fork")
        self.run, self.ring = run, ring
        self.sensor_ip, self.dest, self.speed, self.realtime = sensor_ip, dest, speed, realtime
        self.route, self.clock = route, clock
        self.has_clock = clock is not None
        if clock is not None:
            self.speed = clock.speed
        self.clock0 = _clock_state(clock) if clock is not None else None
        self.parent = os.getpid()
        self.stop = ctx.RawValue("b", 0)  # set by the run's process: the sender stops
        self.count = ctx.RawValue("q", 0)  # control messages written (the sender's cue)
        self._lock = threading.Lock()  # the HTTP API and the relay both write controls
        self.stats = SendStats()  # the live counters, kept up to date by relay()
        self._rx, tx = ctx.Pipe(duplex=False)
        ctl_rx, self._ctl = ctx.Pipe(duplex=False)
        self._sent_clock = self.clock0
        self._child = ctx.Process(target=_sender_main, args=(
            self, tx, ctl_rx, [self._rx, self._ctl]), name="lidar-sender", daemon=True)
        if route is not None:
            route.listeners.append(self._route_changed)
        try:
            self._child.start()
        except BaseException:
            if route is not None:
                route.listeners.remove(self._route_changed)
            self._rx.close()
            self._ctl.close()
            raise
        finally:
            tx.close()
            ctl_rx.close()

    def _control(self, kind: str, body: Any) -> None:
        with self._lock, contextlib.suppress(OSError):
            self._ctl.send((kind, body))
            self.count.value += 1

    def _route_changed(self, dest_ip: str, lidar_port: int, imu_port: int) -> None:
        self._control("route", (dest_ip, lidar_port, imu_port))

    def _watch_clock(self) -> None:
        if not self.has_clock:
            return
        state = _clock_state(self.clock)
        if state is not None and state != self._sent_clock:
            self._sent_clock = state
            self._control("clock", state)

    def relay(self, stop: threading.Event,
              on_fault: Callable[[dict[str, Any]], None] | None,
              progress: Callable[[int, int], None] | None,
              on_track_end: Callable[[], None] | None,
              on_air: Callable[[], None] | None = None) -> dict[str, Any]:
        """Until the sender ends: its messages as callbacks (a re-initialisation's event
        moves ``run.meta`` to the new identity first; ``on_air``: the first frame is about
        to go out), the route and the clock sent to it,
        ``stop`` passed on. Its end report (``error``, ``on_wire``, ``track``, ``stats``,
        ``window``, ``final``); the run's bookkeeping restored to exactly the frames sent."""
        run = self.run
        while True:
            if stop.is_set() and not self.stop.value:
                self.stop.value = 1
            self._watch_clock()
            try:
                if not self._rx.poll(_RELAY_POLL_S):
                    # (its end report may have come between the poll and its exit)
                    if not self._child.is_alive() and not self._rx.poll(0):
                        return {"error": "the lidar sender died "
                                         f"(exit code {self._child.exitcode})"}
                    continue
                kind, body = self._rx.recv()
            except (EOFError, OSError):
                self._child.join(timeout=_JOIN_S)
                return {"error": f"the lidar sender died (exit code {self._child.exitcode})"}
            if kind == "fault":
                if body["kind"] == "lidar_reinit":
                    run.meta = run.meta.with_changes(init_id=body["init_id"])
                if on_fault is not None:
                    on_fault(body)
            elif kind == "track":
                track, self.stats.sent, self.stats.refused, self.stats.errors = body
                if progress is not None:
                    progress(track, run.frames)
            elif kind == "on_air":
                if on_air is not None:
                    on_air()
            elif kind == "track_end":
                if on_track_end is not None:
                    on_track_end()
            elif kind == "end":
                report: dict[str, Any] = body
                if report.get("final") is not None:
                    run.restore(*report["final"])
                if report.get("stats") is not None:
                    self.stats.__dict__.update(report["stats"].__dict__)
                    report["stats"] = self.stats
                self._child.join(timeout=_JOIN_S)
                return report

    def close(self) -> None:
        """The sender stopped (killed if it must be); the route no longer tells it."""
        if self.route is not None and self._route_changed in self.route.listeners:
            self.route.listeners.remove(self._route_changed)
        self.stop.value = 1
        deadline = time.monotonic() + _JOIN_S
        while self._child.is_alive() and time.monotonic() < deadline:
            with contextlib.suppress(EOFError, OSError):  # its report read and dropped (a
                if self._rx.poll(0.05):  # relay that ended early: the sender must not
                    self._rx.recv()  # block on a full pipe)
            self._child.join(timeout=0.0)
        if self._child.is_alive():
            self._child.kill()
            self._child.join(timeout=5.0)
        self._rx.close()
        self._ctl.close()
