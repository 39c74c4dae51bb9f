"""The embedded CAN server (socketcand protocol) between two processes: sustained throughput of
an unpaced blast, and one-way latency at a paced rate.

Run: python benchmarks/bench_canbus.py [--frames 20000] [--rate 1000] [--seconds 5]

The server runs in a thread of this process; a sender and a receiver, each a python-can
``socketcand`` client in its own process, share its bus. Frames are classic 8-byte frames
with extended ids (the id numbers the frame, the data is the sender's ``time.monotonic_ns()``,
the same clock in every process), so the receiver counts losses, checks the order and
measures latency without help.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from typing import Any

import numpy as np

from emulators.canbus import SocketcandServer

SENDER = r"""
import json, logging, sys, time
import can
logging.getLogger("can").setLevel(logging.ERROR)
port, n, rate = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
print("ready", flush=True)
sys.stdin.readline()
period = int(1e9 / rate) if rate > 0 else 0
msg = can.Message(arbitration_id=0, data=bytes(8), is_extended_id=True)
t0 = time.monotonic_ns()
for i in range(n):
    if period:
        due = t0 + i * period
        while (now := time.monotonic_ns()) < due:
            if due - now > 300_000:
                time.sleep((due - now - 200_000) / 1e9)
    msg.arbitration_id = i
    msg.data = bytearray(time.monotonic_ns().to_bytes(8, "little"))
    bus.send(msg)
t1 = time.monotonic_ns()
bus.shutdown()
print(json.dumps({"t0": t0, "t1": t1, "sent": n}), flush=True)
"""

RECEIVER = r"""
import json, logging, sys, time
import can
logging.getLogger("can").setLevel(logging.ERROR)
port, n = int(sys.argv[1]), int(sys.argv[2])
bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
print("ready", flush=True)
ids, lat = [], []
first = last = 0
while len(ids) < n:
    m = bus.recv(2.0)
    if m is None:
        break  # 2 s without a frame: the rest is lost
    now = time.monotonic_ns()
    first = first or now
    last = now
    ids.append(m.arbitration_id)
    lat.append(now - int.from_bytes(m.data, "little"))
bus.shutdown()
in_order = all(a < b for a, b in zip(ids, ids[1:]))
print(json.dumps({"got": len(ids), "first": first, "last": last, "in_order": in_order,
                  "lat_ns": lat}), flush=True)
"""


def _spawn(script: str, *args: object) -> subprocess.Popen[str]:
    p = subprocess.Popen([sys.executable, "-c", script, *map(str, args)],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    if line != "ready":
        p.kill()
        raise RuntimeError(f"child did not start: {line!r}")
    return p


def _result(p: subprocess.Popen[str], timeout: float) -> dict[str, Any]:
    out, _ = p.communicate(timeout=timeout)
    if p.returncode != 0:
        raise RuntimeError(f"child failed ({p.returncode})")
    return dict(json.loads(out.strip().splitlines()[-1]))


def run_once(port: int, n: int, rate: float) -> dict[str, float]:
    """Send ``n`` frames (``rate`` per second, 0: unpaced) from one process to another."""
    rx = _spawn(RECEIVER, port, n)
    tx = _spawn(SENDER, port, n, rate)
    try:
        time.sleep(0.2)  # both joined and past the server's join grace
        assert tx.stdin is not None
        tx.stdin.write("go\n")
        tx.stdin.flush()
        limit = 60 + (n / rate if rate > 0 else 0)
        t = _result(tx, limit)
        r = _result(rx, limit)
    finally:
        for p in (tx, rx):
            if p.poll() is None:
                p.kill()
    lat_ms = np.asarray(r["lat_ns"], dtype=np.float64) / 1e6
    send_s = (t["t1"] - t["t0"]) / 1e9
    recv_s = (r["last"] - t["t0"]) / 1e9
    return {
        "sent": n, "got": r["got"], "lost": n - r["got"], "in_order": float(r["in_order"]),
        "tx_fps": n / send_s if send_s > 0 else float("inf"),
        "rx_fps": r["got"] / recv_s if recv_s > 0 else float("inf"),
        "p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else float("nan"),
        "p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else float("nan"),
        "max_ms": float(lat_ms.max()) if lat_ms.size else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20_000, help="frames in the unpaced blast")
    ap.add_argument("--rate", type=float, default=1000.0, help="paced rate, frames/s")
    ap.add_argument("--seconds", type=float, default=5.0, help="paced duration")
    a = ap.parse_args()
    with SocketcandServer(port=0) as server:
        blast = run_once(server.port, a.frames, 0)
        paced = run_once(server.port, int(a.rate * a.seconds), a.rate)
        stats = server.stats()
    print("CAN server (socketcand protocol), sender and receiver in separate processes")
    print(f"{'run':<24}{'sent':>7}{'lost':>6}{'order':>7}{'tx fps':>10}{'rx fps':>10}"
          f"{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}")
    for name, r in ((f"unpaced {a.frames}", blast),
                    (f"paced {a.rate:g} fps x {a.seconds:g} s", paced)):
        print(f"{name:<24}{r['sent']:>7.0f}{r['lost']:>6.0f}"
              f"{'ok' if r['in_order'] else 'NO':>7}{r['tx_fps']:>10.0f}{r['rx_fps']:>10.0f}"
              f"{r['p50_ms']:>9.3f}{r['p99_ms']:>9.3f}{r['max_ms']:>9.3f}")
    print(f"server: {stats.frames_received} frames received, {stats.frames_relayed} relayed, "
          f"{stats.frames_dropped} dropped, {stats.protocol_errors} protocol errors")
    print("rx fps: frames received / (last receipt - first send); latency: monotonic_ns at "
          "receipt - monotonic_ns in the frame (unpaced latency is queueing delay)")


if __name__ == "__main__":
    main()
