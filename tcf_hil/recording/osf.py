"""Ouster's OSF files (what ``ouster-cli source SENSOR save x.osf`` writes) as recordings to
replay: read with ouster-sdk (an optional dependency: ``pip install 'tcf-hil[osf]'``), each
frame encoded again into the lidar packets of the file's profile by :mod:`protocols.ouster`,
and written out as a capture that a replay sends as it sends a field recording.

An OSF file keeps frames (fields by name, column time stamps, measurement ids and status,
frame ids), not packets: what the packets carried besides, and IMU packets, are not in it.
The packets are the file's frames as the sensor would have sent them (its profile, columns
per packet, init_id and serial from the metadata, a CRC where the firmware writes one), at
the time the file gives each packet (its receive time, else its first column's time)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tcf_hil.errors import InputError

__all__ = ["is_osf", "osf_to_recording", "ouster_sdk"]


def ouster_sdk() -> Any:
    """ouster-sdk's OSF module, or an InputError saying how to install it."""
    try:
        from ouster.sdk import osf
    except ImportError as err:
        raise InputError("ouster-sdk", "", f"OSF files are read and written with ouster-sdk "
                         f"(pip install 'tcf-hil[osf]'): {err}") from err
    return osf


def is_osf(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".osf"


def osf_to_recording(path: Path, work: Path) -> tuple[Path, Path]:
    """The OSF file ``path`` as ``lidar.pcap`` and ``metadata.json`` in ``work`` (its first
    lidar stream; packets from the sensor to the metadata's ports, 7502 where it names
    none)."""
    from protocols.ouster import MetadataError, SensorMetadata
    from protocols.pcap import PcapWriter

    osf = ouster_sdk()
    try:
        src = osf.OsfFrameSetSource(str(path))
    except Exception as err:  # ouster-sdk raises its own errors for a file it cannot read
        raise InputError(str(path), "", f"not an OSF file ouster-sdk reads: "
                         f"{str(err).splitlines()[0] if str(err) else type(err).__name__}"
                         ) from err
    if not src.sensor_info:
        raise InputError(str(path), "", "holds no lidar stream")
    try:
        meta = SensorMetadata.loads(src.sensor_info[0].to_json_string())
    except MetadataError as err:
        raise InputError(str(path), "metadata", str(err)) from err
    meta = meta.with_changes(udp_port_lidar=meta.udp_port_lidar or 7502,
                             udp_port_imu=meta.udp_port_imu or 7503)
    fmt = meta.packet_format
    work.mkdir(parents=True, exist_ok=True)
    (work / "metadata.json").write_text(meta.dumps(), encoding="utf-8")
    w = PcapWriter()
    dest = meta.udp_dest or "127.0.0.1"
    n = 0
    try:
        with open(work / "lidar.pcap", "wb") as out:
            out.write(w.header())
            for fr in _frames(src):
                n += _write_frame(out, w, fr, meta, fmt, dest)
    except (RuntimeError, ValueError) as err:  # ouster-sdk's errors on a damaged file
        raise InputError(str(path), f"frame {n}", f"cannot be read: {err}") from err
    finally:
        close = getattr(src, "close", None)
        if close is not None:
            close()
    if not n:
        raise InputError(str(path), "", "holds no lidar frame")
    return work / "lidar.pcap", work / "metadata.json"


def _frames(src: Any) -> Any:
    for fs in src:
        fr = fs[0] if len(fs) else None
        if fr is not None:
            yield fr


def _write_frame(out: Any, w: Any, fr: Any, meta: Any, fmt: Any, dest: str) -> int:
    """One frame's packets into the capture; the packets the sensor never sent (no valid
    column: lost on the way, or outside a column window) are left out."""
    from protocols.ouster import encode_lidar_frame
    from protocols.pcap import UdpDatagram

    fields = {name: np.asarray(fr.field(name)).astype(np.uint32)
              for name in fmt.field_names if fr.has_field(name)}
    ts = np.asarray(fr.timestamp, np.uint64)
    status = np.asarray(fr.status, np.uint32)
    arr = encode_lidar_frame(fmt, fields, ts, frame_id=int(fr.frame_id) %
                             fmt.frame_id_modulus, init_id=meta.init_id,
                             prod_sn=meta.prod_sn, status=status)
    sent = np.asarray(fr.packet_timestamp, np.int64)
    cpp = fmt.columns_per_packet
    written = 0
    for i in range(arr.shape[0]):
        cols = slice(i * cpp, (i + 1) * cpp)
        valid = np.flatnonzero(status[cols] & 1)
        if not len(valid):
            continue
        t = int(sent[i]) if i < len(sent) and sent[i] else int(ts[cols][valid[0]])
        out.write(w.records(UdpDatagram(t, "169.254.0.1", dest, 7502,
                                        meta.udp_port_lidar, arr[i].tobytes())))
        written += 1
    return 1 if written else 0
