"""Run a command on a pseudo-terminal, as a person's shell runs it, and read back what the
terminal showed (for the live displays, which are quiet when not on a terminal)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import pty
import re
import select
import signal
import struct
import subprocess
import termios
import time
from collections.abc import Sequence

_ESCAPES = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


def run_in_terminal(argv: Sequence[str], *, env: dict[str, str] | None = None,
                    timeout: float = 400, columns: int = 240) -> tuple[int, list[str]]:
    """(exit status, the screen's lines in the order drawn: escape sequences removed, every
    redraw of the live display a line of its own). Stops the command after ``timeout``."""
    master, slave = pty.openpty()
    env = dict(env if env is not None else os.environ, TERM="xterm-256color",
               COLUMNS=str(columns))
    buf = bytearray()
    p: subprocess.Popen[bytes] | None = None
    try:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 60, columns, 0, 0))
        p = subprocess.Popen(list(argv), stdin=slave, stdout=slave, stderr=slave, env=env,
                             close_fds=True, start_new_session=True)
        os.close(slave)
        slave = -1
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # the other side closed (Linux: EIO)
                    break
                if not chunk:
                    break
                buf += chunk
            elif p.poll() is not None:
                break
        rc = p.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if p is not None and p.poll() is None:  # the whole session: SIC, producer, workers
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        os.close(master)
        if slave >= 0:
            os.close(slave)
    text = _ESCAPES.sub("", buf.decode("utf-8", "replace"))
    return rc, [line for line in re.split(r"[\r\n]+", text) if line.strip()]
