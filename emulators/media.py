"""Porous volumes (crowns) a ray passes or stops in: a turbid medium, Beer-Lambert's law drawn
per ray in the compiled cast instead of explicit leaf geometry.

A crown is a cone (conifers, widest at its base) or an ellipsoid (birch, shrubs), possibly
cut across its axis (a broken top keeps the crown below the break), filled with foliage of
extinction coefficient sigma (1/m): the share of rays that pass a depth L inside it is
exp(-sigma L). A ray meets the crowns along its path as intervals (exact ray-cone and
ray-ellipsoid intersections, float64); its free path is drawn once, as an optical depth
E = -ln(U), and it stops where the optical depth it has crossed reaches E, summed over
overlapping crowns (so two crowns that overlap are as dense as both together). This is the
free path HELIOS++'s transmittive voxels draw (-ln(U)/sigma), here through each crown's own
envelope rather than voxels, and with one draw a ray.

The draws are a hash of the ray itself (its origin and direction, float32 bits), not a
generator's next number: a ray cast twice, on any thread, in any order and through any of
the lidar emulator's paths, stops at the same place, so every path writes the same bytes
and a scene is a frozen medium as facets would be. Where the ray stops, the foliage it hit
faces it at a random orientation: |cos incidence| is drawn as sqrt(U), the law of the hits
on randomly oriented flat leaves (a leaf is hit in proportion to the silhouette it shows,
|cos|, and |cos| of a random orientation is uniform).

The crowns a ray meets are found on a horizontal grid (:meth:`Crowns.grid`: each cell lists
the crowns whose bounding box meets it, and their z range), which the ray walks cell by
cell (a 2D DDA) until the optical depth it has crossed reaches its draw: every crown that
holds a point of the ray up to a cell's far side is listed in a cell walked by then, so
the search stops at the first cell that holds the stop. (Embree found them more slowly,
measured on ``pine-thinning``: 64 ms for a frame's rays cast envelope by envelope, 78 ms
with a filter function that lists every envelope in one traversal.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.jit import jit_enabled, numba_module

CONE, ELLIPSOID = 0, 1
# a crown's row in the float64 table the kernels read
APEX, AXIS, LENGTH, RADIUS, CUT, SHAPE, SIGMA = 0, 3, 6, 7, 8, 9, 10
COLUMNS = 12
MAX_CROWNS = 32
"""Crowns one ray weighs at most (a ray from a stand's edge across 100 m of it at crown
height meets about 20); those it meets after are left out."""
_SIDES = 8
FACES_PER_CROWN = 4 * _SIDES  # an envelope's sides (2 a side) and its two caps' fans


@dataclass(frozen=True)
class Crowns:
    """Porous crowns, one per row: ``apex`` (k, 3) and the unit ``axis`` (k, 3) pointing
    from the apex into the crown (down a tree), ``length`` along it, ``radius`` (a cone's at
    its base, an ellipsoid's at its middle), ``cut`` (the crown begins that far below the
    apex: a broken top's; 0 whole), ``shape`` (:data:`CONE` or :data:`ELLIPSOID`),
    ``sigma`` (extinction, 1/m)."""

    apex: NDArray[np.float64]
    axis: NDArray[np.float64]
    length: NDArray[np.float64]
    radius: NDArray[np.float64]
    cut: NDArray[np.float64]
    shape: NDArray[np.int8]
    sigma: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.length)

    def table(self) -> NDArray[np.float64]:
        """(k, :data:`COLUMNS`) float64: the rows the kernels read."""
        t = np.zeros((len(self), COLUMNS))
        t[:, APEX:APEX + 3] = self.apex
        t[:, AXIS:AXIS + 3] = self.axis / np.linalg.norm(self.axis, axis=1)[:, None]
        t[:, LENGTH], t[:, RADIUS], t[:, CUT] = self.length, self.radius, self.cut
        t[:, SHAPE], t[:, SIGMA] = self.shape, self.sigma
        return t

    def envelopes(self) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
        """Each crown's bounding polyhedron, :data:`FACES_PER_CROWN` triangles a crown: a
        cone's an octagonal pyramid about it, an ellipsoid's an octagonal prism, both
        circumscribed and a little wide; vertices (k 18, 3) and faces (k 32, 3). The grid
        (:meth:`grid`) bins the crowns by their boxes; drawn, they show where crowns are."""
        k = len(self)
        ax = self.axis / np.linalg.norm(self.axis, axis=1)[:, None]
        helper = np.where(np.abs(ax[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
        e1 = np.cross(ax, helper)
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        e2 = np.cross(ax, e1)
        pad = 1e-4 + 1e-5 * (self.length + self.radius)
        rc = self.radius / math.cos(math.pi / _SIDES) + pad  # circumscribed octagon
        ang = 2.0 * math.pi * np.arange(_SIDES) / _SIDES
        ring = (np.cos(ang)[None, :, None] * e1[:, None, :]
                + np.sin(ang)[None, :, None] * e2[:, None, :]) * rc[:, None, None]
        cone = (self.shape == CONE)[:, None, None]
        top = self.apex - pad[:, None] * ax  # s = -pad
        bottom = self.apex + (self.length + pad)[:, None] * ax
        # vertices: 8 on the upper ring, 8 on the lower, the upper and lower centres; a
        # cone's upper ring shrinks onto its apex (its upper cap then has no area)
        upper = np.where(cone, top[:, None, :], top[:, None, :] + ring)
        lower = bottom[:, None, :] + ring
        v = np.concatenate([upper, lower, top[:, None, :], bottom[:, None, :]], axis=1)
        i = np.arange(_SIDES)
        j = (i + 1) % _SIDES
        sides = np.concatenate([np.stack([i, j, _SIDES + j], 1),
                                np.stack([i, _SIDES + j, _SIDES + i], 1)])
        caps = np.concatenate([np.stack([np.full(_SIDES, 2 * _SIDES), j, i], 1),
                               np.stack([np.full(_SIDES, 2 * _SIDES + 1), _SIDES + i,
                                         _SIDES + j], 1)])
        per = np.concatenate([sides, caps])[:FACES_PER_CROWN]
        f = (per[None, :, :] + (2 * _SIDES + 2) * np.arange(k)[:, None, None]).reshape(-1, 3)
        return (v.reshape(-1, 3).astype(np.float32), f.astype(np.uint32))

    def grid(self, cell_m: float = 1.5) -> tuple[NDArray[np.float64], NDArray[np.int64],
                                                 NDArray[np.int64], NDArray[np.float64]]:
        """The crowns binned on a horizontal grid for :func:`march`: a header (x0, y0, the
        cell's side, nx, ny, the lowest and highest crown's z), each cell's first entry in
        the list and the list (cells in x-major order, the crowns whose bounding polyhedron's
        box meets the cell), and the z ranges (ncells + len(list), 2) of each cell's crowns
        and then of each listed crown."""
        if not len(self):
            return (np.array([0.0, 0.0, cell_m, 1, 1, 0.0, -1.0]), np.zeros(2, np.int64),
                    np.zeros(0, np.int64), np.array([[np.inf, -np.inf]]))
        v32, _ = self.envelopes()
        v = v32.astype(np.float64).reshape(len(self), -1, 3)
        lo, hi = v.min(axis=1), v.max(axis=1)
        # the cells on a lattice fixed to the world (multiples of the side, exact in
        # binary for a side such as 1.5 m), so that a stand culled to the track walks its
        # rays through the very cells the whole stand's does
        x0 = (math.floor(lo[:, 0].min() / cell_m) - 1) * cell_m
        y0 = (math.floor(lo[:, 1].min() / cell_m) - 1) * cell_m
        nx = math.ceil((hi[:, 0].max() - x0) / cell_m) + 1
        ny = math.ceil((hi[:, 1].max() - y0) / cell_m) + 1
        i0 = np.floor((lo[:, 0] - x0) / cell_m).astype(np.int64)
        i1 = np.floor((hi[:, 0] - x0) / cell_m).astype(np.int64)
        j0 = np.floor((lo[:, 1] - y0) / cell_m).astype(np.int64)
        j1 = np.floor((hi[:, 1] - y0) / cell_m).astype(np.int64)
        span = (i1 - i0 + 1) * (j1 - j0 + 1)
        crown = np.repeat(np.arange(len(self), dtype=np.int64), span)
        k = np.arange(len(crown)) - np.repeat(np.cumsum(span) - span, span)
        w = np.repeat(j1 - j0 + 1, span)
        cell = (np.repeat(i0, span) + k // w) * ny + np.repeat(j0, span) + k % w
        order = np.lexsort((crown, cell))
        cell, crown = cell[order], crown[order]
        start = np.searchsorted(cell, np.arange(nx * ny + 1)).astype(np.int64)
        zr = np.empty((nx * ny + len(crown), 2))
        zr[:, 0], zr[:, 1] = np.inf, -np.inf
        np.minimum.at(zr[:, 0], cell, lo[crown, 2])
        np.maximum.at(zr[:, 1], cell, hi[crown, 2])
        zr[nx * ny:, 0], zr[nx * ny:, 1] = lo[crown, 2], hi[crown, 2]
        head = np.array([x0, y0, cell_m, nx, ny, lo[:, 2].min(), hi[:, 2].max()])
        return head, start, crown, zr



def interval(row: Any, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float
             ) -> tuple[float, float]:
    """Where the ray o + t d (d unit) is inside the crown ``row`` (a row of
    :meth:`Crowns.table`): (t0, t1), t0 > t1 where it is not (t of either sign)."""
    qx, qy, qz = ox - row[0], oy - row[1], oz - row[2]
    wx, wy, wz = row[3], row[4], row[5]
    L, R, s0 = row[LENGTH], row[RADIUS], row[CUT]
    sq = qx * wx + qy * wy + qz * wz
    sd = dx * wx + dy * wy + dz * wz
    qd = qx * dx + qy * dy + qz * dz
    qq = qx * qx + qy * qy + qz * qz
    dd = dx * dx + dy * dy + dz * dz
    # the slab s0 <= s(t) <= L, s(t) = sq + t sd the depth below the apex along the axis
    lo, hi = -np.inf, np.inf
    smin = max(s0, 0.0)
    if smin >= L:  # cut at or below its base: nothing left
        return 1.0, 0.0
    if sd != 0.0:
        a1, b1 = (smin - sq) / sd, (L - sq) / sd
        lo, hi = min(a1, b1), max(a1, b1)
    elif sq < smin or sq > L:
        return 1.0, 0.0
    if row[SHAPE] == CONE:  # |q + t d|^2 - (1 + k^2) s(t)^2 <= 0, k = R / L
        m = 1.0 + (R / L) ** 2
        a = dd - m * sd * sd
        b = 2.0 * (qd - m * sq * sd)
        c = qq - m * sq * sq
    else:  # rho^2 / R^2 + (s - h)^2 / h^2 <= 1, h = L / 2
        h = L / 2.0
        ir, ih = 1.0 / (R * R), 1.0 / (h * h)
        a = (dd - sd * sd) * ir + sd * sd * ih
        b = 2.0 * (qd - sq * sd) * ir + 2.0 * (sq - h) * sd * ih
        c = (qq - sq * sq) * ir + (sq - h) ** 2 * ih - 1.0
    disc = b * b - 4.0 * a * c
    if a == 0.0:  # linear: a ray along a cone's surface line
        if b == 0.0:
            return (lo, hi) if c <= 0.0 else (1.0, 0.0)
        r = -c / b
        return (max(lo, r), hi) if b < 0.0 else (lo, min(hi, r))
    if disc < 0.0:  # g(t) keeps a's sign
        return (lo, hi) if a < 0.0 else (1.0, 0.0)
    sq_disc = math.sqrt(disc)
    qv = -0.5 * (b + math.copysign(sq_disc, b))  # the stable pair of roots
    r1 = qv / a
    r2 = c / qv if qv != 0.0 else r1
    r1, r2 = min(r1, r2), max(r1, r2)
    if a > 0.0:  # inside between the roots
        return max(lo, r1), min(hi, r2)
    # outside the roots: (-inf, r1] and [r2, inf), one of them the cone's upper nappe, which
    # the slab (s >= 0) leaves out; keep the longer piece (the other is empty but for
    # rounding at the apex)
    a0, a1_ = lo, min(hi, r1)
    b0, b1_ = max(lo, r2), hi
    return (a0, a1_) if a1_ - a0 >= b1_ - b0 else (b0, b1_)


def _mix(z: Any) -> Any:
    """splitmix64's finaliser."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def ray_key(ru: Any) -> Any:
    """A 64-bit hash of the ray in an RTCRayHit (its origin's and direction's float32
    bits, words 0-2 and 4-6)."""
    h = np.uint64(0x9E3779B97F4A7C15)
    for k in (0, 1, 2, 4, 5, 6):
        h = _mix(h ^ np.uint64(ru[k]) ^ (np.uint64(k) << np.uint64(32)))
    return h


def uniform(key: Any, k: int) -> float:
    """The ``k``-th uniform (0, 1) of a ray's ``key``."""
    z = _mix(key ^ (np.uint64(k + 1) * np.uint64(0xD1B54A32D192ED03)))
    return (np.float64(z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


def stop_at(tau: float, n: int, a: Any, b: Any, s: Any) -> float:
    """Where the optical depth crossed from 0 reaches ``tau`` through the intervals
    [a_j, b_j] of extinction s_j (j < n), or inf where it does not."""
    t0 = 0.0
    acc = 0.0
    while True:  # from breakpoint to breakpoint; the density on [t0, the next one)
        nxt = np.inf
        dens = 0.0
        for j in range(n):
            if a[j] <= t0 < b[j]:
                dens += s[j]
                if b[j] < nxt:
                    nxt = b[j]
            elif a[j] > t0 and a[j] < nxt:
                nxt = a[j]
        if dens > 0.0:
            if acc + dens * (nxt - t0) >= tau:  # within this stretch (rounding aside)
                return min(t0 + (tau - acc) / dens, nxt)
            acc += dens * (nxt - t0)
        if not np.isfinite(nxt):
            return np.inf
        t0 = nxt
    return np.inf


def _slab(o: float, d: float, lo: float, hi: float, t_lo: float, t_hi: float
          ) -> tuple[float, float]:
    """[t_lo, t_hi] narrowed to where o + t d lies in [lo, hi] (empty: t_lo >= t_hi)."""
    if d != 0.0:
        u, v = (lo - o) / d, (hi - o) / d
        return max(t_lo, min(u, v)), min(t_hi, max(u, v))
    if o < lo or o > hi:
        return 1.0, 0.0
    return t_lo, t_hi


def march(crowns: Any, head: Any, start: Any, items: Any, zr: Any, ox: float, oy: float,
          oz: float, dx: float, dy: float, dz: float, t_max: float, tau: float, a: Any,
          b: Any, s: Any, ids: Any) -> tuple[float, int]:
    """Where the ray o + t d (d unit) stops in the crowns short of ``t_max`` (``crowns``
    their table, the rest their :meth:`Crowns.grid`): its optical depth reaches ``tau``;
    inf where it passes them. The crowns it entered go into ``ids`` with their intervals
    (``a``, ``b``) and extinction (``s``) (each at most :data:`MAX_CROWNS` long), in the
    order of their numbers; their number is returned."""
    x0, y0, cell = head[0], head[1], head[2]
    nx, ny = int(head[3]), int(head[4])
    n_cells = nx * ny
    t_lo, t_hi = _slab(oz, dz, head[5], head[6], 0.0, t_max)
    t_lo, t_hi = _slab(ox, dx, x0, x0 + nx * cell, t_lo, t_hi)
    t_lo, t_hi = _slab(oy, dy, y0, y0 + ny * cell, t_lo, t_hi)
    if not t_lo < t_hi:
        return np.inf, 0
    px, py = ox + t_lo * dx, oy + t_lo * dy
    ix = min(max(math.floor((px - x0) / cell), 0), nx - 1)
    iy = min(max(math.floor((py - y0) / cell), 0), ny - 1)
    sx = 1 if dx > 0.0 else -1
    sy = 1 if dy > 0.0 else -1
    tdx = cell / abs(dx) if dx != 0.0 else np.inf
    tdy = cell / abs(dy) if dy != 0.0 else np.inf
    tx = (x0 + (ix + (1 if dx > 0.0 else 0)) * cell - ox) / dx if dx != 0.0 else np.inf
    ty = (y0 + (iy + (1 if dy > 0.0 else 0)) * cell - oy) / dy if dy != 0.0 else np.inf
    t0 = t_lo
    n = 0
    stop = np.inf
    while True:
        t1 = min(tx, ty, t_hi)
        c = ix * ny + iy
        za, zb = oz + t0 * dz, oz + t1 * dz
        z_lo, z_hi = min(za, zb), max(za, zb)
        if start[c + 1] > start[c] and z_hi >= zr[c, 0] and z_lo <= zr[c, 1]:
            added = False
            for k in range(start[c], start[c + 1]):
                if z_hi < zr[n_cells + k, 0] or z_lo > zr[n_cells + k, 1]:
                    continue
                cid = items[k]
                known = False
                for j in range(n):
                    if ids[j] == cid:
                        known = True
                        break
                if known or n >= MAX_CROWNS:
                    continue
                u, v = interval(crowns[cid], ox, oy, oz, dx, dy, dz)
                v = min(v, t_max)
                if v > max(u, 0.0):  # only the crowns it enters (others may come again)
                    # kept in the order of their numbers, not of the cells they were found
                    # in: what is summed, and which crown is picked where several hold the
                    # stop, then follows the crowns alone (a stand culled to the track,
                    # its crowns numbered afresh in the same order, stops a ray where the
                    # whole stand does, in the same crown)
                    j = n
                    while j > 0 and ids[j - 1] > cid:
                        ids[j], a[j], b[j], s[j] = ids[j - 1], a[j - 1], b[j - 1], s[j - 1]
                        j -= 1
                    ids[j] = cid
                    a[j], b[j], s[j] = max(u, 0.0), v, crowns[cid, SIGMA]
                    n += 1
                    added = True
            if added:
                stop = stop_at(tau, n, a, b, s)
        if stop <= t1 or t1 >= t_hi:
            break
        if tx < ty:
            ix += sx
            t0 = tx
            tx += tdx
            if ix < 0 or ix >= nx:
                break
        else:
            iy += sy
            t0 = ty
            ty += tdy
            if iy < 0 or iy >= ny:
                break
    return (stop if stop < t_max else np.inf), n


# Compiled where numba is (numba calls only compiled functions), inlined into their callers:
# a call between compiled functions counts references to every array it passes, which cost
# more than the work here. The Embree cast that uses them is
# :func:`emulators.embree.intersect1`'s.
if jit_enabled():
    _kernel = numba_module().njit(cache=True, nogil=True, inline="always")
    _mix = _kernel(_mix)
    ray_key = _kernel(ray_key)
    uniform = _kernel(uniform)
    interval = _kernel(interval)
    stop_at = _kernel(stop_at)
    _slab = _kernel(_slab)
    march = _kernel(march)
