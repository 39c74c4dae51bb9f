"""Offline lidar recording: scenario -> forest -> scene -> OS0-64 frames -> packets -> pcap,
with the metadata, ground truth, per-stem visibility and the sensor poses beside it."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from emulators.lidar import Os0Emulator, ReturnModel
from protocols.ouster import (
    ImuPacket,
    SensorMetadata,
    encode_imu_packet,
    encode_lidar_frame,
    os0_64_metadata,
)
from protocols.pcap import PcapWriter, UdpDatagram
from tcf_hil._io import atomic_path, write_bytes_atomic, write_json_atomic
from tcf_hil.forest import generate_forest, ground_truth
from tcf_hil.scenario import Scenario
from tcf_hil.scene import Scene
from tcf_hil.trajectory import StraightTrack, quaternions

SENSOR_IP = "127.0.0.1"


def _crc_rows() -> Callable[[np.ndarray], np.ndarray] | None:
    try:
        import fastcrc
    except ImportError:
        return None  # protocols' numpy tables

    def rows(a: np.ndarray) -> np.ndarray:
        return np.fromiter((fastcrc.crc64.xz(r.tobytes()) for r in a), np.uint64, len(a))
    return rows


@dataclass(frozen=True)
class RecordResult:
    out_dir: Path
    frames: int
    packets: int
    returns: int
    stems_seen: int
    backend: str


def record_pcap(scn: Scenario, out_dir: str | Path, *, mode: str = "1024x10",
                profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
                backend: str = "embree", model: ReturnModel | None = None,
                max_frames: int | None = None, mtu: int = 1500,
                progress: Callable[[int, int], None] | None = None) -> RecordResult:
    """Drive the sensor along the scenario's track and write the run's files into ``out_dir``:
    ``lidar.pcap`` (lidar to 7502, LEGACY IMU at 100 Hz to 7503, fragmented at ``mtu``),
    ``metadata.json``, ``ground_truth.json`` (with ``returns`` per stem), ``visibility.json``
    and ``sensor_poses.csv`` (time_ns, x, y, z, qw, qx, qy, qz: the sensor frame in the world
    at every column time stamp)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    forest = generate_forest(scn, seed)
    scene = Scene.from_forest(forest, backend=backend)
    track = StraightTrack.from_config(scn.track, forest.terrain)
    init_id = (forest.seed * 2654435761 + 12345) % (1 << 24) or 1
    meta: SensorMetadata = os0_64_metadata(mode, profile, init_id=init_id)
    emu = Os0Emulator(meta, scene, track, model, seed=forest.seed, start_ns=track.t0_ns)
    n_frames = max(1, math.ceil(track.duration_ns / emu.period_ns))
    if max_frames is not None:
        n_frames = min(n_frames, max_frames)
    fmt = meta.packet_format
    crc = _crc_rows()
    writer = PcapWriter(mtu=mtu)
    origin = forest.origin
    counts = np.zeros(len(forest.stems) + 1, dtype=np.int64)
    packets = 0
    cpp = fmt.columns_per_packet
    poses = io.StringIO()
    pw = csv.writer(poses, lineterminator="\n")
    pw.writerow(["time_ns", "x", "y", "z", "qw", "qx", "qy", "qz"])
    imu_period = 10_000_000
    next_imu = track.t0_ns
    buf = np.empty((fmt.packets_per_frame, fmt.packet_bytes), np.uint8)
    with atomic_path(out / "lidar.pcap") as tmp, open(tmp, "wb") as fh:
        fh.write(writer.header())
        for k in range(n_frames):
            fr = emu.frame(k)
            arr = encode_lidar_frame(fmt, fr.fields, fr.timestamps_ns, frame_id=k & 0xFFFF,
                                     init_id=meta.init_id, prod_sn=meta.prod_sn,
                                     crc_rows=crc, out=buf)
            end_ts = fr.timestamps_ns[cpp - 1::cpp]
            recs = []
            for i in range(arr.shape[0]):
                t_send = int(end_ts[i])
                while next_imu <= t_send:
                    imu = encode_imu_packet(ImuPacket(next_imu, next_imu, next_imu,
                                                      (0.0, 0.0, 1.0), (0.0, 0.0, 0.0)))
                    recs.append(writer.records(UdpDatagram(next_imu, SENSOR_IP, meta.udp_dest,
                                                           meta.udp_port_imu,
                                                           meta.udp_port_imu, imu)))
                    next_imu += imu_period
                recs.append(writer.records(UdpDatagram(t_send, SENSOR_IP, meta.udp_dest,
                                                       meta.udp_port_lidar,
                                                       meta.udp_port_lidar, arr[i].tobytes())))
            fh.write(b"".join(recs))
            packets += arr.shape[0]
            hit = fr.stem_id[fr.stem_id >= 0]
            counts += np.bincount(hit, minlength=len(counts))[: len(counts)]
            q = quaternions(fr.rotations)
            p = fr.positions + origin
            for j in range(len(fr.timestamps_ns)):
                pw.writerow([int(fr.timestamps_ns[j]), f"{p[j, 0]:.6f}", f"{p[j, 1]:.6f}",
                             f"{p[j, 2]:.6f}", f"{q[j, 0]:.9f}", f"{q[j, 1]:.9f}",
                             f"{q[j, 2]:.9f}", f"{q[j, 3]:.9f}"])
            if progress:
                progress(k + 1, n_frames)
    write_bytes_atomic(out / "sensor_poses.csv", poses.getvalue().encode())
    write_bytes_atomic(out / "metadata.json", meta.dumps().encode())
    gt = ground_truth(forest)
    for o in gt["objects"]:
        o["returns"] = int(counts[o["id"]])
    write_json_atomic(out / "ground_truth.json", gt)
    vis: dict[str, Any] = {
        "frames": n_frames, "mode": mode, "profile": profile, "backend": backend,
        "terrain_returns": int(counts[0]),
        "stem_returns": int(counts[1:].sum()),
        "stems_seen": int(np.count_nonzero(counts[1:])),
        "stems_total": len(forest.stems),
        "returns_per_stem": {str(i): int(c) for i, c in enumerate(counts) if i and c},
    }
    write_json_atomic(out / "visibility.json", vis)
    return RecordResult(out, n_frames, packets, int(counts.sum()), vis["stems_seen"], backend)
