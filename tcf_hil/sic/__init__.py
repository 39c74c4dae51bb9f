"""The reference stem identification and classification (SIC) core: the paper's algorithm
as pure functions on point arrays. The live onboard program built on it talks to the rest of
tcf-hil only through the wire."""

from tcf_hil.sic._circle import Circle, fit_circle, fit_circle_algebraic
from tcf_hil.sic._stems import (
    PRESETS,
    StemParams,
    cluster_points,
    identify_stems,
    remove_ground,
    stem_params,
)

__all__ = [
    "PRESETS",
    "Circle",
    "StemParams",
    "cluster_points",
    "fit_circle",
    "fit_circle_algebraic",
    "identify_stems",
    "remove_ground",
    "stem_params",
]
