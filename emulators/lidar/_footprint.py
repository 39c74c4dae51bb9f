"""The physical sensor model's per-pixel work, compiled (numba): the centre rays' echoes,
the pixels whose footprint can straddle an edge, their sub-rays, the echoes their hits
form, and detection, noise and the pixel words - without the GIL, a chunk of pixels a call.

Each kernel computes exactly what :class:`~emulators.lidar._physics.Physics`'s numpy path
computes (the tests compare the two byte for byte); that path runs where numba is missing.
Plain Python functions written with numpy scalars, built by :func:`emulators.jit.compiled`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from emulators.jit import compiled

SQRT2 = math.sqrt(2.0)
GOLDEN64 = np.uint64(0x9E3779B97F4A7C15)  # 2^64 / golden ratio: splitmix64's step


def mix64(x: Any) -> Any:
    """splitmix64's finaliser (Steele, Lea and Flood, "Fast splittable pseudorandom number
    generators", OOPSLA 2014; the constants of Vigna's splitmix64.c): a uint64 (or uint64
    array) to 64 well-mixed bits, wrapping as uint64 arithmetic does."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


# Acklam's rational approximation of the inverse normal CDF (P. J. Acklam, "An algorithm
# for computing the inverse normal cumulative distribution function", 2003; relative error
# under 1.15e-9 over (0, 1)): a standard normal from a uniform in a dozen multiply-adds,
# with a logarithm and a square root only in the tails (p < 0.02425 or > 0.97575).
_ACKLAM_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
             1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
_ACKLAM_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
             6.680131188771972e+01, -1.328068155288572e+01)
_ACKLAM_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
             -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
_ACKLAM_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
             3.754408661907416e+00)
_A1, _A2, _A3, _A4, _A5, _A6 = _ACKLAM_A
_B1, _B2, _B3, _B4, _B5 = _ACKLAM_B
_C1, _C2, _C3, _C4, _C5, _C6 = _ACKLAM_C
_D1, _D2, _D3, _D4 = _ACKLAM_D
P_LOW = 0.02425


def ndtri(p: float) -> float:
    """The standard normal quantile of ``p`` in (0, 1) (Acklam's approximation)."""
    if p < P_LOW:
        q = math.sqrt(-2.0 * math.log(p))
        return (((((_C1 * q + _C2) * q + _C3) * q + _C4) * q + _C5) * q + _C6) / \
            ((((_D1 * q + _D2) * q + _D3) * q + _D4) * q + 1.0)
    if p > 1.0 - P_LOW:
        q = math.sqrt(-2.0 * math.log(1.0 - p))
        return -(((((_C1 * q + _C2) * q + _C3) * q + _C4) * q + _C5) * q + _C6) / \
            ((((_D1 * q + _D2) * q + _D3) * q + _D4) * q + 1.0)
    q = p - 0.5
    r = q * q
    return (((((_A1 * r + _A2) * r + _A3) * r + _A4) * r + _A5) * r + _A6) * q / \
        (((((_B1 * r + _B2) * r + _B3) * r + _B4) * r + _B5) * r + 1.0)


def ndtri_np(p: Any) -> Any:
    """:func:`ndtri` of an array, the same operations in the same order."""
    lo, hi = p < P_LOW, p > 1.0 - P_LOW
    with np.errstate(divide="ignore", invalid="ignore"):
        qt = np.sqrt(-2.0 * np.log(np.where(lo, p, np.where(hi, 1.0 - p, 0.5))))
    tail = (((((_C1 * qt + _C2) * qt + _C3) * qt + _C4) * qt + _C5) * qt + _C6) / \
        ((((_D1 * qt + _D2) * qt + _D3) * qt + _D4) * qt + 1.0)
    q = p - 0.5
    r = q * q
    mid = (((((_A1 * r + _A2) * r + _A3) * r + _A4) * r + _A5) * r + _A6) * q / \
        (((((_B1 * r + _B2) * r + _B3) * r + _B4) * r + _B5) * r + 1.0)
    return np.where(lo, tail, np.where(hi, -tail, mid))


def pixel_uniforms(key: Any, i: int) -> tuple[float, float]:
    """Pixel ``i``'s two uniform draws in (0, 1) of a frame's return (``key``, uint64): a
    counter-based generator (the pixel's own 64 bits ``mix64(key + (i + 1) * golden)``,
    split in two), so a pixel draws only where it is asked, in any order and on any thread,
    and always the same; :func:`ndtri` of each is a standard normal (a 32-bit uniform
    reaches 6.2 standard deviations: beyond, a normal has a chance of 3e-10)."""
    h = _mix64(key + np.uint64(i + 1) * GOLDEN64)
    u1 = (np.float64(h >> np.uint64(32)) + 0.5) * (1.0 / 4294967296.0)
    u2 = (np.float64(h & np.uint64(0xFFFFFFFF)) + 0.5) * (1.0 / 4294967296.0)
    return u1, u2


def pixel_normals_np(key: Any, n: int) -> tuple[Any, Any]:
    """:func:`ndtri` of :func:`pixel_uniforms` of pixels 0 .. n - 1 at once (numpy)."""
    i = np.arange(1, n + 1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        h = mix64(np.uint64(key) + i * GOLDEN64)
    u1 = ((h >> np.uint64(32)).astype(np.float64) + 0.5) * (1.0 / 4294967296.0)
    u2 = ((h & np.uint64(0xFFFFFFFF)).astype(np.float64) + 0.5) * (1.0 / 4294967296.0)
    return ndtri_np(u1), ndtri_np(u2)


def surface(p: int, cn: float, dx: float, dy: float, dz: float, stem_of_prim: Any,
            material_of_prim: Any, normals: Any, surf: bool) -> tuple[int, int, float]:
    """What a ray of direction (dx, dy, dz) hit, from ``p`` (the triangle, -1 none, or
    ``-2 - j`` curve segment ``j``, whose |cos incidence| ``cn`` the cast reported; or,
    without ``surf``, the stem id): its stem id (-1 none), material and |cos incidence|.
    The tables hold the triangles, then the curve segments last to first, then the miss:
    a negative ``p`` indexes them from the end."""
    if not surf:
        return p, (1 if p > 0 else 0), 1.0
    if p < -1:
        return stem_of_prim[p], material_of_prim[p], cn
    if p == -1:  # nothing (a scene may have no triangles: no normal to read)
        return stem_of_prim[stem_of_prim.shape[0] - 1], material_of_prim[
            material_of_prim.shape[0] - 1], 0.0
    c = float(abs(np.float64(normals[p, 0]) * np.float64(dx)
                  + np.float64(normals[p, 1]) * np.float64(dy)
                  + np.float64(normals[p, 2]) * np.float64(dz)))
    if c > 1.0:
        c = 1.0
    return stem_of_prim[p], material_of_prim[p], c


def wrap(x: int, n: int) -> int:
    """``x % n`` for ``-n <= x < 2 n`` (a neighbour's column), without the division."""
    if x >= n:
        return x - n
    if x < 0:
        return x + n
    return x


def centre_echoes(prim: Any, cn: Any, t: Any, d: Any, stem_of_prim: Any, material_of_prim: Any,
                  normals: Any, refl: Any, surf: bool, n_m: float, r_near: float,
                  ambient: float, i0: int, i1: int, ss: Any, r: Any, e: Any,
                  nir: Any) -> None:
    """Pixels i0 .. i1 of the centre cast (``prim`` the triangle hit, -1 none, or a curve
    primitive, whose |cos incidence| ``cn`` holds, read only there; or, without ``surf``,
    the stem id): stem id (``ss``, -1 no hit), range from the lidar axis (``r``,
    inf none), echo energy ``refl cos / max(r, r_near)^2`` (``e``, ``cos`` of the
    incidence) and the NEAR_IR the surface reflects (uint32)."""
    for i in range(i0, i1):
        p = prim[i]
        s, m, c = surface(p, cn[i] if p < -1 and cn.shape[0] > 0 else 0.0, d[i, 0], d[i, 1],
                          d[i, 2], stem_of_prim, material_of_prim, normals, surf)
        tt = t[i]
        if np.isfinite(tt) and s >= 0:
            rr = tt + n_m
            rn = max(rr, r_near)
            ss[i] = s
            r[i] = rr
            e[i] = refl[m] * c / (rn * rn)
            nir[i] = min(ambient * refl[m], 65535.0)
        else:
            ss[i] = -1
            r[i] = np.inf
            e[i] = 0.0
            nir[i] = min(ambient * 0.05, 65535.0)


def flag_edges(ss: Any, step: Any, reach: int, vw: int, every: bool, c0: int, c1: int,
               out: Any) -> None:
    """``out[c0:c1]`` of (W, H): the pixels whose footprint can straddle an edge, as bits:
    1 horizontally, where a column within ``reach`` either side (wrapping) hits another
    object (or nothing) than the pixel's centre ray; 2 towards the next beam, where the
    pixel hits another object than all of the next beam's pixels within ``vw`` columns of
    the one nearest in angle (column ``c + step[h]``: the beams' azimuth offsets stagger a
    column's pixels by degrees, so a vertical edge seen a column or two apart, a stem's
    side that leans or bows, is not a horizontal one); 4 towards the previous beam, where
    it hits another object than all of the previous beam's about the pixel it is nearest
    to (the beams are 1.4 degrees apart: the edge lies somewhere between, which the probes
    tell). With ``every``, bits 2 and 4 where any of them differs (every pixel whose
    footprint can reach another object above or below: the ``edges`` footprint's bound).
    Each pixel reads its neighbours and writes itself: columns apart run in parallel."""
    W, H = ss.shape
    for c in range(c0, c1):
        col = ss[c]
        for h in range(H):
            out[c, h] = 0
        # bit 1 a column at a time, without branches (the compiler's vector loop); bits 2
        # and 4 stop at the first neighbour that decides (most pixels: the first one)
        for k in range(1, reach + 1):
            right, left = ss[_wrap(c + k, W)], ss[_wrap(c - k, W)]
            for h in range(H):
                out[c, h] |= np.uint8((col[h] != right[h]) | (col[h] != left[h]))
        for h in range(H):
            s = col[h]
            f = out[c, h]
            if h + 1 < H and _beam_differs(ss, s, _wrap(c + step[h], W), h + 1, vw, every):
                f |= 2
            if h > 0 and _beam_differs(ss, s, _wrap(c - step[h - 1], W), h - 1, vw, every):
                f |= 4  # (cp: the previous beam's pixel whose nearest this is)
            out[c, h] = f


def beam_differs(ss: Any, s: int, c2: int, h2: int, vw: int, every: bool) -> bool:
    """Whether ``s`` differs from all of beam ``h2``'s pixels within ``vw`` columns of
    ``c2`` (``every``: from any of them)."""
    W = ss.shape[0]
    for k in range(-vw, vw + 1):
        if (s != ss[_wrap(c2 + k, W), h2]) == every:
            return every
    return not every


def probe_entries(fv: Any, H: int, S: int, V: int, down: int, ent: Any, who: Any,
                  pv: Any) -> tuple[int, int]:
    """The probes of the pixels of ``fv`` (flat flags) with bit 2 or 4, in lattice order:
    ``pv[:m]`` those pixels in order; ``ent[:n]`` the lattice index of each probe (the
    footprint's outer row on the edge's side: ``down`` rows towards beam h + 1 for bit 2,
    away for bit 4; the lower index first), ``who[:n]`` its pixel's place in ``pv``.
    Returns (n, m)."""
    NR = 2 * V + 1
    n = 0
    m = 0
    step = abs(down)
    for i in range(fv.shape[0]):
        f = fv[i]
        if f & 6:
            base = ((i // H) * S * H + i % H) * NR + V
            pv[m] = i
            first, then = (f & 4, f & 2) if down > 0 else (f & 2, f & 4)
            if first:
                ent[n] = base - step
                who[n] = m
                n += 1
            if then:
                ent[n] = base + step
                who[n] = m
                n += 1
            m += 1
    return n, m


def probe_verdicts(fv: Any, pv: Any, who: Any, ss: Any, ts: Any, ps: Any, stem_of_prim: Any,
                   surf: bool) -> None:
    """Each probed pixel ``pv`` (flat flags ``fv``) flagged 3 (the grid) where one of its
    probes (``who``: its pixel's place in ``pv``; ``ts``, ``ps``: distance and primitive)
    sees another object than its centre ray (``ss``), else left with bit 1 only."""
    differs = np.zeros(pv.shape[0], np.bool_)
    for n in range(who.shape[0]):
        p = ps[n]
        sid = stem_of_prim[p] if surf else p  # -1 (and a curve's -2 - j) from the end
        if not math.isfinite(ts[n]):
            sid = -1
        if sid != ss[pv[who[n]]]:
            differs[who[n]] = True
    for m in range(pv.shape[0]):
        fv[pv[m]] = 3 if differs[m] else fv[pv[m]] & 1


def mark_lattice(idx: Any, fl: Any, row_j: Any, grid_j: Any, grid_i: Any, S: int, V: int,
                 W: int, H: int, j0: int, j1: int, need: Any) -> None:
    """``need`` (flat lattice, zeroed) set where the flagged pixels ``idx[j0:j1]`` sample a
    lattice ray that is not a centre ray (as
    :meth:`~emulators.lidar._physics.FootprintGrid.needed` marks them)."""
    WS, NR = W * S, 2 * V + 1
    KH = row_j.shape[0]
    for j in range(j0, j1):
        i = idx[j]
        f = fl[j]
        c = i // H
        h = i - c * H
        for k in range(KH + grid_j.shape[0]):
            if k < KH:
                if not f & 1:
                    continue
                dj, di = row_j[k], 0
            else:
                if not f & 2:
                    continue
                dj, di = grid_j[k - KH], grid_i[k - KH]
            if di == 0 and dj % S == 0:
                continue
            x = _wrap(c * S + dj, WS)
            need[(x * H + h) * NR + di + V] = True


def lattice_rays(o: Any, d: Any, pix: Any, ra: Any, rb: Any, n0: int, n1: int, oo: Any,
                 dd: Any) -> None:
    """Lattice rays n0 .. n1: from pixel ``pix[n]``'s origin (``o`` (W, 3) by column, ``d``
    (W H, 3) column-major), its centre ray turned by ``ra[n]`` radians along the ray's
    horizontal perpendicular and ``rb[n]`` along the perpendicular in its vertical plane,
    unit, float32, into ``oo``/``dd``."""
    H = d.shape[0] // o.shape[0]
    for n in range(n0, n1):
        i = pix[n]
        dx, dy, dz = float(d[i, 0]), float(d[i, 1]), float(d[i, 2])
        ex, ey, ez = -dy, dx, 0.0
        nn = math.sqrt(ex * ex + ey * ey + ez * ez)
        if nn < 1e-9:
            ex, ey, ez = 1.0, 0.0, 0.0
        nn = max(math.sqrt(ex * ex + ey * ey + ez * ez), 1e-12)
        ex, ey, ez = ex / nn, ey / nn, ez / nn
        fx, fy, fz = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex
        a, b = ra[n], rb[n]
        x = dx + a * ex + b * fx
        y = dy + a * ey + b * fy
        z = dz + a * ez + b * fz
        nr = math.sqrt(x * x + y * y + z * z)
        dd[n, 0], dd[n, 1], dd[n, 2] = x / nr, y / nr, z / nr
        c = i // H
        oo[n, 0], oo[n, 1], oo[n, 2] = o[c, 0], o[c, 1], o[c, 2]


def footprint_echoes(idx: Any, fl: Any, j0: int, j1: int, grid: tuple[Any, ...],
                     centre: tuple[Any, ...], lattice: tuple[Any, ...],
                     surfaces: tuple[Any, ...], consts: tuple[Any, ...],
                     out: tuple[Any, ...]) -> None:
    """In groups (tuples, unpacked here; numba passes them as they are): ``grid`` (``wt,
    row_j, grid_j, grid_i, S, V, pos, H``: the footprint's weights and slots, the lattice's
    positions, the beams), ``centre`` (``ss, r, e``: the centre rays' echoes), ``lattice``
    (``t_sub, prim_sub, cn_sub, dd``: the lattice rays cast), ``surfaces``
    (``stem_of_prim, material_of_prim, normals, refl, surf``), ``consts`` (``n_m, r_near,
    resolution, order``) and ``out`` (``e1, r1, s1, e2, r2, s2``).

    The two leading echoes (``order``: 0 strongest first, 1 nearest, 2 farthest) of the
    flagged pixels ``idx[j0:j1]`` from their footprint's samples, in slots: the centre;
    with flag bit 1 the row's others (``row_j`` virtual columns away, ``S`` to a column);
    with bit 2 (always with bit 1) the other rows' (``grid_j`` virtual columns and
    ``grid_i`` rows away). A sample on a column's centre row is that column's centre ray;
    any other is the lattice ray cast at ``pos[(x H + h)(2 V + 1) + i + V]`` (its distance
    ``t_sub``, primitive ``prim_sub`` and, on a curve, |cos| ``cn_sub``). Unused slots
    are left out. A sample of weight ``wt[flags, slot]`` has the energy
    ``w refl cos / max(r, r_near)^2`` (a centre ray's: ``w e``, ``e`` its energy). A
    footprint that one object fills (every sample hits the centre ray's object) answers as
    the centre ray does (``e``, ``r``, ``ss``; no second echo): the sub-rays count only
    where it straddles an edge. Otherwise samples sorted by range (stably) join one echo
    while the gap to the next is within
    ``resolution``; an echo's range is its energy-weighted mean, its stem id that of its
    strongest sample (the nearest on a tie). Pixel ``idx[j]``'s echoes go to ``e1[j]``,
    ``r1[j]``, ``s1[j]`` (the first) and ``e2[j]``, ``r2[j]``, ``s2[j]`` (the second)."""
    wt, row_j, grid_j, grid_i, S, V, pos, H = grid
    ss, r, e = centre
    t_sub, prim_sub, cn_sub, dd = lattice
    stem_of_prim, material_of_prim, normals, refl, surf = surfaces
    n_m, r_near, resolution, order = consts
    e1, r1, s1, e2, r2, s2 = out
    K = wt.shape[1]
    KH = row_j.shape[0]
    W = ss.shape[0] // H
    WS = W * S
    NR = 2 * V + 1
    rs = np.empty(K)
    es = np.empty(K)
    sids = np.empty(K, np.int32)
    ge = np.empty(K)
    ger = np.empty(K)
    gb = np.empty(K)
    gs = np.empty(K, np.int32)
    for j in range(j0, j1):
        i = idx[j]
        f = fl[j]
        c = i // H
        h = i - c * H
        n = 0  # the samples used, in slot order
        fill = ss[i] >= 0  # one object fills the footprint (so far)
        for k in range(K if f & 2 else KH + 1):  # flags 1: the row's slots; 3: all
            w = wt[f, k]
            if k == 0:
                src = i
                row = -1
            else:
                if k <= KH:
                    dj, di = row_j[k - 1], 0
                else:
                    dj, di = grid_j[k - 1 - KH], grid_i[k - 1 - KH]
                x = _wrap(c * S + dj, WS)
                if di == 0 and dj % S == 0:
                    src = (x // S) * H + h
                    row = -1
                else:
                    src = -1
                    row = pos[(x * H + h) * NR + di + V]
            rs[n], es[n], sids[n] = np.inf, 0.0, -1
            if src >= 0:  # a centre ray's sample, the pixel's own or a neighbour's
                if ss[src] >= 0:
                    rs[n], es[n], sids[n] = r[src], w * e[src], ss[src]
            else:
                p = prim_sub[row]
                s, m, cc = surface(p, cn_sub[row] if p < -1 and cn_sub.shape[0] > 0 else 0.0,
                                   dd[row, 0], dd[row, 1],
                                   dd[row, 2], stem_of_prim, material_of_prim, normals, surf)
                tt = np.float64(t_sub[row])
                if np.isfinite(tt) and s >= 0:
                    rr = tt + n_m
                    rn = max(rr, r_near)
                    rs[n], es[n], sids[n] = rr, w * refl[m] * cc / (rn * rn), s
            if sids[n] != ss[i]:
                fill = False
            n += 1
        if fill:
            e1[j], r1[j], s1[j] = e[i], r[i], ss[i]
            e2[j], r2[j], s2[j] = 0.0, np.inf, -1
            continue
        # a stable insertion sort by range, of the samples themselves
        for k in range(1, n):
            x, ex, sx = rs[k], es[k], sids[k]
            m2 = k - 1
            while m2 >= 0 and rs[m2] > x:
                rs[m2 + 1], es[m2 + 1], sids[m2 + 1] = rs[m2], es[m2], sids[m2]
                m2 -= 1
            rs[m2 + 1], es[m2 + 1], sids[m2 + 1] = x, ex, sx
        for g in range(n):
            ge[g], ger[g], gb[g], gs[g] = 0.0, 0.0, -1.0, -1
        g = -1
        prev = 0.0
        for k in range(n):
            x = rs[k]
            if k == 0 or not (x - prev <= resolution):
                g += 1
            prev = x
            if np.isfinite(x):
                ev = es[k]
                ge[g] += ev
                ger[g] += ev * x
                if ev > 0 and ev > gb[g]:
                    gb[g] = ev
                    gs[g] = sids[k]
        # the two leading echoes by the return order, ties to the lower index (the echoes
        # of no energy all read alike: which one comes second does not show)
        b0, b1 = -1, -1
        k0, k1 = np.inf, np.inf
        for g2 in range(g + 1):
            if ge[g2] > 0:
                rg = ger[g2] / ge[g2]
                key = -ge[g2] if order == 0 else (rg if order == 1 else -rg)
            else:
                key = -ge[g2] if order == 0 else np.inf
            if b0 < 0 or key < k0:
                b1, k1 = b0, k0
                b0, k0 = g2, key
            elif b1 < 0 or key < k1:
                b1, k1 = g2, key
        for slot in range(2):
            g2 = b0 if slot == 0 else b1
            eg = ge[g2] if g2 >= 0 else 0.0
            rg = ger[g2] / eg if eg > 0 else np.inf
            sg = gs[g2] if g2 >= 0 else -1
            if slot == 0:
                e1[j], r1[j], s1[j] = eg, rg, sg
            else:
                e2[j], r2[j], s2[j] = eg, rg, sg


def detect(echo: tuple[Any, ...], i0: int, i1: int, model: tuple[Any, ...],
           words: tuple[Any, ...]) -> None:
    """In groups: ``echo`` (``e, r, sid, key``: each pixel's echo, and the return's key of
    draws, :func:`pixel_uniforms`), ``model`` (``scale, gain, sg, width, s_sure, sigma_min,
    sigma0, exponent, s_floor, min_r, max_r, photons, r_near, q``: the return model's
    constants) and ``words`` (``w_range, w_signal, w_refl, sid_out``: written).

    One return for each of pixels i0 .. i1 (column-major) from its echo of energy ``e``
    at range ``r``, with the pixel's two standard normal draws ``v, z`` (:func:`ndtri`
    of its uniforms): detected where
    ``ln(s) / width`` of its signal ``s = e scale gain`` exceeds ``v`` (so with
    probability ``ndtr(ln(s) / width)``; above ``s_sure``, where ``ln(s) / width`` > 9.5,
    always: a draw of 9.5 or more has a chance of 1e-21), its range moved by ``z`` times
    ``max(sigma_min, sigma0 s^-exponent)`` (``sigma_min`` above ``s_floor``), kept
    within [min_r, max_r]; the words RANGE (mm in quanta of ``q``), SIGNAL and
    REFLECTIVITY and the stem id (-1 none) into (N,) column-major arrays. Only a pixel
    with an echo draws (most of a frame's do not: sky, or beyond the reach)."""
    e, r, sid, key = echo
    (scale, gain, sg, width, s_sure, sigma_min, sigma0, exponent, s_floor, min_r, max_r,
     photons, r_near, q) = model
    w_range, w_signal, w_refl, sid_out = words
    for i in range(i0, i1):
        s = e[i] * scale * gain
        ok = False
        rr = 0.0
        if s > 0:
            u1, u2 = _pixel_uniforms(key, i)
            ok = s > s_sure or math.log(s) / width > _ndtri(u1)
            if ok:
                sigma = sigma_min if s > s_floor else max(sigma_min, sigma0 * s ** -exponent)
                rr = r[i] + _ndtri(u2) * sigma
                ok = rr >= min_r and rr <= max_r
        if ok:
            w_range[i] = np.uint32(np.rint(rr * (1000.0 / q)) * q)
            w_signal[i] = np.uint32(min(s * photons, 65535.0))
            rn = max(rr, r_near)
            rho = s * (rn * rn) / sg
            w_refl[i] = np.uint32(min(max(np.rint(rho * 100.0), 0.0), 255.0))
            sid_out[i] = sid[i]
        else:
            w_range[i] = 0
            w_signal[i] = 0
            w_refl[i] = 0
            sid_out[i] = -1


# The kernels call :func:`surface` and :func:`wrap` compiled: numba calls only compiled
# functions.
_surface = compiled(surface)
if _surface is not None:
    surface = _surface
_mix64 = compiled(mix64) or mix64
_ndtri = compiled(ndtri) or ndtri
_pixel_uniforms = compiled(pixel_uniforms) or pixel_uniforms
_wrap = compiled(wrap) or wrap
_beam_differs = compiled(beam_differs) or beam_differs
