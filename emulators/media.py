"""Porous volumes (crowns) a ray passes or stops in: a turbid medium, Beer-Lambert's law drawn
per ray in the compiled cast instead of explicit leaf geometry.

A crown is a cone (conifers, widest at its base) or an ellipsoid (birch, shrubs), possibly
cut across its axis (a broken top keeps the crown below the break), filled with foliage of
extinction coefficient sigma (1/m): the share of rays that pass a depth L inside it is
exp(-sigma L). A ray meets the crowns along its path as intervals (exact ray-cone and
ray-ellipsoid intersections, float64); in a crown it enters it draws a free path,
-ln(U)/sigma from where it enters, and stops there if that is still inside (two crowns
that overlap are then as dense as both together: below). This is the free path HELIOS++'s
transmittive voxels draw (-ln(U)/sigma), here through each crown's own envelope rather
than voxels.

The draws are a hash of the ray itself (its origin and direction, float32 bits) and of the
crown, not a
generator's next number: a ray cast twice, on any thread, in any order and through any of
the lidar emulator's paths, stops at the same place, so every path writes the same bytes
and a scene is a frozen medium as facets would be. Where the ray stops, the foliage it hit
faces it at a random orientation: |cos incidence| is drawn as sqrt(U), the law of the hits
on randomly oriented flat leaves (a leaf is hit in proportion to the silhouette it shows,
|cos|, and |cos| of a random orientation is uniform).

Where crowns overlap, each draws its own free path, from the ray's key and its own (a hash
of its row, so a crown keeps its draws in a stand culled to the track, whatever it is
numbered there), and the ray stops at the nearest: the first point of independent
exponential paths of extinctions s_j is the free path of their sum, and it lies in crown j
with the share s_j / sum of the density there (competing exponentials), so the stop is
Beer-Lambert's through them all, with the crown it falls in. Each crown is then a
primitive on its own: Embree finds them as user geometry (:mod:`emulators.embree`), walking
them in a hierarchy of their own before the branches and stopping at the first stop it
finds nearer than the rest (``pine-thinning``, one thread: a frame's rays in 116 ms, against
163 ms with one draw a ray marched cell by cell on a horizontal grid of the crowns).
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
        circumscribed and a little wide; vertices (k 18, 3) and faces (k 32, 3). Their boxes
        bound the crowns for Embree; drawn, they show where crowns are."""
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


def row_keys(table: NDArray[np.float64]) -> NDArray[np.uint64]:
    """Each crown's own 64-bit key: a hash of its row's bits but the last column (a crown
    keeps it whatever it is numbered in a stand culled to the track)."""
    bits = np.ascontiguousarray(table[:, :COLUMNS - 1]).view(np.uint64)
    h = np.full(len(table), 0x9E3779B97F4A7C15, np.uint64)
    with np.errstate(over="ignore"):
        for k in range(bits.shape[1]):
            z = h ^ bits[:, k] ^ (np.uint64(k) << np.uint64(32))
            z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = z ^ (z >> np.uint64(31))
    return h


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
