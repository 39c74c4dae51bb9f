"""Synthetic forest creation (SFC): terrain, stem placement and geometry, meshes, ground truth."""

from tcf_hil.forest.generate import (
    QUALITY,
    Forest,
    class_counts,
    classify,
    generate_forest,
    ground_truth,
)
from tcf_hil.forest.mesh import sides_for, stem_mesh, terrain_mesh
from tcf_hil.forest.stems import BREAST_HEIGHT_M, StemSet
from tcf_hil.forest.terrain import Terrain

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
