"""The run report: one self-contained HTML file (figures inlined as PNG data URIs) with the
scores against all trees and against the trees the sensor saw, the EM heatmaps, the matched
positions, the score timeline and the run's figures."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tcf_hil._io import write_bytes_atomic
from tcf_hil.evaluation import LABELS, ROWS, show_metric
from tcf_hil.plots import _pyplot, em_heatmap, figure_png, matched_positions

if TYPE_CHECKING:
    from tcf_hil.run import RunResult


def _img(png: bytes, alt: str) -> str:
    return (f'<img alt="{html.escape(alt)}" src="data:image/png;base64,'
            f'{base64.b64encode(png).decode()}">')


def timeline_png(timeline: list[dict[str, Any]]) -> bytes:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.0, 3.2))
    t = [r["arrival_s"] for r in timeline]
    nan = float("nan")  # (no class in a field inventory: no wc)
    ax.plot(t, [nan if r["wc_all"] is None else r["wc_all"] for r in timeline], "o-",
            label="wc, all trees")
    ax.plot(t, [nan if r["wc_seen"] is None else r["wc_seen"] for r in timeline], "s-",
            label="wc, seen trees")
    ax.set_xlabel("publication arrival, s since the run started")
    ax.set_ylabel("evaluation score, %")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    return figure_png(fig)


def _metrics_rows(all_m: dict[str, Any], seen_m: dict[str, Any]) -> str:
    rows = []
    for key, label, fmt in ROWS:
        rows.append(f"<tr><td>{html.escape(label)}</td><td>{show_metric(fmt, all_m[key])}"
                    f"</td><td>{show_metric(fmt, seen_m[key])}</td></tr>")
    rows.append(f"<tr><td>Ground-truth trees</td><td>{all_m['n_ground_truth']}</td>"
                f"<td>{seen_m['n_ground_truth']}</td></tr>")
    return "\n".join(rows)


def _em_table(em: Any) -> str:
    head = "".join(f"<th>{c}</th>" for c in LABELS)
    body = "".join("<tr><th>" + r + "</th>" + "".join(f"<td>{v}</td>" for v in em[i]) + "</tr>"
                   for i, r in enumerate(LABELS))
    return f"<table class=em><tr><th>gt \\ obs</th>{head}</tr>{body}</table>"


WC = "{:.1f} %"


def write_report(path: Path, result: RunResult) -> None:
    sc = result.scores
    assert sc is not None and result.out is not None
    m = result.manifest.to_dict()
    all_m, seen_m = sc.all.metrics, sc.seen.metrics
    figs = [
        _img(em_heatmap(sc.all.em, LABELS, f"EM, all trees: wc = "
                        f"{show_metric(WC, all_m['evaluation_score_percent'])}"),
             "EM all trees"),
        _img(em_heatmap(sc.seen.em, LABELS, f"EM, seen trees: wc = "
                        f"{show_metric(WC, seen_m['evaluation_score_percent'])}"),
             "EM seen trees"),
    ]
    ems = (f'<div style="display:flex;gap:2em">{_em_table(sc.all.em)}'
           f'{_em_table(sc.seen.em)}</div>\n{figs[0]}{figs[1]}')
    if all_m["evaluation_score_percent"] is None:
        ems = "<p>The ground truth (a field inventory) has no classes: no EM.</p>"
    inv_note = (" The ground truth here is a field inventory, which knows nothing of what the "
                "sensor saw: both columns score against every tree."
                if "inventory" in sc.gt_all.doc else "")
    latest = _latest_obs(result)
    pos = _img(matched_positions(sc.gt_all.xyz[:, :2], latest, sc.all.pairs,
                                 f"{len(sc.all.pairs)} matched of {len(sc.gt_all)} ground "
                                 f"truth / {len(latest)} observed"), "matched positions")
    tl = _img(timeline_png(result.timeline), "score timeline") if result.timeline else \
        "<p>No valid publication.</p>"
    score_doc = json.loads((result.out / "score.json").read_text())
    bad = "".join(f"<li>{html.escape(p['file'])}: {html.escape(str(p['error']))}</li>"
                  for p in score_doc["invalid_publications"])
    faults = _faults_section(score_doc.get("faults"), all_m, seen_m)
    title = f"tcf-hil run: {m.get('scenario')} {m.get('mode')}"
    doc = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #ccc; padding: 3px 8px; text-align: right; }}
td:first-child {{ text-align: left; }}
.em td {{ min-width: 3em; }}
img {{ max-width: 100%; }}
pre {{ background: #f6f6f6; padding: 1em; overflow-x: auto; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>Status: <b>{html.escape(result.status)}</b> {html.escape(result.message)}</p>
<h2>Scores</h2>
<p>"All trees" scores against every ground-truth stem; "seen trees" only against the stems
the sensor returned at least one point from, so the difference is what the sensor could not
see, and what remains is what the algorithm missed.{inv_note}</p>
<table><tr><th>metric</th><th>all trees</th><th>seen trees</th></tr>
{_metrics_rows(all_m, seen_m)}
</table>
{faults}
<h3>Evaluation matrix (rows ground truth, columns observed)</h3>
{ems}
<h2>Matched positions</h2>
{pos}
<h2>Score timeline</h2>
{tl}
<h2>Invalid publications</h2>
<ul>{bad or "<li>none</li>"}</ul>
<h2>Run</h2>
<pre>{html.escape(json.dumps(m, indent=2))}</pre>
</body></html>
"""
    write_bytes_atomic(path, doc.encode("utf-8"))


def _faults_section(faults: dict[str, Any] | None, all_m: dict[str, Any],
                    seen_m: dict[str, Any]) -> str:
    """The injected faults beside the score they led to (empty when none were asked)."""
    if faults is None:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{v['count']}</td><td>{v['first_s']:.3f}</td>"
        f"<td>{v['last_s']:.3f}</td></tr>" for k, v in faults.items())
    return f"""<h2>Injected faults</h2>
<p>This run injected the faults below (every event is in <code>faults.jsonl</code>, with its
time in seconds after the track start). With them the SIC scored wc =
{show_metric(WC, all_m['evaluation_score_percent'])} (all trees) and
{show_metric(WC, seen_m['evaluation_score_percent'])} (seen trees).</p>
<table><tr><th>fault</th><th>count</th><th>first, s</th><th>last, s</th></tr>
{rows or '<tr><td colspan=4>none happened (rates too low or times beyond the run)</td></tr>'}
</table>"""


def _latest_obs(result: RunResult) -> Any:
    import numpy as np

    from tcf_hil._io import read_json
    from tcf_hil.stems_json import stem_table

    assert result.out is not None
    n = json.loads((result.out / "score.json").read_text()).get("scored_publication")
    if n is None:
        return np.zeros((0, 2))
    doc = read_json(result.out / "sic" / f"{n:04d}.json")
    return stem_table(doc, f"sic/{n:04d}.json", "observed").xyz[:, :2]
