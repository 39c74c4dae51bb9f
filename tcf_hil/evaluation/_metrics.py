"""The evaluation (EE): evaluation matrix, weighted classification score and the metrics.

EM is indexed by the labels ``[S, C, X, N]``: rows are the ground-truth class, columns the
observed class. A matched pair adds 1 at [gt class, observed class]; an unmatched observed
tree (false positive) adds 1 at [N, observed class]; an unmatched ground-truth tree (missed)
adds 1 at [gt class, N]; EM[N, N] is always 0.

The weighted classification score::

    wc = 100 * sum_g,o w[g] * credit[case(g, o)] * EM[g, o] / (credit[E] * sum_g,o w[g] * EM[g, o])

with the case table mapping (gt, observed) to E (exact), A (almost) or N (no credit). With the
default case table, credits (1, 0, 0) and weights (1, 1, 1, 1) this is the paper's
diag(EM) / sum(EM). Where a denominator would be zero, the metric is defined as 0.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.evaluation._match import MatchMethod, match
from tcf_hil.recording.stems_json import StemTable

LABELS: tuple[str, ...] = ("S", "C", "X", "N")
CASES: tuple[str, ...] = ("E", "A", "N")


def default_case_table() -> dict[tuple[str, str], str]:
    """Diagonal -> E; (C, X) and (X, C) -> A; everything else (N row/column included) -> N."""
    table = {(g, o): "N" for g in LABELS for o in LABELS}
    for c in ("S", "C", "X"):
        table[(c, c)] = "E"
    table[("C", "X")] = table[("X", "C")] = "A"
    return table


@dataclass(frozen=True)
class EvalConfig:
    """Evaluation parameters.

    Attributes:
        match: ``greedy`` (paper, order-independent) or ``optimal`` (minimum total distance).
        max_distance_m: matching radius d in the x-y plane.
        weights: class weights w for S, C, X, N (applied by the EM row).
        credits: credit for the cases E, A, N.
        case_table: (gt label, observed label) -> case.
    """

    match: MatchMethod = "greedy"
    max_distance_m: float = 1.0
    weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    credits: tuple[float, float, float] = (1.0, 0.0, 0.0)
    case_table: Mapping[tuple[str, str], str] = field(default_factory=default_case_table)

    def __post_init__(self) -> None:
        if self.match not in ("greedy", "optimal"):
            raise ValueError(f"match = {self.match!r}; allowed: 'greedy', 'optimal'")
        if not (math.isfinite(self.max_distance_m) and self.max_distance_m > 0):
            raise ValueError(f"max_distance_m = {self.max_distance_m!r}; allowed: a number > 0")
        if len(self.weights) != 4 or any(not math.isfinite(w) or w < 0 for w in self.weights):
            raise ValueError(f"weights = {self.weights!r}; allowed: four numbers >= 0 (S,C,X,N)")
        if len(self.credits) != 3 or any(not math.isfinite(c) or c < 0 for c in self.credits):
            raise ValueError(f"credits = {self.credits!r}; allowed: three numbers >= 0 (E,A,N)")
        if self.credits[0] <= 0 or max(self.credits[1:]) > self.credits[0]:
            raise ValueError(f"credits = {self.credits!r}; the E credit must be > 0 and at "
                             "least the A and N credits (else wc could pass 100 %)")
        for key, case in self.case_table.items():
            if case not in CASES:
                raise ValueError(f"case_table[{key}] = {case!r}; allowed: E, A, N")


@dataclass(frozen=True)
class Evaluation:
    """The outcome of scoring an observed forest against the ground truth."""

    em: NDArray[np.int64]  # (4, 4) over LABELS
    pairs: NDArray[np.int64]  # (k, 2) [gt index, observed index]
    distances: NDArray[np.float64]  # (k,)
    metrics: dict[str, Any]
    config: EvalConfig


def evaluation_matrix(gt_classes: Sequence[str] | NDArray[np.str_],
                      obs_classes: Sequence[str] | NDArray[np.str_],
                      pairs: NDArray[np.int64]) -> NDArray[np.int64]:
    """EM (4 x 4 over S, C, X, N) from the classes and the matched index pairs."""
    code = {c: i for i, c in enumerate(LABELS)}
    g = np.array([code[c] for c in gt_classes], dtype=np.int64)
    o = np.array([code[c] for c in obs_classes], dtype=np.int64)
    em = np.zeros((4, 4), dtype=np.int64)
    gm = np.zeros(len(g), dtype=bool)
    om = np.zeros(len(o), dtype=bool)
    if len(pairs):
        np.add.at(em, (g[pairs[:, 0]], o[pairs[:, 1]]), 1)
        gm[pairs[:, 0]] = True
        om[pairs[:, 1]] = True
    em[:, 3] += np.bincount(g[~gm], minlength=4)
    em[3, :] += np.bincount(o[~om], minlength=4)
    return em


def weighted_score(em: NDArray[np.int64], cfg: EvalConfig | None = None) -> float:
    """wc in percent (0 when the weighted total is 0)."""
    cfg = cfg or EvalConfig()
    w = np.asarray(cfg.weights, dtype=np.float64)[:, None]
    credit_of = dict(zip(CASES, cfg.credits, strict=True))
    credit = np.array([[credit_of[cfg.case_table.get((g, o), "N")] for o in LABELS]
                       for g in LABELS])
    den = cfg.credits[0] * float(np.sum(w * em))
    if den <= 0:
        return 0.0
    return 100.0 * float(np.sum(w * credit * em)) / den


def _div(a: float, b: float) -> float:
    return a / b if b else 0.0


def _err_stats(obs: NDArray[np.float64], gt: NDArray[np.float64]) -> tuple[float, float, int]:
    e = obs - gt
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return 0.0, 0.0, 0
    return float(e.mean()), float(math.sqrt(float(np.mean(e * e)))), len(e)


def evaluate(gt: StemTable, obs: StemTable, cfg: EvalConfig | None = None) -> Evaluation:
    """Match and score ``obs`` against ``gt`` (see the module docstring for definitions)."""
    cfg = cfg or EvalConfig()
    pairs, dist = match(gt.xyz[:, :2], obs.xyz[:, :2], cfg.max_distance_m, cfg.match,
                        gt.sort_keys(), obs.sort_keys())
    em = evaluation_matrix(gt.classes, obs.classes, pairs)
    k = len(pairs)
    n_gt, n_obs = len(gt), len(obs)
    gq = gt.quality[pairs[:, 0]] if k else np.zeros(0, np.int64)
    oq = obs.quality[pairs[:, 1]] if k else np.zeros(0, np.int64)
    correct = int(np.sum(gq == oq))
    missed = n_gt - k
    fp = n_obs - k
    completeness = _div(k, n_gt)
    correctness = _div(k, n_obs)
    f1 = _div(2 * completeness * correctness, completeness + correctness)
    total = float(em.sum())
    m: dict[str, Any] = {
        "evaluation_score_percent": weighted_score(em, cfg),
        "total_matches": k,
        "quality_correct_percent": 100.0 * _div(correct, k),
        "quality_error_percent": 100.0 * _div(k - correct, k),
        "rmse_quality": math.sqrt(_div(float(np.sum((gq - oq) ** 2)), k)),
        "correct_matches": correct,
        "wrong_matches": k - correct,
        "missed": missed,
        "missed_percent": 100.0 * _div(missed, n_gt),
        "false_positives": fp,
        "false_positive_percent": 100.0 * _div(fp, n_obs),
        "completeness": completeness,
        "correctness": correctness,
        "f1": f1,
        # The paper's Table 6 split of all EM entries: accuracy + misclassified + missed (+ FP).
        "accuracy_percent": 100.0 * _div(float(np.trace(em[:3, :3])), total),
        "misclassified_percent": 100.0 * _div(float(em[:3, :3].sum() - np.trace(em[:3, :3])),
                                              total),
        "missed_of_total_percent": 100.0 * _div(float(em[:3, 3].sum()), total),
        "n_ground_truth": n_gt,
        "n_observed": n_obs,
    }
    if k:
        d = gt.xyz[pairs[:, 0], :2] - obs.xyz[pairs[:, 1], :2]
        m["position_bias_m"] = [float(-d[:, 0].mean()), float(-d[:, 1].mean())]
        m["position_rmse_m"] = float(math.sqrt(float(np.mean(np.sum(d * d, axis=1)))))
        m["position_max_m"] = float(dist.max())
    else:
        m["position_bias_m"] = [0.0, 0.0]
        m["position_rmse_m"] = 0.0
        m["position_max_m"] = 0.0
    for name in ("h", "dbh", "maxcurve"):
        label = "height" if name == "h" else name
        if k:
            bias, rmse, cnt = _err_stats(getattr(obs, name)[pairs[:, 1]],
                                         getattr(gt, name)[pairs[:, 0]])
        else:
            bias, rmse, cnt = 0.0, 0.0, 0
        m[f"{label}_bias_m"] = bias
        m[f"{label}_rmse_m"] = rmse
        m[f"{label}_pairs"] = cnt
    m["em"] = {"rows": "ground truth", "columns": "observed", "labels": list(LABELS),
               "matrix": em.tolist()}
    m["config"] = {"match": cfg.match, "max_distance_m": cfg.max_distance_m,
                   "weights": list(cfg.weights), "credits": list(cfg.credits)}
    return Evaluation(em, pairs, dist, m, cfg)
