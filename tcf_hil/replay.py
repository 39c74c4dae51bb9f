"""A recorded run's traffic: its pcap (lidar and IMU) and CAN log read onto one time line and
sent back on the wire with their original relative timing (scaled by ``speed``), and the
harvester node's SDO answers. The session that serves it (the HTTP API with the recorded
metadata, the SIC, the score) is :class:`tcf_hil.run.ReplayTraffic`'s.

Both recordings are put on one time line: pcap records carry simulation time; the CAN log's
wall-clock time stamps are mapped onto it through the run manifest's clock
(``unix_ns_at_sim_t0``). With ``loop``, each pass shifts frame_id (16 bits, continuing where
the last pass ended, which ouster-sdk's own replay does not do), the column time stamps and
the pose time on CAN by the recording's length, so that a consumer sees one continuous drive.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from emulators.harvester import BusSpec
from emulators.lidar import Route
from protocols.harvester import HARVESTER_OD, POSE, TIME_WRAP_US, decode_pdo, encode_pdo
from protocols.ouster import IMU_PACKET_BYTES, SensorMetadata, shift_lidar_packet
from protocols.pcap import read_udp
from tcf_hil._io import read_json
from tcf_hil.errors import InputError

_TIME_KEY = (POSE, 8)


@dataclass
class Recording:
    """A run directory's traffic on one simulation time line."""

    meta: SensorMetadata
    lidar: list[tuple[int, int, bytes]]  # (sim ns, dst port, payload)
    can: list[tuple[int, can.Message]]  # (sim ns, frame)
    frames: int
    span_ns: int

    @classmethod
    def load(cls, run_dir: Path) -> Recording:
        for name in ("lidar.pcap", "metadata.json", "manifest.json"):
            if not (run_dir / name).exists():
                why = "missing: not a tcf-hil run directory"
                if name == "lidar.pcap" and (run_dir / "manifest.json").exists():
                    why = "missing: this run did not record its lidar traffic (a soak run)"
                raise InputError(str(run_dir / name), "", why)
        meta = SensorMetadata.loads((run_dir / "metadata.json").read_text(encoding="utf-8"))
        man = read_json(run_dir / "manifest.json")
        try:
            clock = man["clock"]
            t0, unix0, speed = (int(clock["sim_t0_ns"]), int(clock["unix_ns_at_sim_t0"]),
                                float(clock["speed"]))
        except (KeyError, TypeError, ValueError) as err:
            raise InputError(str(run_dir / "manifest.json"), "clock",
                             f"missing or malformed ({err})") from err
        lidar = [(d.timestamp_ns, d.dst_port, d.payload)
                 for d in read_udp((run_dir / "lidar.pcap").read_bytes())
                 if d.dst_port in (meta.udp_port_lidar, meta.udp_port_imu)]
        frames: list[tuple[int, can.Message]] = []
        if (run_dir / "can.log").exists():
            for m in can.LogReader(str(run_dir / "can.log")):
                frames.append((t0 + round((m.timestamp * 1e9 - unix0) * speed), m))
        lt = [t for t, p, _b in lidar if p == meta.udp_port_lidar]
        n_frames = len(lt) // max(1, meta.packet_format.packets_per_frame)
        # a pass of a loop lasts the lidar recording plus one frame period, so that the
        # next pass's first frame follows the last at the sensor's own rate
        period = 1_000_000_000 // meta.frequency_hz
        span = (max(lt) - min(lt) + period) if lt else 0
        return cls(meta, lidar, frames, n_frames, span)

    @property
    def lidar_start_ns(self) -> int:
        lt = [t for t, p, _b in self.lidar if p == self.meta.udp_port_lidar]
        return min(lt) if lt else 0


def _shift_imu(payload: bytes, dt_ns: int) -> bytes:
    if dt_ns == 0 or len(payload) != IMU_PACKET_BYTES:
        return payload
    ts = np.frombuffer(payload[:24], "<u8") + np.uint64(dt_ns)
    return ts.astype("<u8").tobytes() + payload[24:]


def _shift_can(msg: can.Message, node_id: int, dt_ns: int) -> can.Message:
    if dt_ns == 0:
        return msg
    for m in HARVESTER_OD.tpdos:
        if msg.arbitration_id == m.cob_id(node_id) and _TIME_KEY in m.variables:
            raw = decode_pdo(m, bytes(msg.data))
            raw[_TIME_KEY] = (raw[_TIME_KEY] + dt_ns // 1000) % TIME_WRAP_US
            return can.Message(arbitration_id=msg.arbitration_id, data=encode_pdo(m, raw),
                               is_extended_id=False)
    return msg


def events(rec: Recording, loop: bool, node_id: int) -> Iterator[tuple[int, str, Any]]:
    """(sim ns, "udp"/"can", item) in time order, forever when ``loop``."""
    merged = sorted([(t, 0, i) for i, (t, _p, _b) in enumerate(rec.lidar)]
                    + [(t, 1, i) for i, (t, _m) in enumerate(rec.can)])
    # after the first pass, only the frames of one span: the run's lead (the pose before
    # the first lidar frame) and its tail are not driven again
    lo = rec.lidar_start_ns
    again = [e for e in merged if lo <= e[0] < lo + rec.span_ns]
    k = 0
    while True:
        dt = k * rec.span_ns
        dframe = k * rec.frames
        for t, kind, i in merged if k == 0 else again:
            if kind == 0:
                _t, port, payload = rec.lidar[i]
                if port == rec.meta.udp_port_lidar:
                    payload = shift_lidar_packet(rec.meta.packet_format, payload, dframe, dt)
                else:
                    payload = _shift_imu(payload, dt)
                yield t + dt, "udp", (port, payload)
            else:
                msg = rec.can[i][1]
                if msg.arbitration_id in (0x580 + node_id, 0x600 + node_id):
                    continue  # the recorded SDO exchanges answer nobody now
                yield t + dt, "can", _shift_can(msg, node_id, dt)
        if not loop:
            return
        k += 1


def replay(run_dir: Path, *, speed: float = 1.0, loop: bool = False,
           sensor_ip: str = "127.0.0.1", dest: str | None = None,
           spec: BusSpec | None = None, node_id: int = 10,
           stop: threading.Event | None = None,
           on_progress: Callable[[int, int], None] | None = None,
           rec: Recording | None = None, route: Route | None = None) -> dict[str, int]:
    """Send the recording until it ends (or forever with ``loop``) or ``stop``. ``route``:
    where datagrams go now (a client of the sensor's HTTP API may move them)."""
    rec = rec or Recording.load(run_dir)
    stop = stop or threading.Event()
    dest = dest or rec.meta.udp_dest
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    sock.bind((sensor_ip, 0))
    bus = spec.open() if spec is not None and rec.can else None
    sent = {"udp": 0, "can": 0, "refused": 0}
    total = len(rec.lidar) + len(rec.can)
    start: tuple[int, float] | None = None
    try:
        for n, (t, kind, item) in enumerate(events(rec, loop, node_id)):
            if stop.is_set():
                break
            if start is None:
                start = (t, time.perf_counter())
            due = start[1] + (t - start[0]) / 1e9 / speed
            wait = due - time.perf_counter()
            if wait > 0.0005:
                time.sleep(wait - 0.0003)
            while time.perf_counter() < due:
                pass
            if kind == "udp":
                port, payload = item
                try:
                    sock.sendto(payload, route.address(port) if route is not None
                                else (dest, port))
                    sent["udp"] += 1
                except OSError:
                    sent["refused"] += 1
            elif bus is not None:
                with contextlib.suppress(can.CanError):
                    bus.send(item)
                    sent["can"] += 1
            if on_progress is not None and n % 256 == 0:
                on_progress(n % total if total else 0, total)
    finally:
        sock.close()
        if bus is not None:
            bus.shutdown()
    return sent


class SdoResponder:
    """The harvester node's SDO server alone (datum and lidar mount as recorded), for
    consumers that read them at start: the recorded TPDOs carry the poses."""

    def __init__(self, spec: BusSpec, node: dict[str, Any]) -> None:
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
        self.network.NOTIFIER_CYCLE = 0.1
        self.network.connect(**spec.kwargs())

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.network.disconnect()
