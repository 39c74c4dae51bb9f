"""Replaying a long recording: memory stays flat, and reading keeps ahead of real time.

Writes a synthetic Ouster recording (the emulator's 2048x10 packets, RNG19_RFL8_SIG16_NIR16,
64 beams, IPv4-fragmented at a 1500-byte MTU as a real link carries them, 100 IMU packets a
second) of each length asked, then, each in a fresh process: the check pass
(:meth:`tcf_hil.recording.reader.Recording.load`), one read of every datagram as the replay sends it
(:func:`tcf_hil.recording.reader.events`, no pacing), and sending them all to a local UDP socket as
fast as the loop goes. Reports the file size, the process's peak resident memory (ru_maxrss)
and the seconds of each pass against the recording's length.

Run: ``python benchmarks/bench_replay.py [--minutes 1,10] [--dir /tmp]`` (a 10-minute
2048x10 recording is about 10 GB; it is deleted afterwards unless --keep).
"""

from __future__ import annotations

import argparse
import json
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from protocols.ouster import ImuPacket, encode_imu_packet, encode_lidar_frame, os0_64_metadata
from protocols.pcap import PcapWriter, UdpDatagram
from tcf_hil._crc import fast_crc_rows


def write_recording(path: Path, minutes: float, mode: str = "2048x10") -> None:
    m = os0_64_metadata(mode)
    fmt = m.packet_format
    rng = np.random.default_rng(0)
    fields = {"RANGE": rng.integers(500, 60000, (m.pixels, m.columns)).astype(np.uint32),
              "REFLECTIVITY": rng.integers(0, 255, (m.pixels, m.columns)).astype(np.uint32),
              "SIGNAL": rng.integers(0, 4000, (m.pixels, m.columns)).astype(np.uint32)}
    period = 10**9 // m.frequency_hz
    w = PcapWriter(mtu=1500)
    crc = fast_crc_rows()
    t0 = 1_700_000_000 * 10**9
    with open(path, "wb") as f:
        f.write(w.header())
        for k in range(round(minutes * 60 * m.frequency_hz)):
            t = t0 + k * period
            ts = np.arange(m.columns, dtype=np.uint64) * (period // m.columns) + np.uint64(t)
            arr = encode_lidar_frame(fmt, fields, ts, frame_id=k % 65536, init_id=m.init_id,
                                     prod_sn=m.prod_sn, crc_rows=crc)
            n = arr.shape[0]
            dgs = [UdpDatagram(t + i * period // n, "169.254.0.2", "169.254.0.1", 7502, 7502,
                               arr[i].tobytes()) for i in range(n)]
            dgs += [UdpDatagram(t + j * period // 10, "169.254.0.2", "169.254.0.1", 7503, 7503,
                                encode_imu_packet(ImuPacket(t, t, t, (0.0, 0.0, 1.0),
                                                            (0.0, 0.0, 0.0))))
                    for j in range(10)]
            dgs.sort(key=lambda d: d.timestamp_ns)
            f.write(w.records_many(dgs))
    path.with_suffix(".json").write_text(m.dumps())


def measure(path: Path) -> dict[str, float]:
    """In this process: check, read, send; seconds and peak RSS."""
    from tcf_hil.recording.reader import Recording, events

    out: dict[str, float] = {}
    t = time.perf_counter()
    rec = Recording.load(path)
    out["check_s"] = time.perf_counter() - t
    out["rss_after_check_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t = time.perf_counter()
    n = sum(1 for _e in events(rec, False, None))
    out["read_s"] = time.perf_counter() - t
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    dst = rx.getsockname()
    t = time.perf_counter()
    sent = 0
    for _t, kind, item in events(rec, False, None):
        if kind == "udp":
            try:
                tx.sendto(item[1], dst)
                sent += 1
            except OSError:  # a full receive buffer nobody reads: the send is what counts
                pass
    out["send_s"] = time.perf_counter() - t
    rx.close()
    tx.close()
    out["datagrams"] = n
    out["recorded_s"] = rec.span_ns / 1e9
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", default="1,10")
    ap.add_argument("--dir", default="/tmp")
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--measure", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.measure:
        print(json.dumps(measure(Path(a.measure))))
        return
    print("| recording | file | check | read | send | peak RSS |")
    print("|---|---|---|---|---|---|")
    for minutes in (float(x) for x in a.minutes.split(",")):
        path = Path(a.dir) / f"bench-replay-{minutes:g}min.pcap"
        t = time.perf_counter()
        write_recording(path, minutes)
        made = time.perf_counter() - t
        r = json.loads(subprocess.run([sys.executable, __file__, "--measure", str(path)],
                                      capture_output=True, text=True, check=True).stdout)
        size = path.stat().st_size
        rt = r["recorded_s"]
        print(f"| {minutes:g} min 2048x10 ({r['datagrams']:.0f} datagrams; written in "
              f"{made:.0f} s) | {size / 1e9:.2f} GB | {r['check_s']:.1f} s "
              f"({rt / r['check_s']:.0f}x real time) | {r['read_s']:.1f} s "
              f"({rt / r['read_s']:.0f}x) | {r['send_s']:.1f} s ({rt / r['send_s']:.0f}x) | "
              f"{r['peak_rss_mb']:.0f} MB |")
        if not a.keep:
            path.unlink()
            path.with_suffix(".json").unlink()


if __name__ == "__main__":
    main()
