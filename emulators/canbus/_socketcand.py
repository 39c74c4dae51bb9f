"""A CAN bus without kernel CAN: an embedded server speaking the socketcand protocol (raw mode).

Every frame a client sends is relayed to all *other* clients that opened the same channel name
and switched to raw mode, so separate processes share one bus through
``can.Bus(interface="socketcand", host="127.0.0.1", port=P, channel="vcan0")``.

The messages (``< hi >``, ``< open CH >``, ``< rawmode >``, ``< send ... >``,
``< frame ... >`` ...) are parsed and written by the sans-IO codec :mod:`protocols.socketcand`,
whose docstring gives the grammar; this module is the asyncio server around it. A ``send``
is relayed as ``< frame ID SECS.USECS HEXDATA >`` stamped with the server's wall clock on
receipt; ``< echo >`` is answered ``< echo >``; ``< bcmmode >`` (answered ``< ok >``) stops
delivery again, as a BCM socket without subscriptions would.

Decisions:

* **No self-echo.** A client never receives its own frames (the daemon's raw socket does not
  set CAN_RAW_RECV_OWN_MSGS, and python-can's client must not see its own sends).
* **Classic CAN only** (DLC 0-8, standard and extended identifiers), as the codec parses it:
  FD and remote frames from python-can's client are malformed ``send`` messages.
* **Garbage disconnects.** A client that sends something that is not a well-formed message
  (data outside ``< ... >``, bytes that are not printable ASCII, a message over
  :data:`~protocols.socketcand.MAX_MESSAGE_BYTES`, an unknown command, a malformed ``send``
  or ``open``, any command but ``open``/``echo`` before ``open``, or a message only a server
  sends) is sent ``< error REASON >`` and disconnected; the reason is logged on logger
  ``tcf_hil.canbus``. Commands the protocol defines but this server does not implement
  (``add``, ``subscribe``, ``filter``, ``controlmode``, ``isotpmode`` ...) are answered
  ``< error unsupported command VERB >`` and the connection stays, as the daemon answers
  ``< error unknown command >``.
* **Slow clients never hold up the others.** All writes are non-blocking. Frames a client
  does not take (once its socket buffers, 256 KiB of kernel send buffer and 64 KiB of
  transport buffer are full) wait in a per-client queue of at most ``max_queue`` frames.
  Beyond that either the oldest queued frames are dropped (the default,
  ``slow_client="drop-oldest"``, like a kernel socket buffer overflowing: order is kept and
  the newest frames survive) or the client is disconnected (``slow_client="disconnect"``).
  Both are counted in :meth:`SocketcandServer.stats` and logged. Dropping is the default
  because a send-only python-can program never reads and must not lose its connection.
* **Joining.** For ``rawmode_grace_s`` (50 ms) after ``< rawmode >`` frames for the new client
  are held back (not lost), so the ``< ok >`` reaches python-can's exact ``recv(256)`` alone.
* **Latency.** Every read is acknowledged at once (TCP_QUICKACK, as ``socketcand -q`` does):
  python-can's client leaves Nagle on, so back-to-back sends would otherwise wait up to 40 ms
  for a delayed ACK.
* **Ordering.** Frames from one client reach every other client in the order sent (one event
  loop thread handles everything; drops only ever remove frames, never reorder).

The server binds 127.0.0.1 by default. Any other address is accepted but exposes the bus (and
a way to inject frames into it) to every host that can reach that address.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Literal

from protocols.socketcand import (
    SERVER_MESSAGES,
    Command,
    MessageReader,
    SocketcandProtocolError,
    encode_frame,
    format_timestamp,
    parse_command,
)

__all__ = ["DEFAULT_PORT", "ServerStats", "SocketcandServer"]

log = logging.getLogger("tcf_hil.canbus")

DEFAULT_PORT = 29536
"""socketcand's default TCP port."""
DEFAULT_MAX_QUEUE = 65536
"""Frames queued per slow client before the policy applies (about 8 s of a saturated
1 Mbit/s bus, at most a few MiB)."""

_QUICKACK: int | None = getattr(socket, "TCP_QUICKACK", None)


@dataclass(frozen=True, slots=True)
class ServerStats:
    """Counters since start (a snapshot; the server may be counting on meanwhile)."""

    clients_connected: int
    """Connections open now."""
    clients_total: int
    """Connections accepted since start."""
    frames_received: int
    """``send`` commands accepted."""
    frames_relayed: int
    """Frame deliveries handed to receiving clients' connections (one per recipient)."""
    frames_dropped: int
    """Deliveries dropped because a client's queue was full (``drop-oldest``)."""
    protocol_errors: int
    """Clients disconnected for garbage."""
    slow_disconnects: int
    """Clients disconnected for a full queue (``slow_client="disconnect"``)."""
    unsupported_commands: int
    """Valid commands answered ``< error ... >`` (connection kept)."""
    bytes_received: int
    """Bytes read from all clients."""
    bytes_sent: int
    """Bytes written to all clients (greetings, answers and frames)."""


def _sanitize(reason: str) -> str:
    text = "".join(c if 0x20 <= ord(c) < 0x7F and c not in "<>" else "?" for c in reason)
    return text[:120]


class _Hub:
    """State of one server; touched only from its event loop thread."""

    def __init__(self, max_queue: int, slow_client: str, grace_s: float,
                 sndbuf: int | None) -> None:
        self.max_queue = max_queue
        self.sndbuf = sndbuf
        self.slow_client = slow_client
        self.grace_s = grace_s
        self.clients: set[_Client] = set()
        self.receivers: dict[str, list[_Client]] = {}
        self.touched: list[_Client] = []
        self.total = self.received = self.relayed = self.dropped = 0
        self.errors = self.slow = self.unsupported = self.rx_bytes = self.tx_bytes = 0
        self.closing = False

    def stats(self) -> ServerStats:
        return ServerStats(len(self.clients), self.total, self.received, self.relayed,
                           self.dropped, self.errors, self.slow, self.unsupported,
                           self.rx_bytes, self.tx_bytes)

    def relay(self, sender: _Client, line: bytes) -> None:
        for c in self.receivers.get(sender.channel or "", ()):
            if c is not sender:
                if not c.pending:
                    self.touched.append(c)
                c.pending.append(line)

    def flush(self) -> None:
        touched, self.touched = self.touched, []
        for c in touched:
            c.flush_pending()

    def set_receiving(self, c: _Client, on: bool) -> None:
        if c.channel is None or c.receiving == on:
            return
        c.receiving = on
        group = self.receivers.setdefault(c.channel, [])
        if on:
            group.append(c)
        else:
            group.remove(c)
            if not group:
                del self.receivers[c.channel]

    def forget(self, c: _Client) -> None:
        self.set_receiving(c, False)
        self.clients.discard(c)


class _Client(asyncio.Protocol):
    """One connection: parses what it sends, queues what it receives."""

    def __init__(self, hub: _Hub) -> None:
        self.hub = hub
        self.transport: asyncio.Transport | None = None
        self.reader = MessageReader()
        self.name = "client ?"
        self.channel: str | None = None
        self.receiving = False
        self.pending: list[bytes] = []
        self.queue: deque[bytes] = deque()
        self.paused = False
        self.held = False
        self.closed = False  # we are closing it (or it is gone)
        self.lost = False  # connection_lost ran
        self.episode_drops = 0
        self.sock: socket.socket | None = None

    # -- asyncio callbacks ---------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        hub = self.hub
        hub.total += 1
        self.name = f"client #{hub.total} {transport.get_extra_info('peername')}"
        sock = transport.get_extra_info("socket")
        if hub.sndbuf is not None and sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, hub.sndbuf)
            except OSError as e:
                log.debug("%s: SO_SNDBUF not set: %s", self.name, e)
        if _QUICKACK is not None:
            self.sock = sock
        if hub.closing:
            transport.abort()
            return
        hub.clients.add(self)
        log.debug("%s connected", self.name)
        self.reply(b"< hi >")

    def connection_lost(self, exc: Exception | None) -> None:
        self.lost = True
        if not self.closed:
            self.closed = True
            log.info("%s disconnected%s", self.name, f" ({exc})" if exc else "")
        self.pending.clear()
        self.queue.clear()
        self.hub.forget(self)

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        self.drain()

    def data_received(self, data: bytes) -> None:
        if self.closed:
            return
        hub = self.hub
        hub.rx_bytes += len(data)
        if self.sock is not None:
            self._quickack()
        stamp: str | None = None
        try:
            for raw in self.reader.feed(data):
                cmd = parse_command(raw)
                if cmd.verb == "send" and self.channel is not None:
                    assert cmd.frame is not None
                    stamp = stamp or format_timestamp(time.time())
                    hub.received += 1
                    hub.relay(self, encode_frame(cmd.frame, stamp))
                else:
                    self.command(cmd)
                if self.closed:
                    break
        except SocketcandProtocolError as e:
            self.fail(str(e))
        finally:
            hub.flush()

    def _quickack(self) -> None:
        # Acknowledge at once (Linux clears the flag on its own): python-can's client leaves
        # Nagle on, so without an immediate ACK its next small send would wait up to 40 ms
        # for the delayed one. socketcand's -q option does the same.
        assert self.sock is not None and _QUICKACK is not None
        try:
            self.sock.setsockopt(socket.IPPROTO_TCP, _QUICKACK, 1)
        except OSError:
            self.sock = None

    # -- commands ------------------------------------------------------------------------
    def command(self, cmd: Command) -> None:
        verb, hub = cmd.verb, self.hub
        if verb == "echo":
            self.reply(b"< echo >")
        elif verb in SERVER_MESSAGES:
            raise SocketcandProtocolError(f"{verb!r} is a message a server sends")
        elif self.channel is None:
            if verb != "open":
                raise SocketcandProtocolError(f"{verb!r} before '< open CHANNEL >'")
            self.channel = cmd.channel
            log.debug("%s opened %r", self.name, self.channel)
            self.reply(b"< ok >")
        elif verb in ("rawmode", "bcmmode"):
            on = verb == "rawmode"
            if on and not self.receiving and hub.grace_s > 0:
                self.held = True
                asyncio.get_running_loop().call_later(hub.grace_s, self.release)
            hub.set_receiving(self, on)
            self.reply(b"< ok >")
        else:  # open again, or a protocol command not implemented here
            hub.unsupported += 1
            what = "bus already open" if verb == "open" else f"unsupported command {verb}"
            log.info("%s: %s", self.name, what)
            self.reply(f"< error {what} >".encode("ascii"))

    def reply(self, msg: bytes) -> None:
        if self.transport is not None and not self.closed:
            self.hub.tx_bytes += len(msg)
            self.transport.write(msg)

    def release(self) -> None:
        self.held = False
        self.drain()

    # -- delivery ------------------------------------------------------------------------
    def _write(self, frames: list[bytes]) -> None:
        assert self.transport is not None
        blob = b"".join(frames)
        self.hub.relayed += len(frames)  # counted first: the peer may look at once
        self.hub.tx_bytes += len(blob)
        self.transport.write(blob)

    def flush_pending(self) -> None:
        batch, self.pending = self.pending, []
        if self.closed:
            return
        if self.paused or self.held or self.queue:
            self.enqueue(batch)
        else:
            self._write(batch)

    def enqueue(self, batch: list[bytes]) -> None:
        hub, q = self.hub, self.queue
        over = len(q) + len(batch) - hub.max_queue
        if over > 0:
            if hub.slow_client == "disconnect":
                hub.slow += 1
                self.disconnect(f"too slow: over {hub.max_queue} frames queued", abort=True)
                return
            if self.episode_drops == 0:
                log.warning("%s too slow: queue of %d frames full, dropping the oldest",
                            self.name, hub.max_queue)
            k = min(over, len(q))
            for _ in range(k):
                q.popleft()
            if over > k:
                batch = batch[over - k:]
            hub.dropped += over
            self.episode_drops += over
        q.extend(batch)

    def drain(self) -> None:
        q = self.queue
        while q and not (self.paused or self.held or self.closed):
            self._write([q.popleft() for _ in range(min(len(q), 512))])
        if not q and self.episode_drops and not self.closed:
            log.warning("%s caught up; %d frames dropped meanwhile", self.name,
                        self.episode_drops)
            self.episode_drops = 0

    # -- closing -------------------------------------------------------------------------
    def fail(self, reason: str) -> None:
        """Disconnect for garbage: counted, logged, told ``< error REASON >``."""
        if self.closed:
            return
        self.hub.errors += 1
        self.reply(f"< error {_sanitize(reason)} >".encode("ascii"))
        self.disconnect(reason, abort=False)

    def disconnect(self, reason: str, *, abort: bool) -> None:
        if self.closed:
            return
        log.warning("disconnecting %s: %s", self.name, reason)
        self.closed = True
        self.pending.clear()
        self.queue.clear()
        self.hub.set_receiving(self, False)
        t = self.transport
        if t is None:
            return
        if abort:
            t.abort()
        else:
            t.close()  # flushes the error message first
            asyncio.get_running_loop().call_later(1.0, self._abort_if_open)

    def _abort_if_open(self) -> None:
        if not self.lost and self.transport is not None:
            self.transport.abort()


SlowClientPolicy = Literal["drop-oldest", "disconnect"]


class SocketcandServer:
    """A CAN bus for python-can's ``socketcand`` clients, served from a background thread.

    Args:
        host: address to bind; 127.0.0.1 by default. Any other address exposes the bus.
        port: TCP port; 0 picks a free one (see :attr:`port` after :meth:`start`).
        max_queue: frames queued for a client that does not keep up before ``slow_client``
            applies.
        slow_client: ``"drop-oldest"`` (default) drops that client's oldest queued frames;
            ``"disconnect"`` closes its connection.
        rawmode_grace_s: how long frames for a client that just sent ``< rawmode >`` are held
            back, so that its ``< ok >`` arrives alone.
        sndbuf: kernel send buffer per connection (SO_SNDBUF, which Linux doubles); None
            leaves the OS's autotuning (up to 4 MiB), under which ``max_queue`` engages only
            after megabytes of stale frames.

    ``start()`` returns once listening; ``stop()`` closes every client and the listener.
    Use it as a context manager, or ``serve_forever()`` from a command line. A server is
    started at most once.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
                 max_queue: int = DEFAULT_MAX_QUEUE,
                 slow_client: SlowClientPolicy = "drop-oldest",
                 rawmode_grace_s: float = 0.05, sndbuf: int | None = 256 * 1024) -> None:
        if max_queue < 1:
            raise ValueError(f"max_queue {max_queue}; expected >= 1")
        if slow_client not in ("drop-oldest", "disconnect"):
            raise ValueError(f"slow_client {slow_client!r}; expected 'drop-oldest' or "
                             "'disconnect'")
        if not rawmode_grace_s >= 0:
            raise ValueError(f"rawmode_grace_s {rawmode_grace_s}; expected >= 0")
        self.host = host
        self._port = port
        if sndbuf is not None and sndbuf < 1:
            raise ValueError(f"sndbuf {sndbuf}; expected >= 1 or None")
        self._hub = _Hub(max_queue, slow_client, rawmode_grace_s, sndbuf)
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.Server | None = None
        self._thread: threading.Thread | None = None
        self._stopped = threading.Event()

    @property
    def port(self) -> int:
        """The listening port (the one chosen by the OS once started with ``port=0``)."""
        return self._port

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stopped.is_set()

    def stats(self) -> ServerStats:
        """Counters since start."""
        return self._hub.stats()

    # -- life cycle ----------------------------------------------------------------------
    def start(self) -> SocketcandServer:
        """Listen and serve in a background thread; returns once listening.

        Raises:
            OSError: the address cannot be bound (e.g. the port is taken).
            RuntimeError: already started.
        """
        with self._lock:
            if self._thread is not None:
                raise RuntimeError("SocketcandServer already started (it starts once)")
            ready = threading.Event()
            failure: list[BaseException] = []
            self._thread = threading.Thread(target=self._run, args=(ready, failure),
                                            name="socketcand-server", daemon=True)
            self._thread.start()
        ready.wait()
        if failure:
            self._thread.join()
            raise failure[0]
        if self.host not in ("127.0.0.1", "localhost", "::1"):
            log.warning("CAN server bound to %s: the bus is reachable from the network",
                        self.host)
        log.info("CAN server (socketcand protocol) listening on %s:%d", self.host, self._port)
        return self

    def _run(self, ready: threading.Event, failure: list[BaseException]) -> None:
        loop = asyncio.new_event_loop()
        try:
            try:
                self._server = loop.run_until_complete(loop.create_server(
                    lambda: _Client(self._hub), self.host, self._port, reuse_address=True))
                self._port = int(self._server.sockets[0].getsockname()[1])
                self._loop = loop
            except BaseException as e:  # handed to start()
                failure.append(e)
                return
            finally:
                ready.set()
            loop.run_forever()
        finally:
            loop.close()
            self._stopped.set()

    async def _shutdown(self) -> None:
        hub = self._hub
        hub.closing = True
        if self._server is not None:
            self._server.close()
        for c in list(hub.clients):
            c.closed = True
            if c.transport is not None:
                c.transport.abort()
        deadline = time.monotonic() + 2.0
        while hub.clients and time.monotonic() < deadline:
            await asyncio.sleep(0.001)

    def stop(self) -> None:
        """Close every client and the listener, and end the thread (idempotent)."""
        with self._lock:
            loop, thread = self._loop, self._thread
            if thread is None or loop is None or self._stopped.is_set() or loop.is_closed():
                return
            if threading.current_thread() is thread:
                raise RuntimeError("stop() from the server's own thread")
            try:
                asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(5.0)
            finally:
                loop.call_soon_threadsafe(loop.stop)
                thread.join(5.0)
        log.info("CAN server on %s:%d stopped", self.host, self._port)

    def serve_forever(self) -> None:
        """Start if needed and block until :meth:`stop` (from another thread) or Ctrl-C."""
        if self._thread is None:
            self.start()
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            log.info("CAN server interrupted")
        finally:
            self.stop()

    def __enter__(self) -> SocketcandServer:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()
