"""Safe defaults: every endpoint binds 127.0.0.1 unless told otherwise, request bodies and SIC
publications are bounded and schema-checked on every channel (a runaway SIC cannot fill the
bench's memory), no request path reaches the filesystem, and the SIC command runs without a
shell unless asked."""

from __future__ import annotations

import http.client
import json
import sys
from pathlib import Path

import pytest

from emulators.canbus import SocketcandServer
from emulators.lidar import SensorApi
from protocols.ouster import os0_64_metadata
from tcf_hil.run import SicProcess, sic_command
from tcf_hil.run.recorder import MAX_PUBLICATION_BYTES, FileWatcher, Inbox, PublishServer

DOC = {"timestamp": "20250213_035113", "total_objects_count": 1, "objects": [
    {"id": 1, "name": "tree_1", "cp": [1.0, 2.0, 0.0], "d": 2.24, "height": 15.0,
     "dbh": 0.25, "class": "S", "quality": 1, "maxcurve": 0.01}]}


def request(host: str, port: int, method: str, path: str, body: bytes = b"",
            headers: dict[str, str] | None = None) -> tuple[int, bytes]:
    c = http.client.HTTPConnection(host, port, timeout=10)
    try:
        c.request(method, path, body=body, headers=headers or {})
        r = c.getresponse()
        return r.status, r.read()
    finally:
        c.close()


def test_every_endpoint_binds_loopback_by_default(tmp_path: Path) -> None:
    with SensorApi(os0_64_metadata("512x10"), port=0) as api:
        assert api.address[0] == "127.0.0.1"
    server = PublishServer(Inbox(tmp_path / "sic"))
    assert server.server.server_address[0] == "127.0.0.1"
    assert server.url.startswith("http://127.0.0.1:")
    server.close()
    can = SocketcandServer(port=0)
    can.start()
    try:
        assert can.host == "127.0.0.1" and can.port > 0
    finally:
        can.stop()


@pytest.mark.parametrize("path", [
    "/../../../etc/passwd", "/api/v1/sensor/metadata/../../../../etc/passwd",
    "/api/v1/sensor/metadata/%2e%2e%2f%2e%2e%2fetc%2fpasswd", "//etc/passwd",
    "/api/v1/sensor/metadata/beam_intrinsics/../../../../README.md", "/README.md"])
def test_no_request_path_reaches_the_filesystem(path: str) -> None:
    with SensorApi(os0_64_metadata("512x10"), port=0) as api:
        status, body = request(*api.address[:2], "GET", path)  # type: ignore[misc]
    assert status == 404
    assert b"root:" not in body and b"tcf-hil" not in body


def test_request_bodies_are_bounded_and_checked(tmp_path: Path) -> None:
    with SensorApi(os0_64_metadata("512x10"), port=0) as api:
        host, port = api.address[:2]
        big = b"{" + b" " * (70 * 1024) + b"}"
        status, _ = request(host, port, "POST", "/api/v1/sensor/config", big,  # type: ignore[arg-type]
                            {"Content-Type": "application/json"})
        assert status == 413
        status, body = request(host, port, "POST", "/api/v1/sensor/config", b"[1, 2",  # type: ignore[arg-type]
                               {"Content-Type": "application/json"})
        assert status == 400 and b"malformed JSON" in body
    inbox = Inbox(tmp_path / "sic")
    server = PublishServer(inbox).start()
    try:
        port = server.server.server_address[1]
        status, _ = request("127.0.0.1", port, "POST", "/publish", b"x",
                            {"Content-Length": str(MAX_PUBLICATION_BYTES + 1)})
        assert status == 413 and not inbox.items  # refused before reading the body
        status, body = request("127.0.0.1", port, "POST", "/publish",
                               json.dumps({"objects": "nope"}).encode())
        assert status == 400 and inbox.items[-1].valid is False  # schema-checked, kept
        status, _ = request("127.0.0.1", port, "POST", "/publish", json.dumps(DOC).encode())
        assert status == 200 and inbox.items[-1].valid
        assert request("127.0.0.1", port, "GET", "/publish")[0] == 405
    finally:
        server.close()
        inbox.close()


def test_a_runaway_sic_line_is_bounded_and_the_next_forest_still_counts(tmp_path: Path) -> None:
    """A SIC that prints a line longer than any publication may be: its start is kept as an
    invalid publication, the rest skipped, and the next line is read as usual."""
    (tmp_path / "sic").mkdir()
    inbox = Inbox(tmp_path / "sic")
    script = ("import sys, json; w = sys.stdout.buffer.write; "
              f"w(b'{{' + b'x' * {MAX_PUBLICATION_BYTES + 5_000_000} + b'\\n'); "
              f"w(json.dumps({DOC!r}).encode() + b'\\n'); sys.stdout.flush()")
    proc = SicProcess([sys.executable, "-c", script], {}, tmp_path, inbox, False)
    assert proc.proc.wait(60) == 0
    proc.reader.join(60)
    proc.close()
    inbox.close()
    assert [p.valid for p in inbox.items] == [False, True]
    assert "at most" in str(inbox.items[0].error)
    assert inbox.items[0].bytes == MAX_PUBLICATION_BYTES + 1
    assert inbox.table_of(inbox.items[1]).xyz.shape == (1, 3)


def test_a_huge_publication_file_is_not_read_whole(tmp_path: Path) -> None:
    inbox = Inbox(tmp_path / "sic")
    f = tmp_path / "published.json"
    f.write_bytes(b"{" + b" " * (MAX_PUBLICATION_BYTES + 10) + b"}")
    FileWatcher(inbox, f).poll()
    assert inbox.items[0].bytes == MAX_PUBLICATION_BYTES + 1 and not inbox.items[0].valid
    f.write_text(json.dumps(DOC))
    FileWatcher(inbox, f).poll()
    assert inbox.items[1].valid
    inbox.close()


def test_only_the_latest_table_stays_in_memory(tmp_path: Path) -> None:
    inbox = Inbox(tmp_path / "sic")
    for k in range(5):
        doc = dict(DOC, objects=[dict(DOC["objects"][0], cp=[float(k), 0.0, 0.0])])
        inbox.record(json.dumps(doc).encode(), "test")
    assert [p.table is not None for p in inbox.items] == [False] * 4 + [True]
    # older ones come back from their files, unchanged
    assert [float(inbox.table_of(p).xyz[0, 0]) for p in inbox.items] == [0, 1, 2, 3, 4]
    inbox.close()


def test_the_sic_command_runs_without_a_shell_unless_asked() -> None:
    env = {"TCF_LIDAR_PORT": "7502"}
    argv = sic_command("./my_sic --port {lidar_port} ; rm -rf $HOME `id`", env, False)
    # no shell: metacharacters are plain arguments, nothing is expanded
    assert argv == ["./my_sic", "--port", "7502", ";", "rm", "-rf", "$HOME", "`id`"]
    assert sic_command("./my_sic | tee x", env, True) == "./my_sic | tee x"
