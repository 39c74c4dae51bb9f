"""A CAN bus without kernel CAN: an embedded server speaking the socketcand protocol (raw mode).

Every frame a client sends is relayed to all *other* clients that opened the same channel name
and switched to raw mode, so separate processes share one bus through
``can.Bus(interface="socketcand", host="127.0.0.1", port=P, channel="vcan0")``.

Protocol (linux-can/socketcand ``doc/protocol.md``, as the daemon and python-can 4.6 speak it):

* the server greets ``< hi >``; the client sends ``< open CH >`` and ``< rawmode >``, each
  answered ``< ok >`` in its own write (python-can compares a single ``recv(256)`` exactly);
* ``< send ID DLC B0 B1 ... >``: ``ID`` is hex, 8 digits for an extended (29-bit) identifier,
  fewer for a standard one (at most 0x7FF); ``DLC`` is 0-8; each data byte is its own token of
  1-2 hex digits (python-can sends ``1 a ff``, socketcandcl sends ``01 0a ff``);
* other clients receive ``< frame ID SECS.USECS HEXDATA >`` (3 or 8 upper-case ID digits; data
  upper-case hex without spaces; an empty frame has two spaces before ``>``, as the daemon
  writes it and as python-can's parser needs); the time is the server's wall clock on receipt;
* ``< echo >`` is answered ``< echo >``; ``< bcmmode >`` (answered ``< ok >``) stops delivery
  again, as a BCM socket without subscriptions would.

Decisions:

* **No self-echo.** A client never receives its own frames (the daemon's raw socket does not
  set CAN_RAW_RECV_OWN_MSGS, and python-can's client must not see its own sends).
* **Classic CAN only** (DLC 0-8, standard and extended identifiers). python-can's client has
  no FD or remote-frame syntax: an FD message reaches the server as a ``send`` with a DLC
  above 8 and a remote frame with fewer data bytes than its DLC; both are malformed (a
  remote frame with DLC 0 looks like an empty data frame and is relayed as one).
* **Garbage disconnects.** A client that sends something that is not a well-formed message
  (data outside ``< ... >``, bytes that are not printable ASCII, a message over
  :data:`MAX_MESSAGE_BYTES`, an unknown command, a malformed ``send`` or ``open``, any command
  but ``open``/``echo`` before ``open``, or a message only a server sends) is sent
  ``< error REASON >`` and disconnected; the reason is logged on logger ``tcf_hil.canbus``.
  Commands the protocol defines but this server does not implement (``add``, ``subscribe``,
  ``filter``, ``controlmode``, ``isotpmode`` ...) are answered ``< error unsupported command
  VERB >`` and the connection stays, as the daemon answers ``< error unknown command >``.
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
import math
import re
import socket
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

__all__ = [
    "DEFAULT_PORT", "MAX_MESSAGE_BYTES", "CanFrame", "Command", "MessageReader", "ServerStats",
    "SocketcandProtocolError", "SocketcandServer", "format_frame", "format_send",
    "parse_command",
]

log = logging.getLogger("tcf_hil.canbus")

DEFAULT_PORT = 29536
"""socketcand's default TCP port."""
MAX_MESSAGE_BYTES = 4096
"""Longest message (``<`` to ``>`` inclusive) accepted from a client."""
MAX_CHANNEL_CHARS = 64
DEFAULT_MAX_QUEUE = 65536
"""Frames queued per slow client before the policy applies (about 8 s of a saturated
1 Mbit/s bus, at most a few MiB)."""

_WS = b" \t\r\n"
_PRINTABLE = bytes(range(0x20, 0x7F)) + b"\t\r\n"
_HEX_ID = re.compile(r"[0-9A-Fa-f]{1,8}")
_HEX_BYTE = re.compile(r"[0-9A-Fa-f]{1,2}")
_DLC = re.compile(r"[0-9]{1,2}")
_TIMESTAMP = re.compile(r"([0-9]{1,12})\.([0-9]{6})")
_HEX_DATA = re.compile(r"(?:[0-9A-Fa-f]{2}){1,8}")
_NO_ARGS = frozenset({"rawmode", "bcmmode", "controlmode", "isotpmode", "echo", "hi", "ok"})
UNSUPPORTED_COMMANDS = frozenset({
    "add", "update", "delete", "filter", "muxfilter", "subscribe", "unsubscribe",
    "controlmode", "isotpmode", "statistics", "isotpconf", "sendpdu"})
"""Client commands of the protocol that this server answers with ``< error ... >``."""
SERVER_MESSAGES = frozenset({"hi", "ok", "frame", "error", "stat", "pdu"})
"""Messages only a server sends; a client sending one is disconnected."""
_QUICKACK: int | None = getattr(socket, "TCP_QUICKACK", None)
_FREE_ARGS = (UNSUPPORTED_COMMANDS | {"error", "stat", "pdu"}) - _NO_ARGS


class SocketcandProtocolError(ValueError):
    """A message (or byte stream) that is not acceptable socketcand; the text says why."""


@dataclass(frozen=True, slots=True)
class CanFrame:
    """A classic CAN data frame: ``can_id`` (11 or 29 bits per ``extended``), 0-8 data bytes.

    Raises:
        SocketcandProtocolError: identifier out of range or more than 8 data bytes.
    """

    can_id: int
    data: bytes = b""
    extended: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "data", bytes(self.data))
        limit = 0x1FFFFFFF if self.extended else 0x7FF
        if not 0 <= self.can_id <= limit:
            kind = "extended" if self.extended else "standard"
            raise SocketcandProtocolError(f"{kind} CAN id {self.can_id:#x} beyond {limit:#x}")
        if len(self.data) > 8:
            raise SocketcandProtocolError(f"{len(self.data)} data bytes; classic CAN has 0-8")


@dataclass(frozen=True, slots=True)
class Command:
    """One parsed message.

    ``verb`` is the first token (``open``, ``rawmode``, ``send``, ``frame``, ``echo`` ...),
    ``args`` the remaining tokens. ``channel`` is set for ``open``, ``frame`` for ``send`` and
    ``frame``, ``timestamp_us`` (microseconds) for ``frame``.
    """

    verb: str
    args: tuple[str, ...] = ()
    channel: str | None = None
    frame: CanFrame | None = None
    timestamp_us: int | None = None


def _parse_id(tok: str) -> tuple[int, bool]:
    if not _HEX_ID.fullmatch(tok):
        raise SocketcandProtocolError(f"CAN id {tok!r}: expected 1-8 hex digits")
    return int(tok, 16), len(tok) == 8


def _frame(can_id: int, data: bytes, extended: bool) -> CanFrame:
    return CanFrame(can_id, data, extended)  # validates the ranges


def _parse_send(args: tuple[str, ...]) -> CanFrame:
    if len(args) < 2:
        raise SocketcandProtocolError("send: expected '< send ID DLC [BYTE ...] >'")
    can_id, extended = _parse_id(args[0])
    if not _DLC.fullmatch(args[1]) or int(args[1]) > 8:
        raise SocketcandProtocolError(f"send: DLC {args[1]!r}; classic CAN frames only (0-8)")
    dlc, raw = int(args[1]), args[2:]
    if len(raw) != dlc:
        raise SocketcandProtocolError(f"send: DLC {dlc} but {len(raw)} data bytes")
    for b in raw:
        if not _HEX_BYTE.fullmatch(b):
            raise SocketcandProtocolError(f"send: data byte {b!r} is not 1-2 hex digits")
    return _frame(can_id, bytes(int(b, 16) for b in raw), extended)


def _parse_frame(args: tuple[str, ...]) -> tuple[CanFrame, int]:
    if len(args) not in (2, 3):
        raise SocketcandProtocolError("frame: expected '< frame ID SECS.USECS [HEX] >'")
    can_id, extended = _parse_id(args[0])
    m = _TIMESTAMP.fullmatch(args[1])
    if m is None:
        raise SocketcandProtocolError(f"frame: timestamp {args[1]!r} is not SECS.USECS")
    data = b""
    if len(args) == 3:
        if not _HEX_DATA.fullmatch(args[2]):
            raise SocketcandProtocolError(f"frame: data {args[2]!r} is not 1-8 hex bytes")
        data = bytes.fromhex(args[2])
    return _frame(can_id, data, extended), int(m[1]) * 1_000_000 + int(m[2])


def parse_command(msg: bytes) -> Command:
    """Parse one complete message, brackets included (``b"< send 123 1 ff >"``).

    Both directions are understood: client commands (``open``, ``rawmode``, ``bcmmode``,
    ``echo``, ``send`` and the protocol's other commands, whose arguments are passed through
    unchecked) and server messages (``hi``, ``ok``, ``frame``, ``error``, ``stat``, ``pdu``).

    Raises:
        SocketcandProtocolError: anything else (and nothing else is raised).
    """
    if len(msg) > MAX_MESSAGE_BYTES:
        raise SocketcandProtocolError(f"message of {len(msg)} bytes; at most "
                                      f"{MAX_MESSAGE_BYTES}")
    if msg[:1] != b"<" or msg[-1:] != b">" or len(msg) < 2:
        raise SocketcandProtocolError("a message must be '< ... >'")
    body = bytes(msg[1:-1])
    if body.translate(None, _PRINTABLE):
        raise SocketcandProtocolError("bytes that are not printable ASCII in a message")
    if b"<" in body or b">" in body:
        raise SocketcandProtocolError("'<' or '>' inside a message")
    tokens = body.decode("ascii").split()
    if not tokens:
        raise SocketcandProtocolError("empty message '< >'")
    verb, args = tokens[0], tuple(tokens[1:])
    if verb in _NO_ARGS:
        if args:
            raise SocketcandProtocolError(f"{verb}: takes no arguments")
        return Command(verb)
    if verb == "open":
        if len(args) != 1 or len(args[0]) > MAX_CHANNEL_CHARS:
            raise SocketcandProtocolError(
                f"open: expected '< open CHANNEL >' with a name of 1-{MAX_CHANNEL_CHARS} chars")
        return Command(verb, args, channel=args[0])
    if verb == "send":
        return Command(verb, args, frame=_parse_send(args))
    if verb == "frame":
        frame, t_us = _parse_frame(args)
        return Command(verb, args, frame=frame, timestamp_us=t_us)
    if verb in _FREE_ARGS:
        return Command(verb, args)
    raise SocketcandProtocolError(f"unknown command {verb[:40]!r}")


def _id_text(can_id: int, extended: bool) -> str:
    return f"{can_id:08X}" if extended else f"{can_id:03X}"


def _frame_line(frame: CanFrame, stamp: str) -> bytes:
    return (f"< frame {_id_text(frame.can_id, frame.extended)} {stamp} "
            f"{frame.data.hex().upper()} >").encode("ascii")


def _stamp(t: float) -> str:
    secs = int(t)
    usecs = round((t - secs) * 1e6)  # t - secs is exact; t * 1e6 would not be
    if usecs == 1_000_000:
        secs, usecs = secs + 1, 0
    return f"{secs}.{usecs:06d}"


_MAX_T = 999_999_999_999.0  # 12 digits of seconds, as the parser reads them


def format_frame(can_id: int, data: bytes, t: float, *, extended: bool | None = None) -> bytes:
    """``< frame ID SECS.USECS HEX >`` as the server sends it to receiving clients.

    Args:
        can_id: the identifier; ``extended`` defaults to ``can_id > 0x7FF``.
        data: 0-8 bytes.
        t: the time stamp, seconds (0 to 999 999 999 999), rounded to the nearest
            microsecond.

    Raises:
        SocketcandProtocolError: identifier or data out of range, or a bad time.
    """
    if not (math.isfinite(t) and 0 <= t <= _MAX_T):
        raise SocketcandProtocolError(f"time stamp {t!r}; expected 0 <= t < 1e12 s")
    frame = CanFrame(can_id, data, can_id > 0x7FF if extended is None else extended)
    return _frame_line(frame, _stamp(t))


def format_send(can_id: int, data: bytes, *, extended: bool | None = None) -> bytes:
    """``< send ID DLC B0 B1 ... >`` as a client sends it (lower-case unpadded bytes, like
    python-can and the protocol document)."""
    frame = CanFrame(can_id, data, can_id > 0x7FF if extended is None else extended)
    body = "".join(f" {b:x}" for b in frame.data)
    return (f"< send {_id_text(frame.can_id, frame.extended)} {len(frame.data)}{body} >"
            .encode("ascii"))


class MessageReader:
    """Splits a byte stream into ``< ... >`` messages (pure; no I/O).

    Whitespace between messages is allowed, anything else is junk. ``feed`` yields each
    complete message in order and raises :class:`SocketcandProtocolError` at the first junk,
    ``<`` inside a message, or message longer than ``max_message`` (even before its ``>``
    arrives), after yielding the messages before it. After an error the reader stays failed.
    """

    def __init__(self, max_message: int = MAX_MESSAGE_BYTES) -> None:
        self.max_message = max_message
        self._buf = b""
        self._error: SocketcandProtocolError | None = None

    @property
    def pending(self) -> int:
        """Bytes of an incomplete message held back."""
        return len(self._buf)

    def _fail(self, reason: str) -> SocketcandProtocolError:
        self._error = SocketcandProtocolError(reason)
        return self._error

    def feed(self, data: bytes) -> Iterator[bytes]:
        if self._error is not None:
            raise self._error
        buf = self._buf + bytes(data) if self._buf else bytes(data)
        self._buf = b""
        pos, n = 0, len(buf)
        try:
            while pos < n:
                start = buf.find(b"<", pos)
                gap_end = n if start < 0 else start
                if gap_end > pos and buf[pos:gap_end].strip(_WS):
                    raise self._fail("data outside '< ... >'")
                if start < 0:
                    pos = n
                    break
                end = buf.find(b">", start + 1)
                if end < 0:
                    if n - start > self.max_message:
                        raise self._fail(f"message longer than {self.max_message} bytes")
                    pos = start
                    break
                if end + 1 - start > self.max_message:
                    raise self._fail(f"message longer than {self.max_message} bytes")
                if buf.find(b"<", start + 1, end) >= 0:
                    raise self._fail("'<' inside a message")
                pos = end + 1
                yield buf[start:pos]
        finally:
            if self._error is None:
                self._buf = buf[pos:]


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
                    stamp = stamp or _stamp(time.time())
                    hub.received += 1
                    hub.relay(self, _frame_line(cmd.frame, stamp))
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
