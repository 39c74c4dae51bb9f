"""``python -m tcf_hil.sic`` / ``tcf-hil sic``: the reference onboard SIC as a program."""

from __future__ import annotations

import click

from tcf_hil.errors import SicError
from tcf_hil.sic._online import SicConfig, main_with
from tcf_hil.sic._stems import PRESETS

_D = SicConfig.from_env()


@click.command(name="sic", context_settings={"max_content_width": 100})
@click.option("--metadata", default=_D.metadata, show_default="$TCF_METADATA",
              help="The sensor's metadata JSON file.")
@click.option("--sensor-url", default=_D.sensor_url, show_default="$TCF_SENSOR_URL",
              help="Or the sensor's HTTP API (http://HOST[:PORT]) to fetch it from.")
@click.option("--lidar-bind", default=_D.lidar_bind, show_default="$TCF_LIDAR_BIND",
              help="Address to receive lidar packets on.")
@click.option("--lidar-port", type=int, default=_D.lidar_port,
              show_default="$TCF_LIDAR_PORT, else the metadata's udp_port_lidar")
@click.option("--can-interface", default=_D.can_interface, show_default="$TCF_CAN_INTERFACE",
              help="python-can interface of the harvester's bus (socketcand, socketcan, ...).")
@click.option("--can-channel", default=_D.can_channel, show_default="$TCF_CAN_CHANNEL")
@click.option("--can-host", default=_D.can_host, show_default="$TCF_CAN_HOST",
              help="socketcand server host.")
@click.option("--can-port", type=int, default=_D.can_port, show_default="$TCF_CAN_PORT")
@click.option("--node-id", type=click.IntRange(1, 127), default=_D.node_id,
              show_default="$TCF_CAN_NODE_ID")
@click.option("--eds", default=_D.eds, show_default="$TCF_EDS, else the packaged EDS",
              help="The harvester node's EDS file.")
@click.option("--publish", default=_D.publish,
              show_default="$TCF_PUBLISH_URL / file:$TCF_PUBLISH_FILE / stdout",
              help="Where forests go: stdout (NDJSON), file:PATH (rewritten atomically) or "
                   "an http:// URL (POST).")
@click.option("--preset", type=click.Choice(sorted(PRESETS)), default="field",
              show_default=True,
              help="Stem algorithm: field (the default: mixed edge returns kept out of the "
                   "diameters, stems found by their shape among branches and crowns and "
                   "followed up the tree), tuned (the paper's clusters, refined) or paper "
                   "(as published).")
@click.option("--publish-every", "publish_s", type=click.FloatRange(min=0.1), default=2.0,
              show_default=True, help="Seconds between publications.")
@click.option("--idle", "idle_s", type=click.FloatRange(min=0.1), default=3.0,
              show_default=True, help="End of stream after this long without a packet.")
@click.option("--finish", "finish_s", type=click.FloatRange(min=0), default=10.0,
              show_default=True,
              help="After SIGTERM or SIGINT: at most this many seconds finishing the forest "
                   "(frames still waiting mapped, dirty tiles run) before the final forest "
                   "is published and the program exits; tcf-hil run sends SIGKILL 15 s after "
                   "its SIGTERM.")
@click.option("--stand", "stand_s", type=click.FloatRange(min=0), default=5.0,
              show_default=True,
              help="End of the drive once the machine (its CAN pose) has stood still this "
                   "many seconds after it moved, as at the end of a strip road: an always-on "
                   "sensor does not fall silent (0: only --idle and SIGTERM end it).")
@click.option("--voxel", "voxel_m", type=click.FloatRange(min=0.001), default=None,
              help="Voxel map resolution, m (default 0.03 for tuned, 0.1 for paper: about "
                   "the paper's point density).")
@click.option("--max-points", type=click.IntRange(min=10_000), default=_D.max_points,
              show_default=True,
              help="Voxel map cap, points (24 bytes each; the farthest tiles dropped beyond "
                   "it, a tile due for its last run held up to 1.5 times it).")
@click.option("--stem-worker/--inline-stems", "stem_worker", default=_D.stem_worker,
              show_default="$TCF_SIC_STEM_WORKER, else a worker",
              help="Run the stem algorithm in a process of its own at a lower priority (so "
                   "that no tile run holds up a frame), or inline between frames.")
def sic_command(**kw: object) -> None:
    """The reference onboard stem identification and classification program.

    It uses only the wire: Ouster lidar UDP (metadata from a file or the sensor's HTTP API)
    and the harvester's CANopen pose (through the EDS), and publishes the observed forest
    (tcf-hil's observed-forest JSON) every few seconds and at the end of the stream.
    `tcf-hil run` starts it with every endpoint in the environment.
    """
    cfg = SicConfig(**kw)  # type: ignore[arg-type]
    try:
        code = main_with(cfg)
    except SicError as err:  # its message alone on stderr, exit status 1
        raise SystemExit(str(err)) from err
    raise SystemExit(code)
