"""ROS 2 bags (issue 46): ``tcf-hil export RUN --out run_bag`` writes a rosbag2 folder (MCAP
storage) that the ``rosbags`` library reads back: the Ouster packets byte for byte as the
run's pcap holds them, on ouster-ros's topics and message type, the metadata, clouds,
transforms and stems; ``tcf-hil replay BAG`` sends a bag's packets (one we wrote, and one
laid out as ouster-ros records them) byte for byte to real sockets."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader, Writer

from protocols.ouster import IMU_PACKET_BYTES, SensorMetadata
from protocols.pcap import UdpReader
from tcf_hil.cli import main
from tcf_hil.devices.offline import record_pcap
from tcf_hil.errors import InputError
from tcf_hil.recording.reader import Recording
from tcf_hil.recording.rosbag import typestore
from tcf_hil.results.rosbag import BAG_TOPICS
from tcf_hil.run import replay_run
from tcf_hil.scenario import load_scenario


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "run"
    record_pcap(load_scenario("forest-ii"), out, mode="512x10", max_frames=4)
    return out


@pytest.fixture(scope="module")
def bag(run_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bagout") / "run_bag"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    return out


def _pcap_datagrams(run: Path) -> list[tuple[int, bytes]]:
    meta = SensorMetadata.loads((run / "metadata.json").read_text())
    with open(run / "lidar.pcap", "rb") as f:
        return [(d.dst_port, bytes(d.payload)) for d in UdpReader(f)
                if d.dst_port == meta.udp_port_lidar
                or (d.dst_port == meta.udp_port_imu and len(d.payload) == IMU_PACKET_BYTES)]


def test_the_bag_holds_the_packets_byte_for_byte(run_dir: Path, bag: Path) -> None:
    store = typestore()
    meta = SensorMetadata.loads((run_dir / "metadata.json").read_text())
    with Reader(bag) as r:
        assert r.metadata["storage_identifier"] == "mcap"
        assert {c.topic: c.msgtype for c in r.connections} == BAG_TOPICS
        pkt = [c for c in r.connections if c.topic in ("/ouster/lidar_packets",
                                                       "/ouster/imu_packets")]
        got = [(meta.udp_port_imu if c.topic.endswith("imu_packets") else meta.udp_port_lidar,
                bytes(store.deserialize_cdr(raw, c.msgtype).buf))
               for c, _t, raw in r.messages(connections=pkt)]
        md = [c for c in r.connections if c.topic == "/ouster/metadata"]
        text = [store.deserialize_cdr(raw, c.msgtype).data
                for c, _t, raw in r.messages(connections=md)]
        clouds = [store.deserialize_cdr(raw, c.msgtype) for c, _t, raw in r.messages(
            connections=[c for c in r.connections if c.topic == "/ouster/points"])]
        tfs = [c.msgcount for c in r.connections if c.topic == "/tf"]
    with open(next(bag.glob("*.mcap")), "rb") as f:  # as written, not sorted by a reader
        times = [m.log_time for _s, _c, m in make_reader(f).iter_messages(
            log_time_order=False)]
    assert got == _pcap_datagrams(run_dir)  # every lidar and IMU packet, in capture order
    assert text == [(run_dir / "metadata.json").read_text()]
    assert len(clouds) == 4 == tfs[0]
    c0 = clouds[0]
    assert c0.header.frame_id == "world" and c0.width > 1000
    assert [f.name for f in c0.fields] == ["x", "y", "z", "intensity", "ring", "component",
                                           "stem_id"]
    assert len(c0.data) == c0.width * c0.point_step
    assert times == sorted(times)
    doc = json.loads((bag / "metadata.yaml").read_text())  # YAML's JSON subset
    topics = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
              for t in doc["rosbag2_bagfile_information"]["topics_with_message_count"]}
    assert "durability: 1" in topics["/ouster/metadata"]  # latched, as ouster-ros has it


def test_one_clock_for_every_topic_at_any_speed(run_dir: Path, tmp_path: Path) -> None:
    """A run at --speed 2: the capture's time stamps run twice as fast as the wall clock
    the CAN log and the publications keep; in the bag every topic is on the wall clock, so a
    frame's cloud comes with its last packets, not at twice their distance from the start."""
    run = tmp_path / "run"
    run.mkdir()
    for f in run_dir.iterdir():
        (run / f.name).symlink_to(f)
    first = int((run_dir / "sensor_poses.csv").read_text().splitlines()[1].split(",")[0])
    unix0 = 1_767_225_600 * 10**9
    (run / "manifest.json").write_text(json.dumps(
        {"clock": {"sim_t0_ns": first, "unix_ns_at_sim_t0": unix0, "speed": 2.0}}))
    out = tmp_path / "bag2"
    assert main(["export", str(run), "--out", str(out)]) == 0
    with Reader(out) as r:
        lidar = [t for c, t, _raw in r.messages() if c.topic == "/ouster/lidar_packets"]
        clouds = [t for c, t, _raw in r.messages() if c.topic == "/ouster/points"]
    packets_per_frame = len(lidar) // 4
    for k, t in enumerate(clouds):  # a frame's cloud: at its last packet's time (wall)
        last = lidar[(k + 1) * packets_per_frame - 1]
        assert abs(t - last) < 2_000_000, (k, t - last)
    assert lidar[0] >= unix0 - 10**9 and lidar[-1] - lidar[0] < 0.3e9  # 4 frames at 2x


def test_a_bag_replays_byte_for_byte(run_dir: Path, bag: Path) -> None:
    rec = Recording.load(bag)
    want = _pcap_datagrams(run_dir)
    assert rec.counts["lidar"] + rec.counts["imu"] == len(want)
    socks = []
    for _ in range(2):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
        s.bind(("127.0.0.1", 0))
        socks.append(s)
    ports = tuple(s.getsockname()[1] for s in socks)
    got: list[tuple[int, bytes]] = []
    stop = threading.Event()

    def rx() -> None:
        import select

        while not stop.is_set():
            ready, _w, _x = select.select(socks, [], [], 0.1)
            for s in ready:
                got.append((s.getsockname()[1], s.recv(65536)))

    th = threading.Thread(target=rx)
    th.start()
    try:
        replay_run(bag, None, None, speed=4.0, lead_s=0.0, sensor_ip="127.0.0.1",
                   http_port=0, ports=ports)  # type: ignore[arg-type]
        deadline = time.monotonic() + 10
        while len(got) < len(want) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        th.join()
        for s in socks:
            s.close()
    meta = SensorMetadata.loads((run_dir / "metadata.json").read_text())
    lidar = [b for p, b in want if p == meta.udp_port_lidar]
    assert [b for p, b in got if p == ports[0]] == lidar


def test_a_bag_as_ouster_ros_records_it_is_read(run_dir: Path, tmp_path: Path) -> None:
    """ouster-ros's ``record.launch``: /ouster/lidar_packets, /ouster/imu_packets (its
    PacketMsg, here the older ``ouster_msgs`` name), /ouster/metadata; SQLite storage, as
    ``ros2 bag record`` wrote by default before Jazzy. No CAN, no clouds."""
    store = typestore()
    want = _pcap_datagrams(run_dir)
    meta = SensorMetadata.loads((run_dir / "metadata.json").read_text())
    path = tmp_path / "ouster_ros_bag"
    typ = "ouster_msgs/msg/PacketMsg"
    with Writer(path) as w:
        cm = w.add_connection("/ouster/metadata", "std_msgs/msg/String", typestore=store)
        cl = w.add_connection("/ouster/lidar_packets", typ, typestore=store)
        ci = w.add_connection("/ouster/imu_packets", typ, typestore=store)
        t = 1_700_000_000 * 10**9
        w.write(cm, t, store.serialize_cdr(store.types["std_msgs/msg/String"](
            data=(run_dir / "metadata.json").read_text()), "std_msgs/msg/String"))
        for k, (port, payload) in enumerate(want):
            conn = cl if port == meta.udp_port_lidar else ci
            w.write(conn, t + k * 100_000, store.serialize_cdr(store.types[typ](
                buf=np.frombuffer(payload, np.uint8)), typ))
    rec = Recording.load(path)
    assert rec.counts["lidar"] == sum(p == meta.udp_port_lidar for p, _b in want)
    assert rec.can_log is None
    sent = [payload for _t, _port, payload in rec.datagrams()]
    assert sent == [b for _p, b in want]


def test_bad_bags_are_one_line(run_dir: Path, bag: Path, tmp_path: Path) -> None:
    store = typestore()
    path = tmp_path / "no_meta"
    with Writer(path) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        w.write(c, 1, store.serialize_cdr(store.types["std_msgs/msg/String"](data="hi"),
                                          "std_msgs/msg/String"))
    with pytest.raises(InputError, match="not a bag of an Ouster sensor") as err:
        Recording.load(path)
    assert "\n" not in str(err.value)
    assert main(["export", str(run_dir), "--out", str(bag)]) == 1  # exists: not overwritten
    assert (bag / "metadata.yaml").exists()
