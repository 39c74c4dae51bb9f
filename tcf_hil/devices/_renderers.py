"""The lidar run's renderer processes (forked: they share the built scene): the frame pipe
they send packed frames through (a frame number and its length, then its bytes, written from
its pieces), one worker's share of a parallel render (blocks of :data:`RENDER_BLOCK` frames
in turn, for :meth:`tcf_hil.devices.lidar.LidarRun.rendered`) and a render into the store
going on beside a run (:class:`RenderAhead`)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tcf_hil._io import name_process, read_exact, settle_heap, write_gathered
from tcf_hil.recording.store import pack_frame

if TYPE_CHECKING:
    from tcf_hil.devices.lidar import LidarRun

@dataclass
class RenderAhead:
    """A render into the store going on in a process of its own (forked: it shares the
    built scene; ``nice`` 10, below the program under test): ``done`` (shared) counts the
    frames stored, ``state`` is 0 while rendering, 1 done, 2 failed."""

    process: Any
    done: Any
    state: Any
    upto: int

    def running(self) -> bool:
        """Whether the renderer still runs (asked from any process of the run)."""
        if self.state.value != 0:
            return False
        try:
            os.kill(self.process.pid, 0)
        except OSError:
            return False
        return True

    def stop(self) -> None:
        """The renderer stopped (what it stored stays: a later render resumes it)."""
        if self.process.pid is not None and self.running():
            self.process.terminate()
        self.process.join(timeout=10.0)


RENDER_BLOCK = 10  # frames a render worker renders in a row (a second at 10 Hz)
RENDER_AHEAD_BLOCKS = 8  # blocks kept waiting for their turn, at the most (at 2048x10, ~30 MB)
RENDER_SILENT_S = 300.0  # a render worker that makes no frame this long has failed
FRAME_HEAD = struct.Struct("<qQ")  # before each packed frame a worker sends: its number
# (-1 the worker's end, -2 it failed: the reason follows) and the bytes that follow


def send_frame(fd: int, k: int, parts: list[Any]) -> None:
    """A message of :meth:`LidarRun._render_parallel`'s pipes: frame ``k`` and its bytes,
    written from its pieces as they are (a frame's few megabytes are not joined first)."""
    write_gathered(fd, [FRAME_HEAD.pack(k, sum(memoryview(p).nbytes for p in parts)),
                        *parts])


FRAME_MAX = 1 << 31  # bytes: a message claiming more is no frame (a worker cut off mid-way)


def recv_frame(fd: int) -> tuple[int, bytearray]:
    """The next :func:`send_frame` message on ``fd``, read straight into one buffer."""
    k, n = FRAME_HEAD.unpack(read_exact(fd, FRAME_HEAD.size))
    if n > FRAME_MAX or k < -2:
        raise EOFError(f"not a frame message (frame {k}, {n} bytes)")
    return k, read_exact(fd, n)


def widen_pipe(fd: int) -> None:
    """A frame's records (a few MB) through a pipe of 1 MiB where the system allows it, not
    Linux's default 64 KiB: fewer reads and wake-ups in the parent for each frame."""
    with contextlib.suppress(OSError, AttributeError, ValueError):
        cap = int(Path("/proc/sys/fs/pipe-max-size").read_text())
        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, min(cap, 1 << 20))


def render_part(run: LidarRun, start: int, i: int, workers: int, fd: int,
                 readers: list[int], end: int, compress: bool = True) -> None:
    """Renderer ``i`` of ``workers`` of :meth:`LidarRun._render_parallel`: blocks ``i``,
    ``i + workers``, ... of :data:`RENDER_BLOCK` frames from ``start`` to ``end``, each frame
    packed (``compress``; else its record as is) and sent, then its end mark. No fault plan
    runs here (a frame's bytes follow from its index); the ray threads are shared out among
    the workers."""
    name_process(f"tcf-render-{i}")
    settle_heap()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when it stops
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    for r in readers:  # the parent's read ends (forked here): with them closed, a parent
        os.close(r)  # that is gone breaks this worker's pipe instead of blocking it for ever
    parent = os.getppid()
    try:
        caster = run.scene.caster
        if caster.threads is not None:
            caster.threads = max(1, caster.threads // workers)
        run.emu.threads = max(1, run.emu.threads // workers)
        a = start + i * RENDER_BLOCK
        while a < end:
            for rf in run.compact_frames(a, min(a + RENDER_BLOCK, end)):
                if os.getppid() != parent:
                    return
                send_frame(fd, rf.k, [pack_frame(rf, run.ports)] if compress
                            else rf.encode_parts(run.ports))
            a += workers * RENDER_BLOCK
        send_frame(fd, -1, [])
    except BaseException as err:
        with contextlib.suppress(Exception):
            send_frame(fd, -2, [f"{type(err).__name__}: {err}".encode()])
    finally:
        os.close(fd)
