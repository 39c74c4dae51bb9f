"""The stem algorithm in a process of its own, at a lower priority than the frames.

A live SIC must take every frame at the sensor's rate (10 or 20 Hz) however long the stem
algorithm takes on a tile (a second or more on a dense natural stand): run inline, one long
tile run holds up the frames behind it until the receiver's queue overflows. Here the frame
loop hands tile runs (:class:`~tcf_hil.sic._map.TileJob`: a tile's points and the ground
grid under them) to a child process and takes their stems back when they are done. The points
go in a file on the RAM disk, not through the pipe: a pipe holds 64 KiB and would block the
frame loop until the busy child read them. The child runs at a lower scheduling priority
(``nice``), so on one core the kernel gives the frames the CPU when they need it and the
tile runs the rest.

The child is started with ``spawn`` (the SIC has threads, the receiver's and canopen's, which
``fork`` would copy half-way), with one BLAS/OpenMP thread.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import queue
import shutil
import signal
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from tcf_hil.sic._circle import use_compiled_fits
from tcf_hil.sic._fitkernels import warm as warm_fits
from tcf_hil.sic._map import GroundGrid, StemMap, TileJob, tile_stems
from tcf_hil.sic._params import StemParams

# one thread for numpy's BLAS/LAPACK and OpenMP in the child: the point is one core's share
_ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "NUMBA_NUM_THREADS": "1"}


def _write_job(job: TileJob, folder: str) -> tuple[str, int]:
    """The job's points in a file of their own in ``folder`` (a RAM disk where there is one),
    a block at a time; returns the path and how many points. A pipe holds 64 KiB, and a
    tile's points (megabytes) sent through it would hold the frame loop until the busy child
    reads them."""
    fd, path = tempfile.mkstemp(prefix="tcf-sic-tile-", suffix=".f32", dir=folder)
    n = 0
    try:
        with os.fdopen(fd, "wb") as f:
            for piece in job.pieces():
                np.ascontiguousarray(piece, dtype=np.float32).tofile(f)
                n += len(piece)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(path)
        raise
    return path, n


def _read_job(path: str, tid: tuple[int, int], n: int, ground: GroundGrid,
              tile_m: float) -> TileJob:
    pts = np.fromfile(path, dtype=np.float32, count=4 * n).reshape(n, 4)
    return TileJob.of(tid, pts, ground, tile_m)


def _serve(conn: Connection, params: StemParams, nice: int) -> None:
    """The child: tile jobs in (a file, read and removed), (tile id, stems, CPU seconds)
    out, until None or EOF."""
    # the SIC's own SIGTERM/SIGINT (a bench ending the run signals the process group) is
    # the parent's to handle: it drains this worker, then closes it; a parent that dies
    # closes the pipe, which ends this loop
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    # the fits compiled (the same stems, 1.8x faster), compiled now, while the first tile
    # gathers its points: a cold compile here delays at most the first tile's stems, never
    # a frame (the frame loop is the parent's)
    use_compiled_fits()
    try:
        warm_fits()
    except Exception:  # no working kernels here: the fits stay in numpy
        use_compiled_fits(False)
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        path, tid, n, ground, tile_m = msg
        t0 = time.process_time()
        try:
            job = _read_job(path, tid, n, ground, tile_m)
            with contextlib.suppress(OSError):
                os.unlink(path)
            stems = tile_stems(job, params)
        except Exception as e:  # one bad tile must not end the SIC
            conn.send((tid, None, f"{type(e).__name__}: {e}"))
            continue
        conn.send((tid, stems, time.process_time() - t0))


class TileWorker:
    """A child process that runs a :class:`StemMap`'s tile jobs; at most ``depth`` in flight
    (two: the child starts the next as soon as it sends a result, without waiting for the
    frame loop to notice).

    ``pump(smap)`` (after each frame): takes finished runs into the map and hands it the
    next jobs. ``drain(smap, timeout)``: the end of the stream, every dirty tile run."""

    def __init__(self, params: StemParams, *, nice: int = 10, depth: int = 2) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        saved = {k: os.environ.get(k) for k in _ONE_THREAD}
        os.environ.update(_ONE_THREAD)  # the child's environment is the parent's at start
        try:
            self.proc = ctx.Process(target=_serve, args=(child, params, nice), daemon=True,
                                    name="tcf-sic-stems")
            self.proc.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        child.close()
        # the job files: a folder of this worker's own, on the RAM disk where there is one
        ram = "/dev/shm" if os.access("/dev/shm", os.W_OK) else None
        self.folder = tempfile.mkdtemp(prefix="tcf-sic-stems-", dir=ram)
        self.depth = depth
        self.in_flight: deque[tuple[int, int]] = deque()
        self.errors: list[str] = []
        # the feeder thread writes the jobs' files and sends them: the frame loop only
        # hands it a job (views of the map's blocks), and a big tile's megabytes are copied
        # a block at a time beside the frames, not in one of them
        self._jobs: queue.SimpleQueue[TileJob | None] = queue.SimpleQueue()
        self._failed: deque[tuple[Any, Any, Any]] = deque()  # (tile, None, why)
        self._feeder = threading.Thread(target=self._feed, name="tcf-sic-feeder", daemon=True)
        self._feeder.start()
        self.cpu_s = 0.0
        self.runs = 0

    @property
    def busy(self) -> bool:
        return len(self.in_flight) >= self.depth

    def _feed(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            path = None
            try:
                path, n = _write_job(job, self.folder)
                # the ground grid (a few cells) goes through the pipe
                self._conn.send((path, job.tid, n, job.ground, job.tile_m))
            except Exception as e:  # a full RAM disk, a closed pipe: that tile fails
                if path is not None:
                    with contextlib.suppress(OSError):
                        os.unlink(path)
                self._failed.append((job.tid, None, f"{type(e).__name__}: {e}"))
            job = None  # its blocks go once the map lets them go

    def collect(self, smap: StemMap, timeout: float = 0.0) -> int:
        """Take the finished runs into ``smap`` (waiting up to ``timeout`` for the first);
        returns how many."""
        n = 0
        while self.in_flight:
            result: tuple[Any, Any, Any]
            if self._failed:
                result = self._failed.popleft()
            elif self._conn.poll(timeout if n == 0 else 0.0):
                try:
                    result = self._conn.recv()
                except EOFError:
                    raise RuntimeError("the stem worker process ended") from None
            else:
                break
            tid, stems, cost = result
            self.in_flight.remove(tid)
            n += 1
            if stems is None:
                self.errors.append(f"tile {tid}: {cost}")
                continue
            self.cpu_s += cost
            self.runs += 1
            smap.accept(tid, stems, cost)
        return n

    def pump(self, smap: StemMap, *, final: bool = False) -> int:
        """Take finished runs, then hand out jobs up to the depth (``final``: every dirty
        tile, the stream has ended); returns runs taken."""
        n = self.collect(smap)
        while not self.busy:
            job = smap.next_job(final=final)
            if job is None:
                break
            self.submit(job)
        return n

    def submit(self, job: TileJob) -> None:
        """Hand ``job`` to the worker (its file is written beside the frame loop)."""
        if not self.proc.is_alive():
            raise RuntimeError(f"the stem worker process ended (exit {self.proc.exitcode})")
        self.in_flight.append(job.tid)
        self._jobs.put(job)

    def idle(self, smap: StemMap) -> bool:
        """Nothing in flight and nothing left to run."""
        return not self.in_flight and not smap.backlog and not smap.dirty_tiles()

    def drain(self, smap: StemMap, timeout: float = math.inf,
              progress: Callable[[], None] | None = None, every_s: float = 2.0,
              until: float = math.inf) -> int:
        """Run until nothing is dirty or in flight, waiting at most ``timeout`` for each
        result, calling ``progress`` every ``every_s`` while runs are left (a SIC publishes
        its forest so far), or until ``time.monotonic()`` reaches ``until`` (what is in
        flight then is left); returns runs taken."""
        n = 0
        waited = 0.0
        next_call = time.monotonic() + every_s
        while True:
            if time.monotonic() >= until:
                return n
            n += self.pump(smap, final=True)
            if not self.in_flight:
                return n
            got = self.collect(smap, 0.1)
            if got:
                n, waited = n + got, 0.0
            elif not self.proc.is_alive():
                raise RuntimeError("the stem worker process ended")
            else:
                waited += 0.1
                if waited >= timeout:
                    raise RuntimeError(f"the stem worker gave no result in {timeout:g} s")
            if progress is not None and time.monotonic() >= next_call and not self.idle(smap):
                progress()
                next_call = time.monotonic() + every_s

    def close(self, timeout: float = 2.0) -> None:
        self._jobs.put(None)
        self._feeder.join(timeout)
        if self._feeder.is_alive():  # writing a big job, or blocked on a child that hangs
            self.proc.kill()
            self._feeder.join(timeout)
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(None)
        self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(timeout)
        self._conn.close()
        shutil.rmtree(self.folder, ignore_errors=True)  # with jobs the child never read

    def __enter__(self) -> TileWorker:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
