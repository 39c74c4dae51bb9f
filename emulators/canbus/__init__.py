"""A shared CAN bus without kernel CAN: an embedded server speaking the socketcand protocol
(raw mode) on 127.0.0.1, so python-can programs in separate processes join one bus with
``can.Bus(interface="socketcand", host="127.0.0.1", port=P, channel="vcan0")``.

The protocol's pure parser/formatter lives in :mod:`protocols.socketcand`; its names are
re-exported here for compatibility (import them from ``protocols.socketcand``)."""

from emulators.canbus._process import ServerProcess
from emulators.canbus._socketcand import DEFAULT_PORT, ServerStats, SocketcandServer
from protocols.socketcand import (
    MAX_MESSAGE_BYTES,
    CanFrame,
    Command,
    MessageReader,
    SocketcandProtocolError,
    format_frame,
    format_send,
    parse_command,
)

__all__ = ["DEFAULT_PORT", "MAX_MESSAGE_BYTES", "CanFrame", "Command", "MessageReader",
           "ServerProcess", "ServerStats", "SocketcandProtocolError", "SocketcandServer",
           "format_frame", "format_send", "parse_command"]
