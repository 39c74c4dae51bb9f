"""``demo``, ``run``, ``replay``, ``soak`` and ``sic``: runs of a program under test, all
driving one :class:`tcf_hil.run.RunSession`."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from tcf_hil.cli._shared import (
    ExitStatus,
    LiveRun,
    announce_backend,
    console,
    err_console,
    fault_option,
    finish,
    graceful_stop,
    mode_option,
    preset_option,
    profile_option,
    run_dir,
    run_dir_option,
    scenario_with_faults,
    seed_option,
    sensor_option,
)

_STOP_RUN = "stopping the run: closing the recording and scoring what was published"


def _recording_options(f: Any) -> Any:
    """--meta, --can-log and --can-offset: what goes with a field recording's pcap."""
    f = click.option("--can-offset", type=float, default=0.0, show_default=True,
                     help="Seconds added to the CAN log's time stamps (where its clock and "
                          "the pcap's differ).")(f)
    f = click.option("--can-log", type=click.Path(dir_okay=False, exists=True,
                                                  path_type=Path), default=None,
                     help="A CAN log to put on the bus with a pcap: candump .log, .asc, "
                          ".blf or .trc (read by python-can).")(f)
    return click.option("--meta", type=click.Path(dir_okay=False, exists=True,
                                                  path_type=Path), default=None,
                        help="The pcap's metadata JSON [default: the .json beside it that "
                             "shares the longest prefix with its name, as ouster-cli "
                             "finds it].")(f)


def _session(start: Any, out: Path, what: str = "building the scene",
             keep: list[Any] | None = None) -> int:
    """Drive a run session (``start(stop, announce, live)`` returns its result; ``live``:
    the :class:`LiveRun` display) with the graceful stop (the partial recording is kept and
    scored); prints the score table. Returns the exit status (``keep``: gets the result)."""
    from tcf_hil._logs import library_logs
    from tcf_hil.run import RunStatus

    with graceful_stop(_STOP_RUN) as stop, library_logs(out / "bench.log"), \
            LiveRun(what) as live:
        r = start(stop, err_console.print, live)
    if keep is not None:
        keep.append(r)
    if r.status == RunStatus.CAN_CONFLICT:  # nothing was scored: its poses were not the run's
        click.echo(f"Error: {r.message}; nothing scored (run directory {r.out}/)", err=True)
        return ExitStatus.BAD_INPUT
    _print_run(r)
    if r.passed:
        return ExitStatus.OK
    return ExitStatus.INTERRUPTED if r.status == RunStatus.INTERRUPTED else ExitStatus.FAILED


def _print_run(r: Any) -> None:
    from tcf_hil.evaluation import ROWS, show_metric

    m = r.manifest
    if r.scores is not None:
        t = Table(title=f"{m.scenario} {m.mode}: the SIC's final forest", header_style="bold")
        t.add_column("metric")
        t.add_column("all trees", justify="right")
        t.add_column("seen trees", justify="right")
        a, b = r.scores.all.metrics, r.scores.seen.metrics
        for key, label, fmt in ROWS[:1] + ROWS[7:13] + ROWS[13:15]:
            t.add_row(label, show_metric(fmt, a[key]), show_metric(fmt, b[key]))
        t.add_row("Ground-truth trees", str(a["n_ground_truth"]), str(b["n_ground_truth"]))
        console.print(t)
    sent = (f"frames sent {(m.lidar or {}).get('frames_sent', 0)}" if m.replay_sent is None
            else f"replayed {m.replay_sent.get('udp', 0)} datagrams, "
                 f"{m.replay_sent.get('can', 0)} CAN frames")
    console.print(f"{sent}, publications {r.publications} "
                  f"({r.invalid_publications} invalid), SIC exit code {r.sic_returncode}")
    pacing = _pacing_line(m.lidar or {})
    if pacing:
        err_console.print(pacing)
    if r.message:
        err_console.print(f"[bold]{r.status}[/]: {r.message}")
    report = r.out / "report.html"
    console.print(f"run directory: {r.out}/" + (f"  report: {report}" if report.exists()
                                               else ""))


def _pacing_line(lidar: dict[str, Any]) -> str | None:
    """One line when track packets left 1 ms or more late: how many, and how much CPU time
    the hypervisor withheld meanwhile (a vCPU the host does not run sends nothing); where no
    frame came late from the producer, where to see the machine's own floor."""
    late = lidar.get("track_packets_late_1ms") or 0
    if not late:
        return None
    p99 = (lidar.get("track_pacing_us_p50_p99") or [0, 0])[1]
    line = (f"lidar: {late} track packet(s) left 1 ms or more late (pacing p99 "
            f"{p99:,.0f} us)")
    steal = lidar.get("track_steal_ms_per_s")
    producer = lidar.get("frames_late_from_producer") or 0
    if producer:
        line += f"; {producer} frame(s) came late from the frame producer"
    if steal is not None and steal >= 1.0:
        line += (f"; the hypervisor withheld {steal:.0f} ms/s of this machine's CPU "
                 "meanwhile (steal: a vCPU the host does not run sends nothing)")
    if not producer:  # the pacing's, then: what the machine allows any sender
        line += "; `tcf-hil lidar timing` shows what this machine allows any sender"
    return line


@click.command()
@run_dir_option()
@seed_option()
@preset_option()
@click.option("--compare/--no-compare", default=True, show_default=True,
              help="Then replay the recording to the paper's algorithm (--preset paper) and "
                   "print both scores side by side.")
def demo(out: Path | None, seed: int | None, preset: str, compare: bool) -> None:
    """The main job end to end, on loopback: Forest V at 1024x10.

    \b
    The emulated OS0-64 streams over UDP (with its HTTP API), the harvester publishes its
    pose as a CANopen node on the embedded CAN server, the reference onboard SIC
    (`python -m tcf_hil.sic`, the field-grade preset) runs as a separate program on that
    wire, and the recorder scores its forest. Then the same recording is replayed (at twice
    real time) to the paper's published algorithm (`--preset paper`) and both scores are
    printed side by side: what the bench is for. Writes ./runs/<UTC time stamp>/ (or --out):
    lidar.pcap, can.log, metadata.json, ground_truth.json, visibility.json, sic/,
    manifest.json, score.json, report.html, and the replay's run directory compare-paper/.
    About five minutes the first time (the first 20-odd seconds render the track ahead
    into the render store; a later demo of the same seed streams from it).
    """
    from tcf_hil.run import replay_run, run_bridge, sic_reference_command
    from tcf_hil.scenario import load_scenario

    scn, out = load_scenario("forest-v"), run_dir(out)
    announce_backend()
    results: list[Any] = []
    # the SIC's stem worker finishes the map's last tiles after the stream: seconds as a
    # rule, a minute on a machine busy with other work (a SIC that is done exits at once)
    code = _session(lambda stop, say, live: run_bridge(
        scn, sic_reference_command(preset), out, mode="1024x10", seed=seed, stop=stop,
        announce=say, watch=live.watch, grace_s=120.0), out, keep=results)
    if code == 0 and compare and preset != "paper":
        other = out / "compare-paper"
        err_console.print("the same recording, replayed to the paper's algorithm "
                          f"(--preset paper) at twice real time: {other}/")
        if _session(lambda stop, say, live: replay_run(
                out, sic_reference_command("paper"), other, speed=2.0, stop=stop,
                announce=say, watch=live.watch), other, "replaying", keep=results) == 0:
            _print_side_by_side(results[0], results[1], preset)
    finish(code)


def _print_side_by_side(a: Any, b: Any, preset: str) -> None:
    """The two presets' scores on the same recording, and per band of distance from the
    track (score.json's ``by_distance``)."""
    import json

    from tcf_hil.evaluation import ROWS, show_metric

    if a.scores is None or b.scores is None:
        return
    t = Table(title=f"{a.manifest.scenario} {a.manifest.mode}, the same recording: the "
                    f"reference SIC ({preset}) and the paper's algorithm", header_style="bold")
    t.add_column("all trees")
    t.add_column(preset, justify="right")
    t.add_column("paper", justify="right")
    ma, mb = a.scores.all.metrics, b.scores.all.metrics
    for key, label, fmt in ROWS[:1] + ROWS[7:9] + ROWS[11:13] + ROWS[14:15]:
        t.add_row(label, show_metric(fmt, ma[key]), show_metric(fmt, mb[key]))
    t.add_row("DBH bias", show_metric("{:+.4f} m", ma.get("dbh_bias_m")),
              show_metric("{:+.4f} m", mb.get("dbh_bias_m")))
    bands = [{x["from_m"]: x for x in (json.loads((r.out / "score.json").read_text(
        encoding="utf-8")).get("by_distance") or {}).get("bands", [])} for r in (a, b)]

    def cell(x: dict[str, Any] | None) -> str:
        if x is None:
            return "absent"
        return f"{x['found']}/{x['trees']}, {show_metric('{:.3f} m', x['dbh_rmse_m'])}"

    for lo in sorted(set(bands[0]) | set(bands[1])):
        ba = bands[0].get(lo) or bands[1][lo]
        if not ba["trees"] or ba["to_m"] is None or lo >= 15:
            continue
        t.add_row(f"{lo:g}-{ba['to_m']:g} m from the track: found, DBH RMSE",
                  cell(bands[0].get(lo)), cell(bands[1].get(lo)))
    console.print(t)


@click.command("run")
@click.argument("scenario_name", metavar="SCENARIO", required=False)
@click.option("--sic", "sic", default=None,
              help="The onboard program to test, e.g. \"./my_sic --port {lidar_port}\" "
                   "(default: the reference SIC). {placeholders} and TCF_* environment "
                   "variables carry the endpoints (see README).")
@click.option("--shell", is_flag=True, help="Run --sic through /bin/sh (default: no shell).")
@mode_option("2048x10")
@profile_option()
@seed_option()
@run_dir_option()
@click.option("--speed", type=click.FloatRange(min=0.05, max=20), default=1.0,
              show_default=True, help="Simulation seconds per second (1 = real time).")
@click.option("--duration", type=click.FloatRange(min=0.1), default=None,
              help="Stop the stream after this many simulated seconds (default: the track).")
@click.option("--can", "can_spec", default="own", show_default=True,
              help="CAN bus: own (a CAN server of the run's own on a free port: no other "
                   "bench or harvester can mix in), or join one on purpose: auto, "
                   "socketcan:IFACE, socketcand:HOST:PORT:CHANNEL. On a joined bus a second "
                   "node with the harvester's id stops the run (exit 1).")
@click.option("--grace", type=click.FloatRange(min=0), default=120.0, show_default=True,
              help="Seconds the SIC gets after the stream ends to publish its final forest "
                   "and exit; then SIGTERM (its cue to publish and exit), 15 s more, then "
                   "SIGKILL, each to its whole process group; the run says in one line when "
                   "it had to stop the SIC before its final forest, and the manifest keeps "
                   "sic.ended_by and sic.final_forest. A SIC that exits sooner ends the run "
                   "sooner. The reference SIC's stem worker needs up to a minute after a "
                   "natural stand at 1024x10, minutes at 2048x10 on one core.")
@click.option("--ready-timeout", "ready_s", type=click.FloatRange(min=0), default=15.0,
              show_default=True,
              help="The clock starts when the SIC listens on the lidar UDP port, or after "
                   "this many seconds (0: at once).")
@click.option("--replay", "replay_dir", type=click.Path(exists=True, path_type=Path),
              default=None, help="Send recorded traffic instead of the live emulators: a "
                                 "run directory, or an Ouster pcap (with --meta, --can-log).")
@click.option("--render", type=click.Choice(["auto", "stored", "ahead", "live"]),
              default="auto", show_default=True,
              help="Where the frames come from: auto streams the render store's frames "
                   "where tcf-hil render (or an earlier run) stored this run's (the bench "
                   "then only paces and copies), else renders ahead (below); stored renders "
                   "the whole track into the store first (with progress) and streams from "
                   "it; ahead renders into the store in a process of its own, below the "
                   "program's priority, while the run streams from it, after a lead "
                   "computed from its rate so that the track never waits for a frame (the "
                   "next run of the scene streams from the store at once); live always "
                   "renders as it goes, in the frame producer, a few frames ahead (for a "
                   "scene that changes during a run). The bytes are the same either way.")
@_recording_options
@click.option("--truth", type=click.Path(dir_okay=False, exists=True, path_type=Path),
              default=None, help="With --replay: the ground truth to score against, a "
                                 "ground_truth.json or a field inventory CSV (id,x,y[,z,dbh_m,"
                                 "height_m,class]) [default: the run directory's].")
@fault_option
@sensor_option
@click.option("--foxglove", "foxglove_port", type=click.IntRange(0, 65535), is_flag=False,
              flag_value=8765, default=None, metavar="[PORT]",
              help="Serve the run live to Foxglove (its WebSocket protocol, on 127.0.0.1, "
                   "port 8765 unless given; 0: a free one): the current frame's cloud "
                   "coloured by what it hit, the sensor's pose, the track, the ground-truth "
                   "stems and the SIC's latest, coloured by outcome, and the live score. "
                   "Open connection in Foxglove, ws://127.0.0.1:PORT; the layout is "
                   "tcf_hil/report_assets/foxglove-layout.json. (Before SCENARIO give the "
                   "port: --foxglove 8765 forest-v.)")
def run_cmd(scenario_name: str | None, sic: str | None, shell: bool, mode: str, profile: str,
            seed: int | None, out: Path | None, speed: float, duration: float | None,
            can_spec: str, grace: float, ready_s: float, replay_dir: Path | None,
            meta: Path | None, can_log: Path | None, can_offset: float, truth: Path | None,
            faults: tuple[str, ...], sensor: str | None, render: str,
            foxglove_port: int | None) -> None:
    """A hardware-in-the-loop run of an onboard SIC program against SCENARIO.

    \b
    Builds the forest, starts the harvester (CANopen on the CAN bus) and the OS0-64 (UDP and
    its HTTP API) on one simulation clock, launches --sic as its own process with the
    endpoints in its environment, records everything into the run directory, and scores
    the SIC's last published forest against all trees and against the trees the sensor saw.
    Exit status 0 when the run completed and the SIC published a valid forest, 1 when a
    second node with the harvester's id was on a joined CAN bus, 3 when the SIC failed
    (exited early or with an error, or published nothing valid), 130 when stopped by
    Ctrl-C/SIGTERM (the partial run is still recorded and scored).

    \b
    The run owns its endpoints: the sensor gets a loopback address of its own (127.0.0.2,
    ...; packets come from it, its HTTP API answers on port 80 there, so
    SensorFrameSetSource($TCF_SENSOR_HOST) works), the lidar and IMU ports are 7502/7503
    unless taken, and the CAN bus is the run's own unless --can joins one.

    \b
    On a terminal one line follows the run live: simulation time, frames sent and lost, CAN
    poses, the SIC's publications and the score of its latest forest.

    \b
    Faults (the scenario's [faults] section, or --fault KEY=VALUE) are injected on the wire
    and logged with their times in faults.jsonl; score.json and report.html show the score
    next to them, e.g.:
      tcf-hil run forest-v --duration 30 --fault udp.loss=0.01 --fault can.bus_off_at_s=[10]
    """
    from tcf_hil.run import check_sic_command, replay_run, run_bridge, sic_reference_command

    command = sic or sic_reference_command()
    try:
        check_sic_command(command, shell)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--sic") from err
    if replay_dir is None and (truth or meta or can_log):
        raise click.UsageError("--truth, --meta and --can-log go with --replay RECORDING")
    if replay_dir is not None and foxglove_port is not None:
        raise click.UsageError("--foxglove shows a live run (its world: the track and the "
                               "truth); a recording goes to Foxglove with tcf-hil export "
                               "RUN --out run.mcap")
    out = run_dir(out)
    if replay_dir is not None:
        src = replay_dir
        finish(_session(lambda stop, say, live: replay_run(
            src, command, out, speed=speed, shell=shell, can_spec=can_spec, grace_s=grace,
            ready_s=ready_s, stop=stop, announce=say, meta=meta, can_log=can_log,
            can_offset_s=can_offset, truth=truth, watch=live.watch,
            progress=lambda done, total: live.counter(done >> 20, total >> 20)), out,
            "checking the recording"))
        return
    if scenario_name is None:
        raise click.UsageError("give a SCENARIO (a preset name or TOML file) or --replay "
                               "RECORDING")
    scn = scenario_with_faults(scenario_name, faults, sensor=sensor)
    announce_backend()
    view = _foxglove_view(foxglove_port)

    def watch(live: Any) -> Any:
        """The terminal's line (None off a terminal) and the Foxglove view, each told
        separately (one that fails does not keep the figures from the other)."""
        fns = [fn for fn in (live.watch, view.watch if view is not None else None)
               if fn is not None]
        if len(fns) < 2:
            return fns[0] if fns else None

        def both(fig: Any) -> None:
            for fn in fns:
                with contextlib.suppress(Exception):  # a display never stops a run
                    fn(fig)
        return both

    try:
        finish(_session(lambda stop, say, live: run_bridge(
            scn, command, out, mode=mode, profile=profile, seed=seed, speed=speed,
            duration_s=duration, can=can_spec, shell=shell, grace_s=grace, ready_s=ready_s,
            stop=stop, announce=say, watch=watch(live), render=render), out))
    finally:
        if view is not None:
            view.close()
            if view.errors:
                err_console.print(f"Foxglove: the live view missed {view.errors} update(s); "
                                  f"the first: {view.first_error}")


def _foxglove_view(port: int | None) -> Any:
    """The run's live view in Foxglove (None: not asked for)."""
    if port is None:
        return None
    from tcf_hil.results.foxglove import LiveView

    try:
        view = LiveView(port)
    except Exception as err:  # (foxglove-sdk raises its own error for a taken port)
        raise click.BadParameter(f"cannot serve on 127.0.0.1:{port}: {err}",
                                 param_hint="--foxglove") from err
    err_console.print(f"Foxglove: ws://127.0.0.1:{view.port} (Open connection, Foxglove "
                      "WebSocket; the layout: tcf_hil/report_assets/foxglove-layout.json)")
    return view


@click.command("replay")
@click.argument("recording", metavar="RECORDING",
                type=click.Path(exists=True, path_type=Path))
@_recording_options
@click.option("--speed", type=click.FloatRange(min=0.05, max=20), default=1.0,
              show_default=True, help="Playback speed (1 = the original timing).")
@click.option("--loop", is_flag=True, help="Start over at the end (frame_id, column time "
                                           "stamps and pose time continue) until Ctrl-C.")
@click.option("--sensor-address", default="auto", show_default=True,
              help="Address the packets come from and the HTTP API answers on; auto: a "
                   "loopback address of its own (127.0.0.2, ...), the API on port 80.")
@click.option("--dest", default=None, help="Where packets go (default: the recorded "
                                           "udp_dest).")
@click.option("--lidar-port", type=click.IntRange(1, 65535), default=None,
              help="Send the lidar packets to this port [default: the recorded one].")
@click.option("--imu-port", type=click.IntRange(1, 65535), default=None,
              help="Send the IMU packets to this port [default: the recorded one].")
@click.option("--http-port", type=click.IntRange(0, 65535), default=None,
              help="Port of the HTTP API serving the recorded metadata [default: 80 with "
                   "--sensor-address auto where it may be bound, else a free one].")
@click.option("--can", "can_spec", default="auto", show_default=True,
              help="CAN bus for the recorded frames (auto, socketcan:IFACE, "
                   "socketcand:HOST:PORT:CHANNEL).")
def replay_cmd(recording: Path, meta: Path | None, can_log: Path | None, can_offset: float,
               speed: float, loop: bool, sensor_address: str, dest: str | None,
               lidar_port: int | None, imu_port: int | None, http_port: int | None,
               can_spec: str) -> None:
    """Send recorded lidar, IMU and CAN traffic to live endpoints.

    \b
    RECORDING is a tcf-hil run directory, or a field recording: an Ouster pcap (pcap or
    pcapng, as ouster-cli, ouster-ros or tcpdump write it) whose metadata JSON is found
    beside it as ouster-cli finds it (or given with --meta), and a CAN log (--can-log:
    candump .log, Vector .asc or .blf, PCAN .trc). The recording is checked first in one
    pass (every lidar packet must fit the metadata; other traffic is skipped and counted),
    then every lidar and IMU payload goes out byte for byte in recorded order and timing
    (times --speed), from --sensor-address to --dest and the recorded ports (or --lidar-port,
    --imu-port), the CAN frames on the bus between them; the sensor's HTTP API serves the
    recorded metadata. Files are streamed: memory stays flat whatever their length.

    \b
    Examples:
      tcf-hil replay runs/forest-v-20261125T101500Z
      tcf-hil replay drive.pcap --can-log drive.log --dest 127.0.0.1
      tcf-hil replay drive.pcap --meta sensor.json --loop --speed 0.5

    To score a SIC on this traffic use: tcf-hil run --replay RECORDING --sic "COMMAND".
    """
    from tcf_hil.run import replay_run

    with graceful_stop("stopping the replay") as stop, \
            LiveRun("checking the recording") as live:

        def checked(done: int, total: int) -> None:
            live.counter(done >> 20, total >> 20)

        try:
            r = replay_run(recording, None, None, speed=speed, loop=loop, dest=dest,
                           can_spec=can_spec, lead_s=0.0,
                           sensor_ip=None if sensor_address == "auto" else sensor_address,
                           http_port=http_port, stop=stop, announce=console.print, meta=meta,
                           can_log=can_log, can_offset_s=can_offset,
                           ports=(lidar_port, imu_port), progress=checked,
                           watch=live.watch)
        except OSError as err:
            if err.errno is None:
                raise
            raise click.ClickException(f"cannot serve the sensor's HTTP API: "
                                       f"{err.strerror}") from err
    sent = r.manifest.replay_sent or {}
    console.print(f"sent {sent.get('udp', 0)} UDP datagrams and {sent.get('can', 0)} CAN "
                  "frames")


@click.command("sic", add_help_option=False,
               context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.pass_context
def sic_cmd(ctx: click.Context) -> None:
    """The reference onboard SIC (the same as python -m tcf_hil.sic; --help for options)."""
    from tcf_hil.sic import sic_command

    sic_command.main(args=list(ctx.args), prog_name="tcf-hil sic")


@click.command("soak")
@click.argument("scenario_name", metavar="[SCENARIO]", default="forest-v", required=False)
@click.option("--minutes", type=click.FloatRange(min=0.25, max=30), default=10.0,
              show_default=True, help="How long the stream runs.")
@mode_option("2048x10")
@preset_option()
@seed_option()
@click.option("--max-growth", type=click.FloatRange(min=0), default=5.0, show_default=True,
              help="Memory growth after the warm-up (%) above which the soak fails.")
@run_dir_option("Run directory (default ./runs/soak-<UTC time stamp>/).")
@fault_option
@sensor_option
def soak_cmd(scenario_name: str, minutes: float, mode: str, preset: str, seed: int | None,
             max_growth: float, out: Path | None, faults: tuple[str, ...], sensor: str | None
             ) -> None:
    """Run the whole bench live for --minutes with the reference SIC and watch it.

    \b
    The track becomes a stretch of the strip road driven back and forth, so after the first
    pass (the warm-up) the SIC has seen all it will see. Reports the frames lost at the
    receiver, the pacing error (p50, p99), and the resident memory of the bench, its frame
    producer and the SIC after the warm-up and at the end. Writes soak.json and soak.md in
    the run directory (no lidar.pcap: 2048x10 sends 16 MB/s). Exit status 0 when the run
    completed with no frame lost and memory growth under --max-growth, 3 when the soak
    failed, 130 when stopped by Ctrl-C.
    """
    from tcf_hil._logs import library_logs
    from tcf_hil.run.soak import run_soak

    scn = scenario_with_faults(scenario_name, faults, sensor=sensor)
    out = run_dir(out, "soak-")
    announce_backend()
    try:
        with graceful_stop("stopping the soak: judging what ran") as stop, \
                library_logs(out / "bench.log"), LiveRun("building the scene") as live:
            r = run_soak(scn, out, minutes=minutes, mode=mode, preset=preset, seed=seed,
                         max_growth_percent=max_growth, announce=err_console.print,
                         stop=stop, watch=live.watch)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--minutes") from err
    console.print((out / "soak.md").read_text())
    console.print(f"run directory: {out}/")
    if not r.ok:
        finish(ExitStatus.INTERRUPTED if r.doc["status"] == "interrupted" else ExitStatus.FAILED)
