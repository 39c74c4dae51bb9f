"""The CAN server in a process of its own: its relaying (every frame of the bus parsed and
sent on to each client) then never holds the interpreter lock of the process that starts it,
where a run's lidar sender wakes for a packet every 0.8 ms at 2048x10."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
from typing import Any

from emulators.canbus._socketcand import SocketcandServer

__all__ = ["ServerProcess"]

_START_S = 60.0  # a fresh interpreter imports asyncio and the server: well under a second


class ServerProcess:
    """A :class:`SocketcandServer` on ``host``:``port`` (0: a free port, then :attr:`port`)
    served by a spawned process until :meth:`stop` (or until the process that started it is
    gone). Raises OSError where the address cannot be bound, RuntimeError where the process
    does not start."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: no thread or lock of ours
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(host, port, child, os.getpid()),
                                 name="socketcand-server", daemon=True)
        self._proc.start()
        child.close()
        if not self._conn.poll(_START_S):
            self._kill()
            self._conn.close()
            raise RuntimeError(f"the CAN server process did not start within {_START_S:g} s")
        try:
            ok, said = self._conn.recv()
        except EOFError:
            self._kill()
            self._conn.close()
            raise RuntimeError("the CAN server process ended as it started "
                               f"(exit code {self._proc.exitcode})") from None
        if not ok:
            self._kill()
            self._conn.close()
            raise OSError(said)
        self.host, self.port = host, int(said)

    def stop(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self._conn.send("stop")
        self._proc.join(5.0)
        self._kill()
        self._conn.close()

    def _kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5.0)


def _serve(host: str, port: int, conn: Any, parent: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the starter decides when it stops (a
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # group's Ctrl-C or SIGTERM is its too)
    try:
        server = SocketcandServer(host, port).start()
    except BaseException as err:
        conn.send((False, f"{type(err).__name__}: {err}"))
        return
    conn.send((True, server.port))
    try:
        while not conn.poll(0.5) and os.getppid() == parent:
            pass
    finally:
        server.stop()
