"""Fuzzing every wire decoder of ``protocols``: any input gives a value or the decoder's
documented error, whose message is one line, and nothing else (issue 7, item 2).

Each decoder gets arbitrary bytes or text and structure-aware mutations of a valid input:
lidar packets of every profile with the CRC recomputed after the damage (so decoding gets
past the CRC check), LEGACY IMU packets with NaN/inf/denormal floats, metadata documents
mutated field by field, libpcap and pcapng captures with damaged block lengths, and CANopen
frame sequences. Where a decoder returns a value, an independent reference decoder or a
re-encoding checks it. ``benchmarks/fuzz_atheris.py`` runs the packet decoders for longer.
"""

from __future__ import annotations

import json
import math
import struct
from functools import cache
from typing import Any

import numpy as np
from _fuzz import fuzz_settings, mutations, one_line, paths
from hypothesis import event, example, given
from hypothesis import strategies as st

import protocols.ouster as o
from protocols.harvester import (
    HARVESTER_OD,
    CanProtocolError,
    Pose,
    PoseAssembler,
    decode_time,
    encode_pose,
    encode_time,
)
from protocols.pcap import PcapError, PcapWriter, UdpDatagram, read_udp

FUZZ = fuzz_settings(300)


# ----------------------------------------------------------------------------- lidar packets

#: (profile, pixels per column, columns per packet, columns per frame): a small layout for
#: dense structural coverage and the OS0-64's real one.
LAYOUTS = [(p, 8, 4, 32) for p in sorted(o.PROFILES)] + \
          [(p, 64, 16, 1024) for p in sorted(o.PROFILES)]
INIT_ID, PROD_SN = 0x0ABCDE, 992100000123


@cache
def _valid_packet(layout: tuple[str, int, int, int]) -> bytes:
    fmt = o.PacketFormat.create(*layout)
    rng = np.random.default_rng(7)
    fields = {f.name: rng.integers(0, 1 << min(f.bits, 31),
                                   (fmt.pixels_per_column, fmt.columns_per_frame))
              for f in fmt.profile.fields}
    ts = np.arange(fmt.columns_per_frame, dtype=np.uint64) * 97_656 + 10**12
    arr = o.encode_lidar_frame(fmt, fields, ts, frame_id=321, init_id=INIT_ID, prod_sn=PROD_SN)
    return arr[1].tobytes()


def _u(buf: bytes, off: int, size: int) -> int:
    return int.from_bytes(buf[off:off + size], "little")


def _hot_offsets(fmt: o.PacketFormat) -> list[int]:
    """Bytes worth damaging: packet header and footer, column headers and footers."""
    p = fmt.profile
    out = list(range(p.header_bytes)) + list(range(fmt.packet_bytes - p.footer_bytes,
                                                   fmt.packet_bytes))
    for c in range(fmt.columns_per_packet):
        col = p.header_bytes + c * fmt.col_bytes
        out += range(col, col + p.col_header_bytes)
        out += range(col + fmt.col_bytes - p.col_footer_bytes, col + fmt.col_bytes)
    return out


def _fix_crc(fmt: o.PacketFormat, buf: bytearray) -> None:
    if not fmt.profile.legacy and len(buf) == fmt.packet_bytes:
        buf[-8:] = o.crc64_xz(bytes(buf[:-8])).to_bytes(8, "little")


@st.composite
def mutated_packets(draw: st.DrawFn) -> tuple[tuple[str, int, int, int], bytes]:
    layout = draw(st.sampled_from(LAYOUTS))
    fmt = o.PacketFormat.create(*layout)
    buf = bytearray(_valid_packet(layout))
    hot = _hot_offsets(fmt)
    for _ in range(draw(st.integers(0, 6))):
        at = draw(st.one_of(st.sampled_from(hot), st.integers(0, len(buf) - 1)))
        kind = draw(st.sampled_from(["byte", "flip", "splice", "u16"]))
        if kind == "byte":
            buf[at] = draw(st.integers(0, 255))
        elif kind == "flip":
            buf[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "u16":  # a 16-bit word at its extremes: measurement_id, packet_type...
            word = draw(st.sampled_from([0, 1, 2, fmt.columns_per_frame - 1,
                                         fmt.columns_per_frame, 0x7FFF, 0xFFFF]))
            buf[at:at + 2] = word.to_bytes(2, "little")[:len(buf) - at]
        else:
            junk = draw(st.binary(min_size=1, max_size=16))
            buf[at:at + len(junk)] = junk
    if draw(st.integers(0, 9)) == 0:  # the wrong size, now and then
        cut = draw(st.integers(-24, 24))
        buf = buf[:cut] if cut < 0 else buf + bytes(cut)
    if draw(st.integers(0, 3)):  # mostly: a correct CRC, so the damage reaches the fields
        _fix_crc(fmt, buf)
    return layout, bytes(buf)


def _expected_error(fmt: o.PacketFormat, buf: bytes, init_id: int, prod_sn: int,
                    check_crc: bool) -> type[o.ProtocolError] | None:
    """The error the decoder must raise (its documented checks, in order), or None."""
    p = fmt.profile
    if len(buf) != fmt.packet_bytes:
        return o.PacketSizeError
    if not p.legacy:
        fusa = fmt.header.name == "FUSA"  # (a byte of packet_type, a 32-bit frame_id, no CRC)
        if _u(buf, 0, 1 if fusa else 2) != 1:
            return o.PacketTypeError
        if check_crc and not fusa and o.crc64_xz(buf[:-8]) != _u(buf, len(buf) - 8, 8):
            return o.CrcError
        pid, psn = _ids(fmt, buf)[1:]
        if (init_id and pid and pid != init_id) or (prod_sn and psn and psn != prod_sn):
            return o.PacketIdError
    for c in range(fmt.columns_per_packet):
        if _u(buf, p.header_bytes + c * fmt.col_bytes + 8, 2) >= fmt.columns_per_frame:
            return o.MeasurementIdError
    return None


def _check_against_reference(fmt: o.PacketFormat, buf: bytes, pkt: o.LidarPacket) -> None:
    """An independent, byte-by-byte decoder of the same layout tables."""
    p = fmt.profile
    for c in range(fmt.columns_per_packet):
        col = p.header_bytes + c * fmt.col_bytes
        assert int(pkt.timestamps_ns[c]) == _u(buf, col, 8)
        assert int(pkt.measurement_id[c]) == _u(buf, col + 8, 2)
        want_status = _u(buf, col + fmt.col_bytes - 4, 4) if p.legacy else _u(buf, col + 10, 2)
        assert int(pkt.status[c]) == want_status
        for px in range(fmt.pixels_per_column):
            base = col + p.col_header_bytes + px * p.pixel_bytes
            for f in p.fields:
                word = _u(buf, base + f.offset, np.dtype(f.dtype).itemsize) & f.mask
                v = word >> f.shift if f.shift >= 0 else word << -f.shift
                assert int(pkt.fields[f.name][px, c]) == v & 0xFFFFFFFF, (f.name, px, c)
                assert v < 1 << f.bits
    if p.legacy:
        assert pkt.frame_id == _u(buf, p.header_bytes + 10, 2)
    else:
        assert (pkt.frame_id, pkt.init_id, pkt.prod_sn) == _ids(fmt, buf)
        assert pkt.crc == (None if fmt.header.name == "FUSA" else _u(buf, len(buf) - 8, 8))


def _ids(fmt: o.PacketFormat, buf: bytes) -> tuple[int, int, int]:
    """frame_id, init_id and prod_sn where the STANDARD and FUSA headers put them."""
    if fmt.header.name == "FUSA":
        return _u(buf, 4, 4), _u(buf, 1, 3), _u(buf, 11, 5)
    return _u(buf, 2, 2), _u(buf, 4, 3), _u(buf, 7, 5)


@FUZZ
@given(mutated_packets(), st.sampled_from([(INIT_ID, PROD_SN), (0, 0), (INIT_ID + 1, 0)]),
       st.booleans())
def test_mutated_lidar_packets_decode_as_the_reference_or_raise_the_documented_error(
        case: tuple[tuple[str, int, int, int], bytes], ids: tuple[int, int],
        check_crc: bool) -> None:
    layout, buf = case
    fmt = o.PacketFormat.create(*layout)
    want = _expected_error(fmt, buf, *ids, check_crc)
    try:
        pkt = o.decode_lidar_packet(fmt, buf, init_id=ids[0], prod_sn=ids[1],
                                    check_crc=check_crc)
    except o.ProtocolError as err:
        one_line(err)
        assert type(err) is want, f"{type(err).__name__}: {err}; expected {want}"
        got_error: type[o.ProtocolError] | None = type(err)
    else:
        assert want is None, f"decoded a packet that should raise {want.__name__}"
        event("value")
        _check_against_reference(fmt, buf, pkt)
        got_error = None
    # The batch decoder agrees with the per-packet one on the same bytes.
    try:
        batch = o.decode_lidar_packets(fmt, np.frombuffer(buf, np.uint8).reshape(1, -1),
                                       init_id=ids[0], prod_sn=ids[1], check_crc=check_crc)
    except o.ProtocolError as err:
        one_line(err)
        assert type(err) is got_error
    else:
        assert got_error is None
        for name in fmt.field_names:
            np.testing.assert_array_equal(batch.fields[name], pkt.fields[name])


@FUZZ
@given(st.sampled_from(LAYOUTS[:4]), st.binary(max_size=400), st.booleans())
@example(LAYOUTS[0], b"", True)
def test_arbitrary_bytes_are_a_lidar_packet_or_a_protocol_error(
        layout: tuple[str, int, int, int], data: bytes, exact: bool) -> None:
    fmt = o.PacketFormat.create(*layout)
    if exact:  # the right length, and a lidar packet_type, so the other checks run
        data = (b"\x01\x00" + data)[:fmt.packet_bytes].ljust(fmt.packet_bytes, b"\x00")
    want = _expected_error(fmt, data, INIT_ID, PROD_SN, False)
    try:
        pkt = o.decode_lidar_packet(fmt, data, init_id=INIT_ID, prod_sn=PROD_SN,
                                    check_crc=False)
    except o.ProtocolError as err:
        one_line(err)
        assert type(err) is want
    else:
        assert want is None
        _check_against_reference(fmt, data, pkt)


# ----------------------------------------------------------------------------- IMU packets

_IMU = struct.Struct("<QQQ6f")
SPECIAL_F32 = [0x7FC00000, 0xFFC00001, 0x7F800000, 0xFF800000, 0x00000001, 0x80000000,
               0x7F7FFFFF, 0x3F800000]


@st.composite
def imu_packets(draw: st.DrawFn) -> bytes:
    buf = bytearray(_IMU.pack(1, 2, 3, 0.0, 0.0, 1.0, 0.1, 0.2, 0.3))
    for _ in range(draw(st.integers(1, 4))):
        lane = draw(st.integers(0, 8))
        if lane < 3:
            buf[lane * 8:lane * 8 + 8] = draw(st.sampled_from([0, 2**63, 2**64 - 1])).to_bytes(
                8, "little")
        else:
            off = 24 + (lane - 3) * 4
            buf[off:off + 4] = draw(st.sampled_from(SPECIAL_F32)).to_bytes(4, "little")
    return bytes(buf)


@FUZZ
@given(st.one_of(st.binary(max_size=100), st.binary(min_size=48, max_size=48), imu_packets()))
@example(_IMU.pack(0, 0, 0, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0))  # was a bare ValueError
@example(_IMU.pack(0, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, -math.inf))
def test_any_bytes_are_an_imu_packet_or_a_protocol_error(data: bytes) -> None:
    try:
        pkt = o.decode_imu_packet(data)
    except o.ProtocolError as err:
        one_line(err)
        if len(data) != o.IMU_PACKET_BYTES:
            assert isinstance(err, o.PacketSizeError)
        else:
            assert isinstance(err, o.PacketValueError)
            assert not all(math.isfinite(v) for v in _IMU.unpack(data)[3:])
        return
    event("value")
    assert len(data) == o.IMU_PACKET_BYTES
    assert o.encode_imu_packet(pkt) == data  # float32 -> float -> float32 is exact


# ----------------------------------------------------------------------------- metadata

VALID_META = o.os0_64_metadata("1024x10", init_id=0x0ABCDE)
VALID_DOC = VALID_META.to_json()


META_PATHS = paths(VALID_DOC, 3)

#: Values of the wrong type or beyond range, for any field.
BAD_VALUES = st.one_of(
    st.none(), st.booleans(), st.sampled_from([0, -1, 1.5, 10**30, -(10**30), 2**64, 2**24]),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -0.0, 5e-324]),
    st.integers(), st.floats(), st.text(max_size=12),
    st.sampled_from(["", "1024x10", "512x20", "4096x5", "2048x", "x10", "1024x10x1", "LEGACY",
                     "RNG15_RFL8_NIR8", "@auto", "992100000123", "-5", "1e3", "0x10"]),
    st.just([]), st.just({}), st.lists(st.integers(-3, 3), max_size=17),
    st.lists(st.floats(), min_size=16, max_size=16), st.just([[1, 2], [3]]),
    st.just([None] * 16), st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))


def mutated_metadata() -> st.SearchStrategy[dict[str, Any]]:
    return mutations(VALID_DOC, META_PATHS, BAD_VALUES)


def _check_metadata_value(m: o.SensorMetadata) -> None:
    event("value")
    text = json.dumps(m.to_json(), allow_nan=False)  # raises on NaN/inf
    assert o.SensorMetadata.loads(text) == m
    assert o.SensorMetadata.from_json(m.to_json()) == m
    assert m.packet_format.packet_bytes > 0 and m.columns % m.columns_per_packet == 0


@FUZZ
@given(mutated_metadata())
@example({**VALID_DOC, "sensor_info": []})  # was AttributeError
@example({**VALID_DOC, "sensor_info": {**VALID_DOC["sensor_info"], "prod_sn": math.inf}})
@example({**VALID_DOC, "sensor_info": {**VALID_DOC["sensor_info"], "initialization_id": "x"}})
@example({**VALID_DOC, "config_params": {**VALID_DOC["config_params"], "udp_port_imu": []}})
@example({**VALID_DOC, "lidar_data_format": {**VALID_DOC["lidar_data_format"],
                                              "columns_per_frame": 10**5000}})
@example({**VALID_DOC, "lidar_data_format": {**VALID_DOC["lidar_data_format"],
                                              "udp_profile_lidar": "LEGACY",
                                              "columns_per_packet": 16}})
@example({**VALID_DOC, "beam_intrinsics": {**VALID_DOC["beam_intrinsics"],
                                            "lidar_origin_to_beam_origin_mm": math.nan}})
@example({**VALID_DOC, "lidar_intrinsics": {"lidar_to_sensor_transform": [None] * 16}})
@example({**VALID_DOC, "imu_intrinsics": {"imu_to_sensor_transform": [[1, 2], [3]]}})
@example({**VALID_DOC, "imu_intrinsics": {"imu_to_sensor_transform": ["a"] * 16}})
def test_mutated_metadata_is_read_or_raises_metadata_error(doc: dict[str, Any]) -> None:
    try:
        m = o.SensorMetadata.from_json(doc)
    except o.MetadataError as err:
        one_line(err)
        return
    _check_metadata_value(m)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids,
                                                              max_size=4), max_leaves=20)


@FUZZ
@given(st.one_of(st.text(max_size=200), JSON_VALUES.map(json.dumps),
                 mutated_metadata().map(json.dumps),
                 st.tuples(mutated_metadata().map(json.dumps), st.integers(0, 5000),
                           st.text(max_size=8)).map(lambda t: t[0][:t[1]] + t[2] + t[0][t[1]:])))
@example("9" * 5000)  # was ValueError (int string conversion limit)
@example("[" * 100_000)  # was RecursionError
@example('{"a": NaN}')
def test_any_text_is_metadata_or_a_metadata_error(text: str) -> None:
    try:
        m = o.SensorMetadata.loads(text)
    except o.MetadataError as err:
        one_line(err)
        return
    _check_metadata_value(m)


FINITE = st.floats(-1e6, 1e6)
#: Per field: values a sensor would take (the fuzzing mixes them with BAD_VALUES).
GOOD_CHANGES: dict[str, tuple[str, st.SearchStrategy[Any]]] = {
    "lidar_mode": ("mode", st.sampled_from(o.MODES)),
    "udp_profile_lidar": ("profile", st.sampled_from(sorted(o.PROFILES))),
    "udp_dest": ("udp_dest", st.sampled_from(["10.0.0.1", "169.254.1.2", "localhost"])),
    "udp_port_lidar": ("udp_port_lidar", st.integers(0, 65535)),
    "udp_port_imu": ("udp_port_imu", st.integers(0, 65535)),
    "columns_per_packet": ("columns_per_packet", st.sampled_from([8, 16, 32, 64, 128])),
    "init_id": ("init_id", st.integers(0, 2**24 - 1)),
    "prod_sn": ("prod_sn", st.integers(0, 2**40 - 1)),
    "beam_altitude_deg": ("beam_altitude_deg", st.tuples(*[FINITE] * 64)),
    "lidar_to_sensor": ("lidar_to_sensor", st.tuples(*[FINITE] * 16)),
    "lidar_origin_to_beam_origin_mm": ("lidar_origin_to_beam_origin_mm", FINITE),
}


@st.composite
def metadata_changes(draw: st.DrawFn) -> dict[str, Any]:
    keys = draw(st.lists(st.sampled_from(sorted(GOOD_CHANGES)), min_size=1, max_size=3,
                         unique=True))
    return {k: draw(GOOD_CHANGES[k][1] if draw(st.booleans()) else BAD_VALUES) for k in keys}


@FUZZ
@given(metadata_changes())
@example({"lidar_mode": 5})  # was AttributeError (the sensor's config POST)
@example({"udp_profile_lidar": []})  # was TypeError
@example({"udp_port_lidar": "7502"})  # was accepted, and served as a string
@example({"lidar_origin_to_beam_origin_mm": 10**30})  # an int the JSON round trip changed
def test_metadata_changes_give_metadata_or_a_metadata_error(change: dict[str, Any]) -> None:
    """``with_changes`` is how the emulated sensor applies a config POST (untrusted JSON)."""
    try:
        m = VALID_META.with_changes(**{GOOD_CHANGES[k][0]: v for k, v in change.items()})
    except o.MetadataError as err:
        one_line(err)
        return
    _check_metadata_value(m)


# ----------------------------------------------------------------------------- pcap

def _block(btype: int, body: bytes) -> bytes:
    body = body + b"\x00" * (-len(body) % 4)
    n = len(body) + 12
    return struct.pack("<II", btype, n) + body + struct.pack("<I", n)


SHB = _block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1))


def _pcapng_head(tsresol: int = 9) -> bytes:
    """Section header and one Ethernet interface (with if_tsresol)."""
    return SHB + _block(1, struct.pack("<HHI", 1, 0, 65535)
                        + struct.pack("<HHB3x", 9, 1, tsresol) + struct.pack("<HH", 0, 0))


def _pcapng(packets: list[bytes], tsresol: int = 9) -> bytes:
    """A little-endian pcapng: SHB, IDB (if_tsresol), EPBs and an SPB."""
    out = [_pcapng_head(tsresol)]
    for i, frame in enumerate(packets):
        ts = 1_700_000_000_000_000_000 + i
        out.append(_block(6, struct.pack("<IIIII", 0, ts >> 32, ts & 0xFFFFFFFF, len(frame),
                                         len(frame)) + frame))
    if packets:
        out.append(_block(3, struct.pack("<I", len(packets[0])) + packets[0]))
    return b"".join(out)


def _frames_of(capture: bytes) -> list[bytes]:
    """The Ethernet frames of a libpcap capture (to re-wrap them as pcapng)."""
    pos, out = 24, []
    while pos < len(capture):
        incl = struct.unpack_from("<I", capture, pos + 8)[0]
        out.append(capture[pos + 16:pos + 16 + incl])
        pos += 16 + incl
    return out


DATAGRAMS = [UdpDatagram(5_000_000_123, "10.0.0.2", "10.0.0.1", 7502, 7502, b"L" * 700),
             UdpDatagram(5_000_000_999, "10.0.0.2", "10.0.0.1", 7503, 7503, b"I" * 48)]
PCAP_SEEDS = [PcapWriter(mtu=300).encode(DATAGRAMS),
              PcapWriter(mtu=1500, nanosecond=False).encode(DATAGRAMS),
              _pcapng(_frames_of(PcapWriter(mtu=300).encode(DATAGRAMS))),
              _pcapng(_frames_of(PcapWriter(mtu=1500).encode(DATAGRAMS)), tsresol=0x86)]


@st.composite
def mutated_captures(draw: st.DrawFn) -> bytes:
    buf = bytearray(draw(st.sampled_from(PCAP_SEEDS)))
    for _ in range(draw(st.integers(1, 5))):
        at = draw(st.integers(0, len(buf) - 1))
        kind = draw(st.sampled_from(["byte", "byte", "byte", "u32", "cut", "splice"]))
        if kind == "byte":
            buf[at] = draw(st.integers(0, 255))
        elif kind == "u32":  # block lengths, record lengths, IP/UDP lengths at extremes
            v = draw(st.sampled_from([0, 1, 4, 8, 12, 16, 20, 24, 28, 0xFFFF, 0xFFFFFFFF]))
            buf[at:at + 4] = v.to_bytes(4, draw(st.sampled_from(["little", "big"])))
        elif kind == "cut":
            del buf[at:at + draw(st.integers(1, 64))]
        else:
            buf[at:at] = draw(st.binary(min_size=1, max_size=16))
        if not buf:
            break
    return bytes(buf)


def _check_datagram(d: UdpDatagram) -> None:
    assert 0 <= d.src_port <= 0xFFFF and 0 <= d.dst_port <= 0xFFFF
    assert len(d.payload) <= 65535 - 8
    if 0 <= d.timestamp_ns < (1 << 32) * 1_000_000_000 and len(d.payload) <= 65507:
        assert list(read_udp(PcapWriter(mtu=576).encode([d]))) == [d]


_EMPTY_IDB = SHB + struct.pack("<III", 1, 12, 12)


@FUZZ
@given(st.one_of(mutated_captures(), st.binary(max_size=120),
                 st.sampled_from([b"\x0a\x0d\x0d\x0a", b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1",
                                  b"\xa1\xb2\xc3\xd4"]).flatmap(
                     lambda m: st.binary(max_size=120).map(lambda b: m + b))))
@example(_EMPTY_IDB)  # an IDB without a body: was struct.error
@example(SHB + _block(1, struct.pack("<HHI", 1, 0, 0) + struct.pack("<HH", 9, 1)))  # IndexError
@example(_pcapng_head() + _block(6, b"\x00" * 8))  # a short EPB: was struct.error
@example(_pcapng_head() + _block(3, b""))  # an empty SPB: was struct.error
def test_any_capture_gives_datagrams_or_a_pcap_error(data: bytes) -> None:
    try:
        got = list(read_udp(data))
    except PcapError as err:
        one_line(err)
        return
    event(f"{min(len(got), 3)}+ datagrams")
    for d in got:
        _check_datagram(d)


def test_the_capture_seeds_read_back_as_written() -> None:
    for seed in PCAP_SEEDS:
        got = list(read_udp(seed))
        assert [(d.dst_port, d.payload) for d in got][:2] == [(7502, b"L" * 700),
                                                                (7503, b"I" * 48)]


# ----------------------------------------------------------------------------- CANopen

NODE = 10
COBS = sorted(m.cob_id(NODE) for m in HARVESTER_OD.tpdos)
SEED_POSE = Pose(12.345, -6.5, 0.25, 359.99, -12.5, 3.25, -1.5, 2**32 - 5, 0x0307)
SEED_FRAMES = encode_pose(SEED_POSE, NODE, synchronous=False) + encode_pose(SEED_POSE, NODE)


@st.composite
def can_frames(draw: st.DrawFn) -> tuple[int, bytes]:
    cob, data = draw(st.sampled_from(SEED_FRAMES))
    kind = draw(st.sampled_from(["valid", "valid", "byte", "resize", "random"]))
    buf = bytearray(data)
    if kind == "byte" and buf:
        buf[draw(st.integers(0, len(buf) - 1))] = draw(st.sampled_from([0, 0x7F, 0x80, 0xFF]))
    elif kind == "resize":
        buf = buf[:draw(st.integers(0, 8))] if draw(st.booleans()) else buf + b"\x00"
    elif kind == "random":
        cob = draw(st.one_of(st.sampled_from(COBS), st.integers(0, 0x7FF)))
        buf = bytearray(draw(st.binary(max_size=8)))
    return cob, bytes(buf)


def _angle_same(a: float, b: float) -> bool:
    return abs((a - b + 180.0) % 360.0 - 180.0) < 1e-9


@FUZZ
@given(st.lists(can_frames(), max_size=30))
def test_frame_sequences_give_poses_that_re_encode_or_the_documented_error(
        frames: list[tuple[int, bytes]]) -> None:
    asm = PoseAssembler(NODE)
    poses: list[Pose] = []
    for cob, data in frames:
        try:
            p = asm.feed(cob, data)
        except CanProtocolError as err:
            one_line(err)
            continue
        if p is not None:
            poses.append(p)
    event(f"{min(len(poses), 3)}+ poses")
    for p in poses:
        assert 0 <= p.status <= 0xFFFF
        again = PoseAssembler(NODE)
        out = [q for c, d in encode_pose(p, NODE, synchronous=False) + encode_pose(p, NODE)
               if (q := again.feed(c, d)) is not None]
        assert len(out) == 1
        q = out[0]
        assert (q.x_m, q.y_m, q.z_m, q.speed_m_s, q.status) == (p.x_m, p.y_m, p.z_m,
                                                                p.speed_m_s, p.status)
        assert q.time_us == p.time_us % 2**32
        for a, b in ((q.heading_deg, p.heading_deg), (q.pitch_deg, p.pitch_deg),
                     (q.roll_deg, p.roll_deg)):
            assert _angle_same(a, b), (a, b)


@FUZZ
@given(st.one_of(st.binary(max_size=10), st.binary(min_size=6, max_size=6)))
@example(bytes([0xFF, 0x5B, 0x26, 0x05, 0xFF, 0xFF]))  # 86_399_999 ms after midnight
def test_any_time_payload_is_a_time_or_the_documented_error(data: bytes) -> None:
    try:
        ms = decode_time(data)
    except CanProtocolError as err:
        one_line(err)
        assert len(data) != 6 or int.from_bytes(data[:4], "little") & 0x0FFFFFFF >= 86_400_000
        return
    event("value")
    assert encode_time(ms) == data[:3] + bytes([data[3] & 0x0F]) + data[4:]
