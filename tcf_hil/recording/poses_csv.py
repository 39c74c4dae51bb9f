"""``sensor_poses.csv``'s rows made from arrays: the very text Python's ``f"{v:.6f}"`` and
``str(int)`` write, built with a few array operations per column instead of one format
call per number (a 2048x10 frame has 2048 rows of eight numbers: 9 ms a frame formatted
one by one, about a tenth of that here).

The rounding is exact, as Python's: ``v * 10**d`` is split into the double nearest it and
the error of that product (Dekker's exact product, T. J. Dekker, "A floating-point technique
for extending the available precision", Numer. Math. 18, 1971), so a product that lands on
a half in doubles but not in exact arithmetic rounds the way the exact value does, and an
exact half (a dyadic value such as 2**-7 at six decimals) rounds to even. Values this does
not cover (not finite, or ``|v| * 10**d`` at or past 2**51) are left to Python's formatting.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from emulators.jit import compiled, register_kernel_source

register_kernel_source(__file__)  # _rows_kernel is a kernel (see emulators.jit)

_SPLIT = 134217729.0  # 2**27 + 1: Veltkamp's split of a double into two 26-bit halves
_LIMIT = float(2**51)  # below it a double's spacing is at most 1/4: the rounding is exact
_FILL = 0  # a byte that no row holds: removed at the end


def _split(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    c = _SPLIT * a
    hi = c - (c - a)
    return hi, a - hi


def _round_scaled(a: NDArray[np.float64], decimals: int) -> NDArray[np.int64]:
    """``a * 10**decimals`` (``a >= 0``) rounded to the nearest integer, ties to even, as
    the exact product rounds."""
    s = float(10**decimals)
    x = a * s
    ah, al = _split(a)
    sh, sl = _split(np.array(s))
    err = ((ah * sh - x) + ah * sl + al * sh) + al * sl  # x + err == a * s exactly
    f = np.floor(x)
    fr = x - f  # exact below 2**51
    r = f.astype(np.int64)
    up = (fr > 0.5) | ((fr == 0.5) & ((err > 0) | ((err == 0) & (r & 1).astype(bool))))
    return r + up


_POW10 = 10 ** np.arange(1, 19, dtype=np.int64)  # n has k + 1 digits where k of these are <= n
_QUAD = np.array([list(f"{k:04d}".encode()) for k in range(10_000)], np.uint8)  # 4 digits


def _digits(n: NDArray[np.int64], keep: int) -> NDArray[np.uint8]:
    """``n >= 0`` (any shape) as ASCII digits along a new last axis, right-aligned in as
    many columns as the largest needs (at least ``keep``), four at a time from a table;
    leading zeros beyond the last ``keep`` are the fill byte."""
    top = int(n.max()) if n.size else 0
    width = max(keep, len(str(top)))
    quads = -(-width // 4)
    out = np.empty((*n.shape, 4 * quads), np.uint8)
    rest = n
    for k in range(quads - 1, -1, -1):
        rest, d = np.divmod(rest, 10_000)
        out[..., 4 * k:4 * k + 4] = _QUAD[d]
    out = out[..., 4 * quads - width:]
    shown = np.maximum(np.searchsorted(_POW10, n, side="right") + 1, keep)  # digits each shows
    out[np.arange(width) < (width - shown)[..., None]] = _FILL
    return out


def _fields(v: NDArray[np.float64], decimals: int) -> NDArray[np.uint8] | None:
    """Columns ``v`` (n, k) as fixed-width slots (n, k, width): sign, integer digits, point,
    decimals; None where a value is not covered (see the module doc)."""
    a = np.abs(np.ascontiguousarray(v))
    if not np.all(np.isfinite(a)) or np.any(a >= _LIMIT / 10**decimals):
        return None
    whole, frac = np.divmod(_round_scaled(a, decimals), 10**decimals)
    sign = np.where(np.signbit(v), ord("-"), _FILL).astype(np.uint8)[..., None]
    parts = [sign, _digits(whole, 1)]
    if decimals:
        parts += [np.full((*v.shape, 1), ord("."), np.uint8), _digits(frac, decimals)]
    return np.concatenate(parts, axis=-1)


def _int_fields(t: NDArray[np.int64]) -> NDArray[np.uint8] | None:
    if np.any(t == np.iinfo(np.int64).min):
        return None
    sign = np.where(t < 0, ord("-"), _FILL).astype(np.uint8)[..., None]
    return np.concatenate([sign, _digits(np.abs(t), 1)], axis=-1)


def put_whole(out: Any, p: int, q: Any, digits: Any) -> int:
    """The decimal digits of ``q`` (>= 0) into ``out`` from ``p`` (``digits``: scratch of
    20 or more); where they end."""
    m = 0
    while True:
        digits[m] = 48 + q % 10
        q //= 10
        m += 1
        if q == 0:
            break
    for e in range(m - 1, -1, -1):
        out[p] = digits[e]
        p += 1
    return p


_put_whole = put_whole  # compiled before the kernel that calls it (:func:`pose_rows`)


def _rows_kernel(t: Any, v: Any, scale: Any, limit: Any, unit: Any, decs: Any,
                 out: Any) -> int:
    """The rows of :func:`pose_rows` into ``out`` (bytes enough), compiled: the very
    arithmetic of the array path (:func:`_round_scaled`, in its order of operations), a
    value at a time; the bytes written, or -1 where a value is not covered (the caller then
    takes the array path). ``scale``, ``limit``, ``unit``: each column's ``10**d`` as a
    double, its bound (:data:`_LIMIT` ``/ 10**d``) and ``10**d`` as an integer."""
    n, k = v.shape
    p = 0
    digits = np.empty(24, np.uint8)
    c = _SPLIT * scale
    for i in range(n):
        q = t[i]
        if q == -9223372036854775807 - 1:
            return -1
        if q < 0:
            out[p] = 45  # "-"
            p += 1
            q = -q
        p = _put_whole(out, p, q, digits)
        for j in range(k):
            x = v[i, j]
            a = abs(x)
            if not a < limit[j]:  # not finite, or too large to round exactly here
                return -1
            s = scale[j]
            sh = c[j] - (c[j] - s)
            sl = s - sh
            y = a * s
            ca = _SPLIT * a
            ah = ca - (ca - a)
            al = a - ah
            err = ((ah * sh - y) + ah * sl + al * sh) + al * sl
            f = math.floor(y)
            fr = y - f
            r = np.int64(f)
            if fr > 0.5 or (fr == 0.5 and (err > 0 or (err == 0 and r % 2 == 1))):
                r += 1
            out[p] = 44  # ","
            p += 1
            if math.copysign(1.0, x) < 0:
                out[p] = 45
                p += 1
            whole, frac = r // unit[j], r % unit[j]
            p = _put_whole(out, p, whole, digits)
            if decs[j] > 0:
                out[p] = 46  # "."
                p += 1
                for e in range(decs[j] - 1, -1, -1):
                    out[p + e] = 48 + frac % 10
                    frac //= 10
                p += decs[j]
        out[p] = 10  # "\n"
        p += 1
    return p


def pose_rows(t_ns: NDArray[np.int64], values: NDArray[np.float64],
              decimals: tuple[int, ...] = (6, 6, 6, 9, 9, 9, 9)) -> str:
    """CSV rows (``\\n`` ended) of ``t_ns`` (n,) as integers and ``values`` (n, k) with the
    given decimals each: ``str(int(t))`` and ``f"{v:.{d}f}"``, comma separated (compiled
    where kernels are on: a 2048-row frame in a fraction of a millisecond; else from
    arrays)."""
    t = np.asarray(t_ns, np.int64)
    v = np.asarray(values, np.float64)
    n = len(t)
    if n == 0:
        return ""
    global _put_whole
    _put_whole = compiled(put_whole) or put_whole  # (numba calls only compiled functions)
    kernel = compiled(_rows_kernel)
    if kernel is not None and t.ndim == 1 and v.ndim == 2 and v.shape == (n, len(decimals)) \
            and max(decimals, default=0) <= 15:
        d = np.array(decimals, np.int64)
        room = n * (22 + int(np.sum(d + 20)))  # sign, 19 digits, comma, point, decimals
        out = np.empty(room, np.uint8)
        got = kernel(t, np.ascontiguousarray(v), np.array([float(10**x) for x in decimals]),
                     np.array([_LIMIT / 10**x for x in decimals]), 10**d, d, out)
        if got >= 0:
            return out[:got].tobytes().decode("ascii")
    return _array_rows(t, v, decimals)


def warm_up() -> None:
    """Compile :func:`pose_rows`' kernel now (numba, or its on-disk cache; importing numba
    first): about a second on a loaded 2-core machine, which a live stream's frame producer
    spends before its first frame rather than at the track's first."""
    pose_rows(np.zeros(1, np.int64), np.zeros((1, 7)), (6, 6, 6, 9, 9, 9, 9))


def _array_rows(t: NDArray[np.int64], v: NDArray[np.float64], decimals: tuple[int, ...]
                ) -> str:
    n = len(t)
    pieces: list[NDArray[np.uint8]] = []
    head = _int_fields(t[:, None])
    if head is None:
        return _rows_one_by_one(t, v, decimals)
    pieces.append(head[:, 0])
    j = 0
    while j < len(decimals):  # a run of columns with the same decimals at a time
        e = j
        while e < len(decimals) and decimals[e] == decimals[j]:
            e += 1
        f = _fields(v[:, j:e], decimals[j])
        if f is None:
            return _rows_one_by_one(t, v, decimals)
        f = np.concatenate([np.full((n, e - j, 1), ord(","), np.uint8), f], axis=-1)
        pieces.append(f.reshape(n, -1))
        j = e
    pieces.append(np.full((n, 1), ord("\n"), np.uint8))
    grid = np.hstack(pieces)
    return grid[grid != _FILL].tobytes().decode("ascii")


def _rows_one_by_one(t_ns: NDArray[np.int64], values: NDArray[np.float64],
                     decimals: tuple[int, ...]) -> str:
    return "".join(
        ",".join([str(int(t)), *(f"{v:.{d}f}" for v, d in zip(row, decimals, strict=True))])
        + "\n" for t, row in zip(np.asarray(t_ns).tolist(), np.asarray(values).tolist(),
                                 strict=True))
