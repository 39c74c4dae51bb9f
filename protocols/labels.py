"""``lidar_labels.bin``: what every lidar return of a run hit, beside ``lidar.pcap``.

The emulator knows, for each pixel it sent, the object its return came from; the packets do
not carry it. This sidecar keeps it, so a run's cloud can be exported with ground truth per
point (``tcf-hil export``). Sans-IO: bytes in, bytes out.

Layout (little-endian)::

    header  b"TCFLABL1", u32 H, u32 W, u32 flags (bit 0: a second return per pixel),
            u32 n_stems, u32 n_ids, n_ids x u8 component of each object id
    record  u64 first column time (ns), u64 last column time (ns), u32 n_bytes,
            n_bytes of zlib-compressed i32 (H, W) object ids (then the second return's)

Object ids are the emulator's (-1 no return; 0 the ground; 1..n the stems; n+1..2n tree
i's branches as n + i; 2n+1..3n its foliage; then one id per understory plant, dead-wood log,
stump and boulder); the component table (``tcf_hil.world.forest.scenery.COMPONENTS`` codes) tells
which is which. Images are staggered (indexed by measurement id, as the packets' columns).
Records are in send order, one per frame that left with lidar packets; a frame is found by
its column times (a reader of the capture knows them; frame ids wrap and restart).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

__all__ = ["LabelsError", "LabelsHeader", "LabelsRecord", "LabelsRecords", "encode_labels_header",
           "encode_labels_record", "read_labels"]

MAGIC = b"TCFLABL1"
_HEAD = struct.Struct("<8sIIIII")
_REC = struct.Struct("<QQI")
DUAL = 1
MAX_IDS = 1 << 28  # object ids a header may list (a 50 ha stand has about 400,000)


class LabelsError(ValueError):
    """A labels file is malformed; the message says where."""


@dataclass(frozen=True)
class LabelsHeader:
    rows: int
    columns: int
    dual: bool
    n_stems: int
    component_of_id: NDArray[np.uint8]


@dataclass(frozen=True)
class LabelsRecord:
    first_ns: int
    last_ns: int
    ids: NDArray[np.int32]  # (H, W)
    ids2: NDArray[np.int32] | None  # the second return's, with a DUAL profile


def encode_labels_header(rows: int, columns: int, dual: bool, n_stems: int,
                         component_of_id: NDArray[np.integer]) -> bytes:
    comp = np.ascontiguousarray(component_of_id, dtype=np.uint8)
    if comp.ndim != 1:
        raise LabelsError(f"component_of_id must be 1-D, got shape {comp.shape}")
    return _HEAD.pack(MAGIC, rows, columns, DUAL if dual else 0, n_stems, len(comp)) + \
        comp.tobytes()


def encode_labels_record(first_ns: int, last_ns: int, ids: NDArray[np.integer],
                         ids2: NDArray[np.integer] | None = None, level: int = 1) -> bytes:
    """One frame's record (zlib ``level`` 1: the frame producer pays for it in real time)."""
    raw = np.ascontiguousarray(ids, dtype="<i4").tobytes()
    if ids2 is not None:
        raw += np.ascontiguousarray(ids2, dtype="<i4").tobytes()
    body = zlib.compress(raw, level)
    return _REC.pack(first_ns, last_ns, len(body)) + body


def _read(f: BinaryIO, n: int, name: str, what: str) -> bytes:
    b = f.read(n)
    if len(b) != n:
        raise LabelsError(f"{name}: {what} cut short ({len(b)} of {n} bytes)")
    return b


def read_labels(f: BinaryIO, name: str = "lidar_labels.bin"
                ) -> tuple[LabelsHeader, LabelsRecords]:
    """The header, and the records one at a time (constant memory). A record cut short at
    the end (a crash while writing) ends the iteration, as a capture's last partial record
    does; anything else malformed raises :class:`LabelsError` naming ``name``."""
    magic, rows, cols, flags, n_stems, n_ids = _HEAD.unpack(
        _read(f, _HEAD.size, name, "header"))
    if magic != MAGIC:
        raise LabelsError(f"{name}: not a labels file (magic {magic!r}, "
                          f"expected {MAGIC!r})")
    if not (0 < rows <= 256 and 0 < cols <= 1 << 16):
        raise LabelsError(f"{name}: header: image of {rows} x {cols} pixels")
    if n_ids > MAX_IDS:
        raise LabelsError(f"{name}: header: {n_ids} object ids (at most {MAX_IDS})")
    comp = np.frombuffer(_read(f, n_ids, name, "component table"), np.uint8).copy()
    head = LabelsHeader(rows, cols, bool(flags & DUAL), n_stems, comp)
    images = 2 if head.dual else 1
    return head, LabelsRecords(f, name, rows, cols, images)


class LabelsRecords:
    """The records of a labels file, one at a time; :meth:`skip_before` passes over the
    records that end before a time without inflating them (a reader that samples frames)."""

    def __init__(self, f: BinaryIO, name: str, rows: int, cols: int, images: int) -> None:
        self.f, self.name, self.rows, self.cols, self.images = f, name, rows, cols, images
        self.size = rows * cols * 4 * images
        self.k = 0
        self._head: tuple[int, int, int] | None = None

    def __iter__(self) -> Iterator[LabelsRecord]:
        return self

    def _peek(self) -> tuple[int, int, int] | None:
        if self._head is None:
            raw = self.f.read(_REC.size)
            if len(raw) < _REC.size:
                return None
            first, last, n = _REC.unpack(raw)
            if n > self.size + (self.size >> 8) + 1024:  # zlib's worst: bytes per 16 KiB
                raise LabelsError(f"{self.name}: record {self.k}: {n} bytes for {self.size} "
                                  "bytes of ids")
            self._head = (first, last, n)
        return self._head

    def skip_before(self, ns: int) -> None:
        """Pass over the records whose last column time is before ``ns``."""
        while (h := self._peek()) is not None and h[1] < ns:
            here = self.f.tell()
            self.f.seek(h[2], 1)
            if self.f.tell() != here + h[2]:
                return
            self._head = None
            self.k += 1

    def __next__(self) -> LabelsRecord:
        h = self._peek()
        if h is None:
            raise StopIteration
        first, last, n = h
        self._head = None
        body = self.f.read(n)
        if len(body) < n:  # cut short at the end (a crash while writing)
            raise StopIteration
        try:
            data = zlib.decompress(body)
        except zlib.error as err:
            raise LabelsError(f"{self.name}: record {self.k}: {err}") from err
        if len(data) != self.size:
            raise LabelsError(f"{self.name}: record {self.k}: {len(data)} bytes of ids, "
                              f"expected {self.size}")
        arr = np.frombuffer(data, "<i4").reshape(self.images, self.rows, self.cols)
        self.k += 1
        return LabelsRecord(first, last, arr[0], arr[1] if self.images == 2 else None)
