"""Scenarios: presets reproduce DESIGN's Forest I–X table; validation names key, value and
what is allowed; resolved TOML round-trips."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcf_hil.errors import ConfigError
from tcf_hil.scenario import (
    PRESET_NAMES,
    load_scenario,
    preset_name,
    scenario_from_dict,
    scenario_to_toml,
)

# DESIGN.md, "Forest presets (paper, section 2.2)".
TABLE = {
    "forest-i": ((10, 20), 10, "even", "rolling"),
    "forest-ii": ((20, 40), 24, "even", "flat"),
    "forest-iii": ((20, 40), 192, "even", "flat"),
    "forest-iv": ((20, 40), 192, "uneven", "rolling"),
    "forest-v": ((100, 100), 550, "even", "flat"),
    "forest-vi": ((100, 100), 550, "uneven", "flat"),
    "forest-vii": ((100, 100), 550, "clustered", "rolling"),
    "forest-viii": ((100, 100), 550, "uneven", "rolling"),
    "forest-ix": ((100, 100), 1100, "even", "rolling"),
    "forest-x": ((100, 100), 1100, "clustered", "rolling"),
}


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_presets_match_the_design_table(name: str) -> None:
    s = load_scenario(name)
    size, count, dist, terrain = TABLE[name]
    assert s.name == name
    assert s.plot.size_m == tuple(float(v) for v in size)
    assert s.stems.count == count
    assert s.distribution.kind == dist
    assert s.terrain.kind == terrain
    assert s.stems.height_m == (11.0, 27.0)


def test_hectare_presets_drive_the_papers_track() -> None:
    for name in ("forest-v", "forest-x"):
        t = load_scenario(name).track
        assert t.start_m == (0.0, -50.0, 2.0)
        assert t.end_m == (0.0, 50.0, 2.0)


def test_forest_i_has_nine_curved_and_one_straight() -> None:
    mix = load_scenario("forest-i").stems.class_mix
    assert (mix.S, mix.C, mix.X) == (1.0, 9.0, 0.0)


@pytest.mark.parametrize("alias", ["V", "v", "forest-v", "Forest_V", "forest v"])
def test_preset_aliases(alias: str) -> None:
    assert preset_name(alias) == "forest-v"


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_resolved_toml_round_trips(name: str) -> None:
    s = load_scenario(name)
    text = scenario_to_toml(s)
    assert scenario_from_dict(tomllib.loads(text)) == s
    assert "# terrain shape" in text  # documented keys


def test_extends_and_override(tmp_path: Path) -> None:
    p = tmp_path / "mine.toml"
    p.write_text('extends = "forest-vi"\nname = "mine"\n[stems]\ncount = 80\n'
                 'lean_deg = [0.0, 5.0]\n[terrain]\nkind = "rolling"\n')
    s = load_scenario(str(p), seed=99)
    assert (s.name, s.seed, s.stems.count, s.stems.lean_deg) == ("mine", 99, 80, (0.0, 5.0))
    assert s.distribution.kind == "uneven"  # from the preset
    assert s.terrain.kind == "rolling"


@pytest.mark.parametrize(("toml", "key", "allowed"), [
    ("[stems]\ncount = -1\n", "stems.count", ">= 0"),
    ("[stems]\ncount = 1.5\n", "stems.count", "an integer"),
    ("[terrain]\nkind = \"hilly\"\n", "terrain.kind", "'flat', 'rolling'"),
    ("[terrain]\nbumpiness = 2\n", "terrain.bumpiness", "keys here: kind"),
    ("[plot]\nsize_m = [10.0]\n", "plot.size_m", "an array of 2 numbers"),
    ("[plot]\nsize_m = [10.0, -3.0]\n", "plot.size_m[1]", "> 0.0"),
    ("[stems]\nheight_m = [20.0, 12.0]\n", "stems.height_m", "low <= high"),
    ("[stems.sweep_m]\nS = [0.0, 0.06]\n", "stems.sweep_m.S", "below stems.curve_threshold_m"),
    ("[stems]\ncurve_threshold_m = 0.3\n", "stems.curve_threshold_m", "other_threshold_m"),
    ("[stems.dbh]\nmean_m = 0.9\n", "stems.dbh.mean_m", "within"),
    ("seed = true\n", "seed", "an integer"),
    ("[distribution]\nkind = \"even\"\nedge_margin_m = 60.0\n", "distribution.edge_margin_m",
     "half the plot"),
    ("stems = 3\n", "stems", "a table"),
    ('extends = "forest-xi"\n', "extends", "a preset name"),
])
def test_errors_name_key_value_and_allowed(tmp_path: Path, toml: str, key: str,
                                           allowed: str) -> None:
    p = tmp_path / "bad.toml"
    p.write_text(toml)
    with pytest.raises(ConfigError) as ei:
        load_scenario(str(p))
    msg = str(ei.value)
    assert ei.value.key == key
    assert allowed in msg
    assert str(p) in msg
    assert "\n" not in msg


def test_unreadable_and_invalid_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="a TOML file or a preset"):
        load_scenario(str(tmp_path / "missing.toml"))
    p = tmp_path / "broken.toml"
    p.write_text("[stems\ncount = 3\n")
    with pytest.raises(ConfigError, match="valid TOML"):
        load_scenario(str(p))


def test_scenarios_are_frozen() -> None:
    s = load_scenario("forest-ii")
    with pytest.raises(AttributeError):
        s.stems.count = 3  # type: ignore[misc]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 5000), st.floats(0.5, 500.0), st.floats(0.0, 3.0),
       st.sampled_from(["even", "uneven", "clustered"]))
def test_valid_values_round_trip(count: int, size: float, amp: float, kind: str) -> None:
    s = scenario_from_dict({"stems": {"count": count}, "plot": {"size_m": [size, size * 2]},
                            "terrain": {"kind": "rolling", "amplitude_m": amp},
                            "distribution": {"kind": kind, "edge_margin_m": 0.1}})
    assert scenario_from_dict(tomllib.loads(scenario_to_toml(s))) == s


def test_a_file_named_like_a_preset_does_not_hide_it(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "forest-v").write_text("not toml at all")
    (tmp_path / "v").write_text('name = "notes"\n')
    assert load_scenario("forest-v").name == "forest-v"
    assert load_scenario("v").name == "forest-v"
    assert load_scenario("./v").name == "notes"  # a path means the file


def test_coordinate_keys_document_as_many_numbers_as_they_take() -> None:
    """A key documented as "(x, y; ...)" that takes three numbers sends users to an error:
    every key whose documentation lists its coordinates in brackets lists them all."""
    import dataclasses
    import re

    from tcf_hil.scenario import _model

    checked = 0
    for cls in vars(_model).values():
        if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
            continue
        for f in dataclasses.fields(cls):
            doc = f.metadata.get("doc", "")
            m = re.search(r"\((x\b[^;)]*)", doc)
            if m is None or not isinstance(f.default, tuple) or not f.default \
                    or isinstance(f.default[0], tuple):
                continue
            listed = [p for p in m.group(1).split(",") if p.strip()]
            assert len(listed) == len(f.default), (cls.__name__, f.name, doc)
            checked += 1
    assert checked >= 3  # start_m, end_m, mount_xy_m at least
