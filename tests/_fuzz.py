"""Helpers shared by the fuzz tests: settings, the one-line error check, and paths into a
JSON-like document to mutate."""

from __future__ import annotations

import copy
from typing import Any

from hypothesis import HealthCheck, event, settings
from hypothesis import strategies as st


def fuzz_settings(examples: int) -> Any:
    return settings(max_examples=examples, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def one_line(err: BaseException) -> None:
    """A documented error says what it says in one non-empty line."""
    event(f"error {type(err).__name__}")  # --hypothesis-show-statistics shows the mix
    msg = str(err)
    assert msg and "\n" not in msg, f"{type(err).__name__} message is not one line: {msg!r}"


def paths(doc: Any, items: int, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path into ``doc``, through the first ``items`` entries of each list."""
    out = [prefix] if prefix else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += paths(v, items, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:items]):
            out += paths(v, items, (*prefix, i))
    return out


def set_path(doc: Any, path: tuple[Any, ...], value: Any, delete: bool) -> None:
    """Replace (a copy of ``value``: st.just([]) gives one shared list) or delete at path."""
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = copy.deepcopy(value)


@st.composite
def mutations(draw: st.DrawFn, base: Any, paths: list[tuple[Any, ...]],
              values: st.SearchStrategy[Any], most: int = 3) -> Any:
    """A copy of ``base`` with 1..``most`` of its paths set to ``values`` (one in five
    deleted instead)."""
    doc = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, most))):
        path = draw(st.sampled_from(paths))
        try:
            set_path(doc, path, draw(values), draw(st.integers(0, 4)) == 0)
        except (KeyError, IndexError, TypeError):
            pass  # an earlier mutation replaced a parent
    return doc
