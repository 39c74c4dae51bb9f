"""Scoring a SIC's forest: against every ground-truth tree and against the trees the sensor
saw, overall and by distance from the track (the bands of ``score.json``). The one place a
forest is scored: a run (:mod:`tcf_hil.run`), ``score``, the export and the experiments call
it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.evaluation import EvalConfig, Evaluation, evaluate
from tcf_hil.recording.stems_json import StemTable, stem_table


def seen_truth(gt_doc: dict[str, Any]) -> dict[str, Any]:
    """The ground truth restricted to the stems with at least one lidar return; a field
    inventory, which knows nothing of what the sensor saw, as it is."""
    if "inventory" in gt_doc:
        return gt_doc
    objs = [o for o in gt_doc["objects"] if int(o.get("returns", 0)) > 0]
    return {**gt_doc, "objects": objs, "total_objects_count": len(objs)}


@dataclass
class Scores:
    all: Evaluation
    seen: Evaluation
    gt_all: StemTable
    gt_seen: StemTable

    def summary(self) -> dict[str, Any]:
        return {"all_trees": self.all.metrics, "seen_trees": self.seen.metrics}


@dataclass(frozen=True)
class ScoredForest:
    """A SIC's final forest scored once: the scores, the forest as a table and as the
    document it published, the truth document, and the configuration. A run makes one and
    hands it to the report and the export, which no longer score the forest again (nor read
    the track again: ``track``, the sensor's horizontal track as the run read it, (n, 2),
    where it did)."""

    scores: Scores
    forest: StemTable
    forest_doc: dict[str, Any]
    truth_doc: dict[str, Any]
    config: EvalConfig
    track: NDArray[np.float64] | None = None


DISTANCE_BANDS_M = ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 25.0), (25.0, math.inf))


def by_distance(ev: Evaluation, gt: StemTable, obs: StemTable, gt_d: NDArray[np.float64],
                obs_d: NDArray[np.float64],
                bands: tuple[tuple[float, float], ...] = DISTANCE_BANDS_M
                ) -> list[dict[str, Any]]:
    """The scoring per band of horizontal distance from the track (the report's "Errors by
    distance", for scripts): a true stem counts in the band of its own distance, a SIC stem
    in its own (an unmatched one is a false positive there). Per band: trees, found,
    detection, SIC stems, false positives and their share, position RMSE, DBH bias and
    RMSE, class correct (of the found)."""
    g2o = {int(g): int(o) for g, o in ev.pairs}
    matched = set(g2o.values())
    out = []
    for lo, hi in bands:
        gi = np.flatnonzero((gt_d >= lo) & (gt_d < hi))
        oi = np.flatnonzero((obs_d >= lo) & (obs_d < hi))
        m = [(g, g2o[g]) for g in gi.tolist() if g in g2o]
        fp = sum(1 for o in oi.tolist() if o not in matched)
        pos = [math.dist(gt.xyz[g, :2], obs.xyz[o, :2]) for g, o in m]
        dbh = [float(obs.dbh[o] - gt.dbh[g]) for g, o in m
               if math.isfinite(obs.dbh[o]) and math.isfinite(gt.dbh[g])]
        cls = [obs.classes[o] == gt.classes[g] for g, o in m]

        def rms(v: list[float]) -> float | None:
            return round(math.sqrt(sum(e * e for e in v) / len(v)), 4) if v else None

        out.append({
            "from_m": lo, "to_m": None if math.isinf(hi) else hi, "trees": len(gi),
            "found": len(m), "detection": round(len(m) / len(gi), 4) if len(gi) else None,
            "sic_stems": len(oi), "false_positives": fp,
            "false_positive_share": round(fp / len(oi), 4) if len(oi) else None,
            "position_rmse_m": rms(pos),
            "dbh_bias_m": round(sum(dbh) / len(dbh), 4) if dbh else None,
            "dbh_rmse_m": rms(dbh),
            "class_correct": round(sum(cls) / len(cls), 4) if cls else None})
    return out


def score_forest(gt_doc: dict[str, Any], obs: StemTable, cfg: EvalConfig | None = None,
                 gt_source: str = "ground_truth.json") -> Scores:
    """``obs`` scored against a generated forest's ground truth or a field inventory
    (:func:`tcf_hil.recording.inventory.read_inventory`: the metrics it cannot give are None)."""
    if "inventory" in gt_doc:  # all trees count as seen: one evaluation serves both
        gt = stem_table(gt_doc, gt_source, "observed")
        ev = evaluate(gt, obs, cfg)
        blank_absent(ev.metrics, gt_doc)
        return Scores(ev, ev, gt, gt)
    gt_all = stem_table(gt_doc, gt_source, "ground_truth")
    gt_seen = stem_table(seen_truth(gt_doc), gt_source, "ground_truth")
    scores = Scores(evaluate(gt_all, obs, cfg), evaluate(gt_seen, obs, cfg), gt_all, gt_seen)
    return scores


def blank_absent(metrics: dict[str, Any], gt_doc: dict[str, Any]) -> None:
    """Metrics whose inputs a field inventory lacks become None (absent, not zero): its
    missing columns', and the errors no matched pair had both values for."""
    from tcf_hil.recording.inventory import absent_metrics

    for key in absent_metrics(gt_doc):
        metrics[key] = None
    if metrics.get("evaluation_score_percent", 0) is None:  # no classes: no EM either
        metrics["em"] = None
    if "inventory" in gt_doc:
        for name in ("height", "dbh", "maxcurve"):
            if not metrics[f"{name}_pairs"]:
                metrics[f"{name}_rmse_m"] = metrics[f"{name}_bias_m"] = None


def empty_forest() -> StemTable:
    return stem_table({"objects": []}, "<no publication>", "observed")
