"""Shared fixtures: small generated forests (module-scoped; generation is deterministic)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator

import pytest

from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import Forest, generate_forest

# The render store of this test session: its own, empty folder (never the user's cache, so
# nothing an earlier run or install stored decides a test; subprocesses inherit it).
os.environ["TCF_HIL_CACHE"] = tempfile.mkdtemp(prefix="tcf-hil-cache-")


@pytest.fixture(scope="session", autouse=True)
def _render_cache() -> Iterator[None]:
    yield
    shutil.rmtree(os.environ["TCF_HIL_CACHE"], ignore_errors=True)


@pytest.fixture(scope="session")
def forest_ii() -> Forest:
    """Forest II: 24 stems, even, flat."""
    return generate_forest(load_scenario("forest-ii"))


@pytest.fixture(scope="session")
def forest_iv() -> Forest:
    """Forest IV: 192 stems, uneven, rolling."""
    return generate_forest(load_scenario("forest-iv"))
