"""Faults in a whole run: `--fault` and the scenario's [faults] section; a pcap with faults read
packet by packet and by ouster-sdk; the reference SIC, as its own process on the wire,
surviving every kind of fault at once (a re-initialised sensor included) with the faults
logged beside its score; and the SIC's pose assembly refusing a pose torn by a lost TPDO."""

from __future__ import annotations

import collections
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _tty import run_in_terminal
from ouster.sdk import pcap as opcap

from protocols.harvester import Pose, encode_pose
from protocols.ouster import SensorMetadata, decode_lidar_packet
from protocols.pcap import read_udp
from tcf_hil.devices.faults import apply_fault_options, read_fault_log
from tcf_hil.devices.offline import record_pcap
from tcf_hil.errors import ConfigError
from tcf_hil.run._live import LOSSES
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_toml
from tcf_hil.world.faults import faults_active

TCF = [sys.executable, "-m", "tcf_hil.cli"]
ENV = dict(os.environ, COLUMNS="200", PYTHONUNBUFFERED="1")

SMALL = {"name": "faults-small", "plot": {"size_m": [20.0, 30.0]}, "stems": {"count": 12},
         "track": {"start_m": [0.0, -12.0, 2.0], "end_m": [0.0, 12.0, 2.0],
                   "speed_m_s": 2.0}}


def test_fault_options_are_checked_like_scenario_keys() -> None:
    scn = load_scenario("forest-ii")
    assert not faults_active(scn.faults)
    f = apply_fault_options(scn, ["udp.loss=0.01", "can.bus_off_at_s=[2, 4.5]",
                                  "faults.udp.ports=lidar"])
    assert f.faults.udp.loss == 0.01 and f.faults.can.bus_off_at_s == (2.0, 4.5)
    assert f.faults.udp.ports == "lidar" and faults_active(f.faults)
    # the section round-trips through the resolved TOML (what a sweep cell carries)
    assert load_scenario_text(scenario_to_toml(f)).faults == f.faults
    for bad, key in (("udp.loss=2", "faults.udp.loss"), ("udp.lose=0.1", "faults.udp.lose"),
                     ("can.bus_off_at_s=[-1]", "faults.can.bus_off_at_s[0]"),
                     ("nope.x=1", "faults.nope"), ("udp.loss", "--fault")):
        with pytest.raises(ConfigError) as err:
            apply_fault_options(scn, [bad])
        assert key in str(err.value)


def load_scenario_text(text: str) -> object:
    import tomllib

    return scenario_from_dict(tomllib.loads(text))


def test_cli_rejects_a_bad_fault_in_one_line() -> None:
    p = subprocess.run([*TCF, "lidar", "pcap", "forest-ii", "--out", "/tmp/never-written",
                        "--fault", "udp.loss=1.5"], capture_output=True, text=True, env=ENV,
                       timeout=120)
    assert p.returncode == 1
    assert "faults.udp.loss" in p.stderr and "1.5" in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1
    assert not Path("/tmp/never-written").exists()


def test_pcap_with_faults_holds_exactly_what_was_sent(tmp_path: Path) -> None:
    """Dropouts skip frame ids, a re-initialisation switches init_id and restarts frame_id,
    random loss removes exactly the datagrams faults.jsonl names."""
    scn = apply_fault_options(scenario_from_dict(SMALL), [
        "lidar.dropout_at_s=[0.55]", "lidar.dropout_frames=2", "lidar.reinit_at_s=[1.5]",
        "lidar.reinit_gap_s=0.3", "udp.loss=0.02", "udp.ports=lidar"])
    r = record_pcap(scn, tmp_path, mode="512x10", max_frames=25)
    meta = SensorMetadata.loads((tmp_path / "metadata.json").read_text())
    fmt = meta.packet_format
    events = read_fault_log(tmp_path / "faults.jsonl")
    kinds = collections.Counter(e["kind"] for e in events)
    assert kinds["lidar_dropout"] == 2 and kinds["lidar_reinit"] == 1
    reinit = next(e for e in events if e["kind"] == "lidar_reinit")
    assert reinit["init_id"] == meta.init_id != reinit["init_id_old"]  # the file is the new one
    packets = [d.payload for d in read_udp((tmp_path / "lidar.pcap").read_bytes())
               if d.dst_port == meta.udp_port_lidar]
    seen = [(p.init_id, p.frame_id) for p in (decode_lidar_packet(fmt, b) for b in packets)]
    lost = sum(e["count"] for e in events if e["kind"] == "udp_loss")
    frames_sent = 25 - 2 - 3  # two dropped, three silent (1.5 s to 1.8 s)
    assert r.frames == 25
    assert len(packets) == frames_sent * fmt.packets_per_frame - lost
    before = sorted({f for i, f in seen if i == reinit["init_id_old"]})
    after = sorted({f for i, f in seen if i == meta.init_id})
    assert before == [0, 1, 2, 3, 4, 7, 8, 9, 10, 11, 12, 13, 14]  # 5, 6 dropped at 0.55 s
    assert after == list(range(7))  # frame_id from 0 after the 0.3 s of silence
    # ouster-sdk, given the metadata after the re-initialisation, reads those frames
    src = opcap.PcapFrameSetSource(str(tmp_path / "lidar.pcap"),
                                   meta=[str(tmp_path / "metadata.json")])
    ids = [fs[0].frame_id for fs in src]
    assert ids == after
    # nothing of a fault-free capture changes but what the faults named
    clean = tmp_path / "clean"
    record_pcap(scenario_from_dict(SMALL), clean, mode="512x10", max_frames=25)
    assert not (clean / "faults.jsonl").exists()
    n_clean = sum(1 for d in read_udp((clean / "lidar.pcap").read_bytes())
                  if d.dst_port == meta.udp_port_lidar)
    assert n_clean == 25 * fmt.packets_per_frame


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_the_reference_sic_survives_every_fault_at_once(tmp_path: Path) -> None:
    """A live run, the SIC its own process: UDP loss, bursts, duplicates, reordering and
    jitter; frame dropouts and a re-initialised sensor; CAN loss, late poses, a bus-off and
    an NMT reset. The run completes, every fault is logged with its time, the SIC re-reads
    the metadata once, and its forest is still right (Forest II, 24 stems). Run in a
    terminal: its live display counts exactly the frames the faults struck out."""
    out = tmp_path / "run"
    faults = ["udp.loss=0.01", "udp.burst_rate=0.0005", "udp.burst_packets=8",
              "udp.duplicate=0.01", "udp.reorder=0.01", "udp.jitter_us=100",
              "lidar.dropout=0.02", "lidar.reinit_at_s=[6]", "can.loss=0.01",
              "can.pose_delay_ms=30", "can.bus_off_at_s=[9]", "can.bus_off_s=0.5",
              "can.nmt_reset_at_s=[12]"]
    # the exact sensor: what is scored here is the faults' effect, not the beam's
    rc, screen = run_in_terminal([*TCF, "run", "forest-ii", "--mode", "512x10", "--speed",
                                  "2", "--sensor", "ideal", "--out", str(out),
                                  *(a for f in faults for a in ("--fault", f))], env=ENV)
    assert rc == 0, "\n".join(screen[-40:])
    score = json.loads((out / "score.json").read_text())
    assert score["status"] == "complete"
    injected = score["faults"]
    for kind in ("udp_loss", "udp_burst_loss", "udp_duplicate", "udp_reorder", "udp_jitter",
                 "lidar_dropout", "lidar_reinit", "can_loss", "can_pose_delay", "can_bus_off",
                 "can_bus_off_recovered", "can_nmt_reset", "can_nmt_start"):
        assert injected[kind]["count"] >= 1, kind
    assert abs(injected["lidar_reinit"]["first_s"] - 6.0) < 0.11
    assert abs(injected["can_bus_off"]["first_s"] - 9.0) < 0.05
    log = read_fault_log(out / "faults.jsonl")
    assert len(log) >= sum(1 for _ in injected)
    assert all(set(e) >= {"t_s", "source", "kind"} for e in log)
    man = json.loads((out / "manifest.json").read_text())
    assert man["faults"]["config"]["udp"]["loss"] == 0.01
    # the SIC followed the sensor to its new init_id and kept going
    index = [json.loads(x) for x in (out / "sic" / "index.ndjson").read_text().splitlines()]
    last = json.loads((out / "sic" / index[-1]["file"]).read_text())
    assert last["sic"]["sensor_reinits"] == 1
    assert last["sic"]["frames"] > 0.8 * man["lidar"]["frames_sent"]
    meta = SensorMetadata.loads((out / "metadata.json").read_text())
    assert meta.init_id == log[[e["kind"] for e in log].index("lidar_reinit")]["init_id"]
    m = score["all_trees"]
    assert m["f1"] >= 0.9 and m["evaluation_score_percent"] >= 75.0
    assert "Injected faults" in (out / "report.html").read_text()
    struck = {e["frame"] for e in log if e["kind"] in LOSSES}
    shown = [int(m[1]) for x in screen if (m := re.search(r"frames \d+/\d+.*, lost (\d+)", x))]
    assert shown and shown == sorted(shown) and shown[-1] == len(struck), (shown, len(struck))


def test_a_pose_torn_by_a_lost_tpdo_is_not_used() -> None:
    """TPDO1-3 of one SYNC make a pose; with TPDO1 lost the parts left from the previous
    SYNC would put the machine where it was 10 ms earlier, so the SIC skips that pose."""
    import canopen

    from tcf_hil.sic._online import CanPose, PoseTrack, SicConfig

    net = canopen.Network()
    track = PoseTrack()
    cp = CanPose(SicConfig(node_id=10), track, network=net)
    for k in range(5):
        frames = encode_pose(Pose(float(k), 0.0, 1.0, 90.0, 0.0, 0.0, 1.0, k * 10_000), 10)
        if k == 2:
            frames = [f for f in frames if f[0] != 0x18A]  # TPDO1 (x, y) lost
        for cob, data in frames:
            net.notify(cob, bytearray(data), k * 0.01)
    assert track.received == 4 and cp.incomplete == 1
    pos, _rot = track.at(np.array([30_000_000.0]))  # type: ignore[misc]
    assert abs(pos[0, 0] - 3.0) < 1e-3
