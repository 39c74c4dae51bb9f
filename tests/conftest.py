"""Shared fixtures: small generated forests (module-scoped; generation is deterministic)."""

from __future__ import annotations

import pytest

from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import Forest, generate_forest


@pytest.fixture(scope="session")
def forest_ii() -> Forest:
    """Forest II: 24 stems, even, flat."""
    return generate_forest(load_scenario("forest-ii"))


@pytest.fixture(scope="session")
def forest_iv() -> Forest:
    """Forest IV: 192 stems, uneven, rolling."""
    return generate_forest(load_scenario("forest-iv"))
