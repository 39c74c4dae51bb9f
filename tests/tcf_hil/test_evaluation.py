"""The evaluation (EE) against its definition: hand-computed evaluation matrices and scores,
greedy and optimal matching, defined zeros, property tests, input errors and `tcf-hil score`."""

from __future__ import annotations

import itertools
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
from tcf_hil.evaluation import LABELS, EvalConfig, Evaluation, evaluate, match
from tcf_hil.recording.stems_json import load_stems, stem_table

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
QUALITY = {"S": 1, "C": 2, "X": 3}


def obj(oid: Any, x: float, y: float, cls: str, **extra: Any) -> dict[str, Any]:
    return {"id": oid, "cp": [x, y, 0.0], "class": cls, **extra}


def evaluate_docs(gt: dict[str, Any], obs: dict[str, Any], **cfg: Any) -> Evaluation:
    return evaluate(stem_table(gt, "gt.json"), stem_table(obs, "obs.json"), EvalConfig(**cfg))


def id_pairs(ev: Evaluation, gt: dict[str, Any], obs: dict[str, Any]) -> set[tuple[Any, Any]]:
    g, o = gt["objects"], obs["objects"]
    return {(g[a]["id"], o[b]["id"]) for a, b in ev.pairs.tolist()}


def assert_same(a: Any, b: Any, path: str = "metrics") -> None:
    """Equal structures; floats equal to rounding."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for k in a:
            assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list | tuple):
        assert isinstance(b, list | tuple) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12), path
    else:
        assert a == b, path


def numbers(value: Any) -> list[float]:
    """Every number inside a metrics value (nested dicts and lists included)."""
    if isinstance(value, bool):
        return []
    if isinstance(value, int | float):
        return [float(value)]
    if isinstance(value, dict):
        return [n for v in value.values() for n in numbers(v)]
    if isinstance(value, list | tuple):
        return [n for v in value for n in numbers(v)]
    return []


# ------------------------------------------------------------------ hand-computed scene
#
# Ground truth, 5 m apart on the x axis; observed near five of them, two false positives.
#
#   gt  class  observed       obs class   distance   case
#    1   S     101 (+0.25, 0)    S          0.25     E   S->S
#    2   S     102 (0, +0.5)     X          0.5      N   S->X
#    3   C     103 (0, -0.25)    C          0.25     E   C->C
#    4   C     104 (+0.5, 0)     X          0.5      A   C->X
#    5   X     105 (0, +0.75)    C          0.75     A   X->C
#    6   X     -                                      missed -> EM[X, N]
#    -         106 (50, 50)      C                    FP     -> EM[N, C]
#    -         107 (-20, 0)      S                    FP     -> EM[N, S]
#
#            S  C  X  N     (rows: ground truth, columns: observed)
HAND_EM = [[1, 0, 1, 0],
           [0, 1, 1, 0],
           [0, 1, 0, 1],
           [1, 1, 0, 0]]
# total 8, diagonal (S,S)+(C,C)+(X,X) = 2  ->  wc = 100 * 2 / 8 = 25 %.

HAND_GT = {"objects": [obj(1, 0, 0, "S"), obj(2, 5, 0, "S"), obj(3, 10, 0, "C"),
                       obj(4, 15, 0, "C"), obj(5, 20, 0, "X"), obj(6, 25, 0, "X")]}
HAND_OBS = {"objects": [obj(101, 0.25, 0, "S"), obj(102, 5, 0.5, "X"), obj(103, 10, -0.25, "C"),
                        obj(104, 15.5, 0, "X"), obj(105, 20, 0.75, "C"), obj(106, 50, 50, "C"),
                        obj(107, -20, 0, "S")]}


@pytest.mark.parametrize("method", ["greedy", "optimal"])
def test_hand_computed_em_pairs_and_default_score(method: str) -> None:
    ev = evaluate_docs(HAND_GT, HAND_OBS, match=method)
    assert ev.em.dtype.kind == "i"
    assert ev.em.tolist() == HAND_EM
    assert ev.em[3, 3] == 0
    assert ev.pairs.tolist() == [[0, 0], [1, 1], [2, 2], [3, 3], [4, 4]]
    assert ev.distances.tolist() == pytest.approx([0.25, 0.5, 0.25, 0.5, 0.75])
    m = ev.metrics
    assert m["evaluation_score_percent"] == pytest.approx(25.0)
    assert m["em"]["labels"] == ["S", "C", "X", "N"]
    assert m["em"]["matrix"] == HAND_EM


def test_hand_computed_weights_and_credits() -> None:
    # weights (S, C, X, N) = (2, 1, 1, 1), credits (E, A, N) = (2, 1, 0):
    #   numerator   = S row: 2*2*1 (S->S, E) + 2*0*1 (S->X, N)
    #               + C row: 1*2*1 (C->C, E) + 1*1*1 (C->X, A)
    #               + X row: 1*1*1 (X->C, A) + 1*0*1 (X->N)
    #               + N row: 0                                   = 4 + 2 + 1 + 1 = 8
    #   denominator = credit E * sum w*EM = 2 * (2*2 + 2 + 2 + 2) = 20   ->  wc = 40 %
    ev = evaluate_docs(HAND_GT, HAND_OBS, weights=(2, 1, 1, 1), credits=(2, 1, 0))
    assert ev.metrics["evaluation_score_percent"] == pytest.approx(100 * 8 / 20)
    # weights (1, 1, 1, 0) drop the false-positive row; credits (1, 0.5, 0):
    #   numerator = 1 + 1 + 0.5 + 0.5 = 3, denominator = 1 * 6  ->  50 %
    ev = evaluate_docs(HAND_GT, HAND_OBS, weights=(1, 1, 1, 0), credits=(1, 0.5, 0))
    assert ev.metrics["evaluation_score_percent"] == pytest.approx(100 * 3 / 6)
    # weights (0, 0, 3, 0): only the X row (X->C almost, X->N missed) counts, credits (4, 1, 0):
    #   numerator = 3*1*1 = 3, denominator = 4 * (3*2) = 24  ->  12.5 %
    ev = evaluate_docs(HAND_GT, HAND_OBS, weights=(0, 0, 3, 0), credits=(4, 1, 0))
    assert ev.metrics["evaluation_score_percent"] == pytest.approx(100 * 3 / 24)
    # a custom case table: S->X counts as almost too, credits (1, 1, 0) -> (2 + 3) / 8
    table = dict(ev.config.case_table)
    table[("S", "X")] = "A"
    ev = evaluate_docs(HAND_GT, HAND_OBS, credits=(1, 1, 0), case_table=table)
    assert ev.metrics["evaluation_score_percent"] == pytest.approx(100 * 5 / 8)
    # every weight zero: the weighted total is 0, so the score is a defined 0
    ev = evaluate_docs(HAND_GT, HAND_OBS, weights=(0, 0, 0, 0))
    assert ev.metrics["evaluation_score_percent"] == 0.0


def test_hand_computed_counts_and_quality() -> None:
    m = evaluate_docs(HAND_GT, HAND_OBS).metrics
    # quality codes (gt, obs): (1,1) (1,3) (2,2) (2,3) (3,2); squared errors 0 4 0 1 1
    assert m["total_matches"] == 5
    assert m["correct_matches"] == 2
    assert m["wrong_matches"] == 3
    assert m["quality_correct_percent"] == pytest.approx(40.0)
    assert m["quality_error_percent"] == pytest.approx(60.0)
    assert m["rmse_quality"] == pytest.approx(math.sqrt(6 / 5))
    assert m["missed"] == 1
    assert m["false_positives"] == 2
    assert m["missed_percent"] == pytest.approx(100 / 6)
    assert m["false_positive_percent"] == pytest.approx(200 / 7)
    assert m["completeness"] == pytest.approx(5 / 6)
    assert m["correctness"] == pytest.approx(5 / 7)
    # 2 * (5/6)(5/7) / (5/6 + 5/7) = (50/42) / (65/42)
    assert m["f1"] == pytest.approx(10 / 13)
    assert m["accuracy_percent"] == pytest.approx(100 * 2 / 8)
    assert m["misclassified_percent"] == pytest.approx(100 * 3 / 8)
    assert m["missed_of_total_percent"] == pytest.approx(100 * 1 / 8)
    assert (m["n_ground_truth"], m["n_observed"]) == (6, 7)
    # position: observed - gt = (.25,0) (0,.5) (0,-.25) (.5,0) (0,.75)
    assert m["position_bias_m"] == pytest.approx([0.75 / 5, 1.0 / 5])
    assert m["position_rmse_m"] == pytest.approx(math.sqrt(1.1875 / 5))
    assert m["position_max_m"] == pytest.approx(0.75)


def test_quality_codes_and_classes_are_interchangeable() -> None:
    as_quality = {"objects": [{"id": o["id"], "cp": o["cp"], "quality": QUALITY[o["class"]]}
                              for o in HAND_OBS["objects"]]}
    a = evaluate_docs(HAND_GT, HAND_OBS).metrics
    b = evaluate_docs(HAND_GT, as_quality).metrics
    assert_same(a, b)


def test_matching_radius_is_respected() -> None:
    gt = {"objects": [obj(1, 0, 0, "S")]}
    near = {"objects": [obj(1, 0.6, 0.6, "S")]}  # 0.85 m
    assert evaluate_docs(gt, near).metrics["total_matches"] == 1
    assert evaluate_docs(gt, near, max_distance_m=0.8).metrics["total_matches"] == 0
    # the radius is in the x-y plane: a large z difference does not matter
    high = {"objects": [{"id": 1, "cp": [0.5, 0, 30.0], "class": "S"}]}
    assert evaluate_docs(gt, high).metrics["total_matches"] == 1


# ------------------------------------------------------------------ greedy and optimal


def test_greedy_and_optimal_differ_on_a_chain() -> None:
    # gt g0 at x=0, g1 at x=1.25; observed o0 at x=0.5, o1 at x=-0.75 (d = 1):
    #   g0-o0 0.5, g1-o0 0.75, g0-o1 0.75, g1-o1 2.0 (too far)
    # greedy takes g0-o0 (closest) and then nothing is free: 1 match.
    # optimal: two matches g0-o1 + g1-o0, total 1.5.
    gt = {"objects": [obj(1, 0, 0, "S"), obj(2, 1.25, 0, "C")]}
    obs = {"objects": [obj(1, 0.5, 0, "C"), obj(2, -0.75, 0, "S")]}
    greedy = evaluate_docs(gt, obs, match="greedy")
    optimal = evaluate_docs(gt, obs, match="optimal")
    assert greedy.pairs.tolist() == [[0, 0]]
    assert greedy.distances.tolist() == pytest.approx([0.5])
    assert greedy.em.tolist() == [[0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 0], [1, 0, 0, 0]]
    assert optimal.pairs.tolist() == [[0, 1], [1, 0]]
    assert optimal.distances.tolist() == pytest.approx([0.75, 0.75])
    assert optimal.em.tolist() == [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]
    assert greedy.metrics["evaluation_score_percent"] == pytest.approx(0.0)
    assert optimal.metrics["evaluation_score_percent"] == pytest.approx(100.0)


def test_optimal_prefers_the_smaller_total_distance() -> None:
    # g0 (0, 0), g1 (0.8, 0.5); o0 (0.5, 0), o1 (0, 0.55):
    #   g0-o0 0.5, g0-o1 0.55, g1-o0 sqrt(0.34) ~ 0.583, g1-o1 sqrt(0.6425) ~ 0.802
    # greedy: g0-o0, then g1-o1 (total ~1.302); optimal: g0-o1 + g1-o0 (total ~1.133).
    gt = {"objects": [obj(1, 0, 0, "S"), obj(2, 0.8, 0.5, "C")]}
    obs = {"objects": [obj(1, 0.5, 0, "C"), obj(2, 0, 0.55, "S")]}
    greedy = evaluate_docs(gt, obs, match="greedy")
    optimal = evaluate_docs(gt, obs, match="optimal")
    assert greedy.pairs.tolist() == [[0, 0], [1, 1]]
    assert float(greedy.distances.sum()) == pytest.approx(0.5 + math.sqrt(0.6425))
    assert optimal.pairs.tolist() == [[0, 1], [1, 0]]
    assert float(optimal.distances.sum()) == pytest.approx(0.55 + math.sqrt(0.34))
    assert greedy.metrics["evaluation_score_percent"] == pytest.approx(0.0)
    assert optimal.metrics["evaluation_score_percent"] == pytest.approx(100.0)


def test_greedy_ties_follow_id_rank_not_object_order() -> None:
    # gt ids 7 and 3 are both exactly 0.5 m from the one observed tree: id 3 wins.
    for gt_objs in ([obj(7, -0.5, 0, "S"), obj(3, 0.5, 0, "C")],
                    [obj(3, 0.5, 0, "C"), obj(7, -0.5, 0, "S")]):
        gt = {"objects": gt_objs}
        obs = {"objects": [obj(1, 0, 0, "C")]}
        ev = evaluate_docs(gt, obs)
        assert id_pairs(ev, gt, obs) == {(3, 1)}
        assert ev.em[1, 1] == 1 and ev.em[0, 3] == 1
    # observed ids 9 and 4 tie for the one gt tree: id 4 wins; ints rank before strings.
    for obs_objs in ([obj(9, 0, 0.5, "S"), obj(4, 0, -0.5, "X")],
                     [obj(4, 0, -0.5, "X"), obj(9, 0, 0.5, "S")],
                     [obj("a", 0, 0.5, "S"), obj(4, 0, -0.5, "X")],
                     [obj(4, 0, -0.5, "X"), obj("a", 0, 0.5, "S")]):
        gt = {"objects": [obj(1, 0, 0, "S")]}
        obs = {"objects": obs_objs}
        ev = evaluate_docs(gt, obs)
        assert id_pairs(ev, gt, obs) == {(1, 4)}
        assert ev.em.tolist() == [[0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]
    # string ids rank among themselves ("b" < "c")
    gt = {"objects": [obj("c", -0.5, 0, "S"), obj("b", 0.5, 0, "X")]}
    obs = {"objects": [obj("z", 0, 0, "X")]}
    assert id_pairs(evaluate_docs(gt, obs), gt, obs) == {("b", "z")}


# Regression tests: candidate_pairs once subtracted the ground truth's mean, whose rounding
# broke exact ties and the d boundary and made greedy depend on object order.


def test_greedy_tie_by_id_with_exact_coordinates_and_other_trees_present() -> None:
    # Observed ids 2 and 1 are both exactly 0.75 m from gt 1 (all coordinates exact in
    # binary). Two far gt trees make the gt mean (10/3, 20/3). The definition takes the tie
    # by id rank: observed 1 (class S) should be matched.
    gt = {"objects": [obj(1, 0, 0, "S"), obj(2, 10, 0, "S"), obj(3, 0, 20, "S")]}
    obs = {"objects": [obj(2, 0.75, 0, "C"), obj(1, -0.75, 0, "S")]}
    ev = evaluate_docs(gt, obs)
    assert id_pairs(ev, gt, obs) == {(1, 1)}


def test_a_tree_exactly_at_the_radius_is_matched_whatever_else_is_in_the_scene() -> None:
    # Integer coordinates: observed at (-1, 0) is exactly d = 1 m from gt (0, 0).
    obs = {"objects": [obj(1, -1, 0, "S")]}
    alone = {"objects": [obj(1, 0, 0, "S")]}
    assert evaluate_docs(alone, obs).metrics["total_matches"] == 1
    crowd = {"objects": [obj(1, 0, 0, "S"), obj(2, 10, 0, "S"), obj(3, 0, 20, "S")]}
    assert evaluate_docs(crowd, obs).metrics["total_matches"] == 1


def test_greedy_does_not_depend_on_gt_order_for_a_geometric_tie() -> None:
    # gt 1 (1.6, 0.5) and gt 2 (0.2, 0.5) are both (0.7, 0.4) from observed (0.9, 0.1).
    g1, g2, g3 = obj(1, 1.6, 0.5, "S"), obj(2, 0.2, 0.5, "C"), obj(3, 0.8, 1.6, "X")
    obs = {"objects": [obj(1, 0.9, 0.1, "S")]}
    a = {"objects": [g1, g2, g3]}
    b = {"objects": [g1, g3, g2]}
    assert id_pairs(evaluate_docs(a, obs), a, obs) == id_pairs(evaluate_docs(b, obs), b, obs)


# ------------------------------------------------------------------ empty forests

THREE = {"objects": [obj(1, 0, 0, "S"), obj(2, 5, 0, "C"), obj(3, 10, 0, "X")]}
EMPTY: dict[str, Any] = {"objects": []}


@pytest.mark.parametrize("method", ["greedy", "optimal"])
@pytest.mark.parametrize(("gt", "obs", "em"), [
    (EMPTY, THREE, [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [1, 1, 1, 0]]),
    (THREE, EMPTY, [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, 0]]),
    (EMPTY, EMPTY, [[0] * 4] * 4),
], ids=["empty-gt", "empty-observed", "both-empty"])
def test_empty_forests_give_defined_zeros(gt: dict[str, Any], obs: dict[str, Any],
                                          em: list[list[int]], method: str) -> None:
    ev = evaluate_docs(gt, obs, match=method, weights=(2, 1, 1, 3), credits=(2, 1, 0))
    m = ev.metrics
    assert ev.em.tolist() == em
    assert ev.pairs.shape == (0, 2)
    assert m["evaluation_score_percent"] == 0.0
    assert m["total_matches"] == 0
    assert m["missed"] == len(gt["objects"])
    assert m["false_positives"] == len(obs["objects"])
    for key in ("completeness", "correctness", "f1", "quality_correct_percent",
                "quality_error_percent", "rmse_quality", "position_rmse_m", "height_rmse_m",
                "dbh_rmse_m", "maxcurve_rmse_m"):
        assert m[key] == 0.0, key
    assert m["height_pairs"] == 0
    for key, value in m.items():
        assert all(math.isfinite(n) for n in numbers(value)), key
    json.dumps(m, allow_nan=False)  # the metrics can be written as strict JSON


# ------------------------------------------------------------------ property errors


def test_position_height_dbh_bias_and_rmse_on_a_constructed_offset() -> None:
    gt = {"objects": [obj(1, 0, 0, "S", h=20.0, dbh=0.30, maxcurve=0.01),
                      obj(2, 10, 0, "C", h=15.0, dbh=0.25, maxcurve=0.05),
                      obj(3, 0, 10, "X", h=10.0, dbh=0.20, maxcurve=0.12)]}
    # every observed tree shifted by (+0.3, -0.4): 0.5 m; heights off by +1, -1, +2;
    # dbh off by +0.02, +0.02, -0.01; no maxcurve.
    obs = {"objects": [obj(1, 0.3, -0.4, "S", h=21.0, dbh=0.32),
                       obj(2, 10.3, -0.4, "C", h=14.0, dbh=0.27),
                       obj(3, 0.3, 9.6, "X", h=12.0, dbh=0.19)]}
    m = evaluate_docs(gt, obs).metrics
    assert m["total_matches"] == 3
    assert m["position_bias_m"] == pytest.approx([0.3, -0.4])
    assert m["position_rmse_m"] == pytest.approx(0.5)
    assert m["position_max_m"] == pytest.approx(0.5)
    assert m["height_bias_m"] == pytest.approx(2 / 3)
    assert m["height_rmse_m"] == pytest.approx(math.sqrt((1 + 1 + 4) / 3))
    assert m["height_pairs"] == 3
    assert m["dbh_bias_m"] == pytest.approx(0.03 / 3)
    assert m["dbh_rmse_m"] == pytest.approx(math.sqrt((0.0004 + 0.0004 + 0.0001) / 3))
    assert m["dbh_pairs"] == 3
    assert (m["maxcurve_pairs"], m["maxcurve_bias_m"], m["maxcurve_rmse_m"]) == (0, 0.0, 0.0)

    # one observed tree without h: two height pairs remain (errors +1, -1)
    del obs["objects"][2]["h"]
    m = evaluate_docs(gt, obs).metrics
    assert m["height_pairs"] == 2
    assert m["height_bias_m"] == pytest.approx(0.0)
    assert m["height_rmse_m"] == pytest.approx(1.0)

    # observed without h or dbh at all
    bare = {"objects": [{"id": o["id"], "cp": o["cp"], "class": o["class"]}
                        for o in obs["objects"]]}
    m = evaluate_docs(gt, bare).metrics
    assert m["total_matches"] == 3
    assert (m["height_pairs"], m["dbh_pairs"]) == (0, 0)
    assert (m["height_rmse_m"], m["height_bias_m"], m["dbh_rmse_m"]) == (0.0, 0.0, 0.0)


def test_position_bias_sign_is_observed_minus_ground_truth() -> None:
    gt = {"objects": [obj(1, 100, 200, "S")]}
    obs = {"objects": [obj(1, 99.75, 200.5, "S")]}
    m = evaluate_docs(gt, obs).metrics
    assert m["position_bias_m"] == pytest.approx([-0.25, 0.5])


# ------------------------------------------------------------------ property tests

QUARTER = st.integers(-20, 20).map(lambda k: k / 4)  # exact in binary: no rounding ties
MILLIMETRE = st.integers(-10**6, 10**6).map(lambda k: k / 1000)  # distinct trees >= 1 mm apart
CLASS = st.sampled_from(("S", "C", "X"))
ANY_ID = st.one_of(st.integers(1, 10_000), st.text(alphabet="abcxyz", min_size=1, max_size=3))


def _id_key(v: Any) -> tuple[str, Any]:
    return (type(v).__name__, v)


@st.composite
def scenes(draw: st.DrawFn, max_trees: int = 8) -> tuple[dict[str, Any], dict[str, Any]]:
    """A ground truth and an observation on a quarter-metre grid; many observed trees near a
    ground-truth tree, so that conflicts and exact distance ties are common."""
    gt_xy = draw(st.lists(st.tuples(QUARTER, QUARTER), max_size=max_trees))
    gt_ids = draw(st.lists(ANY_ID, min_size=len(gt_xy), max_size=len(gt_xy), unique_by=_id_key))
    gt = [obj(i, x, y, draw(CLASS)) for i, (x, y) in zip(gt_ids, gt_xy, strict=True)]
    n_obs = draw(st.integers(0, max_trees))
    obs_ids = draw(st.lists(ANY_ID, min_size=n_obs, max_size=n_obs, unique_by=_id_key))
    obs = []
    for oid in obs_ids:
        if gt_xy and draw(st.booleans()):
            x, y = draw(st.sampled_from(gt_xy))
            x += draw(st.integers(-4, 4)) / 4
            y += draw(st.integers(-4, 4)) / 4
        else:
            x, y = draw(QUARTER), draw(QUARTER)
        obs.append(obj(oid, x, y, draw(CLASS)))
    return {"objects": gt}, {"objects": obs}


@settings(max_examples=60, deadline=None)
@given(trees=st.lists(st.tuples(MILLIMETRE, MILLIMETRE, CLASS),
                      min_size=1, max_size=12, unique_by=lambda t: (t[0], t[1])),
       method=st.sampled_from(["greedy", "optimal"]),
       as_quality=st.booleans())
def test_a_perfect_observation_scores_100(trees: list[tuple[float, float, str]], method: str,
                                          as_quality: bool) -> None:
    gt = {"objects": [obj(i, x, y, c) for i, (x, y, c) in enumerate(trees, 1)]}
    if as_quality:
        obs = {"objects": [{"id": i, "cp": [x, y, 0.0], "quality": QUALITY[c]}
                           for i, (x, y, c) in enumerate(trees, 1)]}
    else:
        obs = json.loads(json.dumps(gt))
    m = evaluate_docs(gt, obs, match=method).metrics
    assert m["evaluation_score_percent"] == pytest.approx(100.0)
    assert m["total_matches"] == len(trees)
    assert (m["missed"], m["false_positives"], m["wrong_matches"]) == (0, 0, 0)
    assert m["f1"] == pytest.approx(1.0)
    assert m["position_rmse_m"] == 0.0


@settings(max_examples=150, deadline=None)
@given(scene=scenes(),
       weights=st.tuples(*[st.floats(0, 10)] * 4),
       e_credit=st.floats(0.01, 10),
       fractions=st.tuples(st.floats(0, 1), st.floats(0, 1)),
       cases=st.lists(st.sampled_from("EAN"), min_size=16, max_size=16),
       method=st.sampled_from(["greedy", "optimal"]))
def test_score_stays_within_0_and_100(scene: tuple[dict[str, Any], dict[str, Any]],
                                      weights: tuple[float, float, float, float],
                                      e_credit: float, fractions: tuple[float, float],
                                      cases: list[str], method: str) -> None:
    credits = (e_credit, e_credit * fractions[0], e_credit * fractions[1])
    table = {(g, o): c for (g, o), c in zip(itertools.product(LABELS, LABELS), cases,
                                            strict=True)}
    for case_table in (table, None):
        cfg: dict[str, Any] = {"match": method, "weights": weights, "credits": credits}
        if case_table is not None:
            cfg["case_table"] = case_table
        ev = evaluate_docs(*scene, **cfg)
        wc = ev.metrics["evaluation_score_percent"]
        assert math.isfinite(wc)
        assert -1e-9 <= wc <= 100 + 1e-9
        assert ev.em.sum() == len(scene[0]["objects"]) + len(scene[1]["objects"]) - len(ev.pairs)
        assert ev.em[3, 3] == 0


@settings(max_examples=150, deadline=None)
@given(scene=scenes(), data=st.data())
def test_object_order_changes_no_metric(scene: tuple[dict[str, Any], dict[str, Any]],
                                        data: st.DataObject) -> None:
    gt, obs = scene
    gt2 = {"objects": data.draw(st.permutations(gt["objects"]))}
    obs2 = {"objects": data.draw(st.permutations(obs["objects"]))}
    a = evaluate_docs(gt, obs)
    b = evaluate_docs(gt2, obs2)
    assert id_pairs(a, gt, obs) == id_pairs(b, gt2, obs2)
    assert_same(a.metrics, b.metrics)


@st.composite
def separated_scenes(draw: st.DrawFn) -> tuple[dict[str, Any], dict[str, Any]]:
    """Ground truth on a 3 m grid (3 d); 0 to 2 observed trees within d/2 of each, at
    clearly different distances; false positives far from everything."""
    cells = draw(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5)), min_size=1,
                          max_size=12, unique=True))
    gt, obs = [], []
    for k, (i, j) in enumerate(cells, 1):
        x, y = 3.0 * i, 3.0 * j
        gt.append(obj(k, x, y, draw(CLASS)))
        n = draw(st.integers(0, 2))
        for r_lo, r_hi in [(0.0, 0.2), (0.3, 0.5)][:n]:
            r = draw(st.floats(r_lo, r_hi))
            a = draw(st.floats(0, 2 * math.pi))
            obs.append(obj(100 * k + len(obs), x + r * math.cos(a), y + r * math.sin(a),
                           draw(CLASS)))
    for f in range(draw(st.integers(0, 3))):
        obs.append(obj(10_000 + f, 500.0 + 5 * f, -500.0, draw(CLASS)))
    order = draw(st.permutations(range(len(obs))))
    return {"objects": gt}, {"objects": [obs[i] for i in order]}


@settings(max_examples=80, deadline=None)
@given(scene=separated_scenes())
def test_greedy_and_optimal_agree_when_stems_are_far_apart(
        scene: tuple[dict[str, Any], dict[str, Any]]) -> None:
    greedy = evaluate_docs(*scene, match="greedy")
    optimal = evaluate_docs(*scene, match="optimal")
    assert greedy.pairs.tolist() == optimal.pairs.tolist()
    a, b = dict(greedy.metrics), dict(optimal.metrics)
    assert a.pop("config")["match"] == "greedy"
    assert b.pop("config")["match"] == "optimal"
    assert_same(a, b)
    # every gt tree with an observed tree near it is matched, to the nearest one (< 0.2 m)
    near = {o["id"] // 100 for o in scene[1]["objects"] if o["id"] < 10_000}
    assert {scene[0]["objects"][g]["id"] for g, _ in greedy.pairs.tolist()} == near
    assert np.all(greedy.distances <= 0.2 + 1e-9)


def _exact_edges(gt: dict[str, Any], obs: dict[str, Any], d: float) -> dict[tuple[int, int], int]:
    """(gt index, obs index) -> squared distance in quarter metres (exact integers)."""
    edges = {}
    for i, g in enumerate(gt["objects"]):
        for j, o in enumerate(obs["objects"]):
            dx = round(4 * (g["cp"][0] - o["cp"][0]))
            dy = round(4 * (g["cp"][1] - o["cp"][1]))
            if dx * dx + dy * dy <= (4 * d) ** 2:
                edges[(i, j)] = dx * dx + dy * dy
    return edges


# d = 1.1 m keeps every grid distance clear of the radius (quarter-metre grid: squared
# distances are integers / 16, and 1.1 ** 2 * 16 = 19.36).
D_CLEAR = 1.1


@settings(max_examples=100, deadline=None)
@given(scene=scenes(max_trees=5))
def test_optimal_is_a_maximum_matching_of_least_total_distance(
        scene: tuple[dict[str, Any], dict[str, Any]]) -> None:
    gt, obs = scene
    edges = _exact_edges(gt, obs, D_CLEAR)
    best = (0, 0.0)  # (size, -total) maximised

    def search(i: int, used: frozenset[int], size: int, total: float) -> None:
        nonlocal best
        if i == len(gt["objects"]):
            if (size, -total) > (best[0], -best[1] + 1e-12):
                best = (size, total)
            return
        search(i + 1, used, size, total)
        for (g, o), s in edges.items():
            if g == i and o not in used:
                search(i + 1, used | {o}, size + 1, total + math.sqrt(s) / 4)

    search(0, frozenset(), 0, 0.0)
    ev = evaluate_docs(gt, obs, match="optimal", max_distance_m=D_CLEAR)
    pairs = [tuple(p) for p in ev.pairs.tolist()]
    assert all(p in edges for p in pairs)
    assert len({g for g, _ in pairs}) == len({o for _, o in pairs}) == len(pairs)
    assert len(pairs) == best[0]
    assert float(ev.distances.sum()) == pytest.approx(best[1], abs=1e-9)
    assert [p[0] for p in pairs] == sorted(p[0] for p in pairs)


@settings(max_examples=150, deadline=None)
@given(scene=scenes(max_trees=7))
def test_greedy_leaves_no_closer_free_pair(scene: tuple[dict[str, Any], dict[str, Any]]) -> None:
    """Greedy's defining property: every candidate pair it did not take lost to a pair at
    no greater distance that holds one of its trees (maximal, one-to-one, nearest first)."""
    gt, obs = scene
    edges = _exact_edges(gt, obs, D_CLEAR)
    ev = evaluate_docs(gt, obs, match="greedy", max_distance_m=D_CLEAR)
    pairs = [tuple(p) for p in ev.pairs.tolist()]
    assert all(p in edges for p in pairs)
    g_dist = {g: edges[(g, o)] for g, o in pairs}
    o_dist = {o: edges[(g, o)] for g, o in pairs}
    assert len(g_dist) == len(o_dist) == len(pairs)
    for (g, o), s in edges.items():
        if (g, o) not in pairs:
            assert min(g_dist.get(g, math.inf), o_dist.get(o, math.inf)) <= s, (g, o)


# ------------------------------------------------------------------ bad input

GOOD = {"id": 1, "cp": [0.0, 0.0, 0.0], "class": "S"}


def _with(second: dict[str, Any], **doc: Any) -> dict[str, Any]:
    return {"objects": [dict(GOOD), second], **doc}


@pytest.mark.parametrize(("bad", "field"), [
    (_with({"id": 1, "cp": [5.0, 0.0, 0.0], "class": "S"}), "objects[1].id"),
    (_with({"id": 2, "cp": [5.0, float("nan"), 0.0], "class": "S"}), "objects[1].cp[1]"),
    (_with({"id": 2, "cp": [float("inf"), 0.0, 0.0], "class": "S"}), "objects[1].cp[0]"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0], "class": "S", "h": float("inf")}), "objects[1].h"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0], "class": "Q"}), "objects[1].class"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0], "class": "C", "quality": 3}), "objects[1].quality"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0], "quality": 4}), "objects[1].quality"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0]}), "objects[1]"),
    (_with({"id": 2, "class": "S"}), "objects[1]"),
    (_with({"id": 2, "cp": [5.0, 0.0], "class": "S"}), "objects[1].cp"),
    (_with({"id": 2, "cp": [5.0, 0.0, 0.0], "class": "S"}, total_objects_count=3),
     "total_objects_count"),
], ids=["duplicate-id", "nan-cp", "inf-cp", "inf-h", "unknown-class", "class-vs-quality",
        "unknown-quality", "no-class-or-quality", "missing-cp", "short-cp", "wrong-count"])
def test_bad_documents_name_the_source_and_field(bad: dict[str, Any], field: str) -> None:
    with pytest.raises(InputError) as info:
        stem_table(bad, "forest-ix.json")
    assert info.value.path == "forest-ix.json"
    assert info.value.field == field
    text = str(info.value)
    assert text.startswith(f"forest-ix.json at {field}")
    assert "\n" not in text


def test_ids_of_different_type_are_different_ids() -> None:
    table = stem_table(_with({"id": "1", "cp": [5.0, 0.0, 0.0], "class": "S"}), "ok.json")
    assert table.ids == [1, "1"]


def test_ids_1_and_1_point_0_are_duplicates() -> None:
    with pytest.raises(InputError) as info:
        stem_table(_with({"id": 1.0, "cp": [5.0, 0.0, 0.0], "class": "S"}), "dup.json")
    assert info.value.field == "objects[1].id"


def test_overflowing_json_number_is_refused_with_file_and_field(tmp_path: Path) -> None:
    path = tmp_path / "observed.json"
    path.write_text('{"objects": [{"id": 1, "cp": [0, 0, 0], "class": "S"},\n'
                    '             {"id": 2, "cp": [1e400, 0, 0], "class": "X"}]}\n')
    with pytest.raises(InputError) as info:
        load_stems(path)
    assert info.value.field == "objects[1].cp[0]"
    assert str(path) in str(info.value)
    assert "objects[1].cp[0]" in str(info.value)


# ------------------------------------------------------------------ the score command

SCORE_KEYS = ("evaluation_score_percent", "total_matches", "quality_correct_percent",
              "quality_error_percent", "rmse_quality", "correct_matches", "wrong_matches",
              "missed", "false_positives", "completeness", "correctness", "f1",
              "position_rmse_m", "dbh_rmse_m", "height_rmse_m", "em")


def _write(path: Path, doc: Any) -> Path:
    path.write_text(json.dumps(doc))
    return path


def test_score_command_writes_metrics_and_plots(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    gt = _write(tmp_path / "gt.json", HAND_GT)
    obs = _write(tmp_path / "obs.json", HAND_OBS)
    out, plots = tmp_path / "out" / "metrics.json", tmp_path / "plots"
    rc = main(["score", str(gt), str(obs), "--json", str(out), "--plots", str(plots)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    metrics = json.loads(out.read_text())
    for key in SCORE_KEYS:
        assert key in metrics, key
    assert metrics["em"]["labels"] == ["S", "C", "X", "N"]
    assert metrics["em"]["matrix"] == HAND_EM
    assert metrics["evaluation_score_percent"] == pytest.approx(25.0)
    assert metrics["total_matches"] == 5
    for name in ("em_heatmap.png", "matched_positions.png"):
        data = (plots / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE), name
    assert "Evaluation score" in captured.out


def test_score_command_passes_weights_credits_and_method(tmp_path: Path) -> None:
    gt = _write(tmp_path / "gt.json", HAND_GT)
    obs = _write(tmp_path / "obs.json", HAND_OBS)
    out = tmp_path / "m.json"
    rc = main(["score", str(gt), str(obs), "--json", str(out), "--weights", "2,1,1,1",
               "--credits", "2,1,0", "--match", "optimal", "--max-distance", "0.6"])
    assert rc == 0
    metrics = json.loads(out.read_text())
    # d = 0.6 drops the X->C pair (0.75 m): EM rows S [1,0,1,0], C [0,1,1,0], X [0,0,0,2],
    # N [1,2,0,0]; numerator 2*2 + 2 + 1 = 7, denominator 2 * (2*2 + 2 + 2 + 3) = 22
    assert metrics["em"]["matrix"] == [[1, 0, 1, 0], [0, 1, 1, 0], [0, 0, 0, 2], [1, 2, 0, 0]]
    assert metrics["evaluation_score_percent"] == pytest.approx(100 * 7 / 22)
    assert metrics["config"] == {"match": "optimal", "max_distance_m": 0.6,
                                 "weights": [2, 1, 1, 1], "credits": [2, 1, 0]}


@pytest.mark.parametrize(("which", "text", "needle"), [
    ("observed", '{"objects": [', "invalid JSON"),
    ("observed", json.dumps(_with({"id": 1, "cp": [1.0, 0.0, 0.0], "class": "S"})),
     "objects[1].id"),
    ("gt", json.dumps({"objects": [{"id": 1, "cp": [0, 0, 0], "class": "Q"}]}),
     "objects[0].class"),
], ids=["invalid-json", "duplicate-id", "bad-class-in-gt"])
def test_score_bad_file_is_one_error_line_and_writes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], which: str, text: str,
        needle: str) -> None:
    gt = _write(tmp_path / "gt.json", HAND_GT)
    obs = _write(tmp_path / "obs.json", HAND_OBS)
    bad = gt if which == "gt" else obs
    bad.write_text(text)
    out, plots = tmp_path / "metrics.json", tmp_path / "plots"
    rc = main(["score", str(gt), str(obs), "--json", str(out), "--plots", str(plots)])
    err = capsys.readouterr().err
    assert rc == 1
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("Error:")
    assert str(bad) in lines[0]
    assert needle in lines[0]
    assert not out.exists()
    assert not (plots / "em_heatmap.png").exists()


def test_score_missing_file_is_an_error_naming_it(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    gt = _write(tmp_path / "gt.json", HAND_GT)
    missing = tmp_path / "nowhere.json"
    out = tmp_path / "metrics.json"
    assert main(["score", str(gt), str(missing), "--json", str(out)]) == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and str(missing) in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("option", [
    ["--weights", "1,2"],
    ["--weights", "1,1,1,x"],
    ["--weights", "1,1,1,-1"],
    ["--credits", "1,0"],
    ["--credits", "0,0,0"],
    ["--match", "best"],
    ["--max-distance", "0"],
])
def test_score_usage_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   option: list[str]) -> None:
    gt = _write(tmp_path / "gt.json", HAND_GT)
    obs = _write(tmp_path / "obs.json", HAND_OBS)
    out = tmp_path / "metrics.json"
    assert main(["score", str(gt), str(obs), "--json", str(out), *option]) == 2
    assert capsys.readouterr().err.strip()
    assert not out.exists()


def test_evaluation_arrays_have_the_documented_shapes() -> None:
    ev = evaluate_docs(HAND_GT, HAND_OBS)
    assert ev.em.shape == (4, 4)
    assert ev.pairs.shape == (5, 2) and ev.pairs.dtype.kind == "i"
    assert ev.distances.shape == (5,)
    assert np.all(ev.distances <= ev.config.max_distance_m)
    # the free function gives the same pairs as evaluate
    g, o = stem_table(HAND_GT, "gt"), stem_table(HAND_OBS, "obs")
    pairs, dist = match(g.xyz[:, :2], o.xyz[:, :2], 1.0, "greedy", g.ids, o.ids)
    assert pairs.tolist() == ev.pairs.tolist()
    assert dist.tolist() == pytest.approx(ev.distances.tolist())
