"""Natural stands: what it costs to generate them, and what culling by the track saves.

Run: ``python benchmarks/bench_stands.py [--big-ha 50] [--frames 20]
[--geometries curves,mesh] [--json OUT]``

1. Generation: each stand in a fresh process (its peak memory is the process's): the stems
   and their ground truth, then the scenery (branches, foliage, understory, ...), then the
   scene the lidar casts through (Embree: stems and branches as round curves, or as meshes:
   ``--geometries``), for ``pine-thinning`` (1 ha) and a ``pine-thinning`` of ``--big-ha``
   hectares with ``stand.detail_range_m`` = 60 m (the detail the sensor can reach from the
   track).
2. Culling: ``pine-thinning``'s first ``--frames`` frames at 1024x10 with the realistic sensor,
   built whole and with ``detail_range_m`` = 20, 30 and 40 m: the triangles each keeps,
   and how many returns differ from the whole stand's (byte for byte: range, signal,
   reflectivity and the object hit of every pixel).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np

_CHILD = r"""
import json, math, resource, sys, time
from tcf_hil.forest import generate_forest, ground_truth
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.scene import Scene
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


def culling(frames: int, ranges: list[float]) -> list[dict[str, Any]]:
    from tcf_hil.lidar import LidarRun
    from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict

    base = scenario_to_dict(load_scenario("pine-thinning"))
    ref: list[Any] | None = None
    rows = []
    for r in [0.0, *ranges]:
        d = json.loads(json.dumps(base))
        d["stand"]["detail_range_m"] = r
        run = LidarRun(scenario_from_dict(d), mode="1024x10", max_frames=frames)
        sc = run.forest.scenery()
        t0 = time.perf_counter()
        got = [(fr.packets.copy(), fr.stem_id.copy()) for fr, _ in run.datagrams()]
        dt = (time.perf_counter() - t0) / frames
        if ref is None:
            ref = got
        diff = sum(int(np.count_nonzero(a[1] != b[1])) for a, b in zip(got, ref, strict=True))
        bytes_same = all(np.array_equal(a[0], b[0]) for a, b in zip(got, ref, strict=True))
        rows.append({"detail_range_m": r, "triangles": len(run.scene.faces),
                     "scenery_triangles": sc.solid_triangles if sc is not None else 0,
                     "crowns": len(sc.foliage) if sc is not None else 0,
                     "pixels_whose_object_differs": diff, "packets_identical": bytes_same,
                     "ms_per_frame": 1000.0 * dt})
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
        res["culling"] = culling(a.frames, [20.0, 30.0, 40.0])
    print(f"(this process peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB)")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
