"""One cell of an experiment grid (forest x mode x seed x SIC) and the row it gives.

A :class:`Cell` is small and self-contained (it carries the fully resolved scenario as TOML
text), so a worker anywhere rebuilds the forest and the scene from it; nothing large crosses
the network. :func:`run_cell` never raises: a failure becomes a row with ``status = failed``
and the error, so one broken cell cannot stop a sweep.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import subprocess
import sys
import time
import tomllib
import traceback
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tcf_hil.evaluation import LABELS, EvalConfig, Evaluation, weighted_score
from tcf_hil.scenario import Scenario, scenario_from_dict, scenario_to_toml

SAMPLED = "sampled"
"""The pseudo mode of the paper's Experiments 1 and 4 (Table 9): stem surfaces sampled at
1000 points per stem, no lidar and no wire."""

WEIGHTINGS: dict[str, tuple[float, float, float, float]] = {
    "w111": (1.0, 1.0, 1.0, 1.0), "w211": (2.0, 1.0, 1.0, 1.0), "w121": (1.0, 2.0, 1.0, 1.0)}
"""Experiment 5's W:x-y-z (weights of S, C and N; X, which the paper does not weight, 1)."""

METRICS: tuple[tuple[str, str], ...] = (
    ("wc", "evaluation score wc = weighted diag(EM) / EM, % (the paper's evaluation score)"),
    ("quality_error_percent", "matched stems whose class differs, %"),
    ("rmse_quality", "RMSE of the class code (S=1, C=2, X=3) over matched stems"),
    ("total_matches", "observed stems matched to a ground-truth stem (within 1 m)"),
    ("quality_correct_percent", "matched stems with the right class, %"),
    ("correct_matches", "matched stems with the right class"),
    ("wrong_matches", "matched stems with the wrong class"),
    ("missed", "ground-truth stems with no observed stem"),
    ("false_positives", "observed stems with no ground-truth stem"),
    ("completeness", "matches / ground-truth stems"),
    ("correctness", "matches / observed stems"),
    ("f1", "harmonic mean of completeness and correctness"),
    ("accuracy_percent", "diagonal of the EM's S/C/X block / all EM entries, % (Table 6)"),
    ("position_rmse_m", "horizontal position error of matched stems, RMSE"),
    ("height_rmse_m", "height error of matched stems, RMSE"),
    ("dbh_rmse_m", "DBH error of matched stems, RMSE"),
    ("maxcurve_rmse_m", "maximum-curvature error of matched stems, RMSE"),
)
_METRIC_KEY = {"wc": "evaluation_score_percent"}

COLUMNS: tuple[tuple[str, str], ...] = (
    ("cell", "cell id: forest-mode-sSEED-SIC"),
    ("forest", "scenario name"),
    ("mode", "lidar mode (512x10, 1024x10, 2048x10, ...) or 'sampled' (no lidar, Table 9)"),
    ("seed", "scenario seed: forest layout, shapes and noise"),
    ("sic", "'reference' or the SIC command"),
    ("preset", "reference SIC preset (field, tuned or paper); empty for another SIC"),
    ("profile", "lidar packet profile"),
    ("backend", "ray backend: auto (Embree where it exists), embree, open3d or trimesh"),
    ("sensor", "sensor physics preset of the scenario's [sensor] (os0-64-rev7, ideal, ...)"),
    ("passes", "passes along the strip road"),
    ("status", "ok or failed"),
    ("error", "why the cell failed (one line); empty when ok"),
    ("stems", "ground-truth stems in the plot"),
    ("stems_seen", "ground-truth stems with at least one lidar return"),
    ("observed", "stems in the SIC's final forest"),
    *((f"all_{k}", f"against all trees: {d}") for k, d in METRICS),
    *((f"seen_{k}", f"against the seen trees only: {d}") for k, d in METRICS),
    *((f"wc_{w}", f"wc against all trees with Experiment 5's weights {w[1]}-{w[2]}-{w[3]} "
       "(S-C-N)") for w in WEIGHTINGS),
    ("frames", "lidar frames in the run"),
    ("sim_s", "simulated seconds of track"),
    ("emulator_s", "emulator seconds (raycast and packet encoding; sampling for 'sampled')"),
    ("emulator_x_realtime", "sim_s / emulator_s"),
    ("sic_ms_p50", "SIC milliseconds per frame, median (decode, pose, map)"),
    ("sic_ms_p99", "SIC milliseconds per frame, 99th percentile"),
    ("stem_s", "SIC seconds in the stem algorithm"),
    ("cell_s", "wall seconds of the whole cell"),
    ("worker", "host:pid that ran the cell"),
    ("frames_from", "where the lidar frames came from: 'store' (the render store: a cell of "
     "the same scene rendered them; emulator_s is then reading), 'rendered', or empty"),
)
"""results.csv, in order: (column, meaning). A stable contract; append, never reorder."""

COLUMN_NAMES = tuple(c for c, _ in COLUMNS)


@dataclass(frozen=True)
class Cell:
    forest: str  # the scenario's name
    mode: str
    seed: int
    scenario_toml: str  # fully resolved, so a remote worker needs no files
    sic: str = "reference"
    preset: str = "field"
    profile: str = "RNG19_RFL8_SIG16_NIR16"
    backend: str = "auto"
    speed: float = 1.0  # another SIC runs live at this pace
    max_frames: int | None = None
    tag: str = ""  # extra id part (e.g. passes) when forests share a name
    keep_pcap: bool = False  # a SIC command's run keeps its lidar.pcap (GBs on big grids)

    @property
    def id(self) -> str:
        if self.sic == "reference":
            who = self.preset
        else:
            who = "sic-" + hashlib.sha1(self.sic.encode()).hexdigest()[:8]
        parts = [self.forest, self.tag, self.mode, f"s{self.seed}", who]
        return "-".join(p for p in parts if p)

    def scenario(self) -> Scenario:
        return scenario_from_dict(tomllib.loads(self.scenario_toml), f"cell {self.id}")


def make_cell(scn: Scenario, mode: str, **kw: Any) -> Cell:
    return Cell(forest=scn.name, mode=mode, seed=scn.seed, scenario_toml=scenario_to_toml(scn),
                **kw)


@dataclass
class CellResult:
    row: dict[str, Any]
    artifacts: dict[str, Any]  # small documents: forest.json, score.json (KB, not MB)


def _metrics(prefix: str, ev: Evaluation) -> dict[str, Any]:
    m = ev.metrics
    return {f"{prefix}_{k}": m[_METRIC_KEY.get(k, k)] for k, _ in METRICS}


def _score_row(all_ev: Evaluation, seen_ev: Evaluation) -> dict[str, Any]:
    row = {**_metrics("all", all_ev), **_metrics("seen", seen_ev)}
    for w, weights in WEIGHTINGS.items():
        cfg = replace(all_ev.config, weights=weights)
        row[f"wc_{w}"] = weighted_score(all_ev.em, cfg)
    return row


def _base_row(cell: Cell, scn: Scenario) -> dict[str, Any]:
    from tcf_hil.world.scene import resolve_backend

    row: dict[str, Any] = dict.fromkeys(COLUMN_NAMES, "")
    row.update(cell=cell.id, forest=cell.forest, mode=cell.mode, seed=cell.seed, sic=cell.sic,
               preset=cell.preset if cell.sic == "reference" else "", profile=cell.profile,
               backend=resolve_backend(cell.backend)[0], sensor=scn.sensor.preset,
               passes=scn.track.passes,
               worker=f"{socket.gethostname()}:{os.getpid()}")
    return row


def run_cell(cell: Cell, out_dir: str | None = None,
             progress: Callable[[int, int], None] | None = None) -> CellResult:
    """Run one cell; never raises (a failure is a row with its error). ``out_dir`` is only
    needed by a SIC command (its run directory; on the worker's disk)."""
    t0 = time.perf_counter()
    try:
        scn = cell.scenario()
        row = _base_row(cell, scn)
        if cell.mode == SAMPLED:
            arts = _sampled(cell, scn, row)
        elif cell.sic == "reference":
            arts = _reference(cell, scn, row, progress)
        else:
            arts = _command(cell, scn, row, out_dir)
        row["status"] = "ok"
    except Exception as err:  # the sweep goes on; the row says what happened
        row = dict.fromkeys(COLUMN_NAMES, "")
        row.update(cell=cell.id, forest=cell.forest, mode=cell.mode, seed=cell.seed,
                   sic=cell.sic, preset=cell.preset, status="failed",
                   worker=f"{socket.gethostname()}:{os.getpid()}")
        msg = f"{type(err).__name__}: {err}".replace("\n", " ")[:500]
        row["error"] = msg
        arts = {"traceback": traceback.format_exc()}
    row["cell_s"] = round(time.perf_counter() - t0, 3)
    return CellResult(row, arts)


def _em_doc(ev: Evaluation) -> dict[str, Any]:
    return {"labels": list(LABELS), "matrix": np.asarray(ev.em).tolist()}


def _reference(cell: Cell, scn: Scenario, row: dict[str, Any],
               progress: Callable[[int, int], None] | None) -> dict[str, Any]:
    from tcf_hil.experiments.offline import run_offline

    # cells that differ only in the SIC share one render: the first keeps it in the store
    r = run_offline(scn, mode=cell.mode, profile=cell.profile, backend=cell.backend,
                    preset=cell.preset, max_frames=cell.max_frames, progress=progress,
                    render="fill")
    row.update(_score_row(r.scores.all, r.scores.seen))
    row.update(stems=len(r.ground_truth["objects"]), stems_seen=r.stems_seen,
               observed=len(r.forest_doc["objects"]), frames=r.frames,
               sim_s=round(r.sim_seconds, 3), emulator_s=round(r.emulator_s, 3),
               emulator_x_realtime=round(r.sim_seconds / max(r.emulator_s, 1e-9), 3),
               sic_ms_p50=round(r.sic_ms(50), 3), sic_ms_p99=round(r.sic_ms(99), 3),
               stem_s=round(r.stem_s, 3), frames_from="store" if r.from_store else "rendered")
    return {"forest.json": r.forest_doc, "score.json": r.scores.summary(),
            "em_all": _em_doc(r.scores.all), "em_seen": _em_doc(r.scores.seen)}


def _sampled(cell: Cell, scn: Scenario, row: dict[str, Any]) -> dict[str, Any]:
    from tcf_hil.evaluation.scoring import score_forest
    from tcf_hil.recording.stems_json import stem_table
    from tcf_hil.sic import identify_stems, stem_params
    from tcf_hil.world.forest import generate_forest, ground_truth
    from tcf_hil.world.forest.sampling import sample_surfaces

    t0 = time.perf_counter()
    forest = generate_forest(scn)
    cloud = sample_surfaces(forest)
    t1 = time.perf_counter()
    prm = stem_params(cell.preset, curve_threshold_m=scn.stems.curve_threshold_m,
                      other_threshold_m=scn.stems.other_threshold_m,
                      scene_centre=tuple(scn.plot.origin_m[:2]))
    doc = json.loads(json.dumps(identify_stems(cloud.xyz, prm)))
    t2 = time.perf_counter()
    gt = ground_truth(forest)
    for o in gt["objects"]:
        o["returns"] = 1  # every stem is sampled: all trees are seen
    sc = score_forest(gt, stem_table(doc, "<stem algorithm>", "observed"))
    row.update(_score_row(sc.all, sc.seen))
    row.update(stems=len(gt["objects"]), stems_seen=len(gt["objects"]),
               observed=len(doc["objects"]), frames=0, sim_s=0.0,
               emulator_s=round(t1 - t0, 3), stem_s=round(t2 - t1, 3))
    return {"forest.json": doc, "score.json": sc.summary(), "em_all": _em_doc(sc.all),
            "em_seen": _em_doc(sc.seen)}


def _command(cell: Cell, scn: Scenario, row: dict[str, Any], out_dir: str | None
             ) -> dict[str, Any]:
    """Another SIC: a live ``tcf-hil run`` in a subprocess (UDP has no flow control, so a
    program that reads sockets runs paced, at ``cell.speed``), on its own CAN server."""

    if out_dir is None:
        raise ValueError("a SIC command needs the cell's output directory")
    cdir = Path(out_dir)
    cdir.mkdir(parents=True, exist_ok=True)
    toml = cdir / "scenario.toml"
    toml.write_text(cell.scenario_toml, "utf-8")
    run_dir = cdir / "run"
    # each run owns its CAN bus, sensor address and UDP ports (tcf_hil.devices.endpoints)
    cmd = [sys.executable, "-m", "tcf_hil", "run", str(toml), "--sic", cell.sic,
           "--mode", cell.mode, "--profile", cell.profile, "--seed", str(cell.seed),
           "--speed", f"{cell.speed:g}", "--out", str(run_dir)]
    if cell.max_frames:
        period = 1.0 / int(cell.mode.split("x")[1])
        cmd += ["--duration", f"{cell.max_frames * period:g}"]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    (cdir / "run.log").write_text(p.stdout + p.stderr, "utf-8")
    score_path = run_dir / "score.json"
    if not score_path.exists():
        last = (p.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"tcf-hil run exited {p.returncode}: {last}")
    score = json.loads(score_path.read_text("utf-8"))
    if p.returncode != 0 or "all_trees" not in score:
        raise RuntimeError(f"the SIC failed (tcf-hil run exited {p.returncode}): "
                           f"{score.get('message') or score.get('status')}")
    if not cell.keep_pcap:
        (run_dir / "lidar.pcap").unlink(missing_ok=True)
    man = json.loads((run_dir / "manifest.json").read_text("utf-8"))
    vis = json.loads((run_dir / "visibility.json").read_text("utf-8"))
    a, s = score["all_trees"], score["seen_trees"]
    for prefix, m in (("all", a), ("seen", s)):
        for k, _ in METRICS:
            row[f"{prefix}_{k}"] = m[_METRIC_KEY.get(k, k)]
    em = np.array(a["em"]["matrix"], dtype=np.int64)
    c = a["config"]
    base = EvalConfig(match=c["match"], max_distance_m=float(c["max_distance_m"]),
                      weights=tuple(c["weights"]), credits=tuple(c["credits"]))
    for w, weights in WEIGHTINGS.items():
        row[f"wc_{w}"] = weighted_score(em, replace(base, weights=weights))
    frames = int(vis.get("frames", 0))
    row.update(stems=a["n_ground_truth"], stems_seen=vis.get("stems_seen", ""),
               observed=a["n_observed"], frames=frames,
               sim_s=round(frames / int(cell.mode.split("x")[1]), 3))
    return {"score.json": {k: score[k] for k in ("all_trees", "seen_trees") if k in score},
            "em_all": a["em"], "em_seen": s["em"], "manifest": {"status": man.get("status")}}


def with_passes(scn: Scenario, n: int, offset: float | None, roads: int) -> Scenario:
    """``n`` passes over a forest cut by ``roads`` strip roads (the same for every n)."""
    off = scn.track.pass_offset_m if offset is None else offset
    tr = replace(scn.track, passes=n, pass_offset_m=off)
    roads = max(roads, scn.distribution.strip_roads) if off > 0 else 1
    dist = replace(scn.distribution, strip_roads=roads)
    return replace(scn, track=tr, distribution=dist)
