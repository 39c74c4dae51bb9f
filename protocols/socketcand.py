"""The socketcand protocol's messages, raw mode (sans-IO: bytes in, values out and back).

The grammar (linux-can/socketcand ``doc/protocol.md``, as the daemon and python-can 4.6 speak
it). A message is ASCII between ``<`` and ``>``, tokens separated by whitespace; whitespace
between messages is allowed, anything else is not:

* the server greets ``< hi >``; the client sends ``< open CH >`` and ``< rawmode >``, each
  answered ``< ok >`` (python-can compares a single ``recv(256)`` exactly, so a server writes
  each answer on its own);
* ``< send ID DLC B0 B1 ... >``: ``ID`` is hex, 8 digits for an extended (29-bit) identifier,
  fewer for a standard one (at most 0x7FF); ``DLC`` is 0-8; each data byte is its own token of
  1-2 hex digits (python-can sends ``1 a ff``, socketcandcl sends ``01 0a ff``);
* the server sends other clients ``< frame ID SECS.USECS HEXDATA >`` (3 or 8 upper-case ID
  digits; data upper-case hex without spaces; an empty frame has two spaces before ``>``, as
  the daemon writes it and as python-can's parser needs);
* ``< echo >`` is answered ``< echo >``; ``< bcmmode >`` is answered ``< ok >``;
* ``< error REASON >``, ``< stat ... >`` and ``< pdu ... >`` are further server messages, and
  ``add``, ``subscribe``, ``filter``, ``controlmode``, ``isotpmode`` ... further client
  commands (:data:`UNSUPPORTED_COMMANDS`), whose arguments are passed through unchecked.

**Classic CAN only** (DLC 0-8, standard and extended identifiers). python-can's client has no
FD or remote-frame syntax: an FD message arrives as a ``send`` with a DLC above 8 and a remote
frame with fewer data bytes than its DLC; both are malformed (a remote frame with DLC 0 looks
like an empty data frame and is parsed as one).

Malformed is: data outside ``< ... >``, bytes that are not printable ASCII, a message over
:data:`MAX_MESSAGE_BYTES`, ``<`` or ``>`` inside a message, an empty message, an unknown
command, arguments to a command that takes none, a malformed ``send``, ``frame`` or ``open``.
Every such input raises :class:`SocketcandProtocolError` (a ``ValueError``) and nothing else.

:func:`parse_command` reads one message, :class:`MessageReader` splits a byte stream into
messages, :func:`format_frame` / :func:`encode_frame` and :func:`format_send` write the
``frame`` and ``send`` messages. The server that speaks it is ``emulators.canbus``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass

__all__ = [
    "MAX_CHANNEL_CHARS", "MAX_MESSAGE_BYTES", "SERVER_MESSAGES", "UNSUPPORTED_COMMANDS",
    "CanFrame", "Command", "MessageReader", "SocketcandProtocolError", "encode_frame",
    "format_frame", "format_send", "format_timestamp", "parse_command",
]

MAX_MESSAGE_BYTES = 4096
"""Longest message (``<`` to ``>`` inclusive) accepted from a client."""
MAX_CHANNEL_CHARS = 64
"""Longest channel name ``< open CH >`` accepts."""

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
"""Client commands of the protocol beyond raw mode (the embedded server answers them with
``< error ... >``)."""
SERVER_MESSAGES = frozenset({"hi", "ok", "frame", "error", "stat", "pdu"})
"""Messages only a server sends."""
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


def encode_frame(frame: CanFrame, stamp: str) -> bytes:
    """``< frame ID SECS.USECS HEX >`` for a frame and a time stamp already formatted by
    :func:`format_timestamp` (a server stamps every frame of one read alike)."""
    return (f"< frame {_id_text(frame.can_id, frame.extended)} {stamp} "
            f"{frame.data.hex().upper()} >").encode("ascii")


_MAX_T = 999_999_999_999.0  # 12 digits of seconds, as the parser reads them


def format_timestamp(t: float) -> str:
    """``SECS.USECS`` for ``t`` seconds (0 to 999 999 999 999), rounded to the nearest
    microsecond.

    Raises:
        SocketcandProtocolError: ``t`` out of range or not finite.
    """
    if not (math.isfinite(t) and 0 <= t <= _MAX_T):
        raise SocketcandProtocolError(f"time stamp {t!r}; expected 0 <= t < 1e12 s")
    secs = int(t)
    usecs = round((t - secs) * 1e6)  # t - secs is exact; t * 1e6 would not be
    if usecs == 1_000_000:
        secs, usecs = secs + 1, 0
    return f"{secs}.{usecs:06d}"


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
    stamp = format_timestamp(t)
    frame = CanFrame(can_id, data, can_id > 0x7FF if extended is None else extended)
    return encode_frame(frame, stamp)


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
