"""The harvester node on the embedded CAN server: CPU share at 100 Hz, TPDO period jitter,
pose latency between processes, and the highest pose rate the node sustains.

Run: python benchmarks/bench_harvester.py [--seconds 10]

The CAN server runs in its own process; the node (``tcf-hil harvester run``) in another; a
consumer process decodes TPDO3 and measures, on the shared monotonic clock, how long after the
pose's simulation time it arrived (pose sampling + encoding + TCP relay + decoding).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys

import numpy as np

CONSUMER = r"""
import json, logging, sys, time, can
from protocols.harvester import PoseAssembler
logging.getLogger("can").setLevel(logging.ERROR)  # "incomplete message": TCP splits lines
port, origin, t0, seconds = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
asm = PoseAssembler(10)
lat, n, first, last = [], 0, None, None
print("ready", flush=True)
end = time.monotonic() + seconds
while time.monotonic() < end:
    m = bus.recv(0.1)
    if m is None:
        continue
    now = time.monotonic_ns()
    n += 1
    p = asm.feed(m.arbitration_id, bytes(m.data))
    if p is not None:
        lat.append((now - (origin + p.time_us * 1000 - t0)) / 1e3)
        first = p.time_us if first is None else first
        last = p.time_us
bus.shutdown()
print(json.dumps({"frames": n, "latency_us": lat, "span_s": (last - first) / 1e6}))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run(seconds: float, rate: float) -> dict[str, float]:
    port = _free_port()
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    server = subprocess.Popen([sys.executable, "-m", "tcf_hil.cli", "can-server", "--port",
                               str(port)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert server.stdout is not None
        server.stdout.readline()
        # the harvester's clock: its SimClock starts when the node starts; the consumer is
        # told the same origin through a small driver script
        driver = (
            "import sys, time, threading\n"
            "from emulators.harvester import SimClock, BusSpec\n"
            "from tcf_hil.world.forest import generate_forest\n"
            "from tcf_hil.devices.harvester import run_harvester\n"
            "from tcf_hil.scenario import load_scenario\n"
            "scn = load_scenario('forest-v'); f = generate_forest(scn)\n"
            "clock = SimClock.start(3 * 10**9, lead_ns=2 * 10**9)\n"
            "print(clock.origin_monotonic_ns, flush=True)\n"
            "cpu = []\n"
            "def tick(t, tot):\n"
            "    if t > 1.0 and t < tot - 0.5:  # steady state: not start-up, not the end\n"
            "        cpu.append((time.process_time(), time.monotonic()))\n"
            f"spec = BusSpec('socketcand', 'vcan0', '127.0.0.1', {port})\n"
            f"r = run_harvester(scn, f.terrain, spec, rate_hz={rate}, duration_s={seconds},"
            " clock=clock, on_tick=tick)\n"
            "r.stats['cpu_share'] = (cpu[-1][0] - cpu[0][0]) / (cpu[-1][1] - cpu[0][1])\n"
            "import json; print(json.dumps(r.stats), flush=True)\n")
        node = subprocess.Popen([sys.executable, "-c", driver], stdout=subprocess.PIPE,
                                text=True, env=env)
        assert node.stdout is not None
        origin = int(node.stdout.readline())
        cons = subprocess.Popen([sys.executable, "-c", CONSUMER, str(port), str(origin),
                                 str(3 * 10**9), str(seconds + 2.5)], stdout=subprocess.PIPE,
                                text=True, env=env)
        assert cons.stdout is not None
        cons.stdout.readline()
        stats = json.loads(node.stdout.readline())
        node.wait()
        out = json.loads(cons.stdout.read())
        cons.wait()
    finally:
        server.terminate()
        server.wait()
    lat = np.array(out["latency_us"])
    span = out["span_s"]
    return {"rate_hz": rate, "poses": len(lat), "poses_per_s": (len(lat) - 1) / span,
            "frames_per_s": out["frames"] / span,
            "latency_p50_us": float(np.median(lat)), "latency_p99_us": float(
                np.percentile(lat, 99)),
            "tpdo_period_p50_us": stats.get("tpdo_period_us_p50", float("nan")),
            "tpdo_jitter_p99_us": stats.get("tpdo_jitter_us_p99", float("nan")),
            "node_cpu_share": stats["cpu_share"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rates", default="100,500,1000")
    args = ap.parse_args()
    rows = [run(args.seconds, float(r)) for r in args.rates.split(",")]
    keys = list(rows[0])
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys))


if __name__ == "__main__":
    main()
