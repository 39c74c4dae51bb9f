"""Real time under load (issue 45): a natural stand at 2048x10 streamed from the render store
while the program under test burns a core sends its track packets on time.

The aim (every track packet within 1 ms of its due time) is a benchmark's figure
(``benchmarks/bench_realtime.py``); this test holds a loose floor, measured against the
machine itself: on a virtual machine a vCPU the host does not run sends nothing, so the bench
is held to what a bare pacer waking at the same interval under SCHED_FIFO gets just before
the run with a core as busy (``emulators.pacing.wake_floor``), not to a figure a busy host
cannot give; where the host withheld more than :data:`STEAL_SKIP_MS_PER_S` during the track
and the floor was missed, the test skips and says why."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from emulators.pacing import wake_floor
from tests.tcf_hil.test_sic_field import pine_thinning_corner

# Above this steal (ms of CPU a second the host withheld from this VM's two vCPUs, during
# the track) the machine gives no real time to measure: seen 0.4-15 ms/s on quiet hours and
# 40-390 ms/s on busy ones (README, "Benchmarks"); a run that misses the floor then skips.
STEAL_SKIP_MS_PER_S = 30.0

# a program under test that publishes an empty forest and then keeps one core busy
BURNER = ("{python} -c \"import json; print(json.dumps({'objects': []}), flush=True)\n"
          "while True: pass\"")


@pytest.mark.slow  # about 2 minutes: .ci/run's second lane
def test_a_natural_stand_at_2048x10_goes_out_on_time_beside_a_busy_program(tmp_path: Path
                                                                          ) -> None:
    toml = pine_thinning_corner(tmp_path / "corner.toml", 6.0)
    env = dict(os.environ, TCF_HIL_CACHE=str(tmp_path / "cache"), COLUMNS="200")
    tcf = [sys.executable, "-m", "tcf_hil.cli"]
    p = subprocess.run([*tcf, "render", str(toml), "--mode", "2048x10"], env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stdout + p.stderr[-2000:]

    interval_ns = round(1e9 / (10 * 2048 / 16))  # a lidar packet every 781 us
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])  # the same load
    try:
        floor = wake_floor(interval_ns, 8.0)
    finally:
        burner.kill()
        burner.wait()
    floor_late = sum(e >= 1000 for e in floor) / len(floor)

    out = tmp_path / "run"
    p = subprocess.run([*tcf, "run", str(toml), "--mode", "2048x10", "--sic", BURNER,
                        "--grace", "1", "--ready-timeout", "0", "--out", str(out)],
                       env=env, capture_output=True, text=True, timeout=900)
    lidar = json.loads((out / "manifest.json").read_text())["lidar"]
    assert lidar["render"]["from_store"], p.stderr[-2000:]
    frames = lidar["track"]["frames"]
    assert frames >= 100, lidar  # 12 m at the track's speed
    packets = frames * 2048 // 16  # the track's lidar packets (the IMU's: a few more)
    late = lidar["track_packets_late_1ms"]
    # the bench may not add lateness of its own: at most what the machine's floor shows
    # (three times over, for a host whose steal comes in bursts) and 0.5 % besides
    allowed = max(0.005, 3.0 * floor_late + 0.002)
    steal = lidar["track_steal_ms_per_s"]
    print(f"{late} of {packets} track packets 1 ms or more late (p50/p99 "
          f"{lidar['track_pacing_us_p50_p99']} us); the bare pacer: {sum(floor) and max(floor)}"
          f" us at most, {100 * floor_late:.2f} % of wake-ups 1 ms late; steal "
          f"{lidar['track_steal_ms_per_s']} ms/s; late frames {lidar['late_frames']}")
    if late / packets > allowed and steal is not None and steal > STEAL_SKIP_MS_PER_S:
        pytest.skip(f"the hypervisor withheld {steal:.0f} ms/s of CPU during the track: no "
                    f"real time to test ({late} of {packets} packets late)")
    assert late / packets <= allowed, (
        f"{late} of {packets} track packets 1 ms or more late; the bare pacer's floor "
        f"{100 * floor_late:.2f} % of wake-ups; steal {lidar.get('track_steal_ms_per_s')} "
        f"ms/s; frames late from the producer {lidar['frames_late_from_producer']}")
    assert lidar["sender_realtime"] in (True, False)
    if lidar["track_packets_late_1ms"]:  # the run said so, in one line
        assert "track packet(s) left 1 ms or more late" in p.stderr
