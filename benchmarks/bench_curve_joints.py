"""Round curves' joints, side by side: the stems as they were (rings spaced by each probe's
own curvature, no joint spheres), with the ring spacing that looks :data:`CURVE_REACH_M`
ahead for a sharper bend, and with that and the joint spheres (:data:`JOINT_SPHERES`).

For each forest: the curve primitives, the bare cast of the same frames' centre rays at
2048x10 (medians over ``--repeats`` passes of ``--frames`` frames, the three scenes in turn
in one process) and, with ``--grazing``, how many of 400,000 rays aimed 0.2 mm inside the
stems' true surfaces pass through each (the grazing test's rays).

Run: ``python benchmarks/bench_curve_joints.py [--forests X,forest-x-natural,pine-thinning]
[--frames 20] [--repeats 3] [--grazing]``
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import tcf_hil.world.forest.mesh as mesh
import tcf_hil.world.scene as scene_mod
from emulators.lidar import Os0Emulator
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.track import Trajectory

CONFIGS = {"before": (0.0, False), "spacing": (mesh.CURVE_REACH_M, False),
           "spacing+spheres": (mesh.CURVE_REACH_M, True)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--forests", default="X,forest-x-natural,pine-thinning")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--grazing", action="store_true")
    a = ap.parse_args()
    reach0, spheres0 = mesh.CURVE_REACH_M, scene_mod.JOINT_SPHERES
    print("| forest | stems as | curve primitives | bare cast ms | ratio | grazing rays through |")
    print("|---|---|---|---|---|---|")
    for name in a.forests.split(","):
        forest = generate_forest(load_scenario(name))
        track = Trajectory.from_config(forest.scenario.track, forest.terrain)
        scenes = {}
        for label, (reach, spheres) in CONFIGS.items():
            mesh.CURVE_REACH_M, scene_mod.JOINT_SPHERES = reach, spheres
            scenes[label] = scene_mod.Scene.from_forest(forest, backend="embree",
                                                        geometry="curves")
        mesh.CURVE_REACH_M, scene_mod.JOINT_SPHERES = reach0, spheres0
        maker = Os0Emulator(os0_64_metadata("2048x10"), scenes["before"], track,
                            start_ns=track.t0_ns)
        k0 = max(1, int(track.duration_ns // maker.period_ns) // 2 - a.frames // 2)
        rays = [maker.rays(k, np.float32)[:2] for k in range(k0, k0 + a.frames)]
        for sc in scenes.values():
            sc.caster.cast(*rays[0])  # committed, warm
        times: dict[str, list[float]] = {k: [] for k in scenes}
        for _ in range(a.repeats):
            for label, sc in scenes.items():
                for o, d in rays:
                    t0 = time.perf_counter()
                    sc.caster.cast(o, d)
                    times[label].append(time.perf_counter() - t0)
        base = statistics.median(times["before"])
        for label, sc in scenes.items():
            through = _grazing(forest, sc) if a.grazing else "-"
            m = statistics.median(times[label])
            print(f"| {name} | {label} | {sc.curve_count:,} | {m * 1e3:.2f} | {m / base:.3f} "
                  f"| {through} |", flush=True)


def _grazing(forest, sc) -> str:  # type: ignore[no-untyped-def]
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "tcf_hil"))
    from test_hard_cases import _grazing_curve_rays  # the test's rays

    rng = np.random.default_rng(11)
    n = through = 0
    for _ in range(10):
        o, d, dist = _grazing_curve_rays(forest, rng, 40_000)
        t, _ = sc.cast(o, d)
        n += len(t)
        through += int((~(t <= dist + 1e-4)).sum())
    return f"{through} of {n:,}"


if __name__ == "__main__":
    main()
