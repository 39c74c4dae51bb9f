"""The reference onboard SIC: what a harvester's stem program does, on the wire only.

- lidar: Ouster UDP packets on the lidar port (decoded with :mod:`protocols.ouster`, CRC
  checked), the metadata from a file or the sensor's HTTP API;
- pose: the harvester's CANopen TPDOs, read through the node's EDS with canopen (datum and
  lidar mount by SDO);
- every column is put into the world with the pose interpolated at its own time stamp; the
  points above the ground go into a bounded voxel map (:class:`~tcf_hil.sic._map.StemMap`)
  whose tiles re-run the stem algorithm when they got enough new points: in a process of its
  own at a lower priority (:mod:`tcf_hil.sic._worker`), so a tile run never holds up a frame
  (``TCF_SIC_STEM_WORKER=0``: inline, between frames, within a time budget);
- the forest is published every ``publish_s`` and at the end of the stream (no packet for
  ``idle_s``; the machine standing still for ``stand_s`` of its pose time after it moved,
  as the lidar frames mapped show it (the end of a strip road, while an always-on sensor
  goes on sending); or
  SIGTERM/SIGINT): NDJSON on stdout, a file rewritten atomically, or an HTTP POST.
"""

from __future__ import annotations

import collections
import contextlib
import datetime as _dt
import json
import logging
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
import urllib.request
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from numpy.typing import NDArray

from protocols.harvester import DATUM, MOUNT, TIME_WRAP_US, eds_path, unwrap_time_us
from protocols.ouster import (
    AssembledFrame,
    AssemblerStats,
    FrameAssembler,
    PacketIdError,
    ProtocolError,
    SensorMetadata,
    beam_rays,
    decode_lidar_packets,
)
from tcf_hil._crc import fast_crc_rows
from tcf_hil._rotations import rotation_ypr
from tcf_hil.errors import SicError
from tcf_hil.sic._field import divergence_of, edge_widths
from tcf_hil.sic._map import StemMap
from tcf_hil.sic._stems import StemParams, stem_params
from tcf_hil.sic._voxelset import warm as warm_voxel_sets

FloatArray = NDArray[np.float64]
_Columns = tuple[NDArray[np.uint32], NDArray[np.int64], FloatArray]


def _log(msg: str) -> None:
    sys.stderr.write(f"sic: {msg}\n")
    sys.stderr.flush()


# ----------------------------------------------------------------------------------- config
@dataclass
class SicConfig:
    """Where the SIC finds its inputs and puts its output (defaults: the environment
    variables ``tcf-hil run`` sets; see README, "The SIC contract")."""

    metadata: str = ""  # file path, or empty to ask sensor_url
    sensor_url: str = ""  # http://HOST[:PORT] of the sensor's HTTP API
    lidar_bind: str = "127.0.0.1"
    lidar_port: int = 0  # 0: the metadata's udp_port_lidar
    can_interface: str = "socketcand"
    can_channel: str = "vcan0"
    can_host: str = "127.0.0.1"
    can_port: int = 29536
    node_id: int = 10
    eds: str = ""
    publish: str = "stdout"  # stdout | file:PATH | http://...
    preset: str = "field"
    publish_s: float = 2.0
    idle_s: float = 3.0
    # after SIGTERM/SIGINT, at most this long finishing the forest before the final one:
    # `tcf-hil run` waits 15 s after its SIGTERM before SIGKILL (run/_sic.py SIGTERM_WAIT_S)
    finish_s: float = 10.0
    # the machine standing still this long (pose time, s) after it moved: the drive is over
    # (longer than a multi-pass track's stop to change gear, 1 s in the presets)
    stand_s: float = 5.0
    voxel_m: float | None = None  # None: 0.03 m for tuned, 0.1 m for paper (its density)
    max_points: int = 12_000_000  # about 400 MB (x, y, z and width float32, and the voxel keys)
    max_seconds: float = 0.0  # stop after this long (0: no limit)
    pose_hold_s: float = 1.0  # a frame waits this long for the poses of its columns
    nmt_start_after_s: float = 2.0  # start a node left in PRE-OPERATIONAL (0: never)
    cluster_voxel_m: float | None = None  # None: 0.1 for the tuned preset, exact for paper
    # the stem algorithm in a process of its own at a lower priority (nice), so that frames
    # are never held up by a tile run (TCF_SIC_STEM_WORKER=0: inline, between frames)
    stem_worker: bool = True
    stem_worker_nice: int = 10

    @classmethod
    def from_env(cls, env: dict[str, str] | None = None) -> SicConfig:
        e = os.environ if env is None else env
        c = cls()
        pub = e.get("TCF_PUBLISH_URL") or (f"file:{e['TCF_PUBLISH_FILE']}"
                                           if e.get("TCF_PUBLISH_FILE") else "stdout")
        c.metadata = e.get("TCF_METADATA", "")
        c.sensor_url = e.get("TCF_SENSOR_URL", "")
        c.lidar_bind = e.get("TCF_LIDAR_BIND", c.lidar_bind)
        c.lidar_port = int(e.get("TCF_LIDAR_PORT", "0") or 0)
        c.can_interface = e.get("TCF_CAN_INTERFACE", c.can_interface)
        c.can_channel = e.get("TCF_CAN_CHANNEL", c.can_channel)
        c.can_host = e.get("TCF_CAN_HOST", c.can_host)
        c.can_port = int(e.get("TCF_CAN_PORT", str(c.can_port)) or 0)
        c.node_id = int(e.get("TCF_CAN_NODE_ID", str(c.node_id)))
        c.eds = e.get("TCF_EDS", "")
        c.publish = e.get("TCF_PUBLISH", pub)
        c.stem_worker = e.get("TCF_SIC_STEM_WORKER", "1").strip().lower() not in (
            "0", "false", "no", "off")
        return c

    def can_kwargs(self) -> dict[str, Any]:
        kw: dict[str, Any] = {"interface": self.can_interface, "channel": self.can_channel}
        if self.can_interface == "socketcand":
            kw.update(host=self.can_host, port=self.can_port)
        return kw


def load_metadata(cfg: SicConfig, timeout_s: float = 10.0) -> SensorMetadata:
    """From the file, else from the sensor's HTTP API (retrying until ``timeout_s``); a
    SicError where neither is given or the sensor does not answer in time."""
    if cfg.metadata:
        return SensorMetadata.loads(Path(cfg.metadata).read_text(encoding="utf-8"))
    if not cfg.sensor_url:
        raise SicError("sic: no metadata: set TCF_METADATA or TCF_SENSOR_URL "
                       "(--metadata / --sensor-url)")
    url = cfg.sensor_url.rstrip("/") + "/api/v1/sensor/metadata"
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2.0) as r:
                return SensorMetadata.loads(r.read().decode())
        except OSError as err:
            if time.monotonic() > deadline:
                raise SicError(f"sic: cannot read the metadata from {url}: {err}") from err
            time.sleep(0.2)


# ------------------------------------------------------------------------------------- pose
class PoseTrack:
    """Poses from the bus, interpolated at any time stamp (linear in position and in the
    unwrapped angles). Kept in a preallocated array; a frame interpolates on the latest
    ``window`` poses only (at 100 Hz, 40 s)."""

    def __init__(self, capacity: int = 60_000, window: int = 4096) -> None:
        self._lock = threading.Lock()
        self._buf = np.empty((capacity, 7))
        self._n = 0
        self.window = window
        self._last_us: int | None = None
        self.received = 0
        self._start: tuple[float, float] | None = None  # the first pose's x, y
        self.moved = False  # more than MOVED_M from the first pose, ever
        self._still: tuple[float, float, int] | None = None  # x, y and time it stood from

    MOVED_M = 0.5  # a machine that went this far from where it stood has driven
    STILL_M = 0.02  # within this of where it stopped, it stands (the pose's noise is below)

    def stood_still_s(self, seen_ns: float | None = None) -> float:
        """How long (pose time) the machine has stood still since it last moved; 0 until it
        has driven at all. With ``seen_ns`` (the latest lidar time stamp mapped), only as far
        as the lidar has shown it: the bus runs on the sensor's clock, but a sensor that
        falls behind (a loaded bench) still has the end of the drive to send."""
        with self._lock:
            if not self.moved or self._still is None or self._last_us is None:
                return 0.0
            last_us = float(self._last_us)
            if seen_ns is not None and self._n:
                last_us = min(last_us, (seen_ns + self._shift_ns(seen_ns)) / 1000.0)
            return max(0.0, (last_us - self._still[2]) / 1e6)

    def add(self, time_raw_us: int, x: float, y: float, z: float, heading_deg: float,
            pitch_deg: float, roll_deg: float) -> None:
        with self._lock:
            t_us = unwrap_time_us(time_raw_us, self._last_us)
            if self._last_us is not None and t_us <= self._last_us:
                return  # repeated or out of order: keep the track monotonic
            self._last_us = t_us
            if self._start is None:
                self._start = (x, y)
            elif not self.moved and math.hypot(x - self._start[0],
                                               y - self._start[1]) > self.MOVED_M:
                self.moved = True
            if self._still is None or math.hypot(x - self._still[0],
                                                 y - self._still[1]) > self.STILL_M:
                self._still = (x, y, t_us)
            yaw = math.radians(90.0 - heading_deg)
            if self._n:
                prev = float(self._buf[self._n - 1, 4])
                yaw = prev + (yaw - prev + math.pi) % (2 * math.pi) - math.pi
            if self._n == len(self._buf):  # full: keep the newer half
                half = len(self._buf) // 2
                self._buf[:half] = self._buf[self._n - half:self._n]
                self._n = half
            self._buf[self._n] = (t_us * 1000.0, x, y, z, yaw, math.radians(pitch_deg),
                                  math.radians(roll_deg))
            self._n += 1
            self.received += 1

    def _shift_ns(self, t_ns: float) -> float:
        """The pose time is a 32-bit microsecond count (unwrapped from the first pose on):
        the multiple of 2^32 us that brings a lidar time stamp nearest the latest pose."""
        last = float(self._buf[self._n - 1, 0])
        wrap = TIME_WRAP_US * 1000.0
        return round((last - t_ns) / wrap) * wrap

    def covers(self, t_ns: float) -> bool:
        with self._lock:
            if not self._n:
                return False
            return float(self._buf[self._n - 1, 0]) >= t_ns + self._shift_ns(t_ns)

    def at(self, t_ns: FloatArray) -> tuple[FloatArray, FloatArray] | None:
        """(positions (n, 3), rotations (n, 3, 3)) of the machine base at ``t_ns`` (lidar
        time stamps); None before the first two poses."""
        with self._lock:
            if self._n < 2:
                return None
            a = self._buf[max(0, self._n - self.window):self._n].copy()
            shift = self._shift_ns(float(np.max(t_ns)))
        t = np.asarray(t_ns, dtype=np.float64) + shift
        cols = [np.interp(t, a[:, 0], a[:, k]) for k in range(1, 7)]
        pos = np.column_stack(cols[:3])
        rot = rotation_ypr(cols[3], cols[4], cols[5])
        return pos, rot


class CanPose:
    """The harvester node on the bus through its EDS: TPDO1-3 of one SYNC make one pose."""

    def __init__(self, cfg: SicConfig, track: PoseTrack, network: Any = None) -> None:
        """``network``: a canopen Network fed by the caller (offline: frames handed to its
        ``notify``); None connects one to the bus of ``cfg``."""
        import canopen

        self.track = track
        kw = cfg.can_kwargs()
        self.bus_text = ":".join(str(kw[k]) for k in ("interface", "host", "port", "channel")
                                 if k in kw)
        if network is None:
            network = canopen.Network()
            network.connect(**kw)
        self.net = network
        self.node = self.net.add_node(cfg.node_id, cfg.eds or str(eds_path()))
        self.node.tpdo.read(from_od=True)
        self._part: dict[str, float] = {}
        self._fresh: set[int] = set()  # TPDOs received since the last complete pose
        self.incomplete = 0  # poses skipped because a TPDO of their SYNC was lost
        self.boot_ups = 0
        self.preop_since: float | None = None  # monotonic time the node was seen waiting
        for k in (1, 2, 3):
            self.node.tpdo[k].add_callback(self._on_pdo)
        self.net.subscribe(0x700 + cfg.node_id, self._on_heartbeat)
        self.datum = (0.0, 0.0, 0.0)
        self.mount = np.zeros(3)
        self.mount_rot = np.eye(3)

    def read_constants(self, timeout_s: float = 10.0) -> None:
        """Datum and lidar mount by SDO (retried while the node boots). canopen's own line
        for a timed-out read ("Transfer aborted by client with code 0x05040000") names
        neither the node nor the object: it is held back, and one line here says what was
        read from whom, how often it failed and why (a SicError once ``timeout_s`` is
        over)."""
        deadline = time.monotonic() + timeout_s
        sdo_log = logging.getLogger("canopen.sdo.client")
        level = sdo_log.level
        sdo_log.setLevel(logging.CRITICAL)
        tries = 0
        what = f"the datum (0x{DATUM:04X}) and lidar mount (0x{MOUNT:04X})"
        try:
            while True:
                try:
                    tries += 1
                    sdo = self.node.sdo
                    self.datum = tuple(float(sdo[DATUM][k].phys) for k in (1, 2, 3))  # type: ignore[assignment]
                    m = [float(sdo[MOUNT][k].phys) for k in range(1, 7)]
                    break
                except Exception as err:  # canopen raises SdoCommAbortedError/timeouts
                    if time.monotonic() > deadline:
                        raise SicError(
                            f"sic: the harvester node {self.node.id} does not answer SDO reads "
                            f"of {what} on {self.bus_text} after {tries} tries in "
                            f"{timeout_s:g} s: {err}") from err
                    if tries == 1:
                        _log(f"SDO read of {what} from node {self.node.id} on {self.bus_text} "
                             f"failed ({err}); retrying while the node boots")
                    time.sleep(0.2)
        finally:
            sdo_log.setLevel(level)
        if tries > 1:
            _log(f"SDO read of {what} from node {self.node.id} answered after {tries} tries")
        self.mount = np.array(m[:3])
        y, p, r = np.radians(m[3:])
        self.mount_rot = rotation_ypr(np.array([y]), np.array([p]), np.array([r]))[0]

    def _on_pdo(self, m: Any) -> None:
        """TPDO1 (x, y), TPDO2 (z, heading, pitch) and TPDO3 (roll, speed, time) of one SYNC
        make a pose; when one of them was lost, the parts left over from an older SYNC would
        make a wrong one, so that pose is skipped."""
        for v in m.map:
            self._part[v.name] = float(v.phys)
        kind = (m.cob_id - self.node.id) >> 7
        self._fresh.add(kind)
        if kind != 7:  # 0x380 >> 7: TPDO3 closes the pose
            return
        complete = {3, 5, 7} <= self._fresh
        self._fresh.clear()
        if not complete:
            self.incomplete += 1
            return
        p = self._part
        with contextlib.suppress(KeyError):
            self.track.add(int(p["Pose.Time"]), p["Pose.X"], p["Pose.Y"], p["Pose.Z"],
                           p["Pose.Heading"], p["Pose.Pitch"], p["Pose.Roll"])

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != 1:
            return
        state = data[0] & 0x7F
        if state == 0:
            self.boot_ups += 1
            _log(f"the harvester node {self.node.id} booted")
        if state in (0, 127):
            if self.preop_since is None:
                self.preop_since = time.monotonic()
        else:
            self.preop_since = None

    def start_if_waiting(self, after_s: float) -> bool:
        """Act as the NMT master of a machine without one: start the node when it has
        waited in PRE-OPERATIONAL (after a reset) for ``after_s``. Returns whether it did."""
        since = self.preop_since
        if since is None or time.monotonic() - since < after_s:
            return False
        self.preop_since = None
        with contextlib.suppress(Exception):
            self.net.send_message(0, bytes([1, self.node.id]))
            _log(f"the harvester node {self.node.id} waited in PRE-OPERATIONAL for "
                 f"{after_s:g} s: sent NMT start")
            return True
        return False

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.net.disconnect()


# ------------------------------------------------------------------------------------ lidar
@dataclass
class LidarStats:
    packets: int = 0
    bad_packets: int = 0
    frames: int = 0
    frames_lost: int = 0  # frame ids never seen (gaps) plus frames dropped when behind
    frames_dropped: int = 0  # complete frames dropped because processing fell behind
    incomplete: int = 0
    duplicates: int = 0  # packets that arrived again (or after their frame was handed on)
    frames_without_pose: int = 0  # no pose covered them within pose_hold_s: not mapped
    reinits: int = 0  # the sensor re-initialised (a new init_id): metadata read again
    last_packet: float = 0.0
    first_error: str = ""


class LidarReceiver(threading.Thread):
    """Receives lidar packets and hands whole frames (an (n, packet_bytes) uint8 array, in
    packet order) to a bounded queue; a full queue drops the oldest frame (counted).

    Packets are assembled by :class:`protocols.ouster.FrameAssembler`, with up to two
    frames open: a packet that arrives twice is counted and skipped, a packet overtaken by
    the next frame's still lands in its own frame, and a frame is handed on when it holds
    every packet of the sensor's column window or when a third frame begins (then as it is,
    counted incomplete). Frames go out in the order they began."""

    OPEN_FRAMES = 2

    def __init__(self, meta: SensorMetadata, bind: str, port: int, depth: int | None = None
                 ) -> None:
        super().__init__(name="sic-lidar", daemon=True)
        self.meta = meta
        self.fmt = meta.packet_format
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
            if opt is None:
                continue
            with contextlib.suppress(OSError):
                self.sock.setsockopt(socket.SOL_SOCKET, opt, 32 << 20)
                break
        self.sock.bind((bind, port))
        self.sock.settimeout(0.2)
        # 5 s of frames: the stem algorithm may hold the main thread for a while (a dense
        # tile with the exact radius graph), after which it catches up
        depth = depth or max(4, 5 * meta.frequency_hz)
        self.frames: queue.Queue[tuple[int, NDArray[np.uint8]] | None] = queue.Queue(depth)
        self.stats = LidarStats()
        self.stop = threading.Event()

    def run(self) -> None:
        asm = FrameAssembler(self.fmt, column_window=self.meta.column_window,
                             open_frames=self.OPEN_FRAMES)
        a, st = asm.stats, self.stats
        buf = bytearray(65536)
        view = memoryview(buf)
        while not self.stop.is_set():
            try:
                n = self.sock.recv_into(buf)
            except TimeoutError:
                continue
            except OSError:
                break
            st.last_packet = time.monotonic()
            out = asm.feed(view[:n])
            for frame in out:
                self._push(frame)
            if out or not a.packets % 64:
                self._count(a)
        for frame in asm.flush():
            self._push(frame)
        self._count(a)
        self._put(None)

    def _count(self, a: AssemblerStats) -> None:
        st = self.stats
        st.packets, st.bad_packets = a.packets, a.bad_size + a.bad_place
        st.duplicates, st.incomplete = a.duplicates + a.late, a.incomplete
        st.frames_lost = a.frames_lost + st.frames_dropped

    def _push(self, frame: AssembledFrame) -> None:
        self._put((frame.frame_id, frame.packets))

    def _put(self, item: tuple[int, NDArray[np.uint8]] | None) -> None:
        while True:
            try:
                self.frames.put_nowait(item)
                return
            except queue.Full:
                with contextlib.suppress(queue.Empty):
                    if self.frames.get_nowait() is not None:
                        self.stats.frames_dropped += 1

    def close(self) -> None:
        self.stop.set()
        self.join(timeout=2.0)
        self.sock.close()


# -------------------------------------------------------------------------------- publisher
class Publisher:
    """Sends each forest document: ``stdout`` (one JSON line), ``file:PATH`` (rewritten
    atomically) or an ``http://`` URL (POST, application/json)."""

    def __init__(self, target: str, out: TextIO | None = None) -> None:
        self.target = target
        self.out = out or sys.stdout
        self.count = 0
        self.failures = 0

    def publish(self, doc: dict[str, Any]) -> None:
        text = json.dumps(doc, separators=(",", ":"))
        try:
            if self.target == "stdout":
                self.out.write(text + "\n")
                self.out.flush()
            elif self.target.startswith("file:"):
                path = Path(self.target[5:])
                tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
                tmp.write_text(text, encoding="utf-8")
                os.replace(tmp, path)
            else:
                req = urllib.request.Request(self.target, data=text.encode(), method="POST",
                                             headers={"Content-Type": "application/json"})
                with urllib.request.urlopen(req, timeout=5.0) as r:
                    r.read()
            self.count += 1
        except OSError as err:
            self.failures += 1
            _log(f"publishing to {self.target} failed: {err}")


# ------------------------------------------------------------------------------------- main
@dataclass
class FrameCost:
    ms: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        if not self.ms:
            return {"frames": 0}
        a = np.array(self.ms)
        return {"frames": len(a), "p50_ms": round(float(np.median(a)), 3),
                "p99_ms": round(float(np.percentile(a, 99)), 3),
                "max_ms": round(float(a.max()), 3)}


@dataclass
class _Live:
    """A listening SIC's parts (:meth:`OnboardSic._open`): the lidar receiver, the pose from
    the bus and its track, the map and its stem worker (None: inline), the publisher and the
    mounted beams (origins, directions)."""

    rx: LidarReceiver
    can: CanPose
    track: PoseTrack
    smap: StemMap
    worker: Any
    pub: Publisher
    rays: tuple[FloatArray, FloatArray]


class OnboardSic:
    """Wires receiver, pose, map and publisher together; :meth:`run` until the end."""

    def __init__(self, cfg: SicConfig, params: StemParams | None = None) -> None:
        self.cfg = cfg
        cv = cfg.cluster_voxel_m
        if cv is None:
            cv = 0.0 if cfg.preset == "paper" else 0.1
        self.params = params or stem_params(cfg.preset, cluster_voxel_m=cv)
        # The paper ran its algorithm on about 1000 points per stem; its exact radius graph
        # on a 3 cm map of a whole pass (tens of thousands per stem) costs seconds per tile.
        # A 10 cm map gives it about the paper's density.
        self.voxel_m = cfg.voxel_m or (0.1 if cfg.preset == "paper" else 0.03)
        self.stop = threading.Event()
        self.cost = FrameCost()
        self.t_start = time.monotonic()
        self.stem_cost = FrameCost()
        self.worker: Any = None  # the stem worker while a run has one
        self.meta: SensorMetadata | None = None
        self.seen_ns: float | None = None  # the latest lidar time stamp put into the map
        self._last_reload = -1e9

    @staticmethod
    def mounted_rays(meta: SensorMetadata, mount: FloatArray, mount_rot: FloatArray
                     ) -> tuple[FloatArray, FloatArray]:
        """The SDK's ray model moved into the machine frame once: (origins, directions), each
        (3, H, W) by component, with the beam-origin offset folded into the origins (a
        return of encoded range r mm lies at origin + r / 1000 * direction)."""
        o, d = beam_rays(meta)
        o = o - (meta.lidar_origin_to_beam_origin_mm / 1000.0) * d
        om = o @ mount_rot.T + mount
        dm = d @ mount_rot.T
        return (np.ascontiguousarray(np.moveaxis(om, -1, 0)),
                np.ascontiguousarray(np.moveaxis(dm, -1, 0)))

    @staticmethod
    def world_points(range_mm: NDArray[np.uint32], cols: NDArray[np.int64],
                     pos: FloatArray, rot: FloatArray, rays: tuple[FloatArray, FloatArray]
                     ) -> FloatArray:
        """Returns (n, 3) in the local world: ``range_mm`` (H, k) of the columns ``cols``,
        ``pos`` (k, 3) and ``rot`` (k, 3, 3) the machine pose at each column's time."""
        om, dm = rays
        r = range_mm.astype(np.float64) * 1e-3
        hit = r > 0
        k = len(cols)
        at: NDArray[np.int64] | slice = cols
        if k and int(cols[0]) >= 0 and int(cols[-1]) - int(cols[0]) == k - 1 and (
                k == 1 or bool((np.diff(cols) == 1).all())):
            at = slice(int(cols[0]), int(cols[0]) + k)  # as a rule, a whole frame: views
        m = [om[c][:, at] + r * dm[c][:, at] for c in range(3)]  # machine frame (H, k)
        out = np.empty((int(hit.sum()), 3))
        for i in range(3):
            w = rot[:, i, 0] * m[0] + rot[:, i, 1] * m[1] + rot[:, i, 2] * m[2] + pos[:, i]
            out[:, i] = w[hit]
        return out

    def run(self) -> dict[str, Any]:
        """Listen, map and publish until the stream ends (or :attr:`stop`): the bus and the
        lidar port opened (:meth:`_open`), the frames mapped as they come
        (:meth:`_stream`), then every tile finished and the final forest published
        (:meth:`_finish`); returns the run's summary."""
        cfg = self.cfg
        # the map's compiled voxel sets, before the port is bound: compiled on a first
        # frame (a second or two where numba's cache is cold), they would hold it up
        warm_voxel_sets()
        meta = self.meta = load_metadata(cfg)
        track = PoseTrack()
        # on the bus first (imports, connection), then listen for lidar: a bench may start
        # the stream once the port is bound; the datum and mount come from the node by SDO
        can = CanPose(cfg, track)
        live: _Live | None = None
        self.t_start = time.monotonic()
        self.seen_ns = None
        try:
            live = self._open(meta, can, track)
            waiting = self._stream(live)
            self._finish(live, waiting)
        finally:
            if live is not None:
                if live.worker is not None:
                    for e in live.worker.errors:
                        _log(f"stem worker: {e}")
                    live.worker.close()
                live.rx.close()
            can.close()
        assert live is not None  # (an error above went on up)
        summary = self._summary(live.rx.stats, track, live.smap, live.pub)
        _log("done: " + json.dumps(summary))
        return summary

    def _open(self, meta: SensorMetadata, can: CanPose, track: PoseTrack) -> _Live:
        """The lidar port bound and listening, the node's constants read, the map (and its
        stem worker) made."""
        cfg = self.cfg
        port = cfg.lidar_port or meta.udp_port_lidar or 7502  # (the sensor's default port)
        pub = Publisher(cfg.publish)
        rx = LidarReceiver(meta, cfg.lidar_bind, port)
        worker: Any = None  # the stem algorithm's process (cfg.stem_worker)
        try:
            rx.start()
            can.read_constants()
            smap = StemMap(self.params, voxel_m=self.voxel_m, max_points=cfg.max_points,
                           datum=can.datum)
            if cfg.stem_worker:
                from tcf_hil.sic._worker import TileWorker

                worker = self.worker = TileWorker(self.params, nice=cfg.stem_worker_nice)
                smap.defer_runs = True
            _log(f"listening for {meta.mode} {meta.profile} on {cfg.lidar_bind}:{port}; "
                 f"pose from node {cfg.node_id} on {cfg.can_interface}:{cfg.can_channel}; "
                 f"preset {cfg.preset}; publishing to {cfg.publish}")
            rays = self.mounted_rays(meta, can.mount, can.mount_rot)
        except BaseException:
            if worker is not None:
                worker.close()
            rx.close()
            raise
        return _Live(rx, can, track, smap, worker, pub, rays)

    def _stream(self, live: _Live) -> collections.deque[tuple[float, _Columns]]:
        """Frames decoded and mapped as they come (the stem algorithm inline in the rest of
        each frame's time, or in its worker), the forest published every ``publish_s``,
        until the stream ends, the machine has stood after driving or :attr:`stop`; returns
        the decoded frames still waiting for their poses."""
        cfg = self.cfg
        rx, can, track, smap, worker, pub = (live.rx, live.can, live.track, live.smap,
                                             live.worker, live.pub)
        meta = self.meta
        assert meta is not None  # (read in run())
        fmt = meta.packet_format
        crc = fast_crc_rows()
        frame_budget = 1.0 / meta.frequency_hz
        next_pub = time.monotonic() + cfg.publish_s
        seen_data = False
        # decoded frames waiting for the poses of their columns (the pose of a frame's
        # last column comes with the next SYNC; a late or silent bus holds them longer)
        waiting: collections.deque[tuple[float, _Columns]] = collections.deque()
        while not self.stop.is_set():
            if cfg.max_seconds and time.monotonic() - self.t_start > cfg.max_seconds:
                break
            try:
                item = rx.frames.get(timeout=0.002 if waiting else 0.1)
            except queue.Empty:
                item = ...  # type: ignore[assignment]
            now = time.monotonic()
            if item is None:
                break
            if cfg.nmt_start_after_s:
                can.start_if_waiting(cfg.nmt_start_after_s)
            t0 = time.perf_counter()
            if item is not ...:
                seen_data = True
                columns = self._decode(item, fmt, self.meta or meta, crc, rx.stats)
                if columns is not None:
                    waiting.append((now, columns))
            mapped = False
            while waiting:
                if self._map(waiting[0][1], track, live.rays, smap, rx.stats):
                    waiting.popleft()
                    mapped = True
                elif now - waiting[0][0] > cfg.pose_hold_s:
                    waiting.popleft()
                    rx.stats.frames_without_pose += 1
                else:
                    break
            if item is not ... or mapped:
                if worker is not None:
                    # the stem worker's finished tiles in, the next out (the job's points
                    # gathered here count as the frame's cost)
                    worker.pump(smap)
                spent = time.perf_counter() - t0
                self.cost.ms.append(spent * 1000.0)
                # inline: the rest of this frame's time goes to the stem algorithm
                # (within 60 %)
                budget = 0.6 * frame_budget - spent
                if (worker is None and budget > 0.005 and rx.frames.empty()
                        and not waiting):
                    t1 = time.perf_counter()
                    if smap.update(budget):
                        self.stem_cost.ms.append((time.perf_counter() - t1) * 1000.0)
            elif seen_data and now - rx.stats.last_packet > cfg.idle_s:
                _log(f"no lidar packet for {cfg.idle_s:g} s: end of stream")
                break
            elif worker is not None:
                worker.pump(smap)
            elif not seen_data:
                smap.update(0.05)
            if now >= next_pub and seen_data:
                pub.publish(self._document(smap, rx.stats, track, final=False))
                next_pub = now + cfg.publish_s
            if (seen_data and cfg.stand_s > 0 and self.seen_ns is not None
                    and track.stood_still_s(self.seen_ns) >= cfg.stand_s):
                _log(f"the machine has stood still for {cfg.stand_s:g} s after driving: "
                     "end of the drive")
                rx.close()  # what the standing sensor sends on is not the drive's: no
                break  # frame of it is counted lost while the last tiles are finished
        return waiting

    def _finish(self, live: _Live, waiting: collections.deque[tuple[float, _Columns]]
                ) -> None:
        """The stream ended: what the poses cover of the frames still waiting mapped, every
        dirty tile finished, publishing as it goes (a bench that cannot wait still gets the
        most complete forest), then the final forest."""
        rx, track, smap, pub = live.rx, live.track, live.smap, live.pub
        # signalled (the bench ending the run): finished within finish_s, what is left of
        # the tiles published as it stands, so that the final forest comes before a SIGKILL
        until = time.monotonic() + self.cfg.finish_s if self.stop.is_set() else math.inf
        for _t, columns in waiting:
            if time.monotonic() >= until:
                break
            if not self._map(columns, track, live.rays, smap, rx.stats):
                rx.stats.frames_without_pose += 1
        if live.worker is not None:
            live.worker.drain(smap, progress=lambda: pub.publish(
                self._document(smap, rx.stats, track, final=False)),
                every_s=self.cfg.publish_s, until=until)
        while (smap.dirty_tiles() or smap.backlog) and time.monotonic() < until:
            smap.update(min(self.cfg.publish_s, max(0.0, until - time.monotonic())))
            if smap.dirty_tiles():
                pub.publish(self._document(smap, rx.stats, track, final=False))
        if time.monotonic() >= until:
            _log(f"signalled: the forest finished for {self.cfg.finish_s:g} s, "
                 f"{len(smap.dirty_tiles())} tiles left as they stand")
        pub.publish(self._document(smap, rx.stats, track, final=True))

    def _decode(self, item: tuple[int, NDArray[np.uint8]], fmt: Any, meta: SensorMetadata,
                crc: Any, st: LidarStats) -> _Columns | None:
        """A frame's valid columns: (range (H, k), column index (k), time stamp (k)); None
        for a frame that does not decode (counted)."""
        _fid, arr = item
        try:
            try:
                batch = decode_lidar_packets(fmt, arr, init_id=meta.init_id,
                                             prod_sn=meta.prod_sn, crc_rows=crc,
                                             fields=("RANGE",))
            except PacketIdError:
                # a re-initialised sensor has a new init_id: read its metadata again
                new = self._reload_metadata(meta)
                if new is None:
                    raise
                st.reinits += 1
                meta = self.meta = new
                batch = decode_lidar_packets(fmt, arr, init_id=meta.init_id,
                                             prod_sn=meta.prod_sn, crc_rows=crc,
                                             fields=("RANGE",))
        except ProtocolError as err:
            st.bad_packets += len(arr)
            if not st.first_error:
                st.first_error = str(err)
                _log(f"dropped a frame: {err}")
            return None
        valid = (batch.status.reshape(-1) & 1).astype(bool)
        cols = batch.measurement_id.reshape(-1).astype(np.int64)
        ts = batch.timestamps_ns.reshape(-1).astype(np.float64)
        return batch.fields["RANGE"][:, valid], cols[valid], ts[valid]

    def _reload_metadata(self, meta: SensorMetadata) -> SensorMetadata | None:
        """The sensor's metadata read again (at most twice a second), if its init_id changed
        and nothing else that the packets' layout depends on."""
        now = time.monotonic()
        if now - self._last_reload < 0.5:
            return None
        self._last_reload = now
        try:
            new = load_metadata(self.cfg, timeout_s=1.0)
        except (SicError, OSError, ProtocolError) as err:
            _log(f"packets with a new init_id, and the metadata cannot be read again: {err}")
            return None
        if new.init_id == meta.init_id:
            return None
        if (new.mode, new.profile) != (meta.mode, meta.profile):
            _log(f"the sensor now runs {new.mode} {new.profile}; this SIC keeps "
                 f"{meta.mode} {meta.profile} (restart it)")
            return None
        _log(f"the sensor re-initialised: init_id {meta.init_id} -> {new.init_id}")
        return new

    def _map(self, columns: _Columns, track: PoseTrack, rays: tuple[FloatArray, FloatArray],
             smap: StemMap, st: LidarStats) -> bool:
        """Put a decoded frame into the map with the pose at each column's time; False when
        the poses do not cover it yet."""
        rng, cols, ts = columns
        if not len(ts):
            return True
        if not track.covers(float(ts.max())):
            return False
        pose = track.at(ts)
        if pose is None:
            return False
        st.frames += 1
        self.seen_ns = float(ts.max()) if self.seen_ns is None else max(self.seen_ns,
                                                                         float(ts.max()))
        pts = self.world_points(rng, cols, pose[0], pose[1], rays)
        smap.add(pts, pose[0][-1, :2], self._widths(rng, cols))
        return True

    def _widths(self, rng: NDArray[np.uint32], cols: NDArray[np.int64]) -> FloatArray | None:
        """The edge half widths of a frame's returns (in :meth:`world_points`' order), where
        the preset flags mixed edge returns."""
        prm = self.params
        if not prm.edge_filter or self.meta is None:
            return None
        div = prm.divergence_deg or divergence_of(self.meta.prod_line)
        w = edge_widths(rng, cols, self.meta.columns, div, prm.edge_jump_m, prm.edge_reach_fwhm)
        out: FloatArray = w[rng > 0].astype(np.float64)
        return out

    def _frame(self, item: tuple[int, NDArray[np.uint8]], fmt: Any, meta: SensorMetadata,
               crc: Any, track: PoseTrack, rays: tuple[FloatArray, FloatArray],
               smap: StemMap, st: LidarStats) -> None:
        """One frame at once, its poses already held (offline: poses are fed first)."""
        columns = self._decode(item, fmt, meta, crc, st)
        if columns is not None and not self._map(columns, track, rays, smap, st):
            if len(columns[2]) and track.at(columns[2]) is not None:
                # the poses end a little before the frame's last columns: use what is held
                rng, cols, ts = columns
                pose = track.at(ts)
                assert pose is not None
                st.frames += 1
                smap.add(self.world_points(rng, cols, pose[0], pose[1], rays),
                         pose[0][-1, :2], self._widths(rng, cols))
            else:
                st.frames_without_pose += 1

    def _document(self, smap: StemMap, st: LidarStats, track: PoseTrack, *, final: bool
                  ) -> dict[str, Any]:
        doc = smap.forest(_dt.datetime.now(_dt.UTC).strftime("%Y%m%d_%H%M%S"))
        doc["algorithm"] = {"name": "tcf-hil reference onboard SIC", "preset": self.cfg.preset,
                            "params": asdict(self.params)}
        doc["sic"] = {"final": final, "frames": st.frames, "frames_lost": st.frames_lost,
                      "frames_dropped": st.frames_dropped,
                      "frames_without_pose": st.frames_without_pose,
                      "sensor_reinits": st.reinits, "bad_packets": st.bad_packets,
                      "poses": track.received, "map_points": smap.stats.points,
                      "frame_cost": self.cost.summary(), "stem_cost": self.stem_cost.summary(),
                      "stem_worker": self._worker_summary(),
                      "cpu_s": round(time.process_time(), 3),
                      "wall_s": round(time.monotonic() - self.t_start, 3)}
        return doc

    def _summary(self, st: LidarStats, track: PoseTrack, smap: Any, pub: Publisher
                 ) -> dict[str, Any]:
        return {"packets": st.packets, "bad_packets": st.bad_packets, "frames": st.frames,
                "frames_lost": st.frames_lost, "frames_dropped": st.frames_dropped,
                "frames_without_pose": st.frames_without_pose, "sensor_reinits": st.reinits,
                "incomplete_frames": st.incomplete, "duplicate_packets": st.duplicates,
                "poses": track.received,
                "publications": pub.count, "frame_cost": self.cost.summary(),
                "stem_cost": self.stem_cost.summary(), "stem_worker": self._worker_summary()}

    def _worker_summary(self) -> dict[str, Any] | None:
        w = self.worker
        if w is None:
            return None
        return {"runs": w.runs, "cpu_s": round(w.cpu_s, 3), "in_flight": len(w.in_flight),
                "errors": len(w.errors)}


def main_with(cfg: SicConfig) -> int:
    sic = OnboardSic(cfg)

    def on_signal(_sig: int, _frm: Any) -> None:
        sic.stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    sic.run()
    return 0
