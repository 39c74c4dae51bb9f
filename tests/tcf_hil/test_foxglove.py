"""Foxglove (issue 46): a run as an MCAP file of Foxglove's schemas, read back with the
``mcap`` library and its protobuf decoder (the cloud's points where the LAS export puts them,
coloured by what they hit; the stems coloured by outcome; the score), and a live run served
over Foxglove's WebSocket protocol to a real WebSocket client."""

from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from tcf_hil.cli import main
from tcf_hil.devices.offline import record_pcap
from tcf_hil.results.export import CLOUD_DTYPE, run_cloud
from tcf_hil.results.foxglove import COMPONENT_COLOURS, TOPICS, layout_bytes
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict

UTM = (512_345.0, 6_912_345.0, 120.0)
# foxglove.PackedElementField's numeric types (Foxglove's schema docs): UINT8 1, UINT16 3,
# UINT32 5, FLOAT32 7
_NUMERIC = {1: "u1", 3: "<u2", 5: "<u4", 7: "<f4"}


def _small_natural() -> dict:
    d = scenario_to_dict(load_scenario("pine-thinning"))
    d["name"] = "foxglove-small"
    d["plot"] = {"size_m": [24.0, 24.0], "origin_m": list(UTM)}
    d["stems"] = {**d["stems"], "count": 60}
    d["track"] = {**d["track"], "start_m": [0.0, -10.0, 2.0], "end_m": [0.0, 10.0, 2.0],
                  "speed_m_s": 2.0}
    return d


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small natural stand's capture (3 frames) with two publications of a SIC: the
    first five trees where they stand, then those and a stem where none stands."""
    out = tmp_path_factory.mktemp("fox") / "run"
    record_pcap(scenario_from_dict(_small_natural()), out, mode="512x10", max_frames=3)
    gt = json.loads((out / "ground_truth.json").read_text())
    objs = [{"id": i + 1, "class": o["class"], "cp": o["cp"], "dbh": o["dbh"], "h": o["h"]}
            for i, o in enumerate(gt["objects"][:5])]
    fp = {"id": 99, "class": objs[0]["class"], "cp": [UTM[0] + 500.0, UTM[1] + 500.0, UTM[2]],
          "dbh": 0.3, "h": 12.0}
    (out / "sic").mkdir()
    t0 = 1_767_225_600 * 10**9
    rows = []
    for n, objects in ((1, objs), (2, objs + [fp])):
        doc = {k: v for k, v in gt.items() if k not in ("objects", "returns_by_component")}
        doc["objects"], doc["total_objects_count"] = objects, len(objects)
        (out / "sic" / f"{n:04d}.json").write_text(json.dumps(doc))
        rows.append({"n": n, "file": f"{n:04d}.json", "via": "file", "arrival_s": 0.1 * n,
                     "bytes": 1, "valid": True, "error": None, "objects": len(objects),
                     "unix_ns": t0 + n * 100_000_000})
    (out / "sic" / "index.ndjson").write_text("".join(json.dumps(r) + "\n" for r in rows))
    first = int((out / "sensor_poses.csv").read_text().splitlines()[1].split(",")[0])
    (out / "manifest.json").write_text(json.dumps(
        {"clock": {"sim_t0_ns": first, "unix_ns_at_sim_t0": t0, "speed": 1.0}}))
    (out / "score.json").write_text(json.dumps({"scored_publication": 2, "timeline": [
        {"n": 1, "wc_all": 10.0, "wc_seen": 20.0}, {"n": 2, "wc_all": 9.0, "wc_seen": 18.0}]}))
    return out


def _messages(path: Path) -> list[tuple[str, int, object]]:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out = []
        for _schema, channel, message in reader.iter_messages():
            out.append((channel.topic, message.log_time, message))
        return out


def _decode(path: Path, topic: str) -> list[object]:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [d for _s, _c, _m, d in reader.iter_decoded_messages(topics=[topic])]


def test_the_mcap_holds_the_runs_scene(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    assert json.loads((tmp_path / "run.layout.json").read_bytes()) == json.loads(
        layout_bytes())
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chans = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert chans == {t: ("tcf_hil.Score" if s == "json" else s) for t, s in TOPICS.items()}
    counts = {summary.channels[k].topic: v
              for k, v in summary.statistics.channel_message_counts.items()}
    assert counts["/lidar/points"] == counts["/tf"] == 3
    assert counts["/stems/sic"] == counts["/score"] == 2
    assert counts["/track"] == counts["/stems/truth"] == 1
    with open(out, "rb") as f:  # as written, not as the reader would sort them
        times = [m.log_time for _s, _c, m in make_reader(f).iter_messages(
            log_time_order=False)]
    assert times == sorted(times)  # written in time order, on the run's clock
    assert 1_767_225_600 * 10**9 <= times[0] < times[-1] < 1_767_225_601 * 10**9


def test_the_clouds_points_are_the_exports(run_dir: Path, tmp_path: Path) -> None:
    """Every frame's points (float32 from the offset in the channel's metadata) are the LAS
    export's world points to the float's precision, each coloured by what it hit."""
    out = tmp_path / "run.mcap"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    clouds = _decode(out, "/lidar/points")
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    meta = next(c.metadata for c in summary.channels.values() if c.topic == "/lidar/points")
    off = np.array([float(v) for v in meta["offset_m"].split()])
    assert off.tolist() == [512_000.0, 6_912_000.0, 0.0]  # the kilometre near the start
    _info, frames = run_cloud(run_dir)
    want = list(frames)
    assert len(clouds) == len(want)
    for pc, pts in zip(clouds, want, strict=True):
        names = [fl.name for fl in pc.fields]  # type: ignore[attr-defined]
        assert names[:3] == ["x", "y", "z"] and {"red", "green", "blue", "alpha"} <= set(names)
        dt = np.dtype({"names": names, "offsets": [fl.offset for fl in pc.fields],  # type: ignore[attr-defined]
                       "formats": [_NUMERIC[fl.type]
                                   for fl in pc.fields],  # type: ignore[attr-defined]
                       "itemsize": pc.point_stride})  # type: ignore[attr-defined]
        got = np.frombuffer(pc.data, dt)  # type: ignore[attr-defined]
        assert pc.frame_id == "world" and len(got) == len(pts)  # type: ignore[attr-defined]
        for i, k in enumerate("xyz"):
            assert np.abs(got[k].astype(np.float64) + off[i] - pts[k]).max() < 2e-3
        for code, rgb in COMPONENT_COLOURS.items():
            hit = pts["component"] == code
            if hit.any():
                assert (got["red"][hit] == rgb[0]).all() and (got["green"][hit] == rgb[1]).all()
                assert (got["blue"][hit] == rgb[2]).all()
        assert (got["stem_id"] == pts["stem_id"]).all()
    assert CLOUD_DTYPE.names is not None


def test_stems_carry_their_outcomes(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    truth = _decode(out, "/stems/truth")[0]
    gt = json.loads((run_dir / "ground_truth.json").read_text())
    cyl = truth.entities[0].cylinders  # type: ignore[attr-defined]
    assert len(cyl) == len(gt["objects"])
    # the truth as scored at the end: five found (green or orange), the rest missed
    green = (0x00 / 255, 0x9E / 255, 0x73 / 255)
    orange = (0xE6 / 255, 0x9F / 255, 0x00 / 255)
    found = [c for c in cyl if (round(c.color.r, 3), round(c.color.g, 3), round(c.color.b, 3))
             in {tuple(round(v, 3) for v in green), tuple(round(v, 3) for v in orange)}]
    assert len(found) == 5
    o = gt["objects"][0]
    c0 = cyl[0]
    assert c0.size.x == pytest.approx(o["dbh"]) and c0.size.z == pytest.approx(o["h"])
    assert c0.pose.position.z == pytest.approx(o["cp"][2] + o["h"] / 2, abs=1e-6)
    sic = _decode(out, "/stems/sic")
    assert [len(m.entities[0].cylinders) for m in sic] == [5, 6]  # type: ignore[attr-defined]
    blue = sic[1].entities[0].cylinders[5].color  # type: ignore[attr-defined]
    assert (round(blue.r * 255), round(blue.g * 255), round(blue.b * 255)) == (0, 0x72, 0xB2)
    scores = [json.loads(m.data) for topic, _t, m in _messages(out)  # type: ignore[attr-defined]
              if topic == "/score"]
    assert [(s["n"], s["objects"], s["wc_all"]) for s in scores] == [(1, 5, 10.0), (2, 6, 9.0)]


def test_a_directory_that_is_not_a_run_is_one_line(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "x.mcap")]) == 1
    err = capsys.readouterr().err.strip()
    assert "lidar.pcap" in err and "\n" not in err
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.slow  # the second lane (.ci/run): a live run with the reference SIC, ~30 s
def test_a_live_run_serves_foxglove_clients(tmp_path: Path) -> None:
    """``tcf-hil run --foxglove 0``: a WebSocket client speaking Foxglove's protocol sees the
    channels advertised, subscribes and gets the cloud, the sensor's transform, the truth, the
    SIC's stems and its score while the run streams (stderr a pipe: no terminal line, the
    view all the same)."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    WANT = ("/lidar/points", "/tf", "/stems/truth", "/stems/sic", "/score")

    env = dict(os.environ, COLUMNS="200", PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tcf_hil.cli", "run", "forest-ii", "--mode", "512x10",
         "--duration", "6", "--render", "ahead", "--foxglove", "0", "--out",
         str(tmp_path / "run")], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, env=env,
        text=True)
    try:
        assert proc.stderr is not None
        port = None
        deadline = time.monotonic() + 120
        while port is None and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            m = re.search(r"Foxglove: ws://127\.0\.0\.1:(\d+)", line)
            port = int(m.group(1)) if m else None
        assert port is not None, "the run did not say where Foxglove connects"
        got: dict[str, int] = {}
        # (foxglove-sdk 0.30 speaks the protocol as foxglove.sdk.v1; earlier servers as
        # foxglove.websocket.v1: the same messages)
        with connect(f"ws://127.0.0.1:{port}", open_timeout=10,
                     subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:  # type: ignore[list-item]
            channels: dict[int, str] = {}
            subscribed = False
            end = time.monotonic() + 90
            while time.monotonic() < end and not set(WANT) <= set(got):
                try:
                    msg = ws.recv(timeout=2)
                except TimeoutError:
                    continue
                except ConnectionClosed:  # the run ended
                    break
                if isinstance(msg, str):
                    doc = json.loads(msg)
                    if doc.get("op") == "advertise":
                        for ch in doc["channels"]:
                            channels[ch["id"]] = ch["topic"]
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid in channels]}))
                        subscribed = True
                elif subscribed and msg[0] == 1:  # message data: op, subscription, time
                    sub, = struct.unpack_from("<I", msg, 1)
                    topic = channels.get(sub, "?")
                    got[topic] = max(got.get(topic, 0), len(msg) - 13)
        assert set(WANT) <= set(got), got
        assert got["/lidar/points"] > 10_000  # a frame's points, not an empty cloud
        assert got["/stems/truth"] > 1_000  # forest-ii's 24 stems as cylinders
    finally:
        proc.terminate()
        proc.wait(60)


@pytest.mark.parametrize(("clock", "replay", "want_capture", "want_wall"), [
    # a live run at --speed 1: the capture's clock is the wall clock
    ({"sim_t0_ns": 60 * 10**9, "unix_ns_at_sim_t0": 10**18, "speed": 1.0}, None,
     10**18 + 5 * 10**9, 10**18 + 5 * 10**9),
    # at --speed 2 the capture's time runs twice as fast as the wall clock
    ({"sim_t0_ns": 60 * 10**9, "unix_ns_at_sim_t0": 10**18, "speed": 2.0}, None,
     10**18 + 10 * 10**9, 10**18 + 5 * 10**9),
    # a replay (at 0.5) of a run at speed 1, its first event (recording time 61 s) sent at
    # 2 * 10**18: a publication 5 s later is 2.5 s into the recording, at 63.5 s
    ({"sim_t0_ns": 60 * 10**9, "unix_ns_at_sim_t0": 10**18, "speed": 1.0},
     {"recording_ns": 61 * 10**9, "unix_ns": 2 * 10**18, "speed": 0.5},
     10**18 + 3_500_000_000, 10**18 + 3_500_000_000),
])
def test_publications_land_on_the_frames_clock(tmp_path: Path, clock: dict,
                                               replay: dict | None, want_capture: int,
                                               want_wall: int) -> None:
    from tcf_hil.recording.rundir import RunDir
    from tcf_hil.results.foxglove import publications

    (tmp_path / "sic").mkdir()
    arrived = (replay["unix_ns"] if replay else 10**18) + 5 * 10**9
    (tmp_path / "sic" / "index.ndjson").write_text(json.dumps(
        {"n": 1, "file": "0001.json", "valid": True, "arrival_s": 5.0, "unix_ns": arrived})
        + "\n")
    man = {"clock": clock, **({"replay_clock": replay} if replay else {})}
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    assert publications(RunDir(tmp_path))[0][0] == want_capture
    assert publications(RunDir(tmp_path), wall=True)[0][0] == want_wall


def test_the_machines_pose_comes_from_its_can_log(tmp_path: Path) -> None:
    """/tf's world -> harvester (and the bag's /harvester/pose) is the pose the node sent:
    its TPDOs in can.log, decoded, less nothing but the datum; compass heading to yaw."""
    from protocols.harvester import Pose, encode_pose
    from tcf_hil.recording.rundir import RunDir
    from tcf_hil.results.foxglove import harvester_poses

    datum_mm = [512_345_000, 6_912_345_000, 120_000]
    lines = []
    for k in range(5):
        p = Pose(x_m=1.0 + k, y_m=2.0, z_m=0.5, heading_deg=0.0, pitch_deg=0.0,
                 roll_deg=0.0, speed_m_s=1.0, time_us=k * 100_000)
        for cob, data in encode_pose(p, 10):
            lines.append(f"({1_700_000_000 + k * 0.1:.6f}) vcan0 {cob:03X}#{data.hex().upper()}")
    (tmp_path / "can.log").write_text("\n".join(lines) + "\n")
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"can_node": {"node_id": 10, "datum_mm": datum_mm}}))
    got = list(harvester_poses(RunDir(tmp_path)))
    assert len(got) == 5
    t, xyz, q = got[2]
    assert t == pytest.approx(1_700_000_000.2e9, abs=2e3)
    assert xyz == pytest.approx([512_345 + 3.0, 6_912_345 + 2.0, 120.5], abs=1e-3)
    # heading 0 (north, +y) is yaw 90 degrees: a quarter turn about z
    assert q == pytest.approx([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], abs=1e-6)
