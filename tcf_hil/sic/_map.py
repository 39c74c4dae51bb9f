"""The onboard SIC's world model: a ground grid (running minimum per 1 m cell, the paper's
ground filter kept incrementally), a bounded voxel map of the points above it, split into
square tiles, and the stem algorithm re-run only on tiles that got new points.

Pure numpy/scipy on arrays; no I/O. Coordinates are local: world minus the pose datum, so
float32 storage loses nothing (micrometres over kilometres).
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocols.stems import QUALITY_BY_CLASS
from tcf_hil.sic._fast import column_min, finite_rows, offset_key, run_starts, sorted_with_order
from tcf_hil.sic._stems import StemParams, identify_stems

FloatArray = NDArray[np.float64]


def _minmod(a: FloatArray, b: FloatArray) -> FloatArray:
    """The smaller of two slopes when they agree in sign, else 0 (NaN counts as missing)."""
    a = np.where(np.isfinite(a), a, b)
    b = np.where(np.isfinite(b), b, a)
    out = np.where(a * b > 0, np.where(np.abs(a) < np.abs(b), a, b), 0.0)
    return np.where(np.isfinite(out), out, 0.0)


class GroundGrid:
    """Minimum z per ``cell`` x ``cell`` m square, on a grid that grows as the map does.

    ``slope``: on a hillside a cell's minimum lies at its downhill edge, up to
    ``cell * tan(slope)`` below the ground under a point at its uphill edge (0.58 m for a
    1 m cell at 30 degrees: the ground then passes for stems). With ``slope``, the height
    under a point is the cell's plane instead: its gradient from the neighbouring cells'
    minima (minmod of the two one-sided differences: exact on a plane, and one neighbour
    whose minimum is a stem, not ground, cannot tilt it), through the minimum at the cell's
    downhill corner. At the edge of the seen area, where a cell has one neighbour along an
    axis, that one difference is taken as it is; gradients are clamped to ``max_gradient``
    (63 degrees, above the steepest scenario hillside).
    """

    def __init__(self, cell_m: float = 1.0, *, slope: bool = False,
                 max_gradient: float = 2.0) -> None:
        self.cell = cell_m
        self.slope = slope
        self.max_gradient = max_gradient
        self.i0 = self.j0 = 0
        self.z = np.full((0, 0), np.inf)
        self._grad: tuple[FloatArray, FloatArray] | None = None

    def _ij(self, xy: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        ij = np.floor(xy / self.cell).astype(np.int64)
        return ij[:, 0], ij[:, 1]

    def _grow(self, i: NDArray[np.int64], j: NDArray[np.int64]) -> None:
        ni, nj = self.z.shape
        lo_i, hi_i = min(int(i.min()), self.i0), max(int(i.max()) + 1, self.i0 + ni)
        lo_j, hi_j = min(int(j.min()), self.j0), max(int(j.max()) + 1, self.j0 + nj)
        if (lo_i, hi_i, lo_j, hi_j) == (self.i0, self.i0 + ni, self.j0, self.j0 + nj):
            return
        # grow by a margin so that a moving machine does not reallocate every frame
        pad = 32
        lo_i, lo_j = lo_i - pad, lo_j - pad
        hi_i, hi_j = hi_i + pad, hi_j + pad
        z = np.full((hi_i - lo_i, hi_j - lo_j), np.inf)
        z[self.i0 - lo_i:self.i0 - lo_i + ni, self.j0 - lo_j:self.j0 - lo_j + nj] = self.z
        self.z, self.i0, self.j0 = z, lo_i, lo_j

    def add(self, pts: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Take the points' z into their cells' minima; returns their cells (i, j), which
        :meth:`height` can be given for the same points."""
        i, j = self._ij(pts[:, :2])
        if len(pts) == 0:
            return i, j
        self._grow(i, j)
        # by flat index into the C-contiguous grid (a view): numpy's ufunc.at is ten times
        # faster on one index array than on two
        f = (i - self.i0) * self.z.shape[1] + (j - self.j0)
        np.minimum.at(self.z.reshape(-1), f, pts[:, 2])
        self._grad = None
        return i, j

    def _gradient(self) -> tuple[FloatArray, FloatArray]:
        if self._grad is None:
            z = np.where(np.isfinite(self.z), self.z, np.nan)
            g = []
            for axis in (0, 1):
                d = np.diff(z, axis=axis) / self.cell
                pad = [(0, 0), (0, 0)]
                pad[axis] = (1, 0)
                back = np.pad(d, pad, constant_values=np.nan)
                pad[axis] = (0, 1)
                fwd = np.pad(d, pad, constant_values=np.nan)
                g.append(np.clip(_minmod(back, fwd), -self.max_gradient, self.max_gradient))
            self._grad = (g[0], g[1])
        return self._grad

    def height(self, xy: FloatArray,
               ij: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None) -> FloatArray:
        """Ground height under each point: its cell's minimum, or with ``slope`` the cell's
        plane (inf where the cell is unseen). ``ij``: the points' cells, as :meth:`add`
        returned them for the same points."""
        if len(xy) == 0:
            return np.zeros(0)
        i, j = self._ij(xy) if ij is None else ij
        ni, nj = self.z.shape
        a, b = i - self.i0, j - self.j0
        ok = (a >= 0) & (a < ni) & (b >= 0) & (b < nj)
        every = bool(ok.all())  # as a rule: the points of a frame just added
        if not every:
            xy, i, j, a, b = xy[ok], i[ok], j[ok], a[ok], b[ok]
        f = a * nj + b  # flat cell index (the grids are C-contiguous)
        h = self.z.ravel().take(f)
        if self.slope and len(f):
            gx, gy = self._gradient()
            sx, sy = gx.ravel().take(f), gy.ravel().take(f)
            # offsets from the cell centre, in [-cell/2, cell/2)
            u = xy[:, 0] - (i + 0.5) * self.cell
            v = xy[:, 1] - (j + 0.5) * self.cell
            h += 0.5 * self.cell * (np.abs(sx) + np.abs(sy)) + sx * u + sy * v
        if every:
            return h
        out = np.full(len(ok), np.inf)
        out[ok] = h
        return out


@dataclass
class TileJob:
    """One run of the stem algorithm on a tile: its points and its border's (x, y, z, edge
    half width; float32, local metres), the ground height under each, and the tile's id and
    size (its stems are those whose centre lies inside it). Pickles small (two arrays), for a
    worker process."""

    tid: tuple[int, int]
    points: NDArray[np.float32]
    ground_z: FloatArray
    tile_m: float


def tile_stems(job: TileJob, params: StemParams) -> list[dict[str, Any]]:
    """The stems of a tile run: the stem algorithm on the job's points, those whose centre
    lies inside the tile."""
    if len(job.points) == 0:
        return []
    pts = job.points.astype(np.float64)
    doc = identify_stems(pts[:, :3], params, ground_z=job.ground_z, widths=pts[:, 3])
    x0, y0 = job.tid[0] * job.tile_m, job.tid[1] * job.tile_m
    return [o for o in doc["objects"]
            if x0 <= o["cp"][0] < x0 + job.tile_m and y0 <= o["cp"][1] < y0 + job.tile_m]


@dataclass
class _Tile:
    chunks: list[NDArray[np.float32]] = field(default_factory=list)
    points: int = 0  # after the last compaction
    pending: int = 0  # in chunks not yet compacted
    dirty: bool = False
    stems: list[dict[str, Any]] = field(default_factory=list)
    basis: int = 0  # the tile's own points its stems were found on
    evicted: bool = False  # lost its points since its stems were found
    run_distance: float = 0.0  # from the machine, when it last ran
    keys: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    runs: list[NDArray[np.int64]] = field(default_factory=list)
    # ^ the voxel keys of the compacted points (chunks[:ncompact]): sorted runs, the big one
    # and the recent ones' (merged as they grow)
    ncompact: int = 0  # chunks[:ncompact] are compacted, the rest pending
    vox: list[NDArray[np.int64]] = field(default_factory=list)  # the pending chunks' voxels


@dataclass
class MapStats:
    points: int = 0
    tiles: int = 0
    evicted_points: int = 0
    tile_runs: int = 0
    tile_seconds: float = 0.0
    held_runs: int = 0  # dirty tiles evicted over the hard cap, their last run held


class StemMap:
    """Points above the ground (x, y, z and the edge half width), one per ``voxel_m`` cube and
    kind, in ``tile_m`` tiles.

    ``add`` takes a frame's points (each tile keeps the new voxels' points at once, against
    its sorted keys: a frame's cost follows the frame, not the tile); ``update`` re-runs the
    stem algorithm on dirty tiles (each with a ``margin_m`` border from its neighbours,
    keeping the stems whose centre lies inside it) for at most ``budget_s``; or a worker
    process takes them (``defer_runs``, :meth:`next_job`, :meth:`accept`); ``forest``
    assembles the observed document. The map holds at most ``max_points``: beyond that the
    tiles farthest from the machine lose their points (their stems stay: the sensor hardly
    reaches them now). Such a tile runs again only once it holds more points than its stems
    were found on.
    """

    def __init__(self, params: StemParams, *, voxel_m: float = 0.03, tile_m: float = 10.0,
                 margin_m: float = 1.5, max_points: int = 6_000_000,
                 datum: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        if not (voxel_m > 0 and tile_m > 2 * margin_m > 0):
            raise ValueError("voxel_m > 0 and tile_m > 2 * margin_m > 0 required")
        self.params = params
        self.voxel = voxel_m
        self.tile = tile_m
        self.margin = margin_m
        self.max_points = max_points
        self.datum = np.asarray(datum, dtype=np.float64)
        self.ground = GroundGrid(params.ground_cell_m, slope=params.ground_slope)
        self.tiles: dict[tuple[int, int], _Tile] = {}
        self.stats = MapStats()
        self._last_xy = np.zeros(2)
        # tile runs done elsewhere (a worker process, :mod:`tcf_hil.sic._worker`): a dirty
        # tile due for eviction keeps its points until the worker ran it (up to hard_cap
        # times max_points), instead of running inside add()
        self.defer_runs = False
        self.hard_cap = 1.5
        self.backlog: collections.deque[TileJob] = collections.deque()
        self.rerun_growth = 0.25  # next_job: a tile runs again once it grew by this share
        self.settle_m = 5.0  # ... or the machine moved this far away from it

    # -- input ------------------------------------------------------------------------------
    def add(self, pts: FloatArray, sensor_xy: FloatArray | None = None,
            widths: NDArray[np.floating] | None = None) -> int:
        """Add a frame's points (local metres, (n, 3)) and their edge half widths (n,: 0 for
        a return whose footprint one surface filled; None: all 0); returns how many were
        above ground. A voxel keeps its first return of each kind (edge or not), so an edge
        return does not hide the clean returns that come later."""
        w = np.zeros(len(pts)) if widths is None else np.asarray(widths, np.float64)
        fin = finite_rows(pts)
        if fin is not None:
            pts, w = pts[fin], w[fin]
        if sensor_xy is not None:
            self._last_xy = np.asarray(sensor_xy, dtype=np.float64)
        if len(pts) == 0:
            return 0
        gz = self.ground.height(pts[:, :2], self.ground.add(pts))
        above = pts[:, 2] > gz + self.params.ground_threshold_m
        keep = np.column_stack([pts[above], w[above]])
        if len(keep) == 0:
            return 0
        # one point per voxel within the frame (the first), then per tile; the voxels keyed
        # from the frame's own corner, so that the packed sort has room for the index
        vox = self._voxels(keep)
        sk, order = sorted_with_order(offset_key(vox))
        sel = np.sort(order[run_starts(sk)])
        keep, vox = keep[sel], vox[sel]
        t = np.floor(keep[:, :2] / self.tile).astype(np.int64)
        t0 = column_min(t)
        nj = int(t[:, 1].max() - t0[1]) + 1
        _, order = sorted_with_order((t[:, 0] - t0[0]) * nj + (t[:, 1] - t0[1]))  # by tile
        keep, t, vox = keep[order], t[order], vox[order]
        starts = np.flatnonzero(np.r_[True, (t[1:, 0] != t[:-1, 0]) | (t[1:, 1] != t[:-1, 1])])
        ends = np.r_[starts[1:], len(keep)]
        f32 = keep.astype(np.float32)
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            tid = (int(t[a, 0]), int(t[a, 1]))
            tile = self.tiles.get(tid)
            if tile is None:
                tile = self.tiles[tid] = _Tile()
            tile.chunks.append(f32[a:b])
            # the voxels of the points as they came (float64), not of their float32 copies
            tile.vox.append(vox[a:b])
            tile.pending += b - a
            self.stats.points += b - a
            fresh = self._absorb(tile)
            if not tile.evicted:
                tile.dirty = tile.dirty or fresh > 0
            elif not tile.dirty and tile.points > tile.basis:
                # a tile that lost its points runs again once it holds more than its stems
                # were found on (a few far returns must not replace them)
                tile.dirty = True
        if self.stats.points > self.max_points:
            self._evict()
        return len(keep)

    def _voxels(self, pts: NDArray[np.floating]) -> NDArray[np.int64]:
        """Voxel indices of (n, 4) points (x, y, z, edge half width; (n, 3): no edge
        returns); z doubled, plus 1 for an edge return."""
        v = np.floor(np.asarray(pts[:, :3], dtype=np.float64) / self.voxel).astype(np.int64)
        v[:, 2] = 2 * v[:, 2] + (pts[:, 3] > 0 if pts.shape[1] > 3 else 0)
        v += 1 << 20  # 21 bits a coordinate: +-31 km at 3 cm (z: +-15 km)
        return v

    @staticmethod
    def _keys_of(v: NDArray[np.int64]) -> NDArray[np.int64]:
        return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]

    def _absorb(self, tile: _Tile) -> int:
        """Take the tile's pending chunks in: the points of voxels it does not hold yet (the
        first of each), in the order they came, appended as one compacted chunk; returns how
        many. Their keys go into sorted runs of decreasing size (``keys``, then ``runs``),
        merged as they grow: a frame's cost grows with the frame's points, not with the
        tile's (a tile beside the track holds millions)."""
        if tile.pending == 0:
            return 0
        rest = tile.chunks[tile.ncompact:]
        new = rest[0] if len(rest) == 1 else np.concatenate(rest)
        if len(tile.vox) == len(rest):
            v = tile.vox[0] if len(rest) == 1 else np.concatenate(tile.vox)
        else:  # chunks that came without their voxels
            v = self._voxels(new)
        tile.vox = []
        nk = self._keys_of(v)
        # stable: the first of equal keys first; sorted by the voxels' offsets from the
        # chunk's corner (the same order as the keys'), which leave the packed sort room
        _, order = sorted_with_order(offset_key(v))
        sk = nk[order]
        first = run_starts(sk)
        uk, ui = sk[first], order[first]
        for run in (tile.keys, *tile.runs):
            if len(run) and len(uk):
                fresh = run[np.minimum(np.searchsorted(run, uk), len(run) - 1)] != uk
                uk, ui = uk[fresh], ui[fresh]
        if len(uk):
            # a new run; runs merge while the newer is a quarter of the older or more (a
            # log-structured merge: a frame's merges are small, the big ones rare), the
            # stable sort (timsort) merging two sorted runs in one pass
            tile.runs.append(uk)
            while len(tile.runs) >= 2 and 4 * len(tile.runs[-1]) >= len(tile.runs[-2]):
                b = tile.runs.pop()
                tile.runs[-1] = np.sort(np.concatenate([tile.runs[-1], b]), kind="stable")
            if 4 * len(tile.runs[0]) >= len(tile.keys):
                tile.keys = np.sort(np.concatenate([tile.keys, tile.runs.pop(0)]),
                                    kind="stable")
        pts = new[np.sort(ui)]
        self.stats.points -= tile.pending - len(pts)
        tile.chunks = tile.chunks[:tile.ncompact] + ([pts] if len(pts) else [])
        tile.ncompact = len(tile.chunks)
        tile.points += len(pts)
        tile.pending = 0
        return len(pts)

    @staticmethod
    def _merge_keys(tile: _Tile) -> None:
        if tile.runs:
            tile.keys = np.sort(np.concatenate([tile.keys, *tile.runs]), kind="stable")
            tile.runs = []

    def _compact(self, tile: _Tile) -> NDArray[np.float32]:
        """The tile's points without repeats (one per voxel, the first seen), in the order
        they came, as one array (kept so: a tile's chunks are joined once per run, not per
        frame); its keys in one sorted run."""
        self._absorb(tile)
        self._merge_keys(tile)
        if len(tile.chunks) > 1:
            tile.chunks = [np.concatenate(tile.chunks)]
            tile.ncompact = 1
        return tile.chunks[0] if tile.chunks else np.zeros((0, 4), np.float32)

    def _evict(self) -> None:
        """Drop the points of the tiles farthest from the machine until 80 % of the cap.

        A dirty tile gets its last run first: at once, inline; with ``defer_runs`` it and the
        tiles nearer than it keep their points until the worker has run it (the worker takes
        the farthest dirty tiles first), unless the map holds more than ``hard_cap`` times
        the cap: then its job (its last run's points) is made now and waits in ``backlog``
        for the worker (counted in ``held_runs``)."""
        ids = list(self.tiles)
        centres = (np.array(ids, dtype=np.float64) + 0.5) * self.tile
        far = np.argsort(-np.hypot(*(centres - self._last_xy).T))
        for k in far:
            if self.stats.points <= 0.8 * self.max_points:
                break
            tile = self.tiles[ids[k]]
            if tile.points + tile.pending == 0:
                continue
            if tile.dirty:
                if not self.defer_runs:
                    self._run_tile(ids[k])  # compacts: duplicates leave the count here
                elif self.stats.points <= self.hard_cap * self.max_points:
                    break  # not the nearer tiles instead: it goes once it ran
                else:
                    # its last run's points go with the job, which waits for the worker
                    self.backlog.append(self.job(ids[k]))
                    self.stats.held_runs += 1
            n = tile.points + tile.pending
            tile.chunks, tile.points, tile.pending, tile.ncompact = [], 0, 0, 0
            tile.vox = []
            tile.keys = np.zeros(0, np.int64)  # not a view: the keys' memory goes too
            tile.runs = []
            tile.evicted = True  # its stems stay (it ran above if it was dirty)
            tile.dirty = False
            self.stats.points -= n
            self.stats.evicted_points += n

    # -- stems ------------------------------------------------------------------------------
    def dirty_tiles(self) -> list[tuple[int, int]]:
        """Dirty tiles, farthest from the machine first (they are the closest to final)."""
        ids = [k for k, t in self.tiles.items() if t.dirty]
        c = (np.array(ids, dtype=np.float64).reshape(-1, 2) + 0.5) * self.tile
        d = np.hypot(*(c - self._last_xy).T) if len(ids) else np.zeros(0)
        return [ids[i] for i in np.argsort(-d)]

    def update(self, budget_s: float = math.inf) -> int:
        """Re-run dirty tiles (and the held jobs) until ``budget_s`` is spent; returns how
        many ran."""
        t0 = time.perf_counter()
        n = 0
        while self.backlog:
            job = self.backlog.popleft()
            t1 = time.perf_counter()
            self.accept(job.tid, tile_stems(job, self.params), time.perf_counter() - t1)
            n += 1
        for tid in self.dirty_tiles():
            if n and time.perf_counter() - t0 >= budget_s:
                break
            self._run_tile(tid)
            n += 1
        return n

    def job(self, tid: tuple[int, int]) -> TileJob:
        """What a run of tile ``tid`` needs, taken from the map now: its points and its
        border's (float32, the map's own), and the ground height under each. The tile counts
        as run from here (new points make it dirty again); :meth:`accept` takes the stems
        :func:`tile_stems` finds in the job, wherever that ran."""
        i, j = tid
        lo = np.array([i, j], dtype=np.float64) * self.tile - self.margin
        hi = lo + self.tile + 2 * self.margin
        parts = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                nb = self.tiles.get((i + di, j + dj))
                if nb is not None and (nb.points or nb.pending):
                    p = self._compact(nb)  # the border's points only (compared in float64)
                    # a tile's points lie within it (up to float32's rounding, far inside
                    # the margin): only the axes along which the neighbour is offset can
                    # leave points outside the border, and the tile itself keeps them all
                    keep = None
                    for a, dv in ((0, di), (1, dj)):
                        if dv:
                            q = p[:, a]
                            m = (q >= lo[a]) & (q < hi[a])
                            keep = m if keep is None else keep & m
                    parts.append(p if keep is None else p[keep])
        tile = self.tiles[tid]
        tile.dirty = tile.evicted = False
        tile.basis = tile.points  # compacted above
        tile.run_distance = self._distance(tid)
        pts = np.concatenate(parts) if parts else np.zeros((0, 4), np.float32)
        gz = self.ground.height(pts[:, :2].astype(np.float64))
        ok = np.isfinite(gz)
        if not ok.all():
            pts, gz = pts[ok], gz[ok]
        return TileJob(tid, pts, gz, self.tile)

    def accept(self, tid: tuple[int, int], stems: list[dict[str, Any]],
               seconds: float = 0.0) -> None:
        """A tile's stems, from a run of its :meth:`job`."""
        tile = self.tiles.get(tid)
        if tile is not None:
            tile.stems = stems
        self.stats.tile_runs += 1
        self.stats.tile_seconds += seconds
        if self.stats.points > self.max_points:
            self._evict()  # the tiles held for their last run can go now

    def _run_tile(self, tid: tuple[int, int]) -> None:
        t0 = time.perf_counter()
        stems = tile_stems(self.job(tid), self.params)
        self.accept(tid, stems, time.perf_counter() - t0)

    def next_job(self, *, final: bool = False) -> TileJob | None:
        """The next tile run a worker should do: a job held by an eviction first, else the
        dirty tile farthest from the machine that is worth a run now; None when there is
        none.

        Worth a run (unless ``final``: the stream has ended, every dirty tile): a tile never
        run, one that grew by ``rerun_growth`` since its last run, or one the machine has
        moved ``settle_m`` away from since then (its view is settling). A tile near the
        machine gains points every frame; run on each, it would take the worker's whole time
        for stems that the next frames change again."""
        if self.backlog:
            return self.backlog.popleft()
        over = self.stats.points > self.max_points
        for tid in self.dirty_tiles():
            tile = self.tiles[tid]
            if (final or over or tile.basis == 0
                    or tile.points + tile.pending >= (1.0 + self.rerun_growth) * tile.basis
                    or self._distance(tid) >= tile.run_distance + self.settle_m):
                return self.job(tid)
        return None

    def _distance(self, tid: tuple[int, int]) -> float:
        cx, cy = (tid[0] + 0.5) * self.tile, (tid[1] + 0.5) * self.tile
        return math.hypot(cx - float(self._last_xy[0]), cy - float(self._last_xy[1]))

    def forest(self, timestamp: str) -> dict[str, Any]:
        """The observed-forest document of every tile's latest stems, in world coordinates,
        ordered by x, y (ids 1..n)."""
        objs = [o for t in self.tiles.values() for o in t.stems]
        objs.sort(key=lambda o: (o["cp"][0], o["cp"][1]))
        cx0, cy0 = self.params.scene_centre
        out = []
        for k, o in enumerate(objs, 1):
            cp = [round(float(o["cp"][a]) + float(self.datum[a]), 4) for a in range(3)]
            obj = {**o, "id": k, "name": f"tree_{k}", "cp": cp,
                   "d": round(math.hypot(cp[0] - cx0, cp[1] - cy0), 4)}
            obj["quality"] = QUALITY_BY_CLASS[obj["class"]]
            out.append(obj)
        self.stats.tiles = len(self.tiles)
        return {"timestamp": timestamp, "total_objects_count": len(out), "objects": out}
