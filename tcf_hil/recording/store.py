"""The render store: a lidar run's frames rendered ahead, kept on disk under a key made of
everything that decides their bytes, and streamed from there at the sensor's cadence.

Rendering (ray casting, physics, packet bytes) is expensive and deterministic; streaming
(pacing, UDP) is cheap and on the clock. A run whose frames are stored sends them from here,
so the program under test gets the machine (the bench only paces and copies), and every run
of the same key sends the same bytes. ``tcf-hil render`` fills the store, ``tcf-hil cache``
lists and frees it.

A render is a folder ``<root>/<key>/`` holding:

- ``render.json``: what the key was made of, the frames the track has, and once every frame
  is in, ``complete``;
- ``frames.bin``: one record per frame, in order (:class:`RenderedFrame`, layout below),
  each stored as a little-endian u32 length and the record compressed with Zstandard at
  level 1 (``zstandard``, which mcap and rosbags need too). A 2048x10 natural stand's frame
  record (1.76 MB, 30 frames of a stored render, medians): zlib level 1 (the store's codec
  until 2026-12-03) 2.53:1, 33 ms to compress, 13 ms to expand; zstd level 1 2.96:1, 8 ms and
  3.8 ms; zstd 3 3.21:1, 19 ms and 3.9 ms; lz4 1.95:1, 6 ms and 1.2 ms. Expanding is
  the frame producer's largest cost while a run streams from the store, compressing the
  renderer's: zstd 1 is cheaper at both and smaller on disk;
- ``frames.idx``: the little-endian u64 offset of each frame record in ``frames.bin``,
  appended only once the record is whole on disk: a render cut short (a crash, Ctrl-C) keeps
  its whole frames and is resumed from there; anything after the last indexed record is
  never read.

A frame record (little-endian): the header ``b"TCFF"``, i64 frame, u8 action (send, drop,
reinit, silent), u32 init_id after the frame, u32 datagrams, u32 labels bytes, u32 poses
bytes, u32 hit ids, u32 events bytes; then per datagram (i64 t_ns, i64 port, i64 length), the
payloads back to back, the labels record, the poses CSV rows, (hit ids) i64 object ids and
(hit ids) i64 return counts, and the fault events as JSON.

The root is ``$TCF_HIL_CACHE`` or ``$XDG_CACHE_HOME/tcf-hil`` (``~/.cache/tcf-hil``), with
renders under ``renders/``; ``$TCF_HIL_CACHE_MAX_GB`` (default 20) bounds it: when a render
is added the least recently used others go.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from numpy.typing import NDArray

from emulators.lidar import Datagram
from tcf_hil._io import write_json_atomic
from tcf_hil.errors import InputError

__all__ = ["ACTIONS", "DEFAULT_MAX_GB", "RenderStore", "RenderWriter", "RenderedFrame",
           "StoredRender", "cache_root", "code_version", "pack_frame", "render_key"]

ACTIONS = ("send", "drop", "reinit", "silent")
DEFAULT_MAX_GB = 20.0
FORMAT = 3  # of the files above: a change makes every older render a miss
_HEAD = struct.Struct("<4sqBIIIIII")
_MAGIC = b"TCFF"


@dataclass
class RenderedFrame:
    """One frame as the sensor sends it, in the compact form the store keeps: its
    datagrams (each at its simulation time, tagged with the port the run was made with),
    what each return hit (``labels``: a :mod:`protocols.labels` record, empty for a frame
    that left without lidar packets), the sensor pose of every column (``poses``: the n
    column times as little-endian int64, then (n, 7) float64 x, y, z, qw, qx, qy, qz in the
    world: ``sensor_poses.csv``'s numbers), the returns per object id
    (``hit_ids``/``hit_counts``), the fault events that struck it, what the sensor did
    (``action``) and its ``init_id`` after the frame."""

    k: int
    datagrams: list[Datagram]
    labels: bytes
    poses: bytes
    hit_ids: NDArray[np.int64]
    hit_counts: NDArray[np.int64]
    events: list[dict[str, Any]]
    action: str
    init_id: int
    result: Any = field(default=None, repr=False)  # the emulator's FrameResult (live only)

    @property
    def sent(self) -> bool:
        """Whether it left with lidar packets (as the sensor frame's ``sent``)."""
        return self.action == "send"

    def encode(self, ports: tuple[int, int] = (0, 1)) -> bytes:
        """The frame's record (the module docstring's layout); a datagram to ``ports``
        (the lidar and IMU ports the run was made with) is kept as to port 0 or 1, so that a
        render serves runs on any ports."""
        return b"".join(self.encode_parts(ports))

    def encode_parts(self, ports: tuple[int, int] = (0, 1)) -> list[bytes | memoryview]:
        """:meth:`encode` in pieces (the payloads as they are), for a gathered write."""
        tag = {ports[0]: 0, ports[1]: 1}
        dg = np.array([(d.t_ns, tag.get(d.port, d.port), len(d.payload))
                       for d in self.datagrams], np.int64).reshape(-1, 3)
        ev = json.dumps(self.events, separators=(",", ":")).encode() if self.events else b""
        head = _HEAD.pack(_MAGIC, self.k, ACTIONS.index(self.action), self.init_id,
                          len(dg), len(self.labels), len(self.poses), len(self.hit_ids),
                          len(ev))
        parts: list[bytes | memoryview] = [head, dg.astype("<i8").tobytes()]
        parts += [d.payload for d in self.datagrams]
        parts += [self.labels, self.poses, self.hit_ids.astype("<i8").tobytes(),
                  self.hit_counts.astype("<i8").tobytes(), ev]
        return parts

    @classmethod
    def decode(cls, buf: Any, offset: int, source: str = "frames.bin",
               ports: tuple[int, int] = (0, 1)) -> tuple[RenderedFrame, int]:
        """The record at ``offset`` of ``buf`` (payloads as views of it, to ``ports``: the
        lidar and IMU ports of the run it serves) and where it ends."""
        try:
            magic, k, act, init_id, n_dg, n_lab, n_pos, n_hit, n_ev = _HEAD.unpack_from(
                buf, offset)
        except struct.error as err:
            raise InputError(source, f"offset {offset}", f"truncated frame record ({err})") \
                from err
        if magic != _MAGIC or act >= len(ACTIONS):
            raise InputError(source, f"offset {offset}", "not a frame record")
        pos = offset + _HEAD.size
        view = memoryview(buf)
        dg = np.frombuffer(view[pos:pos + 24 * n_dg], "<i8").reshape(-1, 3)
        pos += 24 * n_dg
        dgs = []
        for t, port, n in dg.tolist():
            dgs.append(Datagram(t, ports[port] if port in (0, 1) else port, view[pos:pos + n]))
            pos += n
        labels = bytes(view[pos:pos + n_lab])
        pos += n_lab
        poses = bytes(view[pos:pos + n_pos])
        pos += n_pos
        ids = np.frombuffer(view[pos:pos + 8 * n_hit], "<i8").astype(np.int64)
        pos += 8 * n_hit
        counts = np.frombuffer(view[pos:pos + 8 * n_hit], "<i8").astype(np.int64)
        pos += 8 * n_hit
        events = json.loads(bytes(view[pos:pos + n_ev])) if n_ev else []
        pos += n_ev
        if pos > len(view):
            raise InputError(source, f"offset {offset}", "truncated frame record")
        return cls(k, dgs, labels, poses, ids, counts, events, ACTIONS[act], init_id), pos


_LEN = struct.Struct("<I")
# one context each per process (a context is not for two threads at once: the store is
# written and read by one thread in each process that uses it)
_COMPRESS = zstandard.ZstdCompressor(level=1)
_DECOMPRESS = zstandard.ZstdDecompressor()


def _record_end(fh: Any, offset: int, source: str) -> int:
    """Where the stored (compressed) frame record at ``offset`` of the open file ``fh``
    ends."""
    fh.seek(offset)
    head = fh.read(_LEN.size)
    if len(head) < _LEN.size:
        raise InputError(source, f"offset {offset}", "truncated frame record")
    return offset + _LEN.size + _LEN.unpack(head)[0]


def _expand(fd: int, offset: int, source: str) -> bytes:
    """The frame record stored at ``offset`` of the open file ``fd``, read and expanded."""
    try:
        (n,) = _LEN.unpack(os.pread(fd, _LEN.size, offset))
        body = os.pread(fd, n, offset + _LEN.size)
        if len(body) < n:
            raise struct.error(f"{len(body)} of {n} bytes")
        return _DECOMPRESS.decompress(body)
    except (struct.error, zstandard.ZstdError) as err:
        raise InputError(source, f"offset {offset}", f"damaged frame record ({err})") from err


def cache_root() -> Path:
    """Where renders are kept (the module docstring)."""
    env = os.environ.get("TCF_HIL_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "tcf-hil"


_CODE_VERSION: str | None = None


def code_version() -> str:
    """A digest of the source that decides a frame's bytes (the packages ``protocols``,
    ``emulators``, ``tcf_hil.world``, ``tcf_hil.scenario`` and the lidar device): any change
    there makes a new key, so a store never serves frames older code rendered."""
    global _CODE_VERSION
    if _CODE_VERSION is None:
        import emulators
        import protocols
        import tcf_hil

        top = Path(tcf_hil.__file__).parent
        roots = [Path(protocols.__file__).parent, Path(emulators.__file__).parent,
                 top / "world", top / "scenario"]
        files = sorted(p for r in roots for p in r.rglob("*.py"))
        files += [top / "devices" / "lidar.py", top / "_crc.py", top / "_rotations.py",
                  Path(__file__)]
        h = hashlib.sha256()
        for p in files:
            h.update(p.relative_to(top.parent).as_posix().encode())
            h.update(p.read_bytes())
        _CODE_VERSION = h.hexdigest()[:16]
    return _CODE_VERSION


def render_key(doc: dict[str, Any]) -> str:
    """The key of a render: a digest of ``doc`` (everything that decides the bytes, as
    JSON) with the store's format and :func:`code_version`."""
    full = {"format": FORMAT, "code": code_version(), **doc}
    text = json.dumps(full, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


class StoredRender:
    """A render in the store, read: each frame read (``pread``) and expanded as it is asked
    for (its payloads are views of the expanded record). Not a memory map: the frame
    producer that streams a render touched every page of it, and the pages it had read
    counted in its resident memory (a one-minute soak at 2048x10: +22 % in 45 s, where the
    soak allows 5 %), though the kernel may drop them at any time."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.info: dict[str, Any] = json.loads((path / "render.json").read_text())
        self.offsets = np.zeros(0, np.int64)
        self._fh = open(path / "frames.bin", "rb")
        self.refresh()

    def refresh(self) -> int:
        """Whole frames stored now (a render that is being written grows)."""
        p = self.path / "frames.idx"
        idx = p.read_bytes() if p.exists() else b""
        if len(idx) // 8 > len(self.offsets):
            self.offsets = np.frombuffer(idx[:len(idx) // 8 * 8], "<u8").astype(np.int64)
        return len(self.offsets)

    @property
    def frames(self) -> int:
        """Whole frames stored."""
        return len(self.offsets)

    @property
    def complete(self) -> bool:
        return bool(self.info.get("complete")) and self.frames >= int(self.info["frames"])

    def frame(self, i: int, ports: tuple[int, int] = (0, 1)) -> RenderedFrame:
        """Frame ``i``, its datagrams to ``ports`` (the run's lidar and IMU ports)."""
        if not 0 <= i < self.frames:
            raise IndexError(f"frame {i} of {self.frames} stored")
        source = str(self.path / "frames.bin")
        rf, _ = RenderedFrame.decode(_expand(self._fh.fileno(), int(self.offsets[i]), source),
                                     0, source, ports)
        return rf

    def touch(self) -> None:
        """Marked as used now (the size limit frees the least recently used first)."""
        with contextlib.suppress(OSError):
            os.utime(self.path / "render.json")

    def close(self) -> None:
        self._fh.close()


def pack_frame(rf: RenderedFrame, ports: tuple[int, int]) -> bytes:
    """A frame's record as ``frames.bin`` keeps it (compressed), made with the lidar and IMU
    ``ports``: what :meth:`RenderWriter.append_packed` takes (a renderer process packs its
    frames itself, so compressing is parallel too)."""
    return _COMPRESS.compress(rf.encode(ports))


class RenderWriter:
    """Frames appended to a render in the store (resumed after its last whole frame), and
    :meth:`complete` once the last is in. ``lock``: the open lock file it holds (one writer
    per render, across processes and machines' workers sharing the disk)."""

    def __init__(self, path: Path, doc: dict[str, Any], frames: int,
                 lock: Any = None) -> None:
        path.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._lock = lock
        info_path = path / "render.json"
        if info_path.exists():
            self.info = json.loads(info_path.read_text())
        else:
            self.info = {"key": path.name, "made_of": doc, "frames": frames,
                         "created_unix": time.time(), "complete": False}
            write_json_atomic(info_path, self.info)
        idx = (path / "frames.idx").read_bytes() if (path / "frames.idx").exists() else b""
        n = len(idx) // 8
        offsets = np.frombuffer(idx[:n * 8], "<u8")
        self._idx = open(path / "frames.idx", "r+b" if idx else "wb")
        self._idx.truncate(n * 8)
        self._idx.seek(n * 8)
        self._bin = open(path / "frames.bin", "r+b" if (path / "frames.bin").exists() else "wb")
        end = 0
        if n:  # after the last whole frame: what a crash left half-written goes
            end = _record_end(self._bin, int(offsets[-1]), str(path / "frames.bin"))
        self._bin.truncate(end)
        self._bin.seek(end)
        self.frames = n
        self.bytes = end

    def append(self, rf: RenderedFrame, ports: tuple[int, int]) -> None:
        """``rf``, the next frame, made with the lidar and IMU ``ports``."""
        self.append_packed(rf.k, pack_frame(rf, ports))

    def append_packed(self, k: int, z: bytes | bytearray) -> None:
        """Frame ``k``, the next, as :func:`pack_frame` made it (in any process)."""
        if k != self.frames:
            raise ValueError(f"frame {k} appended after {self.frames} frames")
        rec = _LEN.pack(len(z)) + z
        self._bin.write(rec)
        self._bin.flush()
        self._idx.write(struct.pack("<Q", self.bytes))
        self._idx.flush()
        self.bytes += len(rec)
        self.frames += 1

    def complete(self) -> None:
        """Every frame of the track is in: the render may be streamed from now on."""
        self._bin.flush()
        os.fsync(self._bin.fileno())
        self._idx.flush()
        os.fsync(self._idx.fileno())
        self.info.update(complete=True, frames=self.frames, bytes=self.bytes,
                         completed_unix=time.time())
        write_json_atomic(self.path / "render.json", self.info)

    def close(self) -> None:
        self._bin.close()
        self._idx.close()
        if self._lock is not None:
            self._lock.close()  # (the lock goes with the file)
            self._lock = None


class RenderStore:
    """The renders under ``root`` (default :func:`cache_root`), at most ``max_gb``
    gigabytes of them (default ``$TCF_HIL_CACHE_MAX_GB`` or 20)."""

    def __init__(self, root: str | Path | None = None, max_gb: float | None = None) -> None:
        self.root = Path(root) if root is not None else cache_root()
        if max_gb is None:
            env = os.environ.get("TCF_HIL_CACHE_MAX_GB")
            try:
                max_gb = float(env) if env else DEFAULT_MAX_GB
            except ValueError as err:
                raise InputError("$TCF_HIL_CACHE_MAX_GB", "", f"{env!r}: not a number") \
                    from err
        self.max_bytes = int(max_gb * 1e9)

    @property
    def renders_dir(self) -> Path:
        return self.root / "renders"

    def path(self, key: str) -> Path:
        return self.renders_dir / key

    def open(self, key: str, partial: bool = False) -> StoredRender | None:
        """The render ``key`` where it is complete (``partial``: whatever it holds, still
        being written or cut short), else None."""
        p = self.path(key)
        if not (p / "render.json").exists() or not (p / "frames.bin").exists():
            return None
        try:
            r = StoredRender(p)
        except (OSError, ValueError):
            return None
        if not r.complete and not partial:
            r.close()
            return None
        r.touch()
        return r

    def writer(self, key: str, doc: dict[str, Any], frames: int, *, wait: bool = True
               ) -> RenderWriter | None:
        """A writer for the render ``key`` (resumed where a render was cut short), after
        room is made for it (least recently used renders freed beyond the size limit);
        only one at a time per render: ``wait`` for another process's to finish, else None
        while one writes. None too where the render is complete (another finished it)."""
        self.renders_dir.mkdir(parents=True, exist_ok=True)
        lock = open(self.renders_dir / f"{key}.lock", "a+b")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            lock.close()
            return None
        done = self.open(key)
        if done is not None:
            done.close()
            lock.close()
            return None
        self.evict(keep=key)
        return RenderWriter(self.path(key), doc, frames, lock)

    def entries(self) -> list[dict[str, Any]]:
        """Every render: its key, what it was made of, frames stored and expected, whether
        complete, bytes on disk and when last used, most recently used first."""
        out: list[dict[str, Any]] = []
        if not self.renders_dir.is_dir():
            return out
        for p in self.renders_dir.iterdir():
            info_path = p / "render.json"
            if not info_path.is_file():
                continue
            try:
                info = json.loads(info_path.read_text())
            except (OSError, ValueError):
                info = {}
            size = sum(f.stat().st_size for f in p.iterdir() if f.is_file())
            idx = p / "frames.idx"
            stored = idx.stat().st_size // 8 if idx.exists() else 0
            out.append({"key": p.name, "made_of": info.get("made_of", {}),
                        "frames": stored, "frames_total": info.get("frames"),
                        "complete": bool(info.get("complete")) and stored >= int(
                            info.get("frames") or 0),
                        "bytes": size, "used_unix": info_path.stat().st_mtime})
        out.sort(key=lambda e: -e["used_unix"])
        return out

    def size(self) -> int:
        return sum(e["bytes"] for e in self.entries())

    def remove(self, key: str) -> None:
        shutil.rmtree(self.path(key), ignore_errors=True)
        with contextlib.suppress(OSError):
            (self.renders_dir / f"{key}.lock").unlink()

    def clear(self) -> tuple[int, int]:
        """Every render removed: (renders, bytes) freed."""
        es = self.entries()
        for e in es:
            self.remove(e["key"])
        return len(es), sum(e["bytes"] for e in es)

    def evict(self, keep: str | None = None, room: int = 0) -> list[str]:
        """The least recently used renders removed until the rest (and ``room`` bytes more)
        fit under the limit; ``keep`` is never removed. The keys removed."""
        es = self.entries()
        total = sum(e["bytes"] for e in es) + room
        gone = []
        for e in reversed(es):  # least recently used first
            if total <= self.max_bytes:
                break
            if e["key"] == keep:
                continue
            self.remove(e["key"])
            total -= e["bytes"]
            gone.append(e["key"])
        return gone
