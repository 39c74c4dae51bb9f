"""``tcf-hil lidar``: the emulated OS0-64 offline (pcap) or live on the wire."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from tcf_hil.cli._shared import (
    BACKEND_CHOICES,
    Group,
    Progress,
    announce_backend,
    blame,
    console,
    err_console,
    fault_option,
    graceful_stop,
    mode_option,
    profile_option,
    scenario_with_faults,
    seed_option,
    sensor_option,
)


@click.group(cls=Group)
def lidar() -> None:
    """The emulated Ouster OS0-64: offline recording to pcap, or live on the wire."""


def _sensor_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """--mode, --profile and --seed, shared by the lidar commands."""
    return mode_option()(profile_option()(seed_option("Random seed.")(f)))


@lidar.command("pcap")
@click.argument("scenario_name", metavar="SCENARIO")
@_sensor_options
@click.option("--backend", type=click.Choice(BACKEND_CHOICES), default="auto", show_default=True,
              help="Ray casting backend: auto takes Embree where it exists, else open3d, "
              "else trimesh (pure numpy, slow), and says so.")
@click.option("--noise", type=click.FloatRange(min=0), default=None,
              help="With --sensor ideal: Gaussian range noise sigma (m; default 0).")
@click.option("--max-range", type=click.FloatRange(min=0, min_open=True), default=None,
              help="With --sensor ideal: range cap (m; default 50, as the paper).")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Stop after this many frames (default: the whole track).")
@click.option("--mtu", type=click.IntRange(min=68), default=1500, show_default=True,
              help="IPv4 MTU of the recorded link (larger packets are fragmented).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Renderer processes, each taking blocks of 10 frames in turn (the same "
                   "bytes as one) [default: one per CPU]. One renders in order, its ray "
                   "threads over the CPUs; so does a run with fault plans or --noise.")
@fault_option
@sensor_option
def lidar_pcap(scenario_name: str, mode: str, profile: str, seed: int | None, backend: str,
               noise: float | None, max_range: float | None, frames: int | None, mtu: int,
               out: Path, workers: int | None, faults: tuple[str, ...], sensor: str | None
               ) -> None:
    """Drive the sensor along the scenario's track, as fast as the machine allows.

    Writes lidar.pcap (lidar UDP to 7502, LEGACY IMU to 7503 at 100 Hz, from 127.0.0.1),
    metadata.json (read it with ouster-sdk: ouster-cli -m metadata.json source lidar.pcap),
    ground_truth.json (with the returns each stem got), visibility.json and sensor_poses.csv
    (the sensor frame in the world at every column time stamp). UDP and lidar faults
    (--fault, or the scenario's [faults]) go into the capture, logged in faults.jsonl.
    """
    from emulators.lidar import ReturnModel
    from tcf_hil.devices.offline import record_pcap

    scn = scenario_with_faults(scenario_name, faults, sensor=sensor)
    announce_backend(backend)
    model = None
    if noise is not None or max_range is not None:
        if not scn.sensor.ideal:
            raise click.BadParameter(f"applies to --sensor ideal, not {scn.sensor.preset} "
                                     "(whose noise and reach are physics)",
                                     param_hint="--noise/--max-range")
        model = ReturnModel(noise_sigma_m=noise or 0.0,
                            max_range_m=50.0 if max_range is None else max_range)
    with blame(scenario_name), Progress(f"{scn.name} {mode} {profile}") as bar:
        r = record_pcap(scn, out, mode=mode, profile=profile, seed=seed, backend=backend,
                        model=model, max_frames=frames, mtu=mtu, progress=bar.counter,
                        workers=workers)
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
                   "it may be bound, else a free port; otherwise no API]. Given here, the sensor "
                   "stays on after the track until Ctrl-C (the API answers; the machine "
                   "stands where the track left it and its frames go on at the sensor's "
                   "cadence, not recorded); by default the command ends with the track.")
@click.option("--http-address", default=None,
              help="Address of the HTTP API (default: the sensor address).")
@fault_option
@sensor_option
def lidar_stream(scenario_name: str, mode: str, profile: str, seed: int | None,
                 sensor_address: str, dest: str, lidar_port: int, imu_port: int, speed: float,
                 frames: int | None, record: Path | None, http_port: int | None,
                 http_address: str | None, faults: tuple[str, ...], sensor: str | None
                 ) -> None:
    """Stream the emulated OS0-64 live over UDP until the track ends or Ctrl-C.

    \b
    The sensor gets a loopback address of its own with its HTTP API on port 80 (as root),
    and stock clients connect as to a real sensor (the address is printed):
      ouster-cli source 127.0.0.2 slice 0:5 save x.pcap
    Without the HTTP API, give ouster-sdk the metadata instead (written by --record DIR or
    by `tcf-hil lidar pcap`):
      sensor.SensorFrameSetSource("127.0.0.2", sensor_info=[core.SensorInfo(json_text)])
    """
    from tcf_hil.devices.endpoints import claim_sensor_host
    from tcf_hil.devices.lidar import RecordResult

    scn = scenario_with_faults(scenario_name, faults, sensor=sensor)
    announce_backend()
    claims = contextlib.ExitStack()
    linger = http_port is not None  # an API asked for stays up after the track until Ctrl-C
    if sensor_address == "auto":
        host = claims.enter_context(claim_sensor_host(err_console.print))
        sensor_address = host.address
        if http_port is None:
            http_port = host.http_port

    def summary(r: RecordResult) -> None:
        p50, p99 = r.pacing_us
        console.print(f"sent {r.packets} lidar packets in {r.frames} frames; pacing error "
                      f"p50 {p50:.0f} us, p99 {p99:.0f} us "
                      f"({'SCHED_FIFO' if r.realtime else 'ordinary scheduling: not permitted'}"
                      f"; pacing loop {100 * r.sender_cpu_share:.0f} % of a core); "
                      f"refused {r.refused}")

    # the first Ctrl-C finishes the frame on the wire, then writes the recording
    with claims, graceful_stop("stopping after this frame") as stop:
        try:
            _stream(scn, stop, sensor_address, http_port, http_address, linger, summary,
                    mode=mode, profile=profile, seed=seed, dest=dest, lidar_port=lidar_port,
                    imu_port=imu_port, speed=speed, frames=frames, record=record)
        except KeyboardInterrupt:  # the second: the sensor's threads end too
            stop.set()
            raise


def _stream(scn: Any, stop: Any, sensor_address: str, http_port: int | None,
            http_address: str | None, linger: bool, summary: Any, *, mode: str, profile: str,
            seed: int | None, dest: str, lidar_port: int, imu_port: int, speed: float,
            frames: int | None, record: Path | None) -> None:
    from tcf_hil.devices.lidar import stream_lidar
    from tcf_hil.devices.sensor_service import serve_sensor

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


@lidar.command("timing")
@mode_option("2048x10", help="The mode whose packet interval the pacer keeps (2048x10: "
                             "781 us).")
@click.option("--seconds", type=click.FloatRange(min=0.5, max=3600), default=10.0,
              show_default=True, help="How long the pacer wakes.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object instead of the table.")
def lidar_timing(mode: str, seconds: float, as_json: bool) -> None:
    """What this machine lets the live sender do: a bare pacer's wake-ups.

    \b
    The live sender's own wait (SCHED_FIFO where permitted) wakes at the mode's packet
    interval for --seconds, sending nothing; the table gives how late its wake-ups came
    (p50, p99, the most, how many 1 ms or more) and what decides them: the hypervisor's
    steal meanwhile, the kernel's preemption model, the CPU idle driver. No sender is more
    punctual than its own wake-ups: where this shows wake-ups 1 ms late, a run's packets
    1 ms late are the machine's, not the bench's. Run it on a quiet machine, and beside a
    run (from a second terminal) to see what the run's load does to it.

    \b
    Exit status 0 when the floor meets the sender's aims (no wake-up 1 ms late, p99 within
    100 us), 3 when it does not.
    """
    import json

    from rich.table import Table

    from tcf_hil.cli._shared import ExitStatus, finish
    from tcf_hil.devices.timing import P99_AIM_US, machine_timing

    err_console.print(f"a bare pacer at {mode}'s packet interval for {seconds:g} s ...")
    t = machine_timing(mode, seconds)
    if as_json:
        click.echo(json.dumps(t.to_dict()))
    else:
        tab = Table(title=f"wake-ups every {t.interval_us:.0f} us ({mode}), {t.wakes} in "
                          f"{t.seconds:g} s", show_header=False)
        tab.add_column("")
        tab.add_column("", justify="right")
        steal = "not known" if t.steal_ms_per_s is None else f"{t.steal_ms_per_s:.1f} ms/s"
        rows = [("late p50 / p99", f"{t.p50_us} / {t.p99_us} us"),
                ("late at most", f"{t.max_us:,} us"),
                ("1 ms or more late", f"{t.late_1ms} ({t.late_per_10k:.1f} per 10k)"),
                ("scheduling", "SCHED_FIFO" if t.realtime
                 else "ordinary (SCHED_FIFO not permitted)"),
                ("hypervisor's steal", steal if t.hypervisor else f"{steal} (no hypervisor)"),
                ("kernel", f"{t.kernel}, {t.preemption}" + (
                    f" (preempt={t.preemption_now})" if t.preemption_now else "")),
                ("CPU idle driver", t.cpuidle_driver or "none"),
                ("CPUs", str(t.cpus))]
        for k, v in rows:
            tab.add_row(k, v)
        console.print(tab)
        if t.meets_aims:
            console.print("meets the sender's aims: no wake-up 1 ms late, p99 within "
                          f"{P99_AIM_US} us")
        else:
            why = []
            if t.hypervisor:
                why.append("a virtual machine: a vCPU the host does not run wakes late "
                           "whatever its priority inside (steal counts only part of it)")
            if not t.realtime:
                why.append("no SCHED_FIFO (root, or CAP_SYS_NICE, or an rtprio limit)")
            console.print(f"misses the sender's aims (no wake-up 1 ms late, p99 within "
                          f"{P99_AIM_US} us): no sender here is more punctual than this, "
                          "so a run's packets late by as much are the machine's"
                          + (f"; {'; '.join(why)}" if why else ""))
    finish(ExitStatus.OK if t.meets_aims else ExitStatus.FAILED)
