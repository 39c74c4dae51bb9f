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


def surface(p: int, dx: float, dy: float, dz: float, stem_of_prim: Any,
            material_of_prim: Any, normals: Any, surf: bool) -> tuple[int, int, float]:
    """What a ray of direction (dx, dy, dz) hit, from ``p`` (the triangle, -1 none; or,
    without ``surf``, the stem id): its stem id (-1 none), material and |cos incidence|."""
    if not surf:
        return p, (1 if p > 0 else 0), 1.0
    q = p if p >= 0 else stem_of_prim.shape[0] - 1
    qn = p if p > 0 else 0
    c = float(abs(np.float64(normals[qn, 0]) * np.float64(dx)
                  + np.float64(normals[qn, 1]) * np.float64(dy)
                  + np.float64(normals[qn, 2]) * np.float64(dz)))
    if c > 1.0:
        c = 1.0
    return stem_of_prim[q], material_of_prim[q], c


def centre_echoes(prim: Any, t: Any, d: Any, stem_of_prim: Any, material_of_prim: Any,
                  normals: Any, refl: Any, surf: bool, n_m: float, r_near: float,
                  ambient: float, i0: int, i1: int, ss: Any, r: Any, e: Any, mat: Any,
                  cosi: Any, nir: Any) -> None:
    """Pixels i0 .. i1 of the centre cast (``prim`` the triangle hit, -1 none; or, without
    ``surf``, the stem id): stem id (``ss``, -1 no hit), range from the lidar axis (``r``,
    inf none), echo energy ``refl cos / max(r, r_near)^2`` (``e``), material, |cos
    incidence| and the NEAR_IR the surface reflects."""
    for i in range(i0, i1):
        s, m, c = surface(prim[i], d[i, 0], d[i, 1], d[i, 2], stem_of_prim, material_of_prim,
                          normals, surf)
        mat[i] = m
        cosi[i] = c
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


def flag_edges(ss: Any, step: Any, reach: int, c0: int, c1: int, out: Any) -> None:
    """``out[c0:c1]`` of (W, H): the pixels whose footprint can straddle an edge, as bits:
    1 horizontally, where a column within ``reach`` either side (wrapping) hits another
    object (or nothing) than the pixel's centre ray; 3 (the grid) vertically, where the
    pixel hits another object than all three of the next beam's pixels nearest in angle
    (columns ``c + step[h]`` and either side: the beams' azimuth offsets stagger a
    column's pixels by degrees, so a vertical edge seen a column apart is not a horizontal
    one), or than all three of the previous beam's around the pixel it is nearest to.
    Each pixel reads its neighbours and writes itself: columns apart run in parallel."""
    W, H = ss.shape
    for c in range(c0, c1):
        for h in range(H):
            s = ss[c, h]
            f = 0
            for k in range(1, reach + 1):
                if s != ss[(c + k) % W, h] or s != ss[(c - k) % W, h]:
                    f = 1
                    break
            if h + 1 < H:
                c2 = (c + step[h]) % W
                if s != ss[c2, h + 1] and s != ss[(c2 + W - 1) % W, h + 1] \
                        and s != ss[(c2 + 1) % W, h + 1]:
                    f = 3
            if h > 0 and f != 3:
                cp = (c - step[h - 1]) % W  # the previous beam's pixel whose nearest this is
                if s != ss[cp, h - 1] and s != ss[(cp + W - 1) % W, h - 1] \
                        and s != ss[(cp + 1) % W, h - 1]:
                    f = 3
            out[c, h] = f


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
            x = (c * S + dj) % WS
            need[(x * H + h) * NR + di + V] = 1


def lattice_rays(o: Any, d: Any, pix: Any, ra: Any, rb: Any, n0: int, n1: int, oo: Any,
                 dd: Any) -> None:
    """Lattice rays n0 .. n1: from pixel ``pix[n]``'s origin, its centre ray turned by
    ``ra[n]`` radians along the ray's horizontal perpendicular and ``rb[n]`` along the
    perpendicular in its vertical plane, unit, float32, into ``oo``/``dd``."""
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
        oo[n, 0], oo[n, 1], oo[n, 2] = o[i, 0], o[i, 1], o[i, 2]


def footprint_echoes(idx: Any, fl: Any, j0: int, j1: int, wt: Any, row_j: Any,
                     grid_j: Any, grid_i: Any, S: int, V: int, pos: Any, H: int, ss: Any,
                     r: Any, mat: Any, cosi: Any, t_sub: Any, prim_sub: Any, dd: Any,
                     stem_of_prim: Any, material_of_prim: Any, normals: Any, refl: Any,
                     surf: bool, n_m: float, r_near: float, resolution: float, order: int,
                     e1: Any, r1: Any, s1: Any, e2: Any, r2: Any, s2: Any) -> None:
    """The two leading echoes (``order``: 0 strongest first, 1 nearest, 2 farthest) of the
    flagged pixels ``idx[j0:j1]`` from their footprint's samples, in slots: the centre;
    with flag bit 1 the row's others (``row_j`` virtual columns away, ``S`` to a column);
    with bit 2 (always with bit 1) the other rows' (``grid_j`` virtual columns and
    ``grid_i`` rows away). A sample on a column's centre row is that column's centre ray;
    any other is the lattice ray cast at ``pos[(x H + h)(2 V + 1) + i + V]``. Unused slots
    are left out. A sample of weight ``wt[flags, slot]`` has the energy
    ``w refl cos / max(r, r_near)^2``. Samples sorted by range (stably) join one echo while
    the gap to the next is within ``resolution``; an echo's range is its energy-weighted
    mean, its stem id that of its strongest sample (the nearest on a tie)."""
    K = wt.shape[1]
    KH = row_j.shape[0]
    W = ss.shape[0] // H
    WS = W * S
    NR = 2 * V + 1
    rs = np.empty(K)
    es = np.empty(K)
    sids = np.empty(K, np.int32)
    srt = np.empty(K, np.int64)
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
        for k in range(K):
            w = wt[f, k]
            if k == 0:
                src = i
                row = -1
            else:
                if k <= KH:
                    if not f & 1:
                        continue
                    dj, di = row_j[k - 1], 0
                else:
                    if not f & 2:
                        continue
                    dj, di = grid_j[k - 1 - KH], grid_i[k - 1 - KH]
                x = (c * S + dj) % WS
                if di == 0 and dj % S == 0:
                    src = (x // S) * H + h
                    row = -1
                else:
                    src = -1
                    row = pos[(x * H + h) * NR + di + V]
            rs[n], es[n], sids[n] = np.inf, 0.0, -1
            if src >= 0:  # a centre ray's sample, the pixel's own or a neighbour's
                if ss[src] >= 0:
                    rn = max(r[src], r_near)
                    rs[n], es[n], sids[n] = r[src], w * refl[mat[src]] * cosi[src] / (rn * rn), \
                        ss[src]
                n += 1
                continue
            s, m, cc = surface(prim_sub[row], dd[row, 0], dd[row, 1], dd[row, 2],
                               stem_of_prim, material_of_prim, normals, surf)
            tt = np.float64(t_sub[row])
            if np.isfinite(tt) and s >= 0:
                rr = tt + n_m
                rn = max(rr, r_near)
                rs[n], es[n], sids[n] = rr, w * refl[m] * cc / (rn * rn), s
            n += 1
        # a stable insertion sort by range
        for k in range(n):
            srt[k] = k
        for k in range(1, n):
            v = srt[k]
            x = rs[v]
            m2 = k - 1
            while m2 >= 0 and rs[srt[m2]] > x:
                srt[m2 + 1] = srt[m2]
                m2 -= 1
            srt[m2 + 1] = v
        for g in range(n):
            ge[g], ger[g], gb[g], gs[g] = 0.0, 0.0, -1.0, -1
        g = -1
        prev = 0.0
        for k in range(n):
            v = srt[k]
            x = rs[v]
            if k == 0 or not (x - prev <= resolution):
                g += 1
            prev = x
            if np.isfinite(x):
                ge[g] += es[v]
                ger[g] += es[v] * x
                if es[v] > 0 and es[v] > gb[g]:
                    gb[g] = es[v]
                    gs[g] = sids[v]
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
                e1[i], r1[i], s1[i] = eg, rg, sg
            else:
                e2[i], r2[i], s2[i] = eg, rg, sg


def detect(e: Any, r: Any, sid: Any, u: Any, z: Any, i0: int, i1: int, H: int,
           scale: float, gain: float, sg: float, width: float, sigma_min: float,
           sigma0: float, exponent: float, min_r: float, max_r: float, photons: float,
           r_near: float, q: int, w_range: Any, w_signal: Any, w_refl: Any,
           sid_out: Any) -> None:
    """One return for each of pixels i0 .. i1 (column-major, ``H`` a column) from its echo
    of energy ``e`` at range ``r``: detected with probability ``ndtr(ln(s) / width)`` of
    its signal ``s = e scale gain`` (``u`` the pixel's uniform draw), its range moved by
    ``z`` times ``max(sigma_min, sigma0 s^-exponent)``, kept within [min_r, max_r]; the
    words RANGE (mm in quanta of ``q``), SIGNAL and REFLECTIVITY into (H, W) images, the
    stem id (-1 none) into ``sid_out`` (N,)."""
    for i in range(i0, i1):
        c = i // H
        h = i - c * H
        s = e[i] * scale * gain
        ok = False
        if s > 0:
            p = 0.5 * math.erfc(-(math.log(s) / width) / SQRT2)
            ok = u[i] < p
        rr = 0.0
        if ok:
            sigma = max(sigma_min, sigma0 * s ** -exponent)
            rr = r[i] + z[i] * sigma
            ok = rr >= min_r and rr <= max_r
        if ok:
            w_range[h, c] = np.uint32(np.rint(rr * (1000.0 / q)) * q)
            w_signal[h, c] = np.uint32(min(s * photons, 65535.0))
            rn = max(rr, r_near)
            rho = s * (rn * rn) / sg
            w_refl[h, c] = np.uint32(min(max(np.rint(rho * 100.0), 0.0), 255.0))
            sid_out[i] = sid[i]
        else:
            w_range[h, c] = 0
            w_signal[h, c] = 0
            w_refl[h, c] = 0
            sid_out[i] = -1


# The kernels call :func:`surface` compiled: numba calls only compiled functions.
_surface = compiled(surface)
if _surface is not None:
    surface = _surface
