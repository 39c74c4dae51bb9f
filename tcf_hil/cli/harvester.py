"""``tcf-hil harvester`` and ``can-server``: the machine's pose as a CANopen node on a CAN
bus, and a CAN bus without kernel CAN."""

from __future__ import annotations

from pathlib import Path

import click

from tcf_hil.cli._shared import (
    Group,
    Progress,
    blame,
    console,
    fault_option,
    scenario_with_faults,
    seed_option,
)

_CAN_HELP = ("CAN bus: auto (vcan0 if the kernel has it, else the socketcand server on "
             "127.0.0.1:29536, started here if none answers), socketcan:IFACE, "
             "socketcand:HOST:PORT:CHANNEL, virtual:NAME, udp_multicast:GROUP (only in a "
             "network namespace without a default route).")


@click.group(cls=Group)
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
@seed_option("Random seed.")
@click.option("--speed", type=click.FloatRange(min=0, min_open=True, max=100), default=1.0,
              show_default=True, help="Simulation seconds per wall second.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Stop after this many simulation seconds [default: the whole track].")
@click.option("--wait-nmt", is_flag=True,
              help="Stay PRE-OPERATIONAL until an NMT master starts the node.")
@click.option("--external-sync", is_flag=True,
              help="Send TPDOs on SYNC from another node instead of producing SYNC.")
@fault_option
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
    from tcf_hil.devices.faults import FaultLog
    from tcf_hil.devices.harvester import open_bus, run_harvester
    from tcf_hil.world.forest import generate_forest

    if log_path is not None:
        try:
            check_log_path(log_path)
        except ValueError as err:
            raise click.BadParameter(str(err), param_hint="--log") from err
    scn = scenario_with_faults(scenario_name, faults)
    with blame(scenario_name):
        forest = generate_forest(scn, seed)
    flog = FaultLog(None, 0)  # counts only: the CAN log shows what reached the bus
    try:
        with open_bus(can_spec, announce=console.print) as spec:
            nid = node_id or scn.harvester.node_id
            console.print(f"harvester node {nid} of {scn.name} on {spec}"
                          + (f", logging to {log_path}" if log_path else "") + " (Ctrl-C stops)")
            with Progress("drive", 1.0, extra=("sim {task.fields[t]:7.1f} s",), t=0.0) as bar:
                try:
                    r = run_harvester(scn, forest.terrain, spec, seed=forest.seed,
                                      node_id=node_id, rate_hz=rate, log_path=log_path,
                                      speed=speed, duration_s=duration,
                                      sync_producer=not external_sync, autostart=not wait_nmt,
                                      on_tick=lambda t, tot: bar.update(
                                          completed=min(1.0, t / tot), t=t),
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


@click.command("can-server")
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
