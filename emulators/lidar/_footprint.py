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

SQRT2 = math.sqrt(2.0)


def centre_echoes(prim: Any, t: Any, d: Any, stem_of_prim: Any, material_of_prim: Any,
                  normals: Any, refl: Any, surf: bool, n_m: float, r_near: float,
                  ambient: float, i0: int, i1: int, ss: Any, r: Any, e: Any, mat: Any,
                  cosi: Any, nir: Any) -> None:
    """Pixels i0 .. i1 of the centre cast (``prim`` the triangle hit, -1 none; or, without
    ``surf``, the stem id): stem id (``ss``, -1 no hit), range from the lidar axis (``r``,
    inf none), echo energy ``refl cos / max(r, r_near)^2`` (``e``), material, |cos
    incidence| and the NEAR_IR the surface reflects."""
    last = stem_of_prim.shape[0] - 1
    for i in range(i0, i1):
        p = prim[i]
        if surf:
            q = p if p >= 0 else last
            s = stem_of_prim[q]
            m = material_of_prim[q]
            qn = p if p > 0 else 0
            c = float(abs(np.float64(normals[qn, 0]) * np.float64(d[i, 0])
                    + np.float64(normals[qn, 1]) * np.float64(d[i, 1])
                    + np.float64(normals[qn, 2]) * np.float64(d[i, 2])))
            if c > 1.0:
                c = 1.0
        else:
            s = p
            m = 1 if p > 0 else 0
            c = 1.0
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


def flag_edges(ss: Any, step: Any, out: Any) -> None:
    """``out`` (W, H), zeroed: the pixels whose footprint can straddle an edge, those whose
    centre ray hits another object (or nothing) than a neighbour's: the next column
    (wrapping) and beam h + 1's pixel nearest in angle (column ``c + step[h]``: the beams'
    azimuth offsets stagger a column's pixels by degrees). Both pixels of a pair."""
    W, H = ss.shape
    for c in range(W):
        cn = c + 1 if c + 1 < W else 0
        for h in range(H):
            s = ss[c, h]
            if s != ss[cn, h]:
                out[c, h] = 1
                out[cn, h] = 1
            if h + 1 < H:
                c2 = (c + step[h]) % W
                if s != ss[c2, h + 1]:
                    out[c, h] = 1
                    out[c2, h + 1] = 1


def footprint_rays(o: Any, d: Any, idx: Any, a: Any, b: Any, oo: Any, dd: Any) -> None:
    """The sub-rays (all but the centre, ``a[0] = b[0] = 0``) of the pixels ``idx``: offset
    by ``a`` radians along the horizontal perpendicular of the centre ray and ``b`` along
    the one in its vertical plane, unit, float32, into ``oo``/``dd`` (len(idx) (K - 1), 3)."""
    K = a.shape[0]
    for j in range(idx.shape[0]):
        i = idx[j]
        dx, dy, dz = float(d[i, 0]), float(d[i, 1]), float(d[i, 2])
        ex, ey, ez = -dy, dx, 0.0
        nn = math.sqrt(ex * ex + ey * ey + ez * ez)
        if nn < 1e-9:
            ex, ey, ez = 1.0, 0.0, 0.0
        nn = max(math.sqrt(ex * ex + ey * ey + ez * ez), 1e-12)
        ex, ey, ez = ex / nn, ey / nn, ez / nn
        fx, fy, fz = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex
        for k in range(1, K):
            x = dx + a[k] * ex + b[k] * fx
            y = dy + a[k] * ey + b[k] * fy
            z = dz + a[k] * ez + b[k] * fz
            n = math.sqrt(x * x + y * y + z * z)
            row = j * (K - 1) + k - 1
            dd[row, 0], dd[row, 1], dd[row, 2] = x / n, y / n, z / n
            oo[row, 0], oo[row, 1], oo[row, 2] = o[i, 0], o[i, 1], o[i, 2]


def footprint_echoes(idx: Any, j0: int, j1: int, w: Any, ss: Any, r: Any, mat: Any,
                     cosi: Any, t_sub: Any, prim_sub: Any, dd: Any, stem_of_prim: Any,
                     material_of_prim: Any, normals: Any, refl: Any, surf: bool, n_m: float,
                     r_near: float, resolution: float, order: int, e1: Any, r1: Any,
                     s1: Any, e2: Any, r2: Any, s2: Any) -> None:
    """The two leading echoes (``order``: 0 strongest first, 1 nearest, 2 farthest) of the
    flagged pixels ``idx[j0:j1]`` from their K samples: the centre (its cast) and K - 1
    sub-rays (``t_sub``/``prim_sub``/``dd``, K - 1 rows a pixel), each of energy ``w[k]
    refl cos / max(r, r_near)^2``. Hits sorted by range (stably) join one echo while the
    gap to the next is within ``resolution``; an echo's range is its energy-weighted mean,
    its stem id that of its strongest hit (the nearest on a tie)."""
    K = w.shape[0]
    last = stem_of_prim.shape[0] - 1
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
        # the samples: the centre first, then the sub-rays
        if ss[i] >= 0:
            rn = max(r[i], r_near)
            rs[0], es[0], sids[0] = r[i], w[0] * refl[mat[i]] * cosi[i] / (rn * rn), ss[i]
        else:
            rs[0], es[0], sids[0] = np.inf, 0.0, -1
        for k in range(1, K):
            row = j * (K - 1) + k - 1
            p = prim_sub[row]
            if surf:
                q = p if p >= 0 else last
                s = stem_of_prim[q]
                m = material_of_prim[q]
                qn = p if p > 0 else 0
                c = float(abs(np.float64(normals[qn, 0]) * np.float64(dd[row, 0])
                        + np.float64(normals[qn, 1]) * np.float64(dd[row, 1])
                        + np.float64(normals[qn, 2]) * np.float64(dd[row, 2])))
                if c > 1.0:
                    c = 1.0
            else:
                s = p
                m = 1 if p > 0 else 0
                c = 1.0
            tt = np.float64(t_sub[row])
            if np.isfinite(tt) and s >= 0:
                rr = tt + n_m
                rn = max(rr, r_near)
                rs[k], es[k], sids[k] = rr, w[k] * refl[m] * c / (rn * rn), s
            else:
                rs[k], es[k], sids[k] = np.inf, 0.0, -1
        # a stable insertion sort by range
        for k in range(K):
            srt[k] = k
        for k in range(1, K):
            v = srt[k]
            x = rs[v]
            m2 = k - 1
            while m2 >= 0 and rs[srt[m2]] > x:
                srt[m2 + 1] = srt[m2]
                m2 -= 1
            srt[m2 + 1] = v
        for g in range(K):
            ge[g], ger[g], gb[g], gs[g] = 0.0, 0.0, -1.0, -1
        g = -1
        prev = 0.0
        for k in range(K):
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
        # the two leading echoes by the return order, ties to the lower index
        b0, b1 = -1, -1
        k0, k1 = np.inf, np.inf
        for g2 in range(K):
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
            eg = ge[g2]
            rg = ger[g2] / eg if eg > 0 else np.inf
            if slot == 0:
                e1[i], r1[i], s1[i] = eg, rg, gs[g2]
            else:
                e2[i], r2[i], s2[i] = eg, rg, gs[g2]


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
