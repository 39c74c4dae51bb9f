"""The emulated OS0-64 judged by ouster-sdk: it reads our pcap, and its own XYZ, put into
the world with our sensor poses, lands on the ground-truth surfaces within the range quantum
plus the mesh tolerance."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from ouster.sdk import core
from ouster.sdk import pcap as opcap
from scipy.spatial import cKDTree

from emulators.lidar import ReturnModel
from tcf_hil.cli import main
from tcf_hil.devices.offline import record_pcap
from tcf_hil.scenario import Scenario, load_scenario, scenario_from_dict, with_sensor
from tcf_hil.world.forest import Forest, generate_forest

ROLLING = {"name": "rolling-small", "plot": {"size_m": [20.0, 30.0]},
           "terrain": {"kind": "rolling", "amplitude_m": 0.6, "wavelength_m": 15.0,
                       "tolerance_mm": 2.0},
           "stems": {"count": 20},
           "track": {"start_m": [0.0, -20.0, 2.0], "end_m": [0.0, 20.0, 2.0],
                     "speed_m_s": 2.0},
           "sensor": {"preset": "ideal"}}  # exact geometry: points on the true surfaces


def _poses(path: Path) -> dict[int, np.ndarray]:
    rows = list(csv.reader(path.open()))
    assert rows[0] == ["time_ns", "x", "y", "z", "qw", "qx", "qy", "qz"]
    return {int(r[0]): np.array([float(v) for v in r[1:]]) for r in rows[1:]}


def _rot(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


_TREES: dict[int, tuple[cKDTree, np.ndarray]] = {}


def _surface_errors(forest: Forest, pts: np.ndarray) -> np.ndarray:
    """Distance of each world point from the nearest true surface (stem or terrain). The
    centre lines are sampled every 5 mm: the nearest sample is then within 0.1 mm of the
    nearest centre-line point's distance for radii above 3 cm."""
    st = forest.stems
    key = id(st)
    if key not in _TREES:
        cs, rs = [], []
        for i in range(len(st)):
            s = np.arange(-st.below[i], st.length[i], 0.005)
            cs.append(st.centre(np.full(len(s), i), s))
            rs.append(st.radius(np.full(len(s), i), s))
        _TREES[key] = (cKDTree(np.vstack(cs)), np.concatenate(rs))
    tree, radii = _TREES[key]
    local = pts - forest.origin
    d, k = tree.query(local)
    stem = np.abs(d - radii[k])
    gx, gy = forest.terrain.gradient(local[:, 0], local[:, 1])
    terr = np.abs(local[:, 2] - forest.terrain.height(local[:, 0], local[:, 1])) / np.sqrt(
        1 + gx**2 + gy**2)
    return np.minimum(stem, terr)


def _sdk_world_points(out: Path) -> tuple[list[int], np.ndarray]:
    src = opcap.PcapFrameSetSource(str(out / "lidar.pcap"), meta=[str(out / "metadata.json")])
    lut = core.XYZLut(src.sensor_info[0], use_extrinsics=False)
    poses = _poses(out / "sensor_poses.csv")
    ids, pts = [], []
    for fs in src:
        fr = fs[0]
        assert fr.complete()
        ids.append(fr.frame_id)
        pose = np.array([poses[int(t)] for t in fr.timestamp])
        world = np.einsum("wij,hwj->hwi", _rot(pose[:, 3:]), lut(fr)) + pose[None, :, :3]
        pts.append(world[fr.field("RANGE") > 0])
    return ids, np.vstack(pts)


@pytest.mark.parametrize(("profile", "quantum"), [("RNG19_RFL8_SIG16_NIR16", 0.001),
                                                  ("LEGACY", 0.001),
                                                  ("RNG19_RFL8_SIG16_NIR16_DUAL", 0.001),
                                                  ("RNG15_RFL8_NIR8", 0.008)])
def test_sdk_points_land_on_the_true_surfaces(tmp_path: Path, profile: str,
                                              quantum: float) -> None:
    scn = scenario_from_dict(ROLLING)
    r = record_pcap(scn, tmp_path, mode="512x10", profile=profile, max_frames=4)
    ids, pts = _sdk_world_points(tmp_path)
    assert ids == [0, 1, 2, 3] and r.frames == 4
    assert len(pts) > 20_000
    err = _surface_errors(generate_forest(scn), pts)
    tol = max(scn.stems.tolerance_mm, scn.terrain.tolerance_mm) / 1000
    assert err.max() <= quantum / 2 + tol + 0.0002  # + centre-line sampling


@pytest.mark.parametrize("backend", ["embree", "open3d"])
def test_backends_agree_and_count_returns(tmp_path: Path, backend: str) -> None:
    scn = with_sensor(load_scenario("forest-ii"), "ideal")  # exact: on the true surfaces
    r = record_pcap(scn, tmp_path / backend, mode="512x10", backend=backend, max_frames=3)
    gt = json.loads((tmp_path / backend / "ground_truth.json").read_text())
    vis = json.loads((tmp_path / backend / "visibility.json").read_text())
    per_stem = {o["id"]: o["returns"] for o in gt["objects"]}
    assert sum(per_stem.values()) == vis["stem_returns"]
    assert vis["stems_seen"] == sum(1 for v in per_stem.values() if v) == r.stems_seen
    assert r.returns == vis["stem_returns"] + vis["terrain_returns"]
    err = _surface_errors(generate_forest(scn), _sdk_world_points(tmp_path / backend)[1])
    assert err.max() <= 0.0005 + 0.002 + 0.0002


def test_moving_sensor_casts_every_column_from_its_own_pose(tmp_path: Path) -> None:
    """At 20 m/s a frame's first and last columns are 2 m apart; points still land on the
    surfaces only because every column used its own pose."""
    scn = scenario_from_dict({**ROLLING, "track": {**ROLLING["track"], "speed_m_s": 20.0}})
    record_pcap(scn, tmp_path, mode="512x10", max_frames=2)
    poses = _poses(tmp_path / "sensor_poses.csv")
    ys = [p[1] for p in poses.values()]
    assert max(ys) - min(ys) > 3.5
    err = _surface_errors(generate_forest(scn), _sdk_world_points(tmp_path)[1])
    assert err.max() <= 0.0005 + 0.002 + 0.0002


def test_range_cap_and_noise(tmp_path: Path) -> None:
    scn: Scenario = scenario_from_dict(ROLLING)
    record_pcap(scn, tmp_path / "a", mode="512x10", max_frames=1,
                model=ReturnModel(max_range_m=8.0))
    _, pts = _sdk_world_points(tmp_path / "a")
    sensor = np.array(next(iter(_poses(tmp_path / "a" / "sensor_poses.csv").values()))[:3])
    assert np.linalg.norm(pts - sensor, axis=1).max() < 8.0 + 0.6
    record_pcap(scn, tmp_path / "b", mode="512x10", max_frames=1,
                model=ReturnModel(noise_sigma_m=0.02))
    err = _surface_errors(generate_forest(scn), _sdk_world_points(tmp_path / "b")[1])
    assert 0.01 < float(np.std(err)) * 1.6 < 0.05  # noise shows at about its sigma


def test_lidar_pcap_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["lidar", "pcap", "forest-ii", "--mode", "512x10", "--frames", "2", "--out",
                 str(tmp_path)])
    assert code == 0
    assert "2 frames" in capsys.readouterr().out
    for name in ("lidar.pcap", "metadata.json", "ground_truth.json", "visibility.json",
                 "sensor_poses.csv"):
        assert (tmp_path / name).stat().st_size > 0
    info = core.SensorInfo((tmp_path / "metadata.json").read_text())
    assert info.prod_line == "OS-0-64"


_CLAIMS: list[object] = []  # held for the session: a tcf-hil run beside us will not take them


def _free_udp_port() -> int:
    """A free UDP port, claimed as tcf-hil's runs claim theirs (tcf_hil.devices.endpoints)."""
    from tcf_hil.devices.endpoints import reserve_udp_ports

    claim = reserve_udp_ports("127.0.0.1", [0])
    _CLAIMS.append(claim)
    return claim.ports[0]


LIVE_CASES = [("RNG19_RFL8_SIG16_NIR16", m) for m in ("512x10", "1024x10", "2048x10",
                                                       "512x20", "1024x20")] + [
    (p, "1024x10") for p in ("LEGACY", "RNG19_RFL8_SIG16_NIR16_DUAL", "RNG15_RFL8_NIR8")]


@pytest.mark.parametrize(("profile", "mode"), LIVE_CASES)
def test_live_stream_read_by_ouster_sdk(tmp_path: Path, profile: str, mode: str) -> None:
    """Real sockets on 127.0.0.1, real-time pacing: the SDK's live source, given our metadata,
    receives every frame complete and in order, and what we recorded of the stream equals
    what it got."""
    import threading

    from ouster.sdk import sensor

    from tcf_hil.devices.lidar import LidarRun, stream_lidar

    lp, ip = _free_udp_port(), _free_udp_port()
    scn = load_scenario("forest-ii")
    kw = {"mode": mode, "profile": profile, "udp_port_lidar": lp, "udp_port_imu": ip}
    meta = LidarRun(scn, max_frames=1, **kw).meta
    src = sensor.SensorFrameSetSource("127.0.0.1", sensor_info=[core.SensorInfo(meta.dumps())],
                                      timeout=15.0)  # (a loaded machine: the scene is built
    # and the kernels loaded after the source listens)
    result = {}

    def go() -> None:
        result["r"] = stream_lidar(scn, max_frames=8, record=tmp_path, **kw)

    t = threading.Thread(target=go)
    t.start()
    got = []
    for fs in src:
        fr = fs[0]
        got.append((fr.frame_id, fr.complete(), fr.field("RANGE").copy()))
        if len(got) == 6:
            break
    src.close()
    t.join(timeout=30)
    assert [g[0] for g in got] == list(range(6)) and all(g[1] for g in got)
    r = result["r"]
    assert r.refused == 0 and r.frames == 8
    rec = opcap.PcapFrameSetSource(str(tmp_path / "lidar.pcap"),
                                   meta=[str(tmp_path / "metadata.json")])
    recorded = list(rec)
    assert [fs[0].frame_id for fs in recorded] == list(range(8))  # every frame sent
    for (fid, _, rng), fs in zip(got, recorded, strict=False):
        assert fs[0].frame_id == fid
        np.testing.assert_array_equal(fs[0].field("RANGE"), rng)


def test_a_stopped_stream_records_exactly_the_frames_it_sent(tmp_path: Path) -> None:
    """The pcap is written off the pacing loop, by the frame producer, which runs ahead of
    the sender: frames produced but never sent must not reach it."""
    import threading

    from tcf_hil.devices.lidar import stream_lidar

    stop = threading.Event()

    def step(done: int, _total: int) -> None:  # stop mid-stream, the producer ahead
        if done >= 5:
            stop.set()

    r = stream_lidar(load_scenario("forest-ii"), mode="512x20", max_frames=200, stop=stop,
                     record=tmp_path, udp_port_lidar=_free_udp_port(),
                     udp_port_imu=_free_udp_port(), progress=step)
    assert 5 <= r.frames < 200
    rec = opcap.PcapFrameSetSource(str(tmp_path / "lidar.pcap"),
                                   meta=[str(tmp_path / "metadata.json")])
    ids = [fs[0].frame_id for fs in rec]
    assert ids == list(range(r.frames))
    assert not list(tmp_path.glob(".*.part"))  # no temporary left behind
    # the sidecars describe exactly those frames: as a pcap run of that many frames does
    ref = record_pcap(load_scenario("forest-ii"), tmp_path / "ref", mode="512x20",
                      max_frames=r.frames)
    assert (r.packets, r.returns, r.stems_seen) == (ref.packets, ref.returns, ref.stems_seen)
    for name in ("sensor_poses.csv", "visibility.json"):
        assert (tmp_path / name).read_text() == (tmp_path / "ref" / name).read_text()


def test_refusing_destination_does_not_stop_the_stream() -> None:
    """Nobody listens on the ports: the kernel refuses (ICMP port unreachable), we go on."""
    from tcf_hil.devices.lidar import stream_lidar

    r = stream_lidar(load_scenario("forest-ii"), mode="512x20", max_frames=6, speed=0.0,
                     udp_port_lidar=_free_udp_port(), udp_port_imu=_free_udp_port())
    assert r.frames == 6 and r.packets == 6 * 32


def test_dual_second_return_lies_behind_the_first(tmp_path: Path) -> None:
    """DUAL only: where the beam grazes a stem, a sub-ray at the divergence angle lands on
    what is behind it; the SDK reports it as RANGE2, at least the gap behind RANGE, and its
    point (along the central ray) is within divergence x range of a true surface."""
    scn = with_sensor(load_scenario("forest-iii"), "ideal")  # a return model of its own
    model = ReturnModel()
    record_pcap(scn, tmp_path, mode="512x10", profile="RNG19_RFL8_SIG16_NIR16_DUAL",
                max_frames=2, model=model)
    src = opcap.PcapFrameSetSource(str(tmp_path / "lidar.pcap"),
                                   meta=[str(tmp_path / "metadata.json")])
    info = src.sensor_info[0]
    lut = core.XYZLut(info, use_extrinsics=False)
    poses = _poses(tmp_path / "sensor_poses.csv")
    forest = generate_forest(scn)
    seconds = 0
    for fs in src:
        fr = fs[0]
        r1 = fr.field("RANGE").astype(np.int64)
        r2 = fr.field("RANGE2").astype(np.int64)
        m = r2 > 0
        seconds += int(m.sum())
        assert np.all(r1[m] > 0)
        assert np.all(r2[m] - r1[m] >= model.second_return_gap_m * 1000)
        pose = np.array([poses[int(t)] for t in fr.timestamp])
        world = (np.einsum("wij,hwj->hwi", _rot(pose[:, 3:]), lut(fr.field("RANGE2")))
                 + pose[None, :, :3])
        err = _surface_errors(forest, world[m])
        assert np.all(err <= model.divergence_rad * r2[m] / 1000 * 1.01 + 0.003)
    assert seconds > 200
    # Single-return profiles never compute it.
    from tcf_hil.devices.lidar import LidarRun

    run = LidarRun(scn, mode="512x10", max_frames=1)
    assert run.emu.frame(0).stem_id2 is None


def test_imu_packets_carry_the_trajectory_specific_force_and_rate(tmp_path: Path) -> None:
    """Through a U-turn on rolling ground: the IMU packets (100 Hz, port 7503) hold what an
    IMU fixed to the sensor would read, gravity included."""
    from protocols.ouster import decode_imu_packet
    from protocols.pcap import read_udp
    from tcf_hil.world.track import Trajectory

    scn = scenario_from_dict({**ROLLING, "track": {
        "start_m": [0.0, -5.0, 2.0], "end_m": [0.0, 5.0, 2.0], "speed_m_s": 3.0,
        "passes": 2, "pass_offset_m": 6.0, "turn_radius_m": 3.0, "accel_m_s2": 2.0}})
    record_pcap(scn, tmp_path, mode="512x20")
    imu = [decode_imu_packet(d.payload) for d in read_udp((tmp_path / "lidar.pcap").read_bytes())
           if d.dst_port == 7503]
    t = np.array([p.accel_ts_ns for p in imu], dtype=np.int64)
    assert len(imu) > 300 and (np.diff(t) == 10_000_000).all()
    acc, gyro = Trajectory.from_config(scn.track, generate_forest(scn).terrain).imu(t)
    np.testing.assert_allclose([p.accel_g for p in imu], acc, atol=1e-6)  # float32 on the wire
    np.testing.assert_allclose([p.gyro_deg_s for p in imu], gyro, atol=1e-4)
    assert np.abs(gyro[:, 2]).max() == pytest.approx(np.degrees(3.0 / 3.0), rel=0.05)  # v/R
    assert np.median(np.linalg.norm(acc, axis=1)) == pytest.approx(1.0, abs=0.1)  # gravity


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_ctrl_c_ends_a_live_stream_cleanly_and_keeps_the_recording(tmp_path: Path,
                                                                   sig: str) -> None:
    """The user's Ctrl-C: the frame on the wire is finished, the recording and sidecars are
    written, the shared-memory ring is gone, no traceback; a second Ctrl-C aborts."""
    import os
    import signal
    import subprocess
    import sys
    import time

    def shm() -> set[str]:
        return set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()

    before = shm()
    out = tmp_path / "rec"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tcf_hil.cli", "lidar", "stream", "forest-ii", "--mode", "512x20",
         "--record", str(out), "--lidar-port", str(_free_udp_port()), "--imu-port",
         str(_free_udp_port())], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    try:
        # by default the sensor is a host of its own (its HTTP API on port 80 there, as root)
        first = proc.stdout.readline()
        assert first.startswith(("streaming forest-ii", "sensor forest-ii")), first
    except BaseException:
        proc.kill()  # never leave a stream behind
        proc.communicate()
        raise
    time.sleep(2.0)
    proc.send_signal(getattr(signal, sig))
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr and "Error" not in stderr
    sent = int(stdout.split(" lidar packets in ")[1].split()[0])
    assert sent >= 10
    frames = list(opcap.PcapFrameSetSource(str(out / "lidar.pcap"),
                                           meta=[str(out / "metadata.json")]))
    assert len(frames) == sent
    assert (out / "sensor_poses.csv").exists() and not list(out.glob(".*.part"))
    assert not {n for n in shm() - before if n.startswith("psm_")}  # the ring is unlinked


def test_frames_sent_counts_only_the_frames_that_left(tmp_path: Path) -> None:
    """A re-initialisation keeps the sensor silent for its gap: those frame periods send
    nothing, and the run's "frames sent" must not count them (it said 500 where 490 left)."""
    from protocols.ouster import SensorMetadata
    from protocols.pcap import read_udp
    from tcf_hil.devices.faults import apply_fault_options
    from tcf_hil.devices.lidar import stream_lidar

    scn = apply_fault_options(load_scenario("forest-ii"),
                              ["lidar.reinit_at_s=[1.0]", "lidar.reinit_gap_s=1.0"])
    lp, ip = _free_udp_port(), _free_udp_port()
    r = stream_lidar(scn, speed=0, record=tmp_path, mode="512x10", max_frames=40,
                     udp_port_lidar=lp, udp_port_imu=ip)
    meta = SensorMetadata.loads((tmp_path / "metadata.json").read_text())
    lidar = [d for d in read_udp((tmp_path / "lidar.pcap").read_bytes()) if d.dst_port == lp]
    left = len(lidar) / meta.packet_format.packets_per_frame
    assert left == int(left) and left < 40  # the gap sent nothing
    assert r.frames == left


def test_the_sender_is_a_process_of_its_own_and_follows_a_moved_route() -> None:
    """The pacing loop runs in a process of its own (no interpreter lock shared with the
    run's CAN node and HTTP API); a set_config that moves the destination (the sensor's
    HTTP API sets the run's Route) reaches it at once, mid-frame."""
    import os
    import socket
    import threading
    import time

    from emulators.lidar import Route
    from tcf_hil.devices.lidar import stream_lidar

    a, b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), socket.socket(
        socket.AF_INET, socket.SOCK_DGRAM)
    for s in (a, b):
        s.bind(("127.0.0.1", 0))
        s.settimeout(10.0)
    imu = _free_udp_port()
    route = Route("127.0.0.1", a.getsockname()[1], imu)
    result = {}

    def go() -> None:
        result["r"] = stream_lidar(load_scenario("forest-ii"), mode="512x20", max_frames=80,
                                   udp_port_lidar=a.getsockname()[1], udp_port_imu=imu,
                                   route=route)

    t = threading.Thread(target=go)
    t.start()
    try:
        a.recv(65536)  # streaming
        senders = []
        for task in os.listdir(f"/proc/{os.getpid()}/task"):
            with open(f"/proc/{os.getpid()}/task/{task}/children") as fh:
                for pid in fh.read().split():
                    with open(f"/proc/{pid}/comm") as c:
                        if c.read().strip() == "tcf-lidar-send":
                            senders.append(int(pid))
        assert len(senders) == 1
        t0 = time.monotonic()
        route.set("127.0.0.1", b.getsockname()[1], imu)
        b.recv(65536)
        assert time.monotonic() - t0 < 0.5  # the next packets (one each 1.6 ms), not a
        # frame later
    finally:
        t.join(timeout=60)
        a.close()
        b.close()
    assert result["r"].frames == 80
    assert route.listeners == []  # the stream no longer listens
