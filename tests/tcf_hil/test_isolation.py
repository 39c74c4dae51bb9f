"""Two benches on one machine never mix (real processes, real sockets): each `tcf-hil run`
owns its sensor address, UDP ports and CAN bus; a run beside a foreign harvester is not
disturbed by it, and one told to join that harvester's bus refuses with the conflict named;
a SIC that opens the sensor only by its host name (ouster-sdk's stock path) gets whole frames.

Every port is picked free by the code under test or by the test; nothing assumes 7502, 7503,
29536 or any other port is free."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from protocols.ouster import SensorMetadata
from protocols.pcap import read_udp
from tcf_hil.devices.endpoints import claim_sensor_host, reserve_udp_ports

TCF = [sys.executable, "-m", "tcf_hil.cli"]
ENV = dict(os.environ, COLUMNS="200", PYTHONUNBUFFERED="1")
RUN = ["run", "forest-ii", "--mode", "512x10", "--speed", "2", "--duration", "16", "--grace", "20",
       "--sensor", "ideal"]  # exact: the two runs' scores compare closely


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start(args: list[str]) -> subprocess.Popen[str]:
    return subprocess.Popen([*TCF, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV)


def _finish(p: subprocess.Popen[str], timeout: float = 300) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=timeout)
    return p.returncode, out, err


def _score(run: Path) -> dict:
    return json.loads((run / "score.json").read_text())["all_trees"]


def _sources(run: Path) -> set[str]:
    return {d.src_ip for d in read_udp((run / "lidar.pcap").read_bytes())}


def test_claims_are_exclusive_between_processes_and_released_on_exit() -> None:
    """A second process cannot take the sensor address or UDP port this one holds; once it
    is released (or the holder dies) they are free again."""
    with claim_sensor_host() as host, reserve_udp_ports("127.0.0.1", [0, 0]) as ports:
        assert host.address.startswith("127.0.0.") and host.address != "127.0.0.1"
        assert len(set(ports.ports)) == 2
        code = textwrap.dedent(f"""
            from tcf_hil.devices.endpoints import claim_sensor_host, reserve_udp_ports
            h = claim_sensor_host()
            p = reserve_udp_ports("127.0.0.1", {ports.ports!r})
            print(h.address, *p.ports)
        """)
        other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                               timeout=60, check=True).stdout.split()
        assert other[0] != host.address
        assert not set(map(int, other[1:])) & set(ports.ports)
    again = claim_sensor_host()
    again.release()


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_two_runs_at_once_score_as_each_does_alone(tmp_path: Path) -> None:
    code, _out, err = _finish(_start([*RUN, "--out", str(tmp_path / "alone")]))
    assert code == 0, err
    alone = _score(tmp_path / "alone")
    a = _start([*RUN, "--out", str(tmp_path / "a")])
    b = _start([*RUN, "--seed", "7", "--out", str(tmp_path / "b")])
    (ca, _, ea), (cb, _, eb) = _finish(a), _finish(b)
    assert (ca, cb) == (0, 0), ea + eb
    both = [json.loads((tmp_path / r / "manifest.json").read_text())["endpoints"]
            for r in ("a", "b")]
    for key in ("TCF_SENSOR_HOST", "TCF_CAN_SPEC", "TCF_LIDAR_PORT", "TCF_IMU_PORT"):
        assert both[0][key] != both[1][key], key  # nothing shared
    assert _sources(tmp_path / "a") == {both[0]["TCF_SENSOR_HOST"]}
    assert _sources(tmp_path / "b") == {both[1]["TCF_SENSOR_HOST"]}
    sa = _score(tmp_path / "a")
    # the same forest and track as alone: every stem found again, each where it was
    assert sa["f1"] == pytest.approx(alone["f1"], abs=0.05) and sa["f1"] >= 0.95
    # (poses crossed between the runs would put stems metres off; two runs on a 2-core CI
    # machine lose frames to each other and read up to 5.3 cm, alone 1.5 cm)
    assert sa["position_rmse_m"] < 0.1, (sa["position_rmse_m"], alone["position_rmse_m"])
    assert _score(tmp_path / "b")["f1"] >= 0.95
    for e in (ea, eb):  # python-can's chatter went to the runs' bench.log, if anywhere
        assert "incomplete message" not in e


@contextlib.contextmanager
def _foreign_harvester(tmp_path: Path) -> Iterator[str]:
    """A CAN server and a `tcf-hil harvester run` (node 10) on it, as another user's."""
    port = _free_tcp_port()
    server = _start(["can-server", "--port", str(port)])
    spec = f"socketcand:127.0.0.1:{port}:vcan0"
    harv: subprocess.Popen[str] | None = None
    try:
        for _ in range(100):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port),
                                                                        timeout=1):
                break
            time.sleep(0.1)
        harv = _start(["harvester", "run", "forest-v", "--can", spec])
        time.sleep(3.0)  # booted and sending
        assert harv.poll() is None, harv.communicate()
        yield spec
    finally:
        for p in (harv, server):
            if p is not None:
                p.send_signal(signal.SIGINT)
                try:
                    p.communicate(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.communicate()


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_a_run_beside_a_foreign_harvester_is_undisturbed_and_refuses_to_join_it(
        tmp_path: Path) -> None:
    with _foreign_harvester(tmp_path) as spec:
        code, _out, err = _finish(_start([*RUN, "--out", str(tmp_path / "own")]))
        assert code == 0, err
        assert _score(tmp_path / "own")["f1"] >= 0.95
        man = json.loads((tmp_path / "own" / "manifest.json").read_text())
        assert man["endpoints"]["TCF_CAN_SPEC"] != spec
        t0 = time.monotonic()
        code, _out, err = _finish(_start([*RUN, "--can", spec, "--out",
                                          str(tmp_path / "joined")]))
        assert code == 1, err
        lines = [ln for ln in err.splitlines() if ln.startswith("Error:")]
        assert len(lines) == 1 and "second CANopen node with id 10" in lines[0], err
        assert time.monotonic() - t0 < 120
        man = json.loads((tmp_path / "joined" / "manifest.json").read_text())
        assert man["status"] == "can-conflict" and "0x" in man["message"]
        assert "all_trees" not in json.loads((tmp_path / "joined" / "score.json").read_text())


SDK_SIC = textwrap.dedent("""
    # An onboard program written from the README alone: ouster-sdk's stock sensor path,
    # the sensor opened by its host name, no metadata file, none of tcf-hil's code.
    import json, os, signal, sys
    import numpy as np
    from ouster.sdk import sensor

    kw = {}
    ports = {}
    if sys.argv[2] == "own-ports":  # as ouster-ros with lidar_port/imu_port set: set_config
        import socket
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        kw = dict(lidar_port=socks[0].getsockname()[1], imu_port=socks[1].getsockname()[1])
        ports = dict(kw)
        for s in socks:
            s.close()
    if sys.argv[2] != "sdk-defaults":  # else the SDK's own timeouts (1 s for the first frame)
        kw["timeout"] = 20
    src = sensor.SensorFrameSetSource(os.environ["TCF_SENSOR_HOST"], **kw)
    info = src.sensor_info[0]
    whole = ids = 0
    seen = []
    for frames in src:
        f = frames[0]
        if f is None:
            continue
        seen.append(int(f.frame_id))
        if bool(np.all(f.status & 1)) and int(np.count_nonzero(f.field("RANGE"))) > 1000:
            whole += 1
        if len(seen) >= 40:
            break
    src.close()
    with open(sys.argv[1], "w") as fh:
        json.dump({"whole": whole, "frame_ids": seen, "mode": str(info.config.lidar_mode),
                   "init_id": info.init_id, "ports": ports}, fh)
    print(json.dumps({"objects": []}), flush=True)
    signal.pause()  # until the bench's SIGTERM after the stream
""")


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
@pytest.mark.parametrize("ports", ["sdk-defaults", "sensor-ports", "own-ports"])
def test_a_sic_that_opens_the_sensor_by_host_name_gets_whole_frames(tmp_path: Path,
                                                                    ports: str) -> None:
    """``SensorFrameSetSource(TCF_SENSOR_HOST)`` as onboard programs call it, with the SDK's
    default timeouts (the sensor is on from the start: the first frame comes well within
    the SDK's second); with ports of its own (as ouster-ros with lidar_port/imu_port) it
    sets them by set_config and re-initialises, and the run's stream follows without a new
    init_id."""
    pytest.importorskip("ouster.sdk")
    with claim_sensor_host() as host:
        if host.http_port != 80:
            pytest.skip(host.note or "port 80 cannot be bound here")
    sic = tmp_path / "sdk_sic.py"
    sic.write_text(SDK_SIC)
    report = tmp_path / "report.json"
    code, _out, err = _finish(_start(
        ["run", "forest-ii", "--mode", "512x10", "--duration", "6", "--grace", "2",
         "--sic", f"{{python}} {sic} {report} {ports}", "--out", str(tmp_path / "run")]))
    assert report.exists(), err + (tmp_path / "run" / "sic" / "stderr.log").read_text()
    got = json.loads(report.read_text())
    meta = SensorMetadata.loads((tmp_path / "run" / "metadata.json").read_text())
    assert got["whole"] >= 35, got  # 40 frames asked; the first may be partial
    assert got["init_id"] == meta.init_id
    man = json.loads((tmp_path / "run" / "manifest.json").read_text())
    if ports == "own-ports":  # the stream went where the SIC asked, and the manifest says so
        last = man["sensor_redirects"][-1]
        assert (last["udp_port_lidar"], last["udp_port_imu"]) == (got["ports"]["lidar_port"],
                                                                  got["ports"]["imu_port"])
        # metadata.json describes lidar.pcap, recorded with the ports the run was made with,
        # so the run replays
        assert meta.udp_port_lidar == int(man["endpoints"]["TCF_LIDAR_PORT"])
        from tcf_hil.recording.reader import Recording

        assert Recording.load(tmp_path / "run").counts["lidar"] >= 40 * 32
    else:
        assert "sensor_redirects" not in man
    ids = got["frame_ids"]  # in order, modulo 2^16 (the standing machine's count down to
    steps = [(b - a) % 65536 for a, b in itertools.pairwise(ids)]  # the track's 0)
    assert all(0 < d < 65536 // 2 for d in steps), ids
    assert code == 0, err


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_the_fallback_without_port_80_says_why_once(tmp_path: Path) -> None:
    """Without the privilege to bind port 80 (really: CAP_NET_BIND_SERVICE taken away with
    util-linux's setpriv) a run still gets a sensor address of its own, its API goes to a
    free port there, the reason is said once, and the run scores."""
    import shutil

    setpriv = shutil.which("setpriv")
    if setpriv is None or os.geteuid() != 0:
        pytest.skip("needs root and util-linux's setpriv to take the capability away")
    drop = [setpriv, "--bounding-set", "-net_bind_service"]
    probe = subprocess.run([*drop, sys.executable, "-c", textwrap.dedent("""
        from tcf_hil.devices.endpoints import claim_sensor_host
        said = []
        a = claim_sensor_host(said.append)
        b = claim_sensor_host(said.append)
        print(a.address, a.http_port, b.address, b.http_port, len(said))
    """)], capture_output=True, text=True, timeout=60, env=ENV)
    if probe.returncode != 0 and "setpriv" in probe.stderr:
        pytest.skip(f"setpriv refused here: {probe.stderr.strip()}")
    assert probe.returncode == 0, probe.stderr
    a_addr, a_port, b_addr, b_port, said = probe.stdout.split()
    assert (a_port, b_port, said) == ("0", "0", "1") and a_addr != b_addr
    p = subprocess.run([*drop, *TCF, "run", "forest-ii", "--mode", "512x10", "--speed", "2",
                        "--duration", "6", "--grace", "20", "--out", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=300, env=ENV)
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("cannot bind port 80") == 1, p.stderr
    assert "CAP_NET_BIND_SERVICE" in p.stderr and "TCF_METADATA" in p.stderr
    man = json.loads((tmp_path / "run" / "manifest.json").read_text())
    url = man["endpoints"]["TCF_SENSOR_URL"]
    assert url.startswith(f"http://{man['endpoints']['TCF_SENSOR_HOST']}:"), url
