"""The onboard SIC's world model: a ground grid (running minimum per 1 m cell, the paper's
ground filter kept incrementally), a bounded voxel map of the points above it, split into
square tiles, and the stem algorithm re-run only on tiles that got new points.

Pure numpy/scipy on arrays; no I/O. Coordinates are local: world minus the pose datum, so
float32 storage loses nothing (micrometres over kilometres).
"""

from __future__ import annotations

import collections
import functools
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocols.stems import QUALITY_BY_CLASS
from tcf_hil.sic._fast import column_min, finite_rows, sorted_with_order
from tcf_hil.sic._stems import StemParams, identify_stems
from tcf_hil.sic._voxelset import VoxelSet

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

    def snapshot(self, lo: FloatArray, hi: FloatArray) -> GroundGrid:
        """A copy of the cells under the area ``lo`` .. ``hi`` (x, y) and two around them:
        the same heights under any point of the area as this grid gives now (a cell's
        gradient looks one cell away)."""
        out = GroundGrid(self.cell, slope=self.slope, max_gradient=self.max_gradient)
        ni, nj = self.z.shape
        a0 = max(math.floor(lo[0] / self.cell) - 2 - self.i0, 0)
        b0 = max(math.floor(lo[1] / self.cell) - 2 - self.j0, 0)
        a1 = min(math.floor(hi[0] / self.cell) + 3 - self.i0, ni)
        b1 = min(math.floor(hi[1] / self.cell) + 3 - self.j0, nj)
        if a1 > a0 and b1 > b0:
            out.z = self.z[a0:a1, b0:b1].copy()
            out.i0, out.j0 = self.i0 + a0, self.j0 + b0
        return out

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


Crop = tuple[tuple[int, float, float], ...]  # (axis, lo, hi): rows with lo <= v < hi


@dataclass
class TileJob:
    """One run of the stem algorithm on a tile: its points and its border's (x, y, z, edge
    half width; float32, local metres), the ground grid under them as it was when the job was
    made (:meth:`GroundGrid.snapshot`: a few cells), and the tile's id and size (its stems
    are those whose centre lies inside it).

    The points are ``parts``: views of the map's blocks as they were when the job was made,
    each with the crop that keeps a neighbour's border (the map's rows never change once
    written). Making a job copies nothing; whoever runs it takes :meth:`pieces` (a worker's
    feeder, a block at a time) or :attr:`points` (one array). The heights under the points
    are the run's work too."""

    tid: tuple[int, int]
    parts: list[tuple[NDArray[np.float32], Crop]]
    ground: GroundGrid
    tile_m: float

    @classmethod
    def of(cls, tid: tuple[int, int], points: NDArray[np.float32], ground: GroundGrid,
           tile_m: float) -> TileJob:
        """A job of one array of points."""
        return cls(tid, [(points, ())], ground, tile_m)

    def pieces(self) -> Iterator[NDArray[np.float32]]:
        """The points, part by part, cropped (compared in float64)."""
        for rows, crop in self.parts:
            keep = None
            for a, lo, hi in crop:
                q = rows[:, a]
                m = (q >= np.float64(lo)) & (q < np.float64(hi))
                keep = m if keep is None else keep & m
            yield rows if keep is None else rows[keep]

    @functools.cached_property
    def points(self) -> NDArray[np.float32]:
        p = list(self.pieces())
        return np.concatenate(p) if p else np.zeros((0, 4), np.float32)


def tile_stems(job: TileJob, params: StemParams) -> list[dict[str, Any]]:
    """The stems of a tile run: the stem algorithm on the job's points above seen ground,
    those whose centre lies inside the tile."""
    if len(job.points) == 0:
        return []
    pts = job.points.astype(np.float64)
    gz = job.ground.height(pts[:, :2])
    ok = np.isfinite(gz)
    if not ok.all():
        pts, gz = pts[ok], gz[ok]
    doc = identify_stems(pts[:, :3], params, ground_z=gz, widths=pts[:, 3])
    x0, y0 = job.tid[0] * job.tile_m, job.tid[1] * job.tile_m
    return [o for o in doc["objects"]
            if x0 <= o["cp"][0] < x0 + job.tile_m and y0 <= o["cp"][1] < y0 + job.tile_m]


_BLOCK_MIN, _BLOCK_MAX = 4096, 65536  # rows of a tile's storage blocks (64 KiB .. 1 MiB)


@dataclass
class _Tile:
    blocks: list[NDArray[np.float32]] = field(default_factory=list)
    # ^ its points (x, y, z, edge half width), one a voxel and kind, the first seen, in the
    # order they came: in blocks that double up to 1 MiB, the last one filled to ``fill``.
    # Rows once written never change (a job may hold views of them), and a tile that grows
    # never copies what it holds (a copy of a big tile held up a frame by 65 ms)
    fill: int = 0
    points: int = 0
    dirty: bool = False
    stems: list[dict[str, Any]] = field(default_factory=list)
    basis: int = 0  # the tile's own points its stems were found on
    evicted: bool = False  # lost its points since its stems were found
    run_distance: float = 0.0  # from the machine, when it last ran
    voxels: VoxelSet = field(default_factory=VoxelSet)  # the voxel keys of its points

    def views(self) -> list[NDArray[np.float32]]:
        """Its points, block by block (views: later rows do not show in them)."""
        if not self.blocks:
            return []
        return [*self.blocks[:-1], self.blocks[-1][:self.fill]]

    @property
    def held(self) -> NDArray[np.float32]:
        """Its points, as one array."""
        v = self.views()
        return np.concatenate(v) if v else np.zeros((0, 4), np.float32)

    def append(self, pts: NDArray[np.float32]) -> None:
        i = 0
        while i < len(pts):
            if not self.blocks or self.fill == len(self.blocks[-1]):
                rows = min(_BLOCK_MAX, _BLOCK_MIN << len(self.blocks))
                self.blocks.append(np.empty((rows, 4), np.float32))
                self.fill = 0
            last = self.blocks[-1]
            k = min(len(pts) - i, len(last) - self.fill)
            last[self.fill:self.fill + k] = pts[i:i + k]
            self.fill += k
            i += k
        self.points += len(pts)

    def drop(self) -> int:
        """Lets its points and voxels go; returns how many points."""
        n = self.points
        self.blocks, self.fill, self.points = [], 0, 0
        self.voxels = VoxelSet(compiled=self.voxels.compiled)
        return n


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
                 datum: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 compiled_sets: bool = True) -> None:
        if not (voxel_m > 0 and tile_m > 2 * margin_m > 0):
            raise ValueError("voxel_m > 0 and tile_m > 2 * margin_m > 0 required")
        self.params = params
        self.voxel = voxel_m
        self.tile = tile_m
        self.margin = margin_m
        self.max_points = max_points
        self.compiled_sets = compiled_sets  # False: numpy's sorted runs (a benchmark's side)
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
        # by tile (stable: in the order they came), each tile keeping those of voxels it
        # does not hold yet (the first of each)
        keys = self._keys_of(self._voxels(keep))
        t = np.floor(keep[:, :2] / self.tile).astype(np.int64)
        t0 = column_min(t)
        nj = int(t[:, 1].max() - t0[1]) + 1
        _, order = sorted_with_order((t[:, 0] - t0[0]) * nj + (t[:, 1] - t0[1]))
        keep, t, keys = keep[order], t[order], keys[order]
        starts = np.flatnonzero(np.r_[True, (t[1:, 0] != t[:-1, 0]) | (t[1:, 1] != t[:-1, 1])])
        ends = np.r_[starts[1:], len(keep)]
        f32 = keep.astype(np.float32)
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            tid = (int(t[a, 0]), int(t[a, 1]))
            tile = self.tiles.get(tid)
            if tile is None:
                tile = _Tile(voxels=VoxelSet(compiled=self.compiled_sets))
                self.tiles[tid] = tile
            new = tile.voxels.add(keys[a:b])
            fresh = int(np.count_nonzero(new))
            if fresh:
                tile.append(f32[a:b][new])
                self.stats.points += fresh
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
            if tile.points == 0:
                continue
            if tile.dirty:
                if not self.defer_runs:
                    self._run_tile(ids[k])  # compacts: duplicates leave the count here
                elif self.stats.points <= self.hard_cap * self.max_points:
                    break  # not the nearer tiles instead: it goes once it ran
                else:
                    # its last run's points go with the job, which waits for the worker:
                    # copied (its border cropped), not views that would keep the blocks
                    # of the nine tiles this eviction lets go
                    job = self.job(ids[k])
                    self.backlog.append(TileJob.of(job.tid, job.points, job.ground,
                                                   job.tile_m))
                    self.stats.held_runs += 1
            n = tile.drop()
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
        border's (views of the map's own float32 blocks) and the ground grid under them; it
        copies no points (:class:`TileJob`). The tile counts as run from here (new points
        make it dirty again); :meth:`accept` takes the stems
        :func:`tile_stems` finds in the job, wherever that ran."""
        i, j = tid
        lo = np.array([i, j], dtype=np.float64) * self.tile - self.margin
        hi = lo + self.tile + 2 * self.margin
        parts: list[tuple[NDArray[np.float32], Crop]] = []
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                nb = self.tiles.get((i + di, j + dj))
                if nb is not None and nb.points:
                    # a tile's points lie within it (up to float32's rounding, far inside
                    # the margin): only the axes along which the neighbour is offset can
                    # leave points outside the border, and the tile itself keeps them all
                    crop = tuple((a, float(lo[a]), float(hi[a]))
                                 for a, dv in ((0, di), (1, dj)) if dv)
                    parts.extend((v, crop) for v in nb.views())
        tile = self.tiles[tid]
        tile.dirty = tile.evicted = False
        tile.basis = tile.points
        tile.run_distance = self._distance(tid)
        # the ground under the job's area as it is now: the heights are the run's to take
        return TileJob(tid, parts, self.ground.snapshot(lo, hi), self.tile)

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
                    or tile.points >= (1.0 + self.rerun_growth) * tile.basis
                    or self._distance(tid) >= tile.run_distance + self.settle_m):
                return self.job(tid)
        return None

    def nbytes(self) -> int:
        """The memory the map's points and voxel sets take (their arrays)."""
        return sum(sum(b.nbytes for b in t.blocks) + t.voxels.nbytes
                   for t in self.tiles.values())

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
