"""Recorded traffic back on the wire with its original timing (times ``speed``): a tcf-hil
run directory or a field recording (an Ouster pcap with its metadata, and a CAN log); the
recorded metadata on the sensor's HTTP API and, for a run, the harvester node's SDO server
answering what it answered (:mod:`tcf_hil.recording.reader`)."""

from __future__ import annotations

import contextlib
import ipaddress
import os
import shutil
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from protocols.ouster import SensorMetadata
from tcf_hil._io import write_bytes_atomic
from tcf_hil.devices.endpoints import SensorHost
from tcf_hil.run._figures import LiveFigures
from tcf_hil.run._manifest import Manifest, SicRecord
from tcf_hil.run._session import Wire
from tcf_hil.run._sic import sensor_url

RECORDING_FILES = ("lidar.pcap", "can.log", "can.asc", "can.blf", "can.trc",
                   "metadata.json", "ground_truth.json", "inventory.csv", "visibility.json",
                   "sensor_poses.csv", "lidar_labels.bin")


def _loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return address == "localhost"


def _link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` the same bytes as ``src``: a hard link where the file system allows (a day's
    pcap is not copied for every replay of it), else a copy."""
    with contextlib.suppress(FileNotFoundError):
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def copy_recording(src: Path, out: Path) -> None:
    """The replayed run's inputs beside its new SIC output (what was sent is what was
    recorded: the same bytes)."""
    for name in RECORDING_FILES:
        if (src / name).exists():
            _link_or_copy(src / name, out / name)


class ReplayTraffic:
    """The recording ``src`` sent again: a run directory or an Ouster pcap (``meta``: its
    metadata JSON, found beside it when None; ``can_log``: a CAN log to put on the bus,
    ``can_offset_s`` added to its time stamps). ``dest``: where the datagrams go (default:
    the recorded ``udp_dest``); ``loop``: start over at the end (frame_id, column time
    stamps and pose time continue) until stopped; ``lead_s``: the SIC's head start before
    the first datagram (the recorded CAN lead comes on top)."""

    noun = "replay"

    def __init__(self, src: Path, *, speed: float = 1.0, loop: bool = False,
                 dest: str | None = None, lead_s: float = 3.0, meta: Path | None = None,
                 can_log: Path | None = None, can_offset_s: float = 0.0,
                 progress: Callable[[int, int], None] | None = None,
                 ports: tuple[int | None, int | None] = (None, None),
                 truth: Path | None = None) -> None:
        from tcf_hil.recording.reader import Recording

        self.src, self.speed, self.loop, self.lead_s = src, speed, loop, lead_s
        self.ports = ports
        self.truth_path = truth
        if truth is not None:  # read now: a bad inventory is an error before anything runs
            from tcf_hil.recording.inventory import load_truth

            load_truth(truth)
        self.rec = Recording.load(src, meta=meta, can_log=can_log, can_offset_s=can_offset_s,
                                  progress=progress)
        self.src_man: dict[str, Any] = dict(self.rec.manifest or {})
        self.node: dict[str, Any] = dict(self.src_man.get("can_node") or {})
        # a run's harvester node answers its SDO reads again, as does a field log's node
        # that the log shows answering SDO uploads (with the values it gave); any other
        # field log is sent as it is
        rec = self.rec
        self.node_id: int = int(self.node.get("node_id", rec.sdo_node or 10))
        self.sdo_node: int | None = self.node_id if rec.is_run or rec.sdo_node else None
        recorded = self.rec.meta.udp_dest
        if dest is None and not _loopback(recorded):
            dest = "127.0.0.1"  # a field recording's udp_dest is the field computer's
        self.note = "" if dest is None or dest == recorded else \
            f" (recorded udp_dest {recorded or 'not set'}: --dest to change)"
        if rec.guessed_ports is not None:
            self.note += (f" (the metadata names no ports; the capture's: lidar "
                          f"{rec.guessed_ports[0]}, IMU {rec.guessed_ports[1] or 'none'})")
        if dest is not None:
            self.rec.meta = self.rec.meta.with_changes(udp_dest=dest)
        self.meta_served = self.rec.meta
        self.sent: dict[str, int] = {}
        self.end = threading.Event()
        self.thread: threading.Thread | None = None
        self.sdo: Any = None
        self.with_sic = False

    def preferred_ports(self) -> tuple[int, int]:
        lidar, imu = self.ports
        return lidar or self.rec.meta.udp_port_lidar, imu or self.rec.meta.udp_port_imu

    def bind(self, out: Path | None, host: SensorHost, ports: tuple[int, int]
             ) -> tuple[SensorMetadata, Path | None]:
        rec = self.rec
        self.sensor_ip = host.address
        port_map = {rec.meta.udp_port_lidar: ports[0], rec.meta.udp_port_imu: ports[1]}
        rec.port_map = port_map
        meta = rec.meta.with_changes(udp_port_lidar=ports[0], udp_port_imu=ports[1])
        if out is None:
            self.meta_served = meta
            return meta, None
        self._copy(out)  # metadata.json as recorded: it describes lidar.pcap
        path = out / "metadata.json"
        if meta != SensorMetadata.loads(rec.meta_text):  # the recorded ports are taken, or
            # the document named no destination or ports: the SIC gets the ones used now
            path = out / "replay_metadata.json"
            write_bytes_atomic(path, meta.dumps().encode())
        self.meta_served = meta
        return meta, path

    def _copy(self, out: Path) -> None:
        rec = self.rec
        if rec.is_run:
            copy_recording(self.src, out)
        else:
            _link_or_copy(rec.pcap, out / "lidar.pcap")
            write_bytes_atomic(out / "metadata.json", rec.meta_text.encode())
            if rec.can_log is not None:
                _link_or_copy(rec.can_log, out / f"can{rec.can_log.suffix.lower()}")
        if self.truth_path is not None:  # the ground truth given replaces the recorded one
            from tcf_hil.recording.inventory import is_inventory

            for name in ("ground_truth.json", "inventory.csv", "visibility.json"):
                with contextlib.suppress(FileNotFoundError):
                    (out / name).unlink()
            shutil.copyfile(self.truth_path, out / (
                "inventory.csv" if is_inventory(self.truth_path) else "ground_truth.json"))

    def manifest(self, sic: SicRecord | None) -> Manifest:
        m = self.src_man
        self.with_sic = sic is not None
        rec = self.rec
        clock = m.get("clock") or {"sim_t0_ns": rec.can_clock[0],
                                   "unix_ns_at_sim_t0": rec.can_clock[1],
                                   "speed": rec.can_clock[2]}
        return Manifest(scenario=m.get("scenario"), seed=m.get("seed"),
                        mode=m.get("mode", rec.meta.mode),
                        profile=m.get("profile", rec.meta.profile), speed=self.speed, sic=sic,
                        can_node=m.get("can_node"), replay_of=str(self.src.resolve()),
                        clock=clock)

    def prepare(self, wire: Wire) -> None:
        from tcf_hil.run._send import SdoResponder

        if self.sdo_node is not None:
            self.sdo = SdoResponder(wire.spec, {**self.node, "node_id": self.node_id},
                                    self.rec.sdo_values)

    def start(self, wire: Wire, manifest: Manifest) -> None:
        from tcf_hil.run._send import replay

        def send() -> None:
            replay(self.src, speed=self.speed, loop=self.loop, sensor_ip=self.sensor_ip,
                   spec=wire.spec, node_id=self.node_id, answered=self.sdo_node is not None,
                   stop=self.end, rec=self.rec, route=wire.route, sent=self.sent)

        if self.with_sic and wire.stop.wait(self.lead_s):
            return
        self.thread = threading.Thread(target=send, name="replay", daemon=True)
        self.thread.start()

    def describe(self, wire: Wire) -> str:
        rec, port = self.rec, self.meta_served.udp_port_lidar
        api = sensor_url(wire.api) if wire.api is not None else "off"
        n = rec.counts
        other = n["other"] + n["not udp"] + n["other sensors"]
        return (f"replaying {self.src}: {rec.frames} frames ({n['lidar']} lidar, {n['imu']} "
                f"IMU packets from {rec.sensor_ip}"
                f"{f'; {other} other frames skipped' if other else ''}), "
                f"{rec.can_frames} CAN frames at {self.speed:g}x from sensor "
                f"{wire.host.address} (API {api}) to {wire.route.dest_ip}:"
                f"{wire.route.port(port)}/{wire.route.port(self.meta_served.udp_port_imu)}"
                f"{self.note}, CAN {wire.spec}"
                + (" (looping; Ctrl-C stops)" if self.loop else ""))

    def alive(self, timeout_s: float) -> bool:
        """Whether the recording's lidar traffic is still going out (a recording of an
        always-on run goes on with its CAN log's tail, the machine standing, until
        :meth:`close`, as the live run did while its SIC finished)."""
        if self.thread is None:
            return False
        self.thread.join(timeout_s)
        lidar = self.rec.counts["lidar"]
        if not self.loop and lidar and self.sent.get("lidar", 0) >= lidar:
            return False
        return self.thread.is_alive()

    def conflict(self) -> str | None:
        return None

    def truth(self) -> dict[str, Any] | None:
        """The ground truth the run is scored against (``--truth``, else the recording's)."""
        from tcf_hil.recording.inventory import load_truth

        own = [self.src / "ground_truth.json", self.src / "inventory.csv"] \
            if self.rec.is_run else []
        for path in (self.truth_path, *own):
            if path is not None and path.exists():
                return load_truth(path)
        return None

    def figures(self, fig: LiveFigures) -> None:
        rec, sent = self.rec, self.sent
        fig.can_noun = "CAN frames"
        fig.frames_total = None if self.loop else rec.frames
        fig.sim_total_s = None if self.loop else rec.span_ns / 1e9
        if not sent:
            return
        fig.sim_s = max(0.0, (sent["at_ns"] - rec.lidar_start_ns) / 1e9)
        if fig.sim_total_s is not None:  # (the CAN log's tail after the last lidar frame)
            fig.sim_s = min(fig.sim_s, fig.sim_total_s)
        lidar = rec.counts["lidar"]  # (a loop goes on past the recording's frames)
        fig.frames_sent = sent["lidar"] * rec.frames // lidar if lidar else 0
        fig.refused, fig.can = sent["refused"], sent["can"]

    def finish(self) -> None:
        """The lidar traffic has gone out (what is left of the CAN log goes on until
        :meth:`close`)."""
        if self.loop or (self.thread is not None and self.sent.get("lidar", 0)
                         < self.rec.counts["lidar"]):  # stopped early: all of it stops
            self.end.set()
            if self.thread is not None:
                self.thread.join()

    def release_bus(self) -> None:
        """The recording's sending (its CAN frames with it) and the SDO answers stopped."""
        self.end.set()
        if self.thread is not None:
            self.thread.join(timeout=30.0)
        if self.sdo is not None:
            self.sdo.close()

    def close(self, manifest: Manifest) -> None:
        self.release_bus()
        sent = self.sent
        manifest.replay_sent = {k: sent[k] for k in ("udp", "lidar", "can", "refused")
                                if k in sent}
        if "first_ns" in sent:
            manifest.replay_clock = {"recording_ns": sent["first_ns"],
                                     "unix_ns": sent["first_unix_ns"], "speed": self.speed}
