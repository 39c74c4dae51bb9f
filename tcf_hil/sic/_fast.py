"""numpy idioms that are slow on the SIC's arrays, done fast with the same results.

**Sorting integer keys stably**: each key with its index packed in below it, sorted as
plain integers. numpy sorts a plain int64 array with its vectorised sort (x86-simd-sort
where the CPU has AVX2 or AVX-512) several times faster than it argsorts one: on a
1.26 M-point tile of a natural stand, 21 ms against 141 ms for
``np.argsort(kind="stable")`` and 147 ms for ``np.unique(return_index, return_inverse)``.
With the index in the low bits, equal keys come out in index order: exactly the stable
order, and exactly what :func:`numpy.unique` returns. Keys that do not leave room for the
index fall back to numpy's own.

**Reductions over the rows of an (n, 3) array**: numpy reduces ``axis=0`` of a C-ordered
(n, 3) array row by row, ten times slower than three reductions of its columns (47 ms
against 4 ms for the minimum of 1.2 M points), and ``np.all(np.isfinite(p), axis=1)`` as
slowly; minima, maxima and truth are exact in any order, so the fast forms give the same.

``benchmarks/bench_sic_tiles.py`` times the stem algorithm's tile runs with ``PACKED`` on
and off, side by side.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]

PACKED = True  # False: numpy's argsort (the benchmark's side-by-side reference)


def sorted_with_order(key: NDArray[np.integer]) -> tuple[IntArray, IntArray]:
    """``(key[order], order)`` with ``order = np.argsort(key, kind="stable")``."""
    n = len(key)
    k: IntArray = np.asarray(key, dtype=np.int64)
    if n == 0:
        return k.copy(), np.zeros(0, np.int64)
    lo, hi = int(k.min()), int(k.max())
    bits = max(1, (n - 1).bit_length())
    if not PACKED or (hi - lo).bit_length() + bits > 63:
        order: IntArray = np.argsort(k, kind="stable").astype(np.int64, copy=False)
        return k[order], order
    packed = (k - lo) << bits if lo else k << bits
    packed |= np.arange(n, dtype=np.int64)
    packed.sort()
    order = packed & ((1 << bits) - 1)
    packed >>= bits
    if lo:
        packed += lo
    return packed, order


def stable_argsort(key: NDArray[np.integer]) -> IntArray:
    """``np.argsort(key, kind="stable")``."""
    return sorted_with_order(key)[1]


def run_starts(sk: NDArray[Any]) -> NDArray[np.bool_]:
    """True at the first element of each run of equal values in a sorted array."""
    first = np.empty(len(sk), bool)
    first[:1] = True
    np.not_equal(sk[1:], sk[:-1], out=first[1:])
    return first


def offset_key(v: NDArray[np.int64]) -> IntArray:
    """One int64 key a row of an (n, 3) integer array (voxel indices), ordered as the rows
    are lexicographically: the offsets from the rows' least corner, in the span they take.
    Small keys leave :func:`sorted_with_order` room to pack the index in."""
    lo = column_min(v)
    span = column_max(v) - lo + 1
    return ((v[:, 0] - lo[0]) * span[1] + (v[:, 1] - lo[1])) * span[2] + (v[:, 2] - lo[2])


def unique_first(key: NDArray[np.integer]) -> tuple[IntArray, IntArray, IntArray]:
    """``np.unique(key, return_index=True, return_inverse=True)``: the distinct keys in
    ascending order, the index of each one's first occurrence, and each key's position
    among them."""
    sk, order = sorted_with_order(key)
    n = len(sk)
    first = run_starts(sk)
    inverse = np.empty(n, np.int64)
    inverse[order] = np.cumsum(first) - 1
    return sk[first], order[first], inverse


def column_min(a: NDArray[Any]) -> NDArray[Any]:
    """``a.min(axis=0)`` of a 2-D array, a column at a time."""
    return np.array([a[:, k].min() for k in range(a.shape[1])], dtype=a.dtype)


def column_max(a: NDArray[Any]) -> NDArray[Any]:
    """``a.max(axis=0)`` of a 2-D array, a column at a time."""
    return np.array([a[:, k].max() for k in range(a.shape[1])], dtype=a.dtype)


def finite_rows(a: NDArray[np.floating]) -> NDArray[np.bool_] | None:
    """``np.all(np.isfinite(a), axis=1)``, or None where every row is finite (as a rule:
    then the caller need not copy the array)."""
    fin = np.isfinite(a)
    if fin.all():
        return None
    return np.all(fin, axis=1)
