"""The onboard SIC's world model: a ground grid (running minimum per 1 m cell, the paper's
ground filter kept incrementally), a bounded voxel map of the points above it, split into
square tiles, and the stem algorithm re-run only on tiles that got new points.

Pure numpy/scipy on arrays; no I/O. Coordinates are local: world minus the pose datum, so
float32 storage loses nothing (micrometres over kilometres).
"""

from __future__ import annotations

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
class _Tile:
    chunks: list[NDArray[np.float32]] = field(default_factory=list)
    points: int = 0  # after the last compaction
    pending: int = 0  # in chunks not yet compacted
    dirty: bool = False
    stems: list[dict[str, Any]] = field(default_factory=list)
    basis: int = 0  # the tile's own points its stems were found on
    evicted: bool = False  # lost its points since its stems were found
    keys: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    # ^ the voxel keys of the compacted points (chunks[0] where points > 0), sorted


@dataclass
class MapStats:
    points: int = 0
    tiles: int = 0
    evicted_points: int = 0
    tile_runs: int = 0
    tile_seconds: float = 0.0


class StemMap:
    """Points above the ground (x, y, z and the edge half width), one per ``voxel_m`` cube and
    kind, in ``tile_m`` tiles.

    ``add`` takes a frame's points; ``update`` re-runs the stem algorithm on dirty tiles (each
    with a ``margin_m`` border from its neighbours, keeping the stems whose centre lies inside
    it) for at most ``budget_s``; ``forest`` assembles the observed document. The map holds
    at most ``max_points``: beyond that the tiles farthest from the machine lose their
    points (their stems stay: the sensor hardly reaches them now). Such a tile runs again
    only once it holds more points than its stems were found on.
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
        sk, order = sorted_with_order(offset_key(self._voxels(keep)))
        keep = keep[np.sort(order[run_starts(sk)])]
        t = np.floor(keep[:, :2] / self.tile).astype(np.int64)
        t0 = column_min(t)
        nj = int(t[:, 1].max() - t0[1]) + 1
        _, order = sorted_with_order((t[:, 0] - t0[0]) * nj + (t[:, 1] - t0[1]))  # by tile
        keep, t = keep[order], t[order]
        starts = np.flatnonzero(np.r_[True, (t[1:, 0] != t[:-1, 0]) | (t[1:, 1] != t[:-1, 1])])
        ends = np.r_[starts[1:], len(keep)]
        f32 = keep.astype(np.float32)
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
            tid = (int(t[a, 0]), int(t[a, 1]))
            tile = self.tiles.get(tid)
            if tile is None:
                tile = self.tiles[tid] = _Tile()
            tile.chunks.append(f32[a:b])
            tile.pending += b - a
            if not tile.evicted:
                tile.dirty = True
            elif (not tile.dirty and tile.points + tile.pending > tile.basis
                  and 4 * tile.pending >= tile.points):
                # a tile that lost its points runs again once it holds more than its stems
                # were found on (a few far returns must not replace them): its points
                # counted without repeats, after a quarter as many new ones (amortised)
                self._compact(tile)
                tile.dirty = tile.points > tile.basis
            if tile.pending > max(tile.points, 50_000):
                self._compact(tile)
        self.stats.points += len(keep)
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

    def _compact(self, tile: _Tile) -> NDArray[np.float32]:
        """The tile's points without repeats (one per voxel, the first seen), in the order
        they came. The compacted points' keys are kept sorted, so that only the new points
        are sorted and looked up in them, not all of the tile's points again."""
        if tile.pending == 0:
            return tile.chunks[0] if tile.chunks else np.zeros((0, 4), np.float32)
        base = tile.chunks[0] if tile.points else None
        new = np.concatenate(tile.chunks[1:] if base is not None else tile.chunks)
        v = self._voxels(new)
        nk = self._keys_of(v)
        # stable: the first of equal keys first; sorted by the voxels' offsets from the
        # chunk's corner (the same order as the keys'), which leave the packed sort room
        _, order = sorted_with_order(offset_key(v))
        sk = nk[order]
        first = run_starts(sk)
        uk, ui = sk[first], order[first]
        if base is not None:
            bk = tile.keys
            fresh = bk[np.minimum(np.searchsorted(bk, uk), len(bk) - 1)] != uk
            uk, ui = uk[fresh], ui[fresh]
            # two sorted runs: the stable sort (timsort) merges them in one pass
            tile.keys = np.sort(np.concatenate([bk, uk]), kind="stable")
            pts = np.concatenate([base, new[np.sort(ui)]])
        else:
            tile.keys = uk
            pts = new[np.sort(ui)]
        self.stats.points -= tile.points + tile.pending - len(pts)
        tile.chunks = [pts]
        tile.points, tile.pending = len(pts), 0
        return pts

    def _evict(self) -> None:
        """Drop the points of the tiles farthest from the machine until 80 % of the cap."""
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
                self._run_tile(ids[k])  # compacts: duplicates leave the count here
            n = tile.points + tile.pending
            tile.chunks, tile.points, tile.pending = [], 0, 0
            tile.keys = np.zeros(0, np.int64)  # not a view: the keys' memory goes too
            tile.evicted = True  # its stems stay (it ran above if it was dirty)
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
        """Re-run dirty tiles until ``budget_s`` is spent; returns how many ran."""
        t0 = time.perf_counter()
        n = 0
        for tid in self.dirty_tiles():
            if n and time.perf_counter() - t0 >= budget_s:
                break
            self._run_tile(tid)
            n += 1
        return n

    def _run_tile(self, tid: tuple[int, int]) -> None:
        t0 = time.perf_counter()
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
        pts = np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 4))
        stems: list[dict[str, Any]] = []
        if len(pts):
            gz = self.ground.height(pts[:, :2])
            ok = np.isfinite(gz)
            doc = identify_stems(pts[ok, :3], self.params, ground_z=gz[ok],
                                 widths=pts[ok, 3])
            x0, y0 = i * self.tile, j * self.tile
            for o in doc["objects"]:
                x, y = o["cp"][0], o["cp"][1]
                if x0 <= x < x0 + self.tile and y0 <= y < y0 + self.tile:
                    stems.append(o)
        tile.stems = stems
        self.stats.tile_runs += 1
        self.stats.tile_seconds += time.perf_counter() - t0

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
