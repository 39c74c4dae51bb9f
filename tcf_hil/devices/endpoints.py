"""The endpoints a run owns, so that two benches on one machine never mix.

* **A sensor is a host.** Each emulated sensor gets a loopback address of its own
  (127.0.0.2, 127.0.0.3, ...; Linux routes all of 127.0.0.0/8 to ``lo`` with no set-up): its
  packets come from that address and its HTTP API answers on port 80 there, as on a real
  sensor, so ``SensorFrameSetSource(HOST)``, ``ouster-cli source HOST`` and ouster-ros's
  sensor mode need nothing else. Where port 80 cannot be bound (no root and no
  CAP_NET_BIND_SERVICE) the API falls back to a free port on that address, and the reason is
  said once.
* **Free UDP ports.** The lidar and IMU ports are 7502/7503 unless someone has bound them or
  another tcf-hil run holds them; then free ports.

Claims between tcf-hil processes are advisory ``flock`` locks on files in one directory
(``$TMPDIR/tcf-hil-endpoints``): the kernel drops them when the process ends, however it ends,
so nothing stale is ever left behind. A foreign program is seen by the bind test alone.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from tcf_hil.errors import EndpointError

__all__ = ["SensorHost", "UdpPorts", "claim_sensor_host", "lock_dir", "reserve_udp_ports"]

_FIRST_HOST, _LAST_HOST = 2, 254  # 127.0.0.2 ... 127.0.0.254
_SAID: set[str] = set()  # fall-back reasons already said in this process


def lock_dir() -> Path:
    """Where claims live (made on first use, writable by every user like /tmp itself)."""
    d = Path(os.environ.get("TCF_HIL_LOCK_DIR") or Path(tempfile.gettempdir())
             / "tcf-hil-endpoints")
    if not d.is_dir():
        with contextlib.suppress(FileExistsError):
            d.mkdir(parents=True)
        with contextlib.suppress(OSError):
            d.chmod(0o1777)
    return d


def _try_lock(name: str) -> IO[bytes] | None:
    """The lock file ``name`` held by this process, or None if another process holds it
    (or another user's file cannot be opened: then it counts as held). Files are made
    readable and writable by all and never removed (unlinking a lock file races with its
    next user); flock works on a read-only descriptor too."""
    path = lock_dir() / name
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            with contextlib.suppress(OSError):
                os.fchmod(fd, 0o666)
        except PermissionError:
            return None
    except PermissionError:
        return None
    fh = os.fdopen(fd, "rb")  # held for the claim's life
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        fh.close()
        if err.errno in (errno.EWOULDBLOCK, errno.EACCES):
            return None
        raise
    return fh


def _bind_error(family: int, kind: int, address: tuple[str, int]) -> OSError | None:
    s = socket.socket(family, kind)
    try:
        if kind == socket.SOCK_STREAM:  # as the HTTP server will (TIME_WAIT is no obstacle)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(address)
        return None
    except OSError as err:
        return err
    finally:
        s.close()


@dataclass
class SensorHost:
    """A loopback address claimed for one emulated sensor.

    ``http_port`` is 80, or 0 (a free port, chosen when the API binds) where port 80 could
    not be bound; ``note`` then says why."""

    address: str
    http_port: int
    note: str | None = None
    _lock: IO[bytes] | None = field(default=None, repr=False)

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()
            self._lock = None

    def __enter__(self) -> SensorHost:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


def claim_sensor_host(announce: Callable[[str], None] | None = None) -> SensorHost:
    """The first address 127.0.0.N (N >= 2) that no other tcf-hil process holds and whose
    port 80 is free, claimed until :meth:`SensorHost.release` (or the process ends).

    Without the privilege to bind port 80 the first free address is taken with
    ``http_port`` 0 and a ``note``; ``announce`` (a callable) gets that note once per process.

    Where port 80 is served on every address (a web server on 0.0.0.0:80) the first address
    no tcf-hil process holds is taken with ``http_port`` 0, and the note says why.

    Raises:
        EndpointError: every address 127.0.0.2-254 is held by other tcf-hil processes.
    """
    busy: SensorHost | None = None  # the first unclaimed address, if port 80 is taken on all
    served = 0  # addresses whose port 80 another program serves
    for n in range(_FIRST_HOST, _LAST_HOST + 1):
        addr = f"127.0.0.{n}"
        lock = _try_lock(f"sensor-{addr}")
        if lock is None:
            continue
        err = _bind_error(socket.AF_INET, socket.SOCK_STREAM, (addr, 80))
        if err is None or err.errno in (errno.EACCES, errno.EPERM):
            if busy is not None:
                busy.release()
        if err is None:
            return SensorHost(addr, 80, None, lock)
        if err.errno in (errno.EACCES, errno.EPERM):
            # no privilege: every address answers the same, so take this one
            note = (f"cannot bind port 80 ({err.strerror}: it needs root or "
                    "CAP_NET_BIND_SERVICE), so the sensor's HTTP API is on a free port and "
                    "clients that take a host name (ouster-sdk's SensorFrameSetSource(HOST), "
                    "ouster-cli source HOST) cannot reach it; give them the metadata file "
                    "(TCF_METADATA) instead")
            if announce is not None and note not in _SAID:
                _SAID.add(note)
                announce(note)
            return SensorHost(addr, 0, note, lock)
        if busy is None:  # a foreign server holds port 80 there: keep it, try the next
            busy = SensorHost(addr, 0, None, lock)
        else:
            lock.close()
        served += 1
        if served == 8:  # eight addresses: port 80 is taken on all (a server on 0.0.0.0)
            break
    if busy is not None:
        note = ("port 80 is served by another program on every loopback address tried, so "
                "the sensor's HTTP API is on a free port; clients that take a host name "
                "cannot reach it, give them the metadata file (TCF_METADATA) instead")
        busy.note = note
        if announce is not None and note not in _SAID:
            _SAID.add(note)
            announce(note)
        return busy
    raise EndpointError(errno.EADDRINUSE, "every loopback sensor address 127.0.0.2-254 is held "
                        f"by other tcf-hil processes (claims in {lock_dir()})")


@dataclass
class UdpPorts:
    """UDP ports on ``host`` claimed for one run (released with :meth:`release`)."""

    host: str
    ports: list[int]
    _locks: list[IO[bytes]] = field(default_factory=list, repr=False)

    def release(self) -> None:
        for fh in self._locks:
            fh.close()
        self._locks.clear()

    def __enter__(self) -> UdpPorts:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.release()


def reserve_udp_ports(host: str, preferred: list[int]) -> UdpPorts:
    """For each preferred port: itself if nobody has bound it on ``host`` and no other
    tcf-hil process holds it, else a free ephemeral port; all distinct and claimed.

    Raises:
        EndpointError: no free UDP port could be found.
    """
    got = UdpPorts(host, [])
    try:
        for want in preferred:
            for candidate in (want, *([0] * 20)):
                port = candidate
                if port == 0:
                    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    try:
                        s.bind((host, 0))
                        port = int(s.getsockname()[1])
                    finally:
                        s.close()
                if port in got.ports:
                    continue
                lock = _try_lock(f"udp-{port}")
                if lock is None:
                    continue
                if _bind_error(socket.AF_INET, socket.SOCK_DGRAM, (host, port)) is not None:
                    lock.close()
                    continue
                got.ports.append(port)
                got._locks.append(lock)
                break
            else:
                raise EndpointError(errno.EADDRINUSE, f"no free UDP port on {host}")
    except BaseException:
        got.release()
        raise
    return got
