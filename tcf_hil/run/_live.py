"""A live run's traffic: the harvester on CAN and the OS0-64 on UDP on one simulation clock.

The scene is built when the session binds its endpoints; the frame producer forks before
the SIC starts (nothing else has threads or children then); the clock starts once the SIC
is ready, with a lead: the harvester node publishes the standing machine's pose while the
SIC starts, and the first lidar packet is due when the clock reaches the track's start.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from emulators.harvester import SimClock
from protocols.ouster import SensorMetadata
from tcf_hil._io import write_bytes_atomic
from tcf_hil.devices.endpoints import SensorHost
from tcf_hil.devices.faults import FaultLog
from tcf_hil.devices.harvester import HarvesterModel, run_harvester
from tcf_hil.run._figures import LiveFigures
from tcf_hil.run._manifest import Manifest, SicRecord
from tcf_hil.run._session import Announce, Wire, quiet
from tcf_hil.run._sic import sensor_url
from tcf_hil.scenario import Scenario, scenario_to_dict

if TYPE_CHECKING:
    from tcf_hil.world import World

# the track starts at simulation time 60 s: the harvester's lead before it never reaches
# negative times (the CAN pose time is an unsigned 32-bit microsecond count)
RUN_T0_NS = 60_000_000_000
# the fault events that strike a frame out, wholly or in part (emulators.faults)
LOSSES = frozenset({"udp_loss", "udp_burst_loss", "lidar_dropout"})


class _LateClock:
    """The run's clock for the lidar sender, fixed only once the SIC is ready: until then
    the sender (which asks for its first packet's due time) waits."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self._clock: SimClock | None = None
        self._set = threading.Event()

    def set(self, clock: SimClock) -> None:
        if self._clock is None:
            self._clock = clock
        self._set.set()

    def is_set(self) -> bool:
        return self._set.is_set()

    @property
    def clock(self) -> SimClock | None:
        return self._clock

    def monotonic_at(self, t_sim_ns: int) -> int:
        self._set.wait()
        assert self._clock is not None
        return self._clock.monotonic_at(t_sim_ns)


class LiveTraffic:
    """The emulated OS0-64 and harvester node driven along ``scn``'s track (see the module
    docstring). ``record_lidar``: keep lidar.pcap and sensor_poses.csv (off for long runs:
    2048x10 sends 16 MB/s). ``progress(done, total)`` counts frames on the wire."""

    noun = "stream"
    world: World  # the run's world, resolved once in bind(): every device takes it
    harvester: HarvesterModel  # the node's model in that world, built once

    def __init__(self, scn: Scenario, *, mode: str = "2048x10",
                 profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
                 speed: float = 1.0, lead_s: float = 3.0, duration_s: float | None = None,
                 backend: str = "auto", record_lidar: bool = True,
                 progress: Any = None, announce: Announce = quiet) -> None:
        if lead_s * speed * 1e9 >= RUN_T0_NS:
            raise ValueError(f"lead {lead_s} s at speed {speed} reaches before simulation "
                             "time 0")
        self.scn, self.mode, self.profile, self.seed = scn, mode, profile, seed
        self.speed, self.lead_s, self.duration_s = speed, lead_s, duration_s
        self.backend, self.record_lidar = backend, record_lidar
        self.progress, self.announce = progress, announce
        self.node_id = scn.harvester.node_id
        self.late = _LateClock(speed)  # set once the SIC listens (the sender waits for it)
        self.end_stream = threading.Event()
        self.harv_stop = threading.Event()
        self.forked = threading.Event()
        self.threads: list[threading.Thread] = []
        self.lidar_result: Any = None
        self.lidar_error: BaseException | None = None
        self.harv_result: Any = None
        self.conflicts: list[str] = []
        self.flog: FaultLog | None = None
        self.frames_done = 0  # frames the sender has handled (sent, or dropped by a fault)
        self.lost_frames: set[int] = set()  # frames an injected fault struck out, wholly or in part
        self.send_stats: Any = None  # the sender's live SendStats
        self.node_stats: Any = None  # the harvester node's live NodeStats

    def preferred_ports(self) -> tuple[int, int]:
        return 7502, 7503

    def bind(self, out: Path | None, host: SensorHost, ports: tuple[int, int]
             ) -> tuple[SensorMetadata, Path | None]:
        from tcf_hil.devices.lidar import LidarRun
        from tcf_hil.world import World

        assert out is not None, "a live run records into a run directory"
        scn = self.scn
        self.out, self.sensor_ip = out, host.address
        self.announce(f"building {scn.name} ({self.mode}, {self.profile}) ...")
        self.world = world = World.build(scn, seed=self.seed, t0_ns=RUN_T0_NS, lidar_ports=ports)
        self.harvester = HarvesterModel.from_world(world)  # the node's model, once
        run = LidarRun(scn, mode=self.mode, profile=self.profile, backend=self.backend,
                       udp_dest="127.0.0.1", udp_port_lidar=ports[0], udp_port_imu=ports[1],
                       keep_poses=self.record_lidar, world=world)
        if self.duration_s is not None:
            run.frames = max(1, min(run.frames,
                                    round(self.duration_s * run.meta.frequency_hz)))
        self.run = run
        self.can_faults = world.faults.can if world.faults is not None else None
        if world.faults is not None:
            self.flog = FaultLog(out / "faults.jsonl", world.t0_ns)
        write_bytes_atomic(out / "metadata.json", run.meta.dumps().encode())
        return run.meta, out / "metadata.json"

    def manifest(self, sic: SicRecord | None) -> Manifest:
        run, scn = self.run, self.scn
        node = self.harvester.node_config()
        return Manifest(
            scenario=scn.name, seed=run.forest.seed, mode=self.mode, profile=self.profile,
            speed=self.speed, sic=sic, backend=run.backend, lidar_pcap=self.record_lidar,
            frames_planned=run.frames,
            can_node={"node_id": node.node_id, "datum_mm": list(node.datum_mm),
                      "mount_mm": list(node.mount_mm), "mount_cdeg": list(node.mount_cdeg)},
            faults=None if self.flog is None else {
                "config": scenario_to_dict(scn)["faults"], "log": "faults.jsonl"})

    def prepare(self, wire: Wire) -> None:
        """The frame producer forks first, before the threads and the SIC exist."""
        from tcf_hil.devices.lidar import stream_lidar

        run, out, flog = self.run, self.out, self.flog
        api = wire.api

        def on_lidar_fault(ev: dict[str, Any]) -> None:
            assert flog is not None
            flog.log(ev)
            if ev["kind"] in LOSSES:
                self.lost_frames.add(int(ev.get("frame", -1)))
            if ev["kind"] == "lidar_reinit":  # the sensor serves its new identity
                if api is not None:
                    api.update(lambda m: m.with_changes(init_id=ev["init_id"]))
                # the file describes lidar.pcap: the stream's own metadata (made ports; the
                # sender set the new init_id before this call)
                write_bytes_atomic(out / "metadata.json", run.meta.dumps().encode())

        def step(done: int, total: int) -> None:
            self.frames_done = done
            if self.progress is not None:
                self.progress(done, total)

        def on_sender(stats: Any) -> None:
            self.send_stats = stats

        def lidar() -> None:
            try:
                self.lidar_result = stream_lidar(
                    self.scn, sensor_ip=self.sensor_ip, record=out, run=run,
                    stop=self.end_stream, clock=self.late, progress=step, on_sender=on_sender,
                    pcap_in_place=True, forked=self.forked,
                    on_fault=on_lidar_fault if flog is not None else None,
                    pcap=self.record_lidar, route=wire.route)
            except BaseException as err:
                self.lidar_error = err
            finally:
                self.forked.set()

        self._start_thread(lidar, "lidar")
        self.forked.wait(60.0)

    def _start_thread(self, target: Any, name: str) -> None:
        th = threading.Thread(target=target, name=name, daemon=True)
        th.start()
        self.threads.append(th)

    def start(self, wire: Wire, manifest: Manifest) -> None:
        run, speed = self.run, self.speed
        t0 = run.track.t0_ns
        lead_ns = round(self.lead_s * 1e9)  # wall time before the first lidar packet is due
        clock = SimClock.start(t0, speed, lead_ns=lead_ns)
        self.late.set(clock)
        # the harvester's view of the same clock starts now, lead_ns * speed before t0
        harv_clock = SimClock(t0 - round(lead_ns * speed), clock.origin_monotonic_ns - lead_ns,
                              speed)
        unix_at_t0 = time.time_ns() + (clock.origin_monotonic_ns - time.monotonic_ns())
        manifest.clock = {"sim_t0_ns": t0, "unix_ns_at_sim_t0": unix_at_t0, "speed": speed,
                          "lead_s": self.lead_s}
        seconds = run.frames / run.meta.frequency_hz + 1.0
        flog = self.flog

        def harvester() -> None:
            self.harv_result = run_harvester(
                self.scn, self.world.forest.terrain, wire.spec, world=self.world,
                model=self.harvester,
                log_path=self.out / "can.log", speed=speed, stop=self.harv_stop,
                clock=harv_clock, duration_s=self.lead_s * speed + seconds,
                faults=self.can_faults, on_fault=flog.log if flog is not None else None,
                on_conflict=self.conflicts.append, on_node=self._on_node)

        self._start_thread(harvester, "harvester")

    def _on_node(self, stats: Any) -> None:
        self.node_stats = stats

    def truth(self) -> dict[str, Any] | None:
        return self.run.ground_truth()

    def figures(self, fig: LiveFigures) -> None:
        run = self.run
        fig.sim_total_s = run.frames / run.meta.frequency_hz
        clock = self.late.clock
        fig.frames_sent, fig.frames_total = self.frames_done, run.frames
        if clock is not None:
            fig.sim_s = min((clock.now_ns() - run.track.t0_ns) / 1e9, fig.sim_total_s)
            fig.behind_s = max(0.0, fig.sim_s - self.frames_done / run.meta.frequency_hz)
        fig.frames_lost = len(self.lost_frames)
        if self.send_stats is not None:
            fig.refused = self.send_stats.refused
        if self.node_stats is not None:
            fig.can = self.node_stats.pose_samples

    def describe(self, wire: Wire) -> str:
        api = sensor_url(wire.api) if wire.api is not None else "off"
        port = self.run.meta.udp_port_lidar
        return (f"run: sensor {wire.host.address} (API {api}), lidar to "
                f"{wire.route.dest_ip}:{wire.route.port(port)}, CAN {wire.spec}; "
                f"{self.run.frames} frames")

    def alive(self, timeout_s: float) -> bool:
        th = self.threads[0] if self.threads else None
        if th is None:
            return False
        th.join(timeout_s)
        return th.is_alive()

    def conflict(self) -> str | None:
        return self.conflicts[0] if self.conflicts else None

    def finish(self) -> None:
        self.end_stream.set()
        if not self.late.is_set():  # a sender still waiting for the clock goes on
            self.late.set(SimClock.start(0, self.speed))
        if self.threads:
            self.threads[0].join()
        if self.lidar_error is not None:
            raise self.lidar_error

    def close(self, manifest: Manifest) -> None:
        self.end_stream.set()
        self.harv_stop.set()
        if not self.late.is_set():
            self.late.set(SimClock.start(0, self.speed))
        for th in self.threads:
            th.join(timeout=60.0)
        if self.flog is not None:
            self.flog.close()
            assert manifest.faults is not None
            manifest.faults["injected"] = self.flog.summary()
        r = self.lidar_result
        if r is not None:
            manifest.lidar = {"frames_sent": r.frames, "packets_sent": r.packets,
                              "pacing_us_p50_p99": list(r.pacing_us),
                              "sender_cpu_share": r.sender_cpu_share, "refused": r.refused}
        h = self.harv_result
        if h is not None:
            manifest.can = {"bus": h.spec, "node_id": h.node_id, "frames_logged": h.log_frames,
                            "log_error": h.log_error, "conflict": h.conflict}
