"""The harvester's CANopen node on python-can's in-process bus, observed by real python-can and
canopen peers: boot-up, NMT, heartbeat, SYNC-triggered and event TPDOs, TIME, atomic poses,
remapping by SDO, and foreign or malformed frames counted and ignored."""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import canopen
import pytest

from emulators.harvester import BusSpec, CanLog, HarvesterNode, NodeConfig, SimClock
from protocols.harvester import Pose, PoseAssembler, decode_time, eds_path

_names = itertools.count()


def pose_at(t_ns: int) -> Pose:
    """Every field a different function of the same time: a torn frame would show."""
    s = t_ns / 1e9
    return Pose(s, -s, 2 * s, (10 * s) % 360, (s % 50) - 25, -((s % 40) - 20), s % 10,
                t_ns // 1000)


def consistent(p: Pose) -> bool:
    s = p.time_us / 1e6
    return (abs(p.x_m - s) < 2e-3 and abs(p.y_m + s) < 2e-3 and abs(p.z_m - 2 * s) < 2e-3
            and abs(((p.heading_deg - 10 * s) + 180) % 360 - 180) < 0.02
            and abs(p.pitch_deg - ((s % 50) - 25)) < 0.02)


@pytest.fixture
def bus_name() -> str:
    return f"harvester-test-{next(_names)}"


@pytest.fixture
def monitor(bus_name: str) -> Iterator[can.BusABC]:
    with can.Bus(interface="virtual", channel=bus_name) as bus:
        yield bus


def collect(bus: can.BusABC, seconds: float) -> list[can.Message]:
    out, end = [], time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is not None:
            out.append(m)
    return out


def collect_until(bus: can.BusABC, arbitration_id: int, count: int,
                  seconds: float = 10.0) -> list[can.Message]:
    """What comes until ``count`` frames of ``arbitration_id`` have (the node's own pace, not
    a fixed window: on a busy machine a 0.3 s window may hold a third of them), or
    ``seconds`` pass."""
    out, end, seen = [], time.monotonic() + seconds, 0
    while seen < count and (left := end - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is not None:
            out.append(m)
            seen += m.arbitration_id == arbitration_id
    return out


def drain(bus: can.BusABC) -> None:
    """Wait for the node to act on what was just sent, then forget what came before."""
    time.sleep(0.05)
    while bus.recv(0) is not None:
        pass


def node(bus_name: str, **kw: object) -> HarvesterNode:
    cfg = NodeConfig(**kw)  # type: ignore[arg-type]
    return HarvesterNode(BusSpec("virtual", bus_name), pose_at,
                         SimClock.start(1_000_000_000), cfg)


def test_boot_up_then_poses_at_the_sync_rate_all_consistent(bus_name: str,
                                                            monitor: can.BusABC) -> None:
    with node(bus_name, rate_hz=50.0, time_period_s=0.5, unix_epoch_ns=1_767_225_600 * 10**9):
        time.sleep(1.25)
    # stopped between SYNCs: every SYNC's TPDOs are out (the monitor's queue kept them all)
    msgs = collect(monitor, 0.2)
    assert (msgs[0].arbitration_id, bytes(msgs[0].data)) == (0x70A, b"\x00")  # boot-up first
    ids = [m.arbitration_id for m in msgs]
    syncs = ids.count(0x80)
    assert 58 <= syncs <= 65
    for cob in (0x18A, 0x28A, 0x38A):
        assert ids.count(cob) == syncs  # one of each per SYNC
    assert 11 <= ids.count(0x48A) <= 14  # event timer 100 ms
    hb = [bytes(m.data) for m in msgs if m.arbitration_id == 0x70A][1:]
    assert hb and set(hb) == {b"\x05"}  # OPERATIONAL by itself
    asm = PoseAssembler(10)
    poses = [p for m in msgs if (p := asm.feed(m.arbitration_id, bytes(m.data))) is not None]
    assert len(poses) == syncs
    assert all(consistent(p) for p in poses)
    times = [decode_time(bytes(m.data)) for m in msgs if m.arbitration_id == 0x100]
    assert len(times) >= 2
    assert 1_767_225_600_000 <= times[0] < 1_767_225_600_000 + 2000


def test_nmt_states_gate_the_pdos_and_resets_boot_again(bus_name: str,
                                                         monitor: can.BusABC) -> None:
    master = can.Bus(interface="virtual", channel=bus_name)
    try:
        with node(bus_name, autostart=False):
            msgs = collect(monitor, 0.4)
            assert not [m for m in msgs if 0x180 <= m.arbitration_id < 0x500]
            assert bytes(msgs[-1].data) == b"\x7f" or any(
                bytes(m.data) == b"\x7f" for m in msgs if m.arbitration_id == 0x70A)
            master.send(can.Message(arbitration_id=0, data=[1, 10], is_extended_id=False))
            drain(monitor)
            msgs = collect_until(monitor, 0x18A, 20)
            assert sum(m.arbitration_id == 0x18A for m in msgs) >= 20
            master.send(can.Message(arbitration_id=0, data=[2, 0], is_extended_id=False))
            drain(monitor)
            msgs = collect(monitor, 0.3)
            assert not [m for m in msgs if 0x180 <= m.arbitration_id < 0x500]
            assert {bytes(m.data) for m in msgs if m.arbitration_id == 0x70A} == {b"\x04"}
            master.send(can.Message(arbitration_id=0, data=[130, 10], is_extended_id=False))
            msgs = collect_until(monitor, 0x70A, 3)
            hb = [bytes(m.data) for m in msgs if m.arbitration_id == 0x70A]
            # a STOPPED heartbeat already on its way when the reset was sent may come first
            boot = hb.index(b"\x00")
            assert set(hb[:boot]) <= {b"\x04"}
            assert set(hb[boot + 1:]) == {b"\x7f"}  # boot-up, then PRE-OPERATIONAL
            assert not [m for m in msgs if 0x180 <= m.arbitration_id < 0x500]
            master.send(can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False))
            drain(monitor)
            msgs = collect_until(monitor, 0x38A, 20)
            assert sum(m.arbitration_id == 0x38A for m in msgs) >= 20
            # another node's command is not ours
            master.send(can.Message(arbitration_id=0, data=[2, 11], is_extended_id=False))
            drain(monitor)
            msgs = collect_until(monitor, 0x38A, 10)
            assert sum(m.arbitration_id == 0x38A for m in msgs) >= 10
    finally:
        master.shutdown()


def test_external_sync_and_remapping_by_sdo(bus_name: str, monitor: can.BusABC) -> None:
    net = canopen.Network()
    net.connect(interface="virtual", channel=bus_name)
    try:
        with node(bus_name, sync_producer=False, autostart=False) as n:
            remote = net.add_node(10, str(eds_path()))
            remote.tpdo.read()  # mapping by SDO from the node's own server
            assert [v.name for v in remote.tpdo[3].map] == ["Pose.Roll", "Pose.Speed",
                                                             "Pose.Time"]
            assert remote.sdo[0x2002][3].raw == 2000  # lidar mount height, mm
            remote.tpdo[1].trans_type = 2  # every second SYNC
            remote.tpdo[1].save()
            remote.nmt.state = "OPERATIONAL"
            time.sleep(0.1)
            collect(monitor, 0.05)
            for _ in range(10):
                net.sync.transmit()
                time.sleep(0.01)
            msgs = collect(monitor, 0.2)
            ids = [m.arbitration_id for m in msgs]
            assert ids.count(0x28A) == 10 and ids.count(0x38A) == 10
            assert ids.count(0x18A) == 5
            assert n.stats.syncs_received == 10 and n.stats.syncs_sent == 0
            # SDO reads of the pose record answer the latest sample (the event TPDO samples
            # too, so it may be newer than the last SYNC's): z = 2 s in pose_at
            last = {m.arbitration_id: bytes(m.data) for m in msgs}
            t_sent = int.from_bytes(last[0x38A][4:8], "little")
            for _ in range(10):  # three reads; a new sample may land between them
                t_us, z_mm = remote.sdo[0x2000][8].raw, remote.sdo[0x2000][3].raw
                if remote.sdo[0x2000][8].raw == t_us:
                    break
            assert t_us >= t_sent and abs(z_mm - 2 * t_us / 1000) <= 1.0
    finally:
        net.disconnect()


def test_foreign_and_malformed_frames_are_counted_and_ignored(bus_name: str,
                                                              monitor: can.BusABC) -> None:
    other = can.Bus(interface="virtual", channel=bus_name)
    try:
        with node(bus_name) as n:
            time.sleep(0.1)
            for msg in (can.Message(arbitration_id=0x123, data=b"\x01"),
                        can.Message(arbitration_id=0x1ABCDEF, data=b"", is_extended_id=True),
                        can.Message(arbitration_id=0x80, data=b"\x01\x02\x03"),
                        can.Message(arbitration_id=0, data=b"\x01"),
                        can.Message(arbitration_id=0x60A, data=b"\x40\x00")):
                msg.is_extended_id = msg.arbitration_id > 0x7FF
                other.send(msg)
            time.sleep(0.2)
            assert n.stats.foreign_frames == 2
            assert n.stats.malformed_frames == 3
            assert n.state == "OPERATIONAL"
            before = n.stats.tpdo_frames
            time.sleep(0.2)
            assert n.stats.tpdo_frames > before + 30
    finally:
        other.shutdown()


def test_heartbeat_period_follows_an_sdo_write(bus_name: str, monitor: can.BusABC) -> None:
    net = canopen.Network()
    net.connect(interface="virtual", channel=bus_name)
    try:
        with node(bus_name, rate_hz=10.0):
            remote = net.add_node(10, str(eds_path()))
            remote.sdo[0x1017].raw = 20
            collect(monitor, 0.1)
            msgs = collect(monitor, 1.0)
            hb = [m.timestamp for m in msgs if m.arbitration_id == 0x70A]
            assert 40 <= len(hb) <= 55
    finally:
        net.disconnect()


def test_can_logs_in_candump_asc_and_blf_hold_the_same_frames(bus_name: str,
                                                              tmp_path: Path) -> None:
    spec = BusSpec("virtual", bus_name)
    logs = [CanLog(tmp_path / f"bus{ext}", spec).start() for ext in (".log", ".asc", ".blf")]
    try:
        with node(bus_name) as n:
            # until 80 SYNC periods are out: a stalled host skips periods (as a real node
            # would), so a fixed sleep could log fewer frames than the count below
            deadline = time.monotonic() + 20.0
            while n.stats.syncs_sent < 80 and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        for lg in logs:
            lg.stop()
    seen = []
    for lg in logs:
        frames = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(lg.path))]
        assert len(frames) == lg.frames
        stamps = [m.timestamp for m in can.LogReader(str(lg.path))]
        assert stamps == sorted(stamps)
        seen.append(frames)
    assert len(seen[0]) > 300  # 80 periods of a SYNC and 3 TPDOs, heartbeats
    assert seen[0] == seen[1] == seen[2]
    assert {0x80, 0x18A, 0x28A, 0x38A, 0x70A} <= {i for i, _ in seen[0]}


def test_a_log_name_without_a_known_suffix_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"bus\.txt.*\.log, \.asc, \.blf"):
        CanLog(tmp_path / "bus.txt")


def test_a_log_that_cannot_be_written_stops_with_the_reason(bus_name: str,
                                                            tmp_path: Path) -> None:
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here to make a full disk")
    full = tmp_path / "bus.log"
    full.symlink_to("/dev/full")  # every write: ENOSPC, as on a full disk
    lg = CanLog(full, BusSpec("virtual", bus_name)).start()
    with node(bus_name) as n:
        time.sleep(0.3)
        assert n.connected  # the node runs on
    lg.stop()  # no exception: the reason is kept
    assert lg.error is not None and "No space left" in lg.error
    assert lg.frames == 0


def test_a_node_with_the_same_id_is_heard_before_boot_and_a_masters_rtr_is_not() -> None:
    """node_id_in_use: a frame on the node's own COB-IDs from someone else is a twin; a
    master's node-guarding RTR on 0x700+id, or an extended frame, is not."""
    from emulators.harvester import node_id_in_use

    name = f"twin-{os.getpid()}"
    spec = BusSpec("virtual", name, extra={"receive_own_messages": False})
    other = can.Bus(interface="virtual", channel=name)
    stop = threading.Event()

    def talk(frames: list[can.Message]) -> None:
        while not stop.wait(0.02):
            for m in frames:
                other.send(m)

    try:
        rtr = [can.Message(arbitration_id=0x70A, is_remote_frame=True, is_extended_id=False),
               can.Message(arbitration_id=0x18A, data=b"x", is_extended_id=True)]
        t = threading.Thread(target=talk, args=(rtr,), daemon=True)
        t.start()
        assert node_id_in_use(spec, 10, 0.3) is None
        stop.set()
        t.join()
        stop.clear()
        hb = [can.Message(arbitration_id=0x70A, data=b"\x05", is_extended_id=False)]
        t = threading.Thread(target=talk, args=(hb,), daemon=True)
        t.start()
        said = node_id_in_use(spec, 10, 0.3)
        assert said is not None and "id 10" in said and "0x70A" in said
        assert node_id_in_use(spec, 11, 0.2) is None  # another id: no conflict
    finally:
        stop.set()
        other.shutdown()
