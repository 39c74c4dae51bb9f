"""The published JSON Schemas are valid draft-07 and agree with what we generate."""

from __future__ import annotations

import jsonschema
import pytest

from protocols.stems import CLASS_BY_QUALITY, QUALITY_BY_CLASS, SCHEMA_NAMES, load_schema
from tcf_hil.world.forest import Forest, ground_truth


@pytest.mark.parametrize("name", SCHEMA_NAMES)
def test_schema_is_valid_draft7(name: str) -> None:
    jsonschema.Draft7Validator.check_schema(load_schema(name))


def test_generated_ground_truth_validates_with_an_independent_validator(
        forest_ii: Forest) -> None:
    doc = ground_truth(forest_ii)
    jsonschema.Draft7Validator(load_schema("ground_truth")).validate(doc)
    # A ground truth is also a valid observed document (it can be scored against itself).
    jsonschema.Draft7Validator(load_schema("observed")).validate(doc)


def test_observed_needs_class_or_quality() -> None:
    v = jsonschema.Draft7Validator(load_schema("observed"))
    assert v.is_valid({"objects": [{"cp": [0, 0, 0], "quality": 2}]})
    assert v.is_valid({"objects": [{"cp": [0, 0, 0], "class": "X"}]})
    assert not v.is_valid({"objects": [{"cp": [0, 0, 0]}]})
    assert not v.is_valid({"objects": [{"cp": [0, 0], "class": "S"}]})


def test_quality_codes_are_the_papers() -> None:
    assert QUALITY_BY_CLASS == {"S": 1, "C": 2, "X": 3}
    assert {CLASS_BY_QUALITY[q] for q in (1, 2, 3)} == {"S", "C", "X"}
    with pytest.raises(ValueError, match="no schema"):
        load_schema("nope")
