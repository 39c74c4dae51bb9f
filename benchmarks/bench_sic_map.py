"""The reference SIC's map, a frame at a time: its voxel sets compiled (hash tables) and in
numpy (sorted runs, what runs without numba), side by side on the same frames in one run.

Each recorded frame (``bench_sic_field``'s cache: the emulator runs once per scene, mode and
sensor) is decoded and put into the world once, then added to both maps in turn, each timed
on its own (``StemMap.add`` with the map's eviction, and the tile jobs a worker would take
every third frame, made and dropped). The stem algorithm does not run. Pinned to one CPU.

    python benchmarks/bench_sic_map.py --scene pine-thinning --mode 2048x10

Prints the median, 99th percentile and maximum of each map's frame, the ratio, and each
map's memory at the end.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="pine-thinning")
    ap.add_argument("--mode", default="2048x10")
    ap.add_argument("--sensor", default="os0-64-rev7")
    ap.add_argument("--frames", type=int, default=None, help="only the first N frames")
    ap.add_argument("--max-points", type=int, default=12_000_000)
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache/tcf-hil/bench-sic")
    a = ap.parse_args(argv)

    import bench_sic_field as bsf

    from tcf_hil.sic import _map, _voxelset
    from tcf_hil.sic._stems import stem_params

    d = bsf.record(a.scene, a.mode, a.sensor, a.cache, max_frames=None)
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    frames: list[tuple[Any, ...]] = []

    class Capture(_map.StemMap):  # the SIC's own map stands aside: its frames are kept
        def add(self, pts: Any, sensor_xy: Any = None, widths: Any = None) -> int:
            frames.append((pts, sensor_xy, widths))
            return 0

    from tcf_hil.experiments import offline

    offline.StemMap = Capture  # type: ignore[misc]
    _voxelset.warm()
    maps: dict[str, _map.StemMap] = {}
    ms: dict[str, list[float]] = {"compiled": [], "numpy": []}
    for name in ms:
        m = _map.StemMap(stem_params("field"), max_points=a.max_points,
                         compiled_sets=name == "compiled")
        m.defer_runs = True
        maps[name] = m
    count = [0]

    def on_frame() -> None:
        while frames:
            pts, xy, w = frames.pop(0)
            count[0] += 1
            for name, m in maps.items():
                t0 = time.perf_counter()
                m.add(pts, xy, w)
                if count[0] % 3 == 0:
                    job = m.next_job()
                    if job is not None:
                        m.accept(job.tid, [])
                ms[name].append((time.perf_counter() - t0) * 1000.0)
        if a.frames and count[0] >= a.frames:
            raise StopIteration

    orig = offline.OfflineSic.lidar_frame

    def lidar_frame(self: Any, fid: int, arr: Any) -> None:
        orig(self, fid, arr)
        on_frame()

    offline.OfflineSic.lidar_frame = lidar_frame  # type: ignore[method-assign]
    offline.OfflineSic.finish = lambda self: {"objects": []}  # type: ignore[method-assign]
    try:
        bsf.replay(d, "field")
    except StopIteration:
        pass
    print(f"{a.scene} {a.mode} {a.sensor}: {count[0]} frames, cap {a.max_points:,} points")
    for name, v in ms.items():
        x = np.asarray(v[1:])  # the first frame compiles nothing here, but allocates
        print(f"  {name:9s} frame p50 {np.median(x):6.1f}  p99 {np.percentile(x, 99):6.1f}  "
              f"max {x.max():6.1f} ms; {maps[name].stats.points:,} points, "
              f"{maps[name].nbytes() / 2**20:.0f} MB")
    c, n = np.asarray(ms["compiled"][1:]), np.asarray(ms["numpy"][1:])
    print(f"  numpy / compiled: p50 {np.median(n) / np.median(c):.2f}x, "
          f"p99 {np.percentile(n, 99) / np.percentile(c, 99):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
