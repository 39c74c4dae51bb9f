"""The reference stem algorithm's parameters and presets (no heavy imports: the command
line builds its ``--preset`` choices from :data:`PRESETS`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal


@dataclass(frozen=True)
class StemParams:
    """Parameters of the stem algorithm (all lengths in metres)."""

    ground_cell_m: float = 1.0
    ground_threshold_m: float = 0.20
    # the onboard map's ground grid follows hillsides (GroundGrid's ``slope``); the one-shot
    # ``identify_stems`` on a whole cloud keeps the paper's grid filter (``remove_ground``)
    ground_slope: bool = True
    cluster_radius_m: float = 0.3
    min_height_m: float = 2.5
    min_points: int = 10
    neighbors: Literal["scipy", "sklearn"] = "scipy"
    centre: Literal["mean", "breast_height"] = "breast_height"
    height: Literal["extent", "above_ground"] = "above_ground"
    slice_thickness_m: float = 0.3
    slice_step_m: float = 1.0
    min_slice_points: int = 6
    merge_fragments: bool = True
    merge_radius_m: float = 0.6
    merge_gap_m: float = 3.0
    max_dbh_m: float = 1.5
    curve_threshold_m: float = 0.05
    other_threshold_m: float = 0.25
    cluster_voxel_m: float = 0.0  # > 0: cluster one point per voxel of this size (faster)
    scene_centre: tuple[float, float] = (0.0, 0.0)
    timestamp: str = "20250213_035113"

    def __post_init__(self) -> None:
        for name in ("ground_cell_m", "cluster_radius_m", "slice_thickness_m", "slice_step_m",
                     "max_dbh_m", "curve_threshold_m", "other_threshold_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v!r}; allowed: a number > 0")
        if self.curve_threshold_m >= self.other_threshold_m:
            raise ValueError("curve_threshold_m must be below other_threshold_m")


PRESETS: dict[str, StemParams] = {
    # The paper's algorithm as published: mean x, y centre, height = max z - min z,
    # scikit-learn's KD-tree for the radius search.
    "paper": StemParams(neighbors="sklearn", centre="mean", height="extent",
                        merge_fragments=False, ground_slope=False),
    # Default: centre from the breast-height circle fit, height above the local ground,
    # fragments (a sparse stem top that broke off) merged back onto the stem below them,
    # a 0.5 m ground band (on slopes a 1 m cell spans more than 0.2 m, and the ground points
    # left over bridge neighbouring stems into one cluster), scipy's KD-tree (same graph,
    # faster), and a ground grid that follows hillsides (GroundGrid's ``slope``).
    "tuned": StemParams(ground_threshold_m=0.5),
}


def stem_params(preset: str = "tuned", **overrides: Any) -> StemParams:
    """A preset (``paper`` or ``tuned``) with keyword overrides."""
    if preset not in PRESETS:
        raise ValueError(f"unknown SIC preset {preset!r}; allowed: {', '.join(PRESETS)}")
    return replace(PRESETS[preset], **overrides)
