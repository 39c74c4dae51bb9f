"""One run session, whatever the traffic: the endpoints it owns, the CAN bus and the sensor's
HTTP API, the SIC under test as its own process, the recorder, the manifest, the score and
the report. ``run`` (live emulators), ``run --replay`` and ``replay`` (a recording) and
``soak`` all drive this one session; what differs is the :class:`Traffic` put on the wire.

Order of events: the endpoints are claimed and the traffic is made ready with them (a live
run builds its scene: seconds for a hectare), the bus and the API open, the traffic is
prepared (a live sensor forks its frame producer), the SIC is launched, the traffic starts
once the SIC listens on the lidar port (or after ``ready_s``), and the session watches it
until the traffic ends, the SIC exits, a second harvester shows up on a joined bus, or the
user stops it. Then the SIC gets ``grace_s`` to publish its final forest and exit, and the
latest valid forest is scored.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from emulators.harvester import BusSpec
from emulators.lidar import Route, SensorApi
from protocols.ouster import SensorMetadata
from tcf_hil._io import ensure_dir, read_json, write_json_atomic
from tcf_hil.devices.endpoints import SensorHost, UdpPorts, claim_sensor_host, reserve_udp_ports
from tcf_hil.devices.harvester import open_bus
from tcf_hil.evaluation import EvalConfig
from tcf_hil.evaluation.scoring import ScoredForest, Scores, empty_forest, score_forest
from tcf_hil.run._figures import LiveFigures, LiveScore
from tcf_hil.run._manifest import Manifest, RunStatus, SicRecord
from tcf_hil.run._sic import SicProcess, describe, sic_command, sic_environment
from tcf_hil.run.recorder import FileWatcher, Inbox, PublishServer

Announce = Callable[[str], None]


def quiet(_s: str) -> None:
    pass


@dataclass
class Wire:
    """What a session has opened for its traffic."""

    host: SensorHost
    spec: BusSpec
    api: SensorApi | None
    route: Route  # where the sensor's datagrams go now (a client may move them)
    stop: threading.Event  # the user's stop
    announce: Announce
    t_mono0: float


class Traffic(Protocol):
    """What a session puts on the wire (a live sensor and harvester, or a recording)."""

    noun: str  # "stream", "replay": said in messages
    node_id: int  # the harvester's CANopen node id

    def preferred_ports(self) -> tuple[int, int]:
        """The lidar and IMU ports it would use (a run takes free ones if these are taken)."""

    def bind(self, out: Path | None, host: SensorHost, ports: tuple[int, int]
             ) -> tuple[SensorMetadata, Path | None]:
        """Made ready for these endpoints: the metadata the API serves and the file the SIC
        reads it from (``TCF_METADATA``)."""

    def manifest(self, sic: SicRecord | None) -> Manifest:
        """The run's manifest as it starts."""

    def prepare(self, wire: Wire) -> None:
        """Before the SIC starts."""

    def start(self, wire: Wire, manifest: Manifest) -> None:
        """Once the SIC is ready: the traffic flows (it may block until ``wire.stop``)."""

    def alive(self, timeout_s: float) -> bool:
        """Whether it still flows, after waiting up to ``timeout_s`` for it to end."""

    def conflict(self) -> str | None:
        """Why the run cannot be scored (a second harvester node on a joined bus)."""

    def finish(self) -> None:
        """Stop sending and wait for it; raises what the sender raised."""

    def release_bus(self) -> None:
        """Stop everything that uses the CAN bus (the run's own CAN server closes next: a
        node or a log still on it would fail with a broken pipe). Safe after any failure."""

    def close(self, manifest: Manifest) -> None:
        """Release everything; its figures go into ``manifest``. Safe after any failure."""

    def describe(self, wire: Wire) -> str:
        """One line for the person: what is sent where."""

    def truth(self) -> dict[str, Any] | None:
        """The ground truth a live score is computed against (None: no live score)."""

    def figures(self, fig: LiveFigures) -> None:
        """Its figures so far into ``fig`` (called from another thread, often)."""


@dataclass
class RunResult:
    out: Path | None
    status: RunStatus
    message: str
    scores: Scores | None
    manifest: Manifest
    sic_returncode: int | None
    publications: int
    invalid_publications: int
    timeline: list[dict[str, Any]] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        """The run completed and the SIC published a valid forest that was scored."""
        return (self.status == RunStatus.COMPLETE and self.scores is not None
                and self.publications > self.invalid_publications)


def udp_port_taken(host: str, port: int) -> bool:
    """Whether someone has bound ``host:port`` (UDP), e.g. the SIC listening for lidar."""
    import socket

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


def follow_redirects(route: Route, log: list[dict[str, Any]], t_mono0: float,
                     announce: Announce) -> Callable[[Any], None]:
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


class _Live:
    """The run's :class:`LiveFigures` for ``watch``, from a thread of its own; the live
    score of the latest publication from a helper process (with a SIC and a truth)."""

    def __init__(self, watch: Callable[[LiveFigures], None] | None, traffic: Traffic,
                 inbox: Inbox | None, out: Path | None) -> None:
        self.watch, self.traffic, self.inbox, self.out = watch, traffic, inbox, out
        self.fig = LiveFigures()
        self.score: LiveScore | None = None
        self.end = threading.Event()
        self.thread: threading.Thread | None = None

    def start(self, scored: bool, cfg: EvalConfig | None) -> None:
        if self.watch is None:
            return
        try:  # a display never fails a run: without it the run goes on unwatched
            if scored and self.inbox is not None:
                truth = self.traffic.truth()
                if truth is not None:
                    self.score = LiveScore(truth, cfg)
            self.thread = threading.Thread(target=self._run, name="live figures", daemon=True)
            self.thread.start()
        except Exception:
            self.thread = None
            self.close()

    def phase(self, what: str) -> None:
        self.fig.phase = what

    def show(self, offer: bool = True) -> None:
        if self.watch is None:
            return
        fig, inbox = self.fig, self.inbox
        fig.run_dir = self.out
        self.traffic.figures(fig)
        if inbox is not None:
            items = list(inbox.items)  # one snapshot: the server thread appends
            valid = [p for p in items if p.valid]
            fig.publications, fig.invalid = len(items), len(items) - len(valid)
            fig.latest_publication = valid[-1].n if valid else None
            if self.score is not None:
                if valid and offer:
                    assert self.out is not None
                    self.score.offer(valid[-1].n, self.out / "sic" / valid[-1].file)
                self.score.fill(fig)
        self.watch(fig)

    def _run(self) -> None:
        while not self.end.wait(0.25):
            with contextlib.suppress(Exception):  # a display never stops a run
                self.show()

    def close(self) -> None:
        """The last figures (no new score asked: the run's own follows), and the helper
        stopped. Never raises."""
        if self.thread is not None:
            self.end.set()
            self.thread.join(timeout=5.0)
            self.thread = None
            with contextlib.suppress(Exception):
                self.show(offer=False)
        if self.score is not None:
            with contextlib.suppress(Exception):
                self.score.close()
            self.score = None


@dataclass
class _RunState:
    """What a run's phases hand on (:meth:`RunSession._run`)."""

    manifest: Manifest
    route: Route
    status: RunStatus = RunStatus.COMPLETE
    message: str = ""
    rc: int | None = None
    inbox: Inbox | None = None
    server: PublishServer | None = None
    watcher: FileWatcher | None = None
    proc: SicProcess | None = None
    live: _Live = field(default=None)  # type: ignore[assignment]  # set first thing
    redirects: list[dict[str, Any]] = field(default_factory=list)


class RunSession:
    """One run of ``traffic`` into ``out`` with the program ``sic`` under test.

    ``sic`` None: the traffic alone (``tcf-hil replay``): no recorder, no score, and with
    ``out`` None no files. ``sensor_ip`` None: a sensor address of its own (127.0.0.N,
    its HTTP API on port 80 there, or a free port); given, that address with the API on
    ``http_port`` (0: a free one; None: no API). With a SIC the lidar and IMU ports are the
    run's own (the traffic's preferred ones unless taken); without, the traffic's. ``can``:
    ``own`` (a CAN server of the run's own) or a bus to join (see
    :func:`tcf_hil.devices.harvester.open_bus`). ``stop`` ends the run early (Ctrl-C): everything is
    closed and the forest published so far is scored. ``on_start`` gets the manifest once
    the traffic flows (the SIC's pid is in it). ``watch`` gets the run's
    :class:`LiveFigures` four times a second from a thread of its own while the run goes
    on, and once more at the end (with a SIC and a ground truth, the live score of its latest
    forest is computed in a helper process: see :mod:`tcf_hil.run._figures`).
    """

    def __init__(self, traffic: Traffic, sic: str | None, out: Path | None, *,
                 shell: bool = False, can: str = "own", sensor_ip: str | None = None,
                 http_port: int | None = 0, grace_s: float = 30.0, ready_s: float = 15.0,
                 stop: threading.Event | None = None, announce: Announce = quiet,
                 eval_cfg: EvalConfig | None = None,
                 on_start: Callable[[Manifest], None] | None = None,
                 watch: Callable[[LiveFigures], None] | None = None) -> None:
        self.traffic, self.sic, self.out, self.shell, self.can = traffic, sic, out, shell, can
        self.sensor_ip, self.http_port = sensor_ip, http_port
        self.grace_s, self.ready_s, self.eval_cfg = grace_s, ready_s, eval_cfg
        self.stop = stop or threading.Event()
        self.announce, self.on_start, self.watch = announce, on_start, watch
        self.t_mono0 = time.monotonic()

    # ------------------------------------------------------------------------- endpoints
    def _claim(self, claims: contextlib.ExitStack) -> tuple[SensorHost, tuple[int, int]]:
        if self.sensor_ip is None:
            host = claims.enter_context(claim_sensor_host(self.announce))
            if self.http_port:  # a port asked for on the claimed address
                host = dataclasses.replace(host, http_port=self.http_port)
        else:
            host = SensorHost(self.sensor_ip, -1 if self.http_port is None else self.http_port)
        preferred = self.traffic.preferred_ports()
        if self.sic is None:  # the traffic alone goes where it was meant to go
            return host, preferred
        ports: UdpPorts = claims.enter_context(reserve_udp_ports("127.0.0.1", list(preferred)))
        return host, (ports.ports[0], ports.ports[1])

    # ----------------------------------------------------------------------------- a run
    def run(self) -> RunResult:
        out = self.out
        if out is not None:
            ensure_dir(out)
            if self.sic is not None:
                ensure_dir(out / "sic")
        with contextlib.ExitStack() as claims:
            host, ports = self._claim(claims)
            meta, meta_path = self.traffic.bind(out, host, ports)
            sic = SicRecord(self.sic, self.shell) if self.sic is not None else None
            manifest = self.traffic.manifest(sic)
            return self._run(host, meta, meta_path, manifest)

    def _run(self, host: SensorHost, meta: SensorMetadata, meta_path: Path | None,
             manifest: Manifest) -> RunResult:
        """The run's phases: the recorder opened, the wire up (CAN bus, the sensor's HTTP
        API), the SIC started, the traffic streamed while it is watched, the SIC's final
        forest awaited; then everything closed, the manifest ended and the forest scored."""
        st = _RunState(manifest, Route(meta.udp_dest, meta.udp_port_lidar, meta.udp_port_imu))
        if self.sic is not None:
            assert self.out is not None, "a run with a SIC needs a run directory"
            st.inbox = Inbox(self.out / "sic", self.t_mono0)
            st.server = PublishServer(st.inbox).start()
        st.live = _Live(None, self.traffic, st.inbox, self.out)  # (no one watching: nothing)
        redirect = follow_redirects(st.route, st.redirects, self.t_mono0, self.announce)
        if self.stop.is_set():  # stopped while the traffic was bound (a render before the
            # track, say): no bus, no sensor, and no program started only to be stopped
            st.status, st.message = RunStatus.INTERRUPTED, "stopped by the user"
            self._close(st)
            return self._result(st, manifest)
        try:
            with open_bus(self.can, announce=self.announce) as spec, \
                    contextlib.ExitStack() as apis:
                api = apis.enter_context(SensorApi(
                    meta, host.address, host.http_port, fixed=True, on_redirect=redirect)) \
                    if host.http_port >= 0 else None
                wire = Wire(host, spec, api, st.route, self.stop, self.announce, self.t_mono0)
                try:
                    self._start(st, wire, meta, meta_path)
                    self._stream(st)
                    self._finish(st)
                finally:  # before the bus (the run's own CAN server) closes
                    self.traffic.release_bus()
        except BaseException as err:
            st.status = RunStatus.INTERRUPTED if isinstance(err, KeyboardInterrupt) \
                else RunStatus.FAILED
            st.message = st.message or f"{type(err).__name__}: {err}"
            if st.status == RunStatus.FAILED:
                raise
        finally:
            self._close(st)
        return self._result(st, manifest)

    def _result(self, st: _RunState, manifest: Manifest) -> RunResult:
        if st.inbox is None:
            return RunResult(self.out, st.status, st.message, None, manifest, None, 0, 0)
        assert self.out is not None
        return self._score(self.out, manifest, st.inbox, st.rc)

    def _start(self, st: _RunState, wire: Wire, meta: SensorMetadata,
               meta_path: Path | None) -> None:
        """The traffic prepared, the live display started, the SIC started (the traffic
        waits until it listens on the lidar port, or ``ready_s``), then the traffic."""
        out, traffic, manifest = self.out, self.traffic, st.manifest
        argv: list[str] | str = []
        env: dict[str, str] = {}
        if self.sic is not None:
            assert out is not None and wire.api is not None and st.server is not None \
                and st.inbox is not None and meta_path is not None
            env = sic_environment(out, meta, meta_path, wire.spec, wire.api, st.server.url,
                                  traffic.node_id)
            manifest.endpoints = {k: v for k, v in env.items() if k.startswith("TCF_")}
            argv = sic_command(self.sic, env, self.shell)
        traffic.prepare(wire)
        if self.watch is not None:  # after the frame producer's fork (no threads)
            st.live = _Live(self.watch, traffic, st.inbox, out)
            st.live.start(self.sic is not None, self.eval_cfg)
        if self.sic is not None:
            self._start_sic(st, argv, env, meta.udp_port_lidar)
        if self.sic is None or st.proc is not None:
            st.live.phase({"stream": "streaming", "replay": "replaying"}.get(
                traffic.noun, traffic.noun))
            traffic.start(wire, manifest)
            if out is not None:
                manifest.write(out)  # replayable from here on
            if self.on_start is not None:
                self.on_start(manifest)
            self.announce(traffic.describe(wire))

    def _start_sic(self, st: _RunState, argv: list[str] | str, env: dict[str, str],
                   lidar_port: int) -> None:
        assert st.inbox is not None and self.out is not None
        st.live.phase("starting the SIC")
        st.watcher = FileWatcher(st.inbox, Path(env["TCF_PUBLISH_FILE"]))
        st.watcher.start()
        self.announce(f"SIC: {describe(argv)}")
        try:
            st.proc = SicProcess(argv, env, self.out, st.inbox, self.shell)
            assert st.manifest.sic is not None
            st.manifest.sic.pid = st.proc.pid
        except OSError as err:
            st.status, st.message = RunStatus.SIC_FAILED, f"cannot start the SIC: {err}"
        if st.proc is not None and self.ready_s > 0:
            # the traffic starts once the SIC listens on the lidar port (or after ready_s):
            # a slow start-up must not cost it the first frames
            p, route, stop = st.proc, st.route, self.stop
            if not wait_for_listener(route.dest_ip, lambda: route.port(lidar_port),
                                     self.ready_s, lambda: p.poll() is None, stop):
                if p.poll() is None and not stop.is_set():
                    self.announce(f"the SIC does not listen on UDP {route.port(lidar_port)} "
                                  f"after {self.ready_s:g} s; starting anyway")

    def _stream(self, st: _RunState) -> None:
        """Until the traffic ends, watching for a stop, a CAN conflict or the SIC's exit."""
        traffic, proc = self.traffic, st.proc
        while traffic.alive(0.2) and (proc is not None or self.sic is None):
            if self.stop.is_set():
                st.status, st.message = RunStatus.INTERRUPTED, "stopped by the user"
                break
            if c := traffic.conflict():  # the SIC would get two machines' poses
                st.status, st.message = RunStatus.CAN_CONFLICT, c
                break
            if proc is not None and (code := proc.poll()) is not None:
                st.rc, st.status = code, RunStatus.SIC_EXITED
                st.message = (f"the SIC exited with code {code} before the {traffic.noun} "
                              f"ended (see {proc.stderr_log.name})")
                break

    def _finish(self, st: _RunState) -> None:
        """The traffic finished, then the SIC's final forest awaited (``grace_s``)."""
        traffic, stop = self.traffic, self.stop
        traffic.finish()
        if (c := traffic.conflict()) and st.status == RunStatus.COMPLETE:
            st.status, st.message = RunStatus.CAN_CONFLICT, c  # in the last moments
        if stop.is_set() and st.status == RunStatus.COMPLETE:
            st.status, st.message = RunStatus.INTERRUPTED, "stopped by the user"
        if st.proc is not None:
            if st.status == RunStatus.COMPLETE:
                st.live.phase("waiting for the SIC's final forest")
                self.announce(f"{traffic.noun} ended; waiting for the SIC's final forest ...")
            st.rc = st.proc.end(self.grace_s if st.status == RunStatus.COMPLETE else 0.0, stop)
            if stop.is_set() and st.status == RunStatus.COMPLETE:
                st.status, st.message = RunStatus.INTERRUPTED, "stopped by the user"

    def _close(self, st: _RunState) -> None:
        """Everything closed (never raising past the run's own error), the status concluded
        from how the SIC ended, and the manifest ended and written."""
        manifest, inbox, proc = st.manifest, st.inbox, st.proc
        st.live.close()
        self.traffic.close(manifest)
        if proc is not None:
            proc.close()
            st.rc = proc.proc.returncode
        if st.watcher is not None:
            st.watcher.close()
        if st.server is not None:
            st.server.close()
        if inbox is not None:
            inbox.close()
        if (c := self.traffic.conflict()) and st.status == RunStatus.COMPLETE:
            st.status, st.message = RunStatus.CAN_CONFLICT, c  # it came while the SIC finished
        if inbox is not None and st.status != RunStatus.FAILED:
            assert self.out is not None
            st.status, st.message = self._conclude(st.status, st.message, st.rc, proc, inbox,
                                                   self.out)
        if st.redirects:
            manifest.sensor_redirects = st.redirects
        manifest.ended(st.status, st.message)
        if manifest.sic is not None:
            manifest.sic.returncode = st.rc
            manifest.sic.ended_by = proc.signalled if proc is not None else None
            manifest.sic.final_forest = proc.final_forest() if proc is not None else None
        if inbox is not None:
            manifest.publications = {"total": len(inbox.items), "valid": len(inbox.valid),
                                     "invalid": len(inbox.invalid),
                                     "non_json_stdout_lines": inbox.non_json_lines}
        if self.out is not None:
            manifest.write(self.out)

    # ---------------------------------------------------------------------------- the end
    def _conclude(self, status: RunStatus, message: str, rc: int | None,
                  proc: SicProcess | None, inbox: Inbox, out: Path) -> tuple[RunStatus, str]:
        """The run's final status and message from how the SIC ended and what it published."""
        ended_by = proc.signalled if proc is not None else None
        if status == RunStatus.COMPLETE and ended_by:
            message = (f"the SIC did not exit within {self.grace_s:g} s after the "
                       f"{self.traffic.noun}; ended with {ended_by}")
            if proc is not None and inbox.valid and proc.final_forest() is False:
                message += (" before it published its final forest (its latest forest is "
                            "scored; a longer --grace gives it time)")
        elif status == RunStatus.COMPLETE and rc not in (0, None):
            status = RunStatus.SIC_FAILED
            message = f"the SIC exited with code {rc} (see {out / 'sic' / 'stderr.log'})"
        if proc is None and status == RunStatus.INTERRUPTED:
            message += " before the SIC started"
        elif not inbox.valid:
            message = (message + "; " if message else "") + (
                f"no valid forest published ({len(inbox.invalid)} invalid, "
                f"{inbox.non_json_lines} non-JSON stdout lines; see {out / 'sic'})")
        return status, message

    def _score(self, out: Path, manifest: Manifest, inbox: Inbox, rc: int | None
               ) -> RunResult:
        """Score the latest valid forest (and every valid publication, as a timeline)
        against the run's ground truth; write score.json and report.html."""
        from tcf_hil.results.report import write_report

        status, message, cfg = manifest.status, manifest.message or "", self.eval_cfg
        gt_doc = None
        if status != RunStatus.CAN_CONFLICT:  # (mixed poses: no score)
            if (out / "ground_truth.json").exists():
                gt_doc = read_json(out / "ground_truth.json")
            elif (out / "inventory.csv").exists():  # a field recording's
                from tcf_hil.recording.inventory import read_inventory

                gt_doc = read_inventory(out / "inventory.csv")
        scores: Scores | None = None
        timeline: list[dict[str, Any]] = []
        valid = inbox.valid
        if gt_doc is not None:
            latest = inbox.table_of(valid[-1]) if valid else empty_forest()
            scores = score_forest(gt_doc, latest, cfg)
            for p in valid:
                s = scores if p is valid[-1] else score_forest(gt_doc, inbox.table_of(p), cfg)
                timeline.append({"n": p.n, "arrival_s": round(p.arrival_s, 3),
                                 "objects": p.objects,
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
        track = None
        if scores is not None:
            from tcf_hil.results.export import track_xy

            track = track_xy(out)  # read once: the bands here, the report's map
            score_doc.update(scores.summary())
            score_doc["by_distance"] = _bands(scores, latest, track)
        if manifest.faults is not None:  # the score next to what was done to the SIC
            score_doc["faults"] = manifest.faults.get("injected", {})
        write_json_atomic(out / "score.json", score_doc)
        result = RunResult(out, status, message, scores, manifest, rc, len(inbox.items),
                           len(inbox.invalid), timeline)
        if scores is not None and gt_doc is not None:  # the report takes it as scored here
            latest_doc = inbox.doc_of(valid[-1]) if valid else {"objects": []}
            write_report(out / "report.html", out, manifest.to_dict(), scored=ScoredForest(
                scores, latest, latest_doc, gt_doc, cfg or EvalConfig(), track))
        return result


def _bands(scores: Scores, latest: Any, track: Any) -> dict[str, Any] | None:
    """score.json's ``by_distance``: the scoring of all trees per band of distance from the
    recorded track (``track``: :func:`tcf_hil.results.export.track_xy`; none where the run
    has no sensor_poses.csv)."""
    from tcf_hil.evaluation.scoring import by_distance
    from tcf_hil.world.track import distance_to_track

    if not len(track):
        return None
    gt = scores.gt_all
    return {"bands": by_distance(scores.all, gt, latest,
                                 distance_to_track(gt.xyz[:, :2], track),
                                 distance_to_track(latest.xyz[:, :2], track)),
            "note": "horizontal distance from the sensor's track; each stem in its own band"}
