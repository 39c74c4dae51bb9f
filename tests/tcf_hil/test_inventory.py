"""Field inventory CSVs as ground truth (issue 22, item 3): read as written, scored with the
paper's EE, metrics without inputs absent (never zero), bad files one line naming the file,
the line and the column; and `tcf-hil score` on one."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcf_hil.errors import InputError
from tcf_hil.evaluation.scoring import score_forest
from tcf_hil.recording.inventory import read_inventory
from tcf_hil.recording.stems_json import stem_table

UTM = (425_000.0, 6_950_000.0)  # a projected frame's size of coordinates (UTM zone 35N)
trees = st.lists(st.tuples(st.floats(-500, 500), st.floats(-500, 500),
                           st.one_of(st.none(), st.floats(0.04, 0.8)),
                           st.one_of(st.none(), st.sampled_from("SCX"))),
                 min_size=1, max_size=30)


def _write(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


@settings(max_examples=60, deadline=None)
@given(trees, st.booleans())
def test_an_inventory_scored_against_itself_is_perfect_where_it_has_inputs(
        tmp_path_factory: pytest.TempPathFactory, rows: list, with_class: bool) -> None:
    path = tmp_path_factory.mktemp("inv") / "inventory.csv"
    _write(path, ["id", "x", "y", "dbh_m"] + (["class"] if with_class else []),
           [[f"T{i}", UTM[0] + x, UTM[1] + y, "" if d is None else d]
            + ([c or "S"] if with_class else []) for i, (x, y, d, c) in enumerate(rows)])
    truth = read_inventory(path)
    assert [o["id"] for o in truth["objects"]] == [f"T{i}" for i in range(len(rows))]
    for o, (x, y, d, _c) in zip(truth["objects"], rows, strict=True):
        assert o["cp"][:2] == [pytest.approx(UTM[0] + x), pytest.approx(UTM[1] + y)]
        assert o.get("dbh") == (None if d is None else pytest.approx(d))
    obs = stem_table(truth, str(path), "observed")
    sc = score_forest(truth, obs)
    a = sc.all.metrics
    assert a["total_matches"] <= len(rows)  # (trees closer than 1 m may pair otherwise)
    assert a["height_rmse_m"] is None and a["maxcurve_rmse_m"] is None
    assert (a["evaluation_score_percent"] is None) != with_class
    has_dbh = any(d is not None for _x, _y, d, _c in rows)
    assert (a["dbh_rmse_m"] is None) == (not has_dbh or a["dbh_pairs"] == 0)
    assert sc.seen.metrics["n_ground_truth"] == a["n_ground_truth"] == len(rows)
    if len({(round(x), round(y)) for x, y, _d, _c in rows}) == len(rows) and all(
            math.dist(p[:2], q[:2]) > 2.0 for i, p in enumerate(rows) for q in rows[:i]):
        assert a["f1"] == 1.0
        assert a["dbh_rmse_m"] in (None, 0.0)


@pytest.mark.parametrize(("header", "row", "needle"), [
    (["x", "y"], [1, 2], "line 1: the header has no 'id' column"),
    (["id", "x", "y"], ["a", "east", 2], "line 2, column x: 'east' is not a finite number"),
    (["id", "x", "y"], ["a", "", 2], "line 2, column x: empty; required"),
    (["id", "x", "y", "class"], ["a", 1, 2, "Q"], "line 2, column class: 'Q'; expected S"),
    (["id", "x", "y", "dbh_m"], ["a", 1, 2, -0.2], "line 2, column dbh_m: '-0.2' is negative"),
    (["id", "x", "x", "y"], ["a", 1, 1, 2], "line 1: column 'x' appears twice"),
])
def test_bad_inventories_name_file_line_and_column(tmp_path: Path, header: list[str],
                                                   row: list[object], needle: str) -> None:
    path = _write(tmp_path / "inv.csv", header, [row])
    with pytest.raises(InputError) as e:
        read_inventory(path)
    assert str(e.value).startswith(str(path)) and needle in str(e.value), str(e.value)
    assert "\n" not in str(e.value)


def test_duplicate_ids_name_both_lines(tmp_path: Path) -> None:
    path = _write(tmp_path / "inv.csv", ["id", "x", "y"], [["7", 1, 2], ["8", 3, 4],
                                                           ["7", 5, 6]])
    with pytest.raises(InputError, match=r"line 4, column id: duplicate id '7' \(also on line "
                                         r"2\)"):
        read_inventory(path)


def test_score_command_takes_an_inventory(tmp_path: Path) -> None:
    inv = _write(tmp_path / "inventory.csv", ["id", "x", "y", "z", "height_m", "notes"],
                 [[1, UTM[0], UTM[1], 101.5, 21.0, "leaning"], [2, UTM[0] + 6, UTM[1], "", "",
                                                                 ""]])
    obs = tmp_path / "forest.json"
    obs.write_text(json.dumps({"objects": [
        {"cp": [UTM[0] + 0.1, UTM[1], 100.0], "class": "S", "h": 20.0, "dbh": 0.3}]}))
    out = tmp_path / "score.json"
    p = subprocess.run([sys.executable, "-m", "tcf_hil.cli", "score", str(inv), str(obs),
                        "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    m = json.loads(out.read_text())
    assert (m["total_matches"], m["missed"], m["false_positives"]) == (1, 1, 0)
    assert m["height_rmse_m"] == pytest.approx(1.0) and m["dbh_rmse_m"] is None
    assert m["evaluation_score_percent"] is None
    assert "absent" in p.stdout


def test_a_class_column_with_gaps_gives_no_class_metrics(tmp_path: Path) -> None:
    path = _write(tmp_path / "inv.csv", ["id", "x", "y", "class"],
                  [[1, 0, 0, "S"], [2, 5, 0, ""]])
    truth = read_inventory(path)
    sc = score_forest(truth, stem_table({"objects": [{"cp": [0, 0, 0], "class": "C"}]},
                                        "obs", "observed"))
    m = sc.all.metrics
    assert m["evaluation_score_percent"] is None and m["em"] is None
    assert (m["total_matches"], m["missed"]) == (1, 1) and sc.seen is sc.all
