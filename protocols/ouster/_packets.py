"""Lidar packets: whole-frame vectorised encoding and validated decoding (sans-IO).

Images are in the sensor's *staggered* layout: row u is beam u, column m is the column with
measurement_id m, exactly as the packets carry them (ouster-sdk decodes only this layout).
Encoding a frame is one transpose of each (H, W) image into the (packets, columns, pixels)
view of a preallocated packet array; the CRC of all packets is computed in one call.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import NDArray

from protocols.ouster._crc import crc64_xz_rows
from protocols.ouster._errors import (
    CrcError,
    MeasurementIdError,
    PacketIdError,
    PacketSizeError,
    PacketTypeError,
)
from protocols.ouster._profiles import PROFILES, Field, Profile

__all__ = ["LidarPacket", "PacketBatch", "PacketFormat", "decode_lidar_packet",
           "decode_lidar_packets", "encode_lidar_columns", "encode_lidar_frame",
           "encode_pixel_fields", "finish_lidar_packets", "frame_from_packets",
           "shift_lidar_packet"]

CrcRows = Callable[[NDArray[np.uint8]], NDArray[np.uint64]]
LEGACY_ENCODER_TICKS = 90112  # encoder counts per revolution (legacy column header)


@dataclass(frozen=True, slots=True)
class PacketFormat:
    """Layout of one sensor's lidar packets, derived once from profile and frame geometry."""

    profile: Profile
    pixels_per_column: int = 64
    columns_per_packet: int = 16
    columns_per_frame: int = 1024

    def __post_init__(self) -> None:
        if self.columns_per_frame % self.columns_per_packet:
            raise ValueError(f"columns_per_frame {self.columns_per_frame} is not a multiple "
                             f"of columns_per_packet {self.columns_per_packet}")

    @classmethod
    def create(cls, profile: str, pixels_per_column: int = 64, columns_per_packet: int = 16,
               columns_per_frame: int = 1024) -> PacketFormat:
        if profile not in PROFILES:
            raise KeyError(f"unknown lidar profile {profile!r}; known: {', '.join(PROFILES)}")
        return cls(PROFILES[profile], pixels_per_column, columns_per_packet, columns_per_frame)

    @property
    def packet_bytes(self) -> int:
        return self.profile.packet_bytes(self.pixels_per_column, self.columns_per_packet)

    @property
    def col_bytes(self) -> int:
        return self.profile.col_bytes(self.pixels_per_column)

    @property
    def packets_per_frame(self) -> int:
        return self.columns_per_frame // self.columns_per_packet

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.profile.fields)

    def _columns(self, arr: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """(packets, columns, col_bytes) view of a (packets, packet_bytes) array."""
        h = self.profile.header_bytes
        n = arr.shape[0]
        body = arr[:, h:h + self.columns_per_packet * self.col_bytes]
        return body.reshape(n, self.columns_per_packet, self.col_bytes)

    def _pixels(self, cols: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """(packets, columns, pixels, pixel_bytes) view."""
        p = self.profile
        a = p.col_header_bytes
        px = cols[:, :, a:a + self.pixels_per_column * p.pixel_bytes]
        return px.reshape(*cols.shape[:2], self.pixels_per_column, p.pixel_bytes)

    def pixel_word(self, packets: NDArray[np.uint8], offset: int, dtype: str
                   ) -> NDArray[np.generic]:
        """The (packets, columns, pixels) view of one pixel word (byte ``offset`` in the
        pixel block, numpy ``dtype`` such as ``"<u4"``) of an (n, packet_bytes) array: what
        a writer fills with values already shifted into place (``Field.offset``,
        ``Field.dtype``)."""
        return _word_view(self._pixels(self._columns(packets)), offset, dtype)

    def column_timestamps(self, packets: NDArray[np.uint8]) -> NDArray[np.generic]:
        """The (packets, columns) view of the column time stamps (ns) of an (n, packet_bytes)
        array: the one column header word that changes from frame to frame (a writer may
        copy the rest from packets encoded once, :func:`encode_lidar_columns`)."""
        return _word_view(self._columns(packets), 0, "<u8")

    def pixel_fields(self, packets: NDArray[np.uint8], names: Sequence[str] | None = None
                     ) -> dict[str, NDArray[np.uint32]]:
        """The (H, n * columns_per_packet) image of each named field (default: all of the
        profile's) in an (n, packet_bytes) array of packets, in packet order; no checks."""
        pix = self._pixels(self._columns(packets))
        n = packets.shape[0] * self.columns_per_packet
        return {f.name: _decode_value(f, _word_view(pix, f.offset, f.dtype)).reshape(
            n, self.pixels_per_column).T
            for f in self.profile.fields if names is None or f.name in names}


def _word_view(pix: NDArray[np.uint8], offset: int, dtype: str) -> NDArray[np.generic]:
    size = np.dtype(dtype).itemsize
    return pix[..., offset:offset + size].view(dtype)[..., 0]


def _encode_value(f: Field, value: NDArray[np.integer]) -> NDArray[np.uint32]:
    v = np.asarray(value).astype(np.uint32, copy=False)
    if f.shift > 0:
        v = v << np.uint32(f.shift)
    elif f.shift < 0:
        v = v >> np.uint32(-f.shift)
    return v & np.uint32(f.mask)


def _decode_value(f: Field, word: NDArray[np.generic]) -> NDArray[np.uint32]:
    v = word.astype(np.uint64) & np.uint64(f.mask)
    v = v >> np.uint64(f.shift) if f.shift >= 0 else v << np.uint64(-f.shift)
    return v.astype(np.uint32)


def encode_lidar_frame(fmt: PacketFormat, fields: Mapping[str, NDArray[np.integer]],
                       timestamps_ns: NDArray[np.integer], *, frame_id: int, init_id: int,
                       prod_sn: int, status: NDArray[np.integer] | None = None,
                       crc_rows: CrcRows | None = None,
                       out: NDArray[np.uint8] | None = None) -> NDArray[np.uint8]:
    """Encode one frame into a (packets_per_frame, packet_bytes) uint8 array.

    The same as :func:`encode_lidar_columns` over the whole frame, then
    :func:`finish_lidar_packets`.

    Args:
        fmt: the packet format.
        fields: staggered (H, W) images by field name (RANGE in mm, ...); missing fields are 0.
        timestamps_ns: (W,) column time stamps.
        frame_id: 16 bits; init_id: 24 bits; prod_sn: 40 bits.
        status: (W,) column status (default valid: 1, or 0xFFFFFFFF for LEGACY).
        crc_rows: CRC-64/XZ of each row of a 2-D uint8 array (default: numpy tables; the
            emulator passes a compiled one).
        out: reuse this array (must have the right shape and dtype).
    """
    _check_ids(frame_id, init_id, prod_sn)
    arr = out if out is not None else np.empty((fmt.packets_per_frame, fmt.packet_bytes),
                                               dtype=np.uint8)
    encode_lidar_columns(fmt, arr, 0, fields, timestamps_ns, status)
    return finish_lidar_packets(fmt, arr, frame_id=frame_id, init_id=init_id, prod_sn=prod_sn,
                                crc_rows=crc_rows)


def _check_frame(fmt: PacketFormat, frame: NDArray[np.uint8]) -> None:
    if frame.shape != (fmt.packets_per_frame, fmt.packet_bytes) or frame.dtype != np.uint8:
        raise ValueError(f"packet array of shape {frame.shape} and dtype {frame.dtype}; "
                         f"expected ({fmt.packets_per_frame}, {fmt.packet_bytes}) uint8")


def _check_ids(frame_id: int, init_id: int, prod_sn: int) -> None:
    if not 0 <= frame_id <= 0xFFFF or not 0 <= init_id < 1 << 24 or not 0 <= prod_sn < 1 << 40:
        raise ValueError(f"frame_id {frame_id} (16 bit), init_id {init_id} (24 bit) or prod_sn "
                         f"{prod_sn} (40 bit) out of range")


def encode_lidar_columns(fmt: PacketFormat, frame: NDArray[np.uint8], first_column: int,
                         fields: Mapping[str, NDArray[np.integer]],
                         timestamps_ns: NDArray[np.integer],
                         status: NDArray[np.integer] | None = None) -> None:
    """Encode whole packets' worth of columns into their rows of a frame's packet array.

    Columns ``first_column`` .. ``first_column + n`` (``n`` the width of the images; both
    multiples of ``columns_per_packet``) go into packets ``first_column / C`` ... of
    ``frame``, a (packets_per_frame, packet_bytes) uint8 array: those packets are zeroed, then
    their column headers and pixels written. The packet headers, LEGACY's per-column frame_id
    and the CRC are :func:`finish_lidar_packets`' (the frame_id may be decided last). Parts of
    one frame may be encoded from several threads at once.

    Args:
        fields: staggered (H, n) images by field name; missing fields are 0. Images that are
            transposed views of column-major (n, H) arrays are written without a copy.
        timestamps_ns: (n,) column time stamps.
        status: (n,) column status (default valid: 1, or 0xFFFFFFFF for LEGACY).
    """
    p = fmt.profile
    H, W, C = fmt.pixels_per_column, fmt.columns_per_frame, fmt.columns_per_packet
    ts = np.asarray(timestamps_ns, dtype=np.uint64)
    n = ts.shape[0] if ts.ndim == 1 else -1
    if n <= 0 or first_column % C or n % C or first_column + n > W:
        raise ValueError(f"columns {first_column}..{first_column + n} with timestamps_ns of "
                         f"shape {ts.shape}: expected whole packets of {C} columns within "
                         f"0..{W}")
    _check_frame(fmt, frame)
    for name, img in fields.items():
        if np.shape(img) != (H, n):
            raise ValueError(f"field {name} has shape {np.shape(img)}; expected ({H}, {n})")
        p.field(name)  # KeyError names the profile's fields
    P = n // C
    arr = frame[first_column // C:first_column // C + P]
    arr[...] = 0
    cols = fmt._columns(arr)
    mid = np.arange(first_column, first_column + n, dtype=np.uint16).reshape(P, C)
    fmt.column_timestamps(arr)[...] = ts.reshape(P, C)
    _word_view(cols, 8, "<u2")[...] = mid
    if p.legacy:
        st = (np.full(n, 0xFFFFFFFF, np.uint32) if status is None
              else np.asarray(status, np.uint32))
        _word_view(cols, 12, "<u4")[...] = (mid.astype(np.uint64) * LEGACY_ENCODER_TICKS // W)
        _word_view(cols, fmt.col_bytes - 4, "<u4")[...] = st.reshape(P, C)
    else:
        st = np.ones(n, np.uint16) if status is None else np.asarray(status, np.uint16)
        _word_view(cols, 10, "<u2")[...] = st.reshape(P, C)
    _write_fields(fmt, arr, fields)


def encode_pixel_fields(fmt: PacketFormat, frame: NDArray[np.uint8], first_column: int,
                        fields: Mapping[str, NDArray[np.integer]]) -> None:
    """(Re)write the pixel words that hold the given fields, for columns ``first_column`` ..
    ``first_column + n`` (whole packets) of a frame's packet array; a word's other fields
    become 0. For fields known only after the columns were encoded (the DUAL profile's
    second return, say). Images are staggered (H, n)."""
    H, W, C = fmt.pixels_per_column, fmt.columns_per_frame, fmt.columns_per_packet
    n = next(iter(fields.values())).shape[1] if fields else C
    if first_column % C or n % C or first_column + n > W:
        raise ValueError(f"columns {first_column}..{first_column + n}: expected whole "
                         f"packets of {C} columns within 0..{W}")
    for name, img in fields.items():
        if np.shape(img) != (H, n):
            raise ValueError(f"field {name} has shape {np.shape(img)}; expected ({H}, {n})")
        fmt.profile.field(name)  # KeyError names the profile's fields
    _write_fields(fmt, frame[first_column // C:(first_column + n) // C], fields)


def _write_fields(fmt: PacketFormat, rows: NDArray[np.uint8],
                  fields: Mapping[str, NDArray[np.integer]]) -> None:
    # Fields sharing a word are combined in the (H, n) image layout; each word is then
    # written once through a transposed view: (H, n) -> (packets, columns, pixels).
    H, C = fmt.pixels_per_column, fmt.columns_per_packet
    words: dict[tuple[int, str], NDArray[np.uint32]] = {}
    for f in fmt.profile.fields:
        if f.name not in fields:
            continue
        v = _encode_value(f, fields[f.name])
        key = (f.offset, f.dtype)
        words[key] = words[key] | v if key in words else v
    for (off, dt), v in words.items():
        fmt.pixel_word(rows, off, dt)[...] = v.T.reshape(rows.shape[0], C, H)


def finish_lidar_packets(fmt: PacketFormat, frame: NDArray[np.uint8], *, frame_id: int,
                         init_id: int, prod_sn: int, crc_rows: CrcRows | None = None
                         ) -> NDArray[np.uint8]:
    """Write the packet headers (LEGACY: the frame_id of every column) and the CRC footers
    of a frame whose columns :func:`encode_lidar_columns` wrote; returns ``frame``."""
    _check_ids(frame_id, init_id, prod_sn)
    arr = frame
    _check_frame(fmt, arr)
    if fmt.profile.legacy:
        _word_view(fmt._columns(arr), 10, "<u2")[...] = frame_id
        return arr
    arr[:, 0:2].view("<u2")[:, 0] = 1  # packet_type: lidar
    arr[:, 2:4].view("<u2")[:, 0] = frame_id
    arr[:, 4:7] = np.frombuffer(init_id.to_bytes(3, "little"), np.uint8)
    arr[:, 7:12] = np.frombuffer(prod_sn.to_bytes(5, "little"), np.uint8)
    crc = (crc_rows or crc64_xz_rows)(arr[:, :-8])
    arr[:, -8:].view("<u8")[:, 0] = crc
    return arr


def shift_lidar_packet(fmt: PacketFormat, payload: bytes, frames: int, dt_ns: int) -> bytes:
    """``payload`` as the same sensor sends it ``frames`` frames and ``dt_ns`` later: the
    frame_id advanced (16 bits, wrapping), every column time stamp shifted and the CRC
    footer rewritten (a replay that loops). A payload of another size is returned as is."""
    if len(payload) != fmt.packet_bytes or (frames == 0 and dt_ns == 0):
        return payload
    arr = np.frombuffer(payload, np.uint8).copy().reshape(1, -1)
    cols = fmt._columns(arr)
    ts = cast(NDArray[np.uint64], _word_view(cols, 0, "<u8"))
    ts += np.uint64(dt_ns % (1 << 64))
    if fmt.profile.legacy:
        fid = _word_view(cols, 10, "<u2")
        fid[...] = (fid.astype(np.int64) + frames) % 65536
        return arr.tobytes()
    fid = arr[:, 2:4].view("<u2")
    fid[...] = (fid.astype(np.int64) + frames) % 65536
    arr[:, -8:].view("<u8")[:, 0] = crc64_xz_rows(arr[:, :-8])
    return arr.tobytes()


@dataclass(frozen=True)
class LidarPacket:
    """One decoded lidar packet. Field images are (H, columns_per_packet)."""

    frame_id: int
    init_id: int
    prod_sn: int
    packet_type: int
    timestamps_ns: NDArray[np.uint64]
    measurement_id: NDArray[np.uint16]
    status: NDArray[np.uint32]
    fields: dict[str, NDArray[np.uint32]] = field(repr=False)
    crc: int | None = None


def decode_lidar_packet(fmt: PacketFormat, buf: bytes | bytearray | memoryview, *,
                        init_id: int | None = None, prod_sn: int | None = None,
                        check_crc: bool = True,
                        crc_rows: CrcRows | None = None) -> LidarPacket:
    """Decode and validate one lidar packet.

    ``init_id``/``prod_sn``: the metadata's values; a packet must match unless either side is
    0 (as ouster-sdk). Raises a :class:`ProtocolError` subclass naming expected and actual.
    """
    p = fmt.profile
    data = np.frombuffer(buf, dtype=np.uint8)
    if len(data) != fmt.packet_bytes:
        raise PacketSizeError(
            f"lidar packet of {len(data)} bytes; {p.name} with {fmt.pixels_per_column} pixels "
            f"and {fmt.columns_per_packet} columns per packet is {fmt.packet_bytes} bytes")
    arr = data.reshape(1, -1)
    cols = fmt._columns(arr)
    ts = _word_view(cols, 0, "<u8")[0].astype(np.uint64)
    mid = _word_view(cols, 8, "<u2")[0].astype(np.uint16)
    crc = None
    if p.legacy:
        frame_id = int(_word_view(cols, 10, "<u2")[0, 0])
        status = _word_view(cols, fmt.col_bytes - 4, "<u4")[0].astype(np.uint32)
        ptype, pid, psn = 1, 0, 0
    else:
        ptype = int(data[0:2].view("<u2")[0])
        if ptype != 1:
            raise PacketTypeError(f"packet_type {ptype}; a lidar packet carries 1")
        frame_id = int(data[2:4].view("<u2")[0])
        pid = int.from_bytes(data[4:7].tobytes(), "little")
        psn = int.from_bytes(data[7:12].tobytes(), "little")
        status = _word_view(cols, 10, "<u2")[0].astype(np.uint32)
        crc = int(data[-8:].view("<u8")[0])
        if check_crc:
            want = int((crc_rows or crc64_xz_rows)(arr[:, :-8])[0])
            if want != crc:
                raise CrcError(f"CRC-64/XZ footer 0x{crc:016x}; the packet's bytes give "
                               f"0x{want:016x}")
        if init_id and pid and pid != init_id:
            raise PacketIdError(f"init_id {pid}; the metadata says {init_id}")
        if prod_sn and psn and psn != prod_sn:
            raise PacketIdError(f"prod_sn {psn}; the metadata says {prod_sn}")
    bad = mid >= fmt.columns_per_frame
    if bad.any():
        raise MeasurementIdError(
            f"measurement_id {int(mid[bad][0])}; must be below columns_per_frame "
            f"{fmt.columns_per_frame}")
    pix = fmt._pixels(cols)
    out = {f.name: _decode_value(f, _word_view(pix, f.offset, f.dtype))[0].T
           for f in p.fields}
    return LidarPacket(frame_id, pid, psn, ptype, ts, mid, status, out, crc)


@dataclass(frozen=True)
class DecodedFrame:
    """Packets of one frame assembled by measurement_id (staggered (H, W) images)."""

    frame_id: int
    timestamps_ns: NDArray[np.uint64]
    status: NDArray[np.uint32]
    fields: dict[str, NDArray[np.uint32]]
    valid_columns: int


def frame_from_packets(fmt: PacketFormat, packets: Sequence[LidarPacket]) -> DecodedFrame:
    """Place decoded packets' columns by measurement_id; invalid columns stay zero."""
    H, W = fmt.pixels_per_column, fmt.columns_per_frame
    ts = np.zeros(W, np.uint64)
    st = np.zeros(W, np.uint32)
    imgs = {name: np.zeros((H, W), np.uint32) for name in fmt.field_names}
    for pk in packets:
        ok = (pk.status & 1).astype(bool)
        m = pk.measurement_id[ok]
        ts[m] = pk.timestamps_ns[ok]
        st[m] = pk.status[ok]
        for name, img in pk.fields.items():
            imgs[name][:, m] = img[:, ok]
    fid = packets[0].frame_id if packets else 0
    return DecodedFrame(fid, ts, st, imgs, int(np.count_nonzero(st & 1)))


@dataclass(frozen=True)
class PacketBatch:
    """Many lidar packets decoded at once (a receiver's frame): per packet ``frame_id`` (n,),
    per column ``timestamps_ns``, ``measurement_id`` and ``status`` (n, columns), and the
    asked-for fields as (H, n * columns) images in packet order."""

    frame_id: NDArray[np.uint16]
    timestamps_ns: NDArray[np.uint64]
    measurement_id: NDArray[np.uint16]
    status: NDArray[np.uint32]
    fields: dict[str, NDArray[np.uint32]] = field(repr=False)


def decode_lidar_packets(fmt: PacketFormat, packets: NDArray[np.uint8], *,
                         init_id: int | None = None, prod_sn: int | None = None,
                         check_crc: bool = True, crc_rows: CrcRows | None = None,
                         fields: Sequence[str] | None = None) -> PacketBatch:
    """Decode and validate an (n, packet_bytes) array of lidar packets in one pass (the same
    checks as :func:`decode_lidar_packet`; the first bad packet raises, naming its index).
    ``fields`` limits the decoded fields (default: all of the profile's)."""
    p = fmt.profile
    arr = np.asarray(packets, dtype=np.uint8)
    if arr.ndim != 2 or arr.shape[1] != fmt.packet_bytes:
        raise PacketSizeError(
            f"lidar packets of shape {arr.shape}; {p.name} with {fmt.pixels_per_column} "
            f"pixels and {fmt.columns_per_packet} columns per packet is {fmt.packet_bytes} "
            "bytes each")
    cols = fmt._columns(arr)
    ts = _word_view(cols, 0, "<u8").astype(np.uint64)
    mid = _word_view(cols, 8, "<u2").astype(np.uint16)
    if p.legacy:
        frame_id = _word_view(cols, 10, "<u2")[:, 0].astype(np.uint16)
        status = _word_view(cols, fmt.col_bytes - 4, "<u4").astype(np.uint32)
    else:
        ptype = arr[:, 0:2].copy().view("<u2")[:, 0]
        bad = np.flatnonzero(ptype != 1)
        if len(bad):
            raise PacketTypeError(f"packet {bad[0]}: packet_type {ptype[bad[0]]}; a lidar "
                                  "packet carries 1")
        frame_id = arr[:, 2:4].copy().view("<u2")[:, 0]
        weights = np.uint64(1) << (np.arange(5, dtype=np.uint64) * np.uint64(8))
        pid = arr[:, 4:7].astype(np.uint64) @ weights[:3]
        psn = arr[:, 7:12].astype(np.uint64) @ weights
        status = _word_view(cols, 10, "<u2").astype(np.uint32)
        if check_crc:
            crc = arr[:, -8:].copy().view("<u8")[:, 0]
            want = (crc_rows or crc64_xz_rows)(arr[:, :-8])
            bad = np.flatnonzero(want != crc)
            if len(bad):
                i = bad[0]
                raise CrcError(f"packet {i}: CRC-64/XZ footer 0x{int(crc[i]):016x}; the "
                               f"packet's bytes give 0x{int(want[i]):016x}")
        for name, have, want_id in (("init_id", pid, init_id), ("prod_sn", psn, prod_sn)):
            if want_id:
                bad = np.flatnonzero((have != 0) & (have != want_id))
                if len(bad):
                    raise PacketIdError(f"packet {bad[0]}: {name} {have[bad[0]]}; the metadata "
                                        f"says {want_id}")
    bad_mid = mid >= fmt.columns_per_frame
    if bad_mid.any():
        i, j = np.argwhere(bad_mid)[0]
        raise MeasurementIdError(
            f"packet {i}: measurement_id {int(mid[i, j])}; must be below columns_per_frame "
            f"{fmt.columns_per_frame}")
    return PacketBatch(frame_id, ts, mid, status, fmt.pixel_fields(arr, fields))
