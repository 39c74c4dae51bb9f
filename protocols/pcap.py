"""libpcap / pcapng with Ethernet + IPv4 + UDP framing (sans-IO: bytes in, bytes out).

Writing: a libpcap file (nanosecond or microsecond time stamps) whose records are Ethernet
frames carrying IPv4/UDP datagrams; datagrams larger than the MTU are split into IPv4
fragments as a real 1500-byte link would carry a sensor's 12.5 kB packets. Time stamps come
from the caller (the simulation clock), never from a clock read here.

Reading: libpcap (either byte order, µs or ns) and pcapng (SHB, IDB, EPB, SPB, with per-
interface time resolution); Ethernet (with 802.1Q tags) + IPv4 + UDP; fragments reassembled;
from bytes or streamed from a binary file (:class:`UdpReader`: memory stays one record).
"""

from __future__ import annotations

import io
import struct
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

__all__ = ["LIBPCAP_MAGICS", "PcapError", "PcapWriter", "UdpDatagram", "UdpReader",
           "libpcap_resync",
           "read_udp"]

LINKTYPE_ETHERNET = 1
MAX_RECORD = 1 << 18  # bytes: a record claiming more is damage (IPv4's largest is 64 KiB)
MAX_PENDING = 256  # datagrams awaiting fragments: the oldest is dropped beyond this
_ETH = struct.Struct("!6s6sH")
_IP = struct.Struct("!BBHHHBBH4s4s")
_UDP = struct.Struct("!HHHH")
_SRC_MAC = bytes.fromhex("bc0fa7000001")  # Ouster's OUI, a made-up device
_DST_MAC = bytes.fromhex("020000000001")  # locally administered


class PcapError(ValueError):
    """A capture file is malformed; the message says where and what was expected."""


@dataclass(frozen=True, slots=True)
class UdpDatagram:
    timestamp_ns: int
    src_ip: str
    dst_ip: str
    src_port: int
    dst_port: int
    payload: bytes  # (a writer reads it as a buffer only: a view serves as well)


def _ip_bytes(ip: str) -> bytes:
    try:
        parts = [int(p) for p in ip.split(".")]
    except ValueError as err:
        raise ValueError(f"IPv4 address {ip!r} is not dotted decimal") from err
    if len(parts) != 4 or any(not 0 <= p <= 255 for p in parts):
        raise ValueError(f"IPv4 address {ip!r} is not dotted decimal")
    return bytes(parts)


def _checksum(header: bytes) -> int:
    s: int = sum(struct.unpack(f"!{len(header) // 2}H", header))
    while s >> 16:
        s = (s & 0xFFFF) + (s >> 16)
    return ~s & 0xFFFF


@dataclass(frozen=True)
class _Layout:
    """The records of one kind of datagram (:meth:`PcapWriter._layout`): ``width`` bytes,
    of which ``template`` gives those at ``fixed``; the columns of the time stamp (8 a
    fragment), the IP id's and checksum's high and low bytes (one a fragment), each
    fragment's header sum without its id (``base``), and where the payload's spans go
    (``(column, start, end)``)."""

    width: int
    template: NDArray[np.uint8]
    fixed: NDArray[np.intp]
    stamp: NDArray[np.intp]
    id_hi: NDArray[np.intp]
    id_lo: NDArray[np.intp]
    sum_hi: NDArray[np.intp]
    sum_lo: NDArray[np.intp]
    base: NDArray[np.int64]
    payload: list[tuple[int, int, int]]


class PcapWriter:
    """Builds a libpcap byte stream; call :meth:`header` once, then :meth:`records`.

    Args:
        mtu: IPv4 MTU of the simulated link (fragments above it; >= 68).
        nanosecond: ns time stamps (magic a1b23c4d) or µs (a1b2c3d4).
        snaplen: the header's snapshot length.
    """

    def __init__(self, *, mtu: int = 1500, nanosecond: bool = True,
                 snaplen: int = 65535) -> None:
        if mtu < 68:
            raise ValueError(f"mtu {mtu}; IPv4 needs at least 68")
        self.mtu = mtu
        self.nanosecond = nanosecond
        self.snaplen = snaplen
        self._ip_id = 0
        self._layouts: dict[tuple[Any, ...], _Layout] = {}
        self._spare: dict[tuple[int, int], NDArray[np.uint8]] = {}

    def header(self) -> bytes:
        magic = 0xA1B23C4D if self.nanosecond else 0xA1B2C3D4
        return struct.pack("<IHHiIII", magic, 2, 4, 0, 0, self.snaplen, LINKTYPE_ETHERNET)

    def _record(self, ts_ns: int, frame: bytes) -> bytes:
        sec, rem = divmod(ts_ns, 1_000_000_000)
        frac = rem if self.nanosecond else rem // 1000
        return struct.pack("<IIII", sec, frac, len(frame), len(frame)) + frame

    def records(self, d: UdpDatagram) -> bytes:
        """The pcap record(s) of one UDP datagram (several if it is fragmented)."""
        ip_id = (self._ip_id + 1) & 0xFFFF
        out = self._records_of(d, ip_id)  # (a datagram refused takes no id)
        self._ip_id = ip_id
        return out

    def _records_of(self, d: UdpDatagram, ip_id: int) -> bytes:
        if not 0 <= d.timestamp_ns < (1 << 32) * 1_000_000_000:
            raise ValueError(f"timestamp_ns {d.timestamp_ns} does not fit a pcap record")
        if len(d.payload) > 65507:
            raise ValueError(f"UDP payload of {len(d.payload)} bytes exceeds 65507")
        src, dst = _ip_bytes(d.src_ip), _ip_bytes(d.dst_ip)
        udp = _UDP.pack(d.src_port, d.dst_port, 8 + len(d.payload), 0) + d.payload
        room = (self.mtu - 20) // 8 * 8
        out = []
        off = 0
        while True:
            chunk = udp[off:off + room] if len(udp) - off > self.mtu - 20 else udp[off:]
            more = off + len(chunk) < len(udp)
            flags_frag = (0x2000 if more else 0) | (off // 8)
            hdr = _IP.pack(0x45, 0, 20 + len(chunk), ip_id, flags_frag, 64, 17, 0,
                           src, dst)
            hdr = hdr[:10] + struct.pack("!H", _checksum(hdr)) + hdr[12:]
            out.append(self._record(d.timestamp_ns,
                                    _ETH.pack(_DST_MAC, _SRC_MAC, 0x0800) + hdr + chunk))
            off += len(chunk)
            if not more:
                return b"".join(out)

    def records_many(self, datagrams: Sequence[UdpDatagram]) -> bytes:
        """:meth:`records` of each datagram, joined: the same bytes (the IP ids go on in
        the datagrams' order), the alike datagrams (same length, addresses and ports: a
        frame's lidar packets, wherever its IMU packets fall between them) built together
        as arrays, so a frame of 128 packets in 2,000 fragments costs a few array
        operations."""
        return b"".join(self.records_parts(datagrams))

    def records_parts(self, datagrams: Sequence[UdpDatagram]) -> list[bytes | memoryview]:
        """:meth:`records_many` in pieces, one a datagram, in order (for a gathered write:
        a frame's few megabytes are not joined into one more copy first). A payload may be
        any bytes-like object."""
        n = len(datagrams)
        ids = [(self._ip_id + 1 + i) & 0xFFFF for i in range(n)]
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, d in enumerate(datagrams):
            groups.setdefault((len(d.payload), d.src_ip, d.dst_ip, d.src_port, d.dst_port),
                              []).append(i)
        pieces: list[Any] = [b""] * n
        for idx in groups.values():
            if len(idx) < 4:
                for i in idx:
                    pieces[i] = self._records_of(datagrams[i], ids[i])
                continue
            rows = self._alike_records([datagrams[i] for i in idx],
                                       np.array([ids[i] for i in idx], np.int64))
            for r, i in enumerate(idx):
                pieces[i] = rows[r].data
        if n:  # (datagrams refused take no ids)
            self._ip_id = ids[-1]
        return pieces

    def _alike_records(self, run: Sequence[UdpDatagram], ids: NDArray[np.int64]
                       ) -> NDArray[np.uint8]:
        """The records of alike datagrams with their IP ids, one row each."""
        d0 = run[0]
        L = len(d0.payload)
        if L > 65507:
            raise ValueError(f"UDP payload of {L} bytes exceeds 65507")
        ts = np.array([d.timestamp_ns for d in run], np.int64)
        bad = (ts < 0) | (ts >= (1 << 32) * 1_000_000_000)
        if bad.any():
            raise ValueError(f"timestamp_ns {int(ts[bad][0])} does not fit a pcap record")
        lay = self._layout(L, d0.src_ip, d0.dst_ip, d0.src_port, d0.dst_port)
        M = len(run)
        payload = self._scratch(M, L)
        for r, d in enumerate(run):
            payload[r] = np.frombuffer(d.payload, np.uint8)
        sec, rem = np.divmod(ts, 1_000_000_000)
        stamp = np.empty((M, 2), "<u4")
        stamp[:, 0], stamp[:, 1] = sec, rem if self.nanosecond else rem // 1000
        out = self._scratch(M, lay.width)
        out[:, lay.fixed] = lay.template[lay.fixed]
        out[:, lay.stamp] = np.tile(stamp.view(np.uint8), lay.base.size)
        total = lay.base[None, :] + ids[:, None]  # each fragment's header sum with its id
        while (total >> 16).any():
            total = (total & 0xFFFF) + (total >> 16)
        csum = ~total & 0xFFFF
        out[:, lay.id_hi], out[:, lay.id_lo] = (ids >> 8)[:, None], (ids & 0xFF)[:, None]
        out[:, lay.sum_hi], out[:, lay.sum_lo] = csum >> 8, csum & 0xFF
        for col, a, b in lay.payload:
            out[:, col:col + b - a] = payload[:, a:b]
        return out

    def _scratch(self, rows: int, width: int) -> NDArray[np.uint8]:
        """A (rows, width) uint8 array to fill: the one the last call of this shape had,
        where nothing else holds it any more (the pieces of a frame's records are written
        before the next frame's are built), else a new one. A frame's few megabytes in a
        new array each time cost more in page faults than in the copying (3 ms a 2048x10
        frame against 1)."""
        key = (rows, width)
        buf = self._spare.get(key)
        if buf is None or sys.getrefcount(buf) > 3:  # (the dict's, buf's and the call's)
            if len(self._spare) >= 8:
                self._spare.clear()
            buf = self._spare[key] = np.empty((rows, width), np.uint8)
        return buf

    def _layout(self, L: int, src_ip: str, dst_ip: str, src_port: int, dst_port: int
                ) -> _Layout:
        """Where each byte of the records of a datagram of ``L`` bytes goes (the same for
        every such datagram but its time stamp, IP id and checksum): kept for the next."""
        key = (L, src_ip, dst_ip, src_port, dst_port, self.mtu)
        lay = self._layouts.get(key)
        if lay is not None:
            return lay
        src, dst = _ip_bytes(src_ip), _ip_bytes(dst_ip)
        room = (self.mtu - 20) // 8 * 8
        size = 8 + L
        pieces = []  # each fragment's length
        off = 0
        while True:
            clen = room if size - off > self.mtu - 20 else size - off
            pieces.append(clen)
            off += clen
            if off >= size:
                break
        width = sum(50 + c for c in pieces)
        template = np.zeros(width, np.uint8)
        fixed = np.zeros(width, bool)  # the bytes the template gives every record
        stamp: list[int] = []
        id_hi: list[int] = []
        sum_hi: list[int] = []
        base: list[int] = []
        spans: list[tuple[int, int, int]] = []
        col = off = 0
        for clen in pieces:
            more = off + clen < size
            flags_frag = (0x2000 if more else 0) | (off // 8)
            hdr = _IP.pack(0x45, 0, 20 + clen, 0, flags_frag, 64, 17, 0, src, dst)
            base.append(sum(struct.unpack("!10H", hdr)))
            flen = 14 + 20 + clen
            template[col + 8:col + 16] = np.frombuffer(struct.pack("<II", flen, flen), np.uint8)
            template[col + 16:col + 30] = np.frombuffer(_ETH.pack(_DST_MAC, _SRC_MAC, 0x0800),
                                                        np.uint8)
            template[col + 30:col + 50] = np.frombuffer(hdr, np.uint8)
            fixed[col + 8:col + 50] = True
            stamp.extend(range(col, col + 8))
            id_hi.append(col + 34)
            sum_hi.append(col + 40)
            fixed[[col + 34, col + 35, col + 40, col + 41]] = False
            if off == 0:  # the first fragment carries the UDP header
                template[col + 50:col + 58] = np.frombuffer(
                    _UDP.pack(src_port, dst_port, size, 0), np.uint8)
                fixed[col + 50:col + 58] = True
                spans.append((col + 58, 0, clen - 8))
            else:
                spans.append((col + 50, off - 8, off - 8 + clen))
            col += 50 + clen
            off += clen
        hi, sh = np.array(id_hi, np.intp), np.array(sum_hi, np.intp)
        lay = _Layout(width, template, np.flatnonzero(fixed), np.array(stamp, np.intp),
                      hi, hi + 1, sh, sh + 1, np.array(base, np.int64), spans)
        if len(self._layouts) >= 64:  # (a writer sees a few kinds: lidar and IMU packets)
            self._layouts.clear()
        self._layouts[key] = lay
        return lay

    def encode(self, datagrams: Iterable[UdpDatagram]) -> bytes:
        """A whole file: header and every datagram."""
        return self.header() + b"".join(self.records(d) for d in datagrams)


class _Stream:
    """Exact reads from a binary stream, with the byte position for error messages."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.pos = 0

    def read(self, n: int, what: str) -> bytes:
        """``n`` bytes; b"" at a clean end (nothing left); PcapError when cut short."""
        b = self.f.read(n)
        if len(b) != n:
            if not b:
                return b""
            raise PcapError(f"{what} at byte {self.pos} is truncated: {n} bytes expected, "
                            f"{len(b)} remain")
        self.pos += n
        return b


def _frames(f: BinaryIO) -> Iterator[tuple[int, bytes]]:
    """(timestamp_ns, link-layer frame) of every Ethernet record, pcap or pcapng, read from
    a binary stream as they come (memory: one record)."""
    src = _Stream(f)
    magic = src.f.read(4)
    src.pos = len(magic)
    if len(magic) < 4:
        raise PcapError(f"capture of {len(magic)} bytes is too short for a header")
    if magic == b"\x0a\x0d\x0d\x0a":
        yield from _pcapng_frames(src, magic)
        return
    table = {b"\xd4\xc3\xb2\xa1": ("<", 1000), b"\xa1\xb2\xc3\xd4": (">", 1000),
             b"\x4d\x3c\xb2\xa1": ("<", 1), b"\xa1\xb2\x3c\x4d": (">", 1)}
    if magic not in table:
        raise PcapError(f"magic {magic.hex()} is neither libpcap nor pcapng")
    end, scale = table[magic]
    head = src.read(20, "libpcap global header")
    if len(head) < 20:
        raise PcapError("libpcap global header is truncated (24 bytes expected)")
    linktype = struct.unpack(end + "I", head[16:20])[0] & 0x0FFFFFFF
    if linktype != LINKTYPE_ETHERNET:
        raise PcapError(f"link type {linktype}; only Ethernet (1) is supported")
    rec = struct.Struct(end + "IIII")
    while True:
        at = src.pos
        hdr = src.read(16, "record header")
        if not hdr:
            return
        sec, frac, incl, _orig = rec.unpack(hdr)
        if incl > MAX_RECORD:
            raise PcapError(f"record at byte {at} claims {incl} bytes; no frame is over "
                            f"{MAX_RECORD}")
        body = src.read(incl, f"record at byte {at} (claims {incl} bytes)") if incl else b""
        if len(body) != incl:
            raise PcapError(f"record at byte {at} claims {incl} bytes; none remain")
        yield sec * 1_000_000_000 + frac * scale, body


def _pcapng_frames(src: _Stream, first: bytes) -> Iterator[tuple[int, bytes]]:
    end = "<"
    ifaces: list[tuple[int, int]] = []  # (linktype, ns per tick)
    head = first
    while True:
        pos = src.pos - len(head)
        head += src.read(8 - len(head), "pcapng block")
        if not head:
            return
        if len(head) < 8:
            raise PcapError(f"pcapng block at byte {pos} is truncated")
        btype = struct.unpack_from(end + "I", head, 0)[0]
        if btype == 0x0A0D0D0A:
            rest = src.read(4, "pcapng section header")
            bom = rest
            end = "<" if bom == b"\x4d\x3c\x2b\x1a" else ">" if bom == b"\x1a\x2b\x3c\x4d" \
                else ""
            if not end:
                raise PcapError(f"pcapng section at byte {pos} has byte-order magic "
                                f"{bom.hex()}")
            ifaces = []
        else:
            rest = b""
        blen = struct.unpack_from(end + "I", head, 4)[0]
        if blen < 12 or blen % 4 or blen > MAX_RECORD + 64:
            raise PcapError(f"pcapng block at byte {pos} has length {blen}")
        tail = src.read(blen - 8 - len(rest), f"pcapng block of {blen} bytes")
        if len(tail) != blen - 8 - len(rest):
            raise PcapError(f"pcapng block at byte {pos} has length {blen}")
        block = head + rest + tail
        head = b""
        body = block[8:blen - 4]
        least = {1: 8, 6: 20, 3: 4}.get(btype, 0)  # IDB, EPB, SPB fixed fields
        if len(body) < least:
            raise PcapError(f"pcapng block type {btype} at byte {pos} has {len(body)} body "
                            f"bytes; at least {least} expected")
        if btype == 1:  # interface description
            link = struct.unpack_from(end + "H", body, 0)[0]
            tick = 1000  # default µs
            opt = 8
            while opt + 4 <= len(body):
                code, olen = struct.unpack_from(end + "HH", body, opt)
                if code == 0:
                    break
                if opt + 4 + olen > len(body):
                    raise PcapError(f"pcapng interface option {code} at byte {pos + 8 + opt} "
                                    f"claims {olen} bytes; {len(body) - opt - 4} remain")
                if code == 9 and olen >= 1:  # if_tsresol
                    r = body[opt + 4]
                    tick = 2 ** -(r & 0x7F) * 1e9 if r & 0x80 else 10 ** (9 - r)
                opt += 4 + (olen + 3) // 4 * 4
            ifaces.append((link, tick))
        elif btype in (6, 3):  # enhanced / simple packet
            if btype == 6:
                iid, hi, lo, cap, _orig = struct.unpack_from(end + "IIIII", body, 0)
                payload = body[20:20 + cap]
            else:
                iid, hi, lo = 0, 0, 0
                cap = struct.unpack_from(end + "I", body, 0)[0]
                payload = body[4:4 + cap]
            if iid >= len(ifaces):
                raise PcapError(f"pcapng packet at byte {pos} names interface {iid}; "
                                f"{len(ifaces)} described")
            link, tick = ifaces[iid]
            if link == LINKTYPE_ETHERNET:
                yield int(((hi << 32) | lo) * tick), payload


def read_udp(data: bytes) -> Iterator[UdpDatagram]:
    """Every IPv4/UDP datagram in a capture, fragments reassembled, in capture order (a
    fragmented datagram appears at its last fragment's position, with its first fragment's
    time stamp). Non-IPv4 and non-UDP frames are skipped."""
    return iter(UdpReader(io.BytesIO(data)))


class UdpReader:
    """The datagrams of a capture read from a binary stream as they come (memory: one
    record and the fragments of datagrams not yet whole), as :func:`read_udp` gives them;
    ``skipped`` counts the frames that were not IPv4/UDP (other traffic)."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.skipped = 0

    def __iter__(self) -> Iterator[UdpDatagram]:
        return self._read()

    def _read(self) -> Iterator[UdpDatagram]:
        pending: dict[tuple[bytes, bytes, int], tuple[int, dict[int, bytes], int | None]] = {}
        for ts, frame in _frames(self.f):
            d = self._datagram(ts, frame, pending)
            if d is not None:
                yield d

    def _datagram(self, ts: int, frame: bytes,
                  pending: dict[tuple[bytes, bytes, int],
                                tuple[int, dict[int, bytes], int | None]]
                  ) -> UdpDatagram | None:
        if len(frame) < 14:
            self.skipped += 1
            return None
        etype = struct.unpack_from("!H", frame, 12)[0]
        off = 14
        while etype == 0x8100 and len(frame) >= off + 4:  # 802.1Q
            etype = struct.unpack_from("!H", frame, off + 2)[0]
            off += 4
        if etype != 0x0800 or len(frame) < off + 20:
            self.skipped += 1
            return None
        vihl, _tos, total, ident, ff, _ttl, proto, _cs, src, dst = _IP.unpack_from(frame, off)
        ihl = (vihl & 0x0F) * 4
        if vihl >> 4 != 4 or ihl < 20 or proto != 17:
            self.skipped += 1
            return None
        body = frame[off + ihl:off + total]
        if len(body) != total - ihl:
            raise PcapError(f"IPv4 datagram says {total} bytes; the frame holds "
                            f"{len(frame) - off}")
        more, frag = bool(ff & 0x2000), (ff & 0x1FFF) * 8
        if more or frag:
            key = (src, dst, ident)
            if key in pending and frag in pending[key][1]:  # the ident came round again
                del pending[key]  # (a datagram that lost a fragment, 65536 datagrams ago)
            if key not in pending:
                while len(pending) >= MAX_PENDING:  # a lost fragment: give its datagram up
                    del pending[next(iter(pending))]
            t0, parts, last = pending.get(key, (ts, {}, None))
            parts[frag] = body
            if not more:
                last = frag + len(body)
            pending[key] = (t0, parts, last)
            if last is None:
                return None
            buf = bytearray()
            for o in sorted(parts):
                if o != len(buf):
                    break
                buf += parts[o]
            if len(buf) != last:
                return None
            del pending[key]
            ts, body = t0, bytes(buf)
        if len(body) < 8:
            raise PcapError("UDP header truncated")
        sport, dport, ulen, _ = _UDP.unpack_from(body, 0)
        if ulen < 8 or ulen > len(body):
            raise PcapError(f"UDP length {ulen}; the datagram holds {len(body)} bytes")
        return UdpDatagram(ts, ".".join(map(str, src)), ".".join(map(str, dst)), sport, dport,
                          body[8:ulen])


_LIBPCAP_MAGIC = {b"\xd4\xc3\xb2\xa1": ("<", 1_000_000), b"\xa1\xb2\xc3\xd4": (">", 1_000_000),
                  b"\x4d\x3c\xb2\xa1": ("<", 1_000_000_000),
                  b"\xa1\xb2\x3c\x4d": (">", 1_000_000_000)}
LIBPCAP_MAGICS = tuple(_LIBPCAP_MAGIC)  # the four first bytes of a libpcap capture


def libpcap_resync(global_header: bytes, buf: bytes, start: int = 0, chain: int = 4
                   ) -> int | None:
    """The first offset at or after ``start`` in ``buf`` (bytes read from anywhere inside a
    libpcap capture whose first 24 bytes are ``global_header``) where ``chain`` record
    headers in a row are plausible: a sub-second field below one second, a captured length
    of at least an Ethernet header and within the snapshot length and the original length,
    time stamps that do not go back nor jump an hour. None when there is no such offset (or
    the capture is not libpcap), so a reader can start in the middle of a capture:
    ``global_header + buf[offset:]``."""
    form = _LIBPCAP_MAGIC.get(global_header[:4])
    if form is None or len(global_header) < 24:
        return None
    end, frac_limit = form
    snap = struct.unpack(end + "I", global_header[16:20])[0] or MAX_RECORD
    rec = struct.Struct(end + "IIII")
    limit = min(snap, MAX_RECORD)
    for at in range(start, max(start, len(buf) - 16 * chain)):
        p, prev, ok = at, None, 0
        while ok < chain and p + 16 <= len(buf):
            sec, frac, incl, orig = rec.unpack_from(buf, p)
            if frac >= frac_limit or not 14 <= incl <= limit or orig < incl \
                    or orig > MAX_RECORD:
                break
            if prev is not None and not prev <= sec <= prev + 3600:
                break
            prev, p, ok = sec, p + 16 + incl, ok + 1
        if ok == chain:
            return at
    return None
