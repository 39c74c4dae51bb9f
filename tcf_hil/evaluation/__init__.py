"""Experimental evaluation (EE): matching, evaluation matrix, weighted score, metrics, plots,
and the scoring of a SIC's forest against the truth (:mod:`.scoring`: all trees, the trees
the sensor saw, bands of distance from the track), done once per run and handed to the
report and the export.

May import the recordings (stems documents) and the small shared helpers; never the world's
generators, the devices, a run or the results.
"""

from tcf_hil.evaluation._match import candidate_pairs, match
from tcf_hil.evaluation._metrics import (
    CASES,
    LABELS,
    EvalConfig,
    Evaluation,
    default_case_table,
    evaluate,
    evaluation_matrix,
    weighted_score,
)
from tcf_hil.evaluation._report import ROWS, metrics_table, show_metric, write_plots

__all__ = [
    "CASES",
    "LABELS",
    "ROWS",
    "EvalConfig",
    "Evaluation",
    "candidate_pairs",
    "default_case_table",
    "evaluate",
    "evaluation_matrix",
    "match",
    "metrics_table",
    "show_metric",
    "weighted_score",
    "write_plots",
]
