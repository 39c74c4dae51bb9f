"""Synthetic forest creation (SFC): terrain, stem placement and geometry, meshes, ground truth."""

from tcf_hil.world.forest.classes import class_counts, classify
from tcf_hil.world.forest.generate import QUALITY, Forest, generate_forest, ground_truth
from tcf_hil.world.forest.mesh import sides_for, stem_mesh, terrain_mesh
from tcf_hil.world.forest.stems import BREAST_HEIGHT_M, StemSet
from tcf_hil.world.terrain import Terrain

__all__ = [
    "BREAST_HEIGHT_M",
    "QUALITY",
    "Forest",
    "StemSet",
    "Terrain",
    "class_counts",
    "classify",
    "generate_forest",
    "ground_truth",
    "sides_for",
    "stem_mesh",
    "terrain_mesh",
]
