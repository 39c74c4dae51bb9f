"""The reference SIC's presets side by side on the same recorded traffic, scored as a
harvester maker scores a stem program: the true stems within a distance of the track, greedy
matching within 0.75 m, detection, false positives, position RMSE, DBH bias and RMSE and
class accuracy, overall and per distance band, plus the SIC's CPU per frame.

The emulator runs once per (scene, mode, sensor) and its packets and CAN frames are kept in a
cache (``--cache``, default ``~/.cache/tcf-hil/bench-sic``), so the presets (and later
changes to the SIC) are compared on exactly the same bytes; every SIC reads them through the
same decoder and canopen as a live run (``tcf_hil.experiments.offline``).

    python benchmarks/bench_sic_field.py --scenes forest-v,pine-thinning --modes 1024x10 \\
        --sensors os0-64-rev7 --presets field,paper --out sic-field

Writes ``OUT/results.json`` (a row per scene x mode x sensor x preset, with the bands) and
``OUT/results.md``; ``--plot`` adds ``OUT/dbh_error_by_range.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import itertools
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

BANDS = ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 25.0), (25.0, math.inf))


def _scenario(scene: str, sensor: str, divergence_deg: float | None) -> Any:
    from tcf_hil.scenario import load_scenario, with_sensor

    scn = with_sensor(load_scenario(scene), sensor)
    if divergence_deg is not None:
        scn = dataclasses.replace(scn, sensor=dataclasses.replace(
            scn.sensor, divergence_h_deg=divergence_deg, divergence_v_deg=divergence_deg))
    return scn


class _Recorder:
    """Stands where a SIC stands in :func:`tcf_hil.experiments.offline.drive` and keeps the
    bytes."""

    def __init__(self, path: Path) -> None:
        self.lidar = path.open("wb")
        self.shape: tuple[int, int] | None = None
        self.frames: list[int] = []
        self.can: list[tuple[int, bytes, float, int]] = []

    def can_frame(self, cob: int, data: bytes, t_s: float) -> None:
        self.can.append((cob, bytes(data), t_s, len(self.frames)))

    def lidar_frame(self, fid: int, arr: np.ndarray) -> None:
        if self.shape is None:
            self.shape = (arr.shape[0], arr.shape[1])
        assert arr.shape == self.shape
        self.lidar.write(np.ascontiguousarray(arr).tobytes())
        self.frames.append(fid)


def record(scene: str, mode: str, sensor: str, cache: Path, *, max_frames: int | None,
           divergence_deg: float | None = None) -> Path:
    """The emulator's packets and CAN frames for one (scene, mode, sensor), kept under
    ``cache`` (reused when present); returns the directory."""
    from tcf_hil.devices.harvester import HarvesterModel
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.experiments.offline import drive
    from tcf_hil.world.forest.scenery import track_distance

    key = json.dumps([scene, mode, sensor, max_frames, divergence_deg, 2])
    d = cache / f"{scene}-{mode}-{sensor}-{hashlib.sha1(key.encode()).hexdigest()[:8]}"
    if (d / "done").exists():
        return d
    d.mkdir(parents=True, exist_ok=True)
    scn = _scenario(scene, sensor, divergence_deg)
    run = LidarRun(scn, mode=mode, max_frames=max_frames, faults=False, keep_poses=False)
    model = HarvesterModel.from_scenario(scn, run.forest.terrain, run.forest.seed,
                                         run.track.t0_ns)
    rec = _Recorder(d / "lidar.u8")
    t0 = time.perf_counter()

    def progress(i: int, n: int) -> None:
        if i % 50 == 0 or i == n:
            print(f"  {scene} {mode} {sensor}: frame {i}/{n} "
                  f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)

    frames, emu_s = drive(run, model, [rec], progress)
    rec.lidar.close()
    gt = run.ground_truth()
    xy = np.array([o["cp"][:2] for o in gt["objects"]], dtype=np.float64).reshape(-1, 2)
    ncfg = model.node_config()
    np.savez(d / "can.npz", cob=np.array([c[0] for c in rec.can], np.int64),
             data=np.frombuffer(b"".join(c[1].ljust(8, b"\0") for c in rec.can),
                                dtype=np.uint8).reshape(-1, 8),
             dlc=np.array([len(c[1]) for c in rec.can], np.int64),
             t=np.array([c[2] for c in rec.can]), before=np.array([c[3] for c in rec.can]))
    info = {"scene": scene, "mode": mode, "sensor": sensor, "divergence_deg": divergence_deg,
            "frames": frames, "frame_ids": rec.frames, "shape": rec.shape,
            "emulator_s": emu_s, "node": dataclasses.asdict(ncfg),
            "track_distance": track_distance(run.forest, xy).tolist()}
    (d / "meta.json").write_text(run.meta.dumps(), encoding="utf-8")
    (d / "info.json").write_text(json.dumps(info), encoding="utf-8")
    (d / "ground_truth.json").write_text(json.dumps(gt), encoding="utf-8")
    (d / "done").write_text("", encoding="utf-8")
    return d


def replay(d: Path, preset: str, live: bool = False, **overrides: Any) -> dict[str, Any]:
    """The recorded bytes through the reference SIC (``preset``); returns its final forest
    document and the per-frame costs.

    ``live``: as the live SIC runs, in real time on one core: this process is pinned to one
    CPU (its stem worker process inherits it), each frame is handed over when the sensor
    would have sent it (at the recording's frame rate, never before), the stem algorithm
    runs in the live SIC's worker process at a lower priority (:mod:`tcf_hil.sic._worker`),
    and the frame loop pumps it after each frame as the live loop does. ``frame_ms``: a
    frame's decode, edge returns, map update and pump; ``lag_s``: how long after its arrival
    each frame was done (the live SIC's receiver holds 5 s of frames; beyond that it drops
    them)."""
    import os
    from types import SimpleNamespace

    from protocols.ouster import SensorMetadata
    from tcf_hil.experiments.offline import OfflineSic

    info = json.loads((d / "info.json").read_text(encoding="utf-8"))
    meta = SensorMetadata.loads((d / "meta.json").read_text(encoding="utf-8"))
    ncfg = SimpleNamespace(**info["node"])
    sic = OfflineSic(preset, meta, ncfg)
    if overrides:
        sic.sic.params = dataclasses.replace(sic.sic.params, **overrides)
        sic.smap.params = sic.sic.params
    can = np.load(d / "can.npz")
    n, size = info["shape"]
    lidar = np.memmap(d / "lidar.u8", dtype=np.uint8, mode="r").reshape(-1, n, size)
    k = 0
    before = can["before"]
    can = {name: can[name] for name in can.files}
    period = 1.0 / meta.frequency_hz
    lags: list[float] = []
    pump_ms: list[float] = []
    map_bytes = 0
    worker = None
    saved_cpus = os.sched_getaffinity(0) if live else None
    if live:
        from tcf_hil.sic._worker import TileWorker

        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        worker = TileWorker(sic.sic.params)
        sic.smap.defer_runs = True
    t0 = time.process_time()
    start = time.perf_counter()
    try:
        for f, fid in enumerate(info["frame_ids"]):
            while k < len(before) and before[k] <= f:
                sic.can_frame(int(can["cob"][k]),
                              can["data"][k, :int(can["dlc"][k])].tobytes(), float(can["t"][k]))
                k += 1
            if worker is not None:
                due = start + f * period
                while time.perf_counter() < due:
                    time.sleep(min(0.01, max(0.0, due - time.perf_counter())))
            t1 = time.perf_counter()
            sic.lidar_frame(fid, np.asarray(lidar[f]))
            if worker is not None:
                t2 = time.perf_counter()
                worker.pump(sic.smap)
                pump_ms.append((time.perf_counter() - t2) * 1000.0)
                sic.frame_ms[-1] = (time.perf_counter() - t1) * 1000.0
                lags.append(time.perf_counter() - (start + f * period))
                if f % 20 == 0:  # off the frame's clock
                    map_bytes = max(map_bytes, sic.smap.nbytes())
        frames_cpu = time.process_time() - t0
        t_end = time.process_time()
        if worker is not None:
            worker.drain(sic.smap, timeout=600.0)
        doc = sic.finish()
        finish_cpu = time.process_time() - t_end + (worker.cpu_s if worker else 0.0)
        worker_cpu = worker.cpu_s if worker else 0.0
    finally:
        if worker is not None:
            worker.close()
        if saved_cpus is not None:
            os.sched_setaffinity(0, saved_cpus)
    return {"doc": doc, "frame_ms": sic.frame_ms, "frames_cpu_s": frames_cpu,
            "finish_cpu_s": finish_cpu, "frames": len(info["frame_ids"]),
            "worker_cpu_s": worker_cpu, "wall_s": time.perf_counter() - start,
            "lag_s": lags, "pump_ms": pump_ms, "tile_runs": sic.smap.stats.tile_runs,
            "map_points_max": sic.smap.max_points, "map_mb_peak": map_bytes / 2**20,
            "evicted_points": sic.smap.stats.evicted_points}


def score(d: Path, doc: dict[str, Any], *, near_m: float = 15.0, match_m: float = 0.75
          ) -> dict[str, Any]:
    """The issue's yardstick: true stems within ``near_m`` of the track, greedy matching
    within ``match_m``; the SIC's stems within ``near_m`` (+ the matching distance) count for
    false positives. Bands by the true stem's distance from the track."""
    from scipy.spatial import cKDTree

    from tcf_hil.evaluation import match

    info = json.loads((d / "info.json").read_text(encoding="utf-8"))
    gt = json.loads((d / "ground_truth.json").read_text(encoding="utf-8"))["objects"]
    gd = np.asarray(info["track_distance"])
    gxy = np.array([o["cp"][:2] for o in gt]).reshape(-1, 2)
    obs = doc["objects"]
    oxy = np.array([o["cp"][:2] for o in obs], dtype=np.float64).reshape(-1, 2)
    pairs, _ = match(gxy, oxy, match_m, "greedy")
    # the SIC's stems' distance from the track: through the nearest true stem's own, less
    # exact than the track itself but the track is not the SIC's to know; we use the truth's
    # track distances only for scoring
    if len(oxy) and len(gxy):
        near_gt = cKDTree(gxy).query(oxy)[1]
        od = gd[near_gt]
    else:
        od = np.zeros(len(oxy))
    g2o = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))

    def stats(lo: float, hi: float) -> dict[str, Any]:
        gi = np.flatnonzero((gd >= lo) & (gd < hi))
        oi = np.flatnonzero((od >= lo) & (od < hi))
        m = [(g, g2o[g]) for g in gi.tolist() if g in g2o]
        matched_obs = set(g2o.values())
        fp = [o for o in oi.tolist() if o not in matched_obs]
        pos = [math.dist(gxy[g], oxy[o]) for g, o in m]
        dbh = [(obs[o]["dbh"] - gt[g]["dbh"]) for g, o in m
               if obs[o].get("dbh") is not None]
        cls = [obs[o]["class"] == gt[g]["class"] for g, o in m]
        seen100 = int(sum(1 for g in gi if gt[g].get("returns", 0) >= 100))

        def rms(v: list[float]) -> float | None:
            return round(float(np.sqrt(np.mean(np.square(v)))), 4) if v else None

        return {"true": len(gi), "true_100_returns": seen100, "found": len(m),
                "detection": round(len(m) / len(gi), 4) if len(gi) else None,
                "sic_stems": len(oi), "false_positives": len(fp),
                "fp_share": round(len(fp) / len(oi), 4) if len(oi) else None,
                "position_rmse_m": rms(pos),
                "dbh_bias_m": round(float(np.mean(dbh)), 4) if dbh else None,
                "dbh_rmse_m": rms(dbh), "dbh_pairs": len(dbh),
                "class_correct": round(float(np.mean(cls)), 4) if cls else None}

    out = {"near": stats(0.0, near_m),
           "bands": {f"{lo:g}-{hi:g}": stats(lo, hi) for lo, hi in BANDS}}
    # DBH error against the stem's range from the track (for the plot)
    out["dbh_error"] = [[float(gd[g]), float(obs[o]["dbh"] - gt[g]["dbh"])]
                        for g, o in g2o.items() if obs[o].get("dbh") is not None]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="forest-v,forest-v-natural,pine-thinning")
    ap.add_argument("--modes", default="1024x10")
    ap.add_argument("--sensors", default="os0-64-rev7")
    ap.add_argument("--presets", default="field,paper")
    ap.add_argument("--frames", type=int, default=None, help="at most this many frames")
    ap.add_argument("--divergence", type=float, default=None,
                    help="the sensor's FWHM divergence, degrees (default: the preset's)")
    ap.add_argument("--cache", type=Path,
                    default=Path.home() / ".cache" / "tcf-hil" / "bench-sic")
    ap.add_argument("--out", type=Path, default=Path("sic-field"))
    ap.add_argument("--plot", action="store_true")
    ap.add_argument("--live", action="store_true",
                    help="as a live SIC: one core, frames at the sensor's rate, the stem "
                         "algorithm in its worker process; the lag behind the sensor (run it "
                         "with OMP_NUM_THREADS=1)")
    a = ap.parse_args(argv)
    rows = []
    a.out.mkdir(parents=True, exist_ok=True)
    for scene in a.scenes.split(","):
        for mode in a.modes.split(","):
            for sensor in a.sensors.split(","):
                d = record(scene, mode, sensor, a.cache, max_frames=a.frames,
                           divergence_deg=a.divergence)
                for preset in [x for x in a.presets.split(",") if x]:
                    r = replay(d, preset, live=a.live)
                    s = score(d, r["doc"])
                    fm = np.asarray(r["frame_ms"])
                    row = {"scene": scene, "mode": mode, "sensor": sensor,
                           "divergence_deg": a.divergence, "preset": preset,
                           "frames": r["frames"],
                           "frame_ms_p50": round(float(np.median(fm)), 2),
                           "frame_ms_p99": round(float(np.percentile(fm, 99)), 2),
                           "sic_cpu_ms_per_frame": round(
                               1000 * (r["frames_cpu_s"] + r["finish_cpu_s"]) / r["frames"], 2),
                           "evicted_points": r["evicted_points"],
                           **s}
                    if a.live:
                        lag = np.asarray(r["lag_s"])
                        row.update({"lag_s_p99": round(float(np.percentile(lag, 99)), 3),
                                    "lag_s_max": round(float(lag.max()), 3),
                                    "frames_beyond_5s_lag": int((lag > 5.0).sum()),
                                    "worker_cpu_s": round(r["worker_cpu_s"], 1),
                                    "tile_runs": r["tile_runs"],
                                    "map_mb_peak": round(r["map_mb_peak"]),
                                    "pump_ms_p99": round(float(np.percentile(r["pump_ms"], 99)),
                                                         2),
                                    "wall_s": round(r["wall_s"], 1)})
                        print(f"   live, one core: frame p50/p99 {row['frame_ms_p50']}/"
                              f"{row['frame_ms_p99']} ms, lag p99/max {row['lag_s_p99']}/"
                              f"{row['lag_s_max']} s, {row['frames_beyond_5s_lag']} frames "
                              f"beyond 5 s, pump p99 {row['pump_ms_p99']} ms, stem worker "
                              f"{row['worker_cpu_s']} s CPU in {row['tile_runs']} tile runs, map "
                              f"{row['map_mb_peak']} MB at most, wall {row['wall_s']} s",
                              flush=True)
                    rows.append(row)
                    n = s["near"]
                    print(f"{scene:18s} {mode} {sensor:12s} {preset:6s} "
                          f"found {n['found']}/{n['true']} ({n['detection']}) "
                          f"fp {n['false_positives']}/{n['sic_stems']} pos {n['position_rmse_m']}"
                          f" dbh {n['dbh_bias_m']}/{n['dbh_rmse_m']} cls {n['class_correct']} "
                          f"cpu {row['sic_cpu_ms_per_frame']} ms/frame", flush=True)
                    (a.out / "results.json").write_text(json.dumps(rows, indent=1))
    (a.out / "results.md").write_text(markdown(rows), encoding="utf-8")
    if a.plot:
        plot(rows, a.out / "dbh_error_by_range.png")
    return 0


def markdown(rows: list[dict[str, Any]]) -> str:
    """A table per scene: the presets side by side, within 15 m of the track, then by band."""
    def pct(v: float | None) -> str:
        return "–" if v is None else f"{100 * v:.0f} %"

    def cm(v: float | None, sign: bool = False) -> str:
        return "–" if v is None else (f"{100 * v:+.1f}" if sign else f"{100 * v:.1f}")

    out = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        out += [f"### {scene}", "",
                "| mode | sensor | preset | band, m | found | false pos. | position RMSE cm "
                "| DBH bias / RMSE cm | class correct | SIC CPU ms/frame |",
                "|---|---|---|---|---|---|---|---|---|---|"]
        for r in (x for x in rows if x["scene"] == scene):
            for band, b in [("0-15", r["near"]), *r["bands"].items()]:
                if not b["true"] and not b["sic_stems"]:
                    continue
                out.append(
                    f"| {r['mode']} | {r['sensor']} | {r['preset']} | {band} | "
                    f"{b['found']}/{b['true']} ({pct(b['detection'])}) | "
                    f"{b['false_positives']}/{b['sic_stems']} ({pct(b['fp_share'])}) | "
                    f"{cm(b['position_rmse_m'])} | {cm(b['dbh_bias_m'], True)} / "
                    f"{cm(b['dbh_rmse_m'])} | {pct(b['class_correct'])} | "
                    f"{r['sic_cpu_ms_per_frame'] if band == '0-15' else ''} |")
        out.append("")
    return "\n".join(out)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """DBH error (SIC - true) against the true stem's distance from the track: the median
    and the RMSE in 2.5 m bins, a line per scene x mode x preset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    edges = np.arange(0.0, 27.5, 2.5)
    for r in rows:
        e = np.asarray(r["dbh_error"]).reshape(-1, 2)
        if not len(e):
            continue
        mid, med, rms = [], [], []
        for lo, hi in itertools.pairwise(edges):
            v = e[(e[:, 0] >= lo) & (e[:, 0] < hi), 1]
            if len(v) >= 3:
                mid.append((lo + hi) / 2)
                med.append(100 * float(np.median(v)))
                rms.append(100 * float(np.sqrt(np.mean(v * v))))
        style = "-" if r["preset"] != "paper" else ":"
        label = f"{r['scene']} {r['mode']} {r['sensor']} {r['preset']}"
        axes[0].plot(mid, med, style, marker="o", ms=3, label=label)
        axes[1].plot(mid, rms, style, marker="o", ms=3, label=label)
    axes[0].axhline(0.0, color="grey", lw=0.8)
    axes[0].set_ylabel("DBH error, median (cm)")
    axes[1].set_ylabel("DBH error, RMSE (cm)")
    axes[1].set_yscale("log")
    for ax in axes:
        ax.set_xlabel("distance of the true stem from the track (m)")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
