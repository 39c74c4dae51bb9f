"""CAN bus specifications (``--can SPEC``) and how to open them with python-can.

``SPEC`` is ``INTERFACE:ARGS``:

=====================================  ======================================================
``auto``                               ``socketcan:vcan0`` where the kernel has it, otherwise
                                       the socketcand server on 127.0.0.1:29536 (joined if one
                                       answers there, else started in this process)
``socketcan:vcan0``                    a kernel SocketCAN interface
``socketcand:HOST:PORT:CHANNEL``       a socketcand server (ours: ``tcf-hil can-server``)
``virtual:NAME``                       python-can's in-process bus (one process only)
``udp_multicast:GROUP``                python-can's multicast bus; refused while a default route
                                       exists (it would leave the machine): only inside a
                                       network namespace made for it (``unshare -n``)
=====================================  ======================================================
"""

from __future__ import annotations

import contextlib
import select
import socket
import subprocess
from dataclasses import dataclass, field
from typing import Any

import can

from emulators.canbus import DEFAULT_PORT

DEFAULT_SOCKETCAND_PORT = DEFAULT_PORT  # the CAN server's (tcf-hil can-server)


class BusSpecError(ValueError):
    """A ``--can`` value that cannot be used; the message says what is accepted."""


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str
    host: str = ""
    port: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus`` (and ``canopen.Network.connect``)."""
        kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel, **self.extra}
        if self.interface == "socketcand":
            kw.update(host=self.host, port=self.port)
        return kw

    def precheck(self) -> None:
        """Fail at once where python-can would retry, printing a line per try, for 10 s: a
        socketcand server that does not answer.

        Raises:
            can.CanInitializationError: nobody greets at host:port.
        """
        if self.interface == "socketcand" and not socketcand_answers(self.host, self.port, 1.0):
            raise can.CanInitializationError(
                f"no socketcand server answers at {self.host}:{self.port} (start one with "
                f"'tcf-hil can-server --port {self.port}', or use --can auto)")

    def open(self) -> can.BusABC:
        """``can.Bus`` for this spec, after :meth:`precheck`."""
        self.precheck()
        return can.Bus(**self.kwargs())

    def __str__(self) -> str:
        if self.interface == "socketcand":
            return f"socketcand:{self.host}:{self.port}:{self.channel}"
        return f"{self.interface}:{self.channel}"


_FORMS = ("auto, socketcan:IFACE, socketcand:HOST:PORT:CHANNEL, virtual:NAME, "
          "udp_multicast:GROUP")


def parse_bus_spec(spec: str) -> BusSpec | None:
    """The spec as a :class:`BusSpec`; ``None`` for ``auto`` (see :func:`resolve_auto`)."""
    s = spec.strip()
    if s == "auto":
        return None
    iface, _, rest = s.partition(":")
    if iface == "socketcan" and rest:
        return BusSpec("socketcan", rest)
    if iface == "virtual" and rest:
        return BusSpec("virtual", rest, extra={"receive_own_messages": False})
    if iface == "socketcand":
        parts = rest.split(":")
        if len(parts) == 3 and parts[1].isdigit() and 0 < int(parts[1]) < 65536:
            return BusSpec("socketcand", parts[2], parts[0], int(parts[1]))
        raise BusSpecError(f"--can {spec!r}: expected socketcand:HOST:PORT:CHANNEL, "
                           f"e.g. socketcand:127.0.0.1:{DEFAULT_SOCKETCAND_PORT}:vcan0")
    if iface == "udp_multicast" and rest:
        refuse_multicast_in_host_namespace()
        return BusSpec("udp_multicast", rest, extra={"fd": False})
    raise BusSpecError(f"--can {spec!r}: expected one of {_FORMS}")


def refuse_multicast_in_host_namespace() -> None:
    """udp_multicast is only safe where no route leads off the machine."""
    try:
        routes = subprocess.run(["ip", "route", "show", "default"], capture_output=True,
                                text=True, timeout=5).stdout
        routes += subprocess.run(["ip", "-6", "route", "show", "default"], capture_output=True,
                                 text=True, timeout=5).stdout
    except (OSError, subprocess.SubprocessError) as e:
        raise BusSpecError(f"udp_multicast: cannot check the routes ({e}); refusing") from e
    if routes.strip():
        raise BusSpecError("udp_multicast refused: a default route exists (host network "
                           "namespace?), so multicast would leave the machine; run inside "
                           "'unshare -n' with 'ip route add 224.0.0.0/4 dev lo'")


def kernel_has_vcan(channel: str = "vcan0") -> bool:
    """True if a SocketCAN interface ``channel`` exists and a CAN_RAW socket opens."""
    try:
        s = socket.socket(socket.PF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (OSError, AttributeError):
        return False
    with contextlib.closing(s):
        try:
            s.bind((channel,))
        except OSError:
            return False
    return True


def socketcand_answers(host: str, port: int, timeout: float = 0.5) -> bool:
    """True if a socketcand server greets with ``< hi >`` at host:port."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            return s.recv(16).startswith(b"< hi >")
    except OSError:
        return False


def peer_closed(bus: can.BusABC) -> bool:
    """True if ``bus`` is a socketcand client whose server closed the connection.

    python-can's socketcand client treats the end of its TCP stream as "no message yet": its
    ``recv`` spins until the timeout and returns None, for ever, and never raises. A receive-only
    client therefore has to look for itself (sending clients get EPIPE soon enough)."""
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if not isinstance(sock, socket.socket) or sock.fileno() < 0:
        return False
    try:
        readable, _, _ = select.select([sock], [], [], 0)
        return bool(readable) and sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True
