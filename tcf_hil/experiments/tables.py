"""The paper's tables from a sweep's records: Table 9/10 layout with the mean and 95 %
interval over seeds, EM heatmap grids like Tables 7/8, the weighting experiment (Table 11),
and what the paper's text reports beside ours."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tcf_hil._io import ensure_dir, write_bytes_atomic
from tcf_hil.experiments.cells import SAMPLED, WEIGHTINGS
from tcf_hil.experiments.experiment1 import PAPER_TABLE6

TABLE_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("quality_error_percent", "Quality error %", 1),
    ("rmse_quality", "RMSE quality", 3),
    ("total_matches", "Total matches", 1),
    ("quality_correct_percent", "Quality correct %", 1),
    ("wc", "Evaluation score %", 1),
    ("correct_matches", "Correct quality matches", 1),
    ("wrong_matches", "Wrong quality matches", 1),
)
"""The columns of the paper's Tables 9 and 10: (metric, heading, decimals)."""

PAPER_TEXT: dict[tuple[str, str | None], str] = {
    ("forest-i", "512x10"): "I/II best wc 63.6-83.8 %, quality error 16.6-30.0 % (512/1024)",
    ("forest-i", "1024x10"): "I/II best wc 63.6-83.8 %, quality error 16.6-30.0 % (512/1024)",
    ("forest-ii", "512x10"): "I/II best wc 63.6-83.8 %, quality error 16.6-30.0 % (512/1024)",
    ("forest-ii", "1024x10"): "I/II best wc 63.6-83.8 %, quality error 16.6-30.0 % (512/1024)",
    ("forest-i", "2048x10"): "declines at 2048 (rolling terrain)",
    ("forest-iii", "512x10"): "wc 72.0 %",
    ("forest-iv", "2048x10"): "wc 47.1 %",
    ("forest-v", "2048x10"): "even stands: best wc 75.0 % (at 2048)",
    ("forest-ix", "2048x10"): "even stands: best wc 75.0 % (at 2048)",
    ("forest-vi", None): "uneven/clustered stands: wc 34.9-46.7 %",
    ("forest-vii", None): "uneven/clustered stands: wc 34.9-46.7 %",
    ("forest-viii", None): "uneven/clustered stands: wc 34.9-46.7 %",
    ("forest-x", None): "uneven/clustered stands: wc 34.9-46.7 %",
}
"""What the paper's text states about its Table 10 (section 3, Experiment 4). The table's
cells themselves are not in the text we hold; these sentences are all it gives."""

PAPER_WEIGHTING = {"w111": 70.0, "w211": 63.6, "w121": 73.7}
"""Experiment 5 (Table 11): the credit percentage of the paper's example EM per weighting."""


def ci95(values: Sequence[float]) -> tuple[float, float]:
    """(mean, half-width of the 95 % t interval); the half-width is nan below two values."""
    v = np.asarray([x for x in values if x is not None and x != ""], dtype=np.float64)
    if len(v) == 0:
        return math.nan, math.nan
    if len(v) < 2:
        return float(v[0]), math.nan
    from scipy.stats import t

    return float(v.mean()), float(t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))


def _fmt(mean: float, half: float, dec: int) -> str:
    if math.isnan(mean):
        return "—"
    return f"{mean:.{dec}f}" if math.isnan(half) else f"{mean:.{dec}f} ± {half:.{dec}f}"


def _key(r: dict[str, Any]) -> tuple[str, str, str, str]:
    return (str(r["forest"]), str(r["mode"]), str(r["sic"]), str(r.get("preset", "")))


def _groups(records: Sequence[dict[str, Any]]) -> dict[tuple[str, str, str, str],
                                                        list[dict[str, Any]]]:
    g: dict[tuple[str, str, str, str], list[dict[str, Any]]] = {}
    for rec in records:
        r = rec["row"]
        if r.get("status") == "ok":
            g.setdefault(_key(r), []).append(rec)
    return g


def _paper(forest: str, mode: str) -> str:
    if mode == SAMPLED:
        p = PAPER_TABLE6.get(forest)
        return f"Table 6 accuracy {p['accuracy_percent']:.1f} %" if p else ""
    return PAPER_TEXT.get((forest, mode)) or PAPER_TEXT.get((forest, None)) or ""


def summary_rows(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (forest, mode, SIC): mean and 95 % half-width of every table metric,
    against all and against seen trees."""
    out = []
    for (forest, mode, sic, preset), recs in _groups(records).items():
        rows = [r["row"] for r in recs]
        s: dict[str, Any] = {"forest": forest, "mode": mode, "sic": sic, "preset": preset,
                             "seeds": len(rows)}
        for scope in ("all", "seen"):
            for k, _h, _d in TABLE_COLUMNS:
                m, h = ci95([r[f"{scope}_{k}"] for r in rows])
                s[f"{scope}_{k}_mean"], s[f"{scope}_{k}_ci95"] = m, h
        for k in ("stems", "stems_seen", "observed", "all_f1", "all_position_rmse_m",
                  "all_dbh_rmse_m", *(f"wc_{w}" for w in WEIGHTINGS)):
            m, h = ci95([r[k] for r in rows])
            s[f"{k}_mean"], s[f"{k}_ci95"] = m, h
        s["paper_text"] = _paper(forest, mode)
        out.append(s)
    return out


def _md_table(head: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in body]
    return "\n".join(lines) + "\n"


def quality_table(summary: Sequence[dict[str, Any]], *, sampled: bool) -> str:
    """Table 9 (sampled) or Table 10 (lidar) layout, against all trees with the seen-tree
    score and the paper's text beside."""
    body = []
    for s in summary:
        if (s["mode"] == SAMPLED) != sampled:
            continue
        cells = [s["forest"], s["mode"], s["sic"] if s["sic"] != "reference"
                 else f"reference/{s['preset']}", str(s["seeds"])]
        cells += [_fmt(s[f"all_{k}_mean"], s[f"all_{k}_ci95"], d) for k, _h, d in TABLE_COLUMNS]
        cells += [_fmt(s["seen_wc_mean"], s["seen_wc_ci95"], 1),
                  f"{s['stems_seen_mean']:.0f}/{s['stems_mean']:.0f}", s["paper_text"] or "—"]
        body.append(cells)
    head = ["Forest", "Mode", "SIC", "Seeds", *(h for _k, h, _d in TABLE_COLUMNS),
            "Evaluation score %, seen trees", "Seen/all stems", "Paper (text)"]
    return _md_table(head, body)


def weighting_table(summary: Sequence[dict[str, Any]]) -> str:
    body = [[s["forest"], s["mode"], *(_fmt(s[f"wc_{w}_mean"], s[f"wc_{w}_ci95"], 1)
                                      for w in WEIGHTINGS)] for s in summary]
    body.append(["paper's example (Table 11)", "", *(f"{PAPER_WEIGHTING[w]:.1f}"
                                                    for w in WEIGHTINGS)])
    return _md_table(["Forest", "Mode", "W 1-1-1 %", "W 2-1-1 %", "W 1-2-1 %"], body)


def summary_csv(summary: Sequence[dict[str, Any]]) -> bytes:
    buf = io.StringIO()
    if summary:
        w = csv.DictWriter(buf, fieldnames=list(summary[0]), lineterminator="\n")
        w.writeheader()
        for s in summary:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in s.items()})
    return buf.getvalue().encode()


def _em_sum(recs: Sequence[dict[str, Any]], key: str = "em_all") -> np.ndarray | None:
    ems = [np.asarray(r[key]["matrix"], dtype=np.float64) for r in recs if key in r]
    return np.sum(ems, axis=0) if ems else None


def heatmap_grids(records: Sequence[dict[str, Any]], out: Path) -> list[Path]:
    """One PNG per forest and SIC: the EM (summed over seeds) of every mode side by side,
    like the paper's Tables 7 and 8."""
    from tcf_hil._plots import figure_png, pyplot
    from tcf_hil.evaluation import LABELS

    plt = pyplot()
    g = _groups(records)
    by_forest: dict[tuple[str, str, str], list[tuple[str, list[dict[str, Any]]]]] = {}
    for (forest, mode, sic, preset), recs in g.items():
        by_forest.setdefault((forest, sic, preset), []).append((mode, recs))
    paths = []
    ensure_dir(out)
    for (forest, sic, preset), modes in by_forest.items():
        modes.sort(key=lambda m: (m[0] != SAMPLED, _mode_order(m[0])))
        fig, axes = plt.subplots(1, len(modes), figsize=(4.2 * len(modes), 4.0), squeeze=False)
        for ax, (mode, recs) in zip(axes[0], modes, strict=True):
            em = _em_sum(recs)
            if em is None:
                continue
            ax.imshow(em, cmap="viridis")
            for i in range(em.shape[0]):
                for j in range(em.shape[1]):
                    ax.text(j, i, f"{em[i, j]:.0f}", ha="center", va="center",
                            color="white" if em[i, j] < em.max() / 2 else "black", fontsize=9)
            ax.set_xticks(range(len(LABELS)), LABELS)
            ax.set_yticks(range(len(LABELS)), LABELS)
            wc = np.mean([r["row"]["all_wc"] for r in recs])
            ax.set_title(f"{mode}: wc {wc:.1f} % ({len(recs)} seed{'s' * (len(recs) > 1)})",
                         fontsize=10)
            ax.set_xlabel("observed")
            ax.set_ylabel("ground truth")
        who = preset if sic == "reference" else "sic"
        fig.suptitle(f"{forest}, {who}: evaluation matrix by lidar mode (all trees)")
        fig.tight_layout()
        p = out / f"{forest}-{who}.png"
        write_bytes_atomic(p, figure_png(fig))
        paths.append(p)
    return paths


def weighting_figure(records: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Table 11: the EM of the first group weighted by W 1-1-1, 2-1-1 and 1-2-1."""
    from tcf_hil._plots import figure_png, pyplot
    from tcf_hil.evaluation import LABELS

    g = _groups(records)
    if not g:
        return None
    (forest, mode, _sic, _p), recs = next(iter(g.items()))
    em = _em_sum(recs)
    if em is None:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12.6, 4.0))
    for ax, (w, weights) in zip(axes, WEIGHTINGS.items(), strict=True):
        wem = em * np.asarray(weights)[:, None]
        ax.imshow(wem, cmap="magma_r")
        for i in range(wem.shape[0]):
            for j in range(wem.shape[1]):
                ax.text(j, i, f"{wem[i, j]:.0f}", ha="center", va="center", fontsize=9,
                        color="white" if wem[i, j] > wem.max() / 2 else "black")
        ax.set_xticks(range(len(LABELS)), LABELS)
        ax.set_yticks(range(len(LABELS)), LABELS)
        score = np.mean([r["row"][f"wc_{w}"] for r in recs])
        ax.set_title(f"W {w[1]}-{w[2]}-{w[3]}: {score:.1f} %")
    fig.suptitle(f"{forest}, {mode}: weighting the credits (Experiment 5)")
    fig.tight_layout()
    write_bytes_atomic(path, figure_png(fig))
    return path


def _mode_order(mode: str) -> tuple[int, int]:
    try:
        c, f = mode.split("x")
        return int(c), int(f)
    except ValueError:
        return 0, 0


def write_tables(records: Sequence[dict[str, Any]], out: Path,
                 failed: Sequence[dict[str, Any]] = ()) -> dict[str, Path]:
    """summary.md (Tables 9/10, weighting, failures), summary.csv and the figures."""
    summary = sorted(summary_rows(records),
                     key=lambda s: (_forest_order(s["forest"]), s["mode"] != SAMPLED,
                                    _mode_order(s["mode"]), s["sic"], s["preset"]))
    paths = {"summary.csv": out / "summary.csv", "summary.md": out / "summary.md"}
    write_bytes_atomic(paths["summary.csv"], summary_csv(summary))
    figs = heatmap_grids(records, out / "heatmaps")
    wfig = weighting_figure(records, out / "weighting.png")
    parts = ["# Experiments on the wire: results\n",
             "Mean ± 95 % interval (Student t) over seeds; scores against **all** trees of "
             "the plot unless the column says seen trees (stems with at least one lidar "
             "return), which separates sensor limits from algorithm misses. 'Paper (text)' "
             "is what the paper's text states; its table cells are not in the text.\n"]
    if any(s["mode"] == SAMPLED for s in summary):
        parts += ["\n## Table 9 layout: sampled stems (1000 points per stem, no lidar)\n\n",
                  quality_table(summary, sampled=True)]
    if any(s["mode"] != SAMPLED for s in summary):
        parts += ["\n## Table 10 layout: on the wire\n\n", quality_table(summary, sampled=False)]
    parts += ["\n## Experiment 5: weighting the credits (all trees)\n\n",
              weighting_table(summary)]
    parts += ["\n## Figures\n\n", *(f"- heatmaps/{p.name}\n" for p in figs)]
    if wfig is not None:
        parts.append(f"- {wfig.name}\n")
    if failed:
        parts += ["\n## Failed cells\n\n",
                  _md_table(["Cell", "Error"], [[f["cell"], str(f["error"])] for f in failed])]
    write_bytes_atomic(paths["summary.md"], "".join(parts).encode())
    return paths


_ROMAN = ["i", "ii", "iii", "iv", "v", "vi", "vii", "viii", "ix", "x"]


def _forest_order(name: str) -> tuple[int, str]:
    tail = name.rsplit("-", 1)[-1]
    return (_ROMAN.index(tail) if tail in _ROMAN else 99, name)
