"""The reference stem identification and classification (SIC) core: the paper's algorithm
as pure functions on point arrays. The live onboard program built on it talks to the rest of
tcf-hil only through the wire.

The parameters (:data:`PRESETS`) import at once; the algorithm (scipy's KD-tree and sparse
graphs) on first use, so that the command line, which only needs the preset names, starts
quickly."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from tcf_hil.sic._params import PRESETS, StemParams, stem_params

if TYPE_CHECKING:
    from tcf_hil.sic._circle import Circle, fit_circle, fit_circle_algebraic, use_compiled_fits
    from tcf_hil.sic._cli import sic_command
    from tcf_hil.sic._map import StemMap
    from tcf_hil.sic._online import CanPose, LidarStats, OnboardSic, PoseTrack, SicConfig
    from tcf_hil.sic._stems import cluster_points, identify_stems, remove_ground

_LAZY = {"Circle": "_circle", "fit_circle": "_circle", "fit_circle_algebraic": "_circle",
         "use_compiled_fits": "_circle",
         "cluster_points": "_stems", "identify_stems": "_stems", "remove_ground": "_stems",
         "StemMap": "_map", "CanPose": "_online", "LidarStats": "_online",
         "OnboardSic": "_online", "PoseTrack": "_online", "SicConfig": "_online",
         "sic_command": "_cli"}

__all__ = [
    "PRESETS",
    "CanPose",
    "Circle",
    "LidarStats",
    "OnboardSic",
    "PoseTrack",
    "SicConfig",
    "StemMap",
    "StemParams",
    "cluster_points",
    "fit_circle",
    "fit_circle_algebraic",
    "identify_stems",
    "remove_ground",
    "sic_command",
    "stem_params",
    "use_compiled_fits",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f"tcf_hil.sic.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'tcf_hil.sic' has no attribute {name!r}")
