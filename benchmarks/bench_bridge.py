"""The bridge on this machine: `tcf-hil run` with the reference SIC as its own process, per
forest x mode x SIC preset; reports the SIC's per-frame cost (p50, p99; the wait for the pose
excluded), the frames lost at the SIC, the CPU shares of the SIC and of the emulators (the
bench process with its frame producer and CAN server), and the final scores against all and
against seen trees.

    python benchmarks/bench_bridge.py [--forests forest-v,forest-x] [--modes 1024x10,2048x10]
        [--presets tuned,paper] [--duration S] [--json OUT]

Runs one after another (the machine has two cores: a run uses both). A full track is 100 s
of real time per run.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def record(forest: str, mode: str, duration: float | None, out: Path) -> None:
    """A run whose SIC only waits: the emulators have the machine to themselves."""
    cmd = [sys.executable, "-m", "tcf_hil.cli", "run", forest, "--mode", mode, "--out",
           str(out), "--grace", "0", "--ready-timeout", "0",
           "--sic", "{python} -c \"import time; time.sleep(1e6)\""]
    if duration:
        cmd += ["--duration", str(duration)]
    subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, COLUMNS="200"))
    if not (out / "lidar.pcap").exists():
        raise SystemExit(f"recording {forest} {mode} failed")


def one(forest: str, mode: str, preset: str, duration: float | None, keep: Path | None,
        replay: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory(dir=keep) as tmp:
        out = Path(tmp) / "run"
        sic = f"{{python}} -m tcf_hil.sic --preset {preset}"
        if replay is not None:
            cmd = [sys.executable, "-m", "tcf_hil.cli", "run", "--replay", str(replay),
                   "--out", str(out), "--sic", sic]
        else:
            cmd = [sys.executable, "-m", "tcf_hil.cli", "run", forest, "--mode", mode,
                   "--out", str(out), "--sic", sic]
            if duration:
                cmd += ["--duration", str(duration)]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True,
                           env=dict(os.environ, COLUMNS="200"))
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if p.returncode != 0:
            return {"forest": forest, "mode": mode, "preset": preset, "error": p.stderr[-500:]}
        score = json.loads((out / "score.json").read_text())
        man = json.loads((out / "manifest.json").read_text())
        last = json.loads((out / "sic" / f"{score['scored_publication']:04d}.json").read_text())
        sic = last["sic"]
        total_cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        frames = (man["lidar"]["frames_sent"] if "lidar" in man
                  else json.loads((replay / "manifest.json").read_text())["lidar"]["frames_sent"]
                  if replay else 0)
        man.setdefault("lidar", {"frames_sent": frames, "pacing_us_p50_p99": [0.0, 0.0]})
        stream_s = frames / int(mode.split("x")[1])
        a, s = score["all_trees"], score["seen_trees"]
        return {
            "forest": forest, "mode": mode, "preset": preset,
            "frames_sent": man["lidar"]["frames_sent"], "sic_frames": sic["frames"],
            "frames_lost": sic["frames_lost"],
            "sic_ms_p50": sic["frame_cost"].get("p50_ms"),
            "sic_ms_p99": sic["frame_cost"].get("p99_ms"),
            "stem_ms_p50": sic.get("stem_cost", {}).get("p50_ms"),
            "sic_cpu_share": round(sic["cpu_s"] / sic["wall_s"], 3),
            "emulator_cpu_share": round((total_cpu - sic["cpu_s"]) / wall, 3),
            "pacing_us_p99": round(man["lidar"]["pacing_us_p50_p99"][1], 1),
            "wall_s": round(wall, 1), "stream_s": stream_s,
            "wc_all": round(a["evaluation_score_percent"], 1),
            "wc_seen": round(s["evaluation_score_percent"], 1),
            "f1_all": round(a["f1"], 3), "f1_seen": round(s["f1"], 3),
            "n_gt": a["n_ground_truth"], "n_seen": s["n_ground_truth"],
            "n_obs": a["n_observed"],
            "position_rmse_m": round(a["position_rmse_m"], 4),
            "dbh_rmse_m": round(a["dbh_rmse_m"], 4),
            "height_rmse_m": round(a["height_rmse_m"], 3),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--forests", default="forest-v,forest-x")
    ap.add_argument("--modes", default="1024x10,2048x10")
    ap.add_argument("--presets", default="tuned,paper")
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--replay", action="store_true",
                    help="Record each forest x mode once (with a SIC that only waits), then "
                         "run each preset on its replay: the SIC's cost without the "
                         "emulators competing for the two cores.")
    args = ap.parse_args()
    rows = []
    for forest in args.forests.split(","):
        for mode in args.modes.split(","):
            with tempfile.TemporaryDirectory() as rec_tmp:
                rec = None
                if args.replay:
                    rec = Path(rec_tmp) / "rec"
                    record(forest, mode, args.duration, rec)
                for preset in args.presets.split(","):
                    r = one(forest, mode, preset, args.duration, None, rec)
                    r["source"] = "replay" if rec else "live"
                    rows.append(r)
                    print(json.dumps(r), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    keys = ["forest", "mode", "preset", "sic_ms_p50", "sic_ms_p99", "frames_lost",
            "sic_cpu_share", "emulator_cpu_share", "wc_all", "wc_seen", "f1_all",
            "position_rmse_m", "dbh_rmse_m", "height_rmse_m"]
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, r.get("error", ""))) for k in keys) + " |")


if __name__ == "__main__":
    main()
