"""The live SIC's stem worker: tile runs in a child process give the stems the frame loop
would have found itself, the job files are gone when it is done, a tile runs again only when
it is worth it, and an evicted dirty tile's last run waits for the worker, not inside a
frame."""

from __future__ import annotations

import os

import numpy as np
import pytest

from tcf_hil.sic import stem_params
from tcf_hil.sic._map import StemMap, TileJob, tile_stems
from tcf_hil.sic._worker import TileWorker


def _cylinders(centres: list[tuple[float, float]], rng: np.random.Generator, n: int = 6000
               ) -> np.ndarray:
    pts = []
    for cx, cy in centres:
        a = rng.uniform(0, 2 * np.pi, n)
        z = rng.uniform(0, 12, n)
        pts.append(np.column_stack([cx + 0.15 * np.cos(a), cy + 0.15 * np.sin(a), z]))
    g = rng.uniform(-25, 25, (40000, 2))
    pts.append(np.column_stack([g, np.zeros(len(g))]))
    return np.concatenate(pts)


def _stems(smap: StemMap) -> list[tuple[float, float, float]]:
    return sorted((round(o["cp"][0], 4), round(o["cp"][1], 4), round(o["dbh"], 4))
                  for o in smap.forest("t")["objects"])


@pytest.mark.parametrize("preset", ["field", "tuned"])
def test_the_worker_finds_what_the_frame_loop_finds(preset: str) -> None:
    rng = np.random.default_rng(3)
    centres = [(-12.0, 3.0), (0.5, 0.5), (9.5, -4.0), (15.0, 15.0)]
    cloud = _cylinders(centres, rng)
    prm = stem_params(preset)
    inline, deferred = StemMap(prm, voxel_m=0.01), StemMap(prm, voxel_m=0.01)
    deferred.defer_runs = True
    with TileWorker(prm) as w:
        for chunk in np.array_split(rng.permutation(cloud), 5):
            inline.add(chunk)
            deferred.add(chunk)
            w.pump(deferred)
        inline.update()
        w.drain(deferred, timeout=120.0)
        assert w.idle(deferred) and not w.errors and w.runs >= len(centres)
        assert os.listdir(w.folder) == []  # the child removed each job's file
    assert not os.path.exists(w.folder)
    got = _stems(deferred)
    assert got == _stems(inline)
    assert len(got) == len(centres)


def test_a_job_is_the_same_through_the_worker_and_inline() -> None:
    """The job's arrays cross to the child in a file: nothing is rounded on the way."""
    rng = np.random.default_rng(4)
    cloud = _cylinders([(2.0, 3.0)], rng)
    prm = stem_params("field")
    smap = StemMap(prm, voxel_m=0.01)
    smap.add(cloud)
    job = smap.job((0, 0))
    assert isinstance(job, TileJob)
    want = job.points.copy()
    assert want.dtype == np.float32 and len(want) == smap.stats.points
    # the map goes on (the job holds views of its blocks): the job does not change
    smap.add(_cylinders([(2.0, 3.0), (7.0, 7.0)], rng))
    np.testing.assert_array_equal(np.concatenate(list(job.pieces())), want)
    with TileWorker(prm, nice=0) as w:
        w.submit(job)
        assert w.collect(smap, timeout=120.0) == 1
    assert smap.tiles[(0, 0)].stems == tile_stems(job, prm) != []


def test_a_tile_runs_again_when_it_grew_or_the_machine_moved_away() -> None:
    rng = np.random.default_rng(5)
    prm = stem_params("field")
    smap = StemMap(prm, voxel_m=0.01)
    smap.defer_runs = True
    stem = _cylinders([(5.0, 5.0)], rng)
    here = np.array([5.0, 0.0])
    smap.add(stem[::4], here)
    job = smap.next_job()
    assert job is not None and job.tid == (0, 0)  # never run: runs
    smap.accept(job.tid, tile_stems(job, prm))
    tile = smap.tiles[(0, 0)]
    smap.add(stem[1::40], here)  # a few more (under a quarter): not worth a run yet
    assert tile.dirty and smap.next_job() is None
    assert smap.next_job(final=True) is not None  # the stream ended: every dirty tile
    smap.add(stem[2::40], here)
    assert smap.next_job() is None
    smap.add(stem[3::40], np.array([5.0, 30.0]))  # the machine moved away: it settles
    assert smap.next_job() is not None
    smap.add(stem[1::2], np.array([5.0, 30.0]))  # twice the points: worth a run
    assert tile.dirty and smap.next_job() is not None


def test_a_dirty_tile_due_for_eviction_waits_for_the_worker() -> None:
    """Over the cap, a dirty tile keeps its points until the worker has run it (not run
    inside add(), which would hold up the frame), then goes; beyond the hard cap its job is
    made at once and waits for the worker."""
    rng = np.random.default_rng(6)
    cloud = _cylinders([(-20.0, 0.0), (20.0, 0.0)], rng)
    prm = stem_params("tuned")
    smap = StemMap(prm, voxel_m=0.01, max_points=11_000)
    smap.defer_runs = True
    smap.hard_cap = 100.0
    left, right = cloud[cloud[:, 0] < 0], cloud[cloud[:, 0] >= 0]
    smap.add(left, np.array([-20.0, 0.0]))
    runs = smap.stats.tile_runs
    smap.add(right, np.array([20.0, 0.0]))  # over the cap: the left tiles are due
    assert smap.stats.tile_runs == runs and smap.stats.evicted_points == 0
    with TileWorker(prm) as w:
        w.drain(smap, timeout=120.0)
    assert smap.stats.evicted_points > 0  # gone once they ran
    held = sum(t.points for t in smap.tiles.values())
    assert smap.stats.points == held <= 11_000
    xs = sorted(round(o["cp"][0]) for o in smap.forest("t")["objects"])
    assert xs == [-20, 20]
    smap.hard_cap = 1.0  # beyond it: the job is made at once and waits for the worker
    smap.add(left + np.array([0.0, 0.0, 0.001]), np.array([20.0, 0.0]))
    assert smap.stats.held_runs > 0 and smap.backlog and smap.stats.points <= 11_000
    with TileWorker(prm) as w:
        w.drain(smap, timeout=120.0)
    assert not smap.backlog


def test_a_worker_reports_a_failed_tile_and_goes_on() -> None:
    prm = stem_params("field")
    smap = StemMap(prm, voxel_m=0.01)
    smap.add(_cylinders([(2.0, 2.0)], np.random.default_rng(7)))
    good = smap.job((0, 0))
    bad = TileJob.of((9, 9), np.ones((50, 4), np.float32), None, 10.0)  # type: ignore[arg-type]
    with TileWorker(prm, nice=0) as w:
        w.submit(bad)  # no ground grid: the child fails on it
        w.submit(good)
        while w.in_flight:
            w.collect(smap, timeout=120.0)
        assert len(w.errors) == 1 and "(9, 9)" in w.errors[0]
        assert w.proc.is_alive()
    assert len(smap.tiles[(0, 0)].stems) == 1


def test_a_drain_with_a_deadline_returns_though_the_worker_is_stalled() -> None:
    """A SIC told to stop (SIGTERM) finishes within its --finish time even where the
    worker gets no CPU (here: stopped outright, as a niced process starved by a loaded
    machine is in effect): what is in flight is left there."""
    import signal
    import time

    prm = stem_params("field")
    smap = StemMap(prm, voxel_m=0.01)
    smap.defer_runs = True
    smap.add(_cylinders([(2.0, 2.0)], np.random.default_rng(8)))
    with TileWorker(prm) as w:
        os.kill(w.proc.pid, signal.SIGSTOP)
        try:
            t0 = time.monotonic()
            w.drain(smap, until=t0 + 1.0)
            assert 0.9 <= time.monotonic() - t0 < 5.0
            assert w.in_flight and not w.idle(smap)
        finally:
            os.kill(w.proc.pid, signal.SIGCONT)
        w.drain(smap, timeout=120.0)  # let go, it finishes the tile
        assert w.idle(smap) and not w.errors
