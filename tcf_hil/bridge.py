"""A hardware-in-the-loop run: the harvester on CAN and the OS0-64 on UDP (+ HTTP API) on one
simulation clock, the SIC under test as a separate process with its endpoints in the
environment, the recorder keeping everything in the run directory, and the score at the end.

Order of events: the scene is built first (seconds for a hectare), then the SIC is launched,
then the clock starts with a lead (the harvester node publishes the standing machine's pose
while the SIC starts; the first lidar packet is due when the clock reaches the track's start),
then the stream runs until the track ends, the SIC ends, or the user stops the run.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, cast

from emulators.harvester import BusSpec, SimClock
from emulators.lidar import Route, SensorApi
from protocols.harvester import eds_path
from tcf_hil._io import ensure_dir, read_json, write_bytes_atomic, write_json_atomic
from tcf_hil.endpoints import SensorHost, UdpPorts, claim_sensor_host, reserve_udp_ports
from tcf_hil.evaluation import EvalConfig
from tcf_hil.faults import FaultLog, fault_plans, faults_active
from tcf_hil.harvester import HarvesterModel, open_bus, run_harvester
from tcf_hil.recorder import (
    MAX_PUBLICATION_BYTES,
    FileWatcher,
    Inbox,
    PublishServer,
    Scores,
    empty_forest,
    score_forest,
)
from tcf_hil.scenario import Scenario, scenario_to_dict

RUN_T0_NS = 60_000_000_000
ENV_DOC: tuple[tuple[str, str], ...] = (
    ("TCF_RUN_DIR", "the run directory"),
    ("TCF_METADATA", "the sensor's metadata JSON file"),
    ("TCF_SENSOR_URL", "the sensor's HTTP API, http://HOST (port 80, as a real sensor's)"),
    ("TCF_SENSOR_HOST", "the sensor's own address: packets come from it, its API answers "
                        "on port 80 there (SensorFrameSetSource(HOST) works)"),
    ("TCF_LIDAR_BIND", "the address they go to (the metadata's udp_dest)"),
    ("TCF_LIDAR_PORT", "lidar UDP port"),
    ("TCF_IMU_PORT", "IMU UDP port"),
    ("TCF_CAN_SPEC", "the bus as tcf-hil writes it (socketcand:HOST:PORT:CHANNEL, ...)"),
    ("TCF_CAN_INTERFACE", "python-can interface (socketcand, socketcan, virtual)"),
    ("TCF_CAN_CHANNEL", "CAN channel (vcan0)"),
    ("TCF_CAN_HOST", "socketcand host (socketcand only)"),
    ("TCF_CAN_PORT", "socketcand port (socketcand only)"),
    ("TCF_CAN_NODE_ID", "the harvester's CANopen node id"),
    ("TCF_EDS", "the harvester node's EDS file"),
    ("TCF_PUBLISH_URL", "POST forests here (http://127.0.0.1:PORT/publish)"),
    ("TCF_PUBLISH_FILE", "or rewrite this file atomically with each forest"),
    ("TCF_PUBLISH", "where tcf-hil's reference SIC publishes (stdout unless set: "
                    "file:PATH or an http:// URL; yours may ignore it)"),
)


def udp_port_taken(host: str, port: int) -> bool:
    """Whether someone has bound ``host:port`` (UDP), e.g. the SIC listening for lidar."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, port))
        return False
    except OSError:
        return True
    finally:
        s.close()


def wait_for_listener(host: str, port: int | Callable[[], int], timeout_s: float,
                      alive: Callable[[], bool], stop: threading.Event) -> bool:
    """Wait until something listens on ``host:port`` (UDP), ``alive()`` turns false or
    ``stop`` is set; False after ``timeout_s``. ``port`` may be a callable: the port the
    sensor sends to now (a client can move it through the HTTP API while starting)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and alive() and not stop.is_set():
        if udp_port_taken(host, port() if callable(port) else port):
            return True
        time.sleep(0.05)
    return False


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

    def monotonic_at(self, t_sim_ns: int) -> int:
        self._set.wait()
        assert self._clock is not None
        return self._clock.monotonic_at(t_sim_ns)


_PLACEHOLDER = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


def sic_command(command: str, env: dict[str, str], shell: bool) -> list[str] | str:
    """The COMMAND with ``{placeholders}`` (lower-case names of the TCF_ variables without
    the prefix, e.g. ``{lidar_port}``, and ``{python}``) filled in; other braces are left
    alone. Split without a shell unless asked.

    Raises:
        ValueError: an unknown placeholder, or an empty command.
    """
    values = {k[4:].lower(): v for k, v in env.items() if k.startswith("TCF_")}
    values["python"] = sys.executable

    def fill(s: str) -> str:
        def one(m: re.Match[str]) -> str:
            if m.group(1) not in values:
                raise ValueError(f"--sic {command!r}: unknown placeholder {m.group(0)}; "
                                 "known: " + ", ".join("{" + k + "}" for k in sorted(values)))
            return values[m.group(1)]
        return _PLACEHOLDER.sub(one, s)

    if shell:
        if not command.strip():
            raise ValueError("--sic: empty command")
        return fill(command)
    try:
        args = [fill(a) for a in shlex.split(command)]
    except ValueError as err:
        if "placeholder" in str(err):
            raise
        raise ValueError(f"--sic {command!r}: {err}") from err
    if not args:
        raise ValueError("--sic: empty command")
    return args


def check_sic_command(command: str, shell: bool) -> None:
    """Fail before anything starts when COMMAND cannot be filled in."""
    sic_command(command, {k: "x" for k, _ in ENV_DOC}, shell)


@dataclass
class RunResult:
    out: Path
    #: complete | sic-exited | sic-failed | can-conflict | interrupted | failed
    status: str
    message: str
    scores: Scores | None
    manifest: dict[str, Any]
    sic_returncode: int | None
    publications: int
    invalid_publications: int
    timeline: list[dict[str, Any]] = field(default_factory=list)


class _SicProcess:
    """The SIC under test in a session (process group) of its own: stdout read line by line
    (NDJSON forests; other lines kept as its log), stderr straight to a file.

    Raises:
        OSError: the program cannot be started (the log files are closed again).
    """

    def __init__(self, argv: list[str] | str, env: dict[str, str], out: Path, inbox: Inbox,
                 shell: bool) -> None:
        self.stdout_log: IO[bytes] = open(out / "sic" / "stdout.log", "wb")
        self.stderr_log: IO[bytes] = open(out / "sic" / "stderr.log", "wb")
        self.inbox = inbox
        try:
            self.proc = subprocess.Popen(argv, shell=shell, env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.PIPE, stderr=self.stderr_log,
                                         start_new_session=True)
        except OSError:
            self.stdout_log.close()
            self.stderr_log.close()
            raise
        self.signalled: str | None = None  # the signal the bench had to send, if any
        self.reader = threading.Thread(target=self._read, name="sic-stdout", daemon=True)
        self.reader.start()

    def _read(self) -> None:
        """Each stdout line that starts with ``{`` is a publication; a line longer than a
        publication may be is recorded as an invalid one (its start) and skipped to its end,
        so a runaway SIC cannot fill the bench's memory."""
        out = self.proc.stdout
        assert out is not None
        limit = MAX_PUBLICATION_BYTES + 1
        while line := out.readline(limit):
            self.stdout_log.write(line)
            too_long = len(line) == limit and not line.endswith(b"\n")
            while too_long and (rest := out.readline(limit)):  # the rest of that line
                self.stdout_log.write(rest)
                if rest.endswith(b"\n"):
                    break
            self.stdout_log.flush()
            s = line.strip()
            if s.startswith(b"{"):
                self.inbox.record(s, "stdout")
            elif s:
                self.inbox.non_json_lines += 1

    def poll(self) -> int | None:
        return self.proc.poll()

    def end(self, grace_s: float, stop: threading.Event | None = None) -> int:
        """Wait ``grace_s`` (or until ``stop``) for it to finish, then SIGTERM (its cue to
        publish and exit), then SIGKILL; then whatever is left of its process group."""
        deadline = time.monotonic() + grace_s
        while self.proc.poll() is None:
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                self._terminate()
                break
            time.sleep(0.05)
        self._end_group()
        return self.proc.wait()

    def _terminate(self) -> None:
        for sig, wait in ((signal.SIGTERM, 15.0), (signal.SIGKILL, 5.0)):
            self.signalled = sig.name
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)
            try:
                self.proc.wait(wait)
                return
            except subprocess.TimeoutExpired:
                continue

    def _end_group(self) -> None:
        """Children the SIC left behind (a wrapper script's, a shell's) go too."""
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(self.proc.pid, sig)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.2)

    def close(self) -> None:
        self.end(0.0)
        self.reader.join(timeout=5.0)
        self.stdout_log.close()
        self.stderr_log.close()


def _versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": sys.version.split()[0]}
    for pkg in ("tcf-hil", "numpy", "scipy", "python-can", "canopen", "embreex", "trimesh"):
        with contextlib.suppress(PackageNotFoundError):
            out[pkg] = version(pkg)
    return out


def run_bridge(scn: Scenario, sic: str, out: Path, *, mode: str = "2048x10",
               profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
               speed: float = 1.0, can: str = "own", shell: bool = False,
               sensor_ip: str | None = None, lead_s: float = 3.0, grace_s: float = 30.0,
               duration_s: float | None = None, backend: str = "embree",
               eval_cfg: EvalConfig | None = None, stop: threading.Event | None = None,
               announce: Callable[[str], None] = lambda s: None,
               progress: Callable[[int, int], None] | None = None,
               ready_s: float = 15.0, record_lidar: bool = True,
               on_start: Callable[[dict[str, Any]], None] | None = None) -> RunResult:
    """One live run into ``out`` (see the module docstring). ``stop`` ends it early (Ctrl-C):
    everything is closed, and the forest published so far is scored. ``record_lidar``: keep
    lidar.pcap and sensor_poses.csv (off for long runs: 2048x10 sends 16 MB/s).
    ``on_start`` gets the manifest once the clock runs (the SIC's pid is in it).

    The run owns its endpoints (:mod:`tcf_hil.endpoints`): a sensor address of its own
    (``sensor_ip`` None: 127.0.0.N claimed, its HTTP API on port 80 there), free UDP ports
    (7502/7503 unless taken) and, with ``can="own"``, a CAN bus of its own. On a joined bus
    (``can`` a spec) a second node with the harvester's id stops the run ("can-conflict")."""
    stop = stop or threading.Event()
    if lead_s * speed * 1e9 >= RUN_T0_NS:
        raise ValueError(f"lead {lead_s} s at speed {speed} reaches before simulation time 0")
    out = ensure_dir(out)
    ensure_dir(out / "sic")
    started = _dt.datetime.now(_dt.UTC)
    t_mono0 = time.monotonic()
    claims = contextlib.ExitStack()
    try:
        host, ports = claim_run_endpoints(claims, sensor_ip, (7502, 7503), announce)
        return _run_bridge(scn, sic, out, host, ports, mode=mode, profile=profile, seed=seed,
                           speed=speed, can=can, shell=shell, lead_s=lead_s, grace_s=grace_s,
                           duration_s=duration_s, backend=backend, eval_cfg=eval_cfg,
                           stop=stop, announce=announce, progress=progress, ready_s=ready_s,
                           record_lidar=record_lidar, on_start=on_start, started=started,
                           t_mono0=t_mono0)
    finally:
        claims.close()


def claim_run_endpoints(claims: contextlib.ExitStack, sensor_ip: str | None,
                        preferred: tuple[int, int], announce: Callable[[str], None]
                        ) -> tuple[SensorHost, UdpPorts]:
    """The run's sensor host (``sensor_ip`` given: that address, its API on a free port)
    and its lidar and IMU ports on 127.0.0.1, released by ``claims``."""
    if sensor_ip is None:
        host = claims.enter_context(claim_sensor_host(announce))
    else:
        host = SensorHost(sensor_ip, 0)
    ports = claims.enter_context(reserve_udp_ports("127.0.0.1", list(preferred)))
    return host, ports


def follow_redirects(route: Route, log: list[dict[str, Any]], t_mono0: float,
                     announce: Callable[[str], None]) -> Callable[[Any], None]:
    """The sensor API's ``on_redirect`` for a run: a client's set_config (on the HTTP
    thread) moves ``route``, is logged for the manifest and said. metadata.json stays as
    made: it describes lidar.pcap, recorded with the made ports."""

    def redirect(new: Any) -> None:
        route.set(new.udp_dest, new.udp_port_lidar, new.udp_port_imu)
        log.append({"udp_dest": new.udp_dest, "udp_port_lidar": new.udp_port_lidar,
                    "udp_port_imu": new.udp_port_imu,
                    "at_s": round(time.monotonic() - t_mono0, 3)})
        announce(f"sensor: a client moved the stream to {new.udp_dest}:"
                 f"{new.udp_port_lidar}/{new.udp_port_imu}")

    return redirect


def sensor_url(api: SensorApi) -> str:
    """The API's base URL (no port when it is 80, as for a real sensor)."""
    h, p = cast(tuple[str, int], api.address[:2])
    return f"http://{h}" if p == 80 else f"http://{h}:{p}"


def _run_bridge(scn: Scenario, sic: str, out: Path, host: SensorHost, ports: UdpPorts, *,
                mode: str, profile: str, seed: int | None, speed: float, can: str,
                shell: bool, lead_s: float, grace_s: float, duration_s: float | None,
                backend: str, eval_cfg: EvalConfig | None, stop: threading.Event,
                announce: Callable[[str], None], progress: Callable[[int, int], None] | None,
                ready_s: float, record_lidar: bool,
                on_start: Callable[[dict[str, Any]], None] | None, started: _dt.datetime,
                t_mono0: float) -> RunResult:
    from tcf_hil.lidar import LidarRun, stream_lidar

    sensor_ip = host.address
    lidar_port, imu_port = ports.ports
    announce(f"building {scn.name} ({mode}, {profile}) ...")
    # the track starts at simulation time 60 s: the harvester's lead before it never
    # reaches negative times (the CAN pose time is an unsigned 32-bit microsecond count)
    run = LidarRun(scn, mode=mode, profile=profile, seed=seed, backend=backend,
                   udp_dest="127.0.0.1", udp_port_lidar=lidar_port, udp_port_imu=imu_port,
                   t0_ns=RUN_T0_NS, keep_poses=record_lidar)
    if duration_s is not None:
        run.frames = max(1, min(run.frames, round(duration_s * run.meta.frequency_hz)))
    flog: FaultLog | None = None
    can_faults = None
    if faults_active(scn.faults):
        flog = FaultLog(out / "faults.jsonl", run.track.t0_ns)
        can_faults = fault_plans(scn.faults, run.forest.seed, run.track.t0_ns).can
    node_cfg = HarvesterModel.from_scenario(scn, run.forest.terrain, run.forest.seed,
                                            RUN_T0_NS).node_config()
    write_bytes_atomic(out / "metadata.json", run.meta.dumps().encode())
    manifest: dict[str, Any] = {
        "tcf_hil_run": 1, "status": "running", "versions": _versions(),
        "scenario": scn.name, "seed": run.forest.seed, "mode": mode, "profile": profile,
        "speed": speed, "backend": backend, "lidar_pcap": record_lidar,
        "sic": {"command": sic, "shell": shell},
        "started": started.isoformat(), "stopped": None, "frames_planned": run.frames,
        # what the harvester node answers by SDO (replay serves the same)
        "can_node": {"node_id": node_cfg.node_id, "datum_mm": list(node_cfg.datum_mm),
                     "mount_mm": list(node_cfg.mount_mm),
                     "mount_cdeg": list(node_cfg.mount_cdeg)},
    }
    if flog is not None:
        manifest["faults"] = {"config": scenario_to_dict(scn)["faults"], "log": "faults.jsonl"}
    inbox = Inbox(out / "sic", t_mono0)
    server = PublishServer(inbox).start()
    watcher: FileWatcher | None = None
    sic_proc: _SicProcess | None = None
    status, message = "complete", ""
    rc: int | None = None
    lidar_result: Any = None
    lidar_error: list[BaseException] = []
    harv_result: list[Any] = []
    end_stream = threading.Event()
    harv_stop = threading.Event()
    forked = threading.Event()
    threads: list[threading.Thread] = []
    late_ref: list[_LateClock] = []
    conflict: list[str] = []
    route = Route(run.meta.udp_dest, lidar_port, imu_port)
    redirects: list[dict[str, Any]] = []

    redirect = follow_redirects(route, redirects, t_mono0, announce)
    try:
        with open_bus(can, announce=announce) as spec, SensorApi(
                run.meta, sensor_ip, host.http_port, fixed=True, on_redirect=redirect) as api:
            env = _environment(out, run.meta, spec, api, server.url, sensor_ip,
                               scn.harvester.node_id)
            manifest["endpoints"] = {k: v for k, v in env.items() if k.startswith("TCF_")}
            argv = sic_command(sic, env, shell)
            t0 = run.track.t0_ns
            lead_ns = round(lead_s * 1e9)  # wall time before the first lidar packet is due
            late = _LateClock(speed)  # set once the SIC listens (the sender waits for it)
            late_ref.append(late)
            seconds = run.frames / run.meta.frequency_hz + 1.0
            harv_clock: list[SimClock] = []

            def harvester() -> None:
                harv_result.append(run_harvester(
                    scn, run.forest.terrain, spec, seed=run.forest.seed, log_path=out / "can.log",
                    speed=speed, stop=harv_stop, clock=harv_clock[0], t0_ns=t0,
                    duration_s=lead_s * speed + seconds, faults=can_faults,
                    on_fault=flog.log if flog is not None else None,
                    on_conflict=conflict.append))

            def on_lidar_fault(ev: dict[str, Any]) -> None:
                assert flog is not None
                flog.log(ev)
                if ev["kind"] == "lidar_reinit":  # the sensor serves its new identity
                    api.update(lambda m: m.with_changes(init_id=ev["init_id"]))
                    # the file describes lidar.pcap: the stream's own metadata (made ports;
                    # the sender set the new init_id before this call)
                    write_bytes_atomic(out / "metadata.json", run.meta.dumps().encode())

            def lidar() -> None:
                nonlocal lidar_result
                try:
                    lidar_result = stream_lidar(
                        scn, sensor_ip=sensor_ip, record=out, run=run, stop=end_stream,
                        clock=late, progress=progress, pcap_in_place=True, forked=forked,
                        on_fault=on_lidar_fault if flog is not None else None,
                        pcap=record_lidar, route=route)
                except BaseException as err:
                    lidar_error.append(err)
                finally:
                    forked.set()

            # the frame producer forks first, before the threads and the child below exist
            th_l = threading.Thread(target=lidar, name="lidar", daemon=True)
            th_l.start()
            threads.append(th_l)
            forked.wait(60.0)
            watcher = FileWatcher(inbox, Path(env["TCF_PUBLISH_FILE"]))
            watcher.start()
            announce(f"SIC: {argv if isinstance(argv, str) else shlex.join(argv)}")
            try:
                sic_proc = _SicProcess(argv, env, out, inbox, shell)
                manifest["sic"]["pid"] = sic_proc.proc.pid
            except OSError as err:
                status, message = "sic-failed", f"cannot start the SIC: {err}"
                end_stream.set()
            if sic_proc is not None and ready_s > 0:
                # the clock starts once the SIC listens on the lidar port (or after ready_s):
                # a slow start-up must not cost it the first frames
                proc = sic_proc
                if not wait_for_listener(route.dest_ip, lambda: route.port(lidar_port),
                                         ready_s, lambda: proc.poll() is None, stop):
                    if proc.poll() is None and not stop.is_set():
                        announce(f"the SIC does not listen on UDP {route.port(lidar_port)} "
                                 f"after {ready_s:g} s; starting anyway")
            clock = SimClock.start(t0, speed, lead_ns=lead_ns)
            late.set(clock)
            # the harvester's view of the same clock starts now, lead_ns * speed before t0
            harv_clock.append(SimClock(t0 - round(lead_ns * speed),
                                       clock.origin_monotonic_ns - lead_ns, speed))
            unix_at_t0 = time.time_ns() + (clock.origin_monotonic_ns - time.monotonic_ns())
            manifest["clock"] = {"sim_t0_ns": t0, "unix_ns_at_sim_t0": unix_at_t0,
                                 "speed": speed, "lead_s": lead_s}
            write_json_atomic(out / "manifest.json", manifest)  # replayable from here on
            if on_start is not None:
                on_start(manifest)
            th_h = threading.Thread(target=harvester, name="harvester", daemon=True)
            th_h.start()
            threads.append(th_h)
            announce(f"run: sensor {sensor_ip} (API {env['TCF_SENSOR_URL']}), lidar to "
                     f"{route.dest_ip}:{route.port(lidar_port)}, CAN {spec}; "
                     f"{run.frames} frames")
            while th_l.is_alive() and sic_proc is not None:
                th_l.join(0.2)
                if stop.is_set():
                    status, message = "interrupted", "stopped by the user"
                    break
                if conflict:  # the SIC would get two machines' poses: nothing to score
                    status, message = "can-conflict", conflict[0]
                    break
                if sic_proc.poll() is not None:
                    rc = sic_proc.poll()
                    status = "sic-exited"
                    message = (f"the SIC exited with code {rc} before the stream ended "
                               f"(see {out / 'sic' / 'stderr.log'})")
                    break
            end_stream.set()
            th_l.join()
            if lidar_error:
                raise lidar_error[0]
            if conflict and status == "complete":  # it came in the stream's last moments
                status, message = "can-conflict", conflict[0]
            if sic_proc is not None:
                if status == "complete":
                    announce("stream ended; waiting for the SIC's final forest ...")
                rc = sic_proc.end(grace_s if status == "complete" else 0.0, stop)
                if stop.is_set() and status == "complete":
                    status, message = "interrupted", "stopped by the user"
    except BaseException as err:
        status = "interrupted" if isinstance(err, KeyboardInterrupt) else "failed"
        message = message or f"{type(err).__name__}: {err}"
        if status == "failed":
            raise
    finally:
        end_stream.set()
        harv_stop.set()
        if not late_ref or not late_ref[0].is_set():  # a sender still waiting goes on
            for lc in late_ref:
                lc.set(SimClock.start(0, speed))
        for th in threads:
            th.join(timeout=60.0)
        if sic_proc is not None:
            sic_proc.close()
            rc = sic_proc.proc.returncode
        if watcher is not None:
            watcher.close()
        server.close()
        inbox.close()
        if flog is not None:
            flog.close()
            manifest["faults"]["injected"] = flog.summary()
        if conflict and status == "complete":  # it came while the SIC finished
            status, message = "can-conflict", conflict[0]
        if redirects:
            manifest["sensor_redirects"] = redirects
        if lidar_result is not None:
            manifest["lidar"] = {"frames_sent": lidar_result.frames,
                                 "packets_sent": lidar_result.packets,
                                 "pacing_us_p50_p99": list(lidar_result.pacing_us),
                                 "sender_cpu_share": lidar_result.sender_cpu_share,
                                 "refused": lidar_result.refused}
        if harv_result:
            h = harv_result[0]
            manifest["can"] = {"bus": h.spec, "node_id": h.node_id, "frames_logged": h.log_frames,
                               "log_error": h.log_error, "conflict": h.conflict}
        write_end_manifest(out, manifest, status, message, rc, sic_proc, inbox)
    status, message = conclude(status, message, rc, sic_proc, grace_s, inbox, out)
    return finish_run(out, manifest, inbox, status, message, rc, eval_cfg)


def write_end_manifest(out: Path, manifest: dict[str, Any], status: str, message: str,
                       rc: int | None, proc: _SicProcess | None, inbox: Inbox) -> None:
    """The manifest as the run ended: status, the SIC's exit, the publications."""
    manifest.update(status=status, message=message,
                    stopped=_dt.datetime.now(_dt.UTC).isoformat())
    manifest["sic"]["returncode"] = rc
    manifest["sic"]["ended_by"] = proc.signalled if proc is not None else None
    manifest["publications"] = {"total": len(inbox.items), "valid": len(inbox.valid),
                                "invalid": len(inbox.invalid),
                                "non_json_stdout_lines": inbox.non_json_lines}
    write_json_atomic(out / "manifest.json", manifest)


def conclude(status: str, message: str, rc: int | None, proc: _SicProcess | None,
             grace_s: float, inbox: Inbox, out: Path) -> tuple[str, str]:
    """The run's final status and message from how the SIC ended and what it published."""
    ended_by = proc.signalled if proc is not None else None
    if status == "complete" and ended_by:
        message = (f"the SIC did not exit within {grace_s:g} s after the stream; ended with "
                   f"{ended_by}")
    elif status == "complete" and rc not in (0, None):
        status = "sic-failed"
        message = f"the SIC exited with code {rc} (see {out / 'sic' / 'stderr.log'})"
    if not inbox.valid:
        message = (message + "; " if message else "") + (
            f"no valid forest published ({len(inbox.invalid)} invalid, "
            f"{inbox.non_json_lines} non-JSON stdout lines; see {out / 'sic'})")
    return status, message


def _environment(out: Path, meta: Any, spec: BusSpec, api: SensorApi, publish_url: str,
                 sensor_ip: str, node_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update({
        "TCF_RUN_DIR": str(out.resolve()),
        "TCF_METADATA": str((out / "metadata.json").resolve()),
        "TCF_SENSOR_URL": sensor_url(api),
        "TCF_SENSOR_HOST": sensor_ip,
        "TCF_LIDAR_BIND": meta.udp_dest,
        "TCF_LIDAR_PORT": str(meta.udp_port_lidar),
        "TCF_IMU_PORT": str(meta.udp_port_imu),
        "TCF_CAN_SPEC": str(spec),
        "TCF_CAN_INTERFACE": spec.interface,
        "TCF_CAN_CHANNEL": spec.channel,
        "TCF_CAN_HOST": spec.host,
        "TCF_CAN_PORT": str(spec.port or ""),
        "TCF_CAN_NODE_ID": str(node_id),
        "TCF_EDS": str(eds_path()),
        "TCF_PUBLISH_URL": publish_url,
        "TCF_PUBLISH_FILE": str((out / "sic" / "published.json").resolve()),
        "PYTHONUNBUFFERED": "1",
    })
    # the SIC's own --publish default is stdout; tcf-hil's reference SIC reads TCF_PUBLISH
    env.setdefault("TCF_PUBLISH", "stdout")
    return env


def finish_run(out: Path, manifest: dict[str, Any], inbox: Inbox, status: str, message: str,
               rc: int | None, eval_cfg: EvalConfig | None = None) -> RunResult:
    """Score the latest valid forest (and every valid publication, as a timeline) against
    the run's ground truth; write score.json and report.html."""
    from tcf_hil.report import write_report

    gt_doc = read_json(out / "ground_truth.json") if (out / "ground_truth.json").exists() \
        and status != "can-conflict" else None  # poses mixed with another node's: no score
    scores: Scores | None = None
    timeline: list[dict[str, Any]] = []
    valid = inbox.valid
    if gt_doc is not None:
        latest = inbox.table_of(valid[-1]) if valid else empty_forest()
        scores = score_forest(gt_doc, latest, eval_cfg)
        for p in valid:
            s = score_forest(gt_doc, inbox.table_of(p), eval_cfg)
            timeline.append({"n": p.n, "arrival_s": round(p.arrival_s, 3), "objects": p.objects,
                             "wc_all": s.all.metrics["evaluation_score_percent"],
                             "wc_seen": s.seen.metrics["evaluation_score_percent"],
                             "f1_all": s.all.metrics["f1"], "f1_seen": s.seen.metrics["f1"]})
    score_doc: dict[str, Any] = {
        "status": status, "message": message, "sic_returncode": rc,
        "scored_publication": valid[-1].n if valid else None,
        "publications": len(inbox.items), "invalid_publications": [
            {"n": p.n, "file": f"sic/{p.file}", "error": p.error} for p in inbox.invalid],
        "timeline": timeline,
    }
    if scores is not None:
        score_doc.update(scores.summary())
    if "faults" in manifest:  # the score next to what was done to the SIC
        score_doc["faults"] = manifest["faults"].get("injected", {})
    write_json_atomic(out / "score.json", score_doc)
    result = RunResult(out, status, message, scores, manifest, rc, len(inbox.items),
                       len(inbox.invalid), timeline)
    if scores is not None:
        write_report(out / "report.html", result)
    return result


def sic_reference_command(preset: str = "tuned") -> str:
    """The reference SIC as an external program."""
    return f"{{python}} -m tcf_hil.sic --preset {preset}"
