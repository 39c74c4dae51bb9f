"""The lidar run: scenario -> forest -> scene -> OS0-64 frames -> packets (:class:`LidarRun`:
rendered live, read from the render store or rendered into it), and the live stream
(:func:`stream_lidar`: UDP on the wire, paced in real time, always on where the run asks).
The offline path (:mod:`tcf_hil.devices.offline`) writes the same packet bytes to a pcap
file; both keep the metadata, ground truth, per-stem visibility and the sensor poses
beside them."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import json
import math
import multiprocessing as mp
import os
import signal
import threading
import time
import zipfile
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass
from multiprocessing.connection import wait as mp_wait
from pathlib import Path
from typing import Any

import numpy as np

from emulators.faults import FaultEvent
from emulators.lidar import (
    Datagram,
    FrameResult,
    Os0Emulator,
    Os0Sensor,
    ReturnModel,
    Route,
    SendStats,
    carried_range_m,
)
from emulators.lidar import warm_up as warm_up_kernels
from protocols.labels import encode_labels_header, encode_labels_record
from protocols.ouster import (
    MetadataError,
    SensorMetadata,
    decode_lidar_packet,
    finish_lidar_packets,
    os0_64_metadata,
    shift_lidar_packet,
)
from tcf_hil._crc import fast_crc_rows
from tcf_hil._io import (
    atomic_path,
    ensure_dir,
    name_process,
    settle_heap,
    write_bytes_atomic,
    write_json_atomic,
)
from tcf_hil._rotations import quaternions
from tcf_hil.devices._renderers import (
    RENDER_AHEAD_BLOCKS,
    RENDER_BLOCK,
    RENDER_SILENT_S,
    RenderAhead,
    recv_frame,
    render_part,
    widen_pipe,
)
from tcf_hil.devices._ring import FrameRing, PcapTarget
from tcf_hil.devices._ring import ring_slots as ring_slots  # frames a live stream makes ahead
from tcf_hil.devices._sender import SenderProcess
from tcf_hil.devices._standing import OnAir, StandingEmulator, StandingPose
from tcf_hil.errors import ConfigError
from tcf_hil.recording.poses_csv import pose_rows
from tcf_hil.recording.poses_csv import warm_up as warm_up_pose_rows
from tcf_hil.recording.store import (
    RenderedFrame,
    RenderStore,
    RenderWriter,
    StoredRender,
    pack_frame,
    render_key,
)
from tcf_hil.scenario import Scenario
from tcf_hil.world import World
from tcf_hil.world.forest import Forest, ground_truth
from tcf_hil.world.scene import resolve_backend
from tcf_hil.world.track import warm_up as warm_up_poses

# where a run's frames come from (LidarRun; "ahead": a live run's, LiveTraffic)
RENDER_MODES = ("auto", "fill", "stored", "live", "ahead")
# Frames of the standing machine rendered once (1 s at 10 Hz) and sent again, restamped: its
# range noise repeats each second (a real sensor's would not); the geometry does not change.
STANDING_CYCLE = 10


def _render_ahead(run: LidarRun, writer: RenderWriter, upto: int, done: Any,
                  state: Any) -> None:
    """The renderer process of :meth:`LidarRun.render_ahead`."""
    name_process("tcf-render")
    settle_heap()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the run decides when it stops
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with contextlib.suppress(OSError):
        os.nice(10)
    try:
        run.frames = upto
        run.writer = writer
        for rf in run._render_live(start=writer.frames):
            writer.append(rf, run.ports)
            done.value = rf.k + 1
        if writer.frames >= run.track_frames:
            writer.complete()
        state.value = 1
    except BaseException:
        state.value = 2
        raise
    finally:
        writer.close()


@dataclass(frozen=True)
class RecordResult:
    out_dir: Path | None
    frames: int
    packets: int
    returns: int
    stems_seen: int
    backend: str
    pacing_us: tuple[float, float] = (0.0, 0.0)
    refused: int = 0
    realtime: bool = False  # the pacing loop ran under SCHED_FIFO
    sender_cpu_share: float = 0.0  # CPU time of the pacing loop per wall second while sending
    # frames the frame producer handed over 1 ms or more after their first packet was due
    # (late packets that the source, not the pacing, caused)
    frames_late_from_producer: int = 0
    # the first of them: (simulation time of the first packet ns, how late us, phase)
    late_frame_log: tuple[tuple[int, int, str], ...] = ()
    # an always-on sensor's track alone: p50/p99 pacing error (us), packets 1 ms or more late
    track_pacing_us: tuple[float, float] = (0.0, 0.0)
    track_late_1ms: int = 0
    # the hypervisor's steal during the track (ms per second, all CPUs; None: not known):
    # a vCPU the host does not run sends nothing (emulators.pacing.steal_s)
    track_steal_ms_per_s: float | None = None


def sensor_metadata(scn: Scenario, *, mode: str = "1024x10",
                    profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
                    udp_dest: str = "127.0.0.1", udp_port_lidar: int = 7502,
                    udp_port_imu: int = 7503) -> SensorMetadata:
    """The run's metadata (init_id derived from the seed), without building any scene."""
    s = scn.seed if seed is None else seed
    init_id = (s * 2654435761 + 12345) % (1 << 24) or 1
    fw = scn.sensor.firmware
    try:
        # (3.1: the shipped calibration's own revision strings, build date included)
        return os0_64_metadata(mode, profile, firmware=None if fw == "3.1" else fw,
                               init_id=init_id, udp_dest=udp_dest,
                               udp_port_lidar=udp_port_lidar, udp_port_imu=udp_port_imu)
    except MetadataError as err:
        raise ConfigError("sensor.firmware", fw, f"a firmware with profile {profile} "
                          f"({err})") from err


class LidarRun:
    """One sensor driven along a scenario's track; yields each frame's datagrams in send
    order (lidar packets at their last column's time stamp, IMU at 100 Hz)."""

    def __init__(self, scn: Scenario, *, mode: str = "1024x10",
                 profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
                 backend: str = "auto", model: ReturnModel | None = None,
                 max_frames: int | None = None, udp_dest: str = "127.0.0.1",
                 udp_port_lidar: int = 7502, udp_port_imu: int = 7503,
                 meta: SensorMetadata | None = None, t0_ns: int = 1_000_000_000,
                 faults: bool = True, keep_poses: bool = True, forest: Forest | None = None,
                 first_frame_id: int = 0, world: World | None = None,
                 store: RenderStore | None = None, render: str = "live") -> None:
        """``faults``: inject the scenario's ``[faults]`` (UDP and lidar) into the datagrams;
        each frame's fault events are in :attr:`last_events` after it is yielded.
        ``keep_poses``: keep every column's sensor pose for ``sensor_poses.csv`` (about
        100 bytes per column: off for long live runs that need no such file).
        ``forest``: a forest built by the caller (hand-placed stems, say) instead of the one
        ``scn`` generates. ``first_frame_id``: the frame_id of the first frame, as of a sensor
        that has been running a while (frame_id is 16 bits: 65536 frames wrap it).
        ``world``: the run's world, resolved once (:class:`~tcf_hil.world.World`), whose
        forest, track, scene and fault plans the sensor takes; without it the sensor resolves
        one of its own from ``scn``, ``seed``, ``t0_ns``, ``forest`` and its ports.
        ``store`` and ``render``: where the frames come from (:data:`RENDER_MODES`; ``ahead``
        is ``auto`` here, :meth:`render_ahead` is the caller's): ``live``
        renders each as it is asked for; ``auto`` sends the render ``store`` holds for this
        run where it is complete (:attr:`render_key`), else renders live; ``fill`` as
        ``auto``, and a live render is kept in the store as it goes (when no other process
        is writing it: the next run of the key reads it); ``stored`` always sends from the
        store (:meth:`render_into_store` first where the render is missing)."""
        if render not in RENDER_MODES:
            raise ConfigError("render", render, f"one of {', '.join(RENDER_MODES)}")
        self._own_forest = forest is not None and world is None
        if world is None:
            ports = ((meta.udp_port_lidar, meta.udp_port_imu) if meta is not None
                     else (udp_port_lidar, udp_port_imu))
            world = World.build(scn, seed=seed, t0_ns=t0_ns, forest=forest, lidar_ports=ports)
        self.world = world
        self.forest: Forest = world.forest
        self._backend_asked = backend
        self.track = world.track
        self.meta: SensorMetadata = meta or sensor_metadata(
            scn, mode=mode, profile=profile, seed=self.forest.seed, udp_dest=udp_dest,
            udp_port_lidar=udp_port_lidar, udp_port_imu=udp_port_imu)
        limit = carried_range_m(self.meta.packet_format)
        if model is not None and model.max_range_m > limit:
            raise ConfigError("max_range_m", model.max_range_m,
                              f"at most {limit:.0f} m: what {self.meta.profile}'s RANGE "
                              "field carries")
        if model is not None and not scn.sensor.ideal:
            raise ConfigError("sensor", scn.sensor.preset,
                              "'ideal' for a return model of its own (--noise, --max-range)")
        self.sensor = scn.sensor
        self.model = model
        self._meta0 = self.meta  # what the key is made of (render_doc), computed once
        # The scene (a natural stand's takes seconds to build) and the emulator on it are
        # built when first needed: a run whose frames all come from the store never needs
        # them (:attr:`scene`, :attr:`emu`)
        self.period_ns = 1_000_000_000 // self.meta.frequency_hz
        n = max(1, math.ceil(self.track.duration_ns / self.period_ns))
        self.frames = min(n, max_frames) if max_frames is not None else n
        self.backend = resolve_backend(backend)[0]  # the concrete one: auto resolved
        self.n_stems = len(self.forest.stems)
        # returns per object id (grown as ids come: a natural stand's ids reach past its
        # stems, to its branches, foliage and the rest of its scenery)
        self.counts = np.zeros(self.n_stems + 1, dtype=np.int64)
        self.packets = 0
        self._poses = io.StringIO()
        self._pw = csv.writer(self._poses, lineterminator="\n")
        self._pw.writerow(["time_ns", "x", "y", "z", "qw", "qx", "qy", "qz"])
        plans = world.faults if faults else None
        self.keep_poses = keep_poses
        self.first_frame_id = first_frame_id
        self.udp_faults = plans.udp if plans else None
        self.lidar_faults = plans.lidar if plans else None
        self.last_events: list[FaultEvent] = []
        self.last_sent = False
        # the faults injected: a scenario without fault plans renders the same bytes with
        # faults on or off, so a live run and an offline cell share its render
        self.faults_on = plans is not None
        self._doc: dict[str, Any] | None = None
        self._key: str | None = None
        self.store = store if render != "live" else None
        self.render_mode = render
        self.stored: StoredRender | None = None  # the render the frames come from, if any
        self.writer: RenderWriter | None = None  # where rendered frames are kept, if anywhere
        self.ahead: RenderAhead | None = None  # a render being written for this run
        self.halt: Any = None  # an event: stop waiting for frames the render has not made
        if self.store is not None:
            key = self.render_key
            if key is None and render == "stored":
                raise ConfigError("render", render, "a forest built by the caller cannot be "
                                  "stored (its scenario does not say what it holds)")
            if key is not None:
                self.stored = self.store.open(key)

    @functools.cached_property
    def scene(self) -> Any:
        """The scene the rays hit (the world's, on this run's backend), built when first
        asked for."""
        scene = self.world.scene(self._backend_asked)
        if scene.backend != self.backend:  # (resolve_backend decides as the scene does)
            raise RuntimeError(f"the scene's backend {scene.backend} is not the run's "
                               f"{self.backend}")
        return scene

    @functools.cached_property
    def emu(self) -> Os0Emulator:
        """The emulated sensor on :attr:`scene`, built when first asked for."""
        return Os0Emulator(self._meta0, self.scene, self.track, self.model,
                           seed=self.forest.seed, start_ns=self.track.t0_ns,
                           threads=self.scene.caster.threads, sensor=self.sensor)

    @property
    def renders(self) -> bool:
        """Whether this run's scene and emulator have been built (a run streamed from the
        store builds neither)."""
        return "emu" in self.__dict__ or "scene" in self.__dict__

    def _counts_for(self, size: int) -> np.ndarray:
        """:attr:`counts`, zeros added up to ``size`` ids."""
        if len(self.counts) < size:
            self.counts = np.concatenate([self.counts,
                                          np.zeros(size - len(self.counts), np.int64)])
        return self.counts

    @property
    def _packets_per_frame(self) -> int:
        return self.meta.packet_format.packets_per_frame

    @property
    def track_frames(self) -> int:
        """Frames of the whole track (a run may send fewer: ``max_frames``)."""
        return max(1, math.ceil(self.track.duration_ns / self.period_ns))

    def render_doc(self) -> dict[str, Any] | None:
        """Everything that decides this run's frames' bytes (the render store's key is made
        of it with the code's version), or None for a forest built by the caller."""
        if self._own_forest:
            return None
        if self._doc is not None:
            return self._doc
        from tcf_hil.scenario import scenario_to_dict

        meta = dataclasses.asdict(self._meta0)  # (as made: a re-initialisation changes it)
        for name in ("udp_dest", "udp_port_lidar", "udp_port_imu", "extra"):
            meta.pop(name, None)  # not in the bytes: where they go
        scenario = scenario_to_dict(self.world.scenario)
        if not self.faults_on:
            scenario.pop("faults", None)  # not injected: not in the bytes
        doc = {"scenario": scenario, "seed": self.forest.seed,
                "backend": self.backend, "t0_ns": self.track.t0_ns,
                "frames": self.track_frames, "first_frame_id": self.first_frame_id,
                "faults": self.faults_on, "model": None if self.model is None
                else dataclasses.asdict(self.model), "sensor": meta}
        self._doc = doc
        return doc

    @property
    def render_key(self) -> str | None:
        if self._key is None and (doc := self.render_doc()) is not None:
            self._key = render_key(doc)
        return self._key

    @property
    def ports(self) -> tuple[int, int]:
        """The lidar and IMU ports the datagrams are made for."""
        return self.meta.udp_port_lidar, self.meta.udp_port_imu

    def render_into_store(self, progress: Callable[[int, int], None] | None = None,
                          workers: int = 1,
                          remote: Callable[[LidarRun, int],
                                           Generator[tuple[int, bytes | bytearray], None, None]]
                          | None = None) -> int:
        """Every frame of the track rendered into the store (resumed after the last whole
        frame a render cut short kept), unless it is there already; then the run sends from
        it. Frames rendered now (0: all were stored). ``workers`` > 1 (``tcf-hil render``:
        one per CPU this process may use; not from a daemonic process, which may not fork
        children): rendered by that many processes at once (forked: they share
        the built scene), each taking blocks of :data:`RENDER_BLOCK` frames in turn and
        packing its frames itself, the ray threads shared out among them (Forest X at
        2048x10 on 2 cores: 1.6x real time in one, 2.5x in two; pine-thinning 0.9x and
        1.1x); a run with fault plans renders in order, in one. ``remote(run, start)``: the
        frames from ``start``, packed and in order, made elsewhere instead (Dask workers:
        :func:`tcf_hil.devices.dask_render.render_on_dask`), stored here."""
        if self.store is None:
            raise ConfigError("render", self.render_mode, "'auto' or 'stored' (a store)")
        key = self.render_key
        doc = self.render_doc()
        if key is None or doc is None:
            raise ConfigError("render", self.render_mode, "a scenario's own forest")
        if self.stored is not None:
            return 0
        frames, self.frames = self.frames, self.track_frames
        writer = self.store.writer(key, doc, self.track_frames)
        if writer is None:  # another process stored it meanwhile
            self.frames = frames
            self.stored = self.store.open(key)
            if self.stored is None:
                raise RuntimeError(f"render {key}: neither stored nor writable")
            return 0
        done = writer.frames
        keep = self.keep_poses
        self.keep_poses = False  # the store keeps the poses; this run's bookkeeping not
        try:
            self.writer = writer
            blocks: Generator[tuple[int, bytes | bytearray], None, None] | None = None
            if remote is not None:
                if not self.parallel_render():
                    raise ConfigError("executor", "a remote one", "local: a render with "
                                      "fault plans makes every frame in order, in one process")
                blocks = remote(self, done)
            elif workers > 1 and self.parallel_render() and not mp.current_process().daemon:
                blocks = self._render_parallel(done, workers)
            if blocks is not None:
                with contextlib.closing(blocks):  # (its workers or client stop at once)
                    for k, packed in blocks:
                        writer.append_packed(k, packed)
                        if progress is not None:
                            progress(k + 1, self.track_frames)
            else:
                for rf in self._render_live(start=done):
                    writer.append(rf, self.ports)
                    if progress is not None:
                        progress(rf.k + 1, self.track_frames)
            writer.complete()
        finally:
            self.writer = None
            writer.close()
            self.frames, self.keep_poses = frames, keep
        self._reset_bookkeeping()
        self.stored = self.store.open(key)
        self._keep_beside()
        return self.track_frames - done

    def _keep_beside(self) -> None:
        """What a run streamed from this complete render would otherwise build the scene
        for, kept beside it now that the scene is built: the standing machine at the whole
        track's start and end, the labels header, the scene's facts (a run of a shorter
        ``--duration`` renders its own end's cycle once, and keeps it)."""
        if self.stored is None or not self.stored.complete:
            return
        period, t0 = self.period_ns, self.track.t0_ns
        for at in (t0 - period, t0 + self.track_frames * period):
            self.standing(at)
        self.labels_header()
        self._scene_facts()

    def _render_parallel(self, start: int, workers: int, end: int | None = None,
                         compress: bool = True
                         ) -> Generator[tuple[int, bytes | bytearray], None, None]:
        """Frames ``start`` .. ``end`` (default: the track's last) of the track, packed
        (:func:`pack_frame`; without ``compress``, their records as
        :meth:`RenderedFrame.encode` makes them), in order, from
        ``workers`` forked renderer processes (:func:`render_part`: worker ``i`` renders
        blocks ``i``, ``i + workers``, ...). Frames that come ahead of their turn wait here,
        at most :data:`RENDER_AHEAD_BLOCKS` blocks of them; then only the worker whose turn
        it is is read (the others wait on their pipes). A worker that dies or falls silent
        for :data:`RENDER_SILENT_S` fails the render."""
        ctx = mp.get_context("fork")
        end = self.track_frames if end is None else end
        self.emu.warm_up()  # the scene and the kernels made once, here: the workers share them
        procs: list[Any] = []
        conns: list[int] = []  # the read ends of the workers' pipes
        try:
            for i in range(workers):
                r, w = os.pipe()
                try:
                    conns.append(r)
                    widen_pipe(w)
                    proc = ctx.Process(target=render_part, name=f"lidar-render-{i}",
                                       daemon=True,
                                       args=(self, start, i, workers, w, conns, end, compress))
                    proc.start()
                finally:
                    os.close(w)
                procs.append(proc)
            pending: dict[int, bytearray] = {}
            ended: set[int] = set()
            nxt, last = start, time.monotonic()
            while nxt < end:
                if nxt in pending:
                    yield nxt, pending.pop(nxt)
                    nxt += 1
                    last = time.monotonic()
                    continue
                owner = (nxt - start) // RENDER_BLOCK % workers
                if owner in ended:
                    raise RuntimeError(f"render worker {owner} ended without frame {nxt}")
                full = len(pending) >= RENDER_AHEAD_BLOCKS * RENDER_BLOCK
                watch = [conns[owner]] if full else \
                    [c for i, c in enumerate(conns) if i not in ended]
                ready = mp_wait(watch, timeout=1.0)
                if not ready and time.monotonic() - last > RENDER_SILENT_S:
                    raise RuntimeError(f"render worker {owner} made no frame for "
                                       f"{RENDER_SILENT_S:g} s (frame {nxt})")
                for c in ready:
                    assert isinstance(c, int)
                    i = conns.index(c)
                    try:
                        k, msg = recv_frame(c)
                    except (EOFError, OSError):  # gone without its end mark: killed, crashed
                        procs[i].join(1.0)
                        raise RuntimeError(f"render worker {i} died (exit code "
                                           f"{procs[i].exitcode}) before frame {nxt}") from None
                    if k == -2:
                        raise RuntimeError(f"render worker {i} failed: "
                                           f"{msg.decode(errors='replace')}")
                    if k == -1:
                        ended.add(i)
                    else:
                        pending[k] = msg
                        last = time.monotonic()
        finally:
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
            for proc in procs:
                proc.join(10)
            for c in conns:
                os.close(c)

    def packed_frames(self, a: int, b: int, compress: bool = True
                      ) -> Iterator[tuple[int, bytes]]:
        """Frames ``a`` .. ``b`` - 1 of the track as the store keeps them (packed,
        :func:`pack_frame`; without ``compress``, their records as
        :meth:`RenderedFrame.encode` makes them), made now without the ones before (no fault
        plan may run: a frame's bytes then follow from its index alone): a block of a
        parallel render, here or on a Dask worker (:mod:`tcf_hil.devices.dask_render`)."""
        for rf in self.compact_frames(a, b):
            yield rf.k, pack_frame(rf, self.ports) if compress else rf.encode(self.ports)

    def compact_frames(self, a: int, b: int) -> Iterator[RenderedFrame]:
        """Frames ``a`` .. ``b`` - 1 of the track in the store's compact form, made now
        without the ones before (:meth:`packed_frames`)."""
        if self.lidar_faults is not None or self.udp_faults is not None:
            raise ValueError("a render with fault plans makes every frame in order")
        sensor = self.sensor_at(a)
        for k in range(a, b):
            yield self._compact(k, sensor.frame(k), sensor.meta.init_id, True)

    def parallel_render(self) -> bool:
        """Whether blocks of this run's frames may be rendered apart (by processes or Dask
        workers): no fault plan and no noise drawn in frame order."""
        return (self.lidar_faults is None and self.udp_faults is None
                and (self.model is None or self.model.noise_sigma_m == 0))

    def _reset_bookkeeping(self) -> None:
        self.counts[:] = 0
        self.packets = 0
        self._poses = io.StringIO()
        self._pw = csv.writer(self._poses, lineterminator="\n")
        self._pw.writerow(["time_ns", "x", "y", "z", "qw", "qx", "qy", "qz"])

    def rendered(self, workers: int = 1) -> Iterator[RenderedFrame]:
        """Each frame in the compact form the render store keeps, from the store where this
        run sends a stored render, else rendered now; the bookkeeping (returns per stem,
        packets, poses, fault events) follows each as it is yielded, the same either way.
        A ``stored`` run whose render is missing renders it into the store first.
        ``workers`` > 1: a live render of more than a block of frames that keeps none in the
        store is made by that many forked processes at once (:meth:`_render_parallel`, the
        same bytes), where :meth:`parallel_render` allows it and this is no daemonic
        process (which may not fork children)."""
        if self.stored is None and self.render_mode == "stored":
            self.render_into_store()
        if self.stored is not None:
            ports = self.ports
            for k in range(self.frames):
                if k >= self.stored.frames and not self._wait_for(k):
                    return  # halted while waiting
                rf = self.stored.frame(k, ports)
                self._take(rf)
                yield rf
            return
        writer = None
        key, doc = (self.render_key, self.render_doc()) if self.render_mode == "fill" \
            else (None, None)
        if self.store is not None and key and doc and self.frames == self.track_frames:
            writer = self.store.writer(key, doc, self.track_frames, wait=False)
            if writer is not None and writer.frames:  # a render cut short: start over
                writer.close()
                self.store.remove(key)
                writer = self.store.writer(key, doc, self.track_frames, wait=False)
        if writer is None and workers > 1 and self.frames > RENDER_BLOCK \
                and self.parallel_render() and not mp.current_process().daemon:
            yield from self._rendered_parallel(workers)
            return
        try:
            self.writer = writer
            for rf in self._render_live():
                self._take(rf)
                if writer is not None:
                    writer.append(rf, self.ports)
                yield rf
            if writer is not None:
                writer.complete()
        finally:
            self.writer = None
            if writer is not None:
                writer.close()

    def _rendered_parallel(self, workers: int) -> Iterator[RenderedFrame]:
        """:meth:`rendered` by ``workers`` processes: their records read back in order."""
        blocks = self._render_parallel(0, workers, self.frames, compress=False)
        with contextlib.closing(blocks):  # (its workers stop at once)
            for k, record in blocks:
                rf, _ = RenderedFrame.decode(record, 0, f"render worker's frame {k}",
                                             self.ports)
                self._take(rf)
                yield rf

    def _wait_for(self, k: int) -> bool:
        """Until the render being written holds frame ``k``: True, or False where
        :attr:`halt` was set meanwhile (raises where its renderer failed or is gone without
        the frame)."""
        assert self.stored is not None
        ahead = self.ahead
        while self.stored.refresh() <= k:
            if self.halt is not None and self.halt.is_set():
                return False
            if ahead is None or ahead.state.value == 2 or not ahead.running():
                if self.stored.refresh() > k:
                    break
                raise RuntimeError(f"the render ahead into {self.stored.path} stopped "
                                   f"before frame {k} (see the bench's stderr)")
            time.sleep(0.01)
        return True

    def sensor_at(self, k: int) -> Os0Sensor:
        """The sensor that sends this run's frames, as before frame ``k`` (0: at the track's
        start; later only where no fault plan runs: :meth:`Os0Sensor.skip_to`)."""
        sensor = Os0Sensor(self.emu, self.meta, self.track, lidar_faults=self.lidar_faults,
                           udp_faults=self.udp_faults, crc_rows=fast_crc_rows(),
                           first_frame_id=self.first_frame_id, first_imu_ns=self.track.t0_ns)
        if k:
            sensor.skip_to(k)
        return sensor

    def _render_live(self, start: int = 0) -> Iterator[RenderedFrame]:
        """Frames ``start`` .. of this run rendered now (the sensor's per-frame behaviour is
        :class:`emulators.lidar.Os0Sensor`'s; the frames before ``start`` are rendered only
        as far as the sensor's state needs: a frame's fault draws and the IMU's times)."""
        sensor = self.sensor_at(0)
        poses = self.keep_poses or self.writer is not None
        first = 0
        if start and self.lidar_faults is None and self.udp_faults is None:
            sensor.skip_to(start)  # no fault draws to replay: frames before start unmade
            first = start
        for k in range(first, self.frames):
            sf = sensor.frame(k)
            if k < start:
                continue
            yield self._compact(k, sf, sensor.meta.init_id, poses)

    def render_head(self, enough: Callable[[int, float], bool], workers: int,
                    upto: int | None = None) -> int:
        """A head start for :meth:`render_ahead`: this run's first frames rendered into the
        store by ``workers`` forked processes at once (:meth:`_render_parallel`), here and
        now, while nothing else runs yet, until ``enough(frames stored, frames a second so
        far)`` or ``upto`` (default: the run's) are stored; the renderer of
        :meth:`render_ahead` resumes from there. Frames stored now (0: none to render here:
        stored already, another process writes it, fault plans or noise in frame order, one
        worker, or too few frames for two blocks)."""
        key, doc = self.render_key, self.render_doc()
        upto = self.frames if upto is None else upto
        if (self.store is None or key is None or doc is None or workers < 2
                or not self.parallel_render() or mp.current_process().daemon):
            return 0
        writer = self.store.writer(key, doc, self.track_frames, wait=False)
        if writer is None:
            return 0
        start = writer.frames
        if upto - start < 2 * RENDER_BLOCK:
            writer.close()
            return 0
        t0 = time.monotonic()
        try:
            blocks = self._render_parallel(start, workers, end=upto)
            with contextlib.closing(blocks):  # (its workers stop at once)
                for k, packed in blocks:
                    writer.append_packed(k, packed)
                    d = k + 1 - start
                    if enough(k + 1, d / max(time.monotonic() - t0, 1e-9)):
                        break
            if writer.frames >= self.track_frames:
                writer.complete()
            return writer.frames - start
        finally:
            writer.close()

    def render_ahead(self, upto: int | None = None) -> RenderAhead | None:
        """Render this run's frames up to ``upto`` (default: the run's) into the store in a
        process of its own (:class:`RenderAhead`), from where a render cut short stopped,
        and send them from there as they come (:meth:`rendered` waits for a frame not yet
        stored). None where nothing is to render: the store holds the frames already (the
        run sends them), or another process is writing this render (the run renders
        live)."""
        key, doc = self.render_key, self.render_doc()
        if self.store is None or key is None or doc is None:
            return None
        upto = self.frames if upto is None else upto
        writer = self.store.writer(key, doc, self.track_frames, wait=False)
        if writer is None:  # complete meanwhile, or another process writes it
            self.stored = self.store.open(key)
            return None
        if writer.frames >= upto:  # a render cut short that holds this run's frames
            writer.close()
            self.stored = self.store.open(key, partial=True)
            return None
        ctx = mp.get_context("fork")
        self.emu.warm_up()  # the scene and the kernels made here, shared by the fork
        done, state = ctx.RawValue("q", writer.frames), ctx.RawValue("i", 0)
        proc = ctx.Process(target=_render_ahead, args=(self, writer, upto, done, state),
                           name="lidar-render", daemon=True)
        proc.start()
        writer.close()  # (this process's copies: the renderer holds the lock)
        self.stored = self.store.open(key, partial=True)
        self.ahead = RenderAhead(proc, done, state, upto)
        return self.ahead

    def _compact(self, k: int, sf: Any, init_id: int, poses: bool) -> RenderedFrame:
        """A sensor frame in the store's compact form."""
        fr = sf.result
        ids = counts = np.zeros(0, np.int64)
        labels = rows = b""
        if sf.sent:
            ts = fr.timestamps_ns
            labels = encode_labels_record(int(ts[0]), int(ts[-1]), fr.stem_id, fr.stem_id2)
            hit = fr.stem_id[fr.stem_id >= 0]
            if fr.stem_id2 is not None:  # the DUAL profile's second returns count too
                hit = np.concatenate([hit, fr.stem_id2[fr.stem_id2 >= 0]])
            per = np.bincount(hit, minlength=len(self.counts))
            ids = np.flatnonzero(per).astype(np.int64)
            counts = per[ids].astype(np.int64)
            if poses:
                rows = self._pose_rows(fr)
        return RenderedFrame(k, sf.datagrams, labels, rows, ids, counts, sf.events, sf.action,
                             init_id, fr)

    def _pose_rows(self, fr: FrameResult) -> bytes:
        """The sensor pose of a frame's columns as the store keeps them
        (:attr:`RenderedFrame.poses`): written as ``sensor_poses.csv`` rows only where a
        run keeps that file (:meth:`_take`)."""
        q = quaternions(fr.rotations)
        p = fr.positions + self.forest.origin
        return (fr.timestamps_ns.astype("<i8").tobytes()
                + np.hstack([p, q]).astype("<f8").tobytes())

    @staticmethod
    def _poses_csv_rows(poses: bytes) -> str:
        """``sensor_poses.csv``'s rows of :meth:`_pose_rows`' bytes."""
        n = len(poses) // 64
        t = np.frombuffer(poses[:8 * n], "<i8")
        v = np.frombuffer(poses[8 * n:], "<f8").reshape(n, 7)
        return pose_rows(t, v, (6, 6, 6, 9, 9, 9, 9))  # metres to the um, quaternions 1e-9

    def _take(self, rf: RenderedFrame) -> None:
        """A frame's bookkeeping, as it is yielded."""
        if rf.init_id != self.meta.init_id:
            self.meta = self.meta.with_changes(init_id=rf.init_id)
        self.last_events = rf.events
        self.last_sent = rf.sent
        if not rf.sent:
            return
        self.packets += self._packets_per_frame
        if len(rf.hit_ids):
            self._counts_for(int(rf.hit_ids.max()) + 1)[rf.hit_ids] += rf.hit_counts
        if self.keep_poses:
            self._poses.write(self._poses_csv_rows(rf.poses))

    def standing(self, at_ns: int) -> StandingEmulator:
        """The machine standing at the track's pose at ``at_ns``: a cycle of
        :data:`STANDING_CYCLE` frames rendered now, sent again with the times of any
        frame."""
        period = self.period_ns
        start = at_ns - STANDING_CYCLE * period if at_ns < self.track.t0_ns else at_ns
        cycle = self._stored_cycle(at_ns)
        kept = cycle is not None
        if cycle is None:
            emu = Os0Emulator(self.meta, self.scene, StandingPose(self.track, at_ns),
                              self.model, seed=self.forest.seed, start_ns=start,
                              threads=self.scene.caster.threads, sensor=self.sensor)
            cycle = [emu.frame(i) for i in range(STANDING_CYCLE)]
            self._store_cycle(at_ns, cycle)
        standing = StandingEmulator(cycle, start, self.track.t0_ns, period,
                                     self.meta.packet_format)
        standing.from_store = kept
        return standing

    def _cycle_path(self, at_ns: int) -> Path | None:
        """Where a standing cycle at ``at_ns`` is kept: beside the track's complete render in
        the store (the render's key decides its bytes as it does the track's), else
        nowhere."""
        if self.stored is None or not self.stored.complete:
            return None
        return self.stored.path / f"standing-{at_ns}.npz"

    def _stored_cycle(self, at_ns: int) -> list[FrameResult] | None:
        """The standing cycle kept in the store (seconds of rendering saved at a natural
        stand's power-on), or None; one that cannot be read is rendered again."""
        path = self._cycle_path(at_ns)
        if path is None or not path.exists():
            return None
        try:
            with np.load(path) as npz:  # each array read once (``npz[k]`` reads it anew)
                z = {k: npz[k] for k in npz.files}
            names = tuple(str(x) for x in z["field_names"])
            two = z.get("stem_id2")
            return [FrameResult(
                int(z["frame_index"][i]), z["timestamps_ns"][i], z["stem_id"][i],
                None if two is None else two[i], z["positions"][i],
                z["rotations"][i], z["packets"][i], self.meta.packet_format, names)
                for i in range(len(z["frame_index"]))]
        except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile):
            return None

    def _store_cycle(self, at_ns: int, cycle: list[FrameResult]) -> None:
        path = self._cycle_path(at_ns)
        if path is None or not cycle or cycle[0].packet_format != self.meta.packet_format:
            return
        arrays: dict[str, Any] = {
            "frame_index": np.array([fr.frame_index for fr in cycle]),
            "field_names": np.array(cycle[0].field_names),
            **{k: np.stack([getattr(fr, k) for fr in cycle])
               for k in ("timestamps_ns", "stem_id", "positions", "rotations", "packets")}}
        if cycle[0].stem_id2 is not None:
            arrays["stem_id2"] = np.stack([fr.stem_id2 for fr in cycle if fr.stem_id2 is not None])
        with contextlib.suppress(OSError, ValueError), atomic_path(path) as tmp, \
                open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    def on_air(self, air: OnAir, before: StandingEmulator, after: StandingEmulator
               ) -> Iterator[tuple[str, RenderedFrame]]:
        """An always-on sensor's frames from power-on (:class:`OnAir`), each with its phase:
        standing at the track's start (:meth:`standing`) ``unheard`` (before the run's
        decision: sent, not recorded, on the time line of power-on) and ``before`` the
        track (on the track's time line, after the clock's step), the ``track``
        (:meth:`rendered`, with its bookkeeping) and ``after`` it (standing where it
        stopped), endless. Standing frames carry no labels, poses nor returns: they are not
        scored."""
        period, t0 = self.period_ns, self.track.t0_ns
        crc = fast_crc_rows()
        last = -1  # the track's last frame_id
        if not air.track_over:
            last = yield from self._to_track_end(air, before, crc)
        end = t0 + self.frames * period
        sensor = Os0Sensor(after, self.meta, StandingPose(self.track, end), crc_rows=crc,
                           first_frame_id=last + 1 - self.frames, first_imu_ns=end)
        k = self.frames
        while air.after_frames < 0 or k < self.frames + air.after_frames:
            yield "after", self._standing_frame(sensor.frame(k))
            k += 1

    def _to_track_end(self, air: OnAir, before: StandingEmulator, crc: Any
                      ) -> Generator[tuple[str, RenderedFrame], None, int]:
        """:meth:`on_air`'s frames until the track's end; the track's last frame_id."""
        period, t0 = self.period_ns, self.track.t0_ns
        most = (t0 - air.power_on_ns) // period  # standing frames before, at the most
        pose = StandingPose(self.track, t0 - period)
        # frame_id counts the frames since power-on (0 first), on across the clock's step
        sensor = Os0Sensor(before, self.meta, pose, crc_rows=crc, first_frame_id=most,
                           first_imu_ns=air.power_on_ns)
        j, stepped = 0, False
        while True:
            at = int(air.track_at.value)
            if at < 0 and j >= most:  # the standing time ran out: the track starts now
                at = most
            if 0 <= at <= j:
                break
            if at >= 0 and not stepped and j >= int(air.step_at.value):
                stepped = True  # on the track's time line from here: k counts to its start
                sensor = Os0Sensor(before, self.meta, pose, crc_rows=crc, first_frame_id=at,
                                   first_imu_ns=t0 + (j - at) * period)
            k = j - at if stepped else j - most
            yield ("before" if stepped else "unheard"), self._standing_frame(sensor.frame(k))
            j += 1
        # the track's frames as rendered count from its first frame (the same bytes in every
        # run): moved on by the frames stood before it (until a re-initialisation restarts
        # the count), their CRCs rewritten
        fmt, lp = self.meta.packet_format, self.ports[0]
        shift, last = j, j - 1
        for rf in self.rendered():
            if rf.action == "reinit":
                shift = 0
            lidar = [i for i, d in enumerate(rf.datagrams) if d.port == lp]
            if lidar:
                fid = decode_lidar_packet(fmt, bytes(rf.datagrams[lidar[0]].payload),
                                          check_crc=False).frame_id
                last = (fid + shift) & 0xFFFF
                if shift and len(lidar) == fmt.packets_per_frame:  # one header write and
                    arr = np.frombuffer(b"".join(  # one CRC pass for the frame's packets
                        rf.datagrams[i].payload for i in lidar), np.uint8).reshape(
                        len(lidar), -1).copy()
                    finish_lidar_packets(fmt, arr, frame_id=last, init_id=rf.init_id,
                                         prod_sn=self.meta.prod_sn, crc_rows=crc)
                    dgs = list(rf.datagrams)
                    for row, i in enumerate(lidar):
                        d = dgs[i]
                        dgs[i] = Datagram(d.t_ns, d.port, arr[row].tobytes())
                    rf.datagrams = dgs
                elif shift:  # packets lost or doubled on the way (UDP faults): one by one
                    rf.datagrams = [Datagram(d.t_ns, d.port, shift_lidar_packet(
                        fmt, bytes(d.payload), shift, 0, crc)) if d.port == lp else d
                        for d in rf.datagrams]
            yield "track", rf
        return last

    def _standing_frame(self, sf: Any) -> RenderedFrame:
        none = np.zeros(0, np.int64)
        return RenderedFrame(sf.result.frame_index, sf.datagrams, b"", b"", none, none, [],
                             sf.action, self.meta.init_id)

    def datagrams(self) -> Iterator[tuple[FrameResult | None, list[Datagram]]]:
        """Each frame (the emulator's result; None for a stored frame) with the datagrams
        that leave the sensor for it (:meth:`rendered`)."""
        for rf in self.rendered():
            yield rf.result, rf.datagrams

    def labels_header(self) -> bytes:
        """``lidar_labels.bin``'s header: the image size and what each object id is (kept
        beside a complete render in the store: a natural stand's needs its scenery)."""
        path = self.stored.path / "labels_header.bin" if self.stored is not None and \
            self.stored.complete else None
        if path is not None and path.exists():
            with contextlib.suppress(OSError):
                return path.read_bytes()
        head = self._labels_header()
        if path is not None:
            with contextlib.suppress(OSError, ValueError):
                write_bytes_atomic(path, head)
        return head

    def _labels_header(self) -> bytes:
        sc = self.forest.scenery()
        comp = np.concatenate([[0], np.ones(self.n_stems)]).astype(np.uint8) \
            if sc is None else sc.component_of_id
        fmt = self.meta.packet_format
        return encode_labels_header(fmt.pixels_per_column, fmt.columns_per_frame,
                                    fmt.profile.returns > 1, self.n_stems, comp)

    def mark(self) -> tuple[np.ndarray, int, int]:
        """The bookkeeping so far (returns per stem, length of the poses CSV, packets), for
        :meth:`restore`."""
        return self.counts.copy(), self._poses.tell(), self.packets

    def poses_csv(self, upto: int | None = None) -> str:
        """``sensor_poses.csv`` so far (up to a :meth:`mark`'s length)."""
        text = self._poses.getvalue()
        return text if upto is None else text[:upto]

    def restore(self, counts: np.ndarray, poses_csv: str, packets: int) -> None:
        """The bookkeeping as of exactly the frames that were sent (a producer ran ahead)."""
        self.counts, self.packets = counts, packets
        self._poses = io.StringIO(poses_csv)
        self._poses.seek(0, io.SEEK_END)
        self._pw = csv.writer(self._poses, lineterminator="\n")

    def stems_seen(self) -> int:
        """Stems that got at least one return so far (their branches and foliage aside)."""
        return int(np.count_nonzero(self.counts[1:self.n_stems + 1]))

    def returns_by_component(self) -> dict[str, int]:
        """Returns so far by what they hit (ground, stem, and in natural stands branch,
        foliage, understory, dead wood, stump, boulder)."""
        from tcf_hil.world.forest.scenery import COMPONENTS

        sc = self.forest.scenery()
        if sc is None:
            return {"ground": int(self.counts[0]), "stem": int(self.counts[1:].sum())}
        per = np.bincount(sc.component_of_id,
                          weights=self._counts_for(len(sc.component_of_id)),
                          minlength=len(COMPONENTS))
        return {name: int(v) for name, v in zip(COMPONENTS, per.tolist(), strict=True)}

    def ground_truth(self) -> dict[str, Any]:
        """The forest's ground truth with the lidar returns each stem got so far (natural
        stands: also its branches' and foliage's, and the totals by component)."""
        gt = ground_truth(self.forest)
        n = self.n_stems
        sc = self.forest.scenery()
        natural = sc is not None
        if sc is not None:
            self._counts_for(len(sc.component_of_id))
        for o in gt["objects"]:
            o["returns"] = int(self.counts[o["id"]])
            if natural:
                o["returns_by_component"] = {"stem": o["returns"],
                                             "branch": int(self.counts[n + o["id"]]),
                                             "foliage": int(self.counts[2 * n + o["id"]])}
        if natural:
            gt["returns_by_component"] = self.returns_by_component()
        return gt

    def write_sidecars(self, out: Path) -> dict[str, Any]:
        """metadata.json, ground_truth.json (with returns), visibility.json, sensor_poses.csv."""
        ensure_dir(out)
        if self.keep_poses:
            write_bytes_atomic(out / "sensor_poses.csv", self._poses.getvalue().encode())
        write_bytes_atomic(out / "metadata.json", self.meta.dumps().encode())
        write_json_atomic(out / "ground_truth.json", self.ground_truth())
        c = self.counts
        vis: dict[str, Any] = {
            "frames": self.frames, "mode": self.meta.mode, "profile": self.meta.profile,
            "backend": self.backend, "sensor": self.sensor.preset, **self._scene_facts(),
            "terrain_returns": int(c[0]),
            "stem_returns": int(c[1:self.n_stems + 1].sum()), "stems_seen": self.stems_seen(),
            "stems_total": self.n_stems,
            "returns_per_stem": {str(i): int(v) for i, v in enumerate(c[:self.n_stems + 1])
                                 if i and v},
        }
        if self.forest.scenery() is not None:
            vis["returns_by_component"] = self.returns_by_component()
        write_json_atomic(out / "visibility.json", vis)
        return vis

    def _scene_facts(self) -> dict[str, str]:
        """How the scene casts stems and foliage (``visibility.json``): kept beside a
        complete render in the store, so that a run streamed from it does not build the
        scene (seconds for a natural stand) only to say so."""
        path = self.stored.path / "scene.json" if self.stored is not None and \
            self.stored.complete else None
        if path is not None and "scene" not in self.__dict__ and path.exists():
            with contextlib.suppress(OSError, ValueError):
                facts: dict[str, str] = json.loads(path.read_text())
                return facts
        sc = self.forest.scenery()
        facts = {"stems_geometry": "curves" if self.scene.curve_count else "mesh",
                 "foliage_as": ("volume" if self.scene.crown_count else "facets")
                 if sc is not None and len(sc.foliage) else "none"}
        if path is not None:
            with contextlib.suppress(OSError, ValueError):
                write_json_atomic(path, facts)
        return facts

    def result(self, out: Path | None, frames: int | None = None, **kw: Any) -> RecordResult:
        """``frames``: those that left (default: every frame of the run)."""
        return RecordResult(out, self.frames if frames is None else frames, self.packets,
                            int(self.counts.sum()),
                            self.stems_seen(), self.backend, **kw)


LABELS = "lidar_labels.bin"  # what each return hit (protocols.labels), beside lidar.pcap


def stream_lidar(scn: Scenario, *, sensor_ip: str = "127.0.0.1", dest: str = "127.0.0.1",
                 speed: float = 1.0, record: str | Path | None = None,
                 stop: threading.Event | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 realtime: bool = True, run: LidarRun | None = None,
                 clock: Any = None, pcap_in_place: bool = False,
                 forked: threading.Event | None = None,
                 on_fault: Callable[[FaultEvent], None] | None = None, pcap: bool = True,
                 route: Route | None = None,
                 on_sender: Callable[[SendStats], None] | None = None,
                 air: tuple[OnAir, Any, Any] | None = None,
                 on_track_end: Callable[[], None] | None = None,
                 on_air: Callable[[], None] | None = None,
                 **run_kw: Any) -> RecordResult:
    """Send the run live over UDP from ``sensor_ip`` to ``dest``, paced from the simulation
    clock (``speed`` 1.0 = real time, 0 = as fast as possible).

    Frames are ray-cast and encoded (or read from the render store) ahead in a separate,
    lower-priority process that writes them into a ring of shared-memory slots; a sender
    process of its own (:mod:`tcf_hil.devices._sender`) only waits, sends straight from
    shared memory and hands the slot back (nothing competes with the pacing loop for an
    interpreter lock, and no frame is copied through a pipe); this thread relays its
    callbacks. With ``record``, the
    sidecar files and an exact pcap of what was sent go there. Stops at the end of the track
    or when ``stop`` is set. ``run``: an already built :class:`LidarRun` (``run_kw`` are then
    ignored); ``clock``: a shared :class:`~emulators.harvester.SimClock` that decides when
    each packet is due (instead of the first packet's wall time; ``speed`` is the clock's).
    ``pcap_in_place``: write ``lidar.pcap`` under its final name as frames go out (the
    recorder of a run: a crash leaves every whole frame sent) instead of renaming it into
    place at the end. ``forked`` is set once the frame producer process exists.
    ``on_fault`` gets each injected fault event (the scenario's ``[faults]``) just before the
    frame it struck is sent; a re-initialisation's event carries the new ``init_id``.
    ``pcap``: with ``record``, also write ``lidar.pcap`` (off: the sidecar files only).
    ``route``: where the datagrams go now (the sensor's HTTP API moves it when a client
    sets ``udp_dest`` or the ports); the pcap keeps the destination the run was made with.
    ``on_sender`` gets the sender's live :class:`~emulators.lidar.SendStats` as it starts.
    The result's ``frames`` counts the track's frames that left with lidar packets (a
    re-initialisation's silence and dropped frames are not sent). ``air``: an always-on
    sensor (:class:`OnAir` with its standing machines before and after the track,
    :meth:`LidarRun.standing`): it sends from power-on, the track when the plan says, and
    then stands until ``stop`` (``on_track_end`` is told when the first frame after the
    track goes out); ``progress`` counts the track's frames. ``on_air`` is told when the
    first frame is ready and about to go out (power-on over).
    """
    run_kw.setdefault("udp_dest", dest)
    run = run or LidarRun(scn, **run_kw)
    if run.stored is None or not run.stored.complete or run.renders:
        # compiled before the fork: the first frame is not late (the first run on a
        # machine compiles; seconds). A run streamed from a complete render casts nothing.
        warm_up_kernels(run.meta, run.model, run.sensor)
        warm_up_poses()
        if run.stored is None or not run.stored.complete:
            run.emu  # noqa: B018  (the scene built before the fork: the producer shares it)
    # The track's first frame is the producer's first with sensor_poses.csv rows: their
    # kernel compiled there (importing numba: about a second on a loaded 2-core machine)
    # came 0.2 s late, the ring's lead spent on it; in the producer before its first frame,
    # the sensor's first frames came late instead. Here it delays power-on, not a packet.
    warm_up_pose_rows()
    dest = run.meta.udp_dest
    stop = stop or threading.Event()
    out = Path(record) if record is not None else None
    ring: FrameRing | None = None
    sender: SenderProcess | None = None
    with contextlib.ExitStack() as outputs:  # the pcap renamed into place only if all
        try:
            rec = _pcap_target(out, pcap, pcap_in_place, outputs, sensor_ip, dest)  # succeeds
            ring = FrameRing(run, rec, air, speed)
            # the pacing loop in a process of its own (tcf_hil.devices._sender): it does not
            # share an interpreter lock with the run's CAN node, HTTP API and recorder
            sender = SenderProcess(run, ring, sensor_ip, dest, speed=speed, realtime=realtime,
                                   clock=clock, route=route)
            if forked is not None:
                forked.set()
            if on_sender is not None:
                on_sender(sender.stats)
            report = sender.relay(stop, on_fault, progress, on_track_end, on_air)
        finally:
            if sender is not None:
                sender.close()
            if ring is not None:
                ring.close()
        if report["error"] is not None:  # no pcap of a failed run
            raise RuntimeError(f"lidar frame producer failed: {report['error']}")
    stats: SendStats = report["stats"]
    if out is not None:
        run.frames = report["track"]
        run.write_sidecars(out)
    track: dict[str, Any] = {}
    window: SendStats | None = report["window"]
    if window is not None:  # the track alone (standing frames around it)
        track = {"track_pacing_us": window.pacing_us(),
                 "track_late_1ms": window.late_over_us(1000),
                 "track_steal_ms_per_s": window.steal_ms_per_s}
    return run.result(out, frames=report["on_wire"], pacing_us=stats.pacing_us(),
                      refused=stats.refused, realtime=stats.realtime,
                      frames_late_from_producer=stats.late_frames,
                      late_frame_log=tuple(stats.late_frame_log),
                      sender_cpu_share=stats.cpu_s / stats.wall_s if stats.wall_s else 0.0,
                      **track)


def _pcap_target(out: Path | None, pcap: bool, in_place: bool, outputs: contextlib.ExitStack,
                 sensor_ip: str, dest: str) -> PcapTarget | None:
    """Where the producer writes the pcap and the labels of what is sent (None: nowhere):
    under their final names as frames go out (``in_place``), else temporary names that
    ``outputs`` renames into place when it closes without an error."""
    if out is not None:
        ensure_dir(out)
    if out is None or not pcap:
        return None
    path = out / "lidar.pcap" if in_place else \
        outputs.enter_context(atomic_path(out / "lidar.pcap"))
    lpath = out / LABELS if in_place else outputs.enter_context(atomic_path(out / LABELS))
    return PcapTarget(str(path), sensor_ip, dest, str(lpath))


def standing_after(run: LidarRun, track_over: bool = False) -> tuple[OnAir, Any, Any]:
    """An always-on plan for a sensor that streams its track at once and then stands where
    the track left it, sending, until stopped (as a real sensor on a parked machine);
    ``track_over``: the stands only (re-initialised after its track)."""
    ctx = mp.get_context("fork")
    period, t0 = run.period_ns, run.track.t0_ns
    air = OnAir(t0 - period, ctx.RawValue("q", 0), ctx.RawValue("q", 0), -1,
                track_over=track_over)
    after = run.standing(t0 + run.frames * period)
    return air, after, after  # (the track starts at once: nothing stands before it)

