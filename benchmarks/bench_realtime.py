"""Real time on any scene: render into the store, then stream live runs from it with the SIC
running, and measure what the program under test gets.

Run: ``python benchmarks/bench_realtime.py [--scenes forest-v,forest-x,pine-thinning]
[--modes 1024x10,2048x10] [--duration 30] [--repeat 2] [--sic reference|idle] [--floor 5]
[--json OUT]``

Per scene and mode:

- **render**: ``LidarRun.render_into_store`` of the whole track into a store of its own (a
  temporary ``TCF_HIL_CACHE``), by one worker per CPU (as ``tcf-hil render``): its wall time,
  throughput as x real time, and the store's bytes per minute of track;
- **run** (``--repeat`` times): ``tcf-hil run SCENE --mode M --duration D --sic SIC`` streamed
  from that store, with: seconds from the command to the sensor's power-on (its first
  packet leaves half a second later), the track's packets 1 ms or more late and its pacing
  p50/p99 (the sender's own histogram over the track, ``manifest.json``), and the bench's CPU
  share during the track: the CPU seconds of the bench process and its helpers (the frame
  producer, the sender, the live score), not the SIC's, per wall second, sampled from
  ``/proc``; the sender's own share; frames the producer handed over 1 ms late; and the
  hypervisor's steal during the track (ms per second, both vCPUs): on a virtual machine a
  vCPU that is not running sends nothing, whatever the sender's priority;
- **floor** (before each run, ``--floor`` seconds): a bare pacer waking at the mode's packet
  interval under SCHED_FIFO, sending nothing (``emulators.pacing.wake_floor``): its p99 and
  its wake-ups 1 ms or more late per 10,000, what this machine allows any sender right then
  (without the SIC's load: a bound from below).

Medians over the repeats. The machine's other load counts: run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TICK = os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _cpu_s(pid: int) -> float:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(f[11]) + int(f[12])) / TICK  # utime, stime


def _bench_cpu(root: int, sic: set[int]) -> float:
    """CPU seconds of ``root`` and its descendants, the SIC's process tree left out."""
    total, todo = 0.0, [root]
    while todo:
        p = todo.pop()
        if p in sic:
            continue
        total += _cpu_s(p)
        todo += _children(p)
    return total


def _steal_s() -> float:
    """CPU seconds the hypervisor gave to others while this VM's CPUs wanted them (all
    CPUs, ``/proc/stat``): a vCPU not running is a packet late whatever the sender does."""
    from emulators.pacing import steal_s

    return steal_s() or 0.0


def _render(scene: str, mode: str) -> dict[str, Any]:
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.recording.store import RenderStore
    from tcf_hil.run import RUN_T0_NS
    from tcf_hil.scenario import load_scenario

    store = RenderStore()
    run = LidarRun(load_scenario(scene), mode=mode, t0_ns=RUN_T0_NS, store=store,
                   render="stored")
    t0 = time.perf_counter()
    made = run.render_into_store()
    wall = time.perf_counter() - t0
    track_s = run.track_frames / run.meta.frequency_hz
    size = next(e["bytes"] for e in store.entries() if e["key"] == run.render_key)
    os.sync()  # the store written out before the runs (its writeback slowed their start)
    return {"render_s": wall, "render_workers": len(os.sched_getaffinity(0)),
            "render_x_rt": track_s / wall if made else float("nan"),
            "track_s": track_s, "mb_per_min": size / 1e6 / (track_s / 60)}


def _floor(mode: str, seconds: float) -> dict[str, float]:
    """:func:`emulators.pacing.wake_floor` at ``mode``'s packet interval (16 columns a
    packet): p99 (us) and wake-ups 1 ms or more late per 10,000."""
    from tcf_hil.devices.timing import machine_timing

    t = machine_timing(mode, seconds)  # (what tcf-hil lidar timing measures)
    return {"floor_p99_us": float(t.p99_us + 1), "floor_late_per_10k": t.late_per_10k}


def _run(scene: str, mode: str, duration: float, sic: str, out: Path) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "tcf_hil.cli", "run", scene, "--mode", mode, "--duration",
           str(duration), "--grace", "120", "--out", str(out)]
    if sic == "idle":  # listens, reads nothing, publishes an empty forest at the end
        cmd += ["--sic", "{python} -c \"import socket, os, time, json, signal; "
                "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); "
                "s.bind((os.environ['TCF_LIDAR_BIND'], int(os.environ['TCF_LIDAR_PORT']))); "
                "print(json.dumps({'objects': []}), flush=True); signal.pause()\""]
    unix0 = time.time_ns()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    samples: list[tuple[int, float, float]] = []
    sic_pids: set[int] = set()
    man_path = out / "manifest.json"
    while proc.poll() is None:
        if not sic_pids and man_path.exists():
            try:
                pid = json.loads(man_path.read_text())["sic"]["pid"]
                sic_pids = {pid} if pid else set()
            except (ValueError, KeyError, TypeError):
                pass
        samples.append((time.time_ns(), _bench_cpu(proc.pid, sic_pids), _steal_s()))
        time.sleep(0.25)
    man = json.loads(man_path.read_text())
    clock, lidar = man["clock"], man["lidar"]
    t_start = clock["unix_ns_at_sim_t0"] + 1_000_000_000  # the track, less its edges
    t_end = clock["unix_ns_at_sim_t0"] + round(lidar["track"]["frames"] / 10 * 1e9) \
        - 1_000_000_000
    inside = [x for x in samples if t_start <= x[0] <= t_end]
    wall = (inside[-1][0] - inside[0][0]) / 1e9 if len(inside) > 1 else float("nan")
    share = (inside[-1][1] - inside[0][1]) / wall if len(inside) > 1 else float("nan")
    steal = 1000 * (inside[-1][2] - inside[0][2]) / wall if len(inside) > 1 else float("nan")
    return {"to_power_on_s": (clock["unix_ns_at_power_on"] - unix0) / 1e9,
            "late_1ms": lidar["track_packets_late_1ms"],
            "pacing_p50_us": lidar["track_pacing_us_p50_p99"][0],
            "pacing_p99_us": lidar["track_pacing_us_p50_p99"][1],
            "bench_cpu_share": share, "steal_ms_per_s": steal,
            "sender_cpu_share": lidar.get("sender_cpu_share", float("nan")),
            "frames_late_from_producer": lidar.get("frames_late_from_producer", 0),
            "from_store": lidar["render"]["from_store"],
            "frames": lidar["track"]["frames"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="forest-v,forest-x,pine-thinning")
    ap.add_argument("--modes", default="1024x10,2048x10")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--sic", default="reference", choices=["reference", "idle"])
    ap.add_argument("--json", default=None)
    ap.add_argument("--floor", type=float, default=5.0,
                    help="seconds of the bare pacer's wake-ups before each run (0: none)")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-rt-") as tmp:
        os.environ["TCF_HIL_CACHE"] = str(Path(tmp) / "cache")
        print(f"{'scene':14} {'mode':8} {'render x RT':>11} {'MB/min':>7} {'on 1st/next s':>13} "
              f"{'late>=1ms':>9} {'p50 us':>7} {'p99 us':>7} {'bench CPU':>9} {'sender':>6} "
              f"{'lateFr':>6} {'steal':>6} {'floor p99':>9} {'fl>=1ms':>7}", flush=True)
        for scene in a.scenes.split(","):
            for mode in a.modes.split(","):
                r = _render(scene, mode)
                runs = []
                for i in range(a.repeat):
                    fl = _floor(mode, a.floor) if a.floor > 0 else \
                        {"floor_p99_us": float("nan"), "floor_late_per_10k": float("nan")}
                    runs.append({**fl, **_run(scene, mode, a.duration, a.sic,
                                              Path(tmp) / f"{scene}-{mode}-{i}")})
                # the first run after a render keeps what later runs read (a --duration
                # shorter than the track: its own end's standing machine): reported apart
                first_on = runs[0]["to_power_on_s"]
                later_on = statistics.median(x["to_power_on_s"] for x in runs[1:]) \
                    if len(runs) > 1 else float("nan")
                med = {k: statistics.median(x[k] for x in runs)
                       for k in ("to_power_on_s", "late_1ms", "pacing_p50_us", "pacing_p99_us",
                                 "bench_cpu_share", "steal_ms_per_s", "sender_cpu_share",
                                 "frames_late_from_producer", "floor_p99_us",
                                 "floor_late_per_10k")}
                row = {"scene": scene, "mode": mode, **r, **med, "sic": a.sic,
                       "to_power_on_first_s": first_on, "to_power_on_later_s": later_on,
                       "duration_s": a.duration, "repeat": a.repeat,
                       "all_from_store": all(x["from_store"] for x in runs)}
                rows.append(row)
                print(f"{scene:14} {mode:8} {r['render_x_rt']:11.2f} {r['mb_per_min']:7.0f} "
                      f"{first_on:6.1f}/{later_on:6.1f} {med['late_1ms']:9.0f} "
                      f"{med['pacing_p50_us']:7.0f} {med['pacing_p99_us']:7.0f} "
                      f"{med['bench_cpu_share']:9.2f} {med['sender_cpu_share']:6.2f} "
                      f"{med['frames_late_from_producer']:6.0f} {med['steal_ms_per_s']:6.1f} "
                      f"{med['floor_p99_us']:9.0f} {med['floor_late_per_10k']:7.1f}",
                      flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
