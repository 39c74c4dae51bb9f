"""Coverage-guided fuzzing of the packet decoders with atheris (libFuzzer), for longer runs
than the hypothesis suite (tests/protocols/test_fuzz_decoders.py) does in CI.

Each target feeds libFuzzer's bytes to one decoder and lets only the decoder's documented
error pass; anything else (KeyError, struct.error, a failed invariant) is a crash, which
libFuzzer saves as ``crash-<sha1>`` (see ``-artifact_prefix``) and reports. The seed corpus
is generated in code (valid packets, captures, frames and metadata) into a temporary
directory unless a corpus directory is given.

    pip install -e '.[fuzz]'
    python benchmarks/fuzz_atheris.py list
    python benchmarks/fuzz_atheris.py lidar -atheris_runs=100000
    python benchmarks/fuzz_atheris.py pcap -max_total_time=180 -artifact_prefix=/tmp/fz/
    python benchmarks/fuzz_atheris.py imu --check      # the seeds once, without atheris

Targets: ``lidar`` (every profile; the first byte picks the profile, whether the harness
fixes the CRC and the length, so mutations reach the fields), ``lidar-<PROFILE>``, ``imu``,
``pcap``, ``canopen`` (a byte stream cut into frames for a PoseAssembler, and TIME payloads)
and ``metadata`` (the sensor's metadata JSON).
"""

from __future__ import annotations

import json
import struct
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import protocols.ouster as o
from protocols.harvester import (
    CanProtocolError,
    Pose,
    PoseAssembler,
    decode_time,
    encode_pose,
    encode_time,
)
from protocols.pcap import PcapError, PcapWriter, UdpDatagram, read_udp

PROFILE_NAMES = sorted(o.PROFILES)
INIT_ID, PROD_SN = 0x0ABCDE, 992100000123
NODE = 10


@dataclass(frozen=True)
class Target:
    name: str
    doc: str
    seeds: Callable[[], list[bytes]]
    one_input: Callable[[bytes], None]


# ----------------------------------------------------------------------------- lidar

_FORMATS = {p: o.PacketFormat.create(p, 64, 16, 1024) for p in PROFILE_NAMES}


def _lidar_packets(profile: str) -> list[bytes]:
    fmt = _FORMATS[profile]
    rng = np.random.default_rng(1)
    fields = {f.name: rng.integers(0, 1 << min(f.bits, 31), (64, 1024))
              for f in fmt.profile.fields}
    arr = o.encode_lidar_frame(fmt, fields, np.arange(1024, dtype=np.uint64) * 97_656,
                               frame_id=7, init_id=INIT_ID, prod_sn=PROD_SN)
    return [arr[0].tobytes(), arr[-1].tobytes()]


def _decode_lidar(profile: str, control: int, packet: bytes) -> None:
    """``control`` bit 0: fix the CRC first; bit 1: check init_id/prod_sn; bit 2: do not
    check the CRC; bit 5: keep the length as it is (else cut or pad to a packet's size, so
    most inputs get past the size check)."""
    fmt = _FORMATS[profile]
    buf = bytearray(packet)
    if not control & 0x20:
        buf = buf[:fmt.packet_bytes].ljust(fmt.packet_bytes, b"\x00")
    if control & 1 and not fmt.profile.legacy and len(buf) == fmt.packet_bytes:
        crc = o.crc64_xz_rows(np.frombuffer(bytes(buf[:-8]), np.uint8).reshape(1, -1))[0]
        buf[-8:] = int(crc).to_bytes(8, "little")
    ids = (INIT_ID, PROD_SN) if control & 2 else (0, 0)
    check_crc = not control & 4
    try:
        pkt = o.decode_lidar_packet(fmt, bytes(buf), init_id=ids[0], prod_sn=ids[1],
                                    check_crc=check_crc)
    except o.ProtocolError as err:
        _one_line(err)
        return
    if not (pkt.measurement_id < fmt.columns_per_frame).all():
        raise AssertionError("a decoded packet has a measurement_id beyond the frame")
    for f in fmt.profile.fields:
        if int(pkt.fields[f.name].max()) >= 1 << f.bits:
            raise AssertionError(f"{f.name} exceeds {f.bits} bits")
    batch = o.decode_lidar_packets(fmt, np.frombuffer(bytes(buf), np.uint8).reshape(1, -1),
                                   init_id=ids[0], prod_sn=ids[1], check_crc=check_crc)
    if not np.array_equal(batch.fields["RANGE"], pkt.fields["RANGE"]):
        raise AssertionError("the batch decoder disagrees with the per-packet one")


def _lidar_all(data: bytes) -> None:
    if not data:
        return
    _decode_lidar(PROFILE_NAMES[(data[0] >> 3) % len(PROFILE_NAMES)], data[0], data[1:])


def _lidar_all_seeds() -> list[bytes]:
    out = []
    for i, p in enumerate(PROFILE_NAMES):
        for pkt in _lidar_packets(p):
            out += [bytes([i << 3 | c]) + pkt for c in (0, 1, 3, 0x21)]
    return out


def _lidar_one(profile: str) -> Target:
    def one_input(data: bytes) -> None:
        if data:
            _decode_lidar(profile, data[0], data[1:])

    return Target(f"lidar-{profile}", f"lidar packets, {profile} only",
                  lambda: [bytes([c]) + p for p in _lidar_packets(profile)
                           for c in (0, 1, 3, 0x21)],
                  one_input)


# ----------------------------------------------------------------------------- IMU

def _imu_seeds() -> list[bytes]:
    return [o.encode_imu_packet(o.ImuPacket(1, 2, 3, (0.0, 0.0, 1.0), (0.1, -0.2, 0.3))),
            o.encode_imu_packet(o.ImuPacket(2**64 - 1, 0, 2**63, (-2.0, 1e-40, 0.0),
                                            (250.0, -250.0, 0.0)))]


def _imu(data: bytes) -> None:
    try:
        pkt = o.decode_imu_packet(data)
    except o.ProtocolError as err:
        _one_line(err)
        return
    if o.encode_imu_packet(pkt) != data:
        raise AssertionError("an IMU packet does not re-encode to its bytes")


# ----------------------------------------------------------------------------- pcap

def _block(btype: int, body: bytes) -> bytes:
    body += b"\x00" * (-len(body) % 4)
    return struct.pack("<II", btype, len(body) + 12) + body + struct.pack("<I", len(body) + 12)


def _pcapng(frames: list[bytes]) -> bytes:
    out = [_block(0x0A0D0D0A, struct.pack("<IHHq", 0x1A2B3C4D, 1, 0, -1)),
           _block(1, struct.pack("<HHIHHB3xHH", 1, 0, 65535, 9, 1, 9, 0, 0))]
    for i, f in enumerate(frames):
        ts = 1_700_000_000_000_000_000 + i
        out.append(_block(6, struct.pack("<IIIII", 0, ts >> 32, ts & 0xFFFFFFFF, len(f),
                                         len(f)) + f))
    out.append(_block(3, struct.pack("<I", len(frames[0])) + frames[0]))
    return b"".join(out)


def _pcap_seeds() -> list[bytes]:
    ds = [UdpDatagram(5_000_000_123, "10.0.0.2", "10.0.0.1", 7502, 7502, b"L" * 700),
          UdpDatagram(5_000_000_999, "10.0.0.2", "10.0.0.1", 7503, 7503, b"I" * 48)]
    small = PcapWriter(mtu=300).encode(ds)
    frames, pos = [], 24
    while pos < len(small):
        n = struct.unpack_from("<I", small, pos + 8)[0]
        frames.append(small[pos + 16:pos + 16 + n])
        pos += 16 + n
    return [small, PcapWriter(nanosecond=False).encode(ds), _pcapng(frames)]


def _pcap(data: bytes) -> None:
    try:
        got = list(read_udp(data))
    except PcapError as err:
        _one_line(err)
        return
    for d in got:
        if not (0 <= d.src_port <= 0xFFFF and 0 <= d.dst_port <= 0xFFFF
                and len(d.payload) <= 65527):
            raise AssertionError(f"impossible datagram {d!r:.200}")


# ----------------------------------------------------------------------------- CANopen

def _can_seeds() -> list[bytes]:
    p = Pose(12.345, -6.5, 0.25, 359.99, -12.5, 3.25, -1.5, 2**32 - 5, 0x0307)
    frames = encode_pose(p, NODE, synchronous=False) + encode_pose(p, NODE)
    stream = b"".join(struct.pack("<HB", cob, len(d)) + d for cob, d in frames)
    return [stream, stream + struct.pack("<HB", 0x100, 6) + encode_time(1_700_000_000_000)]


def _canopen(data: bytes) -> None:
    """Frames of (u16 COB-ID & 0x7FF, u8 length % 9, data) fed to one PoseAssembler."""
    asm = PoseAssembler(NODE)
    pos = 0
    while pos + 3 <= len(data):
        cob = struct.unpack_from("<H", data, pos)[0] & 0x7FF
        n = data[pos + 2] % 9
        payload = data[pos + 3:pos + 3 + n]
        pos += 3 + n
        try:
            pose = asm.feed(cob, payload)
        except CanProtocolError as err:
            _one_line(err)
            pose = None
        if pose is not None:
            again = PoseAssembler(NODE)
            out = [q for c, d in encode_pose(pose, NODE, synchronous=False)
                   + encode_pose(pose, NODE) if (q := again.feed(c, d)) is not None]
            if len(out) != 1 or (out[0].x_m, out[0].status) != (pose.x_m, pose.status):
                raise AssertionError(f"pose {pose} does not re-encode")
        try:
            ms = decode_time(payload)
        except CanProtocolError as err:
            _one_line(err)
            continue
        if encode_time(ms)[:3] != payload[:3]:
            raise AssertionError("TIME does not re-encode")


# ----------------------------------------------------------------------------- metadata

def _metadata_seeds() -> list[bytes]:
    return [o.os0_64_metadata(m, p).dumps().encode()
            for m, p in (("1024x10", "RNG19_RFL8_SIG16_NIR16"), ("512x20", "LEGACY"))]


def _metadata(data: bytes) -> None:
    try:
        m = o.SensorMetadata.loads(data.decode("utf-8", errors="replace"))
    except o.MetadataError as err:
        _one_line(err)
        return
    text = json.dumps(m.to_json(), allow_nan=False)
    if o.SensorMetadata.loads(text) != m:
        raise AssertionError("metadata does not round-trip")


# ----------------------------------------------------------------------------- running

def _one_line(err: BaseException) -> None:
    msg = str(err)
    if not msg or "\n" in msg:
        raise AssertionError(f"{type(err).__name__} message is not one line: {msg!r}")


TARGETS: dict[str, Target] = {t.name: t for t in (
    Target("lidar", "lidar packets of every profile", _lidar_all_seeds, _lidar_all),
    *(_lidar_one(p) for p in PROFILE_NAMES),
    Target("imu", "LEGACY IMU packets", _imu_seeds, _imu),
    Target("pcap", "libpcap and pcapng captures", _pcap_seeds, _pcap),
    Target("canopen", "CANopen pose TPDOs and TIME", _can_seeds, _canopen),
    Target("metadata", "sensor metadata JSON", _metadata_seeds, _metadata),
)}


def check(name: str) -> int:
    """Run a target's seeds once (no atheris needed); returns how many ran."""
    t = TARGETS[name]
    seeds = t.seeds()
    for s in seeds:
        t.one_input(s)
    return len(seeds)


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[1] in ("list", "-h", "--help"):
        print(__doc__)
        for t in TARGETS.values():
            print(f"  {t.name:34} {t.doc}")
        return 0
    name = argv[1]
    if name not in TARGETS:
        print(f"unknown target {name!r}; known: {', '.join(TARGETS)}", file=sys.stderr)
        return 2
    if "--check" in argv:
        print(f"{name}: {check(name)} seeds decoded")
        return 0
    import atheris  # the [fuzz] extra

    target = TARGETS[name]
    args = [argv[0], *argv[2:]]
    if not any(not a.startswith("-") for a in argv[2:]):  # no corpus directory given
        corpus = Path(tempfile.mkdtemp(prefix=f"fuzz-{name}-"))
        for i, seed in enumerate(target.seeds()):
            (corpus / f"seed-{i}").write_bytes(seed)
        args.append(str(corpus))
        print(f"seed corpus in {corpus}", file=sys.stderr)
    atheris.instrument_all()
    atheris.Setup(args, target.one_input)
    atheris.Fuzz()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
