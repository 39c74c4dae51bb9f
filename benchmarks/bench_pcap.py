"""``tcf-hil lidar pcap`` end to end against a plain embreex cast of the very same rays.

Run: ``python benchmarks/bench_pcap.py [--scene forest-x] [--mode 2048x10]
[--sensors default,ideal] [--frames 60] [--workers N] [--repeat 3] [--geometry mesh]
[--json OUT]``

Per sensor, ``--repeat`` times in alternation (side by side, so the machine's other load
falls on both alike):

- **pcap**: :func:`tcf_hil.devices.offline.record_pcap`, the function ``tcf-hil lidar pcap``
  calls, for ``--frames`` frames into a temporary directory, rendered by one process per
  CPU (its default: blocks of 10 frames each; ``--workers 1``: one process, its ray
  threads over the CPUs); the time a frame from the progress callback (ray cast, the
  sensor's physics, packets, pcap records, labels, the poses of ``sensor_poses.csv``): the
  span from the first frame (warm-up) to the last over the frames between;
- **embreex**: the very rays of those frames (``Os0Emulator.rays``: the centre rays, as
  ``--sensor ideal`` casts them) cast by embreex's own ``run`` on the same meshes.

Figures: the medians of each, the ratio embreex / pcap (1 would be a pcap as fast as the
bare cast; the issue's aim for the default sensor is 0.5 or more) and the end-to-end wall
time of each record_pcap call (scene build included). embreex casts no curves: with
``--geometry mesh`` (the default) both sides cast the stems and branches as meshes
(``stems.geometry = "mesh"``, like for like); with ``--geometry as-is`` the pcap keeps the
scenario's own geometry (Forest X's round curves) against embreex on the meshes.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from tcf_hil.cli._shared import scenario_with_faults
from tcf_hil.devices.lidar import LidarRun
from tcf_hil.devices.offline import record_pcap
from tcf_hil.scenario import scenario_from_dict, scenario_to_dict
from tcf_hil.world.scene.embree import EmbreeCaster


def _scenario(scene: str, sensor: str | None, geometry: str) -> Any:
    scn = scenario_with_faults(scene, (), sensor=sensor)
    if geometry == "mesh":
        d = scenario_to_dict(scn)
        d.setdefault("stems", {})["geometry"] = "mesh"
        scn = scenario_from_dict(d)
    return scn


def _pcap_frames(scn: Any, mode: str, frames: int, workers: int | None
                 ) -> tuple[list[float], float]:
    stamps: list[float] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as out:
        record_pcap(scn, out, mode=mode, max_frames=frames, workers=workers,
                    progress=lambda k, n: stamps.append(time.perf_counter()))
    wall = time.perf_counter() - t0
    # frames come in blocks from several renderer processes: the time per frame is the
    # span from the first frame to the last over the frames between (the first: warm-up)
    return [(stamps[-1] - stamps[0]) / (len(stamps) - 1)], wall


def _embreex_frames(run: LidarRun, caster: EmbreeCaster, frames: int) -> list[float]:
    out = []
    for k in range(frames):
        o, d, _, _ = run.emu.rays(k, np.float32)
        t0 = time.perf_counter()
        caster.cast(o, d)
        if k:
            out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="forest-x")
    ap.add_argument("--mode", default="2048x10")
    ap.add_argument("--sensors", default="default,ideal",
                    help="comma-separated: default (the scenario's own sensor) or a preset")
    ap.add_argument("--frames", type=int, default=60,
                    help="frames a pcap (60: three blocks of 10 for each of two renderers)")
    ap.add_argument("--workers", type=int, default=None,
                    help="renderer processes (default: record_pcap's, one per CPU)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--geometry", choices=["mesh", "as-is"], default="mesh")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    print(f"{'scene':12} {'mode':8} {'sensor':12} {'pcap ms':>8} {'embreex ms':>10} "
          f"{'ratio':>6} {'wall s':>7}", flush=True)
    for name in a.sensors.split(","):
        sensor = None if name == "default" else name
        scn = _scenario(a.scene, sensor, a.geometry)
        run = LidarRun(_scenario(a.scene, sensor, "mesh"), mode=a.mode, max_frames=a.frames)
        caster = EmbreeCaster(run.scene.vertices, run.scene.faces, direct=False)
        o, d, _, _ = run.emu.rays(0, np.float32)
        caster.cast(o, d)  # embreex commits its scene on its first cast
        pcap: list[float] = []
        cast: list[float] = []
        walls: list[float] = []
        ratios: list[float] = []
        for _ in range(a.repeat):
            p, wall = _pcap_frames(scn, a.mode, a.frames, a.workers)
            c = _embreex_frames(run, caster, a.frames)
            pcap += p
            cast += c
            walls.append(wall)
            ratios.append(statistics.median(c) / statistics.median(p))
        row = {"scene": a.scene, "mode": a.mode, "sensor": name, "geometry": a.geometry,
               "pcap_ms": statistics.median(pcap) * 1e3,
               "embreex_ms": statistics.median(cast) * 1e3,
               "ratio": statistics.median(ratios), "ratios": ratios,
               "wall_s": statistics.median(walls), "frames": a.frames, "repeat": a.repeat,
               "workers": a.workers}
        rows.append(row)
        print(f"{a.scene:12} {a.mode:8} {name:12} {row['pcap_ms']:8.1f} "
              f"{row['embreex_ms']:10.1f} {row['ratio']:6.2f} {row['wall_s']:7.1f}",
              flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
