"""Natural stands: what it costs to generate them, and what culling by the track saves.

Run: ``python benchmarks/bench_stands.py [--big-ha 50] [--frames 20]
[--geometries curves,mesh] [--culling-ha 4] [--ranges 20,40,60,80] [--skip-big]
[--skip-culling] [--json OUT]``

1. Generation: each stand in a fresh process (its peak memory is the process's): the stems
   and their ground truth, then the scenery (branches, foliage, understory, ...), then the
   scene the lidar casts through (Embree: stems and branches as round curves, or as meshes:
   ``--geometries``), for ``pine-thinning`` (1 ha) and a ``pine-thinning`` of ``--big-ha``
   hectares with ``stand.detail_range_m`` = 60 m (the detail the sensor can reach from the
   track).
2. Culling: a ``pine-thinning`` of ``--culling-ha`` hectares (4: the 100 m track through
   the middle of a 200 m square), its first ``--frames`` frames at 1024x10 with the
   realistic sensor, built whole and with ``detail_range_m`` = ``--ranges``: what each
   keeps, and how many pixels differ from the whole stand's: the object hit, the return
   (range, signal, reflectivity: any field but NEAR_IR), the ambient NEAR_IR, and whether
   the packets are byte for byte the same.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

_CHILD = r"""
import json, math, resource, sys, time
from tcf_hil.world.forest import generate_forest, ground_truth
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.world.scene import Scene
ha, rng_m, geometry = float(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
d = scenario_to_dict(load_scenario("pine-thinning"))
side = 100.0 * math.sqrt(ha)
d["plot"]["size_m"] = [side, side]
d["stems"]["count"] = round(2200 * ha)
d["stand"]["detail_range_m"] = rng_m
scn = scenario_from_dict(d)
t0 = time.perf_counter()
f = generate_forest(scn)
t1 = time.perf_counter()
gt = ground_truth(f)
t2 = time.perf_counter()
sc = f.scenery()
t3 = time.perf_counter()
scene = Scene.from_forest(f, geometry=geometry)
t4 = time.perf_counter()
print(json.dumps({"ha": ha, "stems": len(f.stems), "detail_range_m": rng_m,
                  "geometry": geometry, "stems_s": t1 - t0, "ground_truth_s": t2 - t1,
                  "scenery_s": t3 - t2, "scene_s": t4 - t3, "total_s": t4 - t0,
                  "scenery_triangles": sc.solid_triangles, "crowns": len(sc.foliage),
                  "scene_triangles": len(scene.faces),
                  "scene_curve_primitives": scene.curve_count, "counts": sc.counts,
                  "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}))
"""


def generation(ha: float, rng_m: float, geometry: str) -> dict[str, Any]:
    out = subprocess.run([sys.executable, "-c", _CHILD, str(ha), str(rng_m), geometry],
                         check=True, capture_output=True, text=True)
    row: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return row


def culling(frames: int, ranges: list[float], ha: float) -> list[dict[str, Any]]:
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict

    base = scenario_to_dict(load_scenario("pine-thinning"))
    side = 100.0 * math.sqrt(ha)
    base["plot"]["size_m"] = [side, side]
    base["stems"]["count"] = round(2200 * ha)
    ref: list[Any] | None = None
    rows = []
    for r in [0.0, *ranges]:
        d = json.loads(json.dumps(base))
        d["stand"]["detail_range_m"] = r
        t0 = time.perf_counter()
        run = LidarRun(scenario_from_dict(d), mode="1024x10", max_frames=frames)
        sc = run.forest.scenery()
        build = time.perf_counter() - t0
        t0 = time.perf_counter()
        got = [(fr.packets.copy(), fr.stem_id.copy(), fr.fields) for fr, _ in run.datagrams()]
        dt = (time.perf_counter() - t0) / frames
        if ref is None:
            ref = got
        pairs = list(zip(got, ref, strict=True))
        diff = sum(int(np.count_nonzero(a[1] != b[1])) for a, b in pairs)
        ret = sum(int(np.count_nonzero(np.any([a[2][k] != b[2][k] for k in a[2]
                                                if k != "NEAR_IR"], axis=0)))
                  for a, b in pairs)
        nir = sum(int(np.count_nonzero(a[2]["NEAR_IR"] != b[2]["NEAR_IR"])) for a, b in pairs)
        bytes_same = all(np.array_equal(a[0], b[0]) for a, b in pairs)
        rows.append({"ha": ha, "detail_range_m": r,
                     "branch_segments": run.scene.curve_count,
                     "scenery_triangles": sc.solid_triangles if sc is not None else 0,
                     "crowns": len(sc.foliage) if sc is not None else 0,
                     "pixels": frames * run.meta.pixels * run.meta.columns,
                     "pixels_whose_object_differs": diff, "returns_that_differ": ret,
                     "near_ir_that_differs": nir, "packets_identical": bytes_same,
                     "build_s": build, "ms_per_frame": 1000.0 * dt,
                     "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6})
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--big-ha", type=float, default=50.0)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--skip-big", action="store_true")
    ap.add_argument("--skip-culling", action="store_true")
    ap.add_argument("--geometries", default="curves,mesh")
    ap.add_argument("--culling-ha", type=float, default=4.0,
                    help="the stand culling is measured on (the track, 100 m, through its "
                         "middle)")
    ap.add_argument("--ranges", default="20,40,60,80",
                    help="stand.detail_range_m values to compare with the whole stand")
    a = ap.parse_args()
    res: dict[str, Any] = {"generation": [], "culling": []}
    for ha, rng_m in ([(1.0, 0.0)] + ([] if a.skip_big else [(a.big_ha, 60.0)])):
        for geometry in a.geometries.split(","):
            row = generation(ha, rng_m, geometry)
            res["generation"].append(row)
            print(f"{ha:g} ha, {row['stems']} stems, detail {rng_m:g} m, {geometry}: stems "
                  f"{row['stems_s']:.1f} s, ground truth {row['ground_truth_s']:.1f} s, "
                  f"scenery {row['scenery_s']:.1f} s, scene {row['scene_s']:.1f} s, total "
                  f"{row['total_s']:.1f} s, {row['scene_triangles'] / 1e6:.2f} M triangles + "
                  f"{row['scene_curve_primitives'] / 1e6:.2f} M curve primitives, peak "
                  f"{row['peak_gb']:.2f} GB", flush=True)
    if not a.skip_culling:
        res["culling"] = culling(a.frames, [float(v) for v in a.ranges.split(",")],
                                 a.culling_ha)
    print(f"(this process peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB)")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
