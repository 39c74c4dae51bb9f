"""Speed against error: stem tessellation tolerance -> range error against the exact
surfaces (tcf_hil.world.analytic) -> rays/s, on one forest and mode, Embree.

Run: ``python benchmarks/bench_tolerance.py [--forest V] [--mode 1024x10]
[--tolerances-mm 0.5,1,2,5,10,20,curves] [--json OUT]``. The surface error (along the
normal) is bounded by the tolerance; the range error is that divided by |cos incidence| and
grows for grazing rays. ``curves``: the stems as Embree's round curves instead
(``stems.geometry``), to within :data:`tcf_hil.world.forest.mesh.CURVE_TOLERANCE_M`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from emulators.lidar import Os0Emulator
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import load_scenario
from tcf_hil.world.analytic import refine_hits
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.track import Trajectory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--forest", default="V")
    ap.add_argument("--mode", default="1024x10")
    ap.add_argument("--tolerances-mm", default="0.5,1,2,5,10,20,curves")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    scn = load_scenario(a.forest)
    forest = generate_forest(scn)
    track = Trajectory.from_config(scn.track, forest.terrain)
    meta = os0_64_metadata(a.mode)
    rows = []
    print(f"{'tol mm':>6} {'primitives':>10} {'stem hits':>9} {'surf p99 mm':>11} "
          f"{'surf max mm':>11} {'range p50 mm':>12} {'range p99 mm':>12} {'bias mm':>8} "
          f"{'Mrays/s':>8}")
    for spec in a.tolerances_mm.split(","):
        curves = spec == "curves"
        tol = 0.0 if curves else float(spec)
        scene = (Scene.from_forest(forest, geometry="curves") if curves
                 else Scene.from_forest(forest, stem_tolerance_m=tol / 1000, geometry="mesh"))
        emu = Os0Emulator(meta, scene, track, start_ns=track.t0_ns)
        n = max(1, int(track.duration_ns // emu.period_ns))
        rng_err, surf_err, secs, rays = [], [], [], 0
        for k in np.linspace(0, n - 1, a.frames).astype(int):
            o, d, _, _ = emu.rays(int(k))
            t0 = time.perf_counter()
            t, sid = scene.cast(o, d)
            secs.append(time.perf_counter() - t0)
            rays = len(o)
            exact, cos = refine_hits(forest, o, d, t, sid)
            m = (sid > 0) & np.isfinite(exact) & (t < 50.0)
            e = t[m] - exact[m]
            rng_err.append(e)
            surf_err.append(e * cos[m])
        e = np.concatenate(rng_err)
        s = np.abs(np.concatenate(surf_err))
        row = {"tolerance_mm": spec, "triangles": len(scene.faces),
               "curve_primitives": scene.curve_count, "stem_hits": len(e),
               "surface_p99_mm": float(np.percentile(s, 99) * 1e3),
               "surface_max_mm": float(s.max() * 1e3),
               "range_p50_mm": float(np.percentile(np.abs(e), 50) * 1e3),
               "range_p99_mm": float(np.percentile(np.abs(e), 99) * 1e3),
               "bias_mm": float(e.mean() * 1e3),
               "mrays_s": rays / statistics.median(secs) / 1e6}
        rows.append(row)
        print(f"{spec:>6} {len(scene.faces) + scene.curve_count:10d} {row['stem_hits']:9d} "
              f"{row['surface_p99_mm']:11.3f} {row['surface_max_mm']:11.3f} "
              f"{row['range_p50_mm']:12.3f} "
              f"{row['range_p99_mm']:12.3f} {row['bias_mm']:8.3f} {row['mrays_s']:8.2f}",
              flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
