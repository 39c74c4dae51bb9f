"""Human-readable tables and the evaluation plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.table import Table

from tcf_hil._io import ensure_dir, write_bytes_atomic
from tcf_hil._plots import em_heatmap, matched_positions
from tcf_hil.evaluation._metrics import LABELS, Evaluation
from tcf_hil.recording.stems_json import StemTable

ROWS: tuple[tuple[str, str, str], ...] = (
    ("evaluation_score_percent", "Evaluation score (wc)", "{:.1f} %"),
    ("total_matches", "Total matches", "{}"),
    ("quality_correct_percent", "Quality correct", "{:.1f} %"),
    ("quality_error_percent", "Quality error", "{:.1f} %"),
    ("rmse_quality", "RMSE quality", "{:.3f}"),
    ("correct_matches", "Correct quality matches", "{}"),
    ("wrong_matches", "Wrong quality matches", "{}"),
    ("missed", "Missed (ground truth unmatched)", "{}"),
    ("false_positives", "False positives", "{}"),
    ("completeness", "Completeness", "{:.3f}"),
    ("correctness", "Correctness", "{:.3f}"),
    ("f1", "F1", "{:.3f}"),
    ("position_rmse_m", "Position RMSE", "{:.3f} m"),
    ("height_rmse_m", "Height RMSE", "{:.3f} m"),
    ("dbh_rmse_m", "DBH RMSE", "{:.4f} m"),
    ("maxcurve_rmse_m", "Maxcurve RMSE", "{:.4f} m"),
)


def show_metric(fmt: str, value: Any) -> str:
    """A metric as the tables show it: "absent" where its inputs were (None)."""
    return "absent" if value is None else fmt.format(value)


def metrics_table(ev: Evaluation, title: str = "Evaluation") -> Table:
    """The main metrics and the EM as a rich table."""
    t = Table(title=title, show_header=True, header_style="bold")
    t.add_column("metric")
    t.add_column("value", justify="right")
    for key, label, fmt in ROWS:
        t.add_row(label, show_metric(fmt, ev.metrics[key]))
    em = ev.em
    t.add_section()
    if ev.metrics["evaluation_score_percent"] is None:  # no ground-truth classes
        t.add_row("EM rows=gt, cols=obs", "absent")
        return t
    t.add_row("EM rows=gt, cols=obs", "  ".join(f"{c:>5}" for c in LABELS))
    for i, r in enumerate(LABELS):
        t.add_row(f"  {r}", "  ".join(f"{v:>5}" for v in em[i]))
    return t


def write_plots(ev: Evaluation, gt: StemTable, obs: StemTable, out_dir: str | Path,
                title: str = "") -> list[Path]:
    """Write ``em_heatmap.png`` and ``matched_positions.png`` into ``out_dir``."""
    out = Path(out_dir)
    ensure_dir(out)
    wc = ev.metrics["evaluation_score_percent"]
    head = f"{title}: " if title else ""
    a = out / "em_heatmap.png"
    write_bytes_atomic(a, em_heatmap(ev.em, LABELS, f"{head}EM, wc = "
                                                    f"{show_metric('{:.1f} %', wc)}"))
    b = out / "matched_positions.png"
    write_bytes_atomic(b, matched_positions(gt.xyz[:, :2], obs.xyz[:, :2], ev.pairs,
                                            f"{head}{len(ev.pairs)} matched of {len(gt)} "
                                            f"ground truth / {len(obs)} observed"))
    return [a, b]
