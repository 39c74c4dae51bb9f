"""Lidar packets: whole-frame vectorised encoding and validated decoding (sans-IO).

Images are in the sensor's *staggered* layout: row u is beam u, column m is the column with
measurement_id m, exactly as the packets carry them (ouster-sdk decodes only this layout).
Encoding a frame is one transpose of each (H, W) image into the (packets, columns, pixels)
view of a preallocated packet array; the CRC of all packets is computed in one call.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

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
from protocols.ouster._profiles import HEADERS, PROFILES, Field, Header, Profile

__all__ = ["LidarPacket", "PacketBatch", "PacketFormat", "decode_lidar_packet",
           "decode_lidar_packets", "encode_lidar_columns", "encode_lidar_frame",
           "encode_pixel_fields", "finish_lidar_packets", "frame_from_packets",
           "shift_lidar_packet"]

CrcRows = Callable[[NDArray[np.uint8]], NDArray[np.uint64]]
LEGACY_ENCODER_TICKS = 90112  # encoder counts per revolution (legacy column header)


@dataclass(frozen=True, slots=True)
class PacketFormat:
    """Layout of one sensor's lidar packets, derived once from profile and frame geometry.

    ``header``: the packet and column header layout (:data:`HEADERS`; default the profile's,
    as ouster-sdk assumes when the metadata names no ``header_type``). ``crc``: whether the
    packet footer's last 8 bytes are a CRC-64/XZ that writers write and readers check
    (default: the header's; firmware before 2.5 had none, see
    :attr:`SensorMetadata.packet_format`); ``footer``: what they hold where there is none."""

    profile: Profile
    pixels_per_column: int = 64
    columns_per_packet: int = 16
    columns_per_frame: int = 1024
    header: Header = None  # type: ignore[assignment]  # (None: the profile's)
    crc: bool = None  # type: ignore[assignment]  # (None: the header's)
    footer: bytes = b""  # what the footer's last 8 bytes hold where there is no CRC

    def __post_init__(self) -> None:
        if self.columns_per_packet <= 0 or self.columns_per_frame % self.columns_per_packet:
            raise ValueError(f"columns_per_frame {self.columns_per_frame} is not a multiple "
                             f"of columns_per_packet {self.columns_per_packet}")
        if self.header is None:
            object.__setattr__(self, "header", HEADERS[self.profile.header])
        if self.profile.legacy != (self.header.name == "LEGACY"):
            raise ValueError(f"header {self.header.name} with profile {self.profile.name}: "
                             "LEGACY packets have LEGACY headers, and only they")
        if self.crc is None:
            object.__setattr__(self, "crc", self.header.crc)

    @classmethod
    def create(cls, profile: str, pixels_per_column: int = 64, columns_per_packet: int = 16,
               columns_per_frame: int = 1024, header_type: str | None = None,
               crc: bool | None = None) -> PacketFormat:
        if profile not in PROFILES:
            raise KeyError(f"unknown lidar profile {profile!r}; known: {', '.join(PROFILES)}")
        p = PROFILES[profile]
        if header_type not in (None, "STANDARD", "FUSA"):
            raise KeyError(f"unknown header_type {header_type!r}; known: STANDARD, FUSA")
        header = None if p.legacy or header_type is None else HEADERS[header_type]
        # (None: the defaults of __post_init__)
        return cls(p, pixels_per_column, columns_per_packet, columns_per_frame,
                   header, crc)  # type: ignore[arg-type]

    @property
    def frame_id_modulus(self) -> int:
        """Frame ids count modulo this (2**16; 2**32 with the FUSA header)."""
        f = self.header.field("frame_id")
        assert f is not None
        return 1 << f.bits

    def header_field(self, packets: NDArray[np.uint8], name: str) -> NDArray[np.uint64]:
        """A packet header field (``frame_id``, ``init_id``, ``prod_sn``, ``packet_type``,
        ``alert_flags``, ...) of each of an (n, packet_bytes) array's packets, as
        :data:`HEADERS` places it (LEGACY: the first column's frame_id; 0 for what the
        header has not)."""
        h = self.header
        if h.name == "LEGACY":
            if name != "frame_id":
                return np.zeros(packets.shape[0], np.uint64)
            return self.column_field(packets, "frame_id")[:, 0]
        f = h.field(name)
        if f is None or f not in h.packet:
            raise KeyError(f"a {h.name} packet header has no field {name!r}")
        return _read(f, packets)

    def column_field(self, packets: NDArray[np.uint8], name: str) -> NDArray[np.uint64]:
        """A column header or footer field (``timestamp``, ``measurement_id``, ``status``;
        LEGACY also ``frame_id``, ``encoder_count``) as a (packets, columns) array."""
        f, cols = self._column_word(packets, name)
        return _read(f, cols)

    def _column_word(self, packets: NDArray[np.uint8], name: str
                     ) -> tuple[Field, NDArray[np.uint8]]:
        h = self.header
        cols = self._columns(packets)
        for f in h.column:
            if f.name == name:
                return f, cols
        for f in h.column_footer:
            if f.name == name:
                return f, cols[..., self.col_bytes - self.profile.col_footer_bytes:]
        raise KeyError(f"a {h.name} column has no field {name!r}")

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
        f, cols = self._column_word(packets, "timestamp")
        return _word_view(cols, f.offset, f.dtype)

    def pixel_fields(self, packets: NDArray[np.uint8], names: Sequence[str] | None = None
                     ) -> dict[str, NDArray[np.uint32]]:
        """The (H, n * columns_per_packet) image of each named field (default: all of the
        profile's; ``RAW32_WORD1`` ... name a pixel's 32-bit words, as ouster-sdk's) in an
        (n, packet_bytes) array of packets, in packet order; no checks."""
        pix = self._pixels(self._columns(packets))
        n = packets.shape[0] * self.columns_per_packet
        p = self.profile
        want = [f for f in p.fields if names is None or f.name in names] + [
            p.field(x) for x in names or () if x.startswith("RAW32_WORD")]
        return {f.name: _decode_value(f, _word_view(pix, f.offset, f.dtype)).reshape(
            n, self.pixels_per_column).T for f in want}


def _word_view(pix: NDArray[np.uint8], offset: int, dtype: str) -> NDArray[np.generic]:
    size = np.dtype(dtype).itemsize
    return pix[..., offset:offset + size].view(dtype)[..., 0]


def _read(f: Field, block: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """Field ``f`` of each block (the last axis: the block's bytes), as uint64."""
    v = _word_view(block, f.offset, f.dtype).astype(np.uint64) & np.uint64(f.mask)
    return v >> np.uint64(f.shift) if f.shift >= 0 else v << np.uint64(-f.shift)


def _write(f: Field, block: NDArray[np.uint8], value: Any) -> None:
    """Write field ``f`` of each block, keeping the other bits of its word."""
    word = _word_view(block, f.offset, f.dtype)
    dt = word.dtype.type
    v = np.asarray(value).astype(np.uint64)
    v = v << np.uint64(f.shift) if f.shift >= 0 else v >> np.uint64(-f.shift)
    v = (v & np.uint64(f.mask)).astype(dt)
    full = (1 << (8 * word.dtype.itemsize)) - 1
    if f.mask == full:
        word[...] = v
    else:
        word[...] = np.bitwise_or(np.bitwise_and(word, dt(~f.mask & full)), v)


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
    _check_ids(fmt, frame_id, init_id, prod_sn)
    arr = out if out is not None else np.empty((fmt.packets_per_frame, fmt.packet_bytes),
                                               dtype=np.uint8)
    encode_lidar_columns(fmt, arr, 0, fields, timestamps_ns, status)
    return finish_lidar_packets(fmt, arr, frame_id=frame_id, init_id=init_id, prod_sn=prod_sn,
                                crc_rows=crc_rows)


def _check_frame(fmt: PacketFormat, frame: NDArray[np.uint8]) -> None:
    if frame.shape != (fmt.packets_per_frame, fmt.packet_bytes) or frame.dtype != np.uint8:
        raise ValueError(f"packet array of shape {frame.shape} and dtype {frame.dtype}; "
                         f"expected ({fmt.packets_per_frame}, {fmt.packet_bytes}) uint8")


def _check_ids(fmt: PacketFormat, frame_id: int, init_id: int, prod_sn: int) -> None:
    fids = fmt.frame_id_modulus
    if not 0 <= frame_id < fids or not 0 <= init_id < 1 << 24 or not 0 <= prod_sn < 1 << 40:
        raise ValueError(f"frame_id {frame_id} ({fids.bit_length() - 1} bit), init_id "
                         f"{init_id} (24 bit) or prod_sn {prod_sn} (40 bit) out of range")


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
    mid = np.arange(first_column, first_column + n, dtype=np.uint16).reshape(P, C)
    fmt.column_timestamps(arr)[...] = ts.reshape(P, C)
    _write(*fmt._column_word(arr, "measurement_id"), mid)
    if p.legacy:
        st = (np.full(n, 0xFFFFFFFF, np.uint32) if status is None
              else np.asarray(status, np.uint32))
        _write(*fmt._column_word(arr, "encoder_count"),
               mid.astype(np.uint64) * LEGACY_ENCODER_TICKS // W)
    else:
        st = np.ones(n, np.uint16) if status is None else np.asarray(status, np.uint16)
    _write(*fmt._column_word(arr, "status"), st.reshape(P, C))
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
    _check_ids(fmt, frame_id, init_id, prod_sn)
    arr = frame
    _check_frame(fmt, arr)
    if fmt.profile.legacy:
        _write(*fmt._column_word(arr, "frame_id"), frame_id)
        return arr
    h = fmt.header
    for name, v in (("packet_type", 1), ("frame_id", frame_id), ("init_id", init_id),
                    ("prod_sn", prod_sn)):  # packet_type 1: lidar
        f = h.field(name)
        assert f is not None
        _write(f, arr, v)
    if fmt.crc:
        arr[:, -8:].view("<u8")[:, 0] = (crc_rows or crc64_xz_rows)(arr[:, :-8])
    elif fmt.footer:
        arr[:, -len(fmt.footer):] = np.frombuffer(fmt.footer, np.uint8)
    return arr


def shift_lidar_packet(fmt: PacketFormat, payload: bytes, frames: int, dt_ns: int,
                       crc_rows: CrcRows | None = None) -> bytes:
    """``payload`` as the same sensor sends it ``frames`` frames and ``dt_ns`` later: the
    frame_id advanced (16 bits, wrapping), every column time stamp shifted and the CRC
    footer rewritten (a replay that loops). A payload of another size is returned as is."""
    if len(payload) != fmt.packet_bytes or (frames == 0 and dt_ns == 0):
        return payload
    arr = np.frombuffer(payload, np.uint8).copy().reshape(1, -1)
    ts = fmt.column_timestamps(arr)
    ts[...] = ts.astype(np.uint64) + np.uint64(dt_ns % (1 << 64))
    m = fmt.frame_id_modulus
    if fmt.profile.legacy:
        f, cols = fmt._column_word(arr, "frame_id")
        _write(f, cols, (_read(f, cols) + np.uint64(frames % m)) % np.uint64(m))
        return arr.tobytes()
    fid = fmt.header.field("frame_id")
    assert fid is not None
    _write(fid, arr, (_read(fid, arr) + np.uint64(frames % m)) % np.uint64(m))
    if fmt.crc:
        arr[:, -8:].view("<u8")[:, 0] = (crc_rows or crc64_xz_rows)(arr[:, :-8])
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
    0 (as ouster-sdk). The CRC is checked where the format carries one (``fmt.crc``) and
    ``check_crc``. Raises a :class:`ProtocolError` subclass naming expected and actual.
    """
    p = fmt.profile
    data = np.frombuffer(buf, dtype=np.uint8)
    if len(data) != fmt.packet_bytes:
        raise PacketSizeError(
            f"lidar packet of {len(data)} bytes; {p.name} with {fmt.pixels_per_column} pixels "
            f"and {fmt.columns_per_packet} columns per packet is {fmt.packet_bytes} bytes")
    arr = data.reshape(1, -1)
    ptype, frame_id, pid, psn, crc = _check_packets(fmt, arr, init_id, prod_sn, check_crc,
                                                    crc_rows, "")
    ts = fmt.column_field(arr, "timestamp")[0]
    mid = fmt.column_field(arr, "measurement_id")[0].astype(np.uint16)
    status = fmt.column_field(arr, "status")[0].astype(np.uint32)
    _check_mid(fmt, mid.reshape(1, -1), "")
    pix = fmt._pixels(fmt._columns(arr))
    out = {f.name: _decode_value(f, _word_view(pix, f.offset, f.dtype))[0].T
           for f in p.fields}
    return LidarPacket(int(frame_id[0]), int(pid[0]), int(psn[0]), int(ptype[0]), ts, mid,
                       status, out, None if crc is None else int(crc[0]))


def _check_packets(fmt: PacketFormat, arr: NDArray[np.uint8], init_id: int | None,
                   prod_sn: int | None, check_crc: bool, crc_rows: CrcRows | None, at: str
                   ) -> tuple[NDArray[np.uint64], NDArray[np.uint64], NDArray[np.uint64],
                              NDArray[np.uint64], NDArray[np.uint64] | None]:
    """packet_type, frame_id, init_id, prod_sn and the footer CRC (None where the format
    has none) of each packet, checked as ouster-sdk reads them, and the CRC; ``at``:
    how an error names the packet ("" for one, "packet {i}: " for many)."""
    n = arr.shape[0]
    frame_id = fmt.header_field(arr, "frame_id")
    if fmt.profile.legacy:
        ones, zeros = np.ones(n, np.uint64), np.zeros(n, np.uint64)
        return ones, frame_id, zeros, zeros, None
    ptype = fmt.header_field(arr, "packet_type")
    bad = np.flatnonzero(ptype != 1)
    if len(bad):
        raise PacketTypeError(f"{at.format(i=bad[0])}packet_type {ptype[bad[0]]}; a lidar "
                              "packet carries 1")
    pid = fmt.header_field(arr, "init_id")
    psn = fmt.header_field(arr, "prod_sn")
    crc = None
    if fmt.crc:
        crc = arr[:, -8:].copy().view("<u8")[:, 0].astype(np.uint64)
        if check_crc:
            want = (crc_rows or crc64_xz_rows)(arr[:, :-8])
            bad = np.flatnonzero(want != crc)
            if len(bad):
                i = bad[0]
                raise CrcError(f"{at.format(i=i)}CRC-64/XZ footer 0x{int(crc[i]):016x}; the "
                               f"packet's bytes give 0x{int(want[i]):016x}")
    for name, have, want_id in (("init_id", pid, init_id), ("prod_sn", psn, prod_sn)):
        if want_id:
            bad = np.flatnonzero((have != 0) & (have != want_id))
            if len(bad):
                raise PacketIdError(f"{at.format(i=bad[0])}{name} {have[bad[0]]}; the "
                                    f"metadata says {want_id}")
    return ptype, frame_id, pid, psn, crc


def _check_mid(fmt: PacketFormat, mid: NDArray[np.uint16], at: str) -> None:
    bad_mid = mid >= fmt.columns_per_frame
    if bad_mid.any():
        i, j = np.argwhere(bad_mid)[0]
        raise MeasurementIdError(
            f"{at.format(i=i)}measurement_id {int(mid[i, j])}; must be below "
            f"columns_per_frame {fmt.columns_per_frame}")


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

    frame_id: NDArray[np.uint16] | NDArray[np.uint32]  # (uint32 with the FUSA header)
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
    _ptype, fid, _pid, _psn, _crc = _check_packets(fmt, arr, init_id, prod_sn, check_crc,
                                                   crc_rows, "packet {i}: ")
    frame_id: NDArray[np.uint16] | NDArray[np.uint32] = (
        fid.astype(np.uint32) if fmt.frame_id_modulus > 65536 else fid.astype(np.uint16))
    ts = fmt.column_field(arr, "timestamp")
    mid = fmt.column_field(arr, "measurement_id").astype(np.uint16)
    status = fmt.column_field(arr, "status").astype(np.uint32)
    _check_mid(fmt, mid, "packet {i}: ")
    return PacketBatch(frame_id, ts, mid, status, fmt.pixel_fields(arr, fields))
