"""The live stream's frame ring: frames ray-cast and encoded ahead in a separate, lower-priority
process (forked: it shares the built scene), written into a ring of shared-memory slots; the
sending process only waits, sends straight from shared memory and hands the slot back (one
thread: nothing competes with the pacing loop for the interpreter lock, and no frame is
copied through a pipe). The producer also writes the pcap of exactly what was sent."""

from __future__ import annotations

import collections
import contextlib
import math
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from emulators.lidar import IMU_PERIOD_NS, Datagram
from protocols.ouster import IMU_PACKET_BYTES
from protocols.pcap import PcapWriter, UdpDatagram
from tcf_hil._io import name_process, settle_heap

__all__ = ["PRIME", "FrameRing", "PcapTarget", "pcap_parts", "pcap_records", "produce",
           "release",
           "slot_bytes"]


def pcap_records(writer: PcapWriter, dgs: list[Datagram], sensor_ip: str, dest: str
                  ) -> bytes:
    """One frame's datagrams as pcap records, each at its simulation time."""
    return b"".join(pcap_parts(writer, dgs, sensor_ip, dest))


def pcap_parts(writer: PcapWriter, dgs: list[Datagram], sensor_ip: str, dest: str
               ) -> list[bytes | memoryview]:
    """:func:`pcap_records` in pieces (:meth:`~protocols.pcap.PcapWriter.records_parts`),
    the payloads read where they are."""
    return writer.records_parts([UdpDatagram(d.t_ns, sensor_ip, dest, d.port, d.port,
                                             cast(bytes, d.payload)) for d in dgs])


# How far ahead of the pacing loop the producer may run: a second of the sensor's frames.
# The producer shares the CPUs with the program under test, and on a virtual machine with
# the host: a producer that stalls for less than the ring's lead costs no packet its time.
# With 4 slots (0.4 s at 10 Hz), such stalls handed up to 42 frames over late in a 30 s run
# (README, "Benchmarks", 2026-12-01/02: with the hypervisor's steal at 4-87 ms/s).
RING_AHEAD_S = 1.0
MIN_SLOTS = 4
RING_MAX_BYTES = 256 << 20  # the ring's shared memory at most (4096x5: 5 slots of 8.5 MB)
PRIME = 3  # frames in hand before the first packet (the rest fill while the sensor stands)


def ring_slots(run: Any, speed: float = 1.0) -> int:
    """Frames produced ahead of the pacing loop for ``run`` sent at ``speed``:
    :data:`RING_AHEAD_S` of wall time's frames (at ``--speed 2`` twice the frames; a stall
    of the producer is wall time, whatever the speed; ``speed`` 0, as fast as possible: a
    second of the sensor's frames), at least :data:`MIN_SLOTS`, within
    :data:`RING_MAX_BYTES`."""
    want = math.ceil(RING_AHEAD_S * run.meta.frequency_hz * max(1.0, speed))
    return max(MIN_SLOTS, min(want, RING_MAX_BYTES // slot_bytes(run)))


def slot_bytes(run: Any) -> int:
    """Upper bound of one frame's datagram bytes (lidar packets plus IMU packets)."""
    fmt = run.meta.packet_format
    packets = fmt.columns_per_frame // fmt.columns_per_packet
    imu = run.period_ns // IMU_PERIOD_NS + 2
    dup = 2 if run.udp_faults is not None and run.udp_faults.duplicate else 1
    return dup * (packets * fmt.packet_bytes + imu * IMU_PACKET_BYTES)


@dataclass
class PcapTarget:
    """The pcap of a live stream, written by the producer process (off the pacing loop):
    a frame's records go to the file once the sender has counted it sent."""

    path: str
    sensor_ip: str
    dest: str
    labels: str  # lidar_labels.bin, beside it


def produce(run: Any, conn: Any, free: Any, shm: Any, slot_bytes: int,
             stop: Any, sent: Any, rec: PcapTarget | None = None,
             parent_end: Any = None, air: tuple[Any, ...] | None = None,
             slots: int = MIN_SLOTS) -> None:
    """Producer process: writes each frame's datagrams into one of ``slots`` shared-memory
    slots and sends
    only (slot, [(t_ns, port, length)], fault events, phase, the time it was handed over:
    CLOCK_MONOTONIC, one clock for every process) down the pipe, then ("done",
    None) after the last. ``air``: an always-on sensor's plan and its standing machines
    (:meth:`~tcf_hil.devices.lidar.LidarRun.on_air`: frames before the track, the track,
    and after it until stopped; the pcap keeps those before and the track), else the
    track's frames only (phase ``track``).
    ``sent`` (shared) counts the frames the sender has finished. When the sender sets
    ``stop``, answers ("final", bookkeeping) as of exactly those frames (it runs a few frames
    ahead), and with ``rec`` the pcap holds exactly those frames too."""
    parent = os.getppid()  # a producer whose sender was killed must not live on
    _become_producer(run, parent_end)
    sink = _PcapSink(rec, sent) if rec is not None else None  # closed in the finally below
    # bookkeeping after each produced frame, back as far as the sender can be behind
    marks: collections.deque[tuple[int, tuple[np.ndarray, int, int]]] = collections.deque(
        [(0, run.mark())], maxlen=slots + 2)
    flush = sink.flush if sink is not None else (lambda: None)
    slot = produced = 0
    try:
        if sink is not None:
            sink.start(run.labels_header())
        run.halt = stop  # a frame the render ahead has not made is not waited for then
        frames = run.on_air(*air) if air is not None else (
            ("track", rf) for rf in run.rendered())
        for phase, rf in frames:
            dgs = rf.datagrams
            while not free.acquire(timeout=0.2):
                flush()
                if stop.is_set() or os.getppid() != parent:
                    stop.set()
                    break
            flush()
            if stop.is_set():
                break
            pos = slot * slot_bytes
            for d in dgs:
                n = len(d.payload)
                shm.buf[pos:pos + n] = d.payload
                pos += n
            meta = np.array([(d.t_ns, d.port, len(d.payload)) for d in dgs],
                            dtype=np.int64).reshape(-1, 3)
            conn.send(("frame", (slot, meta, run.last_events if phase == "track" else [],
                                 phase, time.perf_counter_ns())))
            if sink is not None:  # exactly what goes out, at its simulation time; the
                # rest is sent, not kept (standing before the clock stepped onto the track's
                # time line, and after the track)
                sink.keep(dgs, rf.labels, phase in ("before", "track"))
            produced += 1
            marks.append((produced, run.mark()))
            slot = (slot + 1) % slots
        else:
            conn.send(("done", None))
        while not stop.wait(0.05):  # the last frames are still going out
            flush()
            if os.getppid() != parent:
                break
        flush()
        n_sent = int(sent.value)
        counts, length, packets = next((m for n, m in marks if n == n_sent), marks[-1][1])
        conn.send(("final", (counts, run.poses_csv(length), packets)))
    except BaseException as err:  # reported by the sending side
        with contextlib.suppress(Exception):
            conn.send(("error", f"{type(err).__name__}: {err}"))
    finally:
        if sink is not None:
            sink.close()


def _become_producer(run: Any, parent_end: Any) -> None:
    """The forked producer's process set up: its name, its signals, its priority and its
    threads."""
    name_process("tcf-lidar-frames")
    settle_heap()
    # a terminal's Ctrl-C reaches the whole process group: the sender decides when to stop
    # (and the sender's own handlers, inherited through the fork, are not this process's)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if parent_end is not None:
        parent_end.close()  # the fork's copy of the reading end: a dead reader breaks the pipe
    # The pacing loop and the program under test, not the frame factory, get the CPU when
    # they want it: a producer that casts runs at nice 19. One that only reads a complete
    # render (the sensor's own cadence: 0.1-0.2 of a core) runs at the program's priority:
    # at nice 19 beside the reference SIC and its stem worker on 2 cores, it got too little
    # to keep the ring full (pine-thinning 1024x10: 15 frames handed over late, a stall of
    # over 100 ms). (Before the sender had a process of its own, reading at the ordinary
    # priority cost the SIC frames at 2048x10.) A render still being made ahead (by workers
    # of its own, at nice 19) is only read here too: at nice 19 beside a program that keeps a
    # core busy, this producer shared the other core with the render workers and handed the
    # track over later and later (232, 607, 990 ms ... a 2048x10 natural stand, 2026-12-03).
    casts = run.stored is None
    with contextlib.suppress(OSError):
        os.nice(19 if casts else 0)
    with contextlib.suppress(Exception):  # one core stays free for the pacing loop
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    if casts:
        caster = run.scene.caster
        if caster.threads is not None:  # the same for a ray caster that splits casts itself
            caster.threads = max(1, caster.threads - 1)
        run.emu.threads = max(1, run.emu.threads - 1)  # and for the emulator's column chunks


class _PcapSink:
    """The pcap and labels of a live stream as the producer writes them: each frame's
    records kept until the sender has counted it sent (``sent``, shared), then written
    whole and flushed (a crash leaves a readable capture)."""

    def __init__(self, rec: PcapTarget, sent: Any) -> None:
        self.rec, self.sent = rec, sent
        self.writer = PcapWriter()
        self.fh = open(rec.path, "wb")
        try:
            self.lh = open(rec.labels, "wb")
        except BaseException:
            self.fh.close()
            raise
        self.pending: collections.deque[tuple[bytes, bytes]] = collections.deque()
        self.written = 0

    def start(self, labels_header: bytes) -> None:
        """The files' headers."""
        self.fh.write(self.writer.header())
        self.lh.write(labels_header)

    def keep(self, dgs: list[Datagram], labels: bytes, recorded: bool) -> None:
        """A frame handed to the sender: its records and labels (``recorded``; else an empty
        place, for a frame that is sent and not kept)."""
        self.pending.append((pcap_records(self.writer, dgs, self.rec.sensor_ip,
                                          self.rec.dest), labels) if recorded
                            else (b"", b""))

    def flush(self) -> None:
        """The frames the sender has finished since the last flush, written."""
        n = self.written
        while self.written < self.sent.value and self.pending:
            records, labels = self.pending.popleft()
            self.fh.write(records)
            self.lh.write(labels)
            self.written += 1
        if self.written != n:
            self.fh.flush()  # whole frames reach the file: a crash leaves a readable capture
            self.lh.flush()

    def close(self) -> None:
        self.fh.close()
        self.lh.close()


def release(dgs: list[Datagram]) -> None:
    for d in dgs:
        if isinstance(d.payload, memoryview):
            d.payload.release()


class FrameRing:
    """The frames of a :class:`~tcf_hil.devices.lidar.LidarRun` made ahead in a forked
    producer process at a lower priority (:func:`produce`), each written into one of
    :func:`ring_slots` shared-memory slots; only (slot, [(t_ns, port, length)]) crosses the
    pipe.
    The sender takes a frame's datagrams as views of its slot (:meth:`frame`), sends them,
    and hands the slot back (:meth:`sent`). With ``rec``, the producer writes the pcap of
    exactly the frames sent."""

    def __init__(self, run: Any, rec: PcapTarget | None, air: tuple[Any, ...] | None = None,
                 speed: float = 1.0) -> None:
        from multiprocessing.shared_memory import SharedMemory

        ctx = mp.get_context("fork")
        self.run = run
        self.slot_bytes = slot_bytes(run)
        self.slots = ring_slots(run, speed)
        self.shm = SharedMemory(create=True, size=self.slot_bytes * self.slots)
        self._rx, tx = ctx.Pipe(duplex=False)
        self._free = ctx.Semaphore(self.slots)
        self._stop = ctx.Event()
        self._sent = ctx.RawValue("q", 0)  # frames finished by the sender, read by the producer
        # views of the slots being sent, oldest first (the next frame may be taken before
        # the last one is counted sent)
        self._held: collections.deque[list[Datagram]] = collections.deque()
        self.done = 0  # frames the sender has finished
        self.final: tuple[Any, ...] | None = None  # the producer's bookkeeping at the end
        self._owner = os.getpid()  # the process that forked the producer (may join it)
        self._child: Any = None
        try:
            self._child = ctx.Process(target=produce, args=(
                run, tx, self._free, self.shm, self.slot_bytes, self._stop, self._sent, rec,
                self._rx, air, self.slots), name="lidar-frames", daemon=True)
            self._child.start()
        finally:
            tx.close()

    def receive(self, timeout: float) -> tuple[str, Any] | None:
        """The producer's next message (``frame``, ``done``, ``final`` or ``error``), or
        None after ``timeout`` s."""
        try:
            if self._rx.poll(timeout):
                item: tuple[str, Any] = self._rx.recv()
                return item
        except (EOFError, OSError):
            return ("error", "the frame producer died")
        if os.getpid() == self._owner and not self._child.is_alive():
            return ("error", "the frame producer died")
        return None

    def prime(self, stop: threading.Event) -> collections.deque[tuple[str, Any]]:
        """Frames in hand before sending starts, so that the first ones are not late."""
        ready: collections.deque[tuple[str, Any]] = collections.deque()
        while len(ready) < min(PRIME, self.slots - 1) and not stop.is_set():
            item = self.receive(0.05)
            if item is not None:
                ready.append(item)
                if item[0] != "frame":
                    break
        return ready

    def frame(self, slot: int, meta: np.ndarray) -> list[Datagram]:
        """A frame's datagrams, as views of its slot (held until :meth:`sent`; frames are
        counted sent in the order they were taken)."""
        ends = (slot * self.slot_bytes + np.cumsum(meta[:, 2])).tolist()
        starts = [slot * self.slot_bytes, *ends[:-1]] if ends else []
        view = self.shm.buf
        assert view is not None
        held = [Datagram(t, port, view[a:b]) for (t, port, _n), a, b in
                zip(meta.tolist(), starts, ends, strict=True)]
        del view
        self._held.append(held)
        return held

    def frame_stream(self, slot: int, meta: np.ndarray) -> Iterator[Datagram]:
        """As :meth:`frame`, each datagram made only as it is asked for (a frame's
        138 datagrams at 2048x10 take a few hundred microseconds to make at once: more than
        there is between two packets)."""
        held: list[Datagram] = []
        self._held.append(held)
        return self._views(slot, meta.tolist(), held)

    def _views(self, slot: int, meta: list[list[int]], held: list[Datagram]
               ) -> Iterator[Datagram]:
        pos = slot * self.slot_bytes
        view = self.shm.buf
        assert view is not None
        for t, port, n in meta:
            d = Datagram(t, port, view[pos:pos + n])
            pos += n
            held.append(d)
            yield d

    def sent(self) -> None:
        """The oldest frame taken and not yet counted: counted sent (before its slot goes
        back), its views released, its slot handed back to the producer."""
        self._sent.value = self.done + 1
        if self._held:
            release(self._held.popleft())
        self._free.release()
        self.done += 1

    def release_held(self) -> None:
        """The views of the frames being sent released (an interrupted send holds them)."""
        while self._held:
            release(self._held.popleft())

    def finish(self, error: str | None) -> str | None:
        """Stop the producer; it answers with the bookkeeping of exactly the frames sent
        (restored into the run), writes the pcap's last frames and closes it. The error
        that ended the stream, or the producer's, or None."""
        self._stop.set()
        deadline = time.monotonic() + 60.0
        while error is None and time.monotonic() < deadline:
            item = self.receive(0.2)
            if item is None:
                continue
            if item[0] == "error":
                error = item[1]
            elif item[0] == "final":
                self.final = item[1]
                self.run.restore(*item[1])
                break
        else:
            error = error or "the frame producer did not answer"
        if os.getpid() == self._owner:  # (a sender process leaves that to the owner's close)
            self._child.join(timeout=30.0)
        return error

    def close(self) -> None:
        """The producer stopped (terminated if it must be) and the ring freed. Never raises
        for a producer already gone."""
        self._stop.set()
        self.release_held()  # an interrupted send still holds views of the ring
        with contextlib.suppress(Exception):
            for _ in range(self.slots):
                self._free.release()
        if self._child is not None:
            self._child.join(timeout=5.0)
            if self._child.is_alive():
                self._child.terminate()
                self._child.join(timeout=5.0)
        self._rx.close()
        self.shm.unlink()
        with contextlib.suppress(BufferError):
            self.shm.close()
