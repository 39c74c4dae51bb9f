"""The harvester as a CANopen node on a python-can bus.

canopen's :class:`~canopen.LocalNode` provides the object dictionary (from our EDS) and the SDO
server. Everything time-driven is done here, in one scheduler thread, because canopen 2.4 leaves
it to the application (see the research note's pitfalls): the NMT state machine with boot-up and
resets, the heartbeat, the optional SYNC producer, SYNC-triggered TPDOs (every n-th SYNC per
transmission type), event-timer TPDOs and the TIME object. Every TPDO of one SYNC is packed from
one quantised pose sample, so no frame ever carries parts of two poses; nothing but heartbeat,
SYNC and TIME leaves the node outside OPERATIONAL. A bus that fails (server gone, interface
deleted) is reported and reconnected; foreign and malformed frames are counted and ignored.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen

from emulators.faults import CanFaultPlan, FaultEvent
from emulators.harvester._bus import BusSpec
from emulators.harvester._clock import RunClock, SimClock
from protocols.harvester import (
    DATUM,
    HARVESTER_OD,
    HEARTBEAT_BASE,
    MOUNT,
    SYNC_COB,
    TIME_COB,
    CanProtocolError,
    Mapping,
    Pose,
    eds_path,
    encode_pdo,
    encode_time,
    pose_to_raw,
)

log = logging.getLogger("tcf_hil.harvester")

PRE_OPERATIONAL, OPERATIONAL, STOPPED, INITIALISING = 127, 5, 4, 0
_STATE_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}
_NMT_TARGET = {1: OPERATIONAL, 2: STOPPED, 128: PRE_OPERATIONAL}
#: transports that hand a client its own frames back (multicast loopback): there a second
#: node with our id is only seen in the listening before boot
_ECHOING = frozenset({"udp_multicast"})


@dataclass
class NodeStats:
    """Counters of one node's life (read them any time; they only grow)."""

    syncs_sent: int = 0
    syncs_received: int = 0
    pose_samples: int = 0
    tpdo_frames: int = 0
    heartbeats: int = 0
    time_frames: int = 0
    boot_ups: int = 0
    nmt_commands: int = 0
    foreign_frames: int = 0
    malformed_frames: int = 0
    #: frames on this node's own COB-IDs that it did not send: a second node with its id
    id_conflict_frames: int = 0
    tx_dropped: int = 0  # frames refused by a full transmit queue (ENOBUFS)
    bus_errors: int = 0  # sends or receives that failed (each leads to a reconnect)
    reconnects: int = 0
    pose_errors: int = 0
    fault_lost: int = 0  # frames lost on purpose (injected CAN loss)
    bus_off_dropped: int = 0  # frames not sent while bus-off (injected)
    delayed_batches: int = 0  # pose TPDO batches sent late on purpose
    #: monotonic ns of each SYNC-triggered TPDO batch (bounded; for jitter measurements)
    batch_times_ns: list[int] = field(default_factory=list, repr=False)


@dataclass(frozen=True)
class NodeConfig:
    node_id: int = 10
    rate_hz: float = 100.0  # own SYNC producer rate (pose rate)
    sync_producer: bool = True
    autostart: bool = True  # go OPERATIONAL after boot without an NMT master
    heartbeat_ms: int = 100
    time_period_s: float = 1.0  # TIME object (0: off)
    datum_mm: tuple[int, int, int] = (0, 0, 0)
    mount_mm: tuple[int, int, int] = (0, 0, 2000)
    mount_cdeg: tuple[int, int, int] = (0, 0, 0)  # yaw, pitch, roll in 0.01 deg
    unix_epoch_ns: int | None = None  # wall time (Unix ns) at simulation time t0; None: now
    reconnect_s: float = 0.5
    #: listen this long before booting: a node with the same id already on the bus shows
    #: itself (its heartbeat every 100 ms, its TPDOs at 100 Hz) and this one stays silent
    #: (0: boot at once; tcf-hil's runs and `harvester run` listen 0.5 s)
    listen_s: float = 0.0


class _ReceiveErrors(can.Listener):
    """Hands the notifier's receive errors to the node instead of killing its thread."""

    def __init__(self, node: HarvesterNode) -> None:
        self._node = node

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        self._node._receive_failed(exc)


class HarvesterNode:
    """Run with :meth:`start` / :meth:`stop` (or as a context manager).

    ``pose_at(t_ns)`` gives the pose to publish at simulation time ``t_ns`` (with any pose
    error already applied); ``clock`` is the run's simulation clock. ``faults``: injected
    CAN faults (loss of the node's own frames, late pose TPDOs, bus-off windows, NMT resets
    from a second master), each reported to ``on_fault`` with its simulation time.

    A frame on one of this node's own COB-IDs (EMCY, TPDO1-4, SDO answers, heartbeat) that it
    did not send means a second node with the same id is on the bus, and a consumer would
    mix both poses: :attr:`conflict` then names it and ``on_conflict`` is called once (from
    the bus's receive thread; do not block there). No transport here hands a node its own
    frames back (python-can's ``receive_own_messages`` is off; the CAN server relays to
    the others only) except udp_multicast, where only the listening before boot
    (``cfg.listen_s``) can tell.
    """

    def __init__(self, bus: BusSpec, pose_at: Callable[[int], Pose], clock: SimClock | RunClock,
                 cfg: NodeConfig = NodeConfig(), *, eds: Path | None = None,
                 on_frame: Callable[[can.Message], None] | None = None,
                 faults: CanFaultPlan | None = None,
                 on_fault: Callable[[FaultEvent], None] | None = None,
                 on_conflict: Callable[[str], None] | None = None) -> None:
        if not 1 <= cfg.node_id <= 127:
            raise ValueError(f"node id: expected 1..127, got {cfg.node_id}")
        self.spec, self.pose_at, self.clock, self.cfg = bus, pose_at, clock, cfg
        self.stats = NodeStats()
        self.network = canopen.Network()
        self.node = canopen.LocalNode(cfg.node_id, str(eds or eds_path()))
        self.network.add_node(self.node)
        # NMT and heartbeat are ours (canopen's NmtSlave would start a second heartbeat task
        # on writes to 0x1017 and never boot up again after a reset)
        self.node._write_callbacks.remove(self.node.nmt.on_write)
        self.network.unsubscribe(0, self.node.nmt.on_command)
        self._send_lock = threading.RLock()
        plain_send = self.network.send_message

        def locked_send(can_id: int, data: bytes, remote: bool = False) -> None:
            with self._send_lock:  # the SDO server sends from the notifier thread
                plain_send(can_id, data, remote)

        self.network.send_message = locked_send  # type: ignore[method-assign]
        # SDO reads of the pose objects answer the last sample (no OD writes per SYNC)
        self.node.add_read_callback(self._read_pose_object)
        self._wake = threading.Event()
        self._fail_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = INITIALISING
        self._pending_nmt: list[int] = []
        self._sync_count = 0
        self._ext_syncs: list[int] = []
        self._connected = False
        self._on_frame = on_frame
        self._unix0 = cfg.unix_epoch_ns if cfg.unix_epoch_ns is not None else time.time_ns()
        self._sync_maps: list[Mapping] = []
        self._event_maps: list[Mapping] = []
        self._last_raw: dict[tuple[int, int], int] | None = None
        self._faults = faults
        self._on_fault = on_fault or (lambda ev: None)
        self._on_conflict = on_conflict
        self.conflict: str | None = None
        self._taken_cobs = _taken(cfg.node_id)
        self._delayed: list[tuple[int, int, bytes]] = []  # (due monotonic ns, cob, data)
        self._bus_off: int | None = None  # index of the bus-off window in effect
        self._next_reset = 0  # index into faults.nmt_reset_at_ns
        self._restarts: list[int] = []  # simulation ns of pending master 'start' commands
        od: Any = self.node.sdo
        for i, v in enumerate(cfg.datum_mm, 1):
            od[DATUM][i].raw = v
        for i, v in enumerate((*cfg.mount_mm, *cfg.mount_cdeg), 1):
            od[MOUNT][i].raw = v
        od[0x1017].raw = cfg.heartbeat_ms
        od[0x1006].raw = round(1e6 / cfg.rate_hz)
        if cfg.sync_producer:
            od[0x1005].raw = SYNC_COB | 0x4000_0000

    # -- public ------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        return _STATE_NAMES[self._state]

    @property
    def connected(self) -> bool:
        return self._connected

    def start(self) -> HarvesterNode:
        """Connect, listen ``cfg.listen_s`` for a node with the same id, then boot (unless
        one was heard: then :attr:`conflict` says so and the node never speaks)."""
        if self.cfg.listen_s > 0:
            self._listen_for_twin()
            if self.conflict is not None:
                return self
        self._connect()
        self._thread = threading.Thread(target=self._run, name=f"harvester-{self.cfg.node_id}",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self._disconnect()

    def __enter__(self) -> HarvesterNode:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- bus ---------------------------------------------------------------------------------
    def _connect(self) -> None:
        self.spec.precheck()
        # canopen's notifier waits up to this long per receive; python-can's socketcand client
        # spins through it when its server has gone, so keep it short
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect(**self.spec.kwargs())
        self.network.subscribe(0, self._on_nmt)
        self.network.subscribe(SYNC_COB, self._on_sync)
        assert self.network.notifier is not None
        self.network.notifier.add_listener(self._classify)
        self.network.notifier.add_listener(_ReceiveErrors(self))
        self._connected = True
        log.info("node %d on %s", self.cfg.node_id, self.spec)

    def _listen_for_twin(self) -> None:
        """Before the node's own connection exists (so nothing of this node, not even its
        SDO server, answers yet): :func:`node_id_in_use` for ``cfg.listen_s``."""
        twin = node_id_in_use(self.spec, self.cfg.node_id, self.cfg.listen_s)
        if twin is not None:
            self.stats.id_conflict_frames += 1
            self.conflict = twin
            log.info("node %d: %s", self.cfg.node_id, twin)
            if self._on_conflict is not None:
                self._on_conflict(twin)

    def _disconnect(self) -> None:
        self._connected = False
        with contextlib.suppress(Exception):
            self.network.unsubscribe(0)
            self.network.unsubscribe(SYNC_COB)
        with contextlib.suppress(Exception):
            self.network.disconnect()

    def _reconnect(self) -> None:
        self._disconnect()
        while not self._stop.is_set():
            try:
                self._connect()
                self.stats.reconnects += 1
                log.warning("node %d: bus %s back", self.cfg.node_id, self.spec)
                return
            except Exception as e:
                log.debug("reconnect failed: %s", e)
                self._disconnect()
                self._stop.wait(self.cfg.reconnect_s)

    def _bus_failed(self, e: Exception, where: str) -> None:
        """One failure, counted and reported once, however many threads see it."""
        with self._fail_lock:
            was, self._connected = self._connected, False
        if was:
            self.stats.bus_errors += 1
            log.warning("node %d: bus %s failed on %s (%s); reconnecting", self.cfg.node_id,
                        self.spec, where, e)
        self._wake.set()

    def _receive_failed(self, e: Exception) -> None:
        """From the notifier's thread: the bus failed under a receive; the run loop
        reconnects. Waits a little, so a dead socket does not spin the notifier."""
        self._bus_failed(e, "receive")
        self._stop.wait(min(self.cfg.reconnect_s, 0.1))

    def _send(self, cob_id: int, data: bytes) -> bool:
        if not self._connected:
            return False
        plan = self._faults
        if plan is not None:
            if self._bus_off is not None:
                self.stats.bus_off_dropped += 1
                return False
            if plan.lose():
                self.stats.fault_lost += 1
                self._on_fault({"kind": "can_loss", "t_ns": self.clock.now_ns(),
                                "cob_id": f"0x{cob_id:03X}"})
                return False
        return self._send_raw(cob_id, data)

    def _send_raw(self, cob_id: int, data: bytes) -> bool:
        try:
            with self._send_lock:
                self.network.send_message(cob_id, data)
        except (can.CanError, OSError) as e:
            code = getattr(e, "error_code", None) or getattr(e, "errno", None)
            if code == errno.ENOBUFS:
                # a full transmit queue (real CAN with nobody acknowledging): the frame is
                # lost, the bus is not
                self.stats.tx_dropped += 1
                return False
            self._bus_failed(e, "send")
            return False
        if self._on_frame is not None:
            self._on_frame(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                                       timestamp=time.time()))
        return True

    # -- receive side (notifier thread: never block here) ------------------------------------
    def _own_cobs(self) -> set[int]:
        n = self.cfg.node_id
        return {0, SYNC_COB, TIME_COB, 0x600 + n}

    def _classify(self, msg: can.Message) -> None:
        cob = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            self.stats.foreign_frames += 1
        elif cob == 0 and len(msg.data) != 2:
            self.stats.malformed_frames += 1
        elif cob == SYNC_COB and len(msg.data) > 1:
            self.stats.malformed_frames += 1
        elif cob == 0x600 + self.cfg.node_id and len(msg.data) != 8:
            self.stats.malformed_frames += 1
        elif cob in self._taken_cobs:
            if self.spec.interface not in _ECHOING:  # else it may be our own, looped back
                self._conflicting(msg)
        elif cob not in self._own_cobs():
            self.stats.foreign_frames += 1

    def _conflicting(self, msg: can.Message) -> None:
        self.stats.id_conflict_frames += 1
        if self.conflict is not None:
            return
        self.conflict = _twin_text(self.spec, self.cfg.node_id, msg.arbitration_id)
        log.info("node %d: %s", self.cfg.node_id, self.conflict)  # the caller says it
        if self._on_conflict is not None:
            self._on_conflict(self.conflict)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != 2:
            return
        cs, target = data[0], data[1]
        if target not in (0, self.cfg.node_id) or cs not in (1, 2, 128, 129, 130):
            return
        self.stats.nmt_commands += 1
        self._pending_nmt.append(cs)
        self._wake.set()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) > 1:
            return
        self.stats.syncs_received += 1
        if not self.cfg.sync_producer:
            self._ext_syncs.append(data[0] if data else 0)
            self._wake.set()

    # -- scheduler ---------------------------------------------------------------------------
    def _read_mappings(self) -> None:
        """TPDO parameters from the object dictionary (so SDO remapping in PRE-OPERATIONAL
        takes effect at the next start, as CiA 301 intends)."""
        sd: Any = self.node.sdo
        sync_maps: list[Mapping] = []
        event_maps: list[Mapping] = []
        for k in range(4):
            comm, mp = sd[0x1800 + k], sd[0x1A00 + k]
            cob = int(comm[1].raw)
            if cob & 0x8000_0000:
                continue  # PDO disabled
            n = min(int(mp[0].raw), 8)
            keys = []
            for s in range(1, n + 1):
                code = int(mp[s].raw)
                keys.append((code >> 16, (code >> 8) & 0xFF))
            if not keys:
                continue
            m = Mapping(k + 1, (cob & 0x7FF) - self.cfg.node_id, int(comm[2].raw),
                        int(comm[5].raw), tuple(keys))
            (sync_maps if 1 <= m.trans_type <= 240 else event_maps).append(m)
        self._sync_maps, self._event_maps = sync_maps, event_maps

    def _boot(self, autostart: bool) -> None:
        self._state = INITIALISING
        self._read_mappings()
        self._sync_count = 0
        if self._send(HEARTBEAT_BASE + self.cfg.node_id, b"\x00"):
            self.stats.boot_ups += 1
        self._state = OPERATIONAL if autostart else PRE_OPERATIONAL
        log.info("node %d booted: %s", self.cfg.node_id, self.state)

    def _apply_nmt(self) -> None:
        while self._pending_nmt:
            cs = self._pending_nmt.pop(0)
            if cs in (129, 130):
                # a reset comes from a master: boot up again and wait in PRE-OPERATIONAL
                # for its start command
                self._boot(autostart=False)
            else:
                if cs == 1 and self._state != OPERATIONAL:
                    self._read_mappings()
                self._state = _NMT_TARGET[cs]

    def _read_pose_object(self, *, index: int, subindex: int, od: object) -> int | None:
        raw = self._last_raw
        return None if raw is None else raw.get((index, subindex))

    def _sample(self) -> dict[tuple[int, int], int] | None:
        t = self.clock.now_ns()
        try:
            raw = pose_to_raw(self.pose_at(t), HARVESTER_OD)
        except CanProtocolError as e:
            self.stats.pose_errors += 1
            log.error("node %d: pose at %d ns not encodable: %s", self.cfg.node_id, t, e)
            return None
        self._last_raw = raw
        self.stats.pose_samples += 1
        return raw

    def _publish_sync(self) -> None:
        """One SYNC: every due synchronous TPDO from one pose sample."""
        self._sync_count += 1
        if self._state != OPERATIONAL:
            return
        due = [m for m in self._sync_maps if self._sync_count % m.trans_type == 0]
        if not due:
            return
        raw = self._sample()
        if raw is None:
            return
        frames = [(m.cob_id(self.cfg.node_id), encode_pdo(m, raw, HARVESTER_OD)) for m in due]
        if self._faults is not None and self._faults.pose_delay_ns:
            due_ns = time.monotonic_ns() + round(self._faults.pose_delay_ns / self.clock.speed)
            self._delayed.extend((due_ns, cob, data) for cob, data in frames)
            self.stats.delayed_batches += 1
            self._on_fault({"kind": "can_pose_delay", "t_ns": self.clock.now_ns(),
                            "delay_ms": self._faults.pose_delay_ns / 1e6})
            return
        for cob, data in frames:
            if self._send(cob, data):
                self.stats.tpdo_frames += 1
        bt = self.stats.batch_times_ns
        if len(bt) < 1_000_000:
            bt.append(time.monotonic_ns())

    def _inject(self) -> int | None:
        """Scheduled CAN faults due now (bus-off windows, NMT commands of a second master,
        late TPDOs); returns the next monotonic time something is due, if any."""
        plan = self._faults
        if plan is None:
            return None
        t = self.clock.now_ns()
        w = plan.bus_off(t)
        if w != self._bus_off:
            if w is not None:
                self._bus_off = w
                self._on_fault({"kind": "can_bus_off", "t_ns": t,
                                "recovery_s": plan.bus_off_ns / 1e9})
            else:
                self._bus_off = None
                n = self.cfg.node_id  # EMCY 0x8140 "recovered from bus-off", then "no error"
                self._send_raw(0x80 + n, bytes([0x40, 0x81, 0x11, 0, 0, 0, 0, 0]))
                self._send_raw(0x80 + n, bytes(8))
                self._on_fault({"kind": "can_bus_off_recovered", "t_ns": t,
                                "dropped": self.stats.bus_off_dropped})
        ats = plan.nmt_reset_at_ns
        while self._next_reset < len(ats) and ats[self._next_reset] <= t:
            self._next_reset += 1
            self._send_raw(0, bytes([129, self.cfg.node_id]))  # the frame of a second master
            self._pending_nmt.append(129)
            self.stats.nmt_commands += 1
            self._on_fault({"kind": "can_nmt_reset", "t_ns": t})
            if plan.nmt_restart_ns:
                self._restarts.append(t + plan.nmt_restart_ns)
        while self._restarts and self._restarts[0] <= t:
            self._restarts.pop(0)
            self._send_raw(0, bytes([1, self.cfg.node_id]))
            self._pending_nmt.append(1)
            self.stats.nmt_commands += 1
            self._on_fault({"kind": "can_nmt_start", "t_ns": t})
        now = time.monotonic_ns()
        while self._delayed and self._delayed[0][0] <= now:
            _due, cob, data = self._delayed.pop(0)
            if self._send(cob, data):
                self.stats.tpdo_frames += 1
        nxt = [self._delayed[0][0]] if self._delayed else []
        for at in ([self._restarts[0]] if self._restarts else []) + (
                [ats[self._next_reset]] if self._next_reset < len(ats) else []) + [
                a for a in plan.bus_off_at_ns if a > t] + [
                a + plan.bus_off_ns for a in plan.bus_off_at_ns if a + plan.bus_off_ns > t]:
            nxt.append(self.clock.monotonic_at(at))
        return min(nxt) if nxt else None

    def _run(self) -> None:
        sd: Any = self.node.sdo
        self._boot(self.cfg.autostart)
        now = time.monotonic_ns()
        next_sync = next_hb = next_time = now
        next_event = {m.number: now for m in self._event_maps}
        while not self._stop.is_set():
            if not self._connected:
                self._reconnect()
                continue
            fault_due = self._inject()
            self._apply_nmt()
            now = time.monotonic_ns()
            if self.cfg.sync_producer and now >= next_sync:
                # SYNC and event periods are simulation time: --speed 5 sends 5x as often
                period = round(max(int(sd[0x1006].raw), 100) * 1000 / self.clock.speed)
                next_sync = max(next_sync + period, now - period)
                if self._state in (PRE_OPERATIONAL, OPERATIONAL) and self._send(SYNC_COB, b""):
                    self.stats.syncs_sent += 1
                self._publish_sync()
            while self._ext_syncs:
                self._ext_syncs.pop(0)
                self._publish_sync()
            hb = int(sd[0x1017].raw)
            if hb and now >= next_hb:
                next_hb = max(next_hb + hb * 1_000_000, now)
                if self._send(HEARTBEAT_BASE + self.cfg.node_id, bytes([self._state])):
                    self.stats.heartbeats += 1
            if self.cfg.time_period_s and now >= next_time:
                next_time = max(next_time + round(self.cfg.time_period_s * 1e9), now)
                if self._state in (PRE_OPERATIONAL, OPERATIONAL) and int(sd[0x1012].raw) & (
                        1 << 30):
                    sim = self.clock.now_ns() - self.clock.t0_ns
                    if self._send(TIME_COB, encode_time((self._unix0 + sim) // 1_000_000)):
                        self.stats.time_frames += 1
            for m in self._event_maps:
                due = next_event.setdefault(m.number, now)
                if m.event_timer_ms and now >= due:
                    next_event[m.number] = max(
                        due + round(m.event_timer_ms * 1_000_000 / self.clock.speed), now)
                    if self._state == OPERATIONAL:
                        raw = self._sample()
                        if raw is not None and self._send(m.cob_id(self.cfg.node_id),
                                                          encode_pdo(m, raw, HARVESTER_OD)):
                            self.stats.tpdo_frames += 1
            deadlines = [fault_due, next_time if self.cfg.time_period_s else None,
                         next_hb if hb else None,
                         next_sync if self.cfg.sync_producer else None,
                         *(next_event.get(m.number) for m in self._event_maps
                           if m.event_timer_ms)]
            wake = min(d for d in deadlines if d is not None) if any(
                d is not None for d in deadlines) else time.monotonic_ns() + 100_000_000
            delay = (wake - time.monotonic_ns()) / 1e9
            if delay > 0:
                self._wake.wait(min(delay, 0.1))
                self._wake.clear()

    def __repr__(self) -> str:
        return f"HarvesterNode(id={self.cfg.node_id}, {self.spec}, {self.state})"


def _taken(node_id: int) -> set[int]:
    """The COB-IDs only node ``node_id`` sends: EMCY, TPDO1-4, SDO answers, heartbeat."""
    n = node_id
    return {0x80 + n, 0x180 + n, 0x280 + n, 0x380 + n, 0x480 + n, 0x580 + n,
            HEARTBEAT_BASE + n}


def _twin_text(spec: BusSpec, node_id: int, cob: int) -> str:
    return (f"a second CANopen node with id {node_id} is on {spec}: it sent 0x{cob:03X}, one "
            "of this node's own COB-IDs (another harvester or bench on the same bus?)")


def node_id_in_use(spec: BusSpec, node_id: int, listen_s: float) -> str | None:
    """Listen on ``spec`` for ``listen_s`` with a plain python-can client: what says that a
    node with ``node_id`` is already there (a frame on one of its own COB-IDs), or None.

    Raises:
        can.CanInitializationError: the bus cannot be opened.
    """
    if listen_s <= 0:
        return None
    bus = spec.open()
    taken = _taken(node_id)
    try:
        deadline = time.monotonic() + listen_s
        while (left := deadline - time.monotonic()) > 0:
            msg = bus.recv(timeout=min(left, 0.05))
            if msg is not None and not (msg.is_extended_id or msg.is_remote_frame
                                        or msg.is_error_frame) \
                    and msg.arbitration_id in taken:  # a master's RTR (guarding) is no twin
                return _twin_text(spec, node_id, msg.arbitration_id)
    finally:
        bus.shutdown()
    return None


def describe(node: HarvesterNode) -> dict[str, Any]:
    """A JSON-able summary of the node's counters."""
    s = node.stats
    return {k: v for k, v in vars(s).items() if k != "batch_times_ns"} | {
        "state": node.state, "bus": str(node.spec), "node_id": node.cfg.node_id}

