"""OSF (issue 46): ``tcf-hil export RUN --out run.osf`` writes Ouster's own format with
ouster-sdk, which ``ouster-cli source FILE info`` reads; ``tcf-hil replay FILE.osf`` sends its
frames as the packets of its profile, byte for byte the run's own; and ouster-cli's
``sensor_replay`` of our file sends the run's packets to a real socket. sensor_replay
announces itself over mDNS (multicast), so it runs in a network namespace of the test's own
(``unshare -n``), never on the host's network."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from protocols.ouster import SensorMetadata
from protocols.pcap import UdpReader
from tcf_hil.cli import main
from tcf_hil.devices.offline import record_pcap
from tcf_hil.errors import InputError
from tcf_hil.recording.reader import Recording
from tcf_hil.scenario import load_scenario

OUSTER_CLI = Path(sys.executable).with_name("ouster-cli")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("osf") / "run"
    record_pcap(load_scenario("forest-ii"), out, mode="512x10", max_frames=4)
    return out


@pytest.fixture(scope="module")
def osf_file(run_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("osfout") / "run.osf"
    assert main(["export", str(run_dir), "--out", str(out)]) == 0
    return out


def _lidar(run: Path) -> list[bytes]:
    meta = SensorMetadata.loads((run / "metadata.json").read_text())
    with open(run / "lidar.pcap", "rb") as f:
        return [bytes(d.payload) for d in UdpReader(f) if d.dst_port == meta.udp_port_lidar]


def test_ouster_cli_reads_our_osf(osf_file: Path) -> None:
    r = subprocess.run([str(OUSTER_CLI), "source", str(osf_file), "info"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "Frame Count: 4" in r.stdout and "LidarSensor" in r.stdout


def test_an_osf_replays_as_the_runs_own_packets(run_dir: Path, osf_file: Path) -> None:
    rec = Recording.load(osf_file)
    assert rec.frames == 4 and rec.counts["imu"] == 0  # (an OSF keeps no IMU packets)
    sent = [bytes(p) for _t, _port, p in rec.datagrams()]
    assert sent == _lidar(run_dir)  # every lidar packet, byte for byte


def test_a_file_that_is_not_osf_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "x.osf"
    bad.write_bytes(b"not an osf file" * 10)
    with pytest.raises(InputError, match=r"x\.osf") as err:
        Recording.load(bad)
    assert "\n" not in str(err.value)


_REPLAY = textwrap.dedent('''
    import select, socket, subprocess, sys, time
    lidar = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    lidar.bind(("127.0.0.1", 0))
    imu = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    imu.bind(("127.0.0.1", 0))
    http = socket.socket()
    http.bind(("127.0.0.1", 0))
    port = http.getsockname()[1]
    http.close()
    p = subprocess.Popen([sys.argv[1], "source", sys.argv[2], "sensor_replay", "--http-addr",
                          "127.0.0.1", "--http-port", str(port), "--lidar-port",
                          str(lidar.getsockname()[1]), "--imu-port", str(imu.getsockname()[1]),
                          "--udp-dest", "127.0.0.1", "--loop", "false", "--hide-diagnostics"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    got, end = [], time.monotonic() + 60
    while time.monotonic() < end and len(got) < int(sys.argv[3]):
        if select.select([lidar], [], [], 0.5)[0]:
            got.append(lidar.recv(65536))
    p.terminate()
    p.wait(30)
    sys.stdout.write("".join(g.hex() + "\\n" for g in got))
''')


@pytest.mark.skipif(shutil.which("unshare") is None or shutil.which("ip") is None,
                    reason="unshare and ip (util-linux, iproute2) make the test's own network "
                           "namespace")
def test_ouster_clis_sensor_replay_of_our_osf_sends_the_runs_packets(
        run_dir: Path, osf_file: Path, tmp_path: Path) -> None:
    want = _lidar(run_dir)
    script = tmp_path / "replay.py"
    script.write_text(_REPLAY)
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no network namespace here: {probe.stderr.decode().strip()}")
    r = subprocess.run(["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh",
                        sys.executable, str(script), str(OUSTER_CLI), str(osf_file),
                        str(len(want))], capture_output=True, text=True, timeout=180,
                       env=dict(os.environ))
    got = [bytes.fromhex(x) for x in r.stdout.split()]
    assert got, r.stderr[-2000:]
    assert set(got) <= set(want)  # what ouster-sdk sends from our file is the run's packets
    assert len(got) >= len(want) // 2


_SDK_SIC = textwrap.dedent('''
    import json, os, signal, sys
    import numpy as np
    from ouster.sdk import sensor
    src = sensor.SensorFrameSetSource(os.environ["TCF_SENSOR_HOST"], timeout=20)
    ids, whole = [], 0
    for frames in src:
        f = frames[0]
        if f is None:
            continue
        ids.append(int(f.frame_id))
        whole += bool(np.all(f.status & 1)) and int(np.count_nonzero(f.field("RANGE"))) > 500
        if len(ids) >= int(sys.argv[2]):
            break
    src.close()
    with open(sys.argv[1], "w") as fh:
        json.dump({"frame_ids": ids, "whole": whole}, fh)
    print(json.dumps({"objects": []}), flush=True)
    signal.pause()
''')


@pytest.mark.slow  # the second lane (.ci/run): a run that replays an OSF to an SDK client
def test_an_sdk_client_gets_the_frames_our_osf_replay_sends(tmp_path: Path) -> None:
    """``tcf-hil run --replay FILE.osf``: a program that opens the sensor as ouster-sdk does
    (``SensorFrameSetSource(TCF_SENSOR_HOST)``) gets the OSF's frames, whole, in order."""
    from tcf_hil.devices.endpoints import claim_sensor_host

    with claim_sensor_host() as host:
        if host.http_port != 80:
            pytest.skip(host.note or "port 80 cannot be bound here")
    run = tmp_path / "src"
    record_pcap(load_scenario("forest-ii"), run, mode="512x10", max_frames=12)
    osf = tmp_path / "drive.osf"
    assert main(["export", str(run), "--out", str(osf)]) == 0
    sic = tmp_path / "sdk_sic.py"
    sic.write_text(_SDK_SIC)
    report = tmp_path / "report.json"
    p = subprocess.run([sys.executable, "-m", "tcf_hil.cli", "run", "--replay", str(osf),
                        "--grace", "2", "--sic", f"{{python}} {sic} {report} 8", "--out",
                        str(tmp_path / "out")], capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, COLUMNS="200"))
    assert report.exists(), p.stderr[-3000:]
    got = json.loads(report.read_text())
    assert got["whole"] >= 7 and len(got["frame_ids"]) == 8, got  # (the first may be cut)
    ids = got["frame_ids"]
    assert all((b - a) % 65536 == 1 for a, b in itertools.pairwise(ids)), ids
