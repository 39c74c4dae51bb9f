"""The field algorithm's circle fits (:mod:`tcf_hil.sic._field`) compiled: the same numbers,
bit for bit, as their numpy forms, several times faster.

A stem slice's fit is a RANSAC (MSAC) over a few hundred three-point circles, each scored
against every point of the slice, then Gauss-Newton refits; in numpy each of those is a
dozen small array operations, and on a natural stand's map the stem algorithm made about
8,400 of them a 2048x10 tile batch, 80 % of its time (profiled on Forest X's final map).

Same bits: the element-wise steps are the same IEEE operations in the same order
(``math.hypot`` is the C library's ``hypot``, as numpy's), and every sum is numpy's own:
:func:`pairwise_sum` is numpy's pairwise summation (blocks of 128 summed in eight lanes,
halved above that), which ``ndarray.sum`` uses along a contiguous axis, and a mean over the
rows of an (n, 2) array is a plain running sum, as numpy reduces an outer axis. The 3 x 3
solve is LAPACK's ``gesv`` through numba (SciPy's OpenBLAS build there, numpy's here: the
same bits on 220,000 solves checked, and on every fit of the tests and the tiles). The
kernels take what the stem algorithm passes (C-ordered float64 points, a positive
tolerance, at least one point); anything else stays in numpy. Tests hold the kernels to the
numpy forms on random slices and on whole tiles.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from emulators.jit import jit_enabled, numba_module
from tcf_hil.sic._circle import compiled_fits_wanted

# Not registered as a kernel source (emulators.jit.register_kernel_source), for the reason
# given in _components.py: these kernels call nothing of another file.


def _block_sum(a: Any, lo: int, n: int) -> float:
    """numpy's sum of at most 128 values: in order below 8, else in eight lanes."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0 = a[lo]
    r1 = a[lo + 1]
    r2 = a[lo + 2]
    r3 = a[lo + 3]
    r4 = a[lo + 4]
    r5 = a[lo + 5]
    r6 = a[lo + 6]
    r7 = a[lo + 7]
    i = 8
    m = n - (n % 8)
    while i < m:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


def pairwise_sum(a: Any, lo: int, n: int) -> float:
    """numpy's sum of ``a[lo:lo + n]`` (contiguous float64), the same bits: its pairwise
    summation (numpy/_core/src/umath/loops_utils.h.src, ``pairwise_sum``): blocks of at
    most 128 (:func:`_block_sum`), a longer run halved (the first half a multiple of 8)
    and its halves' sums added. Written without recursion (numba's cache does not keep a
    recursive kernel safely): a stack of (start, length, halves done)."""
    if n <= 128:
        return _block_sum(a, lo, n)
    f_lo = np.empty(96, np.int64)
    f_n = np.empty(96, np.int64)
    f_done = np.empty(96, np.bool_)
    vals = np.empty(96)
    sp = 0
    vp = 0
    f_lo[0], f_n[0], f_done[0] = lo, n, False
    sp = 1
    while sp > 0:
        sp -= 1
        s_lo, s_n, done = f_lo[sp], f_n[sp], f_done[sp]
        if s_n <= 128:
            vals[vp] = _block_sum(a, s_lo, s_n)
            vp += 1
        elif done:  # both halves summed: left + right
            vals[vp - 2] = vals[vp - 2] + vals[vp - 1]
            vp -= 1
        else:
            n2 = s_n // 2
            n2 -= n2 % 8
            f_lo[sp], f_n[sp], f_done[sp] = s_lo, s_n, True
            f_lo[sp + 1], f_n[sp + 1], f_done[sp + 1] = s_lo + n2, s_n - n2, False
            f_lo[sp + 2], f_n[sp + 2], f_done[sp + 2] = s_lo, n2, False
            sp += 3
    return float(vals[0])


def msac_pick(xy: Any, cx: Any, cy: Any, r: Any, cand: Any, tol: float, hollow: bool,
              buf: Any) -> int:
    """The position in ``cand`` of the candidate circle (centre ``cx[j], cy[j]``, radius
    ``r[j]``) with the least MSAC cost over the points ``xy`` (n, 2): as
    :func:`tcf_hil.sic._field.ransac_circle` scores them in numpy (the first of equal
    costs). ``buf``: (n,) float64 scratch.

    A candidate is left as soon as the running sum of its (non-negative) costs passes the
    best so far by a millionth: its full sum, however rounded, cannot be the least (the
    rounding of n terms is n ulps, far below that), so the pick is the same."""
    n = xy.shape[0]
    best = 0
    best_cost = math.inf
    for k in range(cand.shape[0]):
        j = cand[k]
        cj, dj, rj = cx[j], cy[j], r[j]
        tc = min(tol, max(0.5 * rj, 0.005))
        lim = -2.0 * tc
        bound = best_cost * (1.0 + 1e-6)
        run = 0.0
        lost = False
        for lo in range(0, n, 256):
            for i in range(lo, min(lo + 256, n)):
                sres = math.hypot(xy[i, 0] - cj, xy[i, 1] - dj) - rj
                c = min(abs(sres) / tc, 1.0)
                c = c * c
                if hollow and sres < lim:
                    c += 1.0
                buf[i] = c
                run += c
            if run > bound:
                lost = True
                break
        if lost:
            continue
        s = pairwise_sum(buf, 0, n)
        if s < best_cost or k == 0:
            best, best_cost = k, s
    return best


def ransac_pick(xy: Any, idx: Any, r_max: float, near_x: float, near_y: float,
                near_m: float, has_near: bool, tol: float, hollow: bool, buf: Any,
                out: Any) -> int:
    """:func:`tcf_hil.sic._field.ransac_circle` from its drawn triples on: each try's circle
    through ``xy[idx[k]]`` (k, 3) as numpy computes them (the same operations in the same
    order, element by element), those of radius 0.01 .. ``r_max`` (centred within
    ``near_m`` of the near point where ``has_near``) scored by :func:`msac_pick`. Returns
    the try picked, its circle in ``out`` (cx, cy, r), or -1 where no try makes one."""
    t = idx.shape[0]
    cx = np.empty(t)
    cy = np.empty(t)
    r = np.empty(t)
    cand = np.empty(t, np.int64)
    m = 0
    for k in range(t):
        p1x = xy[idx[k, 0], 0]
        p1y = xy[idx[k, 0], 1]
        ax = xy[idx[k, 1], 0] - p1x
        ay = xy[idx[k, 1], 1] - p1y
        bx = xy[idx[k, 2], 0] - p1x
        by = xy[idx[k, 2], 1] - p1y
        dd = 2.0 * (ax * by - ay * bx)
        ok = abs(dd) > 1e-12
        if not ok:
            dd = 1.0
        a2 = ax * ax + ay * ay
        b2 = bx * bx + by * by
        ux = (by * a2 - ay * b2) / dd
        uy = (ax * b2 - bx * a2) / dd
        rk = math.hypot(ux, uy)
        ok = ok and rk <= r_max and rk >= 0.01
        cxk = p1x + ux
        cyk = p1y + uy
        if has_near:
            ok = ok and math.hypot(cxk - near_x, cyk - near_y) <= near_m
        cx[k] = cxk
        cy[k] = cyk
        r[k] = rk
        if ok:
            cand[m] = k
            m += 1
    if m == 0:
        return -1
    j = cand[msac_pick(xy, cx, cy, r, cand[:m], tol, hollow, buf)]
    out[0] = cx[j]
    out[1] = cy[j]
    out[2] = r[j]
    return j


def refine(q: Any, cx: float, cy: float, r: float, huber_m: float, iterations: int,
           out: Any) -> None:
    """:func:`tcf_hil.sic._field.refine_circle`'s Gauss-Newton in one compiled pass, the
    same numbers: ``out`` = (cx, cy, r, rms, 1), or (.., 0) where it gives None. A singular
    step raises numpy's LinAlgError (the numpy form then gives None)."""
    n = q.shape[0]
    out[4] = 0.0
    mx = 0.0
    my = 0.0
    for i in range(n):
        mx += q[i, 0]
        my += q[i, 1]
    mx /= n
    my /= n
    x = np.empty(n)
    y = np.empty(n)
    for i in range(n):
        x[i] = q[i, 0] - mx
        y[i] = q[i, 1] - my
    cx -= mx
    cy -= my
    t = np.empty((9, n))  # w, w ux, w uy, w ux ux, w ux uy, w uy uy, w ux res, w uy res, w res
    H = np.empty((3, 3))
    g = np.empty(3)
    for _ in range(iterations):
        for i in range(n):
            dx = x[i] - cx
            dy = y[i] - cy
            d = max(math.hypot(dx, dy), 1e-12)
            res = d - r
            a = abs(res)
            w = 1.0 if a <= huber_m else huber_m / max(a, 1e-12)
            ux = dx / d
            uy = dy / d
            t[0, i] = w
            t[1, i] = w * ux
            t[2, i] = w * uy
            t[3, i] = w * ux * ux
            t[4, i] = w * ux * uy
            t[5, i] = w * uy * uy
            t[6, i] = w * ux * res
            t[7, i] = w * uy * res
            t[8, i] = w * res
        sw = pairwise_sum(t[0], 0, n)
        sx = pairwise_sum(t[1], 0, n)
        sy = pairwise_sum(t[2], 0, n)
        H[0, 0] = pairwise_sum(t[3], 0, n)
        H[0, 1] = H[1, 0] = pairwise_sum(t[4], 0, n)
        H[1, 1] = pairwise_sum(t[5], 0, n)
        H[0, 2] = H[2, 0] = sx
        H[1, 2] = H[2, 1] = sy
        H[2, 2] = sw
        g[0] = pairwise_sum(t[6], 0, n)
        g[1] = pairwise_sum(t[7], 0, n)
        g[2] = pairwise_sum(t[8], 0, n)
        step = np.linalg.solve(H, g)
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) or r <= 0:
            return
        if max(abs(step[0]), abs(step[1]), abs(step[2])) < 1e-6:
            break
    for i in range(n):
        e = math.hypot(x[i] - cx, y[i] - cy) - r
        t[0, i] = e * e
    out[0] = cx + mx
    out[1] = cy + my
    out[2] = r
    out[3] = math.sqrt(pairwise_sum(t[0], 0, n) / n)
    out[4] = 1.0


def trimmed(q: Any, cx: float, cy: float, r: float, rms: float, tol: float, rounds: int,
            out: Any) -> None:
    """:func:`tcf_hil.sic._field.trimmed_circle` in one compiled pass, the same numbers:
    ``out`` = (cx, cy, r, rms) of the circle it returns (the start's where it keeps it)."""
    n = q.shape[0]
    out[0], out[1], out[2], out[3] = cx, cy, r, rms
    res = np.empty(n)
    neg = np.empty(n)
    ref = np.empty(5)
    for _ in range(rounds):
        k = 0
        for i in range(n):
            res[i] = math.hypot(q[i, 0] - out[0], q[i, 1] - out[1]) - out[2]
            if res[i] < 0:
                neg[k] = -res[i]
                k += 1
        if k >= 3:
            v = np.sort(neg[:k])
            # numpy's median: the middle value, or the mean of the two (0 + a + b) / 2
            med = v[k // 2] if k % 2 == 1 else (0.0 + v[k // 2 - 1] + v[k // 2]) / 2.0
            sigma = 1.4826 * med
        else:
            sigma = tol / 2.5
        cut = max(2.5 * sigma, 0.005)
        low = -max(3.0 * sigma, 0.005) - 0.005
        m = 0
        for i in range(n):
            if res[i] <= cut and res[i] >= low:
                m += 1
        if m < 3:
            return
        sub = np.empty((m, 2))
        m = 0
        for i in range(n):
            if res[i] <= cut and res[i] >= low:
                sub[m, 0] = q[i, 0]
                sub[m, 1] = q[i, 1]
                m += 1
        try:
            refine(sub, out[0], out[1], out[2], 1.0, 5, ref)
        except Exception:  # a singular step: numpy's LinAlgError, the numpy form's None
            return
        if ref[4] == 0.0:
            return
        done = (abs(ref[2] - out[2]) < 1e-4
                and math.hypot(ref[0] - out[0], ref[1] - out[1]) < 1e-4)
        out[0], out[1], out[2], out[3] = ref[0], ref[1], ref[2], ref[3]
        if done:
            return


_KERNELS: dict[str, Any] = {}
_build_lock = threading.Lock()


def fit_kernels() -> dict[str, Any] | None:
    """The kernels the fits call, by name (``ransac_pick``, ``refine``, ``trimmed``),
    compiled, or None where the stem algorithm's fits stay in numpy here
    (:func:`tcf_hil.sic._circle.use_compiled_fits` not called in this process, or kernels
    off). Called for every fit: cheap once built."""
    if not compiled_fits_wanted():
        return None
    if _KERNELS:
        return _KERNELS
    if not jit_enabled():
        return None
    global _block_sum, pairwise_sum, msac_pick, refine
    with _build_lock:
        if not _KERNELS:
            njit = numba_module().njit
            if not hasattr(pairwise_sum, "py_func"):  # not yet numba's (kernels call these)
                _block_sum = njit(cache=True, nogil=True)(_block_sum)
                pairwise_sum = njit(cache=True, nogil=True)(pairwise_sum)
                msac_pick = njit(cache=True, nogil=True)(msac_pick)
                refine = njit(cache=True, nogil=True)(refine)
            built = {"refine": refine,
                     "ransac_pick": njit(cache=True, nogil=True)(ransac_pick),
                     "trimmed": njit(cache=True, nogil=True)(trimmed)}
            _KERNELS.update(built)  # all three at once: a thread that sees one sees all
    return _KERNELS


def warm() -> None:
    """Compile (or load from numba's cache) the kernels now, on a small slice, where a
    process can afford the wait before its first fit (a cold compile: about 14 s on this
    project's 2-core machine; a warm cache: under a second)."""
    kernels = fit_kernels()
    if kernels is None:
        return
    a = np.linspace(0.0, 3.0, 16)
    q = np.column_stack([0.2 * np.cos(a), 0.2 * np.sin(a)])
    idx = np.arange(48).reshape(16, 3) % 16
    kernels["ransac_pick"](q, idx, 0.5, 0.0, 0.0, 0.1, True, 0.01, True, np.empty(16),
                           np.empty(3))
    out = np.empty(5)
    kernels["refine"](q, 0.01, 0.0, 0.19, 0.005, 5, out)
    kernels["trimmed"](q, 0.01, 0.0, 0.19, 0.0, 0.01, 3, out)


__all__ = ["fit_kernels", "msac_pick", "pairwise_sum", "ransac_pick", "refine", "trimmed",
           "warm"]
