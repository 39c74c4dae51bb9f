"""The adaptive beam footprints against the full one: the same frames, the same seed, the
range noise off and detection made a step (so only the footprint's geometry differs), on
Forests II, V and X; per frame the pixels supersampled, the lattice rays cast, ms per frame
(medians; the ``ideal`` sensor's beside), and how far the returns of ``adaptive`` (the
default: the row at a vertical edge) and ``edges`` (the grid at every edge) lie from the
full one's: the share of returns (in both) that differ by more than the range quantum
(1 mm) and by more than 5 mm, on stems and on the ground, and the share returned by one
only. The differences over 1 mm are split by whether the footprint sampled the pixel (an
edge) or took its centre ray alone.

Run: ``python benchmarks/bench_footprint.py [--cases II:1024x10,X:2048x10] [--frames 8]
[--samples 2]`` (noise and detection off as above, so its ms per frame are a little under
the default sensor's).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np

from emulators.lidar import SENSOR_PRESETS, Os0Emulator
from emulators.lidar._physics import Physics
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.track import Trajectory

DEFAULT_CASES = "II:1024x10,V:1024x10,V:2048x10,X:2048x10"
FOOTPRINTS = ("ideal", "adaptive", "edges", "full")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=DEFAULT_CASES,
                    help=f"forest:mode pairs, comma-separated (default {DEFAULT_CASES})")
    ap.add_argument("--frames", type=int, default=8, help="frames from mid-track (default 8)")
    ap.add_argument("--samples", type=int, default=2, help="footprint samples per FWHM")
    a = ap.parse_args()
    exact = dataclasses.replace(SENSOR_PRESETS["os0-64-rev7"], range_sigma_m=0.0,
                                range_sigma_min_m=0.0, detection_width=1e-6,
                                false_positive_rate=0.0, footprint_samples=a.samples)
    print("| forest | mode | footprint | pixels supersampled | lattice rays | ms/frame | "
          "x real time | differ > 1 mm: stems | ground | of which at edges | differ > 5 mm: "
          "stems | ground | returned by one only |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for case in a.cases.split(","):
        fname, mode = case.split(":")
        forest = generate_forest(load_scenario(fname))
        track = Trajectory.from_config(forest.scenario.track, forest.terrain)
        scene = Scene.from_forest(forest, backend="embree")
        meta = os0_64_metadata(mode)
        runs = {}
        for fp in FOOTPRINTS:
            sensor = (SENSOR_PRESETS["ideal"] if fp == "ideal"
                      else dataclasses.replace(exact, footprint=fp))
            emu = Os0Emulator(meta, scene, track, start_ns=track.t0_ns, seed=7, sensor=sensor)
            n = max(1, int(track.duration_ns // emu.period_ns))
            ks = range(n // 2, n // 2 + a.frames)
            emu.frame(ks[0] - 1)  # warm-up
            phys = emu.physics
            frames, ms, sup, cast, flagged = [], [], [], [], []
            for k in ks:
                t0 = time.perf_counter()
                fr = emu.frame(k)
                ms.append((time.perf_counter() - t0) * 1e3)
                frames.append(fr)
                if isinstance(phys, Physics):
                    sup.append(phys.last_flagged / (meta.columns * meta.pixels))
                    cast.append(phys.last_cast)
                    flagged.append(phys.last_flags.T.copy())  # (H, W) as the images
            runs[fp] = (frames, ms, sup, cast, flagged)
        rb = np.stack([f.fields["RANGE"] for f in runs["full"][0]]).astype(np.int64)

        def share(m: np.ndarray, within: np.ndarray, digits: int = 1) -> str:
            n = max(1, np.count_nonzero(within))
            pct = 100.0 * np.count_nonzero(m & within) / n
            return f"{pct:.{digits if pct >= 1 or pct == 0 else 2}f} %"

        for fp in FOOTPRINTS:
            frames, ms, sup, cast, flagged = runs[fp]
            med = statistics.median(ms)
            period_ms = 1e3 / meta.frequency_hz
            cols = (f"| {fname} | {mode} | {fp} | "
                    + (f"{100 * statistics.median(sup):.1f} % | "
                       f"{int(statistics.median(cast)):,} | " if sup else "– | – | ")
                    + f"{med:.1f} | {period_ms / med:.1f} |")
            if fp in ("adaptive", "edges"):
                ra = np.stack([f.fields["RANGE"] for f in frames]).astype(np.int64)
                sid = np.stack([f.stem_id for f in frames])
                edge = np.stack(flagged) != 0
                both = (ra > 0) & (rb > 0)
                diff = np.abs(ra - rb)
                stem, ground = both & (sid > 0), both & (sid == 0)
                big = diff > 1
                one = np.count_nonzero((ra > 0) != (rb > 0)) / max(1, np.count_nonzero(both))
                at_edges = share(edge, big & both, 0) if np.any(big & both) else "–"
                cols += (f" {share(big, stem)} | {share(big, ground)} | {at_edges} | "
                         f"{share(diff > 5, stem)} | {share(diff > 5, ground)} | "
                         f"{100 * one:.2f} % |")
            else:
                cols += " – | – | – | – | – | – |"
            if fp == "ideal":
                cols = cols.replace("| ideal |", "| `ideal` sensor |")
            print(cols, flush=True)


if __name__ == "__main__":
    main()
