"""Faults survived: `tcf-hil run` with the reference SIC as its own process, once per
injected fault (and once clean), on one forest and mode; reports whether the run survived
(exit 0, a scored forest), what was kept (frames sent, frames the SIC mapped, frames it
counted lost, the faults logged) and the SIC's score next to the clean run's.

    python benchmarks/bench_faults.py [--forest forest-ii] [--mode 512x10] [--speed 1]
        [--only NAME,...] [--json OUT]

Runs one after another (a run uses both cores). Forest II's track is 50 s of real time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# name -> (rate in words, --fault KEY=VALUE ...)
FAULTS: dict[str, tuple[str, list[str]]] = {
    "none": ("-", []),
    "udp loss": ("5 % of datagrams", ["udp.loss=0.05"]),
    "udp loss bursts": ("1 burst / 1000 datagrams, mean 20", ["udp.burst_rate=0.001",
                                                               "udp.burst_packets=20"]),
    "udp duplicates": ("5 %", ["udp.duplicate=0.05"]),
    "udp reordering": ("5 % swapped", ["udp.reorder=0.05"]),
    "udp jitter": ("up to 2 ms", ["udp.jitter_us=2000"]),
    "lidar dropouts": ("10 % of frames", ["lidar.dropout=0.1"]),
    "lidar re-init": ("at 10 s and 30 s, 1 s silent", ["lidar.reinit_at_s=[10, 30]"]),
    "can loss": ("5 % of the node's frames", ["can.loss=0.05"]),
    "late poses": ("TPDOs 80 ms after SYNC", ["can.pose_delay_ms=80"]),
    "bus-off": ("at 15 s for 2 s", ["can.bus_off_at_s=[15]", "can.bus_off_s=2"]),
    "nmt reset": ("at 20 s, restarted 0.5 s later", ["can.nmt_reset_at_s=[20]"]),
    "nmt reset, no restart": ("at 20 s; the SIC must start it",
                              ["can.nmt_reset_at_s=[20]", "can.nmt_restart_s=0"]),
    "everything at once": ("all of the above, lighter", [
        "udp.loss=0.01", "udp.burst_rate=0.0005", "udp.duplicate=0.01", "udp.reorder=0.01",
        "udp.jitter_us=200", "lidar.dropout=0.03", "lidar.reinit_at_s=[12]",
        "can.loss=0.01", "can.pose_delay_ms=30", "can.bus_off_at_s=[18]",
        "can.nmt_reset_at_s=[25]"]),
}


def one(name: str, forest: str, mode: str, speed: float) -> dict:
    rate, faults = FAULTS[name]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "tcf_hil.cli", "run", forest, "--mode", mode,
               "--speed", str(speed), "--out", str(out),
               *(a for f in faults for a in ("--fault", f))]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True,
                           env=dict(os.environ, COLUMNS="200"))
        wall = time.perf_counter() - t0
        row: dict = {"fault": name, "rate": rate, "exit": p.returncode,
                     "wall_s": round(wall, 1)}
        if not (out / "score.json").exists():
            row["error"] = (p.stderr or p.stdout)[-300:]
            return row
        score = json.loads((out / "score.json").read_text())
        man = json.loads((out / "manifest.json").read_text())
        last = json.loads((out / "sic" / f"{score['scored_publication']:04d}.json").read_text())
        sic = last["sic"]
        a = score["all_trees"]
        logged = sum(v["count"] for v in score.get("faults", {}).values())
        row.update({
            "survived": p.returncode == 0 and score["status"] == "complete",
            "frames_sent": man["lidar"]["frames_sent"], "sic_frames": sic["frames"],
            "sic_frames_lost": sic["frames_lost"], "sic_reinits": sic["sensor_reinits"],
            "frames_without_pose": sic["frames_without_pose"], "faults_logged": logged,
            "pcap_kept": (out / "lidar.pcap").stat().st_size > 0,
            "can_log_kept": (out / "can.log").stat().st_size > 0,
            "wc_all": round(a["evaluation_score_percent"], 1), "f1": round(a["f1"], 3),
            "position_rmse_m": round(a["position_rmse_m"], 4),
            "dbh_rmse_m": round(a["dbh_rmse_m"], 4),
        })
        return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--forest", default="forest-ii")
    ap.add_argument("--mode", default="512x10")
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--only", default=None, help="comma-separated fault names")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    names = args.only.split(",") if args.only else list(FAULTS)
    rows = []
    for name in names:
        r = one(name, args.forest, args.mode, args.speed)
        rows.append(r)
        print(json.dumps(r), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    keys = ["fault", "rate", "survived", "frames_sent", "sic_frames", "sic_frames_lost",
            "sic_reinits", "faults_logged", "pcap_kept", "wc_all", "f1", "position_rmse_m",
            "dbh_rmse_m"]
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, r.get("error", "") if k == "survived" else ""))
                                for k in keys) + " |")


if __name__ == "__main__":
    main()
