"""The sensor's HTTP API over real sockets on 127.0.0.1, and stock ouster-cli against the
whole emulated sensor (HTTP on port 80 + UDP), run as its own process."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from emulators.lidar import SensorApi
from protocols.ouster import SensorMetadata, os0_64_metadata


def _call(api: SensorApi, method: str, path: str, body: bytes | None = None
          ) -> tuple[int, Any]:
    host, port = api.address[:2]
    req = urllib.request.Request(f"http://{host}:{port}{path}", data=body, method=method,
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, json.loads(r.read() or b"null")
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read() or b"null")


@pytest.fixture
def api() -> Any:
    seen: list[SensorMetadata] = []
    with SensorApi(os0_64_metadata("1024x10"), "127.0.0.1", 0, on_reinit=seen.append) as a:
        a.seen = seen  # type: ignore[attr-defined]
        yield a


def test_metadata_and_sections(api: SensorApi) -> None:
    code, doc = _call(api, "GET", "/api/v1/sensor/metadata")
    assert code == 200 and doc == api.meta.to_json()
    for section in doc:
        assert _call(api, "GET", f"/api/v1/sensor/metadata/{section}") == (200, doc[section])
    assert _call(api, "GET", "/api/v1/system/firmware")[1] == {"fw": api.meta.image_rev}
    assert _call(api, "GET", "/api/v1/sensor/metadata/nope")[0] == 404
    assert _call(api, "GET", "/api/v1/../../etc/passwd")[0] == 404
    assert _call(api, "GET", "/api/v1/sensor/cmd/get_config_param")[0] == 404


def test_status_says_initializing_until_told_running(api: SensorApi) -> None:
    assert _call(api, "GET", "/api/v1/sensor/metadata/sensor_info")[1]["status"] == "RUNNING"
    api.status = "INITIALIZING"
    for path in ("/api/v1/sensor/metadata/sensor_info", "/api/v1/sensor/metadata"):
        doc = _call(api, "GET", path)[1]
        assert doc.get("sensor_info", doc)["status"] == "INITIALIZING"
    assert api.meta.to_json()["sensor_info"]["status"] == "RUNNING"  # served, not kept
    api.status = "RUNNING"
    assert _call(api, "GET", "/api/v1/sensor/metadata")[1] == api.meta.to_json()


def test_config_staging_auto_dest_and_reinit(api: SensorApi) -> None:
    old = api.meta.init_id
    code, _ = _call(api, "POST", "/api/v1/sensor/config?reinit=False&persist=False",
                    b'{"udp_dest": "@auto"}')
    assert code == 200
    assert _call(api, "GET", "/api/v1/sensor/config?staging=true")[1]["udp_dest"] == "127.0.0.1"
    assert api.seen == []  # type: ignore[attr-defined]
    _call(api, "POST", "/api/v1/sensor/config?staging=true&reinit=false",
          b'{"lidar_mode": "2048x10", "udp_profile_lidar": "RNG15_RFL8_NIR8"}')
    assert _call(api, "GET", "/api/v1/sensor/config")[1]["lidar_mode"] == "1024x10"  # active
    code, _ = _call(api, "POST", "/api/v1/sensor/config?staging=true&reinit=true", b"{}")
    assert code == 200
    new = api.seen[-1]  # type: ignore[attr-defined]
    assert (new.mode, new.profile) == ("2048x10", "RNG15_RFL8_NIR8")
    assert new.init_id != old and api.meta == new
    assert new.pixel_shift_by_row[0] == 2 * os0_64_metadata().pixel_shift_by_row[0]
    md = _call(api, "GET", "/api/v1/sensor/metadata")[1]
    assert md["sensor_info"]["initialization_id"] == new.init_id
    assert md["lidar_data_format"]["udp_profile_lidar"] == "RNG15_RFL8_NIR8"


def test_bad_requests(api: SensorApi) -> None:
    assert _call(api, "POST", "/api/v1/sensor/config", b"{not json")[0] == 400
    assert _call(api, "POST", "/api/v1/sensor/config", b"[1, 2]")[0] == 400
    code, body = _call(api, "POST", "/api/v1/sensor/config?reinit=true",
                       b'{"lidar_mode": "999x3"}')
    assert code == 400 and "lidar_mode" in body["error"]["description"]
    assert api.meta.mode == "1024x10"
    assert _call(api, "POST", "/api/v1/sensor/config", b" " * (70 * 1024))[0] == 413
    # found by fuzzing: these used to escape the handler and drop the connection unanswered
    code, body = _call(api, "POST", "/api/v1/sensor/config", b'{"udp_port_lidar": 1'
                       + b"0" * 5000 + b"}")
    assert code == 400 and "malformed JSON" in body["error"]["description"]
    assert _call(api, "POST", "/api/v1/sensor/config", b"[" * 60_000)[0] == 400
    with socket.create_connection(api.address[:2], timeout=5) as s:
        s.sendall(b"POST /api/v1/sensor/config HTTP/1.1\r\nHost: x\r\n"
                  b"Content-Length: lots\r\n\r\n{}")
        assert s.recv(100).split(b"\r\n")[0].split()[1] == b"400"
    assert _call(api, "PUT", "/api/v1/user/data", b'"hello"')[0] == 200
    assert _call(api, "GET", "/api/v1/user/data") == (200, "hello")
    assert _call(api, "DELETE", "/api/v1/user/data")[0] == 200
    assert _call(api, "GET", "/api/v1/user/data") == (200, "")


def _port_80_free() -> str | None:
    from tcf_hil.devices.endpoints import claim_sensor_host

    with claim_sensor_host() as host:
        return None if host.http_port == 80 else host.note


def _ouster_cli() -> str:
    why = _port_80_free()
    if why:
        pytest.skip(why)
    # the venv's own, whether or not the venv is on PATH
    cli = shutil.which("ouster-cli", path=str(Path(sys.executable).parent)) \
        or shutil.which("ouster-cli")
    if cli is None:
        pytest.skip("ouster-cli is not on PATH")
    return cli


def test_stock_ouster_cli_waits_while_the_sensor_initializes(tmp_path: Path) -> None:
    # what makes a slow power-on (a scene to build, a render to make) safe for a client that
    # connects at once: ouster-sdk asks sensor_info again until it says RUNNING
    import threading

    from tcf_hil.devices.endpoints import claim_sensor_host

    cli = _ouster_cli()
    with claim_sensor_host() as host, \
            SensorApi(os0_64_metadata("512x10"), host.address, host.http_port) as api:
        api.status = "INITIALIZING"
        hold_s = 2.5
        timer = threading.Timer(hold_s, lambda: setattr(api, "status", "RUNNING"))
        t0 = time.monotonic()
        timer.start()
        try:  # (nothing streams: it gives up 1 s after RUNNING, exit 0 all the same)
            subprocess.run([cli, "source", host.address, "slice", "0:1", "save",
                            str(tmp_path / "p.pcap")], cwd=tmp_path, capture_output=True,
                           text=True, timeout=60)
        finally:
            timer.cancel()
        took = time.monotonic() - t0
    polls = [r for r in api.requests if r == "GET /api/v1/sensor/metadata/sensor_info"]
    assert took >= hold_s and len(polls) >= 3, (took, api.requests)


def test_stock_ouster_cli_records_from_the_emulated_sensor(tmp_path: Path) -> None:
    cli = _ouster_cli()
    cmd = [sys.executable, "-m", "tcf_hil.cli"]
    rec = tmp_path / "rec"
    # the default: the sensor is a loopback host of its own, its HTTP API on port 80 there
    sensor = subprocess.Popen([*cmd, "lidar", "stream", "forest-ii", "--mode", "512x10",
                               "--frames", "400", "--record", str(rec)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert sensor.stdout is not None
        first = sensor.stdout.readline()
        host = first.split("HTTP API on ")[1].split(":")[0]
        assert host.startswith("127.0.0.") and host != "127.0.0.1", first
        for _ in range(100):
            try:
                urllib.request.urlopen(f"http://{host}/api/v1/system/firmware", timeout=1)
                break
            except OSError:
                time.sleep(0.2)
        # at once, as a user would: the sensor says INITIALIZING until it streams (a slow
        # power-on once made ouster-cli give up after 1 s without data, exit 0, no frames)
        out = tmp_path / "x.pcap"
        # (-t: a loaded test machine may hold a frame back past ouster-cli's 1 s default)
        proc = subprocess.run([cli, "source", "-t", "5", host, "slice", "0:5", "save",
                               str(out)],
                              cwd=tmp_path, capture_output=True, text=True, timeout=90)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    finally:
        sensor.send_signal(signal.SIGINT)
        try:
            said, _ = sensor.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            sensor.kill()
            said = ""
    from ouster.sdk import pcap as opcap

    # Ctrl-C finished the frame on the wire and kept the recording, as without the API
    assert sensor.returncode == 0, said
    sent = int(said.split(" lidar packets in ")[1].split()[0])
    recorded = list(opcap.PcapFrameSetSource(str(rec / "lidar.pcap"),
                                             meta=[str(rec / "metadata.json")]))
    assert len(recorded) == sent >= 5

    metas = list(tmp_path.glob("x*.json"))  # ouster-cli exits 0 even when it cannot connect
    assert metas, f"ouster-cli saved no metadata: {proc.stdout}{proc.stderr}"
    meta = metas[0]
    frames = [fs[0] for fs in opcap.PcapFrameSetSource(str(out), meta=[str(meta)])]
    assert len(frames) >= 4
    ids = [f.frame_id for f in frames]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)
    assert all(int(np.count_nonzero(f.field("RANGE"))) > 10_000 for f in frames[1:])
    assert json.loads(meta.read_text())["sensor_info"]["prod_line"] == "OS-0-64"
    assert os.path.getsize(out) > 500_000


def _served_endpoints() -> tuple[int, list[socket.socket]]:
    """A free TCP port for a served sensor's HTTP API, and its lidar and IMU sockets (bound
    to free UDP ports of 127.0.0.1)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    udp = []
    for _ in range(2):
        u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        u.bind(("127.0.0.1", 0))
        udp.append(u)
    return port, udp


def test_a_reinit_during_a_recorded_stream_starts_a_new_recording(tmp_path: Path) -> None:
    """serve_sensor with ``record``: what was sent before a client's re-initialisation goes
    to DIR, what after it to DIR/reinit-1, each with the metadata it was sent under."""
    import threading

    from ouster.sdk import pcap as opcap

    from tcf_hil.devices.sensor_service import serve_sensor
    from tcf_hil.scenario import load_scenario

    port, udp = _served_endpoints()
    rec, stop, ready = tmp_path / "rec", threading.Event(), threading.Event()
    results: list[Any] = []
    worker = threading.Thread(target=serve_sensor, args=(load_scenario("forest-ii"),), kwargs=dict(
        http_port=port, stop=stop, ready=ready, record=rec, mode="512x20", speed=4.0,
        udp_port_lidar=udp[0].getsockname()[1], udp_port_imu=udp[1].getsockname()[1],
        on_result=results.append))
    worker.start()

    def receive(packets: int) -> None:
        """Wait for ``packets`` lidar packets (the stream's own pace, not a fixed time: on a
        busy machine building the scene alone may take a second)."""
        udp[0].settimeout(60.0)
        for _ in range(packets):
            udp[0].recv(65536)

    try:
        assert ready.wait(60)
        receive(5 * 32)  # five 512x20 frames (32 packets each)
        req = urllib.request.Request(f"http://127.0.0.1:{port}/api/v1/sensor/config?reinit=true",
                                     data=b'{"lidar_mode": "1024x10"}', method="POST")
        assert urllib.request.urlopen(req, timeout=5).status == 200
        receive(5 * 64 + 400)  # five 1024x10 frames, after what the first stream left queued
    finally:
        stop.set()
        worker.join(60)
        for u in udp:
            u.close()
    assert not worker.is_alive() and len(results) == 2
    for out, r, mode in ((rec, results[0], "512x20"), (rec / "reinit-1", results[1], "1024x10")):
        meta = json.loads((out / "metadata.json").read_text())
        assert meta["config_params"]["lidar_mode"] == mode
        frames = list(opcap.PcapFrameSetSource(str(out / "lidar.pcap"),
                                               meta=[str(out / "metadata.json")]))
        assert len(frames) == r.frames > 3
    first = json.loads((rec / "metadata.json").read_text())["sensor_info"]
    second = json.loads((rec / "reinit-1" / "metadata.json").read_text())["sensor_info"]
    assert first["initialization_id"] != second["initialization_id"]


def _parked_sensor() -> tuple[int, list[socket.socket], Any, list[Any], Any]:
    """A served Forest II sensor at 512x10 with a three-frame track that stays on after it
    (serve_sensor in a thread, listening): its API port, lidar and IMU sockets, its stop
    event, the list its results go to, and the thread."""
    import threading

    from tcf_hil.devices.sensor_service import serve_sensor
    from tcf_hil.scenario import load_scenario

    port, udp = _served_endpoints()
    for u in udp:
        u.settimeout(60.0)
    stop, ready = threading.Event(), threading.Event()
    results: list[Any] = []
    worker = threading.Thread(target=serve_sensor, args=(load_scenario("forest-ii"),), kwargs=dict(
        http_port=port, stop=stop, ready=ready, mode="512x10", max_frames=3,
        udp_port_lidar=udp[0].getsockname()[1], udp_port_imu=udp[1].getsockname()[1],
        on_result=results.append))
    worker.start()
    assert ready.wait(60)
    return port, udp, stop, results, worker


def test_a_served_sensor_stands_and_sends_after_its_track_until_stopped() -> None:
    """As a real sensor on a parked machine: after the track (three frames here) the sensor
    goes on sending at its cadence, frame_id counting on, until it is stopped; the result
    counts the track's frames only."""

    from protocols.ouster import decode_lidar_packet, os0_64_metadata

    _, udp, stop, results, worker = _parked_sensor()
    fmt = os0_64_metadata("512x10").packet_format
    try:
        ids = [decode_lidar_packet(fmt, udp[0].recv(65536), check_crc=False).frame_id
               for _ in range(12 * 32)]  # twelve 512x10 frames of 32 packets: 3 of the track
        t0 = time.monotonic()
        for _ in range(5 * 32):  # five more frames, at the sensor's cadence
            udp[0].recv(65536)
        took = time.monotonic() - t0
    finally:
        stop.set()
        worker.join(60)
        for u in udp:
            u.close()
    assert not worker.is_alive() and len(results) == 1 and results[0].frames == 3
    frames = sorted(set(ids))
    assert frames == list(range(frames[0], frames[0] + 12))  # one count, on past the track
    assert 0.3 < took < 5.0  # 10 Hz: five frames take half a second, not nothing


def test_a_reinit_after_the_track_keeps_the_machine_standing() -> None:
    """A client that re-initialises a parked sensor (ouster-ros does at start) gets the
    machine standing where the track left it, frame_id from 0 under the new init_id: the
    track is not driven again."""

    from protocols.ouster import decode_lidar_packet, os0_64_metadata

    port, udp, stop, results, worker = _parked_sensor()
    fmt = os0_64_metadata("512x10").packet_format
    try:
        for _ in range(6 * 32):  # past the track's three frames
            udp[0].recv(65536)
        req = urllib.request.Request(f"http://127.0.0.1:{port}/api/v1/sensor/config?reinit=true",
                                     data=b'{"lidar_mode": "512x10"}', method="POST")
        assert urllib.request.urlopen(req, timeout=5).status == 200
        first = decode_lidar_packet(fmt, udp[0].recv(65536), check_crc=False)
        while True:  # what the first stream left queued, then the new identity's frames
            p = decode_lidar_packet(fmt, udp[0].recv(65536), check_crc=False)
            if p.init_id != first.init_id:
                break
        ids = [p.frame_id] + [decode_lidar_packet(fmt, udp[0].recv(65536),
                                                  check_crc=False).frame_id
                              for _ in range(6 * 32)]
    finally:
        stop.set()
        worker.join(60)
        for u in udp:
            u.close()
    assert not worker.is_alive() and len(results) == 2
    assert results[0].frames == 3 and results[1].frames == 0  # no track the second time
    frames = sorted(set(ids))
    assert frames[0] == 0 and frames == list(range(len(frames))) and len(frames) >= 6
