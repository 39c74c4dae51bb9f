"""Speed against error, measured side by side in one run: lidar mode x stem tessellation
tolerance x ray backend x reference SIC preset.

Each (mode, tolerance, backend) emulates the track once; both SIC presets read the same
packet and CAN bytes in lockstep (:func:`tcf_hil.experiments.offline.drive`), so their
timings share the machine's state. A few frames are also cast exactly
(:mod:`tcf_hil.world.analytic`) to give the range error the tessellation costs.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tcf_hil._io import ensure_dir, write_bytes_atomic, write_json_atomic
from tcf_hil.scenario import Scenario, load_scenario, with_sensor


@dataclass(frozen=True)
class BenchGrid:
    forest: str
    modes: tuple[str, ...]
    tolerances_mm: tuple[float, ...]
    backends: tuple[str, ...]
    presets: tuple[str, ...]
    frames: int | None  # None: the whole track
    error_frames: int = 2  # frames cast exactly for the range error
    sensor: str | None = None  # a sensor preset over the forest's own [sensor]
    footprints: tuple[str, ...] = ("",)  # "off", "adaptive:2", "full:4"; "": the sensor's


QUICK = BenchGrid("forest-ii", ("512x10",), (2.0, 10.0), ("embree", "open3d"),
                  ("field", "paper"), frames=100)
FULL = BenchGrid("forest-v", ("512x10", "1024x10", "2048x10"), (2.0, 10.0),
                 ("embree", "open3d"), ("field", "paper"), frames=300)

BENCH_COLUMNS = ("forest", "mode", "tolerance_mm", "backend", "preset", "sensor", "footprint",
                 "footprint_samples", "supersampled_pct", "triangles", "frames",
                 "emulator_ms_frame", "emulator_x_realtime", "range_err_p50_mm",
                 "range_err_p99_mm", "return_err_p50_mm", "return_err_p99_mm",
                 "return_bias_mm", "returns_on_stems_pct", "sic_ms_p50", "sic_ms_p99",
                 "stem_s", "stems_seen",
                 "wc_all", "wc_seen", "f1_seen", "position_rmse_m", "dbh_rmse_m",
                 "dbh_bias_m", "stems_geometry")


def backend_available(name: str) -> str | None:
    """None if the backend can be used here (``auto`` always can), else why not."""
    from tcf_hil.world.scene import BACKENDS, backend_unavailable

    return backend_unavailable(name) if name in BACKENDS else None


def _range_error(run: Any, k: int) -> np.ndarray:
    from tcf_hil.world.analytic import refine_hits

    o, d, _, _ = run.emu.rays(k)
    t, sid = run.scene.cast(o, d)
    exact, _cos = refine_hits(run.forest, o, d, t, sid)
    m = (sid > 0) & np.isfinite(exact) & (t < 50.0)
    return np.abs(t[m] - exact[m])


def parse_footprint(text: str) -> tuple[str, int | None]:
    """``"adaptive:4"`` -> ("adaptive", 4: samples per FWHM); ``"off"`` -> ("off", None);
    ``""``: the sensor's own (("", None)). Raises ValueError naming what is allowed."""
    kind, _, rays = text.strip().partition(":")
    if kind not in ("", "off", "adaptive", "edges", "full"):
        raise ValueError(f"{text!r}: footprints are off, adaptive:N, edges:N or full:N")
    try:
        n = int(rays) if rays else None
    except ValueError:
        n = 0
    if n is not None and not 1 <= n <= 16:
        raise ValueError(f"{text!r}: samples per FWHM from 1 to 16")
    return kind, n


def _with_footprint(scn: Scenario, text: str) -> Scenario:
    kind, n = parse_footprint(text)
    sensor = scn.sensor
    if kind:
        sensor = dataclasses.replace(sensor, footprint=kind)  # type: ignore[arg-type]
    if n is not None:
        sensor = dataclasses.replace(sensor, footprint_samples=n)
    return dataclasses.replace(scn, sensor=sensor)


def _return_error(run: Any, k: int) -> tuple[np.ndarray, float, float]:
    """Frame k's first returns on stems against the exact surface along each pixel's centre
    ray (m, signed: + behind it): noise, footprint and mesh together, as a user of the
    packets sees them. Also the share of stem pixels with a return, and of pixels
    supersampled."""
    from tcf_hil.world.analytic import refine_hits

    o, d, _, _ = run.emu.rays(k)
    fr = run.emu.frame(k)
    t, sid = run.scene.cast(o, d)
    exact, _cos = refine_hits(run.forest, o, d, t, sid)
    W, H = run.meta.columns, run.meta.pixels
    rng = fr.fields["RANGE"].T.reshape(-1).astype(np.float64) / 1000.0  # column-major
    on = (sid > 0) & np.isfinite(exact)
    got = on & (rng > 0)
    err = rng[got] - run.emu.n_m - exact[got]
    phys = run.emu.physics
    flagged = phys.last_flagged / (W * H) if phys is not None else 0.0
    return err, float(np.count_nonzero(got)) / max(int(np.count_nonzero(on)), 1), flagged


def run_bench(grid: BenchGrid, *, seed: int | None = None,
              say: Callable[[str], None] = lambda _s: None) -> tuple[list[dict[str, Any]],
                                                                    list[str]]:
    """Every combination of the grid; returns (rows, notes on what was skipped)."""
    from tcf_hil.devices.harvester import HarvesterModel
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.evaluation.scoring import score_forest
    from tcf_hil.experiments.offline import RUN_T0_NS, OfflineSic, drive
    from tcf_hil.recording.stems_json import stem_table

    base = with_sensor(load_scenario(grid.forest, seed=seed), grid.sensor)
    rows: list[dict[str, Any]] = []
    notes = []
    backends = []
    for b in grid.backends:
        why = backend_available(b)
        if why:
            notes.append(f"backend {b} skipped: {why}")
        else:
            backends.append(b)
    # each tolerance meshes the stems; where Embree casts round curves (bound directly),
    # one more row per mode casts them instead (tolerance 0: exact)
    from emulators.jit import jit_enabled

    curves = ["embree"] if "embree" in backends and jit_enabled() else []
    combos = [(m, t, fp, b, "mesh") for m in grid.modes for t in grid.tolerances_mm
              for fp in grid.footprints for b in backends]
    combos += [(m, 0.0, fp, b, "curves") for m in grid.modes for fp in grid.footprints
               for b in curves]
    for mode, tol, fp, backend, geometry in combos:
        stems = (dataclasses.replace(base.stems, tolerance_mm=tol, geometry="mesh")
                 if geometry == "mesh" else dataclasses.replace(base.stems, geometry="curves"))
        scn: Scenario = _with_footprint(dataclasses.replace(base, stems=stems), fp)
        say(f"{mode}, {f'{tol:g} mm' if geometry == 'mesh' else 'curves'}, "
            f"{fp or scn.sensor.footprint}, {backend}")
        run = LidarRun(scn, mode=mode, backend=backend, max_frames=grid.frames,
                       t0_ns=RUN_T0_NS, faults=False, keep_poses=False)
        model = HarvesterModel.from_scenario(scn, run.forest.terrain, run.forest.seed,
                                             RUN_T0_NS)
        sics = [OfflineSic(p, run.meta, model.node_config()) for p in grid.presets]
        frames, emu_s = drive(run, model, sics)
        ks = np.linspace(0, max(frames - 1, 0), grid.error_frames).astype(int)
        err = np.concatenate([_range_error(run, int(k)) for k in ks])
        ret = [_return_error(run, int(k)) for k in ks]
        rerr = np.concatenate([r[0] for r in ret])
        gt = run.ground_truth()
        sim_s = frames * run.emu.period_ns / 1e9
        for preset, sic in zip(grid.presets, sics, strict=True):
            doc = sic.finish()
            sc = score_forest(gt, stem_table(doc, "<reference SIC>", "observed"))
            a, s = sc.all.metrics, sc.seen.metrics
            ms = np.asarray(sic.frame_ms)
            rows.append({
                "forest": scn.name, "mode": mode, "tolerance_mm": tol,
                "backend": run.backend, "preset": preset,
                "sensor": scn.sensor.preset, "footprint": scn.sensor.footprint,
                "footprint_samples": scn.sensor.footprint_samples,
                "supersampled_pct": 100.0 * float(np.mean([r[2] for r in ret])),
                "triangles": len(run.scene.faces), "frames": frames,
                "emulator_ms_frame": 1000.0 * emu_s / max(frames, 1),
                "emulator_x_realtime": sim_s / max(emu_s, 1e-9),
                "range_err_p50_mm": float(np.percentile(err, 50) * 1e3) if len(err)
                else float("nan"),
                "range_err_p99_mm": float(np.percentile(err, 99) * 1e3) if len(err)
                else float("nan"),
                "return_err_p50_mm": _pct(np.abs(rerr), 50),
                "return_err_p99_mm": _pct(np.abs(rerr), 99),
                "return_bias_mm": float(np.mean(rerr) * 1e3) if len(rerr)
                else float("nan"),
                "returns_on_stems_pct": 100.0 * float(np.mean([r[1] for r in ret])),
                "sic_ms_p50": float(np.percentile(ms, 50)),
                "sic_ms_p99": float(np.percentile(ms, 99)),
                "stem_s": sic.stem_s,
                "stems_seen": run.stems_seen(),
                "wc_all": a["evaluation_score_percent"],
                "wc_seen": s["evaluation_score_percent"], "f1_seen": s["f1"],
                "position_rmse_m": s["position_rmse_m"], "dbh_rmse_m": s["dbh_rmse_m"],
                "dbh_bias_m": s["dbh_bias_m"], "stems_geometry": geometry,
            })
    return rows, notes


def _pct(v: np.ndarray, q: float) -> float:
    return float(np.percentile(v, q) * 1e3) if len(v) else float("nan")


def pareto(cost: Sequence[float], err: Sequence[float]) -> list[int]:
    """Indices of the points no other point beats on both (lower cost and lower error),
    by increasing cost."""
    order = sorted(range(len(cost)), key=lambda i: (cost[i], err[i]))
    front, best = [], float("inf")
    for i in order:
        if err[i] < best:
            front.append(i)
            best = err[i]
    return front


def _cost(r: dict[str, Any]) -> float:
    return float(r["emulator_ms_frame"] + r["sic_ms_p50"])


def pareto_png(rows: Sequence[dict[str, Any]], title: str) -> bytes:
    from tcf_hil._plots import figure_png, pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 5.0))
    cost = [_cost(r) for r in rows]
    for ax, key, label, scale in ((axes[0], "wc_seen", "100 - wc against seen trees (%)", 1.0),
                                  (axes[1], "dbh_rmse_m", "DBH RMSE, seen trees (mm)", 1e3)):
        err = [(100.0 - r[key]) if key == "wc_seen" else r[key] * scale for r in rows]
        markers = {"field": "o", "tuned": "^", "paper": "s"}
        for i, r in enumerate(rows):
            ax.scatter(cost[i], err[i], marker=markers.get(r["preset"], "^"),
                       c="#1f5fbf" if r["backend"] == "embree" else "#d9822b", s=40)
            ax.annotate(f"{r['mode']} {tol_label(r)} {r['preset']}", (cost[i], err[i]),
                        fontsize=6.5, xytext=(3, 3), textcoords="offset points")
        front = pareto(cost, err)
        ax.plot([cost[i] for i in front], [err[i] for i in front], "k--", lw=1,
                label="Pareto front")
        ax.set_xlabel("ms per frame: emulator + SIC (median)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8,
                  title="blue: Embree, orange: open3d; o field, ^ tuned, s paper", title_fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    return figure_png(fig)


def footprint_label(r: dict[str, Any]) -> str:
    """``adaptive:2``, ``full:4``, ``off`` (ideal sensors: ``-``)."""
    if r["sensor"] == "ideal":
        return "-"
    return "off" if r["footprint"] == "off" else f"{r['footprint']}:{r['footprint_samples']}"


def tol_label(r: dict[str, Any]) -> str:
    """The stems' tessellation tolerance (``2mm``), or ``curves`` (exact)."""
    return "curves" if r.get("stems_geometry") == "curves" else f"{r['tolerance_mm']:g}mm"


def _md(rows: Sequence[dict[str, Any]]) -> str:
    head = ["mode", "stems", "backend", "preset", "sensor", "footprint", "supersampled %",
            "emu ms/frame", "emu × RT", "mesh range p99 mm", "return err p50/p99 mm",
            "SIC ms p50", "SIC ms p99", "stem s", "wc all %", "wc seen %", "F1 seen",
            "pos RMSE mm", "DBH RMSE mm", "DBH bias mm", "Pareto"]
    cost = [_cost(r) for r in rows]
    front = set(pareto(cost, [100.0 - r["wc_seen"] for r in rows]))
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, r in enumerate(rows):
        lines.append("| " + " | ".join([
            r["mode"], tol_label(r), r["backend"], r["preset"], r["sensor"],
            footprint_label(r), f"{r['supersampled_pct']:.1f}",
            f"{r['emulator_ms_frame']:.1f}", f"{r['emulator_x_realtime']:.1f}",
            f"{r['range_err_p99_mm']:.2f}",
            f"{r['return_err_p50_mm']:.1f}/{r['return_err_p99_mm']:.0f}",
            f"{r['sic_ms_p50']:.1f}", f"{r['sic_ms_p99']:.1f}",
            f"{r['stem_s']:.1f}", f"{r['wc_all']:.1f}", f"{r['wc_seen']:.1f}",
            f"{r['f1_seen']:.3f}", f"{r['position_rmse_m'] * 1e3:.1f}",
            f"{r['dbh_rmse_m'] * 1e3:.1f}", f"{r['dbh_bias_m'] * 1e3:+.1f}",
            "yes" if i in front else ""]) + " |")
    return "\n".join(lines) + "\n"


def write_bench(rows: Sequence[dict[str, Any]], notes: Sequence[str], grid: BenchGrid,
                out: Path, wall_s: float) -> dict[str, Path]:
    ensure_dir(out)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(BENCH_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    paths = {"csv": out / "bench.csv", "md": out / "bench.md", "png": out / "pareto.png",
             "json": out / "bench.json"}
    write_bytes_atomic(paths["csv"], buf.getvalue().encode())
    frames = "whole track" if grid.frames is None else f"first {grid.frames} frames"
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    text = (f"# Speed against error: {grid.forest}, {frames}\n\n"
            f"One run, side by side; {wall_s:.0f} s wall, peak RSS {peak_mb:.0f} MB. Cost = "
            "emulator + SIC milliseconds per lidar frame; scores against the trees the sensor "
            "saw (and all trees). The range error is the mesh's against the exact surfaces "
            "(stem hits).\n\n" + _md(rows)
            + "".join(f"\n- {n}" for n in notes) + "\n")
    write_bytes_atomic(paths["md"], text.encode())
    if rows:
        write_bytes_atomic(paths["png"], pareto_png(rows, f"Speed against error, {grid.forest}"))
    write_json_atomic(paths["json"], {"grid": dataclasses.asdict(grid), "rows": list(rows),
                                      "notes": list(notes), "wall_s": wall_s,
                                      "peak_rss_mb": peak_mb,
                                      "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                time.gmtime())})
    return paths
