"""The ``tcf-hil`` command line. Commands stay thin: they parse options and call the library.

Exit status: 0 success, 1 bad input or configuration (one ``Error:`` line naming the file or
key), 2 usage error, 4 internal error (rerun with ``--traceback`` to see it).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from tcf_hil import __version__
from tcf_hil.errors import ConfigError, InputError, TcfHilError

console = Console(soft_wrap=True)
err_console = Console(stderr=True)


def _floats(n: int, names: str) -> Callable[[click.Context, click.Parameter, Any], Any]:
    def convert(_ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        if value is None:
            return None
        try:
            parts = tuple(float(v) for v in str(value).split(","))
        except ValueError as err:
            raise click.BadParameter(f"{value!r}: expected {n} comma-separated numbers "
                                     f"({names})", param=param) from err
        if len(parts) != n:
            raise click.BadParameter(f"{value!r}: expected {n} comma-separated numbers "
                                     f"({names})", param=param)
        return parts
    return convert


@contextlib.contextmanager
def _blame(scenario_name: str) -> Iterator[None]:
    """Name the scenario in a configuration error found only while building its forest."""
    try:
        yield
    except ConfigError as err:
        if err.source is not None:
            raise
        raise ConfigError(err.key, err.value, err.allowed, scenario_name) from err


class _Group(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:  # keep the teaching order
        return list(self.commands)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"],
                                           "max_content_width": 100})
@click.version_option(__version__, prog_name="tcf-hil")
@click.option("--traceback", is_flag=True, help="Show the full traceback of an internal error.")
@click.pass_context
def cli(ctx: click.Context, traceback: bool) -> None:
    """tcf-hil: a hardware-in-the-loop test bench for forest-harvester lidar software.

    \b
    Start here:
      tcf-hil demo                          the main job: a live run of the reference SIC
      tcf-hil run forest-v --sic "./my_sic --port {lidar_port}"   your onboard program
      tcf-hil scenario list                 the paper's Forests I-X
      tcf-hil forest generate forest-v --out forest-v/
      tcf-hil score ground_truth.json observed.json --plots plots/
    """
    ctx.obj = {"traceback": traceback}


# ----------------------------------------------------------------------------- demo


_MODES = ["512x10", "1024x10", "2048x10", "512x20", "1024x20"]


def _run_dir(out: Path | None) -> Path:
    return out or Path("runs") / _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")


_FAULT_HELP = ("Inject a fault: KEY=VALUE below the scenario's [faults] (repeatable), e.g. "
               "udp.loss=0.01, udp.burst_rate=0.001, udp.jitter_us=200, udp.reorder=0.01, "
               "lidar.dropout=0.02, lidar.reinit_at_s=[30], can.loss=0.01, "
               "can.pose_delay_ms=50, can.bus_off_at_s=[20], can.nmt_reset_at_s=[40]. "
               "`tcf-hil scenario show NAME` lists every key.")


def _fault_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--fault", "faults", multiple=True, metavar="KEY=VALUE",
                        help=_FAULT_HELP)(f)


def _scenario_with_faults(name: str, faults: Sequence[str], seed: int | None = None) -> Any:
    from tcf_hil.faults import apply_fault_options
    from tcf_hil.scenario import load_scenario

    return apply_fault_options(load_scenario(name, seed=seed), faults)


def _bridge(scn: Any, sic: str, out: Path, replay_dir: Path | None = None, **kw: Any) -> int:
    """Run the bridge with a progress bar; Ctrl-C / SIGTERM end it cleanly (the partial
    recording is kept and scored); prints the score table. Returns the exit status."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from tcf_hil._logs import library_logs
    from tcf_hil.bridge import run_bridge

    stop = threading.Event()

    def on_signal(_sig: int, _frame: object) -> None:
        err_console.print("stopping the run: closing the recording and scoring what was "
                          "published (Ctrl-C again aborts)")
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _terminate)

    previous = signal.signal(signal.SIGINT, on_signal)
    previous_term = signal.signal(signal.SIGTERM, on_signal)
    try:
        with library_logs(out / "bench.log"), Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeRemainingColumn(), console=err_console, transient=True) as prog:
            task = prog.add_task("frames on the wire", total=None)

            def step(done: int, total: int) -> None:
                prog.update(task, completed=done, total=total)

            if replay_dir is not None:
                from tcf_hil.replay import replay_run

                r = replay_run(replay_dir, sic, out, stop=stop, announce=err_console.print,
                               **kw)
            else:
                r = run_bridge(scn, sic, out, stop=stop, announce=err_console.print,
                               progress=step, **kw)
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
    if r.status == "can-conflict":  # nothing was scored: its poses were not the run's
        click.echo(f"Error: {r.message}; nothing scored (run directory {r.out}/)", err=True)
        return 1
    _print_run(r)
    if r.status == "complete" and r.scores is not None \
            and r.publications > r.invalid_publications:
        return 0
    return 130 if r.status == "interrupted" else 3


def _print_run(r: Any) -> None:
    from tcf_hil.evaluation._report import ROWS

    m = r.manifest
    if r.scores is not None:
        t = Table(title=f"{m.get('scenario')} {m.get('mode')}: the SIC's final forest",
                  header_style="bold")
        t.add_column("metric")
        t.add_column("all trees", justify="right")
        t.add_column("seen trees", justify="right")
        a, b = r.scores.all.metrics, r.scores.seen.metrics
        for key, label, fmt in ROWS[:1] + ROWS[7:13] + ROWS[13:15]:
            t.add_row(label, fmt.format(a[key]), fmt.format(b[key]))
        t.add_row("Ground-truth trees", str(a["n_ground_truth"]), str(b["n_ground_truth"]))
        console.print(t)
    lid = m.get("lidar", {})
    sent = (f"frames sent {lid.get('frames_sent', 0)}" if "replay_sent" not in m else
            f"replayed {m['replay_sent'].get('udp', 0)} datagrams, "
            f"{m['replay_sent'].get('can', 0)} CAN frames")
    console.print(f"{sent}, publications {r.publications} "
                  f"({r.invalid_publications} invalid), SIC exit code {r.sic_returncode}")
    if r.message:
        err_console.print(f"[bold]{r.status}[/]: {r.message}")
    report = r.out / "report.html"
    console.print(f"run directory: {r.out}/" + (f"  report: {report}" if report.exists()
                                               else ""))


@cli.command()
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default ./runs/<UTC time stamp>/).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the seed.")
@click.option("--preset", type=click.Choice(["tuned", "paper"]), default="tuned",
              show_default=True, help="The reference SIC's parameters.")
def demo(out: Path | None, seed: int | None, preset: str) -> None:
    """The main job end to end, on loopback: Forest V at 1024x10.

    \b
    The emulated OS0-64 streams over UDP (with its HTTP API), the harvester publishes its
    pose as a CANopen node on the embedded CAN server, the reference onboard SIC
    (`python -m tcf_hil.sic`) runs as a separate program on that wire, and the recorder
    scores its forest. Writes ./runs/<UTC time stamp>/ (or --out): lidar.pcap, can.log,
    metadata.json, ground_truth.json, visibility.json, sic/, manifest.json, score.json and
    report.html. About two minutes.
    """
    from tcf_hil.bridge import sic_reference_command
    from tcf_hil.scenario import load_scenario

    scn = load_scenario("forest-v")
    code = _bridge(scn, sic_reference_command(preset), _run_dir(out), mode="1024x10",
                   seed=seed)
    if code:
        raise SystemExit(code)


@cli.command("run")
@click.argument("scenario_name", metavar="SCENARIO", required=False)
@click.option("--sic", "sic", default=None,
              help="The onboard program to test, e.g. \"./my_sic --port {lidar_port}\" "
                   "(default: the reference SIC). {placeholders} and TCF_* environment "
                   "variables carry the endpoints (see README).")
@click.option("--shell", is_flag=True, help="Run --sic through /bin/sh (default: no shell).")
@click.option("--mode", type=click.Choice(_MODES), default="2048x10", show_default=True,
              help="Columns x frames per second.")
@click.option("--profile", type=click.Choice(["RNG19_RFL8_SIG16_NIR16", "LEGACY",
                                              "RNG19_RFL8_SIG16_NIR16_DUAL", "RNG15_RFL8_NIR8"]),
              default="RNG19_RFL8_SIG16_NIR16", show_default=True, help="UDP lidar profile.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the seed.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default ./runs/<UTC time stamp>/).")
@click.option("--speed", type=click.FloatRange(min=0.05, max=20), default=1.0,
              show_default=True, help="Simulation seconds per second (1 = real time).")
@click.option("--duration", type=click.FloatRange(min=0.1), default=None,
              help="Stop the stream after this many simulated seconds (default: the track).")
@click.option("--can", "can_spec", default="own", show_default=True,
              help="CAN bus: own (a CAN server of the run's own on a free port: no other "
                   "bench or harvester can mix in), or join one on purpose: auto, "
                   "socketcan:IFACE, socketcand:HOST:PORT:CHANNEL. On a joined bus a second "
                   "node with the harvester's id stops the run (exit 1).")
@click.option("--grace", type=click.FloatRange(min=0), default=30.0, show_default=True,
              help="Seconds the SIC gets after the stream ends to publish its final forest "
                   "and exit (then SIGTERM, then SIGKILL).")
@click.option("--ready-timeout", "ready_s", type=click.FloatRange(min=0), default=15.0,
              show_default=True,
              help="The clock starts when the SIC listens on the lidar UDP port, or after "
                   "this many seconds (0: at once).")
@click.option("--replay", "replay_dir", type=click.Path(file_okay=False, exists=True,
                                                         path_type=Path), default=None,
              help="Send a recorded run's traffic instead of the live emulators.")
@_fault_option
def run_cmd(scenario_name: str | None, sic: str | None, shell: bool, mode: str, profile: str,
            seed: int | None, out: Path | None, speed: float, duration: float | None,
            can_spec: str, grace: float, ready_s: float, replay_dir: Path | None,
            faults: tuple[str, ...]) -> None:
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
    Faults (the scenario's [faults] section, or --fault KEY=VALUE) are injected on the wire
    and logged with their times in faults.jsonl; score.json and report.html show the score
    next to them, e.g.:
      tcf-hil run forest-v --duration 30 --fault udp.loss=0.01 --fault can.bus_off_at_s=[10]
    """
    from tcf_hil.bridge import check_sic_command, sic_reference_command

    sic = sic or sic_reference_command()
    try:
        check_sic_command(sic, shell)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--sic") from err
    if replay_dir is not None:
        code = _bridge(None, sic, _run_dir(out), replay_dir, speed=speed, shell=shell,
                       can_spec=can_spec, grace_s=grace)
        if code:
            raise SystemExit(code)
        return
    if scenario_name is None:
        raise click.UsageError("give a SCENARIO (a preset name or TOML file) or --replay RUN_DIR")
    scn = _scenario_with_faults(scenario_name, faults)
    code = _bridge(scn, sic, _run_dir(out), mode=mode, profile=profile, seed=seed,
                   speed=speed, duration_s=duration, can=can_spec, shell=shell, grace_s=grace,
                   ready_s=ready_s)
    if code:
        raise SystemExit(code)


@cli.command("replay")
@click.argument("run_dir", metavar="RUN_DIR",
                type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--speed", type=click.FloatRange(min=0.05, max=20), default=1.0,
              show_default=True, help="Playback speed (1 = the original timing).")
@click.option("--loop", is_flag=True, help="Start over at the end (frame_id, column time "
                                           "stamps and pose time continue) until Ctrl-C.")
@click.option("--sensor-address", default="auto", show_default=True,
              help="Address the packets come from and the HTTP API answers on; auto: a "
                   "loopback address of its own (127.0.0.2, ...), the API on port 80.")
@click.option("--dest", default=None, help="Where packets go (default: the recorded "
                                           "udp_dest).")
@click.option("--http-port", type=click.IntRange(0, 65535), default=None,
              help="Port of the HTTP API serving the recorded metadata [default: 80 with "
                   "--sensor-address auto where it may be bound, else a free one].")
@click.option("--can", "can_spec", default="auto", show_default=True,
              help="CAN bus for the recorded frames (auto, socketcan:IFACE, "
                   "socketcand:HOST:PORT:CHANNEL).")
def replay_cmd(run_dir: Path, speed: float, loop: bool, sensor_address: str, dest: str | None,
               http_port: int | None, can_spec: str) -> None:
    """Send a recorded run's lidar, IMU and CAN traffic to live endpoints.

    \b
    The pcap and the CAN log go out with their original relative timing (times --speed),
    from --sensor-address to the recorded ports; your program listens as in the run. To
    score another SIC on this traffic use: tcf-hil run --replay RUN_DIR --sic "COMMAND".
    """
    from emulators.lidar import Route, SensorApi
    from tcf_hil._io import read_json
    from tcf_hil.bridge import sensor_url
    from tcf_hil.endpoints import SensorHost, claim_sensor_host
    from tcf_hil.harvester import open_bus
    from tcf_hil.replay import Recording, SdoResponder, replay

    rec = Recording.load(run_dir)
    node = dict(read_json(run_dir / "manifest.json").get("can_node") or {})
    stop = threading.Event()
    # auto: a host of its own, its API on port 80 (or a free one); an address given: the API
    # only with --http-port, as before
    host = claim_sensor_host(err_console.print) if sensor_address == "auto" else \
        SensorHost(sensor_address, -1 if http_port is None else http_port)
    port = host.http_port if http_port is None else http_port
    meta = rec.meta if dest is None else rec.meta.with_changes(udp_dest=dest)
    route = Route(meta.udp_dest, meta.udp_port_lidar, meta.udp_port_imu)
    api: SensorApi | None = None
    try:
        if port >= 0:
            api = SensorApi(meta, host.address, port, fixed=True, on_redirect=lambda m: route.set(
                m.udp_dest, m.udp_port_lidar, m.udp_port_imu)).start()
    except OSError as err:
        host.release()
        raise click.ClickException(f"cannot serve the sensor's HTTP API on {host.address}:"
                                   f"{port}: {err.strerror}") from err
    try:
        with open_bus(can_spec, announce=err_console.print) as spec:
            console.print(f"replaying {run_dir}: {rec.frames} frames, {len(rec.can)} CAN "
                          f"frames at {speed:g}x from sensor {host.address} (API "
                          f"{sensor_url(api) if api else 'off'}) to {meta.udp_dest}:"
                          f"{meta.udp_port_lidar}/{meta.udp_port_imu}, CAN {spec}"
                          + (" (looping; Ctrl-C stops)" if loop else ""))
            sdo = SdoResponder(spec, node)
            try:
                sent = replay(run_dir, speed=speed, loop=loop, sensor_ip=host.address,
                              dest=dest, spec=spec, stop=stop, rec=rec, route=route,
                              node_id=int(node.get("node_id", 10)))
            except KeyboardInterrupt:
                stop.set()
                return
            finally:
                sdo.close()
    finally:
        if api is not None:
            api.close()
        host.release()
    console.print(f"sent {sent['udp']} UDP datagrams and {sent['can']} CAN frames")


@cli.command("sic", add_help_option=False,
             context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
@click.pass_context
def sic_cmd(ctx: click.Context) -> None:
    """The reference onboard SIC (the same as python -m tcf_hil.sic; --help for options)."""
    from tcf_hil.sic._cli import sic_command

    sic_command.main(args=list(ctx.args), prog_name="tcf-hil sic")


# ------------------------------------------------------------------------- scenario


@cli.group(cls=_Group)
def scenario() -> None:
    """List and show scenarios (the Forest I-X presets or your own TOML files)."""


@scenario.command("list")
def scenario_list() -> None:
    """List the presets with their plot, stems, distribution and terrain."""
    from tcf_hil.scenario import list_presets

    t = Table(title="Scenario presets (paper, section 2.2)")
    for col in ("name", "plot (m)", "stems", "distribution", "terrain", "seed"):
        t.add_column(col)
    for s in list_presets():
        t.add_row(s.name, f"{s.plot.size_m[0]:g} x {s.plot.size_m[1]:g}", str(s.stems.count),
                  s.distribution.kind, s.terrain.kind, str(s.seed))
    console.print(t)
    from tcf_hil.scenario._load import EXTRA_PRESETS, load_scenario

    for name in EXTRA_PRESETS:
        console.print(f"Also [bold]{name}[/]: {load_scenario(name).description}.")
    console.print("Show one fully resolved: [bold]tcf-hil scenario show forest-v[/]. "
                  "Start your own"
                  " from a preset with [bold]extends = \"forest-v\"[/] in a TOML file.")


@scenario.command("show")
@click.argument("name")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the seed.")
def scenario_show(name: str, seed: int | None) -> None:
    """Print the fully resolved TOML of a preset or scenario file NAME."""
    from tcf_hil.scenario import load_scenario, scenario_to_toml

    click.echo(scenario_to_toml(load_scenario(name, seed=seed)), nl=False)


# --------------------------------------------------------------------------- forest


@cli.group(cls=_Group)
def forest() -> None:
    """Generate synthetic forests (SFC) and surface-sampled point clouds."""


def _terrain_kind(terrain: Any) -> str:
    shape = "flat" if not len(terrain.waves) else "rolling"
    return shape if terrain.tilt == (0.0, 0.0) else f"{shape} hillside"


@forest.command("generate")
@click.argument("scenario_name", metavar="PRESET_OR_TOML")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Random seed (default: the scenario's). Same scenario + seed = same bytes.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory.")
@click.option("--no-meshes", is_flag=True, help="Skip stems.ply and terrain.ply.")
def forest_generate(scenario_name: str, seed: int | None, out: Path, no_meshes: bool) -> None:
    """Generate a forest: ground_truth.json, stems.ply, terrain.ply and map.png in --out.

    stems.ply has a per-face stem_id (the ground-truth id); coordinates are world metres.
    """
    from tcf_hil.forest import generate_forest
    from tcf_hil.forest.output import write_forest
    from tcf_hil.scenario import load_scenario

    scn = load_scenario(scenario_name, seed=seed)
    with _blame(scenario_name), \
            console.status(f"generating {scn.name} ({scn.stems.count} stems)") as status:
        f = generate_forest(scn)
        paths = write_forest(f, out, meshes=not no_meshes,
                             progress=lambda name: status.update(f"{scn.name}: writing {name}"))
    counts = {c: int(np.sum(f.classes == c)) for c in ("S", "C", "X")}
    console.print(f"{scn.name}, seed {f.seed}: {len(f.stems)} stems "
                  f"(S {counts['S']}, C {counts['C']}, X {counts['X']}), terrain "
                  f"{_terrain_kind(f.terrain)}")
    for p in paths:
        console.print(f"  wrote {p}")


@forest.command("sample")
@click.argument("scenario_name", metavar="PRESET_OR_TOML")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Output .pcd file (binary; x y z float64, stem_id uint32, 0 = terrain).")
@click.option("--points-per-stem", type=click.IntRange(min=0), default=None,
              help="Surface points per stem (default: scenario, paper 1000).")
@click.option("--terrain-density", type=click.FloatRange(min=0), default=None,
              help="Terrain points per m² (default: scenario).")
@click.option("--ground-truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the ground truth JSON here.")
@click.option("--float32", is_flag=True,
              help="x y z as float32 (for open3d's legacy reader; loses precision far from 0).")
def forest_sample(scenario_name: str, seed: int | None, out: Path, points_per_stem: int | None,
                  terrain_density: float | None, ground_truth: Path | None,
                  float32: bool) -> None:
    """Surface-sample a forest (the paper's point clouds without lidar) into a PCD file."""
    from tcf_hil._io import write_bytes_atomic, write_json_atomic
    from tcf_hil.forest import generate_forest
    from tcf_hil.forest import ground_truth as gt_doc
    from tcf_hil.forest.sampling import sample_surfaces
    from tcf_hil.scenario import load_scenario

    scn = load_scenario(scenario_name, seed=seed)
    with _blame(scenario_name), console.status(f"sampling {scn.name}"):
        f = generate_forest(scn)
        cloud = sample_surfaces(f, points_per_stem, terrain_density)
        write_bytes_atomic(out, cloud.to_pcd(float32=float32))
        if ground_truth is not None:
            write_json_atomic(ground_truth, gt_doc(f))
    console.print(f"wrote {out}: {len(cloud)} points "
                  f"({int(np.sum(cloud.stem_id > 0))} on stems)")


# --------------------------------------------------------------------------- detect


def read_cloud(path: Path) -> np.ndarray:
    """x, y, z of a PCD file as an (n, 3) float64 array; InputError names file and field."""
    from protocols.pcd import PcdError, decode_pcd

    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(str(path), "", f"cannot read file ({err.strerror or err})") from err
    try:
        fields = decode_pcd(data)
    except PcdError as err:
        raise InputError(str(path), "", f"not a valid PCD file: {err}") from err
    for k in ("x", "y", "z"):
        if k not in fields:
            raise InputError(str(path), f"FIELDS.{k}",
                             f"the cloud has no {k} field (has: {', '.join(fields)})")
    xyz = np.column_stack([fields[k].astype(np.float64) for k in ("x", "y", "z")])
    bad = ~np.all(np.isfinite(xyz), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(str(path), f"point {i}", f"coordinates {xyz[i].tolist()} are not finite")
    return xyz


@cli.command()
@click.argument("cloud", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Observed-forest JSON to write.")
@click.option("--preset", type=click.Choice(["tuned", "paper"]), default="tuned",
              show_default=True, help="paper: exactly the published algorithm; tuned: refined.")
@click.option("--curve-threshold", type=click.FloatRange(min=0, min_open=True), default=None,
              help="maxcurve (m) from which a stem is C (default 0.05, as the scenarios).")
@click.option("--other-threshold", type=click.FloatRange(min=0, min_open=True), default=None,
              help="maxcurve (m) from which a stem is X (default 0.25).")
@click.option("--scene-centre", callback=_floats(2, "X,Y"), default="0,0", show_default=True,
              help="World x, y of the scene centre that d is measured from (the scenario's "
                   "origin, e.g. 500000,6900000 for a UTM plot).")
def detect(cloud: Path, out: Path, preset: str, curve_threshold: float | None,
           other_threshold: float | None, scene_centre: tuple[float, float]) -> None:
    """Run the reference stem algorithm on a PCD point cloud and write the observed JSON."""
    from tcf_hil._io import write_json_atomic
    from tcf_hil.sic import identify_stems, stem_params

    over: dict[str, Any] = {"scene_centre": tuple(scene_centre)}
    if curve_threshold is not None:
        over["curve_threshold_m"] = curve_threshold
    if other_threshold is not None:
        over["other_threshold_m"] = other_threshold
    try:
        prm = stem_params(preset, **over)
    except ValueError as err:
        raise click.BadParameter(str(err)) from err
    xyz = read_cloud(cloud)
    with console.status(f"stem algorithm on {len(xyz)} points"):
        doc = identify_stems(xyz, prm)
    write_json_atomic(out, doc)
    console.print(f"wrote {out}: {doc['total_objects_count']} stems")


# ---------------------------------------------------------------------------- score


@cli.command()
@click.argument("gt", metavar="GT.json", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("observed", metavar="OBSERVED.json",
                type=click.Path(dir_okay=False, path_type=Path))
@click.option("--match", "match_method", type=click.Choice(["greedy", "optimal"]),
              default="greedy", show_default=True,
              help="greedy: nearest pairs first (paper); optimal: minimum total distance.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=1.0,
              show_default=True, help="Matching radius d in the x-y plane (m).")
@click.option("--weights", callback=_floats(4, "S,C,X,N"), default="1,1,1,1",
              show_default=True, help="Class weights by ground-truth row.")
@click.option("--credits", callback=_floats(3, "E,A,N"), default="1,0,0", show_default=True,
              help="Credits for exact, almost and no match.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="Write every metric to this JSON file.")
@click.option("--plots", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write em_heatmap.png and matched_positions.png into this directory.")
def score(gt: Path, observed: Path, match_method: str, max_distance: float,
          weights: tuple[float, ...], credits: tuple[float, ...], json_out: Path | None,
          plots: Path | None) -> None:
    """Score an observed forest (SIC output) against the ground truth.

    Any document with objects[].cp and class (S/C/X) or quality (1/2/3) can be scored as
    either side; h, dbh and maxcurve are used when present.
    """
    from tcf_hil._io import write_json_atomic
    from tcf_hil.evaluation import EvalConfig, evaluate, metrics_table, write_plots
    from tcf_hil.stems_json import load_stems

    try:
        cfg = EvalConfig(match=match_method, max_distance_m=max_distance,  # type: ignore[arg-type]
                         weights=weights, credits=credits)  # type: ignore[arg-type]
    except ValueError as err:
        raise click.BadParameter(str(err)) from err
    g = load_stems(gt, "observed")
    o = load_stems(observed, "observed")
    ev = evaluate(g, o, cfg)
    console.print(metrics_table(ev, f"{observed.name} vs {gt.name} ({match_method}, "
                                    f"d = {max_distance:g} m)"))
    if json_out is not None:
        write_json_atomic(json_out, ev.metrics)
        console.print(f"wrote {json_out}")
    if plots is not None:
        for p in write_plots(ev, g, o, plots, observed.stem):
            console.print(f"wrote {p}")


# ---------------------------------------------------------------------------- lidar


@cli.group(cls=_Group)
def lidar() -> None:
    """The emulated Ouster OS0-64: offline recording to pcap, or live on the wire."""


def _sensor_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """--mode, --profile and --seed, shared by the lidar commands."""
    f = click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed.")(f)
    f = click.option("--profile", type=click.Choice(["RNG19_RFL8_SIG16_NIR16", "LEGACY",
                                                     "RNG19_RFL8_SIG16_NIR16_DUAL",
                                                     "RNG15_RFL8_NIR8"]),
                     default="RNG19_RFL8_SIG16_NIR16", show_default=True,
                     help="UDP lidar profile.")(f)
    return click.option("--mode", type=click.Choice(["512x10", "1024x10", "2048x10", "512x20",
                                                     "1024x20"]),
                        default="1024x10", show_default=True,
                        help="Columns x frames per second.")(f)


@lidar.command("pcap")
@click.argument("scenario_name", metavar="SCENARIO")
@_sensor_options
@click.option("--backend", type=click.Choice(["embree", "open3d"]), default="embree",
              show_default=True, help="Ray casting backend.")
@click.option("--noise", type=click.FloatRange(min=0), default=0.0, show_default=True,
              help="Range noise sigma (m).")
@click.option("--max-range", type=click.FloatRange(min=0, min_open=True), default=50.0,
              show_default=True, help="Range cap (m), as the paper.")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Stop after this many frames (default: the whole track).")
@click.option("--mtu", type=click.IntRange(min=68), default=1500, show_default=True,
              help="IPv4 MTU of the recorded link (larger packets are fragmented).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory.")
@_fault_option
def lidar_pcap(scenario_name: str, mode: str, profile: str, seed: int | None, backend: str,
               noise: float, max_range: float, frames: int | None, mtu: int,
               out: Path, faults: tuple[str, ...]) -> None:
    """Drive the sensor along the scenario's track, as fast as the machine allows.

    Writes lidar.pcap (lidar UDP to 7502, LEGACY IMU to 7503 at 100 Hz, from 127.0.0.1),
    metadata.json (read it with ouster-sdk: ouster-cli -m metadata.json source lidar.pcap),
    ground_truth.json (with the returns each stem got), visibility.json and sensor_poses.csv
    (the sensor frame in the world at every column time stamp). UDP and lidar faults
    (--fault, or the scenario's [faults]) go into the capture, logged in faults.jsonl.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from emulators.lidar import ReturnModel
    from tcf_hil.lidar import record_pcap

    scn = _scenario_with_faults(scenario_name, faults)
    model = ReturnModel(noise_sigma_m=noise, max_range_m=max_range)
    with _blame(scenario_name), \
            Progress(TextColumn("{task.description}"), BarColumn(),
                     TextColumn("{task.completed}/{task.total} frames"), TimeRemainingColumn(),
                     console=console, transient=True) as prog:
        task = prog.add_task(f"{scn.name} {mode} {profile}", total=None)

        def step(done: int, total: int) -> None:
            prog.update(task, completed=done, total=total)

        r = record_pcap(scn, out, mode=mode, profile=profile, seed=seed, backend=backend,
                        model=model, max_frames=frames, mtu=mtu, progress=step)
    console.print(f"{scn.name}: {r.frames} frames, {r.packets} lidar packets, {r.returns} "
                  f"returns, {r.stems_seen} stems seen ({r.backend}); wrote {out}/")


@lidar.command("stream")
@click.argument("scenario_name", metavar="SCENARIO")
@_sensor_options
@click.option("--sensor-address", default="auto", show_default=True,
              help="Address the packets come from (ouster-sdk checks it; any 127.x works); "
                   "auto: a loopback address of its own (127.0.0.2, ...) with the sensor's "
                   "HTTP API on port 80, as a real sensor.")
@click.option("--dest", default="127.0.0.1", show_default=True, help="Where packets go.")
@click.option("--lidar-port", type=click.IntRange(1, 65535), default=7502, show_default=True)
@click.option("--imu-port", type=click.IntRange(1, 65535), default=7503, show_default=True)
@click.option("--speed", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Simulation seconds per second; 0 = as fast as possible.")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Stop after this many frames (default: the whole track).")
@click.option("--record", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write what was sent (pcap) and the sidecar files here (with "
                   "--http-port, a client's re-initialisation n goes into DIR/reinit-n).")
@click.option("--http-port", type=click.IntRange(0, 65535), default=None,
              help="Serve the sensor's HTTP API on this port (ouster-sdk and ouster-cli "
                   "need 80, which needs root) [default with --sensor-address auto: 80 where "
                   "it may be bound, else a free port; otherwise no API]. Given here, the API "
                   "stays up after the track until Ctrl-C; by default the command ends with "
                   "the track.")
@click.option("--http-address", default=None,
              help="Address of the HTTP API (default: the sensor address).")
@_fault_option
def lidar_stream(scenario_name: str, mode: str, profile: str, seed: int | None,
                 sensor_address: str, dest: str, lidar_port: int, imu_port: int, speed: float,
                 frames: int | None, record: Path | None, http_port: int | None,
                 http_address: str | None, faults: tuple[str, ...]) -> None:
    """Stream the emulated OS0-64 live over UDP until the track ends or Ctrl-C.

    \b
    The sensor gets a loopback address of its own with its HTTP API on port 80 (as root),
    and stock clients connect as to a real sensor (the address is printed):
      ouster-cli source 127.0.0.2 slice 0:5 save x.pcap
    Without the HTTP API, give ouster-sdk the metadata instead (written by --record DIR or
    by `tcf-hil lidar pcap`):
      sensor.SensorFrameSetSource("127.0.0.2", sensor_info=[core.SensorInfo(json_text)])
    """
    from tcf_hil.endpoints import claim_sensor_host
    from tcf_hil.lidar import RecordResult, serve_sensor, stream_lidar

    scn = _scenario_with_faults(scenario_name, faults)
    stop = threading.Event()
    claims = contextlib.ExitStack()
    linger = http_port is not None  # an API asked for stays up after the track until Ctrl-C
    if sensor_address == "auto":
        host = claims.enter_context(claim_sensor_host(err_console.print))
        sensor_address = host.address
        if http_port is None:
            http_port = host.http_port

    def first_ctrl_c(_sig: int, _frame: object) -> None:
        # finish the frame on the wire, then write the recording: a second Ctrl-C aborts
        err_console.print("stopping after this frame (Ctrl-C again aborts)")
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _terminate)

    def summary(r: RecordResult) -> None:
        p50, p99 = r.pacing_us
        console.print(f"sent {r.packets} lidar packets in {r.frames} frames; pacing error "
                      f"p50 {p50:.0f} us, p99 {p99:.0f} us "
                      f"({'SCHED_FIFO' if r.realtime else 'ordinary scheduling: not permitted'}"
                      f"; pacing loop {100 * r.sender_cpu_share:.0f} % of a core); "
                      f"refused {r.refused}")

    previous = signal.signal(signal.SIGINT, first_ctrl_c)
    previous_term = signal.signal(signal.SIGTERM, first_ctrl_c)
    try:
        if http_port is not None:
            host_ip = http_address or sensor_address

            def listening(api: Any) -> None:
                console.print(f"sensor {scn.name} {mode} {profile}: HTTP API on "
                              f"{api.address[0]}:{api.address[1]}, UDP from {sensor_address} "
                              f"to {dest}:{lidar_port}/{imu_port} (Ctrl-C stops)")

            try:
                serve_sensor(scn, http_host=host_ip, http_port=http_port, on_api=listening,
                             sensor_ip=sensor_address, speed=speed, stop=stop, mode=mode,
                             profile=profile, seed=seed, max_frames=frames, udp_dest=dest,
                             udp_port_lidar=lidar_port, udp_port_imu=imu_port, record=record,
                             on_result=summary, linger=linger)
            except OSError as err:
                raise click.ClickException(
                    f"cannot serve {host_ip}:{http_port}: {err.strerror} (port 80 needs root; "
                    "or pass the metadata file to the client instead)") from err
            return
        console.print(f"streaming {scn.name} {mode} {profile} from {sensor_address} to "
                      f"{dest}:{lidar_port}/{imu_port} (Ctrl-C stops)")
        summary(stream_lidar(scn, sensor_ip=sensor_address, dest=dest, speed=speed,
                             record=record, stop=stop, mode=mode, profile=profile, seed=seed,
                             max_frames=frames, udp_port_lidar=lidar_port,
                             udp_port_imu=imu_port))
    except KeyboardInterrupt:
        stop.set()
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
        claims.close()


# ----------------------------------------------------------------------- harvester / CAN


_CAN_HELP = ("CAN bus: auto (vcan0 if the kernel has it, else the socketcand server on "
             "127.0.0.1:29536, started here if none answers), socketcan:IFACE, "
             "socketcand:HOST:PORT:CHANNEL, virtual:NAME, udp_multicast:GROUP (only in a "
             "network namespace without a default route).")


@cli.group(cls=_Group)
def harvester() -> None:
    """The harvester's pose as a CANopen node on a CAN bus (EDS and DBC in `files`)."""


@harvester.command("run")
@click.argument("scenario_name", metavar="SCENARIO")
@click.option("--can", "can_spec", default="auto", show_default=True, help=_CAN_HELP)
@click.option("--node-id", type=click.IntRange(1, 127), default=None,
              help="CANopen node id [default: the scenario's, 10].")
@click.option("--rate", type=click.FloatRange(min=0, min_open=True, max=1000), default=None,
              help="Pose rate in Hz: the node's SYNC period [default: the scenario's, 100].")
@click.option("--log", "log_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="Record every frame on the bus: .log (candump), .asc, .blf.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Random seed.")
@click.option("--speed", type=click.FloatRange(min=0, min_open=True, max=100), default=1.0,
              show_default=True, help="Simulation seconds per wall second.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Stop after this many simulation seconds [default: the whole track].")
@click.option("--wait-nmt", is_flag=True,
              help="Stay PRE-OPERATIONAL until an NMT master starts the node.")
@click.option("--external-sync", is_flag=True,
              help="Send TPDOs on SYNC from another node instead of producing SYNC.")
@_fault_option
def harvester_run(scenario_name: str, can_spec: str, node_id: int | None, rate: float | None,
                  log_path: Path | None, seed: int | None, speed: float,
                  duration: float | None, wait_nmt: bool, external_sync: bool,
                  faults: tuple[str, ...]) -> None:
    """Drive the scenario's track and publish the machine's pose on the CAN bus.

    \b
    The node boots (boot-up, heartbeat), goes OPERATIONAL by itself (unless --wait-nmt) and
    sends per SYNC: TPDO1 0x180+id X,Y (int32 mm), TPDO2 0x280+id Z (int32 mm), heading
    (uint16 0.01 deg, compass), pitch (int16 0.01 deg), TPDO3 0x380+id roll, speed (int16
    mm/s), time (uint32 us); TPDO4 0x480+id status every 100 ms; TIME each second. Read it
    with canopen and the EDS from `tcf-hil harvester files`, or with the DBC:
      python -m can.logger -i socketcand -c vcan0 --bus-kwargs host=127.0.0.1 port=29536
    """
    import can

    from emulators.harvester import BusSpecError, check_log_path
    from tcf_hil.faults import FaultLog
    from tcf_hil.forest import generate_forest
    from tcf_hil.harvester import open_bus, run_harvester

    if log_path is not None:
        try:
            check_log_path(log_path)
        except ValueError as err:
            raise click.BadParameter(str(err), param_hint="--log") from err
    scn = _scenario_with_faults(scenario_name, faults)
    with _blame(scenario_name):
        forest = generate_forest(scn, seed)
    flog = FaultLog(None, 0)  # counts only: the CAN log shows what reached the bus
    try:
        with open_bus(can_spec, announce=console.print) as spec:
            nid = node_id or scn.harvester.node_id
            console.print(f"harvester node {nid} of {scn.name} on {spec}"
                          + (f", logging to {log_path}" if log_path else "") + " (Ctrl-C stops)")
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            with Progress(TextColumn("sim {task.fields[t]:7.1f} s"), BarColumn(),
                          TimeRemainingColumn(), console=err_console, transient=True,
                          disable=not err_console.is_terminal) as bar:
                task = bar.add_task("drive", total=1.0, t=0.0)
                try:
                    r = run_harvester(scn, forest.terrain, spec, seed=forest.seed,
                                      node_id=node_id, rate_hz=rate, log_path=log_path,
                                      speed=speed, duration_s=duration,
                                      sync_producer=not external_sync, autostart=not wait_nmt,
                                      on_tick=lambda t, tot: bar.update(
                                          task, completed=min(1.0, t / tot), t=t),
                                      on_fault=flog.log)
                except KeyboardInterrupt:
                    console.print("stopped")
                    return
    except BusSpecError as err:
        raise click.BadParameter(str(err), param_hint="--can") from err
    except (OSError, can.CanError) as err:
        raise click.ClickException(f"CAN bus {can_spec}: {err}") from err
    if r.conflict:  # its poses and the other node's would be mixed: nothing to report
        raise click.ClickException(f"stopped: {r.conflict}")
    s = r.stats
    console.print(f"{r.sim_seconds:.1f} s simulated: {s['tpdo_frames']} TPDO frames, "
                  f"{s['syncs_sent']} SYNC sent, {s['syncs_received']} received, "
                  f"{s['heartbeats']} heartbeats, {s['foreign_frames']} foreign and "
                  f"{s['malformed_frames']} malformed frames ignored, {s['reconnects']} "
                  f"reconnects" + (f"; TPDO period p50 {s['tpdo_period_us_p50']:.0f} us, "
                                   f"jitter p99 {s['tpdo_jitter_us_p99']:.0f} us"
                                   if "tpdo_period_us_p50" in s else ""))
    if flog.events:
        console.print("faults injected: " + ", ".join(
            f"{k} {v['count']}" for k, v in flog.summary().items()))
    if log_path is not None:
        console.print(f"{r.log_frames} frames logged to {log_path}")
        if r.log_error:
            raise click.ClickException(f"CAN log {log_path}: {r.log_error} (logging stopped "
                                       "there; the node ran on)")


@harvester.command("files")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Directory for harvester.eds and harvester.dbc.")
@click.option("--node-id", type=click.IntRange(1, 127), default=10, show_default=True,
              help="Node id the DBC's frame ids are written for (the EDS serves any).")
def harvester_files(out: Path, node_id: int) -> None:
    """Write the node's EDS (for canopen and CANopen tools) and a DBC (cantools, SavvyCAN)."""
    from protocols.harvester import HARVESTER_OD, render_dbc, render_eds
    from tcf_hil._io import ensure_dir, write_bytes_atomic

    ensure_dir(out)
    write_bytes_atomic(out / "harvester.eds", render_eds(HARVESTER_OD).encode())
    write_bytes_atomic(out / "harvester.dbc", render_dbc(node_id).encode())
    console.print(f"wrote {out / 'harvester.eds'} and {out / 'harvester.dbc'} (node {node_id})")


@cli.command("soak")
@click.argument("scenario_name", metavar="[SCENARIO]", default="forest-v", required=False)
@click.option("--minutes", type=click.FloatRange(min=0.25, max=30), default=10.0,
              show_default=True, help="How long the stream runs.")
@click.option("--mode", type=click.Choice(_MODES), default="2048x10", show_default=True,
              help="Columns x frames per second.")
@click.option("--preset", type=click.Choice(["tuned", "paper"]), default="tuned",
              show_default=True, help="The reference SIC's parameters.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the seed.")
@click.option("--max-growth", type=click.FloatRange(min=0), default=5.0, show_default=True,
              help="Memory growth after the warm-up (%) above which the soak fails.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Run directory (default ./runs/soak-<UTC time stamp>/).")
@_fault_option
def soak_cmd(scenario_name: str, minutes: float, mode: str, preset: str, seed: int | None,
             max_growth: float, out: Path | None, faults: tuple[str, ...]) -> None:
    """Run the whole bench live for --minutes with the reference SIC and watch it.

    \b
    The track becomes a stretch of the strip road driven back and forth, so after the first
    pass (the warm-up) the SIC has seen all it will see. Reports the frames lost at the
    receiver, the pacing error (p50, p99), and the resident memory of the bench, its frame
    producer and the SIC after the warm-up and at the end. Writes soak.json and soak.md in
    the run directory (no lidar.pcap: 2048x10 sends 16 MB/s). Exit status 0 when the run
    completed with no frame lost and memory growth under --max-growth, 2 otherwise.
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from tcf_hil._logs import library_logs
    from tcf_hil.soak import run_soak

    scn = _scenario_with_faults(scenario_name, faults)
    out = out or Path("runs") / ("soak-" + _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ"))
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda _s, _f: stop.set())
    try:
        with library_logs(out / "bench.log"), Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeRemainingColumn(), console=err_console, transient=True) as prog:
            task = prog.add_task("soak: frames on the wire", total=None)
            r = run_soak(scn, out, minutes=minutes, mode=mode, preset=preset, seed=seed,
                         max_growth_percent=max_growth, announce=err_console.print,
                         progress=lambda d, t: prog.update(task, completed=d, total=t),
                         stop=stop)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--minutes") from err
    finally:
        signal.signal(signal.SIGINT, previous)
    console.print((out / "soak.md").read_text())
    console.print(f"run directory: {out}/")
    if not r.ok:
        raise SystemExit(2)


@cli.command("can-server")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on (anything but loopback exposes the bus).")
@click.option("--port", type=click.IntRange(0, 65535), default=29536, show_default=True)
def can_server(host: str, port: int) -> None:
    """A CAN bus without kernel CAN: a socketcand-protocol server that relays frames between
    all its clients on the same channel.

    \b
    Join it from any python-can program:
      can.Bus(interface="socketcand", host="127.0.0.1", port=29536, channel="vcan0")
    or with --can socketcand:127.0.0.1:29536:vcan0 in tcf-hil.
    """
    from emulators.canbus import SocketcandServer

    server = SocketcandServer(host, port)
    try:
        server.start()
    except OSError as err:
        raise click.ClickException(f"cannot listen on {host}:{port}: {err.strerror}") from err
    console.print(f"CAN server (socketcand protocol) on {host}:{server.port} (Ctrl-C stops)")
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        console.print(f"stopped: {server.stats()}")


# ----------------------------------------------------------------------- experiment


@cli.group(cls=_Group)
def experiment() -> None:
    """The paper's experiments."""


def _experiment1(out: Path, seed: int | None, presets: Sequence[str], write_pcd: bool) -> None:
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from tcf_hil.experiments import run_experiment1

    steps = 2 * (2 + len(presets))
    with Progress(SpinnerColumn(), TextColumn("{task.description}"),
                  TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(),
                  console=console, transient=True) as prog:
        task = prog.add_task("experiment 1", total=steps)

        def step(msg: str) -> None:
            prog.update(task, description=msg, advance=1)

        rows = run_experiment1(out, presets=presets, seed=seed, write_pcd=write_pcd,
                               progress=step)
    t = Table(title="Experiment 1 (paper Table 6): surface-sampled stems, no lidar; "
                    "ours (paper)")
    t.add_column("forest", no_wrap=True)
    for col in ("SIC", "stems", "found", "acc. %", "miscl. %", "missed %", "pos RMSE", "SIC s"):
        t.add_column(col, justify="right")

    def p(v: float, ref: float | None) -> str:
        return f"{v:.1f}" if ref is None else f"{v:.1f} ({ref:.1f})"

    for r in rows:
        t.add_row(r.forest, r.preset, str(r.stems), str(r.observed),
                  p(r.accuracy_percent, r.paper_accuracy_percent),
                  p(r.misclassified_percent, r.paper_misclassified_percent),
                  p(r.missed_of_total_percent, r.paper_missed_percent),
                  f"{r.position_rmse_m:.3f} m", f"{r.sic_seconds:.1f}")
    console.print(t)
    console.print(f"Results, plots and clouds: [bold]{out}[/] "
                  f"(summary: {out / 'experiment1.json'})")


@experiment.command("1")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("experiment1"), show_default=True, help="Output directory.")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Override the presets' seeds.")
@click.option("--preset", "presets", type=click.Choice(["tuned", "paper"]), multiple=True,
              help="SIC preset(s) to run (default: both).")
@click.option("--no-pcd", is_flag=True, help="Do not write the sampled clouds.")
def experiment_1(out: Path, seed: int | None, presets: tuple[str, ...], no_pcd: bool) -> None:
    """Experiment 1: Forests V and VI surface-sampled, stem algorithm, paper Table 6 beside ours."""
    _experiment1(out, seed, presets or ("tuned", "paper"), write_pcd=not no_pcd)


def _register_sweeps() -> None:
    from tcf_hil.experiments._cli import bench_cmd, columns_cmd, paper_cmd, passes_cmd

    cli.add_command(bench_cmd, "bench")
    experiment.add_command(paper_cmd, "paper")
    experiment.add_command(passes_cmd, "passes")
    experiment.add_command(columns_cmd, "columns")


_register_sweeps()


# ----------------------------------------------------------------------------- main


def _terminate(_sig: int, _frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Console entry point: maps errors to exit codes (see the module docstring)."""
    args = sys.argv[1:] if argv is None else argv
    if threading.current_thread() is not threading.main_thread():
        return _main(args)
    # kill / a service manager stops a server or stream as Ctrl-C does: cleanly
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _main(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _main(args: list[str]) -> int:
    from tcf_hil._logs import library_logs

    try:
        with library_logs(None):  # python-can's and canopen's warnings off the terminal
            cli.main(args=args, prog_name="tcf-hil", standalone_mode=False)
    except click.exceptions.Abort:
        err_console.print("Aborted.")
        return 1
    except click.ClickException as err:
        err.show()
        return err.exit_code
    except click.exceptions.Exit as err:
        return err.exit_code
    except TcfHilError as err:
        click.echo(f"Error: {err}", err=True)
        return 1
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        return 130
    except Exception:
        if "--traceback" in args:
            traceback.print_exc()
        else:
            exc = sys.exc_info()[1]
            click.echo(f"Internal error: {type(exc).__name__}: {exc} "
                       "(rerun with --traceback and report it)", err=True)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main())
