"""The reference SIC's tile runs (the stem algorithm on a map tile and its border), the
packed integer sort (:mod:`tcf_hil.sic._fast`) against numpy's argsort and unique,
side by side on the same tiles.

An offline cell (emulator and SIC in one process) runs ``--frames`` frames and every tile
the SIC hands to the stem algorithm is kept (the runs its map's bound forces and the final
ones); then the stem algorithm runs over all of them ``--repeats`` times, the packed sort on
and off in turn. Prints the tiles, their points, seconds per pass (medians) and the ratio,
and checks that both give the same stems, to the bit.

Run: ``python benchmarks/bench_sic_tiles.py [--forest forest-x-natural] [--mode 2048x10]
[--frames 250] [--repeats 5]``
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np

import tcf_hil.sic._fast as sorting
import tcf_hil.sic._map as smap
from tcf_hil.experiments.offline import run_offline
from tcf_hil.scenario import load_scenario
from tcf_hil.sic import use_compiled_fits
from tcf_hil.sic._stems import identify_stems


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--forest", default="forest-x-natural")
    ap.add_argument("--mode", default="2048x10")
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    use_compiled_fits()
    tiles: list[tuple[np.ndarray, np.ndarray, Any]] = []
    orig = smap.identify_stems

    def keep(pts: np.ndarray, prm: Any, *, ground_z: np.ndarray) -> dict[str, Any]:
        tiles.append((pts.copy(), ground_z.copy(), prm))
        return orig(pts, prm, ground_z=ground_z)

    smap.identify_stems = keep  # type: ignore[assignment]
    t0 = time.perf_counter()
    run_offline(load_scenario(a.forest), mode=a.mode, max_frames=a.frames)
    smap.identify_stems = orig  # type: ignore[assignment]
    print(f"{a.forest} {a.mode}, {a.frames} frames: {len(tiles)} tile runs, "
          f"{sum(len(t[0]) for t in tiles):,} points (cell {time.perf_counter() - t0:.0f} s)")

    def one_pass() -> tuple[float, list[dict[str, Any]]]:
        t = time.perf_counter()
        docs = [identify_stems(p, prm, ground_z=g) for p, g, prm in tiles]
        return time.perf_counter() - t, docs

    one_pass()  # compiled kernels warm
    times: dict[bool, list[float]] = {True: [], False: []}
    docs: dict[bool, list[dict[str, Any]]] = {}
    for _ in range(a.repeats):
        for packed in (True, False):
            sorting.PACKED = packed
            s, docs[packed] = one_pass()
            times[packed].append(s)
    sorting.PACKED = True
    new, old = statistics.median(times[True]), statistics.median(times[False])
    print("| sort | s per pass (median) | ratio |")
    print("|---|---|---|")
    print(f"| numpy argsort / unique | {old:.2f} | 1.00 |")
    print(f"| packed | {new:.2f} | {new / old:.2f} |")
    print("same stems:", docs[True] == docs[False])


if __name__ == "__main__":
    main()
