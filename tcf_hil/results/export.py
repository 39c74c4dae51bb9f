"""A run's results in the files forestry and GIS tools read (``tcf-hil export``).

**The cloud** (``.las``, ``.laz``, ``.ply``, ``.pcd``): every return of ``lidar.pcap`` as the
sensor sent it (faults included), decoded with :mod:`protocols.ouster`, put into the world
by the sensor pose of its own column (``sensor_poses.csv``) and labelled with what it hit
(``lidar_labels.bin``, :mod:`protocols.labels`). One frame at a time: memory does not grow
with the run (PLY and PCD state the point count in their header, so their body goes to a
temporary file first).

Per point: world x, y, z (the scenario's ``plot.origin_m`` included: UTM-sized
coordinates), GPS time, intensity, return number and number of returns, classification, and
as extra dimensions the ground-truth ``stem_id`` the return belongs to (its stem, branches
or foliage; 0 none), the ``component`` it hit (``COMPONENTS`` codes; 255 nothing: an ambient
false return, classification 7; or not known: a frame without a label record,
classification 0) and the beam's ``ring``.

- LAS 1.4 point format 6 (ASPRS LAS 1.4 R15): X, Y, Z as int32 at a 1 mm scale with an
  offset rounded to the kilometre near the first sensor position, so a UTM origin keeps
  millimetres; GPS time is *adjusted standard GPS time* (GPS seconds - 1e9, global encoding
  bit 0 set) where the run's manifest ties the simulation clock to Unix time: Unix time at
  the simulation's t0 plus simulation time, as the harvester's CANopen TIME object tells it
  (at ``--speed`` 1 the wall clock; GPS = Unix - 315,964,800 s + 18 leap seconds, the
  offset since 2017-01-01 per IERS Bulletin C), else the simulation clock's seconds (bit 0
  clear); intensity is the REFLECTIVITY field scaled
  to 16 bits (the spec asks intensity normalised to 0-65535: 0-255 times 256);
  return numbers follow range (the nearer of a DUAL pixel's two returns is 1; Ouster sends
  the strongest first); classification by the ASPRS standard classes: 2 ground, 5 high
  vegetation (branches, foliage), 3 low vegetation (understory), 1 unclassified (dead wood,
  stumps, boulders), 7 noise (a return that hit nothing), and the stems as 64, the first
  user-definable class (64-255) since LAS 1.4 has none for stems. The extra dimensions are
  described in the Extra Bytes VLR, which CloudCompare, lidR and PDAL read. With ``epsg``
  the OGC coordinate system WKT record (:func:`crs_wkt`). LAZ through laspy's lazrs
  backend.
- PLY (binary little-endian, double x, y, z: CloudCompare offers to shift on load) carries
  the same fields by name; so does PCD (binary), but with float32 x, y, z from the same
  kilometre offset as LAS, stated in a header comment (``# tcf-hil offset X Y Z``): open3d
  reads float64 coordinates of a PCD as zeros (measured with open3d 0.20), and float32
  keeps 0.06 mm within a kilometre of the offset.

**The stems** (``.geojson``, ``.csv``): the ground truth and the SIC's scored forest, one
row or point feature each, with the outcome of scoring (:func:`stem_outcomes`).
"""

from __future__ import annotations

import contextlib
import csv
import io
import itertools
import math
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from protocols.labels import LabelsError, LabelsHeader, LabelsRecord, read_labels
from protocols.ouster import (
    FrameAssembler,
    MetadataError,
    ProtocolError,
    SensorMetadata,
    beam_rays,
    decode_lidar_packets,
)
from protocols.pcap import LIBPCAP_MAGICS, PcapError, UdpReader, libpcap_resync
from tcf_hil._io import atomic_path, read_json
from tcf_hil.errors import InputError
from tcf_hil.recording.rundir import RunDir
from tcf_hil.world.track import distance_to_track

if TYPE_CHECKING:
    from tcf_hil.evaluation import EvalConfig
    from tcf_hil.evaluation.scoring import ScoredForest

__all__ = ["CLOUD_DTYPE", "CLOUD_SUFFIXES", "STEM_SUFFIXES", "export", "run_cloud",
           "stem_outcomes"]

CLOUD_SUFFIXES = (".las", ".laz", ".ply", ".pcd")
STEM_SUFFIXES = (".geojson", ".csv")

# COMPONENTS codes (tcf_hil.world.forest.scenery) -> ASPRS class (see the module docstring)
_COMPONENT_CLASS = np.array([2, 64, 5, 5, 3, 1, 1, 1], np.uint8)
NO_OBJECT = 255  # component of a return that hit nothing (classification 7, noise)
GPS_MINUS_UNIX_S = 315_964_800 - 18  # Unix seconds at the GPS epoch, less the leap seconds
_EXTRA = (("stem_id", "u4", "ground-truth tree of the return (stem, branch, foliage); 0 none"),
          ("component", "u1", "what it hit: 0 ground 1 stem 2 branch 3 foliage 4 understory "
                              "5 dead wood 6 stump 7 boulder 255 nothing"),
          ("ring", "u1", "beam (row) of the OS0-64, 0 at the top"))

CLOUD_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("gps_time", "<f8"),
                        ("intensity", "<u2"), ("return_number", "u1"),
                        ("number_of_returns", "u1"), ("classification", "u1"),
                        *((n, t) for n, t, _ in _EXTRA)])
"""One exported point (packed): what every cloud format carries."""


def _rotations(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3, 3) rotation matrices of unit quaternions (w, x, y, z)."""
    w, x, y, z = (q[:, i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


class _Poses:
    """``sensor_poses.csv`` read ahead as the frames need it (rows in time order)."""

    CHUNK = 8192

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._fh: BinaryIO = open(path, "rb")
        except OSError as err:
            raise InputError(str(path), "", f"cannot read: {err}") from err
        head = self._fh.readline().decode("ascii", "replace").strip().split(",")
        if head != ["time_ns", "x", "y", "z", "qw", "qx", "qy", "qz"]:
            self._fh.close()
            raise InputError(str(path), "header", f"{head}; expected time_ns,x,y,z,qw,qx,qy,qz")
        self._body = self._fh.tell()
        self._line = 1
        # the first pose's time: an always-on sensor's frames before it are the machine
        # standing before the track (sent and recorded, not scored: no pose is kept for them)
        self.first_t: int | None = None
        self.t = np.zeros(0, np.int64)
        self.p = np.zeros((0, 7))
        self._done = False

    def close(self) -> None:
        self._fh.close()

    def skip_to(self, t: int) -> None:
        """Go straight to the rows from time ``t`` on (bisecting the file's bytes: rows are
        in time order), for a reader that samples frames far apart."""
        if self._done or (len(self.t) and self.t[-1] >= t):
            return
        fh = self._fh
        size = fh.seek(0, 2)

        def time_after(pos: int) -> tuple[int, int | None]:
            fh.seek(pos)
            if pos > self._body:
                fh.readline()  # the rest of a row cut by the seek
            at = fh.tell()
            line = fh.readline()
            try:
                return at, int(line.split(b",", 1)[0])
            except ValueError:
                return at, None  # the end, or a bad row: read it the slow way
        lo, hi = self._body, size
        while hi - lo > 1 << 14:
            mid = (lo + hi) // 2
            _, tm = time_after(mid)
            if tm is not None and tm < t:
                lo = mid
            else:
                hi = mid
        at, _ = time_after(lo)
        fh.seek(at)
        self._line = -1  # (line numbers are unknown after a skip)
        self.t = np.zeros(0, np.int64)
        self.p = np.zeros((0, 7))

    def _more(self) -> bool:
        lines = [ln for ln in itertools.islice(self._fh, self.CHUNK)]
        block_lines = [ln.rstrip(b"\r\n") for ln in lines]
        while block_lines and not block_lines[-1]:
            block_lines.pop()  # (a trailing empty line)
        if not block_lines:
            self._done = True
            return False
        try:  # the rows split and converted by numpy: 20 times the csv module's speed
            cells = np.array(b",".join(block_lines).split(b","))
            if len(cells) != 8 * len(block_lines):
                raise ValueError("not 8 columns")
            cells = cells.reshape(-1, 8)
            t = cells[:, 0].astype(np.int64)
            p = cells[:, 1:].astype(np.float64)
            if not np.isfinite(p).all():
                raise ValueError("not finite")
        except (ValueError, OverflowError) as err:
            block = [ln.decode("ascii", "replace").split(",") for ln in block_lines]
            for k, r in enumerate(block):  # the first bad line, for the message
                try:
                    int(r[0])
                    if len(r) != 8 or not all(np.isfinite([float(v) for v in r[1:]])):
                        raise ValueError(f"{len(r)} columns")
                except (ValueError, IndexError) as bad:
                    raise InputError(str(self.path), self._where(k),
                                     f"{','.join(r)!r} is not time_ns and 7 numbers "
                                     f"({bad})") from err
            raise InputError(str(self.path), self._where(0), str(err)) from err
        if self._line >= 0:
            self._line += len(block_lines)
        self.t = np.concatenate([self.t, t])
        self.p = np.vstack([self.p, p])
        return True

    def _where(self, k: int) -> str:
        return f"line {self._line + k + 1}" if self._line >= 0 else "a row"

    def at(self, ts: NDArray[np.uint64]) -> NDArray[np.float64]:
        """(n, 7) poses at the column time stamps ``ts`` (each must have its row)."""
        t = ts.astype(np.int64)
        while (not len(self.t) or self.t[-1] < t.max()) and not self._done:
            self._more()
        keep = np.searchsorted(self.t, t.min())  # rows before this frame are done with
        self.t, self.p = self.t[keep:], self.p[keep:]
        i = np.minimum(np.searchsorted(self.t, t), max(len(self.t) - 1, 0))
        if not len(self.t) or np.any(self.t[i] != t):
            bad = int(t[0] if not len(self.t) else t[self.t[i] != t][0])
            raise InputError(str(self.path), "time_ns",
                             f"no pose for the column time stamp {bad} of lidar.pcap")
        return self.p[i]


class LabelsReader:
    """``lidar_labels.bin`` walked alongside the capture (both in send order); a reader that
    follows a growing file opens it afresh each time (a record cut short at the end is not
    read yet)."""

    def __init__(self, path: Path, meta: SensorMetadata) -> None:
        self.path = path
        self.missing = 0  # frames of the capture without a record
        try:
            self._fh: BinaryIO = open(path, "rb")
        except OSError as err:
            raise InputError(str(path), "", f"cannot read: {err.strerror or err}") from err
        try:
            try:
                head, recs = read_labels(self._fh, str(path))
            except LabelsError as err:
                raise InputError(str(path), "", str(err).split(": ", 1)[-1]) from err
            fmt = meta.packet_format
            if (head.rows, head.columns) != (fmt.pixels_per_column, fmt.columns_per_frame):
                raise InputError(str(path), "header", f"{head.rows} x {head.columns} pixels; "
                                 f"the metadata's mode is {fmt.pixels_per_column} x "
                                 f"{fmt.columns_per_frame}")
            if head.dual != (fmt.profile.returns > 1):
                raise InputError(str(path), "header", f"{'two' if head.dual else 'one'} "
                                 f"return(s) per pixel; the metadata's profile "
                                 f"{fmt.profile.name} has {fmt.profile.returns}")
        except BaseException:
            self._fh.close()
            raise
        self.head: LabelsHeader = head
        self._recs = recs
        self._cur: LabelsRecord | None = None
        comp = head.component_of_id
        n = head.n_stems
        ids = np.arange(len(comp))
        # the tree each object belongs to: a stem, its branches (n + i), its foliage (2n + i)
        tree = np.where((ids >= 1) & (ids <= n), ids,
                        np.where((ids > n) & (ids <= 2 * n), ids - n,
                                 np.where((ids > 2 * n) & (ids <= 3 * n), ids - 2 * n, 0)))
        keep = (comp == 1) | (comp == 2) | (comp == 3)
        self.tree = np.where(keep, tree, 0).astype(np.uint32)
        self.comp = comp

    def close(self) -> None:
        self._fh.close()

    def frame(self, ts: NDArray[np.uint64], skip: bool = False) -> LabelsRecord | None:
        """The record whose column times hold ``ts`` (a frame's valid columns), or None;
        ``skip``: pass over earlier records without inflating them."""
        mid = int(np.median(ts.astype(np.int64)))
        try:
            if skip and (self._cur is None or self._cur.last_ns < mid):
                self._recs.skip_before(mid)
            while self._cur is None or self._cur.last_ns < mid:
                self._cur = next(self._recs)
        except StopIteration:
            self.missing += 1
            return None
        except LabelsError as err:
            raise InputError(str(self.path), "", str(err).split(": ", 1)[-1]) from err
        if self._cur.first_ns <= mid:
            return self._cur
        self.missing += 1
        return None

    def of(self, ids: NDArray[np.int32]) -> tuple[NDArray[np.uint32], NDArray[np.uint8],
                                                  NDArray[np.uint8]]:
        """(stem_id, component, classification) of object ids (-1: nothing)."""
        ok = (ids >= 0) & (ids < len(self.comp))
        j = np.where(ok, ids, 0)
        comp = np.where(ok, self.comp[j], NO_OBJECT).astype(np.uint8)
        cls = np.where(ok, _COMPONENT_CLASS[np.minimum(self.comp[j], 7)], 7).astype(np.uint8)
        return np.where(ok, self.tree[j], 0).astype(np.uint32), comp, cls


@dataclass(frozen=True)
class CloudInfo:
    """What :func:`run_cloud` found out before the first point."""

    meta: SensorMetadata
    labelled: bool
    gps_adjusted: bool  # GPS time is adjusted standard GPS time (else simulation seconds)
    first_position: NDArray[np.float64]  # the first column's sensor position, world
    labels: Any = None  # the labels being read (their ``missing`` count grows as frames go)


def _load_meta(run_dir: Path) -> SensorMetadata:
    path = run_dir / "metadata.json"
    try:
        return SensorMetadata.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(str(path), "", f"cannot read: {err}") from err
    except MetadataError as err:
        raise InputError(str(path), "", str(err)) from err


def _clock(run_dir: Path) -> tuple[int, int] | None:
    """(sim_t0_ns, unix_ns_at_sim_t0) of a run's manifest (a pcap-only recording: None)."""
    path = run_dir / "manifest.json"
    if not path.exists():
        return None
    clock = read_json(path).get("clock")
    try:
        return int(clock["sim_t0_ns"]), int(clock["unix_ns_at_sim_t0"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(str(path), "clock", f"missing or malformed ({err})") from err


def _check_run(run_dir: Path) -> None:
    RunDir(run_dir).require(RunDir.LIDAR, RunDir.METADATA, RunDir.POSES,
                            missing="not a run directory with its lidar recorded")


def run_cloud(run_dir: str | Path, *, every: int = 1,
              progress: Callable[[int, int], None] | None = None,
              sample: tuple[int, int] | None = None
              ) -> tuple[CloudInfo, Iterator[NDArray[np.void]]]:
    """The run's returns as :data:`CLOUD_DTYPE` records, one array per frame (every
    ``every``-th frame), and what is known before the first. ``progress(bytes read, bytes)``
    follows the capture. ``sample=(k, frames)``: instead about ``k`` frames spread evenly
    over a capture of ``frames`` frames, each read from a window of the file (a libpcap
    capture; a pcapng one is read whole, every ``frames // k``-th frame): the cost of
    ``k`` frames, not of the capture."""
    run = Path(run_dir)
    _check_run(run)
    meta = _load_meta(run)
    fmt = meta.packet_format
    clock = _clock(run)
    labels = LabelsReader(run / "lidar_labels.bin", meta) \
        if (run / "lidar_labels.bin").exists() else None
    try:
        poses = _Poses(run / "sensor_poses.csv")
        try:
            if not poses._more():
                raise InputError(str(run / "sensor_poses.csv"), "", "holds no pose")
        except BaseException:
            poses.close()
            raise
    except BaseException:
        if labels is not None:
            labels.close()
        raise
    first = poses.p[:1]
    poses.first_t = int(poses.t[0])
    info = CloudInfo(meta, labels is not None, clock is not None, first[0, :3].copy(), labels)
    return info, _frames(run, meta, fmt, clock, labels, poses, every, progress, sample)


def _frames(run: Path, meta: SensorMetadata, fmt: Any, clock: tuple[int, int] | None,
            labels: LabelsReader | None, poses: _Poses, every: int,
            progress: Callable[[int, int], None] | None,
            sample: tuple[int, int] | None = None) -> Iterator[NDArray[np.void]]:
    pcap = run / "lidar.pcap"
    size = pcap.stat().st_size
    decoder = FrameDecoder(meta, clock)
    asm = FrameAssembler(fmt, column_window=getattr(meta, "column_window", None))
    port = meta.udp_port_lidar
    try:
        try:
            fh = open(pcap, "rb")
        except OSError as err:
            raise InputError(str(pcap), "", f"cannot read: {err.strerror or err}") from err
        def assembled() -> Iterator[Any]:
            """The capture's lidar frames, in the order they began (the last ones at its end)."""
            try:
                for d in UdpReader(fh):
                    if d.dst_port == port:
                        yield from asm.feed(d.payload)
                        if progress:
                            progress(fh.tell(), size)
                yield from asm.flush()
            except PcapError as err:
                raise InputError(str(pcap), "", str(err)) from err

        with fh:
            head = fh.read(24)
            fh.seek(0)
            if sample is not None and head[:4] in LIBPCAP_MAGICS:
                frames = _sampled(fh, head, size, port, fmt, meta, *sample)
                skip = True
            else:
                if sample is not None:
                    every = max(1, sample[1] // max(sample[0], 1))
                frames = (fr for k, fr in enumerate(assembled()) if k % every == 0)
                skip = False
            for fr in frames:
                pts = decoder.points(fr, poses, labels, pcap, skip)
                if len(pts):
                    yield pts
        if progress:
            progress(size, size)
    finally:
        poses.close()
        if labels is not None:
            labels.close()


def last_frame(pcap: Path, meta: SensorMetadata) -> Any | None:
    """The last whole lidar frame of a libpcap capture that is being written (a live view
    of a run): assembled from a window of about the last three frames' bytes, read from the
    first record boundary in it (:func:`libpcap_resync`). None: no whole frame yet."""
    fmt = meta.packet_format
    packets = fmt.columns_per_frame // fmt.columns_per_packet
    frame_bytes = packets * (fmt.packet_bytes + 16 + 42 * (fmt.packet_bytes // 1400 + 1))
    try:
        size = pcap.stat().st_size
        with open(pcap, "rb") as fh:
            head = fh.read(24)
            if len(head) < 24 or head[:4] not in LIBPCAP_MAGICS:
                return None
            at = max(24, size - (3 * frame_bytes + (1 << 16)))
            fh.seek(at)
            buf = fh.read(size - at)
    except OSError:
        return None
    p = 0 if at == 24 else libpcap_resync(head, buf)
    if p is None:
        return None
    asm = FrameAssembler(fmt, column_window=getattr(meta, "column_window", None))
    got: list[Any] = []
    with contextlib.suppress(PcapError):  # the window's cut end
        for d in UdpReader(io.BytesIO(head + buf[p:])):
            if d.dst_port == meta.udp_port_lidar:
                got.extend(asm.feed(d.payload))  # each whole, or ended by the next one
    # the window's first frame began before it; the last one fed may still be growing
    return got[-1] if len(got) >= 2 or (got and at == 24) else None


def _sampled(fh: BinaryIO, head: bytes, size: int, port: int, fmt: Any,
             meta: SensorMetadata, k: int, frames: int) -> Iterator[Any]:
    """About ``k`` whole frames spread over a libpcap capture of about ``frames`` frames:
    each from a window of three frames' bytes, read from the first record boundary in it
    (:func:`libpcap_resync`); the window's first frame began before it and is dropped."""
    per = max(1.0, (size - 24) / max(frames, 1))
    win = int(3.2 * per) + (1 << 16)
    k = max(1, min(k, frames))
    last_id = None
    for i in range(k):
        at = 24 + int(max(0, size - 24 - win) * i / max(k - 1, 1))
        fh.seek(at)
        buf = fh.read(win)
        p = 0 if at == 24 else libpcap_resync(head, buf)
        if p is None:
            continue
        asm = FrameAssembler(fmt, column_window=getattr(meta, "column_window", None))
        got: list[Any] = []
        try:
            for d in UdpReader(io.BytesIO(head + buf[p:])):
                if d.dst_port == port:
                    got.extend(asm.feed(d.payload))
                    if len(got) >= 2:
                        break
        except PcapError:
            pass  # the window's cut end
        fr = got[0] if at == 24 and got else got[1] if len(got) >= 2 else None
        if fr is not None and fr.frame_id != last_id:
            last_id = fr.frame_id
            yield fr


class FrameDecoder:
    """A capture's assembled frames as world points (:data:`CLOUD_DTYPE`), what
    :func:`run_cloud` does frame by frame, for readers with poses and labels of their own (a
    live view following a run as it is written). ``clock``: (sim_t0_ns, unix_ns_at_sim_t0)
    for GPS time (None: simulation seconds)."""

    def __init__(self, meta: SensorMetadata, clock: tuple[int, int] | None = None) -> None:
        self.meta, self.fmt, self.clock = meta, meta.packet_format, clock
        self.origins, self.dirs = beam_rays(meta)
        self.n_off = meta.lidar_origin_to_beam_origin_mm / 1000.0
        self.dual = "RANGE2" in set(self.fmt.field_names)
        # Ouster's calibrated reflectivity is 0-255 in every profile (an 8-bit field, or the
        # low byte of LEGACY's 16 bits: Ouster's sensor docs, "Calibrated Reflectivity")
        self.scale = 256

    def points(self, fr: Any, poses: Any, labels: LabelsReader | None = None,
               source: Path = Path("lidar.pcap"), skip: bool = False) -> NDArray[np.void]:
        """Frame ``fr``'s returns. ``poses``: ``at(ts)`` gives the sensor pose (n, 7: x, y,
        z, qw, qx, qy, qz, world) at column times ``ts``, ``first_t`` the first pose's time
        (earlier frames: none) and ``skip_to(t)``; ``labels``: what each return hit."""
        return _frame_points(fr, self.fmt, self.meta, self.origins, self.dirs, self.n_off,
                             self.fmt.pixels_per_column, self.dual, self.scale, self.clock,
                             labels, poses, source, skip)


def _frame_points(fr: Any, fmt: Any, meta: SensorMetadata, origins: NDArray[np.float64],
                  dirs: NDArray[np.float64], n_off: float, H: int, dual: bool, scale: int,
                  clock: tuple[int, int] | None, labels: LabelsReader | None,
                  poses: _Poses, pcap: Path, skip: bool = False) -> NDArray[np.void]:
    want = ["RANGE", "REFLECTIVITY"] + (["RANGE2", "REFLECTIVITY2"] if dual else [])
    try:
        b = decode_lidar_packets(fmt, fr.packets, check_crc=False,
                                 fields=[w for w in want if w in fmt.field_names])
    except ProtocolError as err:
        raise InputError(str(pcap), f"frame {fr.frame_id}", str(err)) from err
    mid = b.measurement_id.reshape(-1).astype(np.int64)
    ok = (b.status.reshape(-1) & 1).astype(bool)
    ts = b.timestamps_ns.reshape(-1)[ok]
    cols = np.flatnonzero(ok)
    if not len(cols):
        return np.zeros(0, CLOUD_DTYPE)
    m = mid[cols]
    if poses.first_t is not None and int(ts.max()) < poses.first_t:
        return np.zeros(0, CLOUD_DTYPE)  # the machine standing before the track
    if skip:
        poses.skip_to(int(ts.min()))
    pose = poses.at(ts)
    rot = _rotations(pose[:, 3:])
    rec = labels.frame(ts, skip) if labels is not None else None
    out = []
    returns = [("RANGE", "REFLECTIVITY", None if rec is None else rec.ids)]
    if dual:
        returns.append(("RANGE2", "REFLECTIVITY2", None if rec is None else rec.ids2))
    ranges = [b.fields[r][:, cols].astype(np.float64) / 1000.0 for r, _, _ in returns]
    n_ret = (ranges[0] > 0).astype(np.uint8) + (ranges[1] > 0) if dual else None
    nearer2 = (ranges[1] > 0) & ((ranges[0] == 0) | (ranges[1] < ranges[0])) if dual else None
    for k, ((_r, refl, ids), rng) in enumerate(zip(returns, ranges, strict=True)):
        hit = rng > 0
        if not hit.any():
            continue
        rows, j = np.nonzero(hit)
        mm = m[j]
        r = rng[rows, j]
        p = origins[rows, mm] + (r - n_off)[:, None] * dirs[rows, mm]
        world = np.einsum("nij,nj->ni", rot[j], p) + pose[j, :3]
        pts = np.zeros(len(r), CLOUD_DTYPE)
        pts["x"], pts["y"], pts["z"] = world[:, 0], world[:, 1], world[:, 2]
        t = ts[j].astype(np.int64)
        if clock is not None:
            unix_ns = clock[1] + (t - clock[0])
            pts["gps_time"] = (unix_ns // 1000) / 1e6 - GPS_MINUS_UNIX_S - 1e9
        else:
            pts["gps_time"] = t / 1e9
        inten = b.fields[refl][rows, j].astype(np.int64) * scale \
            if refl in b.fields else np.zeros(len(r), np.int64)
        pts["intensity"] = np.minimum(inten, 65535)
        second = k == 1
        if nearer2 is None or n_ret is None:
            pts["return_number"] = 1
            pts["number_of_returns"] = 1
        else:
            first_is_nearer = ~nearer2[rows, j]
            pts["return_number"] = np.where(first_is_nearer != second, 1, 2)
            pts["number_of_returns"] = n_ret[rows, j]
        pts["ring"] = rows
        if ids is not None and labels is not None:
            sid, comp, cls = labels.of(ids[rows, mm])
            pts["stem_id"], pts["component"], pts["classification"] = sid, comp, cls
        else:
            pts["component"] = NO_OBJECT
            pts["classification"] = 1 if labels is None else 0
        out.append(pts)
    return np.concatenate(out) if out else np.zeros(0, CLOUD_DTYPE)


# ---------------------------------------------------------------- writers


PCD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                      *((n, CLOUD_DTYPE.fields[n][0]) for n in CLOUD_DTYPE.names[3:]  # type: ignore[index]
                        )])
"""PCD's points: float32 x, y, z from the offset (open3d reads no float64 coordinates)."""


def _offset(info: CloudInfo) -> NDArray[np.float64]:
    """The kilometre near the first sensor position (z: 0): LAS's offset, PCD's origin."""
    return kilometre_offset(info.first_position)


def kilometre_offset(position: NDArray[np.float64]) -> NDArray[np.float64]:
    """The kilometre near ``position`` (z: 0): what the exports subtract so that float32 and
    int32 coordinates keep their millimetres at UTM-sized origins."""
    off = np.round(np.asarray(position, np.float64)[:3] / 1000.0) * 1000.0
    off[2] = 0.0
    return off


def _local32(pts: NDArray[np.void], off: NDArray[np.float64]) -> NDArray[np.void]:
    out = np.zeros(len(pts), PCD_DTYPE)
    for i, k in enumerate("xyz"):
        out[k] = pts[k] - off[i]
    for name in PCD_DTYPE.names[3:]:  # type: ignore[index]
        out[name] = pts[name]
    return out


def crs_wkt(epsg: int) -> str:
    """The coordinate system EPSG:``epsg`` as OGC WKT 1 (OGC 01-009, the form LAS 1.4 R15
    names for its WKT record; GDAL's flavour, which PDAL, CloudCompare, lidR and QGIS read),
    from PROJ's database through pyproj. An unknown code is an :class:`InputError` naming
    ``--epsg``."""
    import pyproj

    try:
        crs = pyproj.CRS.from_epsg(epsg)
    except pyproj.exceptions.CRSError as err:
        raise InputError("--epsg", "", f"EPSG:{epsg} is not a coordinate system PROJ knows "
                         f"({err})") from err
    wkt = crs.to_wkt(pyproj.enums.WktVersion.WKT1_GDAL)
    if wkt is None:
        raise InputError("--epsg", "", f"EPSG:{epsg} has no WKT 1 form")
    return str(wkt)


def _las_header(info: CloudInfo, laspy: Any, epsg: int | None = None) -> Any:
    from tcf_hil import __version__

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims([laspy.ExtraBytesParams(name=n, type=np.dtype(t), description=d[:31])
                           for n, t, d in _EXTRA])
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = _offset(info)
    header.global_encoding.gps_time_type = (laspy.header.GpsTimeType.STANDARD
                                            if info.gps_adjusted
                                            else laspy.header.GpsTimeType.WEEK_TIME)
    header.global_encoding.wkt = True  # LAS 1.4 R15: required with point formats 6-10
    if epsg is not None:  # the OGC coordinate system WKT record (LASF_Projection, 2112)
        from laspy.vlrs.known import WktCoordinateSystemVlr

        header.vlrs.append(WktCoordinateSystemVlr(crs_wkt(epsg)))
    header.system_identifier = "tcf-hil emulated Ouster OS0-64"
    header.generating_software = f"tcf-hil {__version__}"
    return header


def _write_las(path: Path, info: CloudInfo, frames: Iterator[NDArray[np.void]],
               compress: bool, epsg: int | None = None) -> int:
    import laspy

    header = _las_header(info, laspy, epsg)
    n = 0
    with atomic_path(path) as tmp, laspy.open(tmp, mode="w", header=header,
                                              do_compress=compress) as w:
        for pts in frames:
            rec = laspy.ScaleAwarePointRecord.zeros(len(pts), header=header)
            rec.x, rec.y, rec.z = pts["x"], pts["y"], pts["z"]
            rec.gps_time = pts["gps_time"]
            rec.intensity = pts["intensity"]
            rec.return_number = pts["return_number"]
            rec.number_of_returns = pts["number_of_returns"]
            rec.classification = pts["classification"]
            for name, _, _ in _EXTRA:
                rec[name] = pts[name]
            w.write_points(rec)
            n += len(pts)
    return n


def _write_headed(path: Path, frames: Iterator[NDArray[np.void]],
                  header: Callable[[int], bytes]) -> int:
    """A body streamed to a temporary file, then the header (which needs the count)."""
    n = 0
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=path.parent) as body:
        for pts in frames:
            body.write(np.ascontiguousarray(pts).tobytes())
            n += len(pts)
        body.seek(0)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            fh.write(header(n))
            shutil.copyfileobj(body, fh, 1 << 22)
    return n


# ---------------------------------------------------------------- stems


def track_xy(run: Path, step: int = 64) -> NDArray[np.float64]:
    """The sensor's horizontal track (every ``step``-th column pose, and the last)."""
    path = run / "sensor_poses.csv"
    if not path.exists():
        return np.zeros((0, 2))
    lines = path.read_bytes().split(b"\n")[1:]  # (the rows split at C speed; few parsed)
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        return np.zeros((0, 2))
    pick = lines[::step] + ([lines[-1]] if (len(lines) - 1) % step else [])
    xy = []
    for r in pick:
        f = r.split(b",")
        if len(f) >= 3:
            try:
                xy.append((float(f[1]), float(f[2])))
            except ValueError:
                continue
    return np.array(xy).reshape(-1, 2)


def sensor_poses(run: Path, step: int = 256) -> NDArray[np.float64]:
    """Every ``step``-th row of ``sensor_poses.csv`` (and the last) as (n, 9): time (ns,
    the run's simulation clock), x, y, z, qw, qx, qy, qz and the row's Unix time (ns; the
    simulation time where the run has no clock)."""
    path = run / "sensor_poses.csv"
    if not path.exists():
        return np.zeros((0, 9))
    rows: list[list[float]] = []
    last: bytes = b""
    with open(path, "rb") as fh:  # (a line at a time: a long run's file is gigabytes)
        fh.readline()
        for k, line in enumerate(fh):
            last = line
            if k % step:
                continue
            last = b""
            _pose_row(line, rows)
    if last:
        _pose_row(last, rows)
    out = np.zeros((len(rows), 9))
    if rows:
        out[:, :8] = rows
        clock = _clock(run)
        out[:, 8] = out[:, 0] if clock is None else clock[1] + (out[:, 0] - clock[0])
    return out


def _pose_row(line: bytes, rows: list[list[float]]) -> None:
    f = line.split(b",")
    if len(f) == 8:
        try:
            rows.append([float(v) for v in f])
        except ValueError:
            pass


def publication_outcomes(run_dir: str | Path, publication: Path,
                         gt_doc: dict[str, Any] | None = None,
                         track: NDArray[np.float64] | None = None) -> list[dict[str, Any]]:
    """The stems of one of the SIC's publications (``sic/NNNN.json``) with their outcome
    (``matched``, ``false_positive``) as the run's scoring matches them (``gt_doc``,
    ``track``: the truth and :func:`track_xy` when the caller has read them already)."""
    run = Path(run_dir)
    scored = scored_forest(run, gt_doc, publication=publication)
    return _sic_rows(scored, track_xy(run) if track is None else track)


def live_outcomes(gt_doc: dict[str, Any], publication: Path, track: NDArray[np.float64],
                  cfg: EvalConfig | None = None
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Any]]:
    """The truth's stems and one publication's with their outcomes, and the publication's
    score (``wc_all``, ``wc_seen``, ``f1_all``, ``f1_seen``), for a view while the run is
    under way (``track``: the track's (n, 2) points; ``gt_doc`` without return counts: a
    stem not matched yet is ``missed_seen``; ``cfg``: the scoring's, default
    :class:`~tcf_hil.evaluation.EvalConfig`)."""
    from tcf_hil.evaluation import EvalConfig
    from tcf_hil.evaluation.scoring import ScoredForest, score_forest
    from tcf_hil.recording.stems_json import stem_table

    cfg = cfg or EvalConfig()
    obs_doc = read_json(publication)
    obs = stem_table(obs_doc, str(publication), "observed")
    scores = score_forest(gt_doc, obs, cfg, "ground truth")
    scored = ScoredForest(scores, obs, obs_doc, gt_doc, cfg)
    score = {"wc_all": scores.all.metrics["evaluation_score_percent"],
             "wc_seen": scores.seen.metrics["evaluation_score_percent"],
             "f1_all": scores.all.metrics["f1"], "f1_seen": scores.seen.metrics["f1"]}
    return _truth_rows(scored, track), _sic_rows(scored, track), score


def stem_outcomes(run_dir: str | Path, gt_doc: dict[str, Any] | None = None,
                  track: NDArray[np.float64] | None = None, scored: ScoredForest | None = None
                  ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every ground-truth stem and every stem of the SIC's scored forest with the outcome
    of scoring (the run's own configuration from ``score.json``): a ground-truth stem is
    ``correct`` (matched, class right), ``misclassified``, ``missed_seen`` (returns, no
    match) or ``missed_unseen`` (no return); an observed stem ``matched`` or
    ``false_positive``. Both with their horizontal distance from the track. A missed stem
    says ``why``: ``not seen`` (no return), ``merged with a neighbour`` (a SIC stem lies
    within the matching distance but was matched to another tree), ``few returns`` (fewer
    than the 10th percentile of the returns of the stems the SIC found: the run's own
    yardstick, not a fixed count) or ``seen, not found``. The truth is the run's
    ``ground_truth.json`` or, for a field recording, its ``inventory.csv`` (``gt_doc``,
    ``track``: the truth and :func:`track_xy` when the caller has read them already).
    ``scored``: the final forest as the run scored it (a run hands it over, so that a
    forest is scored once); without it, it is scored again from the run directory."""
    run = Path(run_dir)
    if not run.is_dir():
        raise InputError(str(run), "", "not a directory (a run directory is expected)")
    if scored is None:
        scored = scored_forest(run, gt_doc)
    if track is None:
        track = track_xy(run)
    return _truth_rows(scored, track), _sic_rows(scored, track)


def scored_forest(run_dir: str | Path, gt_doc: dict[str, Any] | None = None, *,
                  publication: Path | None = None) -> ScoredForest:
    """The final forest of the run in ``run_dir`` scored again from its files: the truth
    (``gt_doc``, else ground_truth.json or inventory.csv), the publication ``score.json``
    names (or ``publication``) and the configuration it was scored with."""
    from tcf_hil.evaluation.scoring import ScoredForest, empty_forest, score_forest
    from tcf_hil.recording.stems_json import stem_table

    run = Path(run_dir)
    gt_doc, gt_path = run_truth(run, gt_doc)
    score = read_json(run / "score.json") if (run / "score.json").exists() else {}
    cfg = _eval_config(score, run / "score.json")
    n_pub = score.get("scored_publication")
    obs = empty_forest()
    obs_doc: dict[str, Any] = {"objects": []}
    if publication is not None:
        obs_doc = read_json(publication)
        obs = stem_table(obs_doc, str(publication), "observed")
    elif n_pub is not None:
        pub = next((p for p in sorted((run / "sic").glob("*.json"))
                    if p.stem.isdigit() and int(p.stem) == int(n_pub)), None)
        if pub is None:
            raise InputError(str(run / "score.json"), "scored_publication",
                             f"{n_pub}: no such file under sic/")
        obs_doc = read_json(pub)
        obs = stem_table(obs_doc, str(pub), "observed")
    return ScoredForest(score_forest(gt_doc, obs, cfg, str(gt_path)), obs, obs_doc, gt_doc,
                        cfg)


def run_truth(run: Path, gt_doc: dict[str, Any] | None = None
              ) -> tuple[dict[str, Any], Path]:
    """The run's truth document and its file: ground_truth.json, else a field recording's
    inventory.csv."""
    gt_path = run / "ground_truth.json"
    if gt_doc is not None:
        return gt_doc, gt_path if gt_path.exists() else run / "inventory.csv"
    if gt_path.exists():
        return read_json(gt_path), gt_path
    if (run / "inventory.csv").exists():
        from tcf_hil.recording.inventory import read_inventory

        return read_inventory(run / "inventory.csv"), run / "inventory.csv"
    raise InputError(str(gt_path), "", "missing (and no inventory.csv): not a run directory")


def _eval_config(score: dict[str, Any], path: Path) -> EvalConfig:
    """The configuration a run was scored with (``score.json``'s ``all_trees.config``)."""
    from tcf_hil.evaluation import EvalConfig

    conf = (score.get("all_trees") or {}).get("config")
    if not isinstance(conf, dict):
        return EvalConfig()
    try:
        return EvalConfig(match=conf["match"], max_distance_m=float(conf["max_distance_m"]),
                          weights=tuple(conf["weights"]), credits=tuple(conf["credits"]))
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(str(path), "all_trees.config", str(err)) from err


def _missed_why(i: int, returns: Any, scored: ScoredForest, match_of_obs: dict[int, int],
                near_obs: Any, few: float) -> str:
    """Why ground-truth stem ``i`` was missed (see :func:`stem_outcomes`)."""
    gt, obs = scored.scores.gt_all, scored.forest
    if returns == 0:
        return "not seen"
    taken = [] if near_obs is None else [
        k for k in near_obs.query_ball_point(gt.xyz[i, :2], scored.config.max_distance_m)
        if k in match_of_obs]
    if taken:
        k = min(taken, key=lambda k: float(np.hypot(*(obs.xyz[k, :2] - gt.xyz[i, :2]))))
        return (f"merged with a neighbour (SIC stem {obs.ids[k]} went to tree "
                f"{gt.ids[match_of_obs[k]]})")
    if isinstance(returns, int) and returns < few:
        return "few returns"
    return "not found" if returns is None else "seen, not found"


def _truth_rows(scored: ScoredForest, track: NDArray[np.float64]) -> list[dict[str, Any]]:
    ev, gt, obs = scored.scores.all, scored.scores.gt_all, scored.forest
    match_of_gt = dict(zip(ev.pairs[:, 0].tolist(), ev.pairs[:, 1].tolist(), strict=True))
    match_of_obs = {o: g for g, o in match_of_gt.items()}
    g_objs = scored.truth_doc.get("objects", [])
    gd = distance_to_track(gt.xyz[:, :2], track)
    found = [g_objs[i].get("returns") for i in match_of_gt]
    found = [r for r in found if isinstance(r, int)]
    few = float(np.percentile(found, 10)) if found else 0.0
    near_obs = None
    if len(obs) and len(gt):
        from scipy.spatial import cKDTree

        near_obs = cKDTree(obs.xyz[:, :2])
    rows = []
    for i, o in enumerate(g_objs):
        j = match_of_gt.get(i)
        returns = o.get("returns")
        if j is not None:
            outcome, why = ("correct" if gt.classes[i] == obs.classes[j]
                            else "misclassified"), ""
        else:
            outcome = "missed_unseen" if returns == 0 else "missed_seen"
            why = _missed_why(i, returns, scored, match_of_obs, near_obs, few)
        rows.append({
            "source": "truth", "id": o.get("id"), "class": o.get("class"),
            "x": gt.xyz[i, 0], "y": gt.xyz[i, 1], "z": gt.xyz[i, 2],
            "dbh_m": o.get("dbh"), "height_m": o.get("h"), "species": o.get("species"),
            "returns": returns, "distance_to_track_m": _num(gd[i]), "outcome": outcome,
            "matched_id": None if j is None else obs.ids[j],
            "observed_class": None if j is None else str(obs.classes[j]),
            "observed_dbh_m": None if j is None else _num(obs.dbh[j]),
            "observed_height_m": None if j is None else _num(obs.h[j]),
            "match_distance_m": None if j is None else _num(
                float(np.hypot(*(gt.xyz[i, :2] - obs.xyz[j, :2])))),
            "defects": ";".join(d.get("type", "") for d in o.get("defects", []) or []),
            "why": why,
        })
    return rows


def _sic_rows(scored: ScoredForest, track: NDArray[np.float64]) -> list[dict[str, Any]]:
    ev, gt, obs = scored.scores.all, scored.scores.gt_all, scored.forest
    match_of_obs = dict(zip(ev.pairs[:, 1].tolist(), ev.pairs[:, 0].tolist(), strict=True))
    od = distance_to_track(obs.xyz[:, :2], track)
    rows = []
    for j, _o in enumerate(scored.forest_doc.get("objects", [])):
        g = match_of_obs.get(j)
        rows.append({
            "source": "sic", "id": obs.ids[j], "class": str(obs.classes[j]),
            "x": obs.xyz[j, 0], "y": obs.xyz[j, 1], "z": obs.xyz[j, 2],
            "dbh_m": _num(obs.dbh[j]), "height_m": _num(obs.h[j]), "species": None,
            "returns": None, "distance_to_track_m": _num(od[j]),
            "outcome": "false_positive" if g is None else "matched",
            "matched_id": None if g is None else gt.ids[g],
            "observed_class": None, "observed_dbh_m": None, "observed_height_m": None,
            "match_distance_m": None if g is None else _num(
                float(np.hypot(*(gt.xyz[g, :2] - obs.xyz[j, :2])))),
            "defects": "", "why": "",
        })
    return rows


def _num(v: Any) -> float | None:
    f = float(v)
    return None if math.isnan(f) else round(f, 4)


STEM_COLUMNS = ("source", "id", "class", "x", "y", "z", "dbh_m", "height_m", "species",
                "returns", "distance_to_track_m", "outcome", "matched_id", "observed_class",
                "observed_dbh_m", "observed_height_m", "match_distance_m", "defects", "why")


def _stems_csv(rows: list[dict[str, Any]]) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(STEM_COLUMNS)
    for r in rows:
        w.writerow(["" if r[c] is None else (f"{r[c]:.4f}" if isinstance(r[c], float)
                                             else r[c]) for c in STEM_COLUMNS])
    return buf.getvalue().encode()


def _stems_geojson(rows: list[dict[str, Any]], epsg: int | None) -> bytes:
    from tcf_hil._io import dumps_json

    feats = [{"type": "Feature",
              "geometry": {"type": "Point",
                           "coordinates": [round(float(r["x"]), 4), round(float(r["y"]), 4),
                                           round(float(r["z"]), 4)]},
              "properties": {c: (round(float(r[c]), 4) if isinstance(r[c], float) else r[c])
                             for c in STEM_COLUMNS if c not in ("x", "y", "z")}}
             for r in rows]
    doc: dict[str, Any] = {"type": "FeatureCollection", "name": "stems"}
    if epsg is not None:  # RFC 7946 dropped "crs"; QGIS and GDAL still honour it
        doc["crs"] = {"type": "name", "properties": {"name": f"urn:ogc:def:crs:EPSG::{epsg}"}}
    doc["features"] = feats
    return dumps_json(doc).encode()


# ---------------------------------------------------------------- entry


def _las_writer(laz: bool) -> CloudWriter:
    def write(path: Path, info: CloudInfo, frames: Iterator[NDArray[np.void]],
              epsg: int | None, _run_name: str) -> int:
        return _write_las(path, info, frames, laz, epsg)

    return write


def _write_ply(path: Path, info: CloudInfo, frames: Iterator[NDArray[np.void]],
               _epsg: int | None, run_name: str) -> int:
    from protocols.ply import ply_vertex_header
    from tcf_hil import __version__

    comments = [f"tcf-hil {__version__} export of {run_name}",
                "gps_time: " + ("adjusted standard GPS time (GPS s - 1e9)"
                                if info.gps_adjusted else "simulation seconds")]
    return _write_headed(path, frames, lambda c: ply_vertex_header(CLOUD_DTYPE, c, comments))


def _write_pcd(path: Path, info: CloudInfo, frames: Iterator[NDArray[np.void]],
               _epsg: int | None, _run_name: str) -> int:
    from protocols.pcd import pcd_header

    off = _offset(info)
    comments = [f"tcf-hil offset {off[0]:.3f} {off[1]:.3f} {off[2]:.3f} "
                "(world = x, y, z + offset)"]
    return _write_headed(path, (_local32(p, off) for p in frames),
                         lambda c: pcd_header(PCD_DTYPE, c, comments))


CloudWriter = Callable[[Path, CloudInfo, Iterator[NDArray[np.void]], "int | None", str], int]
CLOUD_WRITERS: dict[str, CloudWriter] = {
    ".las": _las_writer(False), ".laz": _las_writer(True), ".ply": _write_ply,
    ".pcd": _write_pcd}
"""The cloud's writer for each suffix (the file, the run's cloud, its frames, the EPSG code,
the run's name) -> points written."""
STEM_WRITERS: dict[str, Callable[[list[dict[str, Any]], int | None], bytes]] = {
    ".csv": lambda rows, _epsg: _stems_csv(rows), ".geojson": _stems_geojson}
"""The stems' writer for each suffix (rows, EPSG code) -> the file's bytes."""


@dataclass(frozen=True)
class ExportResult:
    path: Path
    kind: str  # "cloud" or "stems"
    count: int
    labelled: bool = True
    gps_adjusted: bool = True
    unlabelled_frames: int = 0  # frames of a labelled run's capture without a label record


def export(run_dir: str | Path, out: str | Path, *, every: int = 1,
           stems: str = "both", epsg: int | None = None,
           progress: Callable[[int, int], None] | None = None) -> ExportResult:
    """Write ``out`` by its suffix: the cloud (``.las``, ``.laz``, ``.ply``, ``.pcd``; every
    ``every``-th frame) or the stems (``.geojson``, ``.csv``; ``stems``: ``truth``, ``sic``
    or ``both``). ``epsg``: the coordinate system of the world coordinates (the scenario's
    origin), written into LAS/LAZ as the OGC WKT record and into GeoJSON as its ``crs``
    member; PLY, PCD and CSV have no place for one (a ValueError). The file appears only
    whole (a temporary name renamed)."""
    from tcf_hil._io import write_bytes_atomic

    path = Path(out)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES + STEM_SUFFIXES:
        raise InputError(str(path), "", f"unknown format {suffix or '(no suffix)'}; one of "
                         + ", ".join(CLOUD_SUFFIXES + STEM_SUFFIXES))
    if epsg is not None and suffix not in (".las", ".laz", ".geojson"):
        raise ValueError(f"{suffix} has no place for a coordinate system (LAS, LAZ and "
                         "GeoJSON have)")
    if epsg is not None:
        crs_wkt(epsg)  # an unknown code fails before anything is read or written
    if suffix in STEM_SUFFIXES:
        gts, obs = stem_outcomes(run_dir)
        rows = {"truth": gts, "sic": obs, "both": gts + obs}[stems]
        write_bytes_atomic(path, STEM_WRITERS[suffix](rows, epsg))
        return ExportResult(path, "stems", len(rows))
    info, frames = run_cloud(run_dir, every=every, progress=progress)
    n = CLOUD_WRITERS[suffix](path, info, frames, epsg, Path(run_dir).name)
    return ExportResult(path, "cloud", n, info.labelled, info.gps_adjusted,
                        info.labels.missing if info.labels is not None else 0)
