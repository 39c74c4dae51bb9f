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
    # ``paper``: the paper's clusters of the radius graph (the paper and tuned presets);
    # ``field``: stems found by their shape among branches, crowns and understory
    # (tcf_hil/sic/_field.py)
    algorithm: Literal["paper", "field"] = "paper"
    # mixed edge returns flagged on the range image (a range jump or no return within one
    # FWHM of the beam divergence in the row) and kept out of the stem fits
    edge_filter: bool = False
    edge_jump_m: float = 0.3  # a range step larger than this is another surface
    divergence_deg: float = 0.0  # FWHM; 0: the datasheet's for the metadata's prod_line
    edge_reach_fwhm: float = 1.0  # a return this many FWHM from a range jump is mixed
    edge_correction: float = 0.75  # share of the footprint's half width taken off a radius
    # that only edge returns give
    band_m: tuple[float, float] = (0.5, 4.0)  # where stems are looked for, above ground
    stem_voxel_m: float = 0.1  # the local PCA's voxels (3 x 3 x 3 of them a neighbourhood)
    max_normal_z: float = 0.35  # a stem-like surface's normal: within ~20 deg of horizontal
    min_z_share: float = 0.3  # ... and its points spread upwards, not only sideways
    max_variation: float = 0.15  # ... and it is thin (smallest eigenvalue / sum)
    min_votes: float = 30.0  # a stem candidate's votes (about a bark voxel each)
    min_stem_extent_m: float = 1.0  # a stem's circles span at least this much of the band
    fit_tolerance_m: float = 0.02  # RANSAC inlier distance from a slice's circle
    dbh_tolerance_m: float = 0.012  # ... and from the breast-height circle
    dbh_window_m: tuple[float, float] = (0.8, 1.8)  # the breast-height circle's points
    min_slices: int = 3  # a stem's candidate has votes in this many band layers (0.5 m)
    # a stem's circle is found in at least this many of the band's slices, which lie one
    # against the next (``slice_thickness_m`` apart: every return of the band in one;
    # 4 x 0.25 m: 0.75 m of stem); a spruce's crown leaves its bark clear of needles in
    # a few of them only
    min_band_slices: int = 4
    # bark is a thin shell: of the points from 5 tolerances inside a slice's circle to
    # ``shell_outside`` tolerances outside it, 60 % lie on it (needles may crowd the bark's
    # outside; nothing of a stem lies inside it). Within ``crowd_m`` of a stem found
    # already, in its crown, a candidate's circles must hold against 5 tolerances outside
    # too (a gap among the crown's needles is no stem)
    shell_outside: float = 2.0
    crowd_m: float = 1.0
    curve_step_m: float = 0.5  # the stem curve's slices above the band
    follow_radius_m: float = 0.15  # a slice up the stem is searched this far off its axis
    follow_misses: int = 5  # the stem is followed until this many slices in a row fail
    crook_m: float = 0.06  # a sideways step of the centre line this large is a crook (X)
    bow_shrink_se: float = 3.0  # the bow's curvature is shrunk by this many standard errors
    min_dbh_m: float = 0.03
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
    # The field-grade program (the default): mixed edge returns kept out of the diameter,
    # stems found by their local shape and followed up the tree (tcf_hil/sic/_field.py)
    "field": StemParams(ground_threshold_m=0.3, algorithm="field", edge_filter=True,
                        slice_thickness_m=0.25, max_dbh_m=1.0),
}


def stem_params(preset: str = "field", **overrides: Any) -> StemParams:
    """A preset (``field``, ``tuned`` or ``paper``) with keyword overrides."""
    if preset not in PRESETS:
        raise ValueError(f"unknown SIC preset {preset!r}; allowed: {', '.join(PRESETS)}")
    return replace(PRESETS[preset], **overrides)
