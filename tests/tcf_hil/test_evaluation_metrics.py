"""The evaluation (EE): hand-computed EM fixtures, weights and credits, defined zeros,
property tests, bad input and the `score` command."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcf_hil.cli import main
from tcf_hil.errors import InputError
from tcf_hil.evaluation import EvalConfig, evaluate, evaluation_matrix, weighted_score
from tcf_hil.recording.stems_json import stem_table


def doc(rows: list[tuple[Any, float, float, str]], **extra: list[float]) -> dict[str, Any]:
    objs = []
    for k, (i, x, y, c) in enumerate(rows):
        o: dict[str, Any] = {"id": i, "cp": [x, y, 0.0], "class": c}
        for key, vals in extra.items():
            o[key] = vals[k]
        objs.append(o)
    return {"objects": objs}


# Ground truth: five trees 10 m apart. Observed: four near a gt tree, one far away.
GT = doc([(1, 0, 0, "S"), (2, 10, 0, "S"), (3, 20, 0, "C"), (4, 30, 0, "X"), (5, 40, 0, "C")])
OBS = doc([(11, 0.2, 0, "S"),   # gt 1 S -> S  exact
           (12, 10, 0.3, "C"),  # gt 2 S -> C  wrong
           (13, 20.5, 0, "X"),  # gt 3 C -> X  almost (A)
           (14, 30, -0.1, "X"),  # gt 4 X -> X  exact
           (15, 99, 99, "S")])  # false positive; gt 5 (C) is missed
#          S  C  X  N      (rows gt, columns observed)
EM = [[1, 1, 0, 0],   # S: one exact, one seen as C
      [0, 0, 1, 1],   # C: one seen as X, one missed
      [0, 0, 1, 0],   # X: exact
      [1, 0, 0, 0]]   # N: the false positive was observed as S


def ev(gt: dict[str, Any] = GT, obs: dict[str, Any] = OBS, **cfg: Any) -> Any:
    return evaluate(stem_table(gt, "gt.json"), stem_table(obs, "obs.json"), EvalConfig(**cfg))


def test_hand_computed_em_and_default_score() -> None:
    e = ev()
    assert e.em.tolist() == EM
    m = e.metrics
    assert m["evaluation_score_percent"] == pytest.approx(100 * 2 / 6)  # diag / total
    assert m["total_matches"] == 4
    assert m["correct_matches"] == 2 and m["wrong_matches"] == 2
    assert m["quality_correct_percent"] == pytest.approx(50.0)
    assert m["quality_error_percent"] == pytest.approx(50.0)
    # quality codes: (1,1), (1,2), (2,3), (3,3) -> squared errors 0, 1, 1, 0
    assert m["rmse_quality"] == pytest.approx(math.sqrt(2 / 4))
    assert m["missed"] == 1 and m["false_positives"] == 1
    assert m["completeness"] == pytest.approx(4 / 5) and m["correctness"] == pytest.approx(4 / 5)
    assert m["f1"] == pytest.approx(4 / 5)
    assert m["accuracy_percent"] == pytest.approx(100 * 2 / 6)
    assert m["misclassified_percent"] == pytest.approx(100 * 2 / 6)
    assert m["missed_of_total_percent"] == pytest.approx(100 * 1 / 6)
    assert m["em"]["labels"] == ["S", "C", "X", "N"] and m["em"]["matrix"] == EM


def test_weights_and_credits_by_hand() -> None:
    # Weights by gt row S=2, C=1, X=1, N=1; credits E=2, A=1, N=0.
    # Numerator: S row 2*(2*1 [S,S] + 0*1 [S,C]) = 4; C row 1*(1*1 [C,X] A + 0 [C,N]) = 1;
    #            X row 1*(2*1) = 2; N row 0.  -> 7
    # Denominator: credit E (2) * (2*2 + 1*2 + 1*1 + 1*1) = 2 * 8 = 16
    e = ev(weights=(2, 1, 1, 1), credits=(2, 1, 0))
    assert e.metrics["evaluation_score_percent"] == pytest.approx(100 * 7 / 16)
    # The A case only counts when it has a credit.
    assert ev(credits=(1, 1, 0)).metrics["evaluation_score_percent"] == \
        pytest.approx(100 * 3 / 6)
    # A custom case table: treat S observed as C as "almost" too.
    from tcf_hil.evaluation import default_case_table

    table = default_case_table()
    table[("S", "C")] = "A"
    assert ev(credits=(2, 1, 0), case_table=table).metrics["evaluation_score_percent"] == \
        pytest.approx(100 * (2 + 1 + 1 + 2) / 12)


def test_distance_limit_and_metrics_of_properties() -> None:
    gt = doc([(1, 0, 0, "S"), (2, 5, 0, "C")], h=[20.0, 15.0], dbh=[0.3, 0.2])
    obs = doc([(1, 0.3, -0.4, "S"), (2, 5.3, -0.4, "C")], h=[19.0, 15.5])
    m = ev(gt, obs).metrics
    assert m["position_rmse_m"] == pytest.approx(0.5)
    assert m["position_bias_m"] == pytest.approx([0.3, -0.4])
    assert m["height_bias_m"] == pytest.approx(-0.25)
    assert m["height_rmse_m"] == pytest.approx(math.sqrt((1 + 0.25) / 2))
    assert m["height_pairs"] == 2 and m["dbh_pairs"] == 0 and m["dbh_rmse_m"] == 0.0
    assert ev(gt, obs, max_distance_m=0.45).metrics["total_matches"] == 0
    assert ev(gt, obs, max_distance_m=0.5).metrics["total_matches"] == 2


def test_greedy_and_optimal_differ_where_they_should() -> None:
    # gt a at 0, b at 1.2; observed p at 0.7, q at -0.45. Greedy takes the closest pair first
    # (q-a 0.45), then p-b (0.5): both matched. Make greedy lose one: p at 0.55 is closest
    # to a (0.55) and 0.65 from b; q at -0.6 is 0.6 from a only.
    gt = doc([(1, 0.0, 0, "S"), (2, 1.2, 0, "S")])
    obs = doc([(1, 0.55, 0, "S"), (2, -0.6, 0, "S")])
    g = ev(gt, obs, match="greedy")
    o = ev(gt, obs, match="optimal")
    assert g.pairs.tolist() == [[0, 0]]          # p took a; q has nobody left
    assert sorted(o.pairs.tolist()) == [[0, 1], [1, 0]]  # both matched
    assert o.metrics["total_matches"] == 2 and g.metrics["total_matches"] == 1


def test_greedy_ties_follow_ids_not_order() -> None:
    gt = doc([(2, 1, 0, "S"), (1, -1, 0, "C")])
    obs = doc([(7, 0, 0, "C")])  # equally far (1 m) from both
    for g in (gt, {"objects": gt["objects"][::-1]}):
        e = ev(g, obs, max_distance_m=1.5)
        gt_ids = [o["id"] for o in g["objects"]]
        assert gt_ids[e.pairs[0, 0]] == 1  # the smaller id wins the tie


@pytest.mark.parametrize(("gt", "obs"), [(doc([]), doc([])), (GT, doc([])), (doc([]), OBS)])
def test_empty_forests_give_defined_zeros(gt: dict[str, Any], obs: dict[str, Any]) -> None:
    for method in ("greedy", "optimal"):
        m = ev(gt, obs, match=method).metrics
        for k, v in m.items():
            if isinstance(v, float):
                assert math.isfinite(v), k
        assert m["total_matches"] == 0
        assert m["quality_correct_percent"] == 0.0 and m["rmse_quality"] == 0.0
        if not gt["objects"] and not obs["objects"]:
            assert m["evaluation_score_percent"] == 0.0
    assert weighted_score(np.zeros((4, 4), dtype=np.int64)) == 0.0


def test_bad_configs_are_refused() -> None:
    for kw in ({"match": "hungarian"}, {"max_distance_m": 0.0}, {"weights": (1, 1, 1)},
               {"credits": (0, 1, 0)}, {"credits": (1, -1, 0)}):
        with pytest.raises(ValueError):
            EvalConfig(**kw)  # type: ignore[arg-type]


@pytest.mark.parametrize(("bad", "field"), [
    ({"objects": [{"id": 1, "cp": [0, 0, 0], "class": "S"},
                  {"id": 1, "cp": [5, 0, 0], "class": "S"}]}, "objects[1].id"),
    ({"objects": [{"id": 1, "cp": [0, float("nan"), 0], "class": "S"}]}, "objects[0].cp[1]"),
    ({"objects": [{"id": 1, "cp": [0, 0, float("inf")], "class": "S"}]}, "objects[0].cp[2]"),
    ({"objects": [{"id": 1, "cp": [0, 0, 0], "class": "Q"}]}, "objects[0].class"),
    ({"objects": [{"id": 1, "cp": [0, 0, 0], "class": "S", "quality": 2}]},
     "objects[0].quality"),
    ({"objects": [{"id": 1, "class": "S"}]}, "objects[0]"),
    ({"objects": [{"id": 1, "cp": [0, 0, 0]}]}, "objects[0]"),
    ({"objects": [{"id": 1, "cp": [0, 0, 0], "class": "S", "h": float("nan")}]},
     "objects[0].h"),
    ({"total_objects_count": 3, "objects": []}, "total_objects_count"),
    ({"objects": "none"}, "objects"),
])
def test_bad_documents_name_file_and_field(bad: dict[str, Any], field: str) -> None:
    with pytest.raises(InputError) as ei:
        stem_table(bad, "obs.json")
    assert ei.value.path == "obs.json"
    assert ei.value.field == field
    assert str(ei.value).startswith(f"obs.json at {field}")


# ------------------------------------------------------------------ properties

coords = st.floats(-200, 200, allow_nan=False)
cls = st.sampled_from("SCX")


@st.composite
def scenes(draw: st.DrawFn, n_max: int = 25) -> tuple[dict[str, Any], dict[str, Any]]:
    ng = draw(st.integers(0, n_max))
    no = draw(st.integers(0, n_max))
    g = doc([(i + 1, draw(coords), draw(coords), draw(cls)) for i in range(ng)])
    o = doc([(i + 1, draw(coords), draw(coords), draw(cls)) for i in range(no)])
    return g, o


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(coords, coords, cls), min_size=1, max_size=30,
                unique_by=lambda t: (round(t[0], 6), round(t[1], 6))),
       st.sampled_from(["greedy", "optimal"]))
def test_a_perfect_observation_scores_100(trees: list[tuple[float, float, str]],
                                          method: str) -> None:
    d = doc([(i + 1, x, y, c) for i, (x, y, c) in enumerate(trees)])
    m = ev(d, d, match=method).metrics
    assert m["evaluation_score_percent"] == pytest.approx(100.0)
    assert m["total_matches"] == len(trees) and m["f1"] == pytest.approx(1.0)


@settings(max_examples=200, deadline=None)
@given(scenes(), st.tuples(*[st.floats(0, 5)] * 4), st.floats(0.1, 5), st.floats(0, 1),
       st.floats(0, 1), st.floats(0.2, 30), st.sampled_from(["greedy", "optimal"]))
def test_score_stays_within_0_and_100(scene: tuple[dict[str, Any], dict[str, Any]],
                                      w: tuple[float, ...], e: float, a: float, n: float,
                                      d: float, method: str) -> None:
    g, o = scene
    m = ev(g, o, weights=w, credits=(e, a * e, n * e), max_distance_m=d, match=method).metrics
    assert 0.0 <= m["evaluation_score_percent"] <= 100.0 + 1e-9
    em = np.asarray(m["em"]["matrix"])
    assert em[3, 3] == 0
    assert em[:3, :].sum() == len(g["objects"]) and em[:, :3].sum() == len(o["objects"])


@settings(max_examples=150, deadline=None)
@given(scenes(), st.randoms(use_true_random=False), st.sampled_from(["greedy", "optimal"]))
def test_object_order_changes_nothing(scene: tuple[dict[str, Any], dict[str, Any]],
                                      rnd: Any, method: str) -> None:
    g, o = scene
    g2 = {"objects": rnd.sample(g["objects"], len(g["objects"]))}
    o2 = {"objects": rnd.sample(o["objects"], len(o["objects"]))}
    a = ev(g, o, match=method, max_distance_m=40.0).metrics
    b = ev(g2, o2, match=method, max_distance_m=40.0).metrics
    if method == "optimal":  # equal-cost optima may pair differently; totals agree
        assert a["total_matches"] == b["total_matches"]
        return
    for k, v in a.items():
        if isinstance(v, float) or (isinstance(v, list) and all(isinstance(x, float)
                                                                 for x in v)):
            assert b[k] == pytest.approx(v, abs=1e-9), k  # summation order may differ
        else:
            assert b[k] == v, k


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 40), st.data())
def test_greedy_and_optimal_agree_when_stems_are_far_apart(n: int, data: st.DataObject) -> None:
    d = 1.0
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(8)), -1).reshape(-1, 2) * 3.0 * d
    gt_xy = grid[rng.choice(len(grid), size=min(n, len(grid)), replace=False)]
    seen = rng.random(len(gt_xy)) < 0.7
    ang = rng.uniform(0, 2 * math.pi, len(gt_xy))
    rr = rng.uniform(0, d / 2, len(gt_xy))
    obs_xy = (gt_xy + np.column_stack([rr * np.cos(ang), rr * np.sin(ang)]))[seen]
    obs_xy = np.vstack([obs_xy, [[500.0, 500.0]]])  # a false positive far from everything
    g = doc([(i + 1, *p, "SCX"[i % 3]) for i, p in enumerate(gt_xy.tolist())])
    o = doc([(i + 1, *p, "SCX"[(i * 2) % 3]) for i, p in enumerate(obs_xy.tolist())])
    a, b = ev(g, o, match="greedy"), ev(g, o, match="optimal")
    assert a.pairs.tolist() == b.pairs.tolist()
    assert a.metrics["evaluation_score_percent"] == b.metrics["evaluation_score_percent"]
    assert a.metrics["total_matches"] == int(seen.sum())


def test_evaluation_matrix_counts() -> None:
    em = evaluation_matrix(["S", "C"], ["C", "C", "X"], np.array([[0, 1]]))
    assert em.tolist() == [[0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 1, 1, 0]]


# ------------------------------------------------------------------------ CLI

KEYS = ("evaluation_score_percent", "total_matches", "quality_correct_percent",
        "quality_error_percent", "rmse_quality", "correct_matches", "wrong_matches", "missed",
        "false_positives", "completeness", "correctness", "f1", "position_rmse_m",
        "dbh_rmse_m", "height_rmse_m", "em")


def test_score_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    g, o = tmp_path / "gt.json", tmp_path / "obs.json"
    g.write_text(json.dumps(GT))
    o.write_text(json.dumps(OBS))
    out, plots = tmp_path / "score.json", tmp_path / "plots"
    code = main(["score", str(g), str(o), "--weights", "2,1,1,1", "--credits", "2,1,0",
                 "--json", str(out), "--plots", str(plots)])
    text = capsys.readouterr().out
    assert code == 0
    m = json.loads(out.read_text())
    assert set(KEYS) <= set(m)
    assert m["em"]["labels"] == ["S", "C", "X", "N"] and m["em"]["matrix"] == EM
    assert m["evaluation_score_percent"] == pytest.approx(100 * 7 / 16)
    assert "43.8 %" in text
    for name in ("em_heatmap.png", "matched_positions.png"):
        assert (plots / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("content", ["{not json", '{"objects": [{"cp": [0, 0, 0]}]}',
                                     '{"objects": [{"cp": [0, 0, NaN], "class": "S"}]}',
                                     '{"objects": [{"cp": [0, 0, 1e999], "class": "S"}]}'])
def test_score_bad_file_is_one_line_and_writes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str) -> None:
    g, o, out = tmp_path / "gt.json", tmp_path / "obs.json", tmp_path / "s.json"
    g.write_text(json.dumps(GT))
    o.write_text(content)
    code = main(["score", str(g), str(o), "--json", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and err[0].startswith("Error:") and "obs.json" in err[0]
    assert not out.exists()


def test_score_usage_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    g = tmp_path / "gt.json"
    g.write_text(json.dumps(GT))
    assert main(["score", str(g), str(g), "--weights", "1,2"]) == 2
    assert main(["score", str(g), str(g), "--credits", "0,0,0"]) == 2
    assert "credit" in capsys.readouterr().err.lower()


def test_matching_is_in_the_xy_plane_and_precise_at_utm() -> None:
    e0, n0 = 500_000.0, 6_900_000.0
    g = doc([(1, e0, n0, "S"), (2, e0 + 3, n0, "C")])
    o = doc([(1, e0 + 0.999, n0, "S"), (2, e0 + 3, n0 + 1.001, "C")])
    for d in (g, o):
        d["objects"][0]["cp"][2] = 50.0  # height differences do not count
    m = ev(g, o).metrics
    assert m["total_matches"] == 1 and m["position_rmse_m"] == pytest.approx(0.999)


# ------------------------------------------------------- review regressions


@pytest.mark.parametrize("method", ["greedy", "optimal"])
def test_objects_without_ids_do_not_make_order_matter(method: str) -> None:
    gt = {"objects": [{"id": 1, "cp": [500000.0, 6900000.0, 0.0], "class": "S"}]}
    a = {"cp": [500000.5, 6900000.0, 0.0], "class": "S"}
    b = {"cp": [499999.5, 6900000.0, 0.0], "class": "C"}
    one = ev(gt, {"objects": [a, b]}, match=method).em.tolist()
    two = ev(gt, {"objects": [b, a]}, match=method).em.tolist()
    assert one == two


def test_absurd_numbers_and_nesting_are_input_errors(tmp_path: Path) -> None:
    from tcf_hil.recording.stems_json import load_stems

    for bad in ('{"objects": [{"cp": [' + "9" * 401 + ', 0, 0], "class": "S"}]}',
                '{"objects": [{"cp": [0, 0, 0], "class": "S", "h": 1e200}]}',
                '{"objects": [{"cp": [1e308, 0, 0], "class": "S"}]}',
                "[" * 100_000 + "]" * 100_000):
        p = tmp_path / "x.json"
        p.write_text(bad)
        with pytest.raises(InputError, match=r"x\.json"):
            load_stems(p)


def test_credits_above_e_are_refused() -> None:
    with pytest.raises(ValueError, match="at least the A and N"):
        EvalConfig(credits=(1.0, 2.0, 0.0))
