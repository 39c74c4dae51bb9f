"""Injected faults: the datagram transform and the sensor's fault plan (properties, seeds),
and the harvester node's CAN faults observed by a real python-can peer on the in-process bus:
loss, late poses, bus-off with recovery, NMT reset by a second master."""

from __future__ import annotations

import collections
import itertools
import statistics
import time
from collections.abc import Iterator

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.faults import CanFaultPlan, LidarFaultPlan, UdpFaults
from emulators.harvester import BusSpec, HarvesterNode, NodeConfig, SimClock
from emulators.lidar import Datagram
from protocols.harvester import Pose

_names = itertools.count()


def datagrams(n: int, step_ns: int = 10_000) -> list[Datagram]:
    return [Datagram(1_000_000 + i * step_ns, 7503 if i % 8 == 7 else 7502, i.to_bytes(4, "big"))
            for i in range(n)]


def ident(d: Datagram) -> int:
    return int.from_bytes(bytes(d.payload), "big")


rates = st.floats(0.0, 0.5)


@settings(max_examples=120, deadline=None)
@given(n=st.integers(1, 300), loss=rates, burst=st.floats(0.0, 0.05), dup=rates,
       reorder=rates, jitter=st.sampled_from([0.0, 5.0, 50.0]), seed=st.integers(0, 2**32),
       ports=st.sampled_from([(), (7502,), (7503,)]))
def test_udp_faults_only_lose_duplicate_swap_and_delay(n: int, loss: float, burst: float,
                                                       dup: float, reorder: float,
                                                       jitter: float, seed: int,
                                                       ports: tuple[int, ...]) -> None:
    dgs = datagrams(n)
    f = UdpFaults(loss, burst, 4.0, dup, reorder, jitter, ports, seed)
    out, events = f.apply(dgs, 7)
    by_kind = {e["kind"]: e for e in events}
    got = collections.Counter(ident(d) for d in out)
    lost = set(by_kind.get("udp_loss", {}).get("datagrams", [])) | set(
        by_kind.get("udp_burst_loss", {}).get("datagrams", []))
    doubled = set(by_kind.get("udp_duplicate", {}).get("datagrams", []))
    # every datagram arrives once, twice if duplicated, never if lost; nothing else arrives
    assert got == collections.Counter(
        {i: 2 if i in doubled else 1 for i in range(n) if i not in lost})
    for i in lost | doubled:  # faults strike only the chosen ports
        assert not ports or dgs[i].port in ports
    assert all(e["frame"] == 7 for e in events)
    # send times never go back, and each is at or after a slot's original time (jitter only
    # delays, by at most jitter_us)
    t = [d.t_ns for d in out]
    assert t == sorted(t)
    if jitter and out:
        assert max(t) <= dgs[-1].t_ns + jitter * 1000
    if not jitter:
        assert set(t) <= {d.t_ns for d in dgs}
    # the same seed gives the same faults
    again, _ = UdpFaults(loss, burst, 4.0, dup, reorder, jitter, ports, seed).apply(dgs, 7)
    assert [(ident(d), d.t_ns) for d in again] == [(ident(d), d.t_ns) for d in out]


def test_loss_rates_and_burst_lengths_are_what_was_asked() -> None:
    dgs = datagrams(200_000, 1)
    out, ev = UdpFaults(loss=0.02, seed=1).apply(dgs, 0)
    assert 0.018 < 1 - len(out) / len(dgs) < 0.022
    out, ev = UdpFaults(burst_rate=0.001, burst_packets=20.0, seed=2).apply(dgs, 0)
    idx = ev[0]["datagrams"]
    runs = [len(list(g)) for _k, g in itertools.groupby(
        enumerate(idx), key=lambda p: p[1] - p[0])]
    assert 15 < sum(runs) / len(runs) < 25  # mean burst length
    assert 0.015 < len(idx) / len(dgs) < 0.03  # about rate * length / (1 + rate * length)


def test_no_fault_asked_is_the_identity() -> None:
    dgs = datagrams(50)
    f = UdpFaults()
    assert not f.active
    assert f.apply(dgs, 0) == (dgs, [])


def test_scheduled_dropouts_and_reinit_hit_the_frames_under_way() -> None:
    period = 100_000_000
    plan = LidarFaultPlan(dropout_at_ns=(1_250_000_000,), dropout_frames=2,
                          reinit_at_ns=(2_000_000_000,), reinit_gap_ns=300_000_000)
    acts = [plan.frame(k, 1_000_000_000 + k * period, period)[0] for k in range(16)]
    assert acts[:2] == ["send", "send"]
    assert acts[2:4] == ["drop", "drop"]  # the frame under way at 1.25 s and the next
    assert acts[4:10] == ["send"] * 6
    assert acts[10:13] == ["reinit", "silent", "silent"]  # 2.0 s, silent for 0.3 s
    assert acts[13:] == ["send"] * 3


def test_random_dropouts_are_seeded() -> None:
    def acts(seed: int) -> list[str]:
        p = LidarFaultPlan(dropout=0.2, seed=seed)
        return [p.frame(k, k * 100, 100)[0] for k in range(500)]

    a = acts(3)
    assert a == acts(3) and a != acts(4)
    assert 70 < a.count("drop") < 130


# ------------------------------------------------------------------- the node's CAN faults
def pose_at(t_ns: int) -> Pose:
    s = t_ns / 1e9
    return Pose(s, -s, 1.0, 90.0, 0.0, 0.0, 1.0, t_ns // 1000)


@pytest.fixture
def bus_name() -> str:
    return f"faults-test-{next(_names)}"


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


def run_node(bus_name: str, plan: CanFaultPlan, seconds: float
             ) -> tuple[list[dict[str, object]], SimClock, HarvesterNode]:
    events: list[dict[str, object]] = []
    clock = SimClock.start(1_000_000_000)
    node = HarvesterNode(BusSpec("virtual", bus_name), pose_at, clock,
                         NodeConfig(rate_hz=100.0), faults=plan, on_fault=events.append)
    with node:
        time.sleep(seconds)
    return events, clock, node


def test_can_loss_drops_that_share_of_the_nodes_frames(bus_name: str,
                                                       monitor: can.BusABC) -> None:
    events, _clock, node = run_node(bus_name, CanFaultPlan(loss=0.25, seed=5), 2.0)
    seen = collect(monitor, 0.2)
    lost = [e for e in events if e["kind"] == "can_loss"]
    assert len(lost) == node.stats.fault_lost
    sent = len(seen)
    assert 0.18 < len(lost) / (sent + len(lost)) < 0.32
    # what was lost never reached the bus: per COB, seen + lost = what the node produced
    by_cob = collections.Counter(m.arbitration_id for m in seen)
    lost_cob = collections.Counter(int(str(e["cob_id"]), 16) for e in lost)
    syncs = by_cob[0x80] + lost_cob[0x80]
    for cob in (0x18A, 0x28A, 0x38A):
        assert by_cob[cob] + lost_cob[cob] == syncs


def test_poses_leave_late_by_the_delay_asked(bus_name: str, monitor: can.BusABC) -> None:
    run_node(bus_name, CanFaultPlan(pose_delay_ns=50_000_000), 1.0)
    msgs = collect(monitor, 0.2)
    sync_t = [m.timestamp for m in msgs if m.arbitration_id == 0x80]
    tpdo_t = [m.timestamp for m in msgs if m.arbitration_id == 0x38A]
    assert len(tpdo_t) > 40
    # each TPDO3 leaves 50 ms after its own SYNC, not right after it. Batches are delayed in
    # order and none is lost, so the k-th TPDO3 carries the k-th SYNC's pose: pair them by
    # index. A stalled host can only make a frame later, never earlier, so the floor is exact;
    # the median stays near 50 ms even when a stall holds back a few batches.
    lag = [t - s for s, t in zip(sync_t, tpdo_t, strict=False)]  # the last few are held
    assert min(lag) > 0.049
    assert statistics.median(lag) < 0.09
    assert len(sync_t) - len(tpdo_t) <= 7  # only the batches still held at the stop are missing


def test_bus_off_is_silent_then_recovers_with_emcy(bus_name: str, monitor: can.BusABC) -> None:
    clock_t0 = 1_000_000_000
    plan = CanFaultPlan(bus_off_at_ns=(clock_t0 + 400_000_000,), bus_off_ns=500_000_000)
    events, clock, node = run_node(bus_name, plan, 1.3)
    msgs = collect(monitor, 0.2)
    kinds = [e["kind"] for e in events]
    assert kinds == ["can_bus_off", "can_bus_off_recovered"]
    off = clock.origin_monotonic_ns / 1e9 + 0.4
    on = off + 0.5
    # python-can's virtual bus stamps frames with time.time(): compare on that clock
    shift = time.time() - time.monotonic()
    ts = sorted(m.timestamp - shift for m in msgs)
    assert not [t for t in ts if off + 0.02 < t < on - 0.02]  # silent while bus-off
    assert [t for t in ts if t > on + 0.02]  # and talking again after
    emcy = [bytes(m.data) for m in msgs if m.arbitration_id == 0x8A]
    assert emcy[0][:2] == bytes([0x40, 0x81])  # 0x8140: recovered from bus-off
    assert emcy[1] == bytes(8)  # then: no error
    assert node.stats.bus_off_dropped > 40


def test_nmt_reset_from_a_second_master_and_restart(bus_name: str,
                                                    monitor: can.BusABC) -> None:
    t0 = 1_000_000_000
    plan = CanFaultPlan(nmt_reset_at_ns=(t0 + 300_000_000,), nmt_restart_ns=400_000_000)
    events, _clock, _node = run_node(bus_name, plan, 1.2)
    msgs = collect(monitor, 0.2)
    assert [e["kind"] for e in events] == ["can_nmt_reset", "can_nmt_start"]
    nmt = [bytes(m.data) for m in msgs if m.arbitration_id == 0]
    assert nmt == [bytes([129, 10]), bytes([1, 10])]
    i_reset = next(i for i, m in enumerate(msgs) if m.arbitration_id == 0)
    after = msgs[i_reset + 1:]
    # boot-up, then PRE-OPERATIONAL heartbeats and no pose until the start command
    assert (after[0].arbitration_id, bytes(after[0].data)) == (0x70A, b"\x00")
    i_start = next(i for i, m in enumerate(after) if m.arbitration_id == 0)
    between = after[1:i_start]
    assert not [m for m in between if m.arbitration_id in (0x18A, 0x28A, 0x38A)]
    assert {bytes(m.data) for m in between if m.arbitration_id == 0x70A} == {b"\x7f"}
    assert [m for m in after[i_start:] if m.arbitration_id == 0x38A]  # poses again
