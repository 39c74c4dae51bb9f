"""A recorded run's traffic: its pcap (lidar and IMU) and CAN log back on the wire with their
original timing (times ``speed``), the recorded metadata on the sensor's HTTP API and the
harvester node's SDO server answering what it answered (:mod:`tcf_hil.replay`)."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path
from typing import Any

from protocols.ouster import SensorMetadata
from tcf_hil._io import read_json, write_bytes_atomic
from tcf_hil.endpoints import SensorHost
from tcf_hil.run._manifest import Manifest, SicRecord
from tcf_hil.run._session import Announce, RunResult, RunSession, Wire, quiet
from tcf_hil.run._sic import sensor_url

RECORDING_FILES = ("lidar.pcap", "can.log", "metadata.json", "ground_truth.json",
                   "visibility.json", "sensor_poses.csv")


def copy_recording(src: Path, out: Path) -> None:
    """The replayed run's inputs beside its new SIC output (what was sent is what was
    recorded: the same bytes)."""
    for name in RECORDING_FILES:
        if (src / name).exists():
            shutil.copyfile(src / name, out / name)


class ReplayTraffic:
    """The recorded run ``src`` sent again. ``dest``: where the datagrams go (default: the
    recorded ``udp_dest``); ``loop``: start over at the end (frame_id, column time stamps
    and pose time continue) until stopped; ``lead_s``: the SIC's head start before the
    first datagram (the recorded CAN lead comes on top)."""

    noun = "replay"

    def __init__(self, src: Path, *, speed: float = 1.0, loop: bool = False,
                 dest: str | None = None, lead_s: float = 3.0) -> None:
        from tcf_hil.replay import Recording

        self.src, self.speed, self.loop, self.lead_s = src, speed, loop, lead_s
        self.rec = Recording.load(src)
        self.src_man: dict[str, Any] = read_json(src / "manifest.json")
        self.node: dict[str, Any] = dict(self.src_man.get("can_node") or {})
        self.node_id = int(self.node.get("node_id", 10))
        if dest is not None:
            self.rec.meta = self.rec.meta.with_changes(udp_dest=dest)
        self.sent: dict[str, int] = {}
        self.end = threading.Event()
        self.thread: threading.Thread | None = None
        self.sdo: Any = None
        self.with_sic = False

    def preferred_ports(self) -> tuple[int, int]:
        return self.rec.meta.udp_port_lidar, self.rec.meta.udp_port_imu

    def bind(self, out: Path | None, host: SensorHost, ports: tuple[int, int]
             ) -> tuple[SensorMetadata, Path | None]:
        rec = self.rec
        self.sensor_ip = host.address
        if out is None:
            return rec.meta, None
        copy_recording(self.src, out)  # metadata.json as recorded: it describes lidar.pcap
        meta = rec.meta.with_changes(udp_port_lidar=ports[0], udp_port_imu=ports[1])
        path = out / "metadata.json"
        if meta != rec.meta:  # the recorded ports are taken: the SIC gets the ones used now
            path = out / "replay_metadata.json"
            write_bytes_atomic(path, meta.dumps().encode())
        port_map = {rec.meta.udp_port_lidar: ports[0], rec.meta.udp_port_imu: ports[1]}
        rec.lidar = [(t, port_map.get(p, p), b) for t, p, b in rec.lidar]
        rec.meta = meta
        return meta, path

    def manifest(self, sic: SicRecord | None) -> Manifest:
        m = self.src_man
        self.with_sic = sic is not None
        return Manifest(scenario=m.get("scenario"), seed=m.get("seed"), mode=m.get("mode"),
                        profile=m.get("profile"), speed=self.speed, sic=sic,
                        can_node=m.get("can_node"), replay_of=str(self.src.resolve()),
                        clock=m.get("clock"))

    def prepare(self, wire: Wire) -> None:
        from tcf_hil.replay import SdoResponder

        self.sdo = SdoResponder(wire.spec, {**self.node, "node_id": self.node_id})

    def start(self, wire: Wire, manifest: Manifest) -> None:
        from tcf_hil.replay import replay

        def send() -> None:
            self.sent.update(replay(self.src, speed=self.speed, loop=self.loop,
                                    sensor_ip=self.sensor_ip, spec=wire.spec,
                                    node_id=self.node_id, stop=self.end, rec=self.rec,
                                    route=wire.route))

        if self.with_sic and wire.stop.wait(self.lead_s):
            return
        self.thread = threading.Thread(target=send, name="replay", daemon=True)
        self.thread.start()

    def describe(self, wire: Wire) -> str:
        rec, port = self.rec, self.rec.meta.udp_port_lidar
        api = sensor_url(wire.api) if wire.api is not None else "off"
        return (f"replaying {self.src}: {rec.frames} frames, {len(rec.can)} CAN frames at "
                f"{self.speed:g}x from sensor {wire.host.address} (API {api}) to "
                f"{wire.route.dest_ip}:{wire.route.port(port)}/"
                f"{wire.route.port(rec.meta.udp_port_imu)}, CAN {wire.spec}"
                + (" (looping; Ctrl-C stops)" if self.loop else ""))

    def alive(self, timeout_s: float) -> bool:
        if self.thread is None:
            return False
        self.thread.join(timeout_s)
        return self.thread.is_alive()

    def conflict(self) -> str | None:
        return None

    def finish(self) -> None:
        self.end.set()
        if self.thread is not None:
            self.thread.join()

    def close(self, manifest: Manifest) -> None:
        self.end.set()
        if self.thread is not None:
            self.thread.join(timeout=30.0)
        if self.sdo is not None:
            self.sdo.close()
        manifest.replay_sent = dict(self.sent)


def replay_run(src: Path, sic: str | None, out: Path | None, *, speed: float = 1.0,
               shell: bool = False, can_spec: str = "own", grace_s: float = 30.0,
               lead_s: float = 3.0, ready_s: float = 15.0, sensor_ip: str | None = None,
               http_port: int | None = 0, dest: str | None = None, loop: bool = False,
               stop: threading.Event | None = None, announce: Announce = quiet,
               eval_cfg: Any = None) -> RunResult:
    """``tcf-hil run --replay SRC --sic COMMAND``: another SIC scored on recorded traffic.
    The new run directory holds the same recording (replayable in turn), this SIC's
    publications and score. With ``sic`` None (``tcf-hil replay``) the traffic alone."""
    traffic = ReplayTraffic(src, speed=speed, loop=loop, dest=dest, lead_s=lead_s)
    return RunSession(traffic, sic, out, shell=shell, can=can_spec, sensor_ip=sensor_ip,
                      http_port=http_port, grace_s=grace_s, ready_s=ready_s, stop=stop,
                      announce=announce, eval_cfg=eval_cfg).run()
