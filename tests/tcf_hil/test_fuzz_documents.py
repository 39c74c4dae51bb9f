"""Fuzzing the documents tcf-hil reads from outside: the SIC's stems JSON (as the recorder
receives it), ground truth, scenario TOML and the emulated sensor's config POST. Any input
gives a value or the documented error (InputError, ConfigError, an HTTP error status), whose
message is one line naming the field, and nothing else (issue 7, item 2)."""

from __future__ import annotations

import atexit
import json
import math
import shutil
import tempfile
import tomllib
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from _fuzz import fuzz_settings, mutations, one_line, paths
from hypothesis import event, example, given
from hypothesis import strategies as st

from emulators.lidar._http import SensorApi, _HttpError
from protocols.ouster import SensorMetadata, os0_64_metadata
from protocols.stems import QUALITY_BY_CLASS
from tcf_hil._io import loads_json
from tcf_hil.errors import ConfigError, InputError
from tcf_hil.recording.stems_json import stem_table
from tcf_hil.run.recorder import Inbox
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.scenario._load import scenario_to_toml

FUZZ = fuzz_settings(200)


#: Wrong types, non-finite and huge numbers, empty containers, near-miss strings.
BAD_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(),
    st.sampled_from([0, -1, 1.5, -0.0, 10**30, -(10**30), 2**63, 2**64, 10**400, 1e308,
                     -1e308, 5e-324, math.nan, math.inf, -math.inf]),
    st.text(max_size=10), st.sampled_from(["", "S", "C", "X", "s", "1", "NaN", "forest-v"]),
    st.just([]), st.just({}), st.lists(st.floats(allow_nan=False), max_size=4),
    st.lists(st.integers(-5, 5), min_size=3, max_size=3), st.just([[1, 2, 3]]),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))




# ----------------------------------------------------------------------------- stems JSON

OBSERVED = {"timestamp": "20250213_035113", "total_objects_count": 3, "objects": [
    {"id": 1, "cp": [1.0, 2.0, 0.5], "class": "S", "quality": 1, "h": 20.0, "dbh": 0.3,
     "maxcurve": 0.01, "name": "a"},
    {"id": "b", "cp": [-3.0, 4.0, 0.0], "quality": 2, "d": 5.0},
    {"cp": [5e5, 6e6, 120.0], "class": "X"}]}
OBSERVED_PATHS = paths(OBSERVED, 2)


@cache
def _ground_truth() -> dict[str, Any]:
    from tcf_hil.world.forest import generate_forest
    from tcf_hil.world.forest.generate import ground_truth

    doc = ground_truth(generate_forest(load_scenario("forest-ii")))
    doc["objects"] = doc["objects"][:2]
    doc["total_objects_count"] = 2
    for o in doc["objects"]:  # keep the mutation targets few
        o["centerline"], o["radii"] = o["centerline"][:3], o["radii"][:3]
    return doc


def _check_table(doc: Any, table: Any) -> None:
    event("value")
    objs = doc["objects"]
    assert len(table) == len(objs) == table.xyz.shape[0]
    assert np.isfinite(table.xyz).all() and (np.abs(table.xyz) <= 1e9).all()
    for i, o in enumerate(objs):
        c = str(table.classes[i])
        assert c in QUALITY_BY_CLASS and table.quality[i] == QUALITY_BY_CLASS[c]
        if "class" in o:
            assert o["class"] == c
        if "quality" in o:
            assert o["quality"] == QUALITY_BY_CLASS[c]
        for k in ("h", "dbh", "maxcurve"):
            v = getattr(table, k)[i]
            assert (math.isnan(v) and k not in o) or v == float(o[k])
    ids = [i for i in table.ids if i is not None]
    assert len({(type(i).__name__, i) for i in ids}) == len(ids)


def _check_stems(doc: Any, kind: str) -> None:
    try:
        table = stem_table(doc, "sic.json", kind)  # type: ignore[arg-type]
    except InputError as err:
        one_line(err)
        assert err.path == "sic.json"
        return
    _check_table(doc, table)


@FUZZ
@given(mutations(OBSERVED, OBSERVED_PATHS, BAD_VALUES))
@example({"objects": [{"cp": [10**5000, 0, 0], "class": "S"}]})  # was ValueError in the message
@example({"objects": [{"cp": [1, 2, 3], "class": "S", "h": math.inf}]})
@example({"objects": [{"cp": [1, 2, 3], "quality": 1.0}]})
@example({"objects": [{"cp": [1, 2, 3], "class": "S", "id": 1}, {"cp": [1, 2, 3],
                                                                  "class": "C", "id": 1.0}]})
def test_mutated_observed_documents_give_a_table_or_an_input_error(doc: Any) -> None:
    _check_stems(doc, "observed")


@fuzz_settings(100)
@given(st.data())
def test_mutated_ground_truth_gives_a_table_or_an_input_error(data: st.DataObject) -> None:
    gt = _ground_truth()
    doc = data.draw(mutations(gt, paths(gt, 2), BAD_VALUES))
    _check_stems(doc, "ground_truth")


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(
        st.sampled_from(["objects", "cp", "class", "quality", "id", "h", "x"]) | st.text(
            max_size=4), kids, max_size=4), max_leaves=25)


@FUZZ
@given(st.one_of(st.text(max_size=200), JSON_VALUES.map(json.dumps),
                 mutations(OBSERVED, OBSERVED_PATHS, BAD_VALUES).map(json.dumps),
                 st.tuples(st.just(json.dumps(OBSERVED)), st.integers(0, 400),
                           st.text(max_size=6)).map(lambda t: t[0][:t[1]] + t[2]
                                                    + t[0][t[1] + len(t[2]):])),
       st.sampled_from(["observed", "ground_truth"]))
@example("[" * 100_000, "observed")
@example('{"objects": [{"cp": [1e999, 0, 0], "class": "S"}]}', "observed")
@example('{"objects": [{"cp": [' + "9" * 5000 + ', 0, 0], "class": "S"}]}', "observed")
def test_any_text_is_a_stems_table_or_an_input_error(text: str, kind: str) -> None:
    try:
        doc = loads_json(text, "sic.json")
    except InputError as err:
        one_line(err)
        return
    _check_stems(doc, kind)


def _tmpdir(prefix: str) -> Path:
    """A temporary folder removed when the test process ends."""
    d = tempfile.mkdtemp(prefix=prefix)
    atexit.register(shutil.rmtree, d, True)
    return Path(d)


@cache
def _inbox() -> Inbox:
    return Inbox(_tmpdir("tcf-hil-fuzz-") / "sic")


@FUZZ
@given(st.one_of(st.binary(max_size=200),
                 mutations(OBSERVED, OBSERVED_PATHS, BAD_VALUES).map(
                     lambda d: json.dumps(d).encode()),
                 st.just(json.dumps(OBSERVED).encode()).flatmap(
                     lambda b: st.tuples(st.integers(0, len(b)), st.binary(max_size=6)).map(
                         lambda t: b[:t[0]] + t[1] + b[t[0]:]))))
@example(b"\xff\xfe{")
@example(json.dumps(OBSERVED).encode())
def test_any_publication_is_recorded_as_valid_or_with_a_one_line_error(raw: bytes) -> None:
    inbox = _inbox()
    pub = inbox.record(raw, "http")
    assert pub.valid == (pub.error is None)
    if pub.valid:
        table = inbox.table_of(pub)
        assert len(table) == pub.objects
        _check_table(json.loads(raw.decode("utf-8", errors="replace")), table)
    else:
        assert pub.error and "\n" not in pub.error
    assert (inbox.dir / pub.file).read_bytes() == raw


# ----------------------------------------------------------------------------- scenarios

def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else "inf" if v == math.inf else "-inf" \
            if v == -math.inf else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    if v is None:
        return '"None"'  # TOML has no null
    raise TypeError(v)


def _toml(doc: dict[str, Any]) -> str:
    """Any nested dict as TOML: every value inline (TOML writes tables as inline tables)."""
    return "\n".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in doc.items()) + "\n"


SCENARIO = scenario_to_dict(load_scenario("forest-ii"))
SCENARIO_PATHS = paths(SCENARIO, 2)
_TMP = _tmpdir("tcf-hil-fuzz-scenarios-")


def _load_text(text: str) -> Any:
    path = _TMP / "scenario.toml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    return load_scenario(str(path))


def _check_scenario(text: str) -> None:
    try:
        scn = _load_text(text)
    except ConfigError as err:
        one_line(err)
        return
    event("value")
    assert scenario_from_dict(scenario_to_dict(scn)) == scn
    assert _load_text(scenario_to_toml(scn)) == scn


@FUZZ
@given(mutations(SCENARIO, SCENARIO_PATHS, BAD_VALUES).map(_toml))
@example('[plot]\nsize_m = [1' + "0" * 400 + ', 100.0]\n')  # was OverflowError
@example('[terrain]\nelevation_m = 1' + "0" * 5000 + '\n')  # was ValueError from tomllib
@example("a = " + "[" * 10_000)  # was RecursionError from tomllib
@example('extends = "forest-v"\n[stems]\ncount = -1\n')
@example('extends = 5\n')
@example('[track]\nwaypoints_m = [[1, 2], [3]]\n')
@example('description = "a\\u007fb"\n')  # was written back as a raw DEL, which TOML refuses
def test_mutated_scenarios_load_or_raise_config_error(text: str) -> None:
    _check_scenario(text)


@FUZZ
@given(st.one_of(st.text(max_size=200),
                 st.tuples(st.just(scenario_to_toml(load_scenario("forest-ii"))),
                           st.integers(0, 3000), st.text(max_size=8)).map(
                     lambda t: t[0][:t[1]] + t[2] + t[0][t[1] + len(t[2]):])))
def test_any_text_is_a_scenario_or_a_config_error(text: str) -> None:
    _check_scenario(text)


def test_config_errors_print_huge_values_in_one_short_line() -> None:
    err = ConfigError("stems.count", 10**5000, "an integer")
    assert "too large to print" in str(err)
    err = ConfigError("plot.size_m", list(range(10_000)), "an array of 2 numbers")
    assert "\n" not in str(err) and len(str(err)) < 400


# ----------------------------------------------------------------------------- sensor config

_API = SensorApi(os0_64_metadata("1024x10"), port=0)  # routes only: never started
atexit.register(_API.close)
CONFIG = _API.meta.to_json()["config_params"]


@FUZZ
@given(st.dictionaries(st.sampled_from(sorted(CONFIG)) | st.text(max_size=6), BAD_VALUES,
                       max_size=4) | JSON_VALUES, st.booleans())
@example({"lidar_mode": 5}, True)  # was AttributeError: a 500 and a dropped connection
@example({"udp_profile_lidar": ["LEGACY"]}, True)
@example({"udp_port_lidar": "7502"}, True)  # was accepted as a string port
@example({"columns_per_packet": 16.0}, True)
def test_any_config_post_is_applied_or_refused_with_an_http_error(change: Any,
                                                                  reinit: bool) -> None:
    meta = os0_64_metadata("1024x10")
    _API.set_metadata(meta)
    query = {"reinit": ["true"]} if reinit else {}
    try:
        status, body = _API.route("POST", "/api/v1/sensor/config", query, lambda: change,
                                  "10.0.0.9")
    except _HttpError as err:
        event("refused")
        assert err.status == 400 and err.message and "\n" not in err.message
        return
    event("applied")
    assert status == 200 and body == {}
    if reinit and isinstance(change, dict):
        new = _API.meta
        assert new.init_id != meta.init_id
        assert SensorMetadata.loads(new.dumps()) == new
        for key, v in change.items():
            if key in ("lidar_mode", "udp_profile_lidar", "udp_port_lidar", "udp_port_imu",
                       "columns_per_packet"):
                assert new.to_json()["config_params"][key] == v


def test_toml_helper_writes_what_tomllib_reads() -> None:
    assert tomllib.loads(_toml(SCENARIO)) == SCENARIO
