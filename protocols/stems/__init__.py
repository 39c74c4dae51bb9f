"""The stems JSON documents (paper's Algorithm 1): published JSON Schemas for ground truth and
for observed (SIC) output, and the class/quality code tables. Data only: validation with a
JSON Schema library happens in :mod:`tcf_hil.recording.stems_json`."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

__all__ = ["CLASSES", "CLASS_BY_QUALITY", "QUALITY_BY_CLASS", "SCHEMA_NAMES", "load_schema"]

CLASSES: tuple[str, ...] = ("S", "C", "X")
QUALITY_BY_CLASS: dict[str, int] = {"S": 1, "C": 2, "X": 3}
CLASS_BY_QUALITY: dict[int, str] = {v: k for k, v in QUALITY_BY_CLASS.items()}
SCHEMA_NAMES: tuple[str, ...] = ("ground_truth", "observed")


def load_schema(name: str) -> dict[str, Any]:
    """The JSON Schema (draft-07) named ``ground_truth`` or ``observed``."""
    if name not in SCHEMA_NAMES:
        raise ValueError(f"no schema {name!r}; known: {', '.join(SCHEMA_NAMES)}")
    text = (resources.files(__package__) / f"{name}.schema.json").read_text("utf-8")
    doc: dict[str, Any] = json.loads(text)
    return doc
