"""The offline lidar run (``tcf-hil lidar pcap``): the sensor driven along a scenario's track
as fast as the machine allows, its packets written to a pcap file with the run's sidecar
files beside it (the same bytes a live stream sends)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from protocols.pcap import PcapWriter
from tcf_hil._io import atomic_path, ensure_dir, write_gathered
from tcf_hil.devices._ring import pcap_parts
from tcf_hil.devices.faults import FaultLog
from tcf_hil.devices.lidar import LABELS, LidarRun, RecordResult
from tcf_hil.scenario import Scenario


def record_pcap(scn: Scenario, out_dir: str | Path, *, mtu: int = 1500,
                sensor_ip: str = "127.0.0.1",
                progress: Callable[[int, int], None] | None = None,
                workers: int | None = None, **run_kw: Any) -> RecordResult:
    """Drive the sensor along the scenario's track and write ``out_dir``: ``lidar.pcap``
    (lidar to 7502, LEGACY IMU at 100 Hz to 7503, fragmented at ``mtu``), ``metadata.json``,
    ``ground_truth.json`` (with ``returns`` per stem), ``visibility.json`` and
    ``sensor_poses.csv`` (time_ns, x, y, z, qw, qx, qy, qz: the sensor frame in the world at
    every column time stamp). ``workers``: renderer processes (default: one per CPU this
    process may use; :meth:`LidarRun.rendered`). Keyword arguments go to
    :class:`LidarRun`."""
    out = Path(out_dir)
    ensure_dir(out)
    run = LidarRun(scn, **run_kw)
    writer = PcapWriter(mtu=mtu)
    dest = run.meta.udp_dest
    flog = FaultLog(out / "faults.jsonl", run.track.t0_ns) \
        if run.udp_faults or run.lidar_faults else None
    try:
        # unbuffered: a frame's records (a few MB) go from their pieces to the file at once
        with atomic_path(out / "lidar.pcap") as tmp, open(tmp, "wb", buffering=0) as fh, \
                atomic_path(out / LABELS) as ltmp, open(ltmp, "wb") as lh:
            write_gathered(fh.fileno(), [writer.header()])
            lh.write(run.labels_header())
            cpus = len(os.sched_getaffinity(0)) if workers is None else workers
            for k, rf in enumerate(run.rendered(cpus)):
                write_gathered(fh.fileno(), pcap_parts(writer, rf.datagrams, sensor_ip, dest))
                lh.write(rf.labels)
                if flog is not None:
                    for ev in run.last_events:
                        flog.log(ev, "lidar")
                if progress:
                    progress(k + 1, run.frames)
    finally:
        if flog is not None:
            flog.close()
    run.write_sidecars(out)
    return run.result(out)
