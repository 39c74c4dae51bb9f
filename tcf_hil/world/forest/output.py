"""Write a generated forest: ground truth JSON, stem and terrain meshes (PLY), map.png."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from protocols.ply import encode_ply
from tcf_hil._io import ensure_dir, write_bytes_atomic, write_json_atomic
from tcf_hil._plots import forest_map
from tcf_hil.world.forest.generate import Forest, ground_truth
from tcf_hil.world.forest.mesh import stem_mesh, terrain_mesh
from tcf_hil.world.forest.scenery import scenery_mesh


def mesh_ply(mesh: trimesh.Trimesh) -> bytes:
    """Binary PLY with float64 vertices (trimesh writes float32, which loses metres at
    UTM-sized coordinates) and every face attribute as an int32 face property."""
    return encode_ply(mesh.vertices, mesh.faces,
                      {k: np.asarray(v) for k, v in mesh.face_attributes.items()},
                      comments=["tcf-hil"])


FILES = ("ground_truth.json", "stems.ply", "terrain.ply", "map.png")


def write_forest(forest: Forest, out_dir: str | Path, *, meshes: bool = True,
                 scenery: bool = False,
                 progress: Callable[[str], None] | None = None) -> list[Path]:
    """Write the forest's files into ``out_dir`` (each atomically); returns their paths.

    ``stems.ply`` carries a per-face ``stem_id`` (1-based, the ground-truth ``id``); with
    ``scenery``, a natural stand adds ``scenery.ply`` (branches, foliage, understory, dead
    wood, stumps, boulders) with the object id (``stem_id``, see the ground truth's
    ``object_ids``) and ``material`` (0 ground, 1 bark, 2 foliage, 3 dead wood, 4 rock) of
    every face.
    ``progress`` is called with the name of each file before it is built.
    """
    say = progress or (lambda _name: None)
    out = Path(out_dir)
    ensure_dir(out)
    scn = forest.scenario
    written = []
    say("ground_truth.json")
    gt = ground_truth(forest)
    write_json_atomic(out / "ground_truth.json", gt)
    written.append(out / "ground_truth.json")
    if meshes:
        say("stems.ply")
        tubes, ids = forest.tubes()
        sm = stem_mesh(tubes, scn.stems.tolerance_mm / 1000.0, forest.origin, ids)
        write_bytes_atomic(out / "stems.ply", mesh_ply(sm))
        say("terrain.ply")
        tm = terrain_mesh(forest.terrain, forest.bounds(), scn.terrain.tolerance_mm / 1000.0,
                          forest.origin)
        write_bytes_atomic(out / "terrain.ply", mesh_ply(tm))
        written += [out / "stems.ply", out / "terrain.ply"]
        sc = forest.scenery() if scenery else None
        if sc is not None:
            say("scenery.ply")
            mesh = scenery_mesh(sc)
            mesh.vertices = mesh.vertices + forest.origin
            write_bytes_atomic(out / "scenery.ply", mesh_ply(mesh))
            written.append(out / "scenery.ply")
        else:
            (out / "scenery.ply").unlink(missing_ok=True)
    else:  # never leave another forest's meshes beside this ground truth
        for name in ("stems.ply", "terrain.ply", "scenery.ply"):
            (out / name).unlink(missing_ok=True)
    say("map.png")
    pos = forest.positions()
    w, h = scn.plot.size_m
    pad = 2.0
    bounds = (-w / 2 - pad, -h / 2 - pad, w / 2 + pad, h / 2 + pad)
    terrain = None
    if not forest.terrain.is_flat:
        terrain = forest.terrain.grid(bounds, 0.05, max_vertices=40_000, coarsen=True)
    png = forest_map(pos[:, :2], list(forest.classes), 2.0 * forest.stems.r_bh,
                     f"{scn.name} (seed {forest.seed}): {len(pos)} stems", bounds,
                     track=(scn.track.start_m, scn.track.end_m), terrain=terrain)
    write_bytes_atomic(out / "map.png", png)
    written.append(out / "map.png")
    return written
