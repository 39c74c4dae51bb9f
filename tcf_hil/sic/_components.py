"""Connected components of the fixed-radius neighbour graph (points within ``r`` of each
other joined) without listing its edges: the same components, and the same labels, as
scipy's ``query_pairs`` followed by ``connected_components``, which on a natural stand's
accumulated cloud lists hundreds of pairs a point (branches and foliage make dense blobs).

The points are binned in cubes of side r / sqrt(3), whose diagonal is r: the points of one
cube are all within r of each other, so a cube is one component from the start. Two cubes
at most two apart on each axis (farther, no two of their points are within r) are joined
as soon as one pair of their points is within r (squared distances summed over x, y, z in
that order and compared with r * r, as scipy's KD-tree does), and not looked at again once
they are in one component (a union-find over the cubes). The labels are numbered as
scipy's are: by the lowest index of a point in each component.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.jit import jit_enabled, numba_module
from tcf_hil.sic._fast import column_max, column_min, run_starts, sorted_with_order

# Not registered as a kernel source (emulators.jit.register_kernel_source): join_cubes calls
# only this file's own _join, whose changes numba's cache notices by itself, and a source
# registered here would give every process that imports the SIC a kernel cache directory
# of its own, cold for the lidar kernels a process without it compiled (a sensor started
# by `tcf-hil lidar stream` took a minute to send its first frame).

_REACH = 2  # cubes apart on an axis that can still hold two points within r


def join_cubes(p: Any, start: Any, keys: Any, ny: int, nz: int, r2: float,
               parent: Any) -> None:
    """Union-find over the cubes: ``p`` (n, 3) float64 the points sorted by cube, cube ``c``
    holding ``p[start[c]:start[c + 1]]``, its key ``keys[c]`` (ascending; key = (i ny + j)
    nz + k of its indices), ``r2`` the squared radius; ``parent`` (m,) starts as
    ``arange(m)`` and ends with each cube pointing towards its component's root."""
    m = keys.shape[0]
    # a cursor per neighbour column (di, dj): the lowest key looked for rises with ka, so
    # each cursor only moves forward (the same cubes as a binary search, a third faster)
    cur = np.zeros((_REACH + 1) * (2 * _REACH + 1), np.int64)
    for a in range(m):
        ka = keys[a]
        q = 0
        for di in range(0, _REACH + 1):
            for dj in range(-_REACH, _REACH + 1):
                if di == 0 and dj < 0:  # each pair of cubes once, from the lower key
                    continue
                base = ka + (di * ny + dj) * nz
                # the cubes k - 2 .. k + 2 of this column are consecutive keys
                lo = ka + 1 if di == 0 and dj == 0 else base - _REACH
                b = cur[q]
                while b < m and keys[b] < lo:
                    b += 1
                cur[q] = b
                q += 1
                while b < m and keys[b] <= base + _REACH:
                    _join(p, start, parent, a, b, r2)
                    b += 1


def _join(p: Any, start: Any, parent: Any, a: int, b: int, r2: float) -> None:
    """Cubes ``a`` and ``b`` into one component where two of their points are within r
    and they are not already."""
    ra = a
    while parent[ra] != ra:
        parent[ra] = parent[parent[ra]]
        ra = parent[ra]
    rb = b
    while parent[rb] != rb:
        parent[rb] = parent[parent[rb]]
        rb = parent[rb]
    if ra == rb:
        return
    for u in range(start[a], start[a + 1]):
        for v in range(start[b], start[b + 1]):
            dx = p[u, 0] - p[v, 0]
            dy = p[u, 1] - p[v, 1]
            dz = p[u, 2] - p[v, 2]
            if dx * dx + dy * dy + dz * dz <= r2:
                if ra < rb:
                    parent[rb] = ra
                else:
                    parent[ra] = rb
                return


_KERNELS: list[Any] = []


def _kernel() -> Any:
    """:func:`join_cubes` compiled (with :func:`_join` inlined into it), or None where
    compiled kernels are off."""
    if not jit_enabled():
        return None
    if not _KERNELS:
        global _join
        njit = numba_module().njit
        _join = njit(cache=True, nogil=True, inline="always")(_join)
        _KERNELS.append(njit(cache=True, nogil=True)(join_cubes))
    return _KERNELS[0]


def radius_components(points: NDArray[np.float64], radius_m: float
                      ) -> NDArray[np.int64] | None:
    """A component label per point (numbered by each component's lowest point index), or
    None where compiled kernels are off (the caller lists the pairs instead)."""
    kernel = _kernel()
    if kernel is None:
        return None
    n = len(points)
    side = radius_m / math.sqrt(3.0) * (1.0 - 1e-9)  # a cube's diagonal under r, rounded
    ijk = np.floor((points - column_min(points)) / side).astype(np.int64) + _REACH
    span = column_max(ijk) + _REACH + 1  # room for the offsets on every side
    key = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    sk, order = sorted_with_order(key)  # the points by cube; in a cube, by index
    new_cube = run_starts(sk)
    start = np.flatnonzero(new_cube)
    keys = sk[start]
    parent = np.arange(len(keys), dtype=np.int64)
    kernel(np.ascontiguousarray(points[order], np.float64),
           np.append(start, n).astype(np.int64), keys, int(span[1]), int(span[2]),
           float(radius_m) * float(radius_m), parent)
    for _ in range(64):  # every cube straight to its root
        nxt = parent[parent]
        if np.array_equal(nxt, parent):
            break
        parent = nxt
    # numbered by each component's lowest point index: a cube's lowest is its first point
    # (the order is stable), a component's the least of its cubes'
    low = np.full(len(keys), n, np.int64)
    np.minimum.at(low, parent, order[start])
    roots = np.flatnonzero(low < n)
    rank = np.empty(len(keys), np.int64)
    rank[roots[np.argsort(low[roots])]] = np.arange(len(roots))
    labels = np.empty(n, np.int64)
    labels[order] = rank[parent][np.cumsum(new_cube) - 1]
    return labels
