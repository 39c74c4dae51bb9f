"""The harvester of a scenario on the CAN bus: trajectory + pose error -> CANopen node.

The pose on the bus is the machine's base point relative to the datum (the scenario's
``plot.origin_m``), evaluated at whole microseconds so that the time stamp in TPDO3 is exactly
the time of the pose it travels with; :func:`truth_pose` gives the error-free pose at the same
time stamp for the recorder and for tests.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from emulators.faults import CanFaultPlan, FaultEvent
from emulators.harvester import (
    DEFAULT_SOCKETCAND_PORT,
    BusSpec,
    CanLog,
    HarvesterNode,
    NodeConfig,
    NodeStats,
    RunClock,
    SimClock,
    kernel_has_vcan,
    node_id_in_use,
    parse_bus_spec,
    socketcand_answers,
)
from protocols.harvester import (
    STATUS_MOVING,
    STATUS_PASS_SHIFT,
    STATUS_POSE_ERROR,
    STATUS_REVERSE,
    STATUS_VALID,
    Pose,
)
from tcf_hil.scenario import Scenario
from tcf_hil.world.faults import fault_plans, faults_active
from tcf_hil.world.terrain import Terrain
from tcf_hil.world.track import PoseError, Trajectory

if TYPE_CHECKING:
    from emulators.canbus import ServerProcess, SocketcandServer
    from tcf_hil.world import World


LISTEN_S = 0.5  # before a run's or `harvester run`'s node boots: see run_harvester


@dataclass(frozen=True)
class HarvesterModel:
    """Everything that decides what the node says, without any bus."""

    scenario: Scenario
    trajectory: Trajectory
    error: PoseError

    @classmethod
    def from_scenario(cls, scn: Scenario, terrain: Terrain, seed: int = 0,
                      t0_ns: int = 1_000_000_000) -> HarvesterModel:
        traj = Trajectory.from_config(scn.track, terrain, t0_ns)
        return cls(scn, traj, PoseError(scn.harvester.pose_error, seed, t0_ns))

    @classmethod
    def from_world(cls, world: World) -> HarvesterModel:
        """The node's model in a run's world: its track, and the pose error drawn from the
        run's seed."""
        return cls(world.scenario, world.track,
                   PoseError(world.scenario.harvester.pose_error, world.seed, world.t0_ns))

    def truth(self, t_ns: np.ndarray, *, pointwise: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Error-free (position (n, 3), heading deg, pitch deg, roll deg, speed, status);
        ``pointwise``: each time's values with the bits it has when asked alone."""
        st = self.trajectory.vehicle_state(t_ns, pointwise=pointwise)
        status = (STATUS_VALID | np.where(st.moving, STATUS_MOVING, 0)
                  | np.where(st.speed < 0, STATUS_REVERSE, 0)
                  | (np.minimum(st.pass_no, 255) << STATUS_PASS_SHIFT))
        if self.error.active:
            status = status | STATUS_POSE_ERROR
        return (st.position, st.heading_deg, np.degrees(st.pitch), np.degrees(st.roll),
                st.speed, status)

    def bus_pose(self, t_ns: int) -> Pose:
        """The pose the node publishes at simulation time ``t_ns`` (taken at the whole
        microsecond it carries; pose error applied)."""
        t_us = t_ns // 1000
        t = np.array([t_us * 1000], dtype=np.int64)
        pos, hd, pitch, roll, speed, status = self.truth(t)
        pos, hd = self.error.apply(pos, hd, t)
        return Pose(float(pos[0, 0]), float(pos[0, 1]), float(pos[0, 2]), float(hd[0]),
                    float(pitch[0]), float(roll[0]), float(speed[0]), t_us, int(status[0]))

    def bus_poses(self, t_ns: list[int]) -> list[Pose]:
        """:meth:`bus_pose` at each of ``t_ns``, evaluated together (what an offline run
        feeds per lidar frame: the per-call overhead of the trajectory and the terrain was
        a few per cent of a cell). Each pose has the bits :meth:`bus_pose` gives it."""
        if not t_ns:
            return []
        t_us = [t // 1000 for t in t_ns]
        t = np.array(t_us, dtype=np.int64) * 1000
        pos, hd, pitch, roll, speed, status = self.truth(t, pointwise=True)
        pos, hd = self.error.apply(pos, hd, t)
        return [Pose(float(pos[i, 0]), float(pos[i, 1]), float(pos[i, 2]), float(hd[i]),
                     float(pitch[i]), float(roll[i]), float(speed[i]), us, int(status[i]))
                for i, us in enumerate(t_us)]

    def truth_pose(self, t_us: int) -> Pose:
        """The error-free pose at a bus time stamp (full microseconds)."""
        t = np.array([t_us * 1000], dtype=np.int64)
        pos, hd, pitch, roll, speed, status = self.truth(t)
        return Pose(float(pos[0, 0]), float(pos[0, 1]), float(pos[0, 2]), float(hd[0]),
                    float(pitch[0]), float(roll[0]), float(speed[0]), t_us, int(status[0]))

    def node_config(self, *, node_id: int | None = None, rate_hz: float | None = None,
                    sync_producer: bool = True, autostart: bool = True,
                    unix_epoch_ns: int | None = None, listen_s: float = 0.0) -> NodeConfig:
        h, tr = self.scenario.harvester, self.scenario.track
        origin = self.scenario.plot.origin_m
        return NodeConfig(
            node_id=node_id if node_id is not None else h.node_id,
            rate_hz=rate_hz if rate_hz is not None else h.rate_hz,
            sync_producer=sync_producer, autostart=autostart, heartbeat_ms=h.heartbeat_ms,
            datum_mm=tuple(round(v * 1000) for v in origin),  # type: ignore[arg-type]
            mount_mm=(round(tr.mount_xy_m[0] * 1000), round(tr.mount_xy_m[1] * 1000),
                      round(tr.start_m[2] * 1000)),
            mount_cdeg=(round(tr.mount_rpy_deg[2] * 100), round(tr.mount_rpy_deg[1] * 100),
                        round(tr.mount_rpy_deg[0] * 100)),
            unix_epoch_ns=unix_epoch_ns, listen_s=listen_s)


@contextlib.contextmanager
def open_bus(spec_text: str, *, announce: Callable[[str], None] = lambda s: None
             ) -> Iterator[BusSpec]:
    """The bus for a ``--can`` value; ``own`` starts a CAN server of its own on a free port
    of 127.0.0.1 (a run's default: nobody else is on it); ``auto`` picks vcan0, else joins or
    starts the socketcand server on 127.0.0.1:29536. A server started here stops on exit."""
    server: SocketcandServer | ServerProcess | None = None
    if spec_text.strip() == "own":
        from emulators.canbus import ServerProcess

        # in a process of its own: the relaying stays off the run's interpreter lock, which
        # the lidar sender needs at every packet
        server = ServerProcess("127.0.0.1", 0)
        spec: BusSpec | None = BusSpec("socketcand", "vcan0", "127.0.0.1", server.port)
        announce(f"bus: the run's own CAN server at {spec}")
    else:
        spec = parse_bus_spec(spec_text)
    if spec is None:
        host, port = "127.0.0.1", DEFAULT_SOCKETCAND_PORT
        if kernel_has_vcan("vcan0"):
            spec = BusSpec("socketcan", "vcan0")
            announce("bus: socketcan:vcan0 (kernel CAN)")
        elif socketcand_answers(host, port):
            spec = BusSpec("socketcand", "vcan0", host, port)
            announce(f"bus: joined the CAN server at {spec}")
        else:
            from emulators.canbus import SocketcandServer

            server = SocketcandServer(host, port)
            server.start()
            spec = BusSpec("socketcand", "vcan0", host, server.port)
            announce(f"bus: no kernel CAN here; embedded CAN server at {spec}")
    try:
        yield spec
    finally:
        if server is not None:
            server.stop()


@dataclass
class HarvesterRunResult:
    spec: str
    node_id: int
    sim_seconds: float
    stats: dict[str, Any]
    log_frames: int
    log_path: Path | None
    log_error: str | None = None  # why the CAN log stopped early (e.g. the disk is full)
    conflict: str | None = None  # a second node with this id was on the bus: stopped


def run_harvester(scn: Scenario, terrain: Terrain, spec: BusSpec, *, seed: int = 0,
                  node_id: int | None = None, rate_hz: float | None = None,
                  log_path: Path | None = None, speed: float = 1.0,
                  duration_s: float | None = None, sync_producer: bool = True,
                  autostart: bool = True, stop: threading.Event | None = None,
                  clock: SimClock | RunClock | None = None, t0_ns: int = 1_000_000_000,
                  on_tick: Callable[[float, float], None] | None = None,
                  faults: CanFaultPlan | None = None,
                  on_fault: Callable[[FaultEvent], None] | None = None,
                  on_conflict: Callable[[str], None] | None = None,
                  on_node: Callable[[NodeStats], None] | None = None,
                  world: World | None = None,
                  model: HarvesterModel | None = None,
                  until_stop: bool = False,
                  stand_from_ns: int | None = None) -> HarvesterRunResult:
    """Drive the scenario's track in (scaled) real time with the node on ``spec`` until the
    track ends (plus one second standing), ``duration_s`` of simulation time, or ``stop``.
    ``faults``/``on_fault``: injected CAN faults and where their events go (default: the
    scenario's ``[faults.can]``, events dropped). A second node with the node's id on the
    bus stops it at once: the result's ``conflict`` says so, and ``on_conflict`` hears it.
    ``on_node`` gets the node's live :class:`~emulators.harvester.NodeStats` as it starts.
    ``world``: the run's world (its track, seed and fault plans), resolved once, in place of
    ``terrain``, ``seed`` and ``t0_ns``; ``model``: the node's model built from it already.
    ``until_stop``: publish until ``stop`` (an always-on run's node), whatever the track;
    ``stand_from_ns``: the machine stands from this simulation time on (a run cut short)."""
    if model is None:
        model = (HarvesterModel.from_world(world) if world is not None
                 else HarvesterModel.from_scenario(scn, terrain, seed, t0_ns))
    clash = threading.Event()

    def conflicting(why: str) -> None:
        clash.set()
        if on_conflict is not None:
            on_conflict(why)

    # half a second of listening first: a node with this id already on the bus (heartbeat
    # every 100 ms, TPDOs at 100 Hz) stops this one before it says a word. With a clock of
    # our own, before that clock starts (no simulated time lost); a caller's clock has its
    # lead for it
    cfg = model.node_config(node_id=node_id, rate_hz=rate_hz, sync_producer=sync_producer,
                            autostart=autostart, listen_s=LISTEN_S if clock else 0.0)
    if clock is None:
        twin = node_id_in_use(spec, cfg.node_id, LISTEN_S)
        if twin is not None:
            conflicting(twin)
            return HarvesterRunResult(str(spec), cfg.node_id, 0.0, {}, 0, log_path,
                                      None, twin)
    clock = clock or SimClock.start(model.trajectory.t0_ns, speed)
    end_ns: int | None = (None if until_stop else model.trajectory.end_ns + 1_000_000_000
                          if duration_s is None else clock.t0_ns + round(duration_s * 1e9))
    stop = stop or threading.Event()
    can_log: CanLog | None = None
    if faults is None and world is not None:
        faults = world.faults.can if world.faults is not None else None
    elif faults is None and faults_active(scn.faults):
        faults = fault_plans(scn.faults, seed, model.trajectory.t0_ns).can
    pose_at = model.bus_pose if stand_from_ns is None else standing_from(model.bus_pose,
                                                                          stand_from_ns)

    node = HarvesterNode(spec, pose_at, clock, cfg, faults=faults, on_fault=on_fault,
                         on_conflict=conflicting)
    if on_node is not None:
        on_node(node.stats)
    try:
        if log_path is not None:  # first, so that it sees the boot-up
            can_log = CanLog(log_path, spec).start()
        node.start()
        total = (end_ns - clock.t0_ns) / 1e9 if end_ns is not None else math.inf
        while not stop.is_set() and not clash.is_set():
            now = clock.now_ns()
            if on_tick is not None:
                on_tick((now - clock.t0_ns) / 1e9, total)
            if end_ns is not None and now >= end_ns:
                break
            clash.wait(0.2 if end_ns is None else
                       min(0.2, max(0.0, (end_ns - now) / 1e9 / clock.speed)))
    finally:
        node.stop()
        if can_log is not None:
            time.sleep(0.05)  # the last frames reach the log's own connection
            can_log.stop()
    st = {k: v for k, v in vars(node.stats).items() if k != "batch_times_ns"}
    bt = np.diff(np.array(node.stats.batch_times_ns, dtype=np.float64)) / 1e3
    if len(bt):
        period = 1e6 / cfg.rate_hz / clock.speed
        st["tpdo_period_us_p50"] = float(np.median(bt))
        st["tpdo_jitter_us_p99"] = float(np.percentile(np.abs(bt - period), 99))
    return HarvesterRunResult(str(spec), cfg.node_id,
                              (min(clock.now_ns(), end_ns if end_ns is not None
                                   else clock.now_ns()) - clock.t0_ns) / 1e9, st,
                              can_log.frames if can_log else 0, log_path,
                              can_log.error if can_log else None, node.conflict)


def standing_from(bus_pose: Callable[[int], Pose], stop_ns: int) -> Callable[[int], Pose]:
    """``bus_pose`` until ``stop_ns``, then the machine standing where it was then: the
    same pose, stamped with each time asked for, at speed 0."""

    stood: list[Pose] = []  # the pose it stands in, made once (the same for every time)

    def pose_at(t_ns: int) -> Pose:
        if t_ns <= stop_ns:
            return bus_pose(t_ns)
        if not stood:
            stood.append(bus_pose(stop_ns))
        return dataclasses.replace(stood[0], time_us=t_ns // 1000, speed_m_s=0.0)

    return pose_at


def heading_error_deg(a: float, b: float) -> float:
    """Smallest angle between two compass headings."""
    d = (a - b) % 360.0
    return min(d, 360.0 - d)


__all__ = ["HarvesterModel", "HarvesterRunResult", "heading_error_deg", "open_bus",
           "run_harvester", "standing_from"]
