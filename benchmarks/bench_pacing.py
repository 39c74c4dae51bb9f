"""Live pacing of the emulated OS0-64: interval error p50/p99 and the pacing loop's CPU share,
with SCHED_FIFO (where permitted) and with ordinary scheduling, runs interleaved with the
machine's floor: a bare pacer waking at the mode's packet interval under SCHED_FIFO for as
long as a run's frames last, sending nothing (``emulators.pacing.wake_floor``); a sender can
be no more punctual than its wake-ups.

Run: python benchmarks/bench_pacing.py [--scenario forest-x] [--mode 2048x10] [--frames 100]
     [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics

from emulators.pacing import steal_s, wake_floor
from tcf_hil.devices.lidar import stream_lidar
from tcf_hil.scenario import load_scenario


def _steal_ms() -> float:
    """CPU time the hypervisor gave to others while this VM wanted it (all CPUs), ms."""
    return 1000.0 * (steal_s() or 0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="forest-x")
    ap.add_argument("--mode", default="2048x10")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    scn = load_scenario(a.scenario)
    rows: dict[bool, list[tuple[float, float, float, bool]]] = {True: [], False: []}
    cols, hz = (int(x) for x in a.mode.split("x"))
    floor: list[tuple[float, float]] = []
    for _ in range(a.repeats):
        errs = sorted(wake_floor(round(1e9 / (hz * cols / 16)), a.frames / hz))
        floor.append((float(errs[len(errs) // 2] + 1),
                      float(errs[min(len(errs) - 1, int(0.99 * len(errs)))] + 1)))
        print(f"  floor: bare pacer p50 {floor[-1][0]:.0f} us, p99 {floor[-1][1]:.0f} us",
              flush=True)
        for rt in (True, False):
            steal = _steal_ms()
            r = stream_lidar(scn, mode=a.mode, max_frames=a.frames, realtime=rt)
            steal = _steal_ms() - steal
            rows[rt].append((*r.pacing_us, r.sender_cpu_share, r.realtime))
            print(f"  run: {'FIFO asked' if rt else 'ordinary'}: p50 {r.pacing_us[0]:.0f} us, "
                  f"p99 {r.pacing_us[1]:.0f} us; hypervisor steal {steal:.0f} ms", flush=True)
    print(f"{a.scenario} {a.mode}, {a.frames} frames x {a.repeats} runs (medians)")
    print("scheduling | p50 us | p99 us | pacing loop CPU share")
    print(f"floor (bare pacer, SCHED_FIFO asked) | "
          f"{statistics.median(f[0] for f in floor):.0f} | "
          f"{statistics.median(f[1] for f in floor):.0f} | -")
    for rt, rs in rows.items():
        name = ("SCHED_FIFO" if all(r[3] for r in rs) else "ordinary (FIFO not permitted)") \
            if rt else "ordinary"
        print(f"{name} | {statistics.median(r[0] for r in rs):.0f} | "
              f"{statistics.median(r[1] for r in rs):.0f} | "
              f"{100 * statistics.median(r[2] for r in rs):.0f} %")


if __name__ == "__main__":
    main()
