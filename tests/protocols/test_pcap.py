"""pcap framing: our files read by dpkt and by ouster-sdk (fragmented at a 1500-byte MTU),
dpkt's pcap and pcapng files read by us, fragments reassembled, errors clear."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import dpkt
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ouster.sdk import pcap as opcap

import protocols.ouster as o
from protocols.pcap import PcapError, PcapWriter, UdpDatagram, libpcap_resync, read_udp

ips = st.tuples(*[st.integers(0, 255)] * 4).map(lambda t: ".".join(map(str, t)))


@st.composite
def datagrams(draw: st.DrawFn) -> list[UdpDatagram]:
    n = draw(st.integers(0, 6))
    t = draw(st.integers(1, 2**40))
    out = []
    for i in range(n):
        out.append(UdpDatagram(t + i * 1000, draw(ips), draw(ips), draw(st.integers(0, 65535)),
                               draw(st.integers(0, 65535)),
                               draw(st.binary(max_size=5000))))
    return out


@settings(max_examples=80, deadline=None)
@given(datagrams(), st.sampled_from([68, 576, 1500, 9000]), st.booleans())
def test_round_trip_with_fragmentation(ds: list[UdpDatagram], mtu: int, ns: bool) -> None:
    data = PcapWriter(mtu=mtu, nanosecond=ns).encode(ds)
    back = list(read_udp(data))
    if not ns:
        ds = [UdpDatagram(d.timestamp_ns // 1000 * 1000, d.src_ip, d.dst_ip, d.src_port,
                          d.dst_port, d.payload) for d in ds]
    assert back == ds


@st.composite
def runs_of_datagrams(draw: st.DrawFn) -> list[UdpDatagram]:
    """Runs of alike datagrams (a frame's lidar packets) among odd ones (IMU packets)."""
    out: list[UdpDatagram] = []
    t = draw(st.integers(0, 2**40))
    for _ in range(draw(st.integers(0, 4))):
        src, dst = draw(ips), draw(ips)
        ports = draw(st.integers(0, 65535)), draw(st.integers(0, 65535))
        size = draw(st.integers(0, 9000))
        for _ in range(draw(st.integers(1, 9))):
            t += draw(st.integers(0, 10**6))
            out.append(UdpDatagram(t, src, dst, *ports, draw(st.binary(min_size=size,
                                                                        max_size=size))))
    if draw(st.booleans()):  # alike datagrams apart (a frame's lidar packets, IMU between)
        out = draw(st.permutations(out))
    return out


@settings(max_examples=80, deadline=None)
@given(runs_of_datagrams(), st.sampled_from([68, 576, 1500, 9000]), st.booleans(),
       st.integers(0, 65535))
def test_records_of_many_are_the_records_of_each(ds: list[UdpDatagram], mtu: int, ns: bool,
                                                 ip_id: int) -> None:
    """The array-built records of a frame are byte for byte those built one by one, and
    the IP ids go on from the same place."""
    a, b = PcapWriter(mtu=mtu, nanosecond=ns), PcapWriter(mtu=mtu, nanosecond=ns)
    a._ip_id = b._ip_id = ip_id
    assert a.records_many(ds) == b"".join(b.records(d) for d in ds)
    assert a._ip_id == b._ip_id
    # again on the same writer (the layouts it kept), the payloads as views, in pieces
    views = [UdpDatagram(d.timestamp_ns, d.src_ip, d.dst_ip, d.src_port, d.dst_port,
                         memoryview(d.payload)) for d in ds]  # type: ignore[arg-type]
    assert b"".join(a.records_parts(views)) == b"".join(b.records(d) for d in ds)
    assert a._ip_id == b._ip_id


def test_pieces_still_held_are_never_written_over() -> None:
    """The writer fills the arrays of the last frame's records again only once nothing
    holds their pieces: pieces kept across calls keep their bytes."""
    ds = [UdpDatagram(1000 * i, "10.0.0.1", "10.0.0.2", 7502, 7502, bytes([i]) * 3000)
          for i in range(8)]
    w = PcapWriter()
    first = w.records_parts(ds)
    want = b"".join(first)
    again = [UdpDatagram(d.timestamp_ns + 1, d.src_ip, d.dst_ip, d.src_port, d.dst_port,
                         bytes([255 - d.payload[0]]) * 3000) for d in ds]
    second = w.records_parts(again)
    assert b"".join(first) == want
    assert b"".join(second) != want
    assert PcapWriter().records_many(ds) == want


def test_records_of_many_refuse_what_records_refuse() -> None:
    d = UdpDatagram(-1, "10.0.0.1", "10.0.0.2", 7502, 7502, bytes(100))
    w = PcapWriter()
    with pytest.raises(ValueError, match="timestamp_ns -1"):
        w.records_many([d] * 5)
    with pytest.raises(ValueError, match="timestamp_ns -1"):
        w.records(d)
    assert w._ip_id == 0  # what is refused takes no IP id
    with pytest.raises(ValueError, match="exceeds 65507"):
        PcapWriter().records_many([UdpDatagram(0, "10.0.0.1", "10.0.0.2", 1, 1,
                                               bytes(65508))] * 5)


def test_dpkt_reads_our_frames_and_checksums() -> None:
    payload = bytes(range(256)) * 49  # 12544 bytes, like an RNG19 packet
    data = PcapWriter(mtu=1500).encode([UdpDatagram(1_700_000_000_123_456_789, "127.0.0.1",
                                                    "127.0.0.1", 7502, 7502, payload)])
    recs = list(dpkt.pcap.Reader(io.BytesIO(data)))
    assert len(recs) == 9  # 12552 bytes of UDP in 1480-byte fragments
    assert float(recs[0][0]) == pytest.approx(1_700_000_000.123456789)
    total = 0
    for i, (_, buf) in enumerate(recs):
        ip = dpkt.ethernet.Ethernet(buf).data
        assert isinstance(ip, dpkt.ip.IP)
        assert ip.len <= 1500 and ip.offset * 8 == total and bool(ip.mf) == (i < 8)
        hdr = bytes(ip)[:20]
        assert dpkt.in_cksum(hdr) == 0  # header checksum valid
        total += len(ip.data) if isinstance(ip.data, bytes) else len(bytes(ip.data))
    assert total == 8 + len(payload)


def test_we_read_dpkt_pcapng_and_pcap(tmp_path: Path) -> None:
    ds = [UdpDatagram(1_000_000_000 + i, "10.0.0.2", "10.0.0.9", 7502 + i, 7502 + i,
                      bytes([i]) * (100 + i)) for i in range(3)]
    frames = []
    for d in ds:
        udp = dpkt.udp.UDP(sport=d.src_port, dport=d.dst_port, data=d.payload)
        udp.ulen = 8 + len(d.payload)
        ip = dpkt.ip.IP(src=bytes(map(int, d.src_ip.split("."))),
                        dst=bytes(map(int, d.dst_ip.split("."))), p=17, data=udp)
        frames.append(bytes(dpkt.ethernet.Ethernet(data=ip, type=0x0800)))
    for writer in (dpkt.pcapng.Writer, dpkt.pcap.Writer):
        buf = io.BytesIO()
        w = writer(buf)
        for d, f in zip(ds, frames, strict=True):
            w.writepkt(f, ts=d.timestamp_ns / 1e9)
        back = list(read_udp(buf.getvalue()))
        assert [(b.src_ip, b.dst_port, b.payload) for b in back] == \
            [(d.src_ip, d.dst_port, d.payload) for d in ds]
        assert all(abs(b.timestamp_ns - d.timestamp_ns) < 1000 for b, d in zip(back, ds,
                                                                                strict=True))


@pytest.mark.parametrize("profile", list(o.PROFILES))
def test_ouster_sdk_reads_our_fragmented_pcap(tmp_path: Path, profile: str) -> None:
    m = o.os0_64_metadata("1024x10", profile)
    fmt = m.packet_format
    rng = np.random.default_rng(0)
    w = PcapWriter(mtu=1500)
    chunks = [w.header()]
    ranges = []
    for fid in range(3):
        rr = (rng.integers(500, 40000, (64, 1024)) // 8 * 8).astype(np.uint32)
        ranges.append(rr)
        ts = 10**9 + fid * 10**8 + np.arange(1024, dtype=np.uint64) * 97_656
        arr = o.encode_lidar_frame(fmt, {"RANGE": rr}, ts, frame_id=fid, init_id=m.init_id,
                                   prod_sn=m.prod_sn)
        for i in range(arr.shape[0]):
            chunks.append(w.records(UdpDatagram(int(ts[(i + 1) * 16 - 1]), "127.0.0.1",
                                                "127.0.0.1", 7502, 7502, arr[i].tobytes())))
        imu = o.encode_imu_packet(o.ImuPacket(int(ts[0]), int(ts[0]), int(ts[0]),
                                              (0.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
        chunks.append(w.records(UdpDatagram(int(ts[-1]), "127.0.0.1", "127.0.0.1", 7503, 7503,
                                            imu)))
    p = tmp_path / "x.pcap"
    p.write_bytes(b"".join(chunks))
    (tmp_path / "x.json").write_text(m.dumps())
    src = opcap.PcapFrameSetSource(str(p), meta=[str(tmp_path / "x.json")])
    frames = [fs[0] for fs in src]
    assert [f.frame_id for f in frames] == [0, 1, 2]
    for f, rr in zip(frames, ranges, strict=True):
        assert f.complete()
        # (ouster-sdk's FIVE_WORD_PIXEL frame holds only the raw words)
        got = f.field("RANGE") if "RANGE" in f.fields else f.field("RAW32_WORD1") & 0x7FFFF
        np.testing.assert_array_equal(got, rr)


def test_malformed_captures_raise_pcap_error() -> None:
    good = PcapWriter().encode([UdpDatagram(5, "1.2.3.4", "5.6.7.8", 1, 2, b"abc")])
    for bad in (b"", b"\x00\x01\x02\x03" * 8, good[:30], good[:-2]):
        with pytest.raises(PcapError):
            list(read_udp(bad))
    with pytest.raises(ValueError, match="dotted decimal"):
        PcapWriter().records(UdpDatagram(0, "localhost", "1.2.3.4", 1, 2, b""))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 200))
def test_fuzzed_captures_give_datagrams_or_pcap_error(junk: bytes, at: int) -> None:
    good = PcapWriter(mtu=200).encode([UdpDatagram(5, "1.2.3.4", "5.6.7.8", 1, 2, b"x" * 500)])
    data = good[:at] + junk + good[at + len(junk):]
    try:
        list(read_udp(data))
    except PcapError:
        pass


def _boundaries(data: bytes) -> list[int]:
    """The true record offsets of a libpcap capture (walked from its header)."""
    end = "<" if data[:4] in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1") else ">"
    out, p = [], 24
    while p + 16 <= len(data):
        out.append(p)
        p += 16 + struct.unpack_from(end + "I", data, p + 8)[0]
    return out


@settings(max_examples=60, deadline=None)
@given(datagrams(), st.sampled_from([576, 1500]), st.booleans(), st.floats(0, 1))
def test_resync_finds_the_next_record_from_anywhere(ds: list[UdpDatagram], mtu: int,
                                                    ns: bool, where: float) -> None:
    """From any byte inside a capture, the reader starts again at the first record that
    begins there or after (and the datagrams from there on read as written)."""
    data = PcapWriter(mtu=mtu, nanosecond=ns).encode(ds)
    start = 24 + int(where * (len(data) - 24))
    bounds = _boundaries(data)
    got = libpcap_resync(data[:24], data[24:], start - 24)
    chainable = [b for b in bounds if b >= start and len(bounds) - bounds.index(b) >= 4]
    if got is None:
        assert not chainable
        return
    assert got + 24 == chainable[0]
    tail = list(read_udp(data[:24] + data[got + 24:]))
    assert tail == [d for d in read_udp(data)][-len(tail):] if tail else True


def test_resync_refuses_what_is_not_libpcap() -> None:
    assert libpcap_resync(b"\x0a\x0d\x0d\x0a" + bytes(20), bytes(4096)) is None
    assert libpcap_resync(PcapWriter().header(), bytes(4096)) is None  # zeros chain no time
