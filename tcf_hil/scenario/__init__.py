"""Scenarios: TOML files validated into frozen objects, and the paper's Forest I–X presets."""

from protocols.stems import CLASSES
from tcf_hil.scenario._load import (
    EXTRA_PRESETS,
    PRESET_NAMES,
    list_presets,
    load_scenario,
    preset_name,
    scenario_from_dict,
    scenario_to_dict,
    scenario_to_toml,
)
from tcf_hil.scenario._model import (
    ClassMix,
    DbhConfig,
    DistributionConfig,
    FaultsConfig,
    HarvesterConfig,
    PlotConfig,
    PoseErrorConfig,
    SamplingConfig,
    Scenario,
    StemsConfig,
    SweepConfig,
    TerrainConfig,
    TrackConfig,
)

__all__ = [
    "CLASSES",
    "EXTRA_PRESETS",
    "PRESET_NAMES",
    "ClassMix",
    "DbhConfig",
    "DistributionConfig",
    "FaultsConfig",
    "HarvesterConfig",
    "PlotConfig",
    "PoseErrorConfig",
    "SamplingConfig",
    "Scenario",
    "StemsConfig",
    "SweepConfig",
    "TerrainConfig",
    "TrackConfig",
    "list_presets",
    "load_scenario",
    "preset_name",
    "scenario_from_dict",
    "scenario_to_dict",
    "scenario_to_toml",
]
