"""The field-grade stem algorithm: what a harvester maker's stem program does where branches,
porous crowns, understory and a real beam's footprint are in the points.

Two parts:

**Mixed edge returns** (:func:`edge_widths`, on a frame's range image before it goes into the
map). A beam of divergence θ (Ouster's OS0 datasheet: 0.35°, FWHM) that straddles a stem's
silhouette returns from the stem at the pixel's own angle, beyond the silhouette: the stem
looks wider by up to about a footprint on each side, which grows with range (Ringdahl et al.
2013, Remote Sens. 5(10):4839, "Enhanced algorithms for estimating tree trunk diameter
using 2D laser scanner": diameters ~40 % too large until the beam width was compensated;
Tang, Huber & Akinci 2009, "Quantification of edge loss of laser scanned data at spatial
discontinuities", Autom. Constr. 18(8): mixed pixels within a beam width of a range jump).
A pixel is an *edge return* when any pixel of its row within one FWHM of azimuth (one
column in 1024x10 and 512x10, two in 2048x10) returned nothing or a range more than
``edge_jump_m`` away. Each edge return carries its footprint's half width at its range
(θ/2 · r): the stem fits below use the other returns where they have them, and take that
half width off the radius where a stem is seen only through edge returns.

**Stems among branches, crowns and understory** (:func:`field_stems`, per map tile). The
points of a band above the ground are binned in 10 cm voxels; each voxel's neighbourhood
(3 x 3 x 3 voxels) gives a local PCA (as dendromatics / 3DFin's verticality, Cabo et al.
2018, Int. J. Appl. Earth Obs. Geoinf. 69:164, and Liang et al. 2012's point-level stem
features): a stem's bark is a surface whose normal is horizontal, a thin stem a vertical
line; needles scatter in every direction and branches run sideways. The stem-like voxels
are joined into vertical components (bridging the band at the sensor's height that a level
OS0-64 never samples): each bark patch votes along its normal for where the stem's axis
can be, and each place that gathers votes through the band is verified with circles:
RANSAC on slices for the axis (Olofsson, Holmgren & Olsson 2014, Remote Sens. 6(5):4323,
"Tree stem and height measurements using terrestrial laser scanning and the RANSAC
algorithm"), then one robust circle at breast height on the returns brought onto that axis.
The stem is then followed up through the crown slice by slice (the stem curve: centre and
diameter every ``curve_step_m``, as FGI reports harvester stem curves, Remote Sens. 16(17)
:3292, 2024), and the class comes from that curve's maxcurve.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.sic._circle import Circle, arc_coverage
from tcf_hil.sic._fast import column_max, column_min, unique_first
from tcf_hil.sic._fitkernels import fit_kernels
from tcf_hil.sic._params import StemParams

FloatArray = NDArray[np.float64]
BREAST_HEIGHT_M = 1.3

# The beam divergence (FWHM) of a sensor family, from its datasheet, by the metadata's
# prod_line prefix: OS0 0.35 deg (Ouster OS0 datasheet; also EGU26-9310, Holmgren et al.:
# "beam divergences were 0.35 and 0.18 degrees" for the OS0 and OS1 on a harvester); the
# first OS1 datasheet labels its figure "FWHM". Unknown sensors: the OS0's.
DIVERGENCE_DEG = {"OS-0": 0.35, "OS0": 0.35, "OS-1": 0.18, "OS1": 0.18}


def divergence_of(prod_line: str, default: float = 0.35) -> float:
    """The datasheet's FWHM beam divergence (degrees) for a metadata ``prod_line``."""
    p = (prod_line or "").upper()
    for prefix, deg in DIVERGENCE_DEG.items():
        if p.startswith(prefix):
            return deg
    return default


def edge_widths(range_mm: NDArray[np.integer], cols: NDArray[np.int64], columns: int,
                divergence_deg: float, jump_m: float, reach_fwhm: float = 1.0
                ) -> NDArray[np.float32]:
    """The footprint half width (m) of every edge return of a frame's range image, 0 for
    the others (and for pixels without a return).

    ``range_mm`` (H, k): the ranges of the frame's columns ``cols`` (k, ascending measurement
    ids of ``columns`` a frame). A return is an edge return when a pixel of its row within
    ``ceil(divergence / column spacing)`` columns returned nothing, is missing, or lies more
    than ``jump_m`` nearer or farther.
    """
    r = np.asarray(range_mm, dtype=np.float64) * 1e-3
    h, k = r.shape
    edge = np.zeros((h, k), dtype=bool)
    spacing = 360.0 / columns
    reach = max(1, math.ceil(reach_fwhm * divergence_deg / spacing - 1e-6))
    whole = k == columns and k > 2 * reach and bool((cols == np.arange(columns)).all())
    for s in range(1, reach + 1):
        if whole:  # a whole frame: the last column is the first one's neighbour
            b = np.roll(r, -s, axis=1)
            jump = (r == 0) | (b == 0) | (np.abs(r - b) > jump_m)
            edge |= jump
            edge |= np.roll(jump, s, axis=1)
            continue
        if k <= s:
            edge[:] = True
            break
        adjacent = (cols[s:] - cols[:-s]) == s
        a, b = r[:, :-s], r[:, s:]
        jump = (a == 0) | (b == 0) | (np.abs(a - b) > jump_m) | ~adjacent[None, :]
        edge[:, :-s] |= jump
        edge[:, s:] |= jump
        edge[:, :s] = True  # a part of a frame: its first and last columns' neighbours
        edge[:, -s:] = True  # are not known
    half = 0.5 * math.radians(divergence_deg)
    out: NDArray[np.float32] = np.where(edge & (r > 0), half * r, 0.0).astype(np.float32)
    return out


# ------------------------------------------------------------------------------ circle fits
_LOCAL_FROM = 200  # a slice with more points than this samples locally too
_LOCAL_K = 48


def _kernel_input(q: FloatArray) -> bool:
    """Points the compiled fits take as numpy's own (C-ordered float64, some)."""
    return q.dtype == np.float64 and q.flags.c_contiguous and len(q) > 0


_rngs = threading.local()  # per thread: {n: (generator, its state as seeded with n)}


def _slice_rng(n: int) -> np.random.Generator:
    """``np.random.default_rng(n)`` as it starts (the same draws) at a tenth of the cost
    (seeding hashes the seed: 19 us, a fit's own work is a few hundred): a generator kept
    per ``n`` and this thread, set back to its seeded state."""
    cache: dict[int, tuple[np.random.Generator, Any]] | None = getattr(
        _rngs, "cache", None)
    if cache is None:
        cache = _rngs.cache = {}
    hit = cache.get(n)
    if hit is None:
        if len(cache) >= 4096:
            cache.clear()
        g = np.random.default_rng(n)
        cache[n] = (g, g.bit_generator.state)
        return g
    hit[0].bit_generator.state = hit[1]
    return hit[0]


def ransac_circle(xy: FloatArray, *, r_max: float, tol: float, tries: int = 256,
                  rng: np.random.Generator | None = None, near: FloatArray | None = None,
                  near_m: float = 0.1, local_m: float = 0.1, hollow: bool = True
                  ) -> tuple[float, float, float, NDArray[np.bool_]] | None:
    """The circle through three of the points that the points lie on best (MSAC: the least
    sum of squared residuals truncated at ``tol``, or half the radius where that is less),
    radius at most ``r_max`` (and its centre within ``near_m`` of ``near`` where given);
    returns (cx, cy, r, inliers) or None. ``local_m``: in a slice of many points, half the
    tries take their second and third point within this of the first (0: all drawn from
    the whole slice). ``hollow``: a point well inside a circle costs twice an outlier."""
    n = len(xy)
    if n < 3:
        return None
    g = rng or _slice_rng(n)
    idx = g.integers(0, n, size=(tries, 3))
    if local_m and n > _LOCAL_FROM:
        # in clutter (a stem inside a crown: a tenth of a slice's points on the bark) three
        # points drawn from the whole slice all lie on the bark once in a thousand tries;
        # half the tries draw the second and third point among the first's neighbours
        # (within ``local_m``), as NAPSAC does (Torr et al. 2002, "NAPSAC: high noise, high
        # dimensional robust estimation"), so that a third of them come from one surface
        from scipy.spatial import cKDTree

        h = tries // 2
        _d, nb = cKDTree(xy).query(xy[idx[h:, 0]], k=_LOCAL_K, distance_upper_bound=local_m)
        cnt = (nb < n).sum(axis=1)  # the first is the point itself
        m = len(cnt)
        # from the farther half of the neighbours: three points a few millimetres apart
        # give a circle the noise decides
        lo = np.maximum(cnt // 2, 1)
        j2 = lo + (g.random(m) * np.maximum(cnt - lo, 1)).astype(np.int64)
        j3 = lo + (g.random(m) * np.maximum(cnt - lo, 1)).astype(np.int64)
        has = cnt >= 3
        rows = np.arange(m)
        idx[h:, 1] = np.where(has, nb[rows, np.minimum(j2, _LOCAL_K - 1)], idx[h:, 1])
        idx[h:, 2] = np.where(has, nb[rows, np.minimum(j3, _LOCAL_K - 1)], idx[h:, 2])
    kernels = fit_kernels()
    if kernels is not None and _kernel_input(xy) and tol > 0:
        # the same circles and the same pick, without the (tries, n) arrays
        out = np.empty(3)
        nx, ny = (float(near[0]), float(near[1])) if near is not None else (0.0, 0.0)
        j = kernels["ransac_pick"](xy, idx, float(r_max), nx, ny, float(near_m),
                                   near is not None, float(tol), hollow, np.empty(n), out)
        if j < 0:
            return None
        cxj, cyj, rj = float(out[0]), float(out[1]), float(out[2])
        tcj = min(tol, max(0.5 * rj, 0.005))
        return cxj, cyj, rj, np.abs(np.hypot(xy[:, 0] - cxj, xy[:, 1] - cyj) - rj) <= tcj
    p1, p2, p3 = xy[idx[:, 0]], xy[idx[:, 1]], xy[idx[:, 2]]
    ax, ay = p2[:, 0] - p1[:, 0], p2[:, 1] - p1[:, 1]
    bx, by = p3[:, 0] - p1[:, 0], p3[:, 1] - p1[:, 1]
    dd = 2.0 * (ax * by - ay * bx)
    ok = np.abs(dd) > 1e-12
    dd = np.where(ok, dd, 1.0)
    a2, b2 = ax * ax + ay * ay, bx * bx + by * by
    ux = (by * a2 - ay * b2) / dd
    uy = (ax * b2 - bx * a2) / dd
    r = np.hypot(ux, uy)
    ok &= (r <= r_max) & (r >= 0.01)
    if not ok.any():
        return None
    cx, cy = p1[:, 0] + ux, p1[:, 1] + uy
    if near is not None:
        ok &= np.hypot(cx - near[0], cy - near[1]) <= near_m
    c = np.flatnonzero(ok)
    if len(c) == 0:
        return None
    d = np.hypot(xy[None, :, 0] - cx[c, None], xy[None, :, 1] - cy[c, None])
    sres = d - r[c, None]
    res = np.abs(sres)
    # a circle's band is no wider than half its radius: with a wider one, a small circle
    # centred on a thick stem's bark holds the bark around its centre as inliers
    tc = np.minimum(tol, np.maximum(0.5 * r[c], 0.005))[:, None]
    inl = res <= tc
    # MSAC (Torr & Zisserman 2000): the least truncated squared residual (in units of the
    # band), not the most inliers alone (a short arc lies within the band of many larger
    # circles). A stem hides what lies behind its bark: a point well inside a circle costs
    # twice an outlier, so that among needles a circle through the crown (more points near
    # it than the bark has, and the crown inside it) loses to the bark's (nothing inside)
    cost = np.minimum(res / tc, 1.0) ** 2
    if hollow:
        cost += sres < -2.0 * tc
    best = int(np.argmin(cost.sum(axis=1)))
    j = c[best]
    return float(cx[j]), float(cy[j]), float(r[j]), inl[best]


def trimmed_circle(q: FloatArray, c: Circle, *, tol: float, rounds: int = 3) -> Circle:
    """The circle refitted on the bark's own shell: nothing of a stem lies inside its bark,
    while branch stubs, needles and mixed returns lie outside it. Each round takes the noise
    from the points inside the circle (their residuals are noise alone), drops the points
    more than 2.5 of it (at least 5 mm) outside, and refits (``tol``: the noise assumed
    where fewer than three points lie inside). Compiled where the fits are (the same
    numbers)."""
    kernels = fit_kernels()
    if kernels is not None and _kernel_input(q) and tol > 0:
        out = np.empty(4)
        kernels["trimmed"](q, float(c.cx), float(c.cy), float(c.r), float(c.rms), float(tol),
                           rounds, out)
        kept = tuple(out) == (c.cx, c.cy, c.r, c.rms)  # else a refit's (arc 0, as refine's)
        return c if kept else Circle(float(out[0]), float(out[1]), float(out[2]),
                                     float(out[3]), 0.0)
    for _ in range(rounds):
        d = np.hypot(q[:, 0] - c.cx, q[:, 1] - c.cy)
        res = d - c.r
        neg = res[res < 0]
        sigma = 1.4826 * float(np.median(-neg)) if len(neg) >= 3 else tol / 2.5
        cut = max(2.5 * sigma, 0.005)
        keep = (res <= cut) & (res >= -max(3.0 * sigma, 0.005) - 0.005)
        if keep.sum() < 3:
            return c
        new = refine_circle(q[keep], c.cx, c.cy, c.r, huber_m=1.0)
        if new is None:
            return c
        if abs(new.r - c.r) < 1e-4 and math.hypot(new.cx - c.cx, new.cy - c.cy) < 1e-4:
            return new
        c = new
    return c


def hyper_circle(q: FloatArray) -> Circle | None:
    """Chernov's hyper-accurate algebraic circle fit (Al-Sharadqah & Chernov 2009, "Error
    analysis for circle fitting algorithms", Electron. J. Statist. 3:886; the HyperSVD
    form): no essential bias in the radius, where the geometric fit's grows with the noise
    on a short arc. None for fewer than 3 points or a line."""
    if len(q) < 3:
        return None
    m = q.mean(axis=0)
    x, y = q[:, 0] - m[0], q[:, 1] - m[1]
    z = x * x + y * y
    A = np.column_stack([z, x, y, np.ones(len(z))])
    try:
        # three points: the circle through them, the null vector of the 3 x 4 system
        _u, s, vt = np.linalg.svd(A, full_matrices=len(q) < 4)
    except np.linalg.LinAlgError:
        return None
    if len(s) < 4:
        s = np.append(s, 0.0)
    if s[3] / s[0] < 1e-12:
        a = vt[3]
    else:
        r = A.mean(axis=0)
        N = np.array([[8 * r[0], 4 * r[1], 4 * r[2], 2.0], [4 * r[1], 1.0, 0.0, 0.0],
                      [4 * r[2], 0.0, 1.0, 0.0], [2.0, 0.0, 0.0, 0.0]])
        W = vt.T @ np.diag(s) @ vt
        try:
            ev, E = np.linalg.eig(W @ np.linalg.inv(N) @ W)
            order = np.argsort(ev.real)
            a = np.linalg.solve(W, E[:, order[1]].real)
        except np.linalg.LinAlgError:
            return None
    if not abs(a[0]) > 1e-12:
        return None
    cx, cy = -a[1] / a[0] / 2.0, -a[2] / a[0] / 2.0
    disc = a[1] * a[1] + a[2] * a[2] - 4.0 * a[0] * a[3]
    if not disc > 0:
        return None
    rad = math.sqrt(disc) / abs(a[0]) / 2.0
    d = np.hypot(x - cx, y - cy)
    return Circle(float(cx + m[0]), float(cy + m[1]), rad, float(np.sqrt(np.mean((d - rad) ** 2))),
                  0.0)


def refine_circle(q: FloatArray, cx: float, cy: float, r: float, *, huber_m: float,
                  iterations: int = 5) -> Circle | None:
    """Geometric circle fit (Gauss-Newton on the distances to the circle, Huber weights
    ``huber_m``) from a start (cx, cy, r); None where it does not converge to a circle.
    Compiled where the fits are (:mod:`tcf_hil.sic._fitkernels`: the same numbers)."""
    kernels = fit_kernels()
    if kernels is not None and _kernel_input(q):
        out = np.empty(5)
        try:
            kernels["refine"](q, float(cx), float(cy), float(r), float(huber_m), iterations,
                              out)
        except np.linalg.LinAlgError:
            return None
        if not out[4]:
            return None
        return Circle(float(out[0]), float(out[1]), float(out[2]), float(out[3]), 0.0)
    m = q.mean(axis=0)
    x, y = q[:, 0] - m[0], q[:, 1] - m[1]
    cx, cy = cx - float(m[0]), cy - float(m[1])
    for _ in range(iterations):
        dx, dy = x - cx, y - cy
        d = np.maximum(np.hypot(dx, dy), 1e-12)
        res = d - r
        a = np.abs(res)
        w = np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12))
        ux, uy = dx / d, dy / d
        # J = [-ux, -uy, -1]; normal equations J^T W J s = -J^T W res
        sw, sx, sy = w.sum(), (w * ux).sum(), (w * uy).sum()
        sxx, sxy, syy = (w * ux * ux).sum(), (w * ux * uy).sum(), (w * uy * uy).sum()
        H = np.array([[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, sw]])
        g = np.array([(w * ux * res).sum(), (w * uy * res).sum(), (w * res).sum()])
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        cx, cy, r = cx + float(step[0]), cy + float(step[1]), r + float(step[2])
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) or r <= 0:
            return None
        if float(np.abs(step).max()) < 1e-6:
            break
    d = np.hypot(x - cx, y - cy)
    rms = float(np.sqrt(np.mean((d - r) ** 2)))
    return Circle(cx + float(m[0]), cy + float(m[1]), r, rms, 0.0)


def arc_deg(xy: FloatArray, cx: float, cy: float) -> float:
    """The angle around (cx, cy) that the points cover (360 less the largest gap)."""
    return arc_coverage(np.arctan2(xy[:, 1] - cy, xy[:, 0] - cx))


def stem_circle(xy: FloatArray, width: FloatArray, *, r_max: float, tol: float,
                min_points: int, min_arc: float = 60.0, near: FloatArray | None = None,
                max_inside: float = 0.1, edge_share: float = 1.0, outside: float = 5.0
                ) -> tuple[float, float, float, float, int, int, bool] | None:
    """A stem's circle from a slice's points (x, y) and their edge half widths: RANSAC, then
    the robust geometric fit on the inliers. The returns without a mixed footprint are fitted
    where at least ``min_points`` of them cover ``min_arc``; else all, less the edge returns'
    median half width. A stem is hollow to the sensor: a circle with more than
    ``max_inside`` of the points within it well inside is no stem (a clump of needles, a
    shrub); nor one with fewer than 60 % of the points from 5 tolerances inside it to
    ``outside`` tolerances outside it on it (bark is a thin shell). ``edge_share``: the
    share of the edge returns' half width taken off a radius that only they give. Returns
    (cx, cy, r, arc, inliers, 0 where the clean returns gave it, 1 where the edge returns
    did, whether the shell holds against 5 tolerances outside it too) or None."""
    inner = width <= 0
    if int(inner.sum()) >= min_points:
        f = _circle_on(xy[inner], xy, r_max=r_max, tol=tol, min_points=min_points, near=near,
                       max_inside=max_inside, outside=outside)
        if f is not None and f[3] >= min_arc:
            return (*f[:5], 0, f[5])
    # the edge returns are weaker, so noisier (and mixed): a wider tolerance
    f = _circle_on(xy, xy, r_max=r_max, tol=2.0 * tol, min_points=min_points, near=near,
                   max_inside=max_inside, outside=outside)
    if f is None:
        return None
    d = np.hypot(xy[:, 0] - f[0], xy[:, 1] - f[1])
    w = width[(np.abs(d - f[2]) <= 2.0 * tol) & (width > 0)]
    r_fit = max(0.01, f[2] - edge_share * (float(np.median(w)) if len(w) else 0.0))
    return f[0], f[1], r_fit, f[3], f[4], 1, f[5]


def _circle_on(q: FloatArray, every: FloatArray, *, r_max: float, tol: float,
               min_points: int, near: FloatArray | None, max_inside: float,
               outside: float = 5.0
               ) -> tuple[float, float, float, float, int, bool] | None:
    if len(q) < min_points:
        return None
    rs = ransac_circle(q, r_max=r_max, tol=tol, near=near)
    if rs is None or int(rs[3].sum()) < min_points:
        return None
    cx, cy, r, inl = rs
    tol = min(tol, max(0.5 * r, 0.005))  # as RANSAC's band
    c = refine_circle(q[inl], cx, cy, r, huber_m=tol / 2) or hyper_circle(q[inl])
    if c is None or c.r > r_max or math.hypot(c.cx - cx, c.cy - cy) > max(r, 0.05):
        return None
    t = trimmed_circle(q, c, tol=tol)
    if t.r > r_max or t.r <= 0:
        return None
    d = np.hypot(q[:, 0] - t.cx, q[:, 1] - t.cy)
    keep = np.abs(d - t.r) <= tol
    if int(keep.sum()) < min_points:
        return None
    de = np.hypot(every[:, 0] - t.cx, every[:, 1] - t.cy)
    # bark is a thin shell that hides what lies behind it: of the points near the circle
    # (from 5 tolerances inside to ``outside`` tolerances outside it: needles may crowd the
    # bark's outside), most lie on it
    inner_band = (t.r - d) <= 5.0 * tol
    if int(keep.sum()) < 0.6 * int((inner_band & (d - t.r <= outside * tol)).sum()):
        return None
    # ... and whether it is so on the outside too (no crown crowds it)
    clean = int(keep.sum()) >= 0.6 * int((inner_band & (d - t.r <= 5.0 * tol)).sum())
    within = int((de <= t.r + tol).sum())
    inside = int((de < t.r - max(2.0 * tol, 0.2 * t.r)).sum())
    if inside > max_inside * within:
        return None
    # one stem's bark is one arc: a circle whose points lie in separate short arcs (through
    # the facing sides of two or three neighbouring stems) is none
    if arc_fill(q[keep], t.cx, t.cy, t.r) < _MIN_ARC_FILL:
        return None
    return t.cx, t.cy, t.r, arc_deg(q[keep], t.cx, t.cy), int(keep.sum()), clean


_MIN_ARC_FILL = 0.5


def arc_fill(xy: FloatArray, cx: float, cy: float, r: float, hole_m: float = 0.05) -> float:
    """The share of the arc the points cover (360 less the largest gap) that holds points:
    gaps between neighbouring points longer than ``hole_m``, at least 10 degrees and three
    times their median gap, count as holes. 1 for a continuous arc."""
    if len(xy) < 2:
        return 0.0
    a = np.sort(np.mod(np.arctan2(xy[:, 1] - cy, xy[:, 0] - cx), 2.0 * math.pi))
    gaps = np.diff(np.concatenate([a, [a[0] + 2.0 * math.pi]]))
    big = int(np.argmax(gaps))
    span = 2.0 * math.pi - float(gaps[big])
    if span <= 0.0:
        return 0.0
    rest = np.delete(gaps, big)
    # a hole is a gap well beyond the points' own spacing (a sparse arc is no two arcs)
    h = max(hole_m / max(r, 1e-6), math.radians(10.0),
            3.0 * float(np.median(rest)) if len(rest) else 0.0)
    return 1.0 - float(rest[rest > h].sum()) / span


# --------------------------------------------------------------------------- stem finding
def _neighbourhood_moments(keys: NDArray[np.int64], span: NDArray[np.int64],
                           mom: FloatArray) -> FloatArray:
    """Sum of ``mom`` (m, c) over each voxel's 3 x 3 x 3 neighbourhood; ``keys`` sorted,
    voxel index = offset key with ``span``."""
    out = mom.copy()
    s1, s2 = int(span[1] * span[2]), int(span[2])
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            for dk in (-1, 0, 1):
                if di == dj == dk == 0:
                    continue
                off = di * s1 + dj * s2 + dk
                q = keys + off
                pos = np.searchsorted(keys, q)
                pos = np.minimum(pos, len(keys) - 1)
                hit = keys[pos] == q
                out[hit] += mom[pos[hit]]
    return out


class Voxels:
    """The band's points in ``voxel`` cubes with each cube's local shape (PCA of the points
    of its 3 x 3 x 3 neighbourhood)."""

    def __init__(self, p: FloatArray, rel: FloatArray, voxel: float, prm: StemParams) -> None:
        corner = column_min(p)
        v = np.floor((p - corner) / voxel).astype(np.int64) + 1
        # keyed with a border of one empty voxel on every side, so that a neighbour's key
        # (+-1 along an axis) never wraps onto a voxel of the next row
        span = column_max(v) + 2
        key = (v[:, 0] * span[1] + v[:, 1]) * span[2] + v[:, 2]
        uk, _first, inv = unique_first(key)
        m = len(uk)
        q = p - corner  # small numbers: no cancellation worth the name at 10 cm
        mom = np.zeros((m, 10))
        cols = [np.ones(len(q)), q[:, 0], q[:, 1], q[:, 2], q[:, 0] * q[:, 0],
                q[:, 0] * q[:, 1], q[:, 0] * q[:, 2], q[:, 1] * q[:, 1], q[:, 1] * q[:, 2],
                q[:, 2] * q[:, 2]]
        for c, col in enumerate(cols):
            mom[:, c] = np.bincount(inv, weights=col, minlength=m)
        nb = _neighbourhood_moments(uk, span, mom)
        n = nb[:, 0]
        mean = nb[:, 1:4] / n[:, None]
        cov = np.empty((m, 3, 3))
        for a, b, c in ((0, 0, 4), (0, 1, 5), (0, 2, 6), (1, 1, 7), (1, 2, 8), (2, 2, 9)):
            cov[:, a, b] = cov[:, b, a] = nb[:, c] / n - mean[:, a] * mean[:, b]
        w, e = np.linalg.eigh(cov)  # ascending eigenvalues
        w = np.maximum(w, 0.0)
        normal = e[:, :, 0]
        axis = e[:, :, 2]
        tr = np.maximum(w.sum(axis=1), 1e-12)
        zshare = cov[:, 2, 2] / tr
        linear = (w[:, 2] - w[:, 1]) / np.maximum(w[:, 2], 1e-12)
        enough = n >= prm.min_slice_points
        # a bark patch: a surface whose normal is horizontal and that spreads upwards
        # (thin: the spread along the normal is a small share of the whole, Pauly et al.
        # 2002's surface variation; needles in a crown scatter in every direction)
        variation = w[:, 0] / tr
        self.surface = enough & (np.abs(normal[:, 2]) <= prm.max_normal_z) & (
            zshare >= prm.min_z_share) & (linear < 0.8) & (variation <= prm.max_variation)
        # a thin stem: a vertical line
        self.line = enough & (linear >= 0.8) & (np.abs(axis[:, 2]) >= 0.9)
        self.stem = self.surface | self.line
        nxy = normal[:, :2]
        self.normal = nxy / np.maximum(np.hypot(nxy[:, 0], nxy[:, 1]), 1e-12)[:, None]
        self.mean = mean + corner
        self.inv = inv  # each point's voxel
        self.rel = np.bincount(inv, weights=rel, minlength=m) / mom[:, 0]  # above ground


_LAYER_VOTES = 2.5  # a layer counts for a stem with this many votes (2-3 bark voxels)


def _peaks(xy: FloatArray, weight: FloatArray, layer: NDArray[np.int64], layers: int,
           cell: float, min_votes: float, min_layers: int) -> FloatArray:
    """Local maxima (3 x 3 cells) of the votes at ``xy`` summed over 3 x 3 cells, where the
    votes of at least ``min_layers`` height layers (of ``layers``) reach one each: a stem
    stands through the band, a clump of needles does not. Returns the vote-weighted mean
    position of each maximum's 3 x 3 cells, the most voted first. (k, 2)."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    lo = column_min(xy)
    ij = np.floor((xy - lo) / cell).astype(np.int64) + 1
    ni, nj = int(ij[:, 0].max()) + 2, int(ij[:, 1].max()) + 2
    flat = ij[:, 0] * nj + ij[:, 1]
    size = ni * nj

    def grid(w: FloatArray, idx: NDArray[np.int64] = flat, n: int = size) -> FloatArray:
        out: FloatArray = np.bincount(idx, weights=w, minlength=n).astype(np.float64)
        return out

    def box(a: FloatArray) -> FloatArray:
        """3 x 3 sums over the first two axes."""
        p = np.pad(a, [(1, 1), (1, 1)] + [(0, 0)] * (a.ndim - 2))
        out = np.zeros_like(a)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                out += p[1 + di:1 + di + ni, 1 + dj:1 + dj + nj]
        return out

    per_layer = box(grid(weight, flat * layers + layer, size * layers).reshape(ni, nj, layers))
    s = per_layer.sum(axis=2)
    persistent = (per_layer >= _LAYER_VOTES).sum(axis=2) >= min_layers
    bx = box(grid(weight * xy[:, 0]).reshape(ni, nj))
    by = box(grid(weight * xy[:, 1]).reshape(ni, nj))
    pad = np.pad(s, 1, constant_values=-1.0)
    is_max = (s >= min_votes) & (s > 0) & persistent
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                other = pad[1 + di:1 + di + ni, 1 + dj:1 + dj + nj]
                # ties: the first in raster order wins
                is_max &= (s > other) | ((s == other) & ((di > 0) | ((di == 0) & (dj > 0))))
    i, j = np.nonzero(is_max)
    order = np.argsort(-s[i, j], kind="stable")
    i, j = i[order], j[order]
    return np.column_stack([bx[i, j] / s[i, j], by[i, j] / s[i, j]])


def stem_candidates(vx: Voxels, prm: StemParams) -> FloatArray:
    """Where stems stand: every bark patch votes for the points along its normal (both ways:
    the side the stem lies on is not known) from 1 cm to ``max_dbh_m / 2`` (at most 0.5 m)
    away, a thin stem's line votes where it is; the stem axes are where the votes pile up
    in enough height layers (``curve_step_m`` thick). (k, 2), the most voted first."""
    step = 0.02
    ts = np.arange(0.01, min(prm.max_dbh_m / 2.0, 0.5) + 1e-9, step)
    sv = np.flatnonzero(vx.surface)
    lv = np.flatnonzero(vx.line)
    m = vx.mean[sv, :2]
    nrm = vx.normal[sv]
    votes = [(m[:, None, :] + sgn * ts[None, :, None] * nrm[:, None, :]).reshape(-1, 2)
             for sgn in (1.0, -1.0)]
    layers = max(1, math.ceil((prm.band_m[1] - prm.band_m[0]) / prm.curve_step_m))
    lay = np.clip(np.floor((vx.rel - prm.band_m[0]) / prm.curve_step_m).astype(np.int64),
                  0, layers - 1)
    # a patch's votes are spread over a line both ways, each 4/len(ts): about 1 of them
    # falls into the 3 x 3 box at the stem's axis (the 12 cm box holds ~6 of the 2 cm steps
    # of the right side); a line voxel (a thin stem's whole cross-section) votes 1 at its mean
    xy = np.concatenate([*votes, vx.mean[lv, :2]])
    wt = np.concatenate([np.full(len(sv) * len(ts) * 2, 4.0 / len(ts)), np.ones(len(lv))])
    layer = np.concatenate([np.repeat(lay[sv], len(ts)), np.repeat(lay[sv], len(ts)),
                            lay[lv]])
    min_votes = prm.min_votes
    return _peaks(xy, wt, layer, layers, 0.04, min_votes, prm.min_slices)


def _fit_window(xy: FloatArray, width: FloatArray, prm: StemParams,
                near: FloatArray | None = None, tol: float | None = None,
                outside: float | None = None
                ) -> tuple[float, float, float, float, int, int, bool] | None:
    return stem_circle(xy, width, r_max=prm.max_dbh_m / 2.0,
                       tol=prm.fit_tolerance_m if tol is None else tol,
                       min_points=prm.min_slice_points, near=near,
                       edge_share=prm.edge_correction,
                       outside=prm.shell_outside if outside is None else outside)


def field_stems(p: FloatArray, width: FloatArray, ground: FloatArray, prm: StemParams
                ) -> list[dict[str, Any]]:
    """Stems in a cloud (local metres (n, 3)), its points' edge half widths (n,) and the
    ground height under each (n,). Returns a dict per stem: x, y (breast-height centre),
    ground, h, dbh, maxcurve, curve [(z, x, y, d), ...]."""
    rel = p[:, 2] - ground
    band = np.flatnonzero((rel >= prm.band_m[0]) & (rel <= prm.band_m[1]))
    if len(band) < prm.min_points:
        return []
    vx = Voxels(p[band], rel[band], prm.stem_voxel_m, prm)
    cands = stem_candidates(vx, prm)
    if len(cands) == 0:
        return []
    # the fits take every band point near a candidate: a stem inside a crown that reaches
    # down to the band has bark whose neighbourhood is mostly needles (not stem-like)
    from scipy.spatial import cKDTree

    tree = cKDTree(p[band, :2])
    above = np.flatnonzero(rel > prm.band_m[1] - 1.0)  # where stems are followed up
    up_tree = cKDTree(p[above, :2]) if len(above) else None
    reach = min(prm.max_dbh_m / 2.0, 0.5) + 0.1
    out: list[dict[str, Any]] = []
    found: list[tuple[float, float, float]] = []
    for c in cands:
        if any(math.hypot(c[0] - fx, c[1] - fy) < fr + 0.05 for fx, fy, fr in found):
            continue
        idx = band[np.asarray(tree.query_ball_point(c, reach), np.int64)]
        # a return belongs to one stem: those on a stem found already (stronger candidates
        # come first) are not another's (a circle through two close stems' facing sides)
        for fx, fy, fr in found:
            if math.hypot(c[0] - fx, c[1] - fy) < reach + fr + 0.05:
                idx = idx[np.hypot(p[idx, 0] - fx, p[idx, 1] - fy) > fr + 0.03]
        if len(idx) < prm.min_points:
            continue
        crowded = any(math.hypot(c[0] - fx, c[1] - fy) < prm.crowd_m for fx, fy, _ in found)
        t = _stem_from(p, width, rel, idx, prm, c, above, up_tree,
                       outside=5.0 if crowded else prm.shell_outside)
        if t is None:
            continue
        if any(math.hypot(t["x"] - fx, t["y"] - fy) < max(fr, t["dbh"] / 2.0) + 0.02
               for fx, fy, fr in found):
            continue
        found.append((t["x"], t["y"], t["dbh"] / 2.0))
        out.append(t)
    return out


def _stem_from(p: FloatArray, width: FloatArray, rel: FloatArray, idx: NDArray[np.int64],
               prm: StemParams, centre: FloatArray, above: NDArray[np.int64],
               up_tree: Any, outside: float | None = None) -> dict[str, Any] | None:
    """Fit a stem to the band points ``idx`` around a candidate ``centre``: the
    axis from slice circles (each centred within 10 cm of the candidate), the DBH from the
    breast-height window brought onto the axis, then the stem followed up, its height from
    the column above its top and its form from the curve."""
    rz = rel[idx]
    band = _band_slices(p, width, rz, idx, prm, centre, outside)
    if band is None:
        return None
    axis = _slice_axis(band, prm)
    if axis is None:
        return None
    zs_a, cs_a, rs_a, line = axis
    bh = _breast_height(p, width, rel, rz, idx, prm, line, zs_a, rs_a)
    if bh is None:
        return None
    cx, cy, dbh, dbh_path = bh
    top_z = float(rz.max())
    curve = [(float(z), float(c[0]), float(c[1]), 2.0 * float(r))
             for z, c, r in zip(zs_a, cs_a, rs_a, strict=True)]
    _follow_up(p, width, rel, prm, line, top_z, dbh / 2.0, above, up_tree, curve)
    h = _stem_height(rel, above, up_tree, curve, top_z)
    if h < prm.band_m[1] + 0.25:
        # nothing above the band over it: a tree of stem size has its stem and crown
        # there (and a sensor 2 m up sees it); this is a shrub, a sapling or a stump
        return None
    cz = np.array([c[0] for c in curve])
    cxy = np.array([[c[1], c[2]] for c in curve])
    mc, crook = stem_form(cz, cxy, h, prm)
    cls = ("X" if crook >= prm.crook_m or mc >= prm.other_threshold_m else
           "C" if mc >= prm.curve_threshold_m else "S")
    ground = float(np.median(p[idx, 2] - rz))
    return {"x": cx, "y": cy, "ground": ground, "h": h, "dbh": dbh, "maxcurve": mc,
            "class": cls, "crook": crook,
            "fit": {"dbh_from": ("returns without a mixed footprint", "edge returns",
                                 "slices")[dbh_path], "slices": len(band.zs),
                    "tried": band.tried, "arc_deg": float(np.median(band.arcs))},
            "curve": [(round(z_ + ground, 3), round(x_, 4), round(y_, 4), round(d_, 4))
                      for z_, x_, y_, d_ in curve]}


_Axis = tuple[FloatArray, FloatArray]  # a stem's axis: its centre at z = 0 and lean (x, y)


@dataclass
class _Band:
    """The slice circles of a candidate's band (:func:`_band_slices`): each slice's height,
    centre, radius, arc (degrees) and whether its bark stood clear of needles, and how many
    slices were tried."""

    zs: list[float] = field(default_factory=list)
    cs: list[tuple[float, float]] = field(default_factory=list)
    rs: list[float] = field(default_factory=list)
    arcs: list[float] = field(default_factory=list)
    clean: list[bool] = field(default_factory=list)
    tried: int = 0


def _band_slices(p: FloatArray, width: FloatArray, rz: FloatArray, idx: NDArray[np.int64],
                 prm: StemParams, centre: FloatArray, outside: float | None) -> _Band | None:
    """The band's slices, each fitted with a circle centred within 10 cm of ``centre``;
    None where too few fit for a stem."""
    half = prm.slice_thickness_m / 2.0
    band = _Band()
    # the band's slices one against the next: every return in one (slices a curve step
    # apart, as above the band, left half the band's returns out; on the natural stands'
    # dumped maps, contiguous slices found 3-8 points more of the stems within 15 m)
    levels = np.arange(max(prm.band_m[0], float(rz.min())) + half, float(rz.max()),
                       prm.slice_thickness_m)
    order = np.argsort(rz, kind="stable")
    srz = rz[order]
    lo_i = np.searchsorted(srz, levels - half)
    hi_i = np.searchsorted(srz, levels + half, side="right")
    usable = int(((hi_i - lo_i) >= prm.min_slice_points).sum())
    for zc, a, b in zip(levels, lo_i, hi_i, strict=True):
        if b - a < prm.min_slice_points:
            continue
        if usable - band.tried + len(band.zs) < prm.min_band_slices:
            return None  # too few slices left to make a stem
        band.tried += 1
        s = idx[order[a:b]]
        f = _fit_window(p[s, :2], width[s], prm, centre, outside=outside)
        if f is None or math.hypot(f[0] - centre[0], f[1] - centre[1]) > 0.1:
            continue
        band.arcs.append(f[3])
        band.zs.append(zc)
        band.cs.append((f[0], f[1]))
        band.rs.append(f[2])
        band.clean.append(f[6])
    zs = band.zs
    if len(zs) < 2 or zs[-1] - zs[0] < prm.min_stem_extent_m - prm.slice_thickness_m:
        return None
    return band


def _slice_axis(band: _Band, prm: StemParams
                ) -> tuple[FloatArray, FloatArray, FloatArray, _Axis] | None:
    """The slices that agree on one stem (heights, centres, radii) and the axis through their
    centres; None where too few agree or the stem is crowded by needles."""
    zs_a, cs_a, rs_a = np.array(band.zs), np.array(band.cs), np.array(band.rs)
    # the slices' radii agree on one stem: drop those far off their median
    rmed = float(np.median(rs_a))
    ok = np.abs(rs_a - rmed) <= max(0.3 * rmed, 0.02)
    # a stem whose bark stands clear of needles in min_band_slices slices; one crowded by
    # them (a weaker shell: a gap in a crown or a sapling's crown pass it too) in one more
    if ok.sum() < prm.min_band_slices or (
            int(np.asarray(band.clean)[ok].sum()) < prm.min_band_slices
            and ok.sum() < prm.min_band_slices + 1):
        return None
    zs_a, cs_a, rs_a = zs_a[ok], cs_a[ok], rs_a[ok]
    # the axis: a robust line through the slice centres (median-based outlier rejection)
    axis = _line(zs_a, cs_a)
    if axis is None:
        return None
    return zs_a, cs_a, rs_a, axis


def _breast_height(p: FloatArray, width: FloatArray, rel: FloatArray, rz: FloatArray,
                   idx: NDArray[np.int64], prm: StemParams,
                   axis: _Axis, zs_a: FloatArray, rs_a: FloatArray
                   ) -> tuple[float, float, float, int] | None:
    """The stem at breast height: centre, DBH and how it was found (0, 1: the window's
    circle, by :func:`stem_circle`'s path; 2: the slices nearest breast height); None where
    the DBH is out of range."""
    c13 = axis[0] + axis[1] * BREAST_HEIGHT_M
    # breast height: the window's points brought onto the axis, one circle
    lo, hi = prm.dbh_window_m
    r_near = float(np.median(rs_a[np.argsort(np.abs(zs_a - BREAST_HEIGHT_M))[:3]]))
    w = idx[(rz >= lo) & (rz <= hi)]
    dbh = math.nan
    dbh_path = 2
    cx, cy = float(c13[0]), float(c13[1])
    if len(w) >= prm.min_slice_points:
        shift = axis[1][None, :] * (rel[w] - BREAST_HEIGHT_M)[:, None]
        f = _fit_window(p[w, :2] - shift, width[w], prm, c13, prm.dbh_tolerance_m)
        if f is None:
            f = _fit_window(p[w, :2] - shift, width[w], prm, c13)
        # the circle must be the stem the slices found: centred on their axis, its radius
        # that of the slices nearest breast height (as the slices' radii agree with each
        # other); a circle through a crown or a neighbour beside the stem is not its DBH
        if (f is not None and math.hypot(f[0] - cx, f[1] - cy) < 0.1
                and abs(f[2] - r_near) <= max(0.3 * r_near, 0.02)):
            cx, cy, dbh = f[0], f[1], 2.0 * f[2]
            dbh_path = f[5]
    if not math.isfinite(dbh):
        dbh = 2.0 * r_near
    if not (prm.min_dbh_m <= dbh <= prm.max_dbh_m):
        return None
    return cx, cy, dbh, dbh_path


def _follow_up(p: FloatArray, width: FloatArray, rel: FloatArray, prm: StemParams,
               axis: _Axis, top_z: float, r_last: float,
               above: NDArray[np.int64], up_tree: Any,
               curve: list[tuple[float, float, float, float]]) -> None:
    """Follow the stem up from the band's top ``top_z``: slices every curve step above it,
    each searched near the centre the curve so far predicts; each slice found is appended
    to ``curve`` (height, centre, diameter)."""
    step = prm.curve_step_m
    half = prm.slice_thickness_m / 2.0
    lean = axis[1]
    z = top_z + step
    last = np.array([*(axis[0] + axis[1] * top_z)])
    misses = 0
    up = (above[np.asarray(up_tree.query_ball_point(last, r_last + prm.follow_radius_m + 1.0),
                           np.int64)] if up_tree is not None else np.zeros(0, np.int64))
    up = up[rel[up] > top_z]
    rel_up = rel[up]  # (gathered once: the loop below takes a slice of them a step)
    while misses < prm.follow_misses and len(up):
        pred = last + lean * step * (misses + 1)
        s = up[(np.abs(rel_up - z) <= half)]
        if len(s):
            d = np.hypot(p[s, 0] - pred[0], p[s, 1] - pred[1])
            s = s[d <= r_last + prm.follow_radius_m]
        f = (_fit_window(p[s, :2], width[s], prm, pred) if len(s) >= prm.min_slice_points
             else None)
        # the stem tapers (a slice no wider than the last, within 10 % and 5 mm of fit
        # noise) and its centre line does not jump (within half a radius, at least 4 cm,
        # of the prediction per step): a wider circle off the line is a neighbour's
        # branches or a whorl, and followed, it bent straight stems' curves into bows and
        # crooks (on the natural stands' matched stems, 2-4 points more classes right)
        if (f is not None and f[2] <= r_last * 1.1 + 0.005
                and math.hypot(f[0] - pred[0], f[1] - pred[1]) <= min(
                    prm.follow_radius_m, max(0.04, 0.5 * r_last) * (misses + 1))):
            curve.append((float(z), f[0], f[1], 2.0 * f[2]))
            new = np.array([f[0], f[1]])
            lean = 0.5 * lean + 0.5 * (new - last) / (step * (misses + 1))
            last, r_last, misses = new, f[2], 0
        else:
            misses += 1
        z += step


def _stem_height(rel: FloatArray, above: NDArray[np.int64], up_tree: Any,
                 curve: list[tuple[float, float, float, float]], top_z: float) -> float:
    """The height: the highest point above the followed stem, in the column around its top,
    walking up while the column has no vertical gap larger than 1.5 m."""
    top_xy = np.array(curve[-1][1:3])
    col = (above[np.asarray(up_tree.query_ball_point(top_xy, 0.5), np.int64)]
           if up_tree is not None else np.zeros(0, np.int64))
    zc = np.sort(rel[col]) if len(col) else np.array([top_z])
    gaps = np.flatnonzero(np.diff(zc) > 1.5)
    gaps = gaps[zc[gaps] >= curve[-1][0]]  # gaps below the followed stem's top: occlusion
    zc_top = zc[gaps[0]] if len(gaps) else zc[-1]
    return max(float(zc_top), curve[-1][0])


def stem_form(z: FloatArray, c: FloatArray, h: float, prm: StemParams
              ) -> tuple[float, float]:
    """(maxcurve, crook) of a stem curve: centres ``c`` (k, 2) at heights ``z`` (k,) above
    the ground, the stem ``h`` tall.

    The bow: a quadratic centre line (robust: slices more than 3 MADs, at least 2 cm, off it
    left out) through the centres, taken from the ground to the top; its largest distance
    from its chord is the maxcurve (the stem is seen only up to the crown, so the bow of
    the whole stem comes from its lower part's curvature). A crook: a sideways step in an
    otherwise straight centre line (a line with a step fitted at each height)."""
    if len(z) < 4:
        return 0.0, 0.0
    keep = np.ones(len(z), bool)
    co = None
    for _ in range(3):
        if keep.sum() < 4:
            break
        co = [np.polyfit(z[keep], c[keep, k], 2) for k in (0, 1)]
        fit = np.column_stack([np.polyval(co[k], z) for k in (0, 1)])
        res = np.hypot(*(c - fit).T)
        mad = 1.4826 * float(np.median(res[keep]))
        new = res <= max(3.0 * mad, 0.02)
        if (new == keep).all():
            break
        keep = new
    if co is not None and keep.sum() >= 4:  # the fit of the final set (its error below)
        co = [np.polyfit(z[keep], c[keep, k], 2) for k in (0, 1)]
    if co is None:
        return 0.0, 0.0
    # the curvature as far as the slices show it: shrunk by bow_shrink_se standard errors
    # (a short, noisy centre line extrapolated to the top would make every stem a bow)
    q = np.array([co[0][0], co[1][0]])
    qn = float(np.hypot(*q))
    if keep.sum() >= 5 and qn > 0:
        zk = z[keep]
        A = np.column_stack([zk * zk, zk, np.ones(len(zk))])
        res2 = [float(np.sum((c[keep, k] - A @ co[k]) ** 2)) for k in (0, 1)]
        try:
            inv = np.linalg.inv(A.T @ A)[0, 0]
        except np.linalg.LinAlgError:
            inv = math.inf
        se = math.sqrt(max(0.0, 0.5 * sum(res2) / max(1, len(zk) - 3) * inv))
        shrink = max(0.0, qn - prm.bow_shrink_se * se) / qn
        co = [np.array([co[k][0] * shrink, co[k][1], co[k][2]]) for k in (0, 1)]
    elif qn > 0:  # four slices or fewer: no error to judge a curvature by, so none
        co = [np.array([0.0, co[k][1], co[k][2]]) for k in (0, 1)]
    zz = np.linspace(0.0, max(h, float(z.max())), 60)
    f = np.column_stack([np.polyval(co[0], zz), np.polyval(co[1], zz), zz])
    chord = f[-1] - f[0]
    u = chord / float(np.linalg.norm(chord))
    bow = float(np.linalg.norm(np.cross(f - f[0], u), axis=1).max())
    # crook: a sideways step in an otherwise straight centre line: for each height between
    # slices, a line with a step there fitted to the centres (three slices at least on
    # either side, the step's own slices adjacent); the largest step whose fit leaves the
    # centres tight (RMS within a quarter of ``crook_m``) and beats the plain line
    crook = 0.0
    k = len(z)
    if k >= 6:
        ones = np.ones(k)
        plain = np.linalg.lstsq(np.column_stack([ones, z]), c, rcond=None)[0]
        base_rms = float(np.sqrt(np.mean(np.sum((c - np.column_stack([ones, z]) @ plain) ** 2,
                                                axis=1))))
        for i in range(3, k - 2):
            if z[i] - z[i - 1] > 1.01 * prm.curve_step_m + 1e-6:
                continue
            A = np.column_stack([ones, z, (np.arange(k) >= i).astype(float)])
            sol = np.linalg.lstsq(A, c, rcond=None)[0]
            rms = float(np.sqrt(np.mean(np.sum((c - A @ sol) ** 2, axis=1))))
            if rms <= prm.crook_m / 4.0 and rms < 0.7 * base_rms:
                crook = max(crook, float(np.hypot(*sol[2])))
    return bow, crook


def _line(z: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """c(z) = a + b z through the slice centres, refitted without those more than 3 robust
    standard deviations (at least 3 cm) off; (a (2,), b (2,))."""
    keep = np.ones(len(z), bool)
    for _ in range(3):
        if keep.sum() < 2:
            return None
        A = np.column_stack([np.ones(int(keep.sum())), z[keep]])
        sol, *_ = np.linalg.lstsq(A, c[keep], rcond=None)
        res = np.hypot(*(c - (sol[0] + np.outer(z, sol[1]))).T)
        mad = float(np.median(res[keep])) * 1.4826
        new = res <= max(3.0 * mad, 0.03)
        if (new == keep).all():
            break
        keep = new
    return sol[0], sol[1]


__all__ = ["DIVERGENCE_DEG", "divergence_of", "edge_widths", "field_stems", "ransac_circle",
           "stem_circle"]
