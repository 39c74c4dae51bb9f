"""Lidar pipeline benchmark: rays/s and x real time for pose -> rays -> cast -> returns ->
packets, next to the bare cast of the same rays in the same run, on Forests II, V and X at
512/1024/2048 columns, for Embree and open3d.

Run: ``python benchmarks/bench_lidar.py [--frames 20] [--forests II,V,X]
[--sensors ideal,os0-64-rev7] [--geometries mesh,curves] [--foliage volume,facets]
[--json OUT]`` (the sensor's
physics: footprint, echoes, detection and noise, after the cast; the bare cast is the centre
rays' alone).

The pipeline is timed as a run reads it: ``--frames`` consecutive frames from the middle of
the track (after one frame of warm-up), each made, encoded into its packets and finished
(headers, CRC); its figures are medians over them (the machines here are shared and noisy;
the pose of a second of frames is asked at once, so one frame in twenty carries it). The
bare cast of each frame's very rays, made by a second emulator, is timed between them:
the backend's own ``cast`` (for Embree the directly bound library the pipeline casts
through, :mod:`emulators.embree`), and for Embree also embreex's ``run`` on a scene of its
own ("embreex ms", meshes only: embreex casts no curves). Ratio = bare / pipeline.
``--geometries``: the stems and branches as meshes (``stems.tolerance_mm``) and/or as
Embree's round curves (``stems.geometry``; curves on Embree only); ``--foliage``: a natural
stand's foliage as porous crowns (``volume``, beside curves only) and/or facets
(``stand.foliage_as``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time

import numpy as np

from emulators.lidar import SENSOR_PRESETS, Os0Emulator
from protocols.ouster import finish_lidar_packets, os0_64_metadata
from tcf_hil._crc import fast_crc_rows
from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.scene.embree import EmbreeCaster
from tcf_hil.world.track import Trajectory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--forests", default="II,V,X")
    ap.add_argument("--modes", default="512x10,1024x10,2048x10")
    ap.add_argument("--backends", default="embree,open3d")
    ap.add_argument("--sensors", default="ideal",
                    help=f"comma-separated presets: {', '.join(SENSOR_PRESETS)}")
    ap.add_argument("--geometries", default="mesh",
                    help="comma-separated: mesh, curves (stems and branches)")
    ap.add_argument("--foliage", default="auto",
                    help="comma-separated: auto, volume, facets (natural stands' foliage)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    print(f"{'forest':14} {'geometry':8} {'foliage':7} {'prims':>9} {'sensor':12} "
          f"{'backend':7} {'mode':8} "
          f"{'rays':>7} {'bare ms':>8} "
          f"{'pipe ms':>8} "
          f"{'ratio':>6} {'x RT':>5} {'Mrays/s':>8} {'finish ms':>9} {'embreex ms':>10}")
    crc = fast_crc_rows()
    for fname in a.forests.split(","):
        forest = generate_forest(load_scenario(fname))
        track = Trajectory.from_config(forest.scenario.track, forest.terrain)
        for backend, geometry, foliage in itertools.product(
                a.backends.split(","), a.geometries.split(","), a.foliage.split(",")):
            if (geometry == "curves" and backend != "embree") or (
                    foliage == "volume" and geometry == "mesh"):
                continue
            scene = Scene.from_forest(forest, backend=backend, geometry=geometry,
                                      foliage_as=foliage)
            prims = len(scene.faces) + scene.curve_count
            embreex = EmbreeCaster(scene.vertices, scene.faces, direct=False) \
                if backend == "embree" and geometry == "mesh" else None
            for mode, sensor in itertools.product(a.modes.split(","), a.sensors.split(",")):
                meta = os0_64_metadata(mode)
                emu = Os0Emulator(meta, scene, track, start_ns=track.t0_ns,
                                  sensor=SENSOR_PRESETS[sensor])
                ray_maker = Os0Emulator(meta, scene, track, start_ns=track.t0_ns)
                fmt = meta.packet_format
                n = max(1, int(track.duration_ns // emu.period_ns))
                k0 = max(1, n // 2 - a.frames // 2)
                emu.frame(k0 - 1)  # warm-up: pools, caches, the first pose block
                o, d, _, _ = ray_maker.rays(k0 - 1, np.float32)
                for caster in (scene.caster, embreex):  # and the casts (embreex commits its
                    if caster is not None:  # scene on its first cast)
                        caster.cast(o, d)
                bare, pipe, enc, other = [], [], [], []
                for k in range(k0, k0 + a.frames):
                    o, d, _, _ = ray_maker.rays(k, np.float32)  # what frame() casts
                    t0 = time.perf_counter()
                    scene.caster.cast(o, d)
                    bare.append(time.perf_counter() - t0)
                    if embreex is not None:
                        t0 = time.perf_counter()
                        embreex.cast(o, d)
                        other.append(time.perf_counter() - t0)
                    buf = np.empty((fmt.packets_per_frame, fmt.packet_bytes), np.uint8)
                    t0 = time.perf_counter()
                    fr = emu.frame(k, packets=buf)
                    t1 = time.perf_counter()
                    finish_lidar_packets(fmt, fr.packets, frame_id=1, init_id=meta.init_id,
                                         prod_sn=meta.prod_sn, crc_rows=crc)
                    t2 = time.perf_counter()
                    pipe.append(t2 - t0)
                    enc.append(t2 - t1)
                rays = meta.pixels * meta.columns
                b, p, e = (statistics.median(x) for x in (bare, pipe, enc))
                x = statistics.median(other) if other else float("nan")
                period = 1.0 / meta.frequency_hz
                row = {"forest": fname, "geometry": geometry, "foliage": foliage,
                       "crowns": scene.crown_count, "triangles": len(scene.faces),
                       "curve_segments": scene.curve_count, "sensor": sensor,
                       "backend": backend, "mode": mode, "rays": rays,
                       "bare_ms": b * 1e3, "pipeline_ms": p * 1e3, "ratio": b / p,
                       "x_realtime": period / p, "mrays_s": rays / p / 1e6,
                       "finish_ms": e * 1e3, "embreex_ms": x * 1e3}
                rows.append(row)
                print(f"{fname:14} {geometry:8} {foliage:7} {prims:9d} {sensor:12} "
                      f"{backend:7} {mode:8} "
                      f"{rays:7d} {b * 1e3:8.1f} "
                      f"{p * 1e3:8.1f} "
                      f"{b / p:6.2f} {period / p:5.1f} {rays / p / 1e6:8.2f} {e * 1e3:9.2f} "
                      f"{x * 1e3:10.1f}", flush=True)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
