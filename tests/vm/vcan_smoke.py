"""Run inside the VM (see .ci/vcan-vm.sh): the socketcan path on a real kernel vcan0.

1. ``candump -L vcan0`` logs the bus into ``$VM_OUT``;
2. a python-can ``socketcan`` receiver runs in its own process;
3. a separate python-can sender process sends 50 frames (id 0x18A, 10 ms apart);
4. ``cansend vcan0 7FF#C0FFEE`` sends one more from can-utils.

Passes when the receiver got all 51 frames in order and candump logged all 51. Python runs
10-20x slower under TCG, so this checks function at a low rate, not timing.
Prints one result line; exits non-zero on failure.
"""

from __future__ import annotations

import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

CHANNEL = "vcan0"
N_PY = 50
EXPECTED = [(0x18A, bytes([i, 0x5A, 0xA5 ^ i])) for i in range(N_PY)] + [(0x7FF, b"\xc0\xff\xee")]

RECEIVER = r"""
import json, sys, time
import can
n, timeout = int(sys.argv[1]), float(sys.argv[2])
bus = can.Bus(interface="socketcan", channel="vcan0")
print("ready", flush=True)
got = []
deadline = time.monotonic() + timeout
while len(got) < n and time.monotonic() < deadline:
    m = bus.recv(1.0)
    if m is not None:
        got.append([m.arbitration_id, m.data.hex(), m.is_extended_id])
bus.shutdown()
print(json.dumps(got), flush=True)
"""

SENDER = r"""
import sys, time
import can
n = int(sys.argv[1])
with can.Bus(interface="socketcan", channel="vcan0") as bus:
    for i in range(n):
        bus.send(can.Message(arbitration_id=0x18A, is_extended_id=False,
                             data=bytes([i, 0x5A, 0xA5 ^ i])))
        time.sleep(0.010)
"""


def fail(msg: str, t0: float) -> None:
    print(f"VCAN-SMOKE FAIL: {msg} ({time.monotonic() - t0:.1f} s)", flush=True)
    sys.exit(1)


def listeners(channel: str) -> int:
    """Receive-all sockets bound to ``channel`` (candump and python-can register one each)."""
    try:
        text = Path("/proc/net/can/rcvlist_all").read_text()
    except OSError:
        return -1
    return sum(1 for line in text.splitlines() if line.split()[:1] == [channel])


def parse_candump(path: Path) -> list[tuple[int, bytes]]:
    """``candump -L`` lines: ``(1700000000.123456) vcan0 18A#005AA5``."""
    frames = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[1] == CHANNEL and "#" in parts[2]:
            can_id, data = parts[2].split("#", 1)
            frames.append((int(can_id, 16), bytes.fromhex(data)))
    return frames


def main() -> None:
    t0 = time.monotonic()
    out = Path(os.environ.get("VM_OUT", "/tmp"))
    py = sys.executable
    dump_log = out / "vcan_smoke.candump.log"
    with dump_log.open("w") as fh:
        candump = subprocess.Popen(["candump", "-L", CHANNEL], stdout=fh)
    receiver = subprocess.Popen([py, "-c", RECEIVER, str(len(EXPECTED)), "120"],
                                stdout=subprocess.PIPE, text=True)
    try:
        assert receiver.stdout is not None
        if receiver.stdout.readline().strip() != "ready":
            fail("the python-can receiver did not start", t0)
        # Both sockets must be bound before the first frame: wait until the kernel lists them.
        deadline = time.monotonic() + 30
        while 0 <= listeners(CHANNEL) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        if listeners(CHANNEL) < 0:
            time.sleep(2)  # no /proc/net/can: give candump time to bind
        if candump.poll() is not None:
            fail(f"candump exited early (rc {candump.returncode})", t0)
        sender = subprocess.run([py, "-c", SENDER, str(N_PY)], capture_output=True, text=True,
                                timeout=300)
        if sender.returncode != 0:
            fail(f"the python-can sender failed: {sender.stderr.strip()[-500:]}", t0)
        subprocess.run(["cansend", CHANNEL, "7FF#C0FFEE"], check=True, timeout=30)
        rx_out = receiver.communicate(timeout=180)[0]
    finally:
        if receiver.poll() is None:
            receiver.kill()
        time.sleep(0.5)  # let candump write the last frame
        candump.send_signal(signal.SIGINT)
        try:
            candump.wait(10)
        except subprocess.TimeoutExpired:
            candump.kill()
    lines = [ln for ln in rx_out.splitlines() if ln.startswith("[")]
    got = [(i, bytes.fromhex(d)) for i, d, ext in json.loads(lines[-1]) if not ext] if lines else []
    dumped = parse_candump(dump_log)
    summary = (f"receiver {len(got)}/{len(EXPECTED)}, candump {len(dumped)}/{len(EXPECTED)} "
               f"on {CHANNEL}, kernel {platform.release()}")
    if got != EXPECTED:
        first = next((k for k, (a, b) in enumerate(zip(got, EXPECTED, strict=False)) if a != b),
                     min(len(got), len(EXPECTED)))
        fail(f"{summary}: the receiver's frames differ from the expected from index {first}", t0)
    if dumped != EXPECTED:
        fail(f"{summary}: candump's log differs from the frames sent", t0)
    print(f"VCAN-SMOKE PASS: {summary}, all in order ({time.monotonic() - t0:.1f} s)",
          flush=True)


if __name__ == "__main__":
    main()
