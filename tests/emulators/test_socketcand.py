"""The embedded socketcand-protocol CAN server with real python-can socketcand clients (in this
process and in a child process) and raw TCP clients, all on 127.0.0.1. The pure protocol
parser/formatter is tested in tests/protocols/test_socketcand_codec.py."""

from __future__ import annotations

import json
import logging
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

from emulators.canbus import ServerStats, SocketcandServer
from protocols.socketcand import Command, MessageReader, format_send, parse_command

# python-can's client warns for every read that ends inside a message; that is noise here
logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)

OpenBus = Callable[..., can.BusABC]


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with SocketcandServer(port=0) as s:
        yield s


@pytest.fixture
def open_bus(server: SocketcandServer) -> Iterator[OpenBus]:
    buses: list[can.BusABC] = []

    def make(channel: str = "vcan0", srv: SocketcandServer | None = None) -> can.BusABC:
        bus = can.Bus(interface="socketcand", host="127.0.0.1",
                      port=(srv or server).port, channel=channel)
        buses.append(bus)
        return bus

    yield make
    for b in buses:
        b.shutdown()


def wait_until(pred: Callable[[], bool], timeout: float = 2.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


def msg(can_id: int, data: bytes, ext: bool) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=ext)


def key(m: can.Message | None) -> tuple[int, bool, bytes]:
    assert m is not None, "frame not received"
    return m.arbitration_id, m.is_extended_id, bytes(m.data)


def exchange(src: can.BusABC, dst: can.BusABC, frames: list[can.Message]) -> None:
    for m in frames:
        src.send(m)
    got = [key(dst.recv(2.0)) for _ in frames]
    assert got == [key(m) for m in frames]


class Raw:
    """A hand-written client on a plain TCP socket."""

    def __init__(self, port: int, rcvbuf: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.connect(("127.0.0.1", port))
        self.buf = b""

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_until(self, marker: bytes, timeout: float = 2.0) -> bytes:
        end = time.monotonic() + timeout
        while marker not in self.buf:
            self.sock.settimeout(max(0.01, end - time.monotonic()))
            chunk = self.sock.recv(65536)
            if not chunk:
                break
            self.buf += chunk
        assert marker in self.buf, f"{marker!r} not in {self.buf[-200:]!r}"
        i = self.buf.index(marker) + len(marker)
        out, self.buf = self.buf[:i], self.buf[i:]
        return out

    def read_to_eof(self, timeout: float = 2.0) -> tuple[bytes, bool]:
        """Everything until the server closes (True) or ``timeout`` passes (False)."""
        end = time.monotonic() + timeout
        out, self.buf = self.buf, b""
        while time.monotonic() < end:
            self.sock.settimeout(max(0.01, end - time.monotonic()))
            try:
                chunk = self.sock.recv(65536)
            except TimeoutError:
                break
            except ConnectionResetError:
                return out, True
            if not chunk:
                return out, True
            out += chunk
        return out, False

    def drain(self, quiet: float = 0.3) -> bytes:
        """Read until nothing arrives for ``quiet`` seconds."""
        out, self.buf = self.buf, b""
        self.sock.settimeout(quiet)
        while True:
            try:
                chunk = self.sock.recv(1 << 20)
            except TimeoutError:
                return out
            if not chunk:
                return out
            out += chunk

    def close(self) -> None:
        self.sock.close()


def frames_of(stream: bytes) -> list[Command]:
    return [c for c in map(parse_command, MessageReader(1 << 20).feed(stream))
            if c.verb == "frame"]


# ---------------------------------------------------------------------------------------------
# python-can clients
# ---------------------------------------------------------------------------------------------
def test_two_clients_exchange_standard_and_extended_frames_without_self_echo(
        server: SocketcandServer, open_bus: OpenBus) -> None:
    a, b = open_bus(), open_bus()
    elsewhere = open_bus("vcan1")
    a_to_b = [msg(0x123, b"\x01\x02\x03", False), msg(0x7FF, bytes(range(8)), False),
              msg(0x000, b"", False), msg(0x1ABCDEF0, b"\xff\x00\xaa\x55\x10\x20\x30\x40", True),
              msg(0x5, b"\x00", True), msg(0x1FFFFFFF, b"", True)]
    b_to_a = [msg(0x321, b"\xde\xad\xbe\xef", False), msg(0x18FF50E5, b"\x11" * 8, True),
              msg(0x080, b"", False)]
    t0 = time.time()
    exchange(a, b, a_to_b)
    exchange(b, a, b_to_a)
    # an echo to the sender would have been written with the delivery just checked
    assert a.recv(0.2) is None and b.recv(0.2) is None
    assert elsewhere.recv(0.05) is None  # another channel name is another bus
    a.send(msg(0x42, b"\x42", False))
    m = b.recv(2.0)
    assert key(m) == (0x42, False, b"\x42") and m is not None
    assert m.is_rx and abs(m.timestamp - t0) < 5.0  # the server's wall clock on receipt
    st_ = server.stats()
    n = len(a_to_b) + len(b_to_a) + 1
    assert (st_.frames_received, st_.frames_relayed, st_.frames_dropped) == (n, n, 0)
    assert (st_.clients_connected, st_.clients_total, st_.protocol_errors) == (3, 3, 0)
    assert st_.bytes_received > 0 and st_.bytes_sent > 0


def test_frames_from_one_client_reach_two_others_in_order(open_bus: OpenBus) -> None:
    a, b, c = open_bus(), open_bus(), open_bus()
    sent = [msg(i & 0x7FF, i.to_bytes(2, "big"), False) for i in range(300)]
    for m in sent:
        a.send(m)
    for rx in (b, c):
        assert [key(rx.recv(2.0)) for _ in sent] == [key(m) for m in sent]


CHILD = r"""
import json, logging, sys, time
import can
logging.getLogger("can").setLevel(logging.ERROR)
port, n = int(sys.argv[1]), int(sys.argv[2])
bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
print("ready", flush=True)
got = []
end = time.monotonic() + 20
while len(got) < n and time.monotonic() < end:
    m = bus.recv(0.5)
    if m is not None:
        got.append([m.arbitration_id, m.is_extended_id, bytes(m.data).hex()])
extra = bus.recv(0.2)
bus.shutdown()
print(json.dumps({"got": got, "extra": extra is not None}), flush=True)
"""


def test_child_process_receives_2000_unpaced_frames_in_order(
        server: SocketcandServer, open_bus: OpenBus) -> None:
    n = 2000
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(server.port), str(n)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "ready"
        tx = open_bus()
        sent = [msg(i if i % 3 else 0x10000000 + i, struct.pack(">H", i) + bytes(i % 7),
                    i % 3 == 0) for i in range(n)]
        for m in sent:
            tx.send(m)
        out, err = child.communicate(timeout=20)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 0, err
    res = json.loads(out)
    assert res["got"] == [[m.arbitration_id, m.is_extended_id, bytes(m.data).hex()]
                          for m in sent]
    assert res["extra"] is False
    assert tx.recv(0.1) is None  # and nothing came back to the sender
    assert server.stats().frames_relayed == n


# ---------------------------------------------------------------------------------------------
# bad clients
# ---------------------------------------------------------------------------------------------
GARBAGE = {
    "text before open": b"hello world\n",
    "send before open": b"< send 123 1 ff >",
    "rawmode before open": b"< rawmode >",
    "unknown command": b"< open vcan0 >< frobnicate 1 2 >",
    "FD length": b"< open vcan0 >< send 123 C " + b"1 " * 12 + b">",
    "DLC over 8": b"< open vcan0 >< send 123 9 " + b"1 " * 9 + b">",
    "fewer data bytes than DLC": b"< open vcan0 >< send 123 3 1 2 >",
    "more data bytes than DLC": b"< open vcan0 >< send 123 1 1 2 >",
    "standard id over 0x7FF": b"< open vcan0 >< send 800 0 >",
    "extended id over 29 bits": b"< open vcan0 >< send 20000000 0 >",
    "bad data byte": b"< open vcan0 >< send 123 1 xyz >",
    "bad id": b"< open vcan0 >< send 12G 0 >",
    "no closing bracket within 4 KiB": b"< open vcan0 >< send " + b"1 " * 3000,
    "binary junk": bytes(range(256)),
    "binary inside a message": b"< open vcan0 >< send 123 1 \x00\xff >",
    "server message from a client": b"< open vcan0 >< rawmode >< frame 123 1.000000 11 >",
    "nested brackets": b"< open < rawmode >",
    "empty message": b"< open vcan0 ><   >",
    "junk after a good frame": b"< open vcan0 >< send 321 1 aa >\x00junk",
}


@pytest.mark.parametrize("garbage", GARBAGE.values(), ids=GARBAGE.keys())
def test_garbage_disconnects_only_the_sender(server: SocketcandServer, open_bus: OpenBus,
                                             garbage: bytes,
                                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="tcf_hil.canbus")
    a, b = open_bus(), open_bus()
    raw = Raw(server.port)
    try:
        assert raw.read_until(b"< hi >") == b"< hi >"
        raw.send(garbage)
        reply, closed = raw.read_to_eof()
    finally:
        raw.close()
    assert closed, f"still connected after {garbage[:40]!r}; got {reply!r}"
    assert b"< error " in reply and reply.endswith(b" >")
    assert wait_until(lambda: server.stats().protocol_errors == 1)
    assert wait_until(lambda: server.stats().clients_connected == 2)
    assert any(r.name == "tcf_hil.canbus" and "disconnecting" in r.getMessage()
               for r in caplog.records)
    if garbage.startswith(b"< open vcan0 >< send 321"):  # what came before the junk counts
        assert key(b.recv(2.0)) == (0x321, False, b"\xaa")
        assert key(a.recv(2.0)) == (0x321, False, b"\xaa")
    exchange(a, b, [msg(0x100, b"\x01", False), msg(0x1000000, b"\x02\x03", True)])
    exchange(b, a, [msg(0x200, b"", False)])
    assert server.stats().protocol_errors == 1


def test_unsupported_commands_are_answered_and_the_wire_format_is_socketcands(
        server: SocketcandServer, open_bus: OpenBus) -> None:
    raw = Raw(server.port)
    try:
        raw.read_until(b"< hi >")
        raw.send(b"< echo >")  # allowed before open
        assert raw.read_until(b">") == b"< echo >"
        raw.send(b"< open vcan0 >\r\n")
        assert raw.read_until(b">") == b"< ok >"
        raw.send(b"< subscribe 0 0 123 >")
        assert raw.read_until(b">") == b"< error unsupported command subscribe >"
        raw.send(b"< open vcan1 >")
        assert raw.read_until(b">") == b"< error bus already open >"
        raw.send(b"< rawmode >")
        assert raw.read_until(b">") == b"< ok >"
        a = open_bus()
        time.sleep(0.1)  # past the raw client's join grace: frames come at once
        a.send(msg(0x12, b"\x0a\xbc", False))
        a.send(msg(0xABCDE, b"", True))
        line = raw.read_until(b">")
        assert line.startswith(b"< frame 012 ") and line.endswith(b" 0ABC >")
        secs, usecs = line.split()[3].split(b".")
        assert len(usecs) == 6 and abs(int(secs) - time.time()) < 5
        line = raw.read_until(b">")
        assert line.startswith(b"< frame 000ABCDE ") and line.endswith(b"  >")  # empty data
        raw.send(format_send(0x7F0, b"\x01\xff") + b"  " + b"< send 1FFFFFFF 0 >")
        assert key(a.recv(2.0)) == (0x7F0, False, b"\x01\xff")
        assert key(a.recv(2.0)) == (0x1FFFFFFF, True, b"")
        raw.send(b"< bcmmode >")
        assert raw.read_until(b">") == b"< ok >"
        a.send(msg(0x13, b"", False))  # not delivered in BCM mode
        raw.send(b"< echo >")
        assert raw.read_until(b">") == b"< echo >"
        time.sleep(0.05)
        assert raw.drain(0.1) == b""
    finally:
        raw.close()
    s = server.stats()
    assert (s.unsupported_commands, s.protocol_errors) == (2, 0)


@pytest.mark.parametrize("policy", ["drop-oldest", "disconnect"])
def test_slow_client_does_not_hold_up_the_others(open_bus: OpenBus, policy: Any) -> None:
    n = 5000
    with SocketcandServer(port=0, max_queue=50, sndbuf=4096, slow_client=policy) as srv:
        stuck = Raw(srv.port, rcvbuf=4096)  # opens the bus and then never reads
        stuck.send(b"< open vcan0 >< rawmode >")
        a, b = open_bus(srv=srv), open_bus(srv=srv)
        time.sleep(0.1)
        t0 = time.monotonic()
        got: list[tuple[int, bool, bytes]] = []
        for i in range(n):
            a.send(msg(0x100, i.to_bytes(4, "big"), False))
            if i % 250 == 249:  # b keeps up; the stuck client does not
                got += [key(b.recv(2.0)) for _ in range(250)]
        assert time.monotonic() - t0 < 2.0
        assert got == [(0x100, False, i.to_bytes(4, "big")) for i in range(n)]
        s = srv.stats()
        if policy == "drop-oldest":
            assert s.frames_dropped > 0 and s.slow_disconnects == 0
            assert s.clients_connected == 3
            seen = [int(c.frame.data.hex(), 16) for c in frames_of(stuck.drain())
                    if c.frame is not None]
            # what the sockets took first, in order, then the newest 50 (the queue)
            assert len(seen) + srv.stats().frames_dropped == n, "every frame accounted for"
            k = len(seen) - 50
            assert k > 0 and seen == [*range(k), *range(n - 50, n)]
        else:
            assert s.slow_disconnects == 1 and s.frames_dropped == 0
            assert wait_until(lambda: srv.stats().clients_connected == 2)
            assert stuck.read_to_eof(2.0)[1], "the stuck client was closed"
        stuck.close()
        exchange(b, a, [msg(0x7, b"\x07", False)])
        for bus in (a, b):
            bus.shutdown()


def test_joining_a_busy_bus_gets_ok_alone_and_no_frame_lost(server: SocketcandServer,
                                                            open_bus: OpenBus) -> None:
    tx = open_bus()
    stop = threading.Event()
    count = [0]

    def blast() -> None:  # one frame every ~0.5 ms, numbered
        while not stop.is_set():
            tx.send(msg(0x55, count[0].to_bytes(4, "big"), False))
            count[0] += 1
            time.sleep(0.0005)

    th = threading.Thread(target=blast, daemon=True)
    th.start()
    try:
        for _ in range(5):  # python-can's exact recv(256) of "< ok >" must not fail
            open_bus().shutdown()
        raw = Raw(server.port)
        raw.read_until(b"< hi >")
        raw.send(b"< open vcan0 >")
        assert raw.read_until(b">") == b"< ok >"
        raw.send(b"< rawmode >")
        time.sleep(0.02)  # a client slow to read its answer
        assert raw.sock.recv(256) == b"< ok >"
        time.sleep(0.1)
    finally:
        stop.set()
        th.join()
    seen = [int(c.frame.data.hex(), 16) for c in frames_of(raw.drain()) if c.frame]
    raw.close()
    assert len(seen) > 50 and seen == list(range(seen[0], seen[0] + len(seen)))
    assert seen[-1] == count[0] - 1


def test_abrupt_disconnects_do_not_disturb_the_others(server: SocketcandServer,
                                                      open_bus: OpenBus) -> None:
    a, b = open_bus(), open_bus()
    dying = Raw(server.port)
    dying.send(b"< open vcan0 >< rawmode >< send 123 2 1")  # half a message, then RST
    time.sleep(0.1)
    sent = [msg(0x300, i.to_bytes(2, "big"), False) for i in range(400)]
    for m in sent[:200]:
        a.send(m)
    dying.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    dying.close()  # reset while the server is writing frames to it
    for m in sent[200:]:
        a.send(m)
    assert [key(b.recv(2.0)) for _ in sent] == [key(m) for m in sent]
    # a python-can client that just goes away (closes its socket without a word)
    c = can.Bus(interface="socketcand", host="127.0.0.1", port=server.port, channel="vcan0")
    c.shutdown()
    assert wait_until(lambda: server.stats().clients_connected == 2)
    exchange(b, a, [msg(0x301, b"\x01", False), msg(0x1234567, b"", True)])
    s = server.stats()
    assert (s.protocol_errors, s.clients_total, s.frames_received) == (0, 4, 402)


# ---------------------------------------------------------------------------------------------
# life cycle
# ---------------------------------------------------------------------------------------------
def test_stop_closes_clients_and_releases_the_port() -> None:
    srv = SocketcandServer(port=0).start()
    port = srv.port
    assert port != 0 and srv.running
    raw = Raw(port)
    raw.read_until(b"< hi >")
    with pytest.raises(OSError):  # the port is taken while it runs
        SocketcandServer(port=port).start()
    srv.stop()
    assert not srv.running
    assert raw.read_to_eof(2.0)[1], "client closed by stop()"
    raw.close()
    thread = srv._thread
    assert thread is not None and not thread.is_alive()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    srv.stop()  # idempotent
    with pytest.raises(RuntimeError):
        srv.start()  # a server starts once
    with SocketcandServer(port=port) as again:  # the same port, at once
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
        bus.shutdown()
        assert wait_until(lambda: again.stats().clients_total == 1)


def test_serve_forever_returns_on_stop() -> None:
    srv = SocketcandServer(port=0)
    done = threading.Event()

    def serve() -> None:
        srv.serve_forever()
        done.set()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    assert wait_until(lambda: srv.running and srv.port != 0)
    assert not done.wait(0.2)
    srv.stop()
    assert done.wait(2.0)
    assert isinstance(srv.stats(), ServerStats)


def test_constructor_rejects_bad_settings() -> None:
    with pytest.raises(ValueError):
        SocketcandServer(port=0, max_queue=0)
    with pytest.raises(ValueError):
        SocketcandServer(port=0, slow_client="block")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        SocketcandServer(port=0, rawmode_grace_s=-1)


def test_a_server_in_a_process_of_its_own_relays_and_stops() -> None:
    from emulators.canbus import ServerProcess

    server = ServerProcess("127.0.0.1", 0)
    try:
        a = can.Bus(interface="socketcand", host="127.0.0.1", port=server.port,
                    channel="vcan0")
        b = can.Bus(interface="socketcand", host="127.0.0.1", port=server.port,
                    channel="vcan0")
        try:
            time.sleep(0.2)  # (both in raw mode)
            a.send(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
            got = b.recv(5.0)
            assert got is not None
            assert (got.arbitration_id, bytes(got.data)) == (0x181, b"\x01\x02")
        finally:
            a.shutdown()
            b.shutdown()
        with pytest.raises(OSError):  # its port is taken: one clear error, no process left
            ServerProcess("127.0.0.1", server.port)
    finally:
        server.stop()
    with socket.socket() as s:  # stopped: the port is free again
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", server.port))
