"""A live run's traffic: the harvester on CAN and the OS0-64 on UDP on one simulation clock.

The scene is built when the session binds its endpoints. The sensor is always on, as a real
OS0 from power-on: when the traffic is prepared (before the SIC starts) it sends the machine
standing at the track's start, at the sensor's cadence, to its current destination, and the
harvester node publishes that standing pose. Once the SIC listens on the lidar port (or
after the ready time) the track is due a lead later: the run's clock
(:class:`~emulators.harvester.RunClock`) steps forward to the track's own start, so the
track keeps its time line and its bytes however long the SIC took. After the track the
machine stands where it stopped until the run ends (those frames are sent, not recorded).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from emulators.harvester import RunClock, SimClock
from protocols.ouster import SensorMetadata
from tcf_hil._io import write_bytes_atomic
from tcf_hil.devices.endpoints import SensorHost
from tcf_hil.devices.faults import FaultLog
from tcf_hil.devices.harvester import HarvesterModel, run_harvester
from tcf_hil.devices.timing import machine_facts
from tcf_hil.recording.store import RenderStore
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
# a render ahead's head start (every core, before the program starts) goes on to the track's
# last frame where the rest takes at most this long (or as long as the head start so far)
HEAD_ALL_S = 30.0


class _HaltedError(Exception):
    """A first Ctrl-C while the whole track renders into the store (``--render stored``)."""


class _LateClock:
    """The run's clock for the lidar sender, fixed only once the frame producer has forked
    (power-on): until then the sender (which asks for its first packet's due time) waits."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self._clock: RunClock | SimClock | None = None
        self._set = threading.Event()

    def set(self, clock: RunClock | SimClock) -> None:
        if self._clock is None:
            self._clock = clock
        self._set.set()

    def is_set(self) -> bool:
        return self._set.is_set()

    @property
    def clock(self) -> RunClock | SimClock | None:
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
                 progress: Any = None, announce: Announce = quiet,
                 render: str = "auto", standing_s: float = 30.0,
                 standing_after_s: float | None = None,
                 halt: threading.Event | None = None) -> None:
        if lead_s * speed * 1e9 >= RUN_T0_NS:
            raise ValueError(f"lead {lead_s} s at speed {speed} reaches before simulation "
                             "time 0")
        self.scn, self.mode, self.profile, self.seed = scn, mode, profile, seed
        self.speed, self.lead_s, self.duration_s = speed, lead_s, duration_s
        self.backend, self.record_lidar = backend, record_lidar
        self.render = render  # where the frames come from (tcf_hil.devices.lidar.RENDER_MODES)
        # the longest the machine may stand before the track (the SIC's start-up and lead):
        # the sensor powers on this much simulation time before the track's start
        self.standing_s = standing_s
        self.standing_after_s = standing_after_s  # None: until the run closes
        self.track_ended = threading.Event()  # the first frame after the track went out
        self.clock: RunClock | None = None
        self.air: Any = None
        self.standing_before = 0  # frames the machine stood before the track
        self.progress, self.announce = progress, announce
        # the run's stop (a first Ctrl-C): ends a render ahead's head start or lead at once
        # (the frames stored so far stay: a later run resumes the render)
        self.halt = halt if halt is not None else threading.Event()
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
        from tcf_hil.devices.lidar import STANDING_CYCLE, LidarRun
        from tcf_hil.world import World

        assert out is not None, "a live run records into a run directory"
        scn = self.scn
        self.out, self.sensor_ip = out, host.address
        self.announce(f"building {scn.name} ({self.mode}, {self.profile}) ...")
        self.world = world = World.build(scn, seed=self.seed, t0_ns=RUN_T0_NS, lidar_ports=ports)
        self.harvester = HarvesterModel.from_world(world)  # the node's model, once
        store = RenderStore() if self.render != "live" else None
        run = LidarRun(scn, mode=self.mode, profile=self.profile, backend=self.backend,
                       udp_dest="127.0.0.1", udp_port_lidar=ports[0], udp_port_imu=ports[1],
                       keep_poses=self.record_lidar, world=world, store=store,
                       render=self.render)
        if self.duration_s is not None:
            run.frames = max(1, min(run.frames,
                                    round(self.duration_s * run.meta.frequency_hz)))
        # the standing machine's frames (before and after the track); the second lot timed:
        # how fast this machine renders the scene (the first lot warmed the emulator up)
        self.announce("the standing machine: its frames ...")
        period = run.period_ns
        before = run.standing(run.track.t0_ns - period)
        t_render = time.perf_counter()
        self.standing = (before, run.standing(run.track.t0_ns + run.frames * period))
        rate = STANDING_CYCLE / max(time.perf_counter() - t_render, 1e-9)
        need = run.meta.frequency_hz * self.speed
        if run.stored is None and self.render == "stored":
            self._render_first(run)
        elif run.stored is None and self.render in ("ahead", "auto"):
            # rendered ahead into the store in a process of its own, below the SIC's
            # priority, and read from there by a producer at the program's priority. auto
            # did render in the producer (at nice 19, a few frames ahead): beside the field
            # SIC and its stem worker on 2 cores that producer fell up to 0.7 s behind (Forest
            # V 1024x10, 676 of 1000 frames late, steal 3.5 ms/s); rendered ahead, none late
            # (2026-12-03; README "Real time")
            self._head_start(run)
            ahead = run.render_ahead() if not self.halt.is_set() else None
            if ahead is not None:
                self._lead(run, ahead)
        # (rendering ahead said its own rate, the track's: the standing cycle's is not it)
        rendered = "" if self.standing[1].from_store or run.stored is not None else (
            f" (the scene renders at {rate / need:.1f}x real time here)")
        if self.halt.is_set() and run.stored is None:  # stopped while rendering
            self.announce("rendering stopped: the frames stored stay (the next run of this "
                          "scene resumes from them)")
        else:
            self.announce(f"frames: {self._source(run)}{rendered}")
        self.run = run
        self.can_faults = world.faults.can if world.faults is not None else None
        if world.faults is not None:
            self.flog = FaultLog(out / "faults.jsonl", world.t0_ns)
        write_bytes_atomic(out / "metadata.json", run.meta.dumps().encode())
        return run.meta, out / "metadata.json"

    def _want(self, run: Any, rate: float) -> float:
        """The frames that must be stored before the track may start, one renderer making
        ``rate`` frames a second alone (:meth:`_lead`'s sum: it keeps a share f of that
        beside the program under test)."""
        cores = os.cpu_count() or 1
        f = 0.85 * 0.5 * max(0.5, (cores - 1) / cores)
        n, need = run.frames, run.meta.frequency_hz * self.speed
        return n - f * rate * (n / need + self.lead_s)

    def _head_start(self, run: Any) -> None:
        """Before the SIC starts the machine is the bench's: the first frames rendered with
        every core this process may use (:meth:`LidarRun.render_head`), until the one
        renderer that carries on beside the program (:meth:`_lead`: the same sum, one
        process's rate taken as the workers' over their number) is far enough behind them,
        and on to the last frame where the rest takes no longer than the head start has, or
        :data:`HEAD_ALL_S` (so that on a small machine nothing renders beside the program at
        all)."""
        workers = len(os.sched_getaffinity(0))
        n, need = run.frames, run.meta.frequency_hz * self.speed
        t0, said = time.monotonic(), [time.monotonic()]

        def enough(d: int, rate: float) -> bool:
            want = self._want(run, rate / workers)
            now = time.monotonic()
            if self.halt.is_set():
                return True
            if d >= n:
                self.announce(f"rendering ahead with {workers} processes: all {n} frames "
                              f"stored ({rate / need:.2f}x real time) in {now - t0:.0f} s")
                return True
            # far enough ahead; but where the rest takes no longer than the head start
            # so far, or HEAD_ALL_S, it is made too: then nothing renders beside the program
            # at all (on 2 cores the one renderer carrying on beside the reference SIC at
            # Forest II 1024x10, speed 2, with the host withholding 0.2 s a second, left the
            # SIC dropping 248 of 500 frames, then 41 with 3 s of frames left to render)
            if d >= want and (n - d) / rate > max(now - t0, HEAD_ALL_S):
                self.announce(f"rendering ahead with {workers} processes: {d}/{n} frames "
                              f"stored ({rate / need:.2f}x real time) in "
                              f"{now - t0:.0f} s; one renderer carries on")
                return True
            if now - said[0] >= 5.0:
                said[0] = now
                eta = ((n - d) if d >= want else (want - d)) / rate
                self.announce(f"rendering ahead with {workers} processes: {d}/{n} frames "
                              f"stored ({rate / need:.2f}x real time); the track can start "
                              f"in about {eta:.0f} s")
            return False

        run.render_head(enough, workers)  # (all of it stored: render_ahead opens it)

    def _lead(self, run: Any, ahead: Any) -> None:
        """Wait until the render going on is far enough ahead that the track, sent at the
        sensor's cadence from a few seconds after power-on, never waits for a frame: with
        the renderer at r frames a second and the track needing c (10 x speed), the frames
        stored d must reach n - f r (n / c + lead), r the rate measured so far (alone on
        the machine) and f = 0.85 (the denser parts of a stand) x half the share of the
        cores the program under test leaves the renderer (it is assumed to keep one busy,
        and its helpers at the renderer's priority to take half of the rest: on 2 cores,
        with the reference SIC and its stem worker at Forest II 1024x10 and speed 2, the
        track still waited for frames with the factor at 0.43; it is 0.21 here). Says how
        far it is every few seconds."""
        n, need = run.frames, run.meta.frequency_hz * self.speed
        t0, d0 = time.monotonic(), int(ahead.done.value)
        said = t0
        while True:
            d, now = int(ahead.done.value), time.monotonic()
            if d >= n or not ahead.running() or self.halt.is_set():
                return
            el = now - t0
            if el >= 1.0 and d > d0:
                rate = (d - d0) / el
                want = self._want(run, rate)
                if d >= want:
                    self.announce(f"rendering ahead: {d}/{n} frames stored "
                                  f"({rate / need:.2f}x real time); the track can start")
                    return
                if now - said >= 5.0:
                    said = now
                    eta = (want - d) / rate
                    self.announce(f"rendering ahead: {d}/{n} frames stored "
                                  f"({rate / need:.2f}x real time); the track can start in "
                                  f"about {eta:.0f} s")
            time.sleep(0.1)

    def _render_first(self, run: Any) -> None:
        """The whole track rendered into the store before the sensor exists (the progress
        line says how far)."""
        total = run.track_frames
        t0 = time.perf_counter()
        step = max(1, total // 10)

        def say(done: int, n: int) -> None:
            if self.halt.is_set():  # a first Ctrl-C: what is stored stays (resumed later)
                raise _HaltedError
            if done % step == 0 or done == n:
                wall = time.perf_counter() - t0
                rate = done / run.meta.frequency_hz / wall if wall else 0.0
                self.announce(f"rendering into the store: {done}/{n} frames "
                              f"({rate:.2f}x real time)")

        with contextlib.suppress(_HaltedError):
            run.render_into_store(progress=say, workers=len(os.sched_getaffinity(0)))

    @staticmethod
    def _source(run: Any) -> str:
        if run.ahead is not None:
            return (f"rendered ahead into the render store ({run.render_key}) and streamed "
                    "from it")
        if run.stored is not None:
            return f"streamed from the render store ({run.render_key})"
        return "rendered live" + (" (nothing stored for this run; tcf-hil render stores it)"
                                  if run.render_mode == "auto" else "")

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

        air = self._power_on_plan(run)
        standing = (air, *self.standing)

        def lidar() -> None:
            try:
                self.lidar_result = stream_lidar(
                    self.scn, sensor_ip=self.sensor_ip, record=out, run=run,
                    stop=self.end_stream, clock=self.late, progress=step, on_sender=on_sender,
                    pcap_in_place=True, forked=self.forked,
                    on_fault=on_lidar_fault if flog is not None else None,
                    pcap=self.record_lidar, route=wire.route, air=standing,
                    on_track_end=self.track_ended.set)
            except BaseException as err:
                self.lidar_error = err
            finally:
                self.forked.set()
                self.track_ended.set()

        self._start_thread(lidar, "lidar")
        self.forked.wait(60.0)
        # power-on: the clock runs from here (half a second for the first frames to be made)
        self.clock = RunClock(air.power_on_ns, time.monotonic_ns() + 500_000_000, self.speed)
        self.late.set(self.clock)
        self.unix_at_power_on = time.time_ns() + (self.clock.origin_monotonic_ns
                                                  - time.monotonic_ns())
        self._start_harvester(wire)

    def _power_on_plan(self, run: Any) -> Any:
        """When the sensor powers on: whole frames before the track's start, as many as the
        machine may stand (``standing_s``), kept after simulation time 0 (the CAN pose
        time is unsigned)."""
        from tcf_hil.devices.lidar import OnAir

        period, t0 = run.period_ns, run.track.t0_ns
        most = min(math.ceil(self.standing_s * 1e9 / period), t0 // period - 1)
        ctx = mp.get_context("fork")
        after = -1 if self.standing_after_s is None else math.ceil(
            self.standing_after_s * self.speed * 1e9 / period)
        self.air = OnAir(t0 - most * period, ctx.RawValue("q", -1), ctx.RawValue("q", -1),
                         after)
        return self.air

    def _start_thread(self, target: Any, name: str) -> None:
        th = threading.Thread(target=target, name=name, daemon=True)
        th.start()
        self.threads.append(th)

    def start(self, wire: Wire, manifest: Manifest) -> None:
        """The SIC is ready: the machine, standing since power-on, drives off ``lead_s``
        from now. The clock steps forward to the track's time line at the next frame the
        producer has not made (``lead_s`` before the track's start: those standing frames
        and the track are recorded on one time line), unless the standing time ran out
        first (then no step: the track starts at its own time)."""
        from tcf_hil.devices.lidar import ring_slots

        run, speed, clock, air = self.run, self.speed, self.clock, self.air
        assert clock is not None and air is not None
        period, t0 = run.period_ns, run.track.t0_ns
        most = (t0 - air.power_on_ns) // period
        now = max(0, math.ceil((clock.now_ns() - air.power_on_ns) / period))
        # (the producer is at most the ring ahead of the clock)
        step = now + ring_slots(run, speed) + 2
        at = step + math.ceil(self.lead_s * speed * 1e9 / period)
        if at < most:
            clock.step(clock.origin_monotonic_ns + round(step * period / speed),
                       t0 - (at - step) * period)
        else:  # no step: the standing frames from here go out on the track's time already
            at, step = most, min(step, most)
        air.step_at.value = step
        air.track_at.value = at
        self.standing_before = at
        at_mono = clock.monotonic_at(t0)
        unix_at_t0 = time.time_ns() + (at_mono - time.monotonic_ns())
        manifest.clock = {"sim_t0_ns": t0, "unix_ns_at_sim_t0": unix_at_t0, "speed": speed,
                          "lead_s": self.lead_s, "power_on_sim_ns": air.power_on_ns,
                          "unix_ns_at_power_on": self.unix_at_power_on,
                          "standing_frames_before_track": at,
                          "standing_frames_recorded": max(0, at - step),
                          "steps": [list(st) for st in clock.steps]}

    def _start_harvester(self, wire: Wire) -> None:
        """The node on the run's clock from power-on (the standing machine's pose first)
        until the run ends."""
        flog, clock = self.flog, self.clock

        def harvester() -> None:
            self.harv_result = run_harvester(
                self.scn, self.world.forest.terrain, wire.spec, world=self.world,
                model=self.harvester,
                log_path=self.out / "can.log", speed=self.speed, stop=self.harv_stop,
                clock=clock, until_stop=True,
                stand_from_ns=self.run.track.t0_ns + self.run.frames * self.run.period_ns,
                faults=self.can_faults, on_fault=flog.log if flog is not None else None,
                on_conflict=self.conflicts.append, on_node=self._on_node)

        self._start_thread(harvester, "harvester")

    def _on_node(self, stats: Any) -> None:
        self.node_stats = stats

    def truth(self) -> dict[str, Any] | None:
        return self.run.ground_truth()

    def figures(self, fig: LiveFigures) -> None:
        run = self.run
        fig.world = self.world
        fig.sim_total_s = run.frames / run.meta.frequency_hz
        clock = self.late.clock
        fig.frames_sent, fig.frames_total = self.frames_done, run.frames
        if clock is not None and self.standing_before:  # the track is under way
            fig.sim_s = max(0.0, min((clock.now_ns() - run.track.t0_ns) / 1e9,
                                     fig.sim_total_s))
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
        """Whether the track is still going out (the sensor stands on afterwards)."""
        if not self.threads:
            return False
        return not self.track_ended.wait(timeout_s)

    def conflict(self) -> str | None:
        return self.conflicts[0] if self.conflicts else None

    def finish(self) -> None:
        """The track has gone out (the sensor stands on until :meth:`close`); a failed
        stream raises here."""
        if not self.late.is_set():  # a sender still waiting for the clock goes on
            self.late.set(SimClock.start(0, self.speed))
        if self.threads and not self.threads[0].is_alive():
            self.threads[0].join()
        if self.lidar_error is not None:
            raise self.lidar_error

    def release_bus(self) -> None:
        """The harvester node and its CAN log stopped (the sensor streams on)."""
        self.harv_stop.set()
        for th in self.threads:
            if th.name == "harvester":
                th.join(timeout=60.0)

    def close(self, manifest: Manifest) -> None:
        self.end_stream.set()
        self.harv_stop.set()
        if not self.late.is_set():
            self.late.set(SimClock.start(0, self.speed))
        for th in self.threads:
            th.join(timeout=60.0)
        run = getattr(self, "run", None)
        if run is not None and run.ahead is not None:
            run.ahead.stop()  # what it stored stays (a later run resumes it)
        if self.flog is not None:
            self.flog.close()
            assert manifest.faults is not None
            manifest.faults["injected"] = self.flog.summary()
        r = self.lidar_result
        if r is not None:
            manifest.lidar = {"frames_sent": r.frames, "packets_sent": r.packets,
                              "pacing_us_p50_p99": list(r.pacing_us),
                              "sender_cpu_share": r.sender_cpu_share, "refused": r.refused,
                              "track_pacing_us_p50_p99": list(r.track_pacing_us),
                              "track_packets_late_1ms": r.track_late_1ms,
                              "track_steal_ms_per_s": r.track_steal_ms_per_s,
                              "sender_realtime": r.realtime,
                              # what decides the sender's wake-ups here (tcf-hil lidar timing)
                              "machine": machine_facts(),
                              "frames_late_from_producer": r.frames_late_from_producer,
                              "late_frames": [{"t_ns": t, "late_us": us, "phase": ph}
                                              for t, us, ph in r.late_frame_log],
                              "render": {"mode": self.render, "key": self.run.render_key,
                                         "from_store": self.run.stored is not None,
                                         "rendered_ahead": self.run.ahead is not None},
                              # the scored part: the track's frames, from the track's start
                              "track": {"first_frame_ns": self.run.track.t0_ns,
                                        "frames": r.frames,
                                        "standing_frames_before": self.standing_before,
                                        "standing_after": "sent, not recorded"}}
        h = self.harv_result
        if h is not None:
            manifest.can = {"bus": h.spec, "node_id": h.node_id, "frames_logged": h.log_frames,
                            "log_error": h.log_error, "conflict": h.conflict}
