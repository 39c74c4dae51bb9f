"""`tcf-hil soak`: a minute of the whole bench live at 2048x10 with the reference SIC (what
CI runs; `--minutes 10` is the full soak), its figures, and the pieces it stands on: the
back-and-forth track, the bounded pacing statistics, and memory read from /proc."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from _tty import run_in_terminal
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.lidar import SendStats
from tcf_hil.run.soak import RssTrace, process_rss_kb, soak_scenario
from tcf_hil.scenario import load_scenario
from tcf_hil.world.track import Trajectory

ENV = dict(os.environ, COLUMNS="200", PYTHONUNBUFFERED="1")


@pytest.mark.parametrize("seconds", [60.0, 600.0, 1800.0])
def test_the_soak_track_drives_a_stretch_back_and_forth_long_enough(seconds: float) -> None:
    scn = load_scenario("forest-v")
    soak, pass_s = soak_scenario(scn, seconds)
    tr = soak.track
    assert tr.passes >= 4 or seconds > 1000
    assert tr.pass_offset_m == 0.0 and tr.start_m == scn.track.start_m
    from tcf_hil.world.forest import generate_forest

    traj = Trajectory.from_config(tr, generate_forest(soak).terrain, 0)
    assert traj.duration_ns / 1e9 >= seconds
    assert pass_s == pytest.approx(abs(tr.end_m[1] - tr.start_m[1]) / tr.speed_m_s)
    with pytest.raises(ValueError, match="longer than"):
        soak_scenario(scn, 3 * 3600.0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-2_000_000, 2_000_000), min_size=1, max_size=400))
def test_pacing_histogram_percentiles_match_the_exact_ones(late: list[int]) -> None:
    s = SendStats()
    for ns in late:
        s.add_late(ns)
    a = np.abs(np.array(late)) / 1000.0
    p50, p99 = s.pacing_us()
    # the histogram gives the upper edge of the 1 us bin of the exact order statistic
    for got, q in ((p50, 0.5), (p99, 0.99)):
        exact = np.sort(a)[max(0, int(np.ceil(q * len(a))) - 1)]
        assert exact <= got <= exact + 1.0 + 1e-9 or (exact >= 100_000 and got == 100_001)


def test_memory_growth_uses_medians_after_the_warm_up() -> None:
    t = RssTrace()
    for i, kb in enumerate([100, 900, 1000, 1000, 1010, 5000, 1020, 1030, 1040]):
        t.add(float(i), {"bench": kb})
    g = t.growth(warmup_s=2.0)["bench"]
    # after the warm-up: medians of (1000, 1000, 1010) and (1020, 1030, 1040); 5000 alone
    # (a sample caught mid-allocation) decides nothing
    assert g["growth_percent"] == pytest.approx(3.0)  # 1000 -> 1030
    assert g["rss_mb_peak"] == round(5000 / 1024, 1)
    assert process_rss_kb(os.getpid()) > 10_000
    assert process_rss_kb(2**22 + 12345) is None


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_a_one_minute_soak_at_2048x10(tmp_path: Path) -> None:
    """In a terminal, as a person runs it: the live display follows the minute."""
    out = tmp_path / "soak"
    rc, screen = run_in_terminal([sys.executable, "-m", "tcf_hil.cli", "soak", "--minutes",
                                  "1", "--out", str(out)], env=ENV)
    assert rc in (0, 3), "\n".join(screen[-40:])
    doc = json.loads((out / "soak.json").read_text())
    assert (rc == 0) == doc["ok"]
    live = [x for x in screen if "streaming" in x and " · CAN poses " in x]
    assert len(live) >= 100, "\n".join(screen[-40:])  # 60 s at 4 redraws a second
    sims = [float(m[1]) for x in live if (m := re.search(r"sim ([\d.]+)/60\.0 s", x))]
    assert len(sims) >= 100 and sims == sorted(sims) and sims[-1] >= 55.0
    assert doc["status"] == "complete" and doc["mode"] == "2048x10"
    assert doc["frames_sent"] == 600  # 60 s at 10 Hz
    assert doc["frames_mapped_by_sic"] >= 0.95 * doc["frames_sent"]
    assert doc["frames_lost_at_receiver"] <= 6
    assert 0 < doc["pacing_us_p50"] <= doc["pacing_us_p99"]
    mem = doc["memory"]
    assert {"bench", "frame producer", "sic"} <= set(mem)
    for role in ("bench", "frame producer"):
        assert mem[role]["samples"] >= 10
        assert mem[role]["growth_percent"] < doc["max_growth_percent"], mem
    assert not (out / "lidar.pcap").exists()  # not kept: 16 MB/s
    assert "frames lost at the receiver" in (out / "soak.md").read_text()
    assert doc["f1_all"] is not None
