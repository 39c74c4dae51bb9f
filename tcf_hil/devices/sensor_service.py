"""The emulated sensor as a client meets a real one (``tcf-hil lidar stream --http-port``): its
HTTP API and its UDP stream, restarted with new metadata when a client re-initialises it."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from emulators.lidar import SensorApi
from emulators.lidar import warm_up as warm_up_kernels
from protocols.ouster import SensorMetadata
from tcf_hil.devices.lidar import (
    LidarRun,
    RecordResult,
    sensor_metadata,
    standing_after,
    stream_lidar,
)
from tcf_hil.scenario import Scenario
from tcf_hil.world.track import warm_up as warm_up_poses


def serve_sensor(scn: Scenario, *, http_host: str = "127.0.0.1", http_port: int = 80,
                 sensor_ip: str = "127.0.0.1", speed: float = 1.0,
                 stop: threading.Event | None = None, ready: threading.Event | None = None,
                 on_result: Callable[[RecordResult], None] | None = None,
                 record: str | Path | None = None, linger: bool = True,
                 on_api: Callable[[SensorApi], None] | None = None,
                 **run_kw: Any) -> SensorApi:
    """The emulated sensor as a client meets a real one: the HTTP API on ``http_host``
    (port 80 for ouster-sdk and ouster-cli) and the UDP stream to the configured
    ``udp_dest``. A configuration change with ``reinit`` restarts the stream with the new
    metadata (new init_id, frame_id from 0), as the real sensor does. Runs until the track
    ends and ``stop`` is set; returns the (closed) API object for inspection. ``record``:
    what was sent goes there (:func:`stream_lidar`); after the n-th re-initialisation, into
    its ``reinit-n`` folder (the metadata changed). ``linger`` False: return when the track
    ends instead of answering HTTP until ``stop``. ``on_api`` gets the API once it listens
    (its ``address`` is where: port 0 was a free port)."""
    stop = stop or threading.Event()
    meta_kw = {k: run_kw[k] for k in ("mode", "profile", "seed", "udp_dest", "udp_port_lidar",
                                      "udp_port_imu") if k in run_kw}
    first = sensor_metadata(scn, **meta_kw)  # the stream itself builds the scene
    reinit = threading.Event()
    current = [first]
    inner = [threading.Event()]

    def on_reinit(meta: SensorMetadata) -> None:
        current[0] = meta
        api.status = "INITIALIZING"  # (as a real sensor until the new stream is out)
        reinit.set()
        inner[0].set()

    # compiled before the API answers: a client that connects at once gets packets at once
    warm_up_kernels(first, run_kw.get("model"), scn.sensor)
    warm_up_poses()
    api = SensorApi(first, http_host, http_port, on_reinit=on_reinit)
    # INITIALIZING until the first frame goes out (a scene to build, a render to read or
    # make): ouster-sdk's client polls sensor_info once a second until it says RUNNING,
    # as it does at a real sensor's power-on, instead of giving up after 1 s without data
    api.status = "INITIALIZING"
    api.start()
    if on_api is not None:
        on_api(api)
    done = threading.Event()

    def relay() -> None:
        while not stop.wait(0.2):
            if done.is_set():
                return
        inner[0].set()

    threading.Thread(target=relay, name="sensor-stop", daemon=True).start()
    if ready is not None:
        ready.set()
    kw = {k: v for k, v in run_kw.items()
          if k not in ("mode", "profile", "udp_dest", "udp_port_lidar", "udp_port_imu")}
    segment = 0
    track_over = threading.Event()  # a re-initialisation after it does not drive it again

    def running() -> None:
        api.status = "RUNNING"

    def driven(done: int, total: int) -> None:  # (a stream stopped early has not driven it)
        if done >= total:
            track_over.set()
    try:
        while not stop.is_set():
            reinit.clear()
            inner[0] = threading.Event()
            if stop.is_set():
                break
            out = None if record is None else (
                Path(record) if segment == 0 else Path(record) / f"reinit-{segment}")
            segment += 1
            run = LidarRun(scn, meta=current[0], **kw)
            # lingering, the recording is written in place as frames go out (the stream
            # ends only when stopped: a crash meanwhile leaves a readable capture)
            r = stream_lidar(scn, sensor_ip=sensor_ip, speed=speed, stop=inner[0],
                             record=out, run=run, pcap_in_place=linger,
                             air=standing_after(run, track_over.is_set()) if linger
                             else None, progress=driven, on_air=running)
            if on_result is not None:
                on_result(r)
            if not reinit.is_set():
                break  # linger: the sensor stood after the track until told to stop
    finally:
        done.set()
        api.close()
    return api
