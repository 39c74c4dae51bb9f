"""A recording sent again: read (:func:`tcf_hil.recording.reader.events`), paced
(:class:`emulators.pacing.Pacer`, the live stream's) and sent (a UDP socket from the sensor's
address, the CAN bus), as python-can's player reads, syncs and sends; and the harvester
node's SDO answers from the recorded ones (:class:`SdoResponder`)."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from emulators.harvester import BusSpec
from emulators.lidar import Route
from emulators.pacing import Pacer
from protocols.ouster import IMU_PACKET_BYTES
from tcf_hil.recording.reader import Recording, events


def replay(run_dir: Path, *, speed: float = 1.0, loop: bool = False,
           sensor_ip: str = "127.0.0.1", dest: str | None = None,
           spec: BusSpec | None = None, node_id: int | None = 10, answered: bool = True,
           stop: threading.Event | None = None,
           on_progress: Callable[[int, int], None] | None = None,
           rec: Recording | None = None, route: Route | None = None,
           sent: dict[str, int] | None = None) -> dict[str, int]:
    """Send the recording until it ends (or forever with ``loop``) or ``stop``. ``route``:
    where datagrams go now (a client of the sensor's HTTP API may move them). ``sent``: the
    counters to keep up to date as it goes (``udp``, ``lidar``, ``can``, ``refused``, and
    ``at_ns``: the recording's time of the latest event); returned."""
    pacer = Pacer(speed)  # read (events), pace (the pacer the live stream uses), send
    rec = rec or Recording.load(run_dir)
    stop = stop or threading.Event()
    dest = dest or rec.meta.udp_dest or "127.0.0.1"  # (a document may name none)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    sock.bind((sensor_ip, 0))
    bus = spec.open() if spec is not None and rec.can_frames else None
    sent = sent if sent is not None else {}
    sent.update(udp=0, lidar=0, can=0, refused=0, at_ns=0)
    lidar_port = rec.port_map.get(rec.meta.udp_port_lidar, rec.meta.udp_port_lidar)
    total = rec.counts["lidar"] + rec.counts["imu"] + rec.can_frames
    try:
        for n, (t, kind, item) in enumerate(events(rec, loop, node_id, answered=answered)):
            if stop.is_set():
                break
            pacer.wait(t)
            sent["at_ns"] = t
            if n == 0:  # where the recording's time line meets the wall clock
                sent["first_ns"], sent["first_unix_ns"] = t, time.time_ns()
            if kind == "udp":
                port, payload = item
                try:
                    sock.sendto(payload, route.address(port) if route is not None
                                else (dest, port))
                    sent["udp"] += 1
                    sent["lidar"] += port == lidar_port and len(payload) != IMU_PACKET_BYTES
                except OSError:
                    sent["refused"] += 1
            elif bus is not None:
                try:
                    bus.send(item)
                    sent["can"] += 1
                except can.CanError:
                    pass
                except OSError:  # the bus is gone (its server closed): the lidar goes on
                    sent["can_lost"] = sent.get("can_lost", 0) + 1
                    with contextlib.suppress(Exception):
                        bus.shutdown()
                    bus = None
            if on_progress is not None and n % 256 == 0:
                on_progress(n % total if total else 0, total)
    finally:
        sock.close()
        if bus is not None:
            bus.shutdown()
    return sent


class SdoResponder:
    """The harvester node's SDO server alone (datum and lidar mount as recorded), for
    consumers that read them at start: the recorded TPDOs carry the poses. ``node``: a run
    manifest's ``can_node`` (node_id, datum_mm, mount_mm, mount_cdeg); ``recorded``: the
    object values a field CAN log shows the node answering
    (:func:`tcf_hil.recording.reader.recorded_sdo`), put in where the harvester's object
    dictionary has them."""

    def __init__(self, spec: BusSpec, node: dict[str, Any],
                 recorded: dict[tuple[int, int], bytes] | None = None) -> None:
        import canopen

        from protocols.harvester import DATUM, MOUNT, eds_path

        self.network = canopen.Network()
        self.node = canopen.LocalNode(int(node.get("node_id", 10)), str(eds_path()))
        self.network.add_node(self.node)
        od: Any = self.node.sdo
        for i, v in enumerate(node.get("datum_mm", (0, 0, 0)), 1):
            od[DATUM][i].raw = int(v)
        for i, v in enumerate((*node.get("mount_mm", (0, 0, 2000)),
                               *node.get("mount_cdeg", (0, 0, 0))), 1):
            od[MOUNT][i].raw = int(v)
        for (index, sub), data in (recorded or {}).items():
            with contextlib.suppress(KeyError, ValueError, TypeError):
                self.node.set_data(index, sub, data, check_writable=False)
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect(**spec.kwargs())

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.network.disconnect()
