"""The lidar emulator's per-ray answer, compiled (numba): range, return class, stem id and
the pixel bytes of a chunk of columns in one pass over its rays, without the GIL.

It computes exactly what :meth:`Os0Emulator._answer_numpy` computes (the tests compare the
two byte for byte); that numpy path runs where numba is missing. The packet layout (where
each field's bytes go) comes in as numbers from :mod:`protocols.ouster`'s tables.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from emulators.jit import compiled


def answer_kernel() -> Callable[..., None] | None:
    """The compiled :func:`answer_chunk` (:func:`emulators.jit.compiled`), or None."""
    return compiled(answer_chunk)


def answer_chunk(t: Any, sid: Any, noise: Any, col0: int, enc: tuple[Any, ...],
                 words: tuple[Any, ...], out: tuple[Any, ...]) -> None:
    """Columns col0 .. col0 + n of a frame. ``t``/``sid`` (n, H): the cast, column-major;
    ``noise`` (n, H) or (0, 0). In groups (tuples, unpacked here; numba passes them as they
    are): ``enc`` (``n_m, min_r, reach_ground, reach_bark, range_units, range_mult, luts,
    signal32, clamp_signal, refl_in_range``: the encoding's constants; ``luts`` (2, 3) the
    REFLECTIVITY and NEAR_IR words by class; ``refl_in_range``: REFLECTIVITY shares RANGE's
    word, and is or-ed in), ``words`` (``w_range, w_refl, w_nir, w_signal``, each
    (packets, columns, H): the pixel words of RANGE, REFLECTIVITY, NEAR_IR and SIGNAL in
    the chunk's zeroed packets, SIGNAL (0, 0, 0) where the profile has none) and ``out``
    (``sid_out`` (W, H); ``t_out``/``ok_out`` (W, H) or (0, 0): the first return for
    DUAL)."""
    (n_m, min_r, reach_ground, reach_bark, range_units, range_mult, luts, signal32,
     clamp_signal, refl_in_range) = enc
    w_range, w_refl, w_nir, w_signal = words
    sid_out, t_out, ok_out = out
    n, H = t.shape
    C = w_range.shape[1]
    noisy = noise.shape[0] > 0
    keep = t_out.shape[0] > 0
    signal = w_signal.shape[0] > 0
    for c in range(n):
        p = c // C
        j = c - p * C
        for h in range(H):
            tt = np.float64(t[c, h])
            if noisy:
                tt += noise[c, h]
            r = tt + n_m
            s = sid[c, h]
            bark = s > 0
            ok = r >= min_r and r <= (reach_bark if bark else reach_ground)
            cls = (2 if bark else 1) if ok else 0
            sid_out[col0 + c, h] = s if ok else -1
            if keep:
                t_out[col0 + c, h] = tt
                ok_out[col0 + c, h] = ok
            w_range[p, j, h] = np.int64(np.rint(r * range_units)) * range_mult if ok else 0
            if refl_in_range:
                w_refl[p, j, h] |= luts[0, cls]
            else:
                w_refl[p, j, h] = luts[0, cls]
            w_nir[p, j, h] = luts[1, cls]
            if signal:
                den = np.float32(max(r, 0.5))
                den = den * den
                sig = signal32[cls] / den
                if clamp_signal and sig > np.float32(65535.0):
                    sig = np.float32(65535.0)
                w_signal[p, j, h] = np.int64(sig)


def rays_kernel() -> Callable[..., None] | None:
    """The compiled :func:`make_rays`, or None."""
    return compiled(make_rays)


def make_rays(beams: Any, mt: Any, oc: Any, col0: int, o: Any, d: Any) -> None:
    """The rays of columns col0 .. col0 + n, column-major: ``o``/``d`` (n, H, 3) float32,
    from the beams' unit vectors ``beams`` (H, 3) and the frame's factors ``mt`` (3, W, 3)
    and beam origins ``oc`` (W, 3) (:func:`column_frames`): ``d[c, h, i] = sum_j
    beams[h, j] mt[j, col0 + c, i]``, summed left to right in float32, one rounding per
    operation (as the numpy path)."""
    for c in range(o.shape[0]):
        # the column's factors in locals: the stores below may alias the arrays
        k = col0 + c
        m00, m01, m02 = mt[0, k, 0], mt[0, k, 1], mt[0, k, 2]
        m10, m11, m12 = mt[1, k, 0], mt[1, k, 1], mt[1, k, 2]
        m20, m21, m22 = mt[2, k, 0], mt[2, k, 1], mt[2, k, 2]
        ox, oy, oz = oc[k, 0], oc[k, 1], oc[k, 2]
        for h in range(o.shape[1]):
            b0, b1, b2 = beams[h, 0], beams[h, 1], beams[h, 2]
            d[c, h, 0] = b0 * m00 + b1 * m10 + b2 * m20
            d[c, h, 1] = b0 * m01 + b1 * m11 + b2 * m21
            d[c, h, 2] = b0 * m02 + b1 * m12 + b2 * m22
            o[c, h, 0], o[c, h, 1], o[c, h, 2] = ox, oy, oz


def frames_kernel() -> Callable[..., None] | None:
    """The compiled :func:`column_frames`, or None."""
    return compiled(column_frames)


def column_frames(pos: Any, rot: Any, cos: Any, sin: Any, lr: Any, lt: Any, n_m: float,
                  mt: Any, oc: Any) -> None:
    """Per column c (``pos`` (n, 3), ``rot`` (n, 3, 3), the encoder angle's ``cos``/``sin``
    (n,)): ``M_c = R_c L Rz(theta_c)`` into ``mt`` (3, n, 3) float32 as ``mt[j, c, i] =
    M_c[i, j]``, and the beam origin ``p_c + R_c t_L + n M_c e_x`` into ``oc`` (n, 3)
    float32; sums left to right, one rounding per operation (as the numpy path)."""
    for c in range(pos.shape[0]):
        for i in range(3):
            r0, r1, r2 = rot[c, i, 0], rot[c, i, 1], rot[c, i, 2]
            a0 = r0 * lr[0, 0] + r1 * lr[1, 0] + r2 * lr[2, 0]
            a1 = r0 * lr[0, 1] + r1 * lr[1, 1] + r2 * lr[2, 1]
            a2 = r0 * lr[0, 2] + r1 * lr[1, 2] + r2 * lr[2, 2]
            m0 = a0 * cos[c] + a1 * sin[c]
            mt[0, c, i] = m0
            mt[1, c, i] = a1 * cos[c] - a0 * sin[c]
            mt[2, c, i] = a2
            oc[c, i] = pos[c, i] + (r0 * lt[0] + r1 * lt[1] + r2 * lt[2]) + n_m * m0
