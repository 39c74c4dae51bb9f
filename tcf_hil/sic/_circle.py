"""Circle fits for stem slices: algebraic (Kåsa) and robust geometric (IRLS Gauss-Newton).

The geometric fit minimises sum w_i (|p_i - c| - r)² with Huber-type weights, starting from
the algebraic fit; the radius is kept within bounds, so a short, noisy arc gives a bounded
answer instead of a wild one.
"""

from __future__ import annotations

import math
import threading
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from emulators.jit import jit_enabled, numba_module

# Not registered as a kernel source (emulators.jit.register_kernel_source), for the reason
# given in _components.py: the kernel here calls nothing of another file.


class Circle(NamedTuple):
    cx: float
    cy: float
    r: float
    rms: float  # RMS of geometric residuals (m)
    arc_deg: float  # angular coverage of the points around the centre


def arc_coverage(ang: NDArray[np.float64]) -> float:
    if len(ang) < 2:
        return 0.0
    a = np.sort(np.mod(ang, 2.0 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2.0 * math.pi]]))
    return math.degrees(2.0 * math.pi - float(gaps.max()))


def fit_circle_algebraic(xy: NDArray[np.float64]) -> Circle | None:
    """Kåsa fit (linear least squares); None with fewer than 3 points or collinear points."""
    if len(xy) < 3:
        return None
    m = xy.mean(axis=0)
    p = xy - m
    A = np.column_stack([p, np.ones(len(p))])
    b = -(p[:, 0] ** 2 + p[:, 1] ** 2)
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 3:
        return None
    cx, cy = -sol[0] / 2.0, -sol[1] / 2.0
    r2 = cx * cx + cy * cy - sol[2]
    if not r2 > 0:
        return None
    r = math.sqrt(r2)
    d = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    arc = arc_coverage(np.arctan2(p[:, 1] - cy, p[:, 0] - cx))
    return Circle(float(cx + m[0]), float(cy + m[1]), r, rms, arc)


def fit_circle(xy: NDArray[np.float64], r_min: float = 0.01, r_max: float = 1.0,
               iterations: int = 15, huber_m: float = 0.01) -> Circle | None:
    """Robust geometric circle fit with the radius bounded to [r_min, r_max].

    Returns None with fewer than 3 points or when no bounded fit exists.
    """
    init = fit_circle_algebraic(xy)
    if init is None:
        return None
    m = xy.mean(axis=0)
    p = xy - m
    cx, cy = init.cx - m[0], init.cy - m[1]
    r = min(max(init.r, r_min), r_max)
    if math.hypot(cx, cy) > 10.0 * r_max:  # nearly straight points: start on the far side
        cx, cy = 0.0, 0.0
    lam = 1e-3
    for _ in range(iterations):
        dx, dy = p[:, 0] - cx, p[:, 1] - cy
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        res = d - r
        a = np.abs(res)
        w = np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12))
        J = np.column_stack([-dx / d, -dy / d, -np.ones(len(d))])
        JW = J * w[:, None]
        H = JW.T @ J
        g = JW.T @ res
        try:
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
        except np.linalg.LinAlgError:
            break
        cx, cy = cx + step[0], cy + step[1]
        r = min(max(r + step[2], r_min), r_max)
        if float(np.abs(step).max()) < 1e-7:
            break
    d = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)):
        return None
    arc = arc_coverage(np.arctan2(p[:, 1] - cy, p[:, 0] - cx))
    return Circle(float(cx + m[0]), float(cy + m[1]), float(r), rms, arc)


def kasa(q: Any, eps: float) -> tuple[float, float, Any, Any, int]:
    """The Kåsa system of ``q`` (k, 2) solved as :func:`fit_circle_algebraic` solves it:
    (mean x, mean y, A (k, 3) with the centred points in its first two columns, the lstsq
    solution, its rank; rank 0 with fewer than 3 points). ``eps``: machine epsilon (lstsq's
    ``rcond`` is eps * k, as numpy's ``None`` sets it): the same solver, the same bits."""
    k = q.shape[0]
    mx = 0.0
    my = 0.0
    for i in range(k):
        mx += q[i, 0]
        my += q[i, 1]
    mx /= k
    my /= k
    a = np.empty((k, 3))
    b = np.empty(k)
    for i in range(k):
        px = q[i, 0] - mx
        py = q[i, 1] - my
        a[i, 0] = px
        a[i, 1] = py
        a[i, 2] = 1.0
        b[i] = -(px * px + py * py)
    if k < 3:
        return mx, my, a, np.zeros(3), 0
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=eps * k)
    return mx, my, a, sol, int(rank)


def slice_centres(xy: Any, order: Any, lo: Any, hi: Any, min_points: int, max_r: float,
                  rcond: float, out: Any) -> None:
    """The centre line's slices of one stem in one pass: slice ``s`` holds the points
    ``xy[order[lo[s]:hi[s]]]`` (its (x, y), ``xy`` (n, 2) float64); ``out[s]`` gets its
    :func:`fit_circle_algebraic` centre where the fit exists, its radius is at most
    ``max_r`` and its arc at least 90 degrees, else the points' mean, and NaN where the slice
    has fewer than ``min_points`` points. ``rcond``: machine epsilon (see :func:`kasa`)."""
    for s in range(lo.shape[0]):
        k = hi[s] - lo[s]
        if k < min_points or k == 0:
            out[s, 0] = np.nan
            out[s, 1] = np.nan
            continue
        q = np.empty((k, 2))
        for i in range(k):
            q[i, 0] = xy[order[lo[s] + i], 0]
            q[i, 1] = xy[order[lo[s] + i], 1]
        mx, my, a, sol, rank = kasa(q, rcond)
        ok = False
        cx = -sol[0] / 2.0
        cy = -sol[1] / 2.0
        if rank >= 3:
            r2 = cx * cx + cy * cy - sol[2]
            if r2 > 0 and math.sqrt(r2) <= max_r:
                ang = np.empty(k)
                for i in range(k):
                    ang[i] = np.mod(np.arctan2(a[i, 1] - cy, a[i, 0] - cx), 2.0 * math.pi)
                ang.sort()
                gap = ang[0] + 2.0 * math.pi - ang[k - 1]
                for i in range(1, k):
                    gap = max(gap, ang[i] - ang[i - 1])
                ok = math.degrees(2.0 * math.pi - gap) >= 90.0
        if ok:
            out[s, 0] = cx + mx
            out[s, 1] = cy + my
        else:
            out[s, 0] = mx
            out[s, 1] = my


def robust_circle(xy: Any, r_min: float, r_max: float, iterations: int, huber_m: float,
                  eps: float, out: Any) -> None:
    """:func:`fit_circle`'s centre and radius in one compiled pass, the same numbers (the
    same LAPACK and BLAS calls in the same order): ``out`` = (cx, cy, r, 1) or (.., 0) where
    :func:`fit_circle` gives None. ``eps``: machine epsilon (lstsq's ``rcond`` as numpy's
    ``None`` sets it). A singular step raises numpy's LinAlgError (the caller then fits in
    numpy, which stops its iterations there)."""
    k = xy.shape[0]
    out[3] = 0.0
    if k < 3:
        return
    mx, my, p, sol, rank = kasa(xy, eps)  # p: the centred points in its first two columns
    if rank < 3:
        return
    acx = -sol[0] / 2.0
    acy = -sol[1] / 2.0
    r2 = acx * acx + acy * acy - sol[2]
    if not r2 > 0:
        return
    cx = (acx + mx) - mx
    cy = (acy + my) - my
    r = min(max(math.sqrt(r2), r_min), r_max)
    if math.hypot(cx, cy) > 10.0 * r_max:
        cx, cy = 0.0, 0.0
    lam = 1e-3
    J = np.empty((k, 3))
    JW = np.empty((k, 3))
    res = np.empty(k)
    M = np.empty((3, 3))
    for _ in range(iterations):
        for i in range(k):
            dx = p[i, 0] - cx
            dy = p[i, 1] - cy
            d = max(math.hypot(dx, dy), 1e-12)
            rs = d - r
            aa = abs(rs)
            w = 1.0 if aa <= huber_m else huber_m / max(aa, 1e-12)
            res[i] = rs
            J[i, 0] = -dx / d
            J[i, 1] = -dy / d
            J[i, 2] = -1.0
            JW[i, 0] = J[i, 0] * w
            JW[i, 1] = J[i, 1] * w
            JW[i, 2] = J[i, 2] * w
        H = JW.T @ J
        g = JW.T @ res
        for u in range(3):
            for v in range(3):
                M[u, v] = H[u, v] + (lam * (H[u, u] + 1e-12) if u == v else lam * 0.0)
        step = np.linalg.solve(M, -g)
        cx, cy = cx + step[0], cy + step[1]
        r = min(max(r + step[2], r_min), r_max)
        if max(abs(step[0]), abs(step[1]), abs(step[2])) < 1e-7:
            break
    out[0] = cx + mx
    out[1] = cy + my
    out[2] = r
    out[3] = 1.0 if (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) else 0.0


_KERNELS: list[Any] = []  # slice_centres and robust_circle compiled, both once built
_build_lock = threading.Lock()
_wanted = False  # see use_compiled_fits


def _build() -> None:
    """Declare both kernels (numba compiles them, or loads them from its cache, at their
    first call); once, whichever thread asks first."""
    global kasa
    with _build_lock:
        if _KERNELS:
            return
        njit = numba_module().njit
        if not hasattr(kasa, "py_func"):  # not yet numba's
            kasa = njit(cache=True, nogil=True, inline="always")(kasa)
        _KERNELS.extend((njit(cache=True, nogil=True)(slice_centres),
                         njit(cache=True, nogil=True)(robust_circle)))


def use_compiled_fits(on: bool = True) -> None:
    """Let the stem algorithm's fits run compiled in this process (the centre line and
    breast-height fits here, the field algorithm's in :mod:`tcf_hil.sic._fitkernels`: the
    same numbers): offline cells, experiments and a live SIC's stems worker process. A live
    SIC's frame loop keeps them in numpy: a cold compile takes about 10 s, and a first tile
    run stalled that long in the frame loop loses the frames the sensor sends meanwhile
    (320 frames of 500 at --speed 2, measured), where a warm cache loads in a fraction of a
    second; in the worker it delays only the first tile's stems."""
    global _wanted
    _wanted = on


def compiled_fits_wanted() -> bool:
    """Whether :func:`use_compiled_fits` asked for compiled fits in this process."""
    return _wanted


def slice_centres_kernel() -> Any:
    """:func:`slice_centres` compiled, or None where compiled fits are not wanted here
    (:func:`use_compiled_fits`) or kernels are off (the caller fits slice by slice in
    numpy)."""
    if not (_wanted and jit_enabled()):
        return None
    if not _KERNELS:
        _build()
    return _KERNELS[0]


def fit_circle_centre(xy: NDArray[np.float64], r_max: float) -> tuple[float, float, float] | None:
    """(cx, cy, r) of :func:`fit_circle` (default bounds but ``r_max``), compiled where
    kernels are on."""
    if slice_centres_kernel() is None:
        c = fit_circle(xy, r_max=r_max)
        return None if c is None else (c.cx, c.cy, c.r)
    out = np.zeros(4)
    try:
        _KERNELS[1](np.ascontiguousarray(xy, np.float64), 0.01, r_max, 15, 0.01,
                    float(np.finfo(np.float64).eps), out)
    except np.linalg.LinAlgError:  # numpy's fit stops at a singular step; so does this
        c = fit_circle(xy, r_max=r_max)
        return None if c is None else (c.cx, c.cy, c.r)
    return (float(out[0]), float(out[1]), float(out[2])) if out[3] else None
