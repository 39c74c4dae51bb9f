"""Live pacing of the emulated OS0-64: interval error p50/p99 and the pacing loop's CPU share,
with SCHED_FIFO (where permitted) and with ordinary scheduling, runs interleaved.

Run: python benchmarks/bench_pacing.py [--scenario forest-x] [--mode 2048x10] [--frames 100]
     [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics

from tcf_hil.devices.lidar import stream_lidar
from tcf_hil.scenario import load_scenario


def _steal_ms() -> float:
    """CPU time the hypervisor gave to others while this VM wanted it (all CPUs), ms."""
    with open("/proc/stat") as fh:
        fields = fh.readline().split()
    return int(fields[8]) * 1000 / os.sysconf("SC_CLK_TCK") if len(fields) > 8 else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="forest-x")
    ap.add_argument("--mode", default="2048x10")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    scn = load_scenario(a.scenario)
    rows: dict[bool, list[tuple[float, float, float, bool]]] = {True: [], False: []}
    for _ in range(a.repeats):
        for rt in (True, False):
            steal = _steal_ms()
            r = stream_lidar(scn, mode=a.mode, max_frames=a.frames, realtime=rt)
            steal = _steal_ms() - steal
            rows[rt].append((*r.pacing_us, r.sender_cpu_share, r.realtime))
            print(f"  run: {'FIFO asked' if rt else 'ordinary'}: p50 {r.pacing_us[0]:.0f} us, "
                  f"p99 {r.pacing_us[1]:.0f} us; hypervisor steal {steal:.0f} ms", flush=True)
    print(f"{a.scenario} {a.mode}, {a.frames} frames x {a.repeats} runs (medians)")
    print("scheduling | p50 us | p99 us | pacing loop CPU share")
    for rt, rs in rows.items():
        name = ("SCHED_FIFO" if all(r[3] for r in rs) else "ordinary (FIFO not permitted)") \
            if rt else "ordinary"
        print(f"{name} | {statistics.median(r[0] for r in rs):.0f} | "
              f"{statistics.median(r[1] for r in rs):.0f} | "
              f"{100 * statistics.median(r[2] for r in rs):.0f} %")


if __name__ == "__main__":
    main()
