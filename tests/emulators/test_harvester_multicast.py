"""python-can's udp_multicast bus: refused in the host network namespace (multicast would leave
the machine), and working end to end inside a network namespace this test makes for itself
(`unshare -n`, loopback up, 224.0.0.0/4 routed to lo): `tcf-hil harvester run` in one process,
a python-can consumer in another, every pose within quantisation of the trajectory truth."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tcf_hil.devices.harvester import HarvesterModel, heading_error_deg
from tcf_hil.scenario import load_scenario
from tcf_hil.world.forest import generate_forest

GROUP = "239.74.163.2"
SCENARIO = "forest-ii"
REPO = Path(__file__).resolve().parents[2]

# Runs inside the private namespace: the consumer joins the group first, then the harvester.
GUEST = r"""
import json, subprocess, sys, time, can
from protocols.harvester import PoseAssembler
group = sys.argv[1]
bus = can.Bus(interface="udp_multicast", channel=group, fd=False)
proc = subprocess.Popen([sys.executable, "-m", "tcf_hil.cli", "harvester", "run", sys.argv[2],
                         "--can", "udp_multicast:" + group, "--duration", "3", "--speed", "3"],
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
asm, poses = PoseAssembler(10), []
def take(m):
    if m is not None and (p := asm.feed(m.arbitration_id, bytes(m.data))) is not None:
        poses.append([p.time_us, p.x_m, p.y_m, p.z_m, p.heading_deg, p.pitch_deg, p.roll_deg])
while proc.poll() is None:
    take(bus.recv(0.1))
while (m := bus.recv(0.3)) is not None:
    take(m)
bus.shutdown()
out, err = proc.communicate()
print(json.dumps({"rc": proc.returncode, "stdout": out, "stderr": err[-2000:], "poses": poses}))
"""


def _private_netns() -> str | None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is missing"
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"cannot create a network namespace: {probe.stderr.strip()}"
    return None


def test_udp_multicast_is_refused_where_it_would_leave_the_machine() -> None:
    route = subprocess.run(["ip", "route", "show", "default"], capture_output=True, text=True)
    if not route.stdout.strip():
        pytest.skip("this namespace has no default route: multicast would stay here")
    proc = subprocess.run([sys.executable, "-m", "tcf_hil.cli", "harvester", "run", SCENARIO,
                           "--can", f"udp_multicast:{GROUP}", "--duration", "1"],
                          capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode != 0
    assert "udp_multicast refused" in proc.stderr and "unshare -n" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_harvester_over_udp_multicast_in_a_private_namespace() -> None:
    why = _private_netns()
    if why:
        pytest.skip(why)
    script = ("ip link set lo up && ip route add 224.0.0.0/4 dev lo && "
              'exec "$0" -c "$1" "$2" "$3"')
    proc = subprocess.run(["unshare", "-n", "sh", "-c", script, sys.executable, GUEST, GROUP,
                           SCENARIO], capture_output=True, text=True, timeout=180, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["rc"] == 0, res["stderr"]
    assert "udp_multicast:" + GROUP in res["stdout"]
    poses = res["poses"]
    # 3 s simulated at 100 Hz: about 300 SYNCs, fewer if the host stalls (the node skips a
    # late period rather than bursting, as a real one would). Every SYNC sent is a pose that
    # must arrive whole over the group.
    sent = re.search(r"(\d+)\s+SYNC\s+sent", res["stdout"])
    assert sent, res["stdout"]
    assert int(sent.group(1)) >= 100, res["stdout"]
    assert len(poses) >= int(sent.group(1)) - 1, (len(poses), res["stdout"])
    scn = load_scenario(SCENARIO)
    forest = generate_forest(scn)
    model = HarvesterModel.from_scenario(scn, forest.terrain, forest.seed)
    times = [p[0] for p in poses]
    assert times == sorted(times) and len(set(times)) == len(times)
    for t_us, x, y, z, heading, pitch, roll in poses:
        tr = model.truth_pose(t_us)
        assert max(abs(x - tr.x_m), abs(y - tr.y_m), abs(z - tr.z_m)) <= 0.0005 + 1e-9
        assert heading_error_deg(heading, tr.heading_deg) <= 0.005 + 1e-9
        assert max(abs(pitch - tr.pitch_deg), abs(roll - tr.roll_deg)) <= 0.005 + 1e-9
