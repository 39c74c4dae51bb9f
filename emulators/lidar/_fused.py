"""Blocks of columns encoded, made, cast through Embree and answered in one compiled call,
without the GIL: the rays (:func:`~emulators.lidar._kernel.make_rays`), ``rtcIntersect1`` per ray
(:mod:`emulators.embree`) and the per-ray answer
(:func:`~emulators.lidar._kernel.answer_chunk`), the very kernels the chunk path calls one
after the other with Python in between. Imported lazily (numba), only where the scene hands
over an Embree scene (:meth:`tcf_hil.world.scene.Scene.direct`) and compiled kernels are on.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from emulators.embree import intersect1, new_rayhit
from emulators.jit import compiled, numba_module
from emulators.lidar._footprint import centre_echoes
from emulators.lidar._kernel import answer_chunk, make_rays

numba = numba_module()  # its cache directory set before the kernels below are declared

_make_rays = compiled(make_rays)
_answer_chunk = compiled(answer_chunk)
_centre_echoes = compiled(centre_echoes)


@intrinsic
def _fetch_add(typingctx: Any, counter: Any, index: Any, value: Any) -> Any:
    """``counter[index] += value`` as one atomic step (an int64 array), giving the value
    before; adding 0 reads what other threads wrote."""
    sig = types.int64(counter, types.intp, types.int64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]])
        return builder.atomic_rmw("add", ptr, args[2], "seq_cst")

    return sig, codegen


@numba.njit(cache=True, nogil=True)
def _wait_go(counter: Any) -> bool:
    """Spin (without the GIL) while ``counter[1]`` is 0; whether it then says go (1)."""
    state = 0
    while state == 0:
        state = _fetch_add(counter, 1, 0)  # type: ignore[call-arg]  # numba: typingctx
    return state == 1


@numba.njit(cache=True, nogil=True)
def _next_block(counter: Any, starts: Any) -> int:
    """The first column of the next block no thread has taken (``counter[0]``), or -1."""
    i: int = _fetch_add(counter, 0, 1)  # type: ignore[call-arg]
    return starts[i] if i < starts.shape[0] else -1


@numba.njit(cache=True, nogil=True)
def _wait_blocks(counter: Any, nb: int) -> None:
    """Spin until ``counter[2]`` says all ``nb`` blocks are done (the other threads')."""
    while _fetch_add(counter, 2, 0) < nb:  # type: ignore[call-arg]
        pass


@numba.njit(cache=True, nogil=True)
def _open_block(a: int, b: int, template: Any, packets: Any, ts_words: Any, ts: Any,
                beams: Any, mt: Any, oc: Any, o: Any, d: Any) -> None:
    """Columns a .. b (whole packets) begun: their packets copied from ``template``, their
    column times written into ``ts_words``, their rays made into ``o``/``d``."""
    C = ts_words.shape[1]
    for p in range(a // C, b // C):  # element loops: numba's slice assignment is slower
        for q in range(packets.shape[1]):
            packets[p, q] = template[p, q]
    for c in range(a, b):
        ts_words[c // C, c % C] = ts[c]
    _make_rays(beams, mt, oc, a, o, d)  # type: ignore[misc]  # compiled: this module needs numba


@numba.njit(cache=True, nogil=True)
def _take_block(counter: Any, starts: Any, width: int, template: Any, packets: Any,
                ts_words: Any, ts: Any, beams: Any, mt: Any, oc: Any, o: Any, d: Any) -> int:
    """The next block this thread takes, begun (:func:`_open_block`): its first column,
    or -1 when none is left."""
    a = _next_block(counter, starts)
    if a >= 0:
        _open_block(a, a + width, template, packets, ts_words, ts, beams, mt, oc, o, d)
    return a


@numba.njit(cache=True, nogil=True)
def cast_answer_blocks(fn: int, scene: int, stem_of_prim: Any, beams: Any, mt: Any, oc: Any,
                       starts: Any, counter: Any, wait_all: bool, width: int, o_all: Any,
                       d_all: Any, template: Any, packets: Any, ts_words: Any, ts: Any,
                       noise: Any, n_m: float, min_r: float, reach_ground: float, reach_bark: float,
                       range_units: float, range_mult: int, luts: Any, signal32: Any,
                       clamp_signal: bool, w_range: Any, w_refl: Any, w_nir: Any,
                       w_signal: Any, refl_in_range: bool, sid_out: Any, t_out: Any,
                       ok_out: Any) -> None:
    """The blocks of ``width`` columns starting at ``starts`` of a frame, as many as this
    thread takes: several threads run this call on the same frame at once, each taking the
    next block when done. ``counter`` (int64, shared): the next block; 0 while the caller
    still makes ``mt``/``oc`` (this call waits), 1 to go, 2 to stop at once; the blocks
    done (``wait_all``: return only once all are, not just those this call took).

    Each block: its packets copied from ``template`` (the frame's packets with every
    column encoded at time 0, :func:`protocols.ouster.encode_lidar_columns`) and its column
    times written into ``ts_words`` (:meth:`protocols.ouster.PacketFormat.column_timestamps`);
    its rays (into ``o_all``/``d_all`` (W, H, 3) where they are kept, DUAL; else (0, 0, 0))
    from the frame's factors ``mt`` (3, W, 3) and origins ``oc`` (W, 3); each cast (``fn``
    is ``rtcIntersect1``, ``scene`` its handles, ``stem_of_prim`` the stem id by primitive
    with -1 last for a miss); then :func:`~emulators.lidar._kernel.answer_chunk` with the
    rest of the arguments, which are whole-frame too (the word views (P, C, H), ``noise``
    (W, H) or (0, 0))."""
    H = beams.shape[0]
    C = w_range.shape[1]
    keep = o_all.shape[0] > 0
    o = np.empty((width, H, 3), np.float32)
    d = np.empty((width, H, 3), np.float32)
    t = np.empty((width, H), np.float32)
    sid = np.empty((width, H), np.int32)
    rf, ru, addr = new_rayhit()
    go = _wait_go(counter)
    while go:
        a = _take_block(counter, starts, width, template, packets, ts_words, ts, beams, mt,
                        oc, o, d)
        if a < 0:
            break
        b = a + width
        p0, p1 = a // C, b // C
        for c in range(width):
            for h in range(H):
                t[c, h], prim, _ = intersect1(fn, scene, rf, ru, addr, o[c, h, 0],
                                              o[c, h, 1], o[c, h, 2], d[c, h, 0], d[c, h, 1],
                                              d[c, h, 2])
                sid[c, h] = stem_of_prim[prim]  # -1 (a miss) and a curve's -2 - j: from the end
                if keep:
                    for q in range(3):
                        o_all[a + c, h, q] = o[c, h, q]
                        d_all[a + c, h, q] = d[c, h, q]
        _answer_chunk(  # type: ignore[misc]  # compiled: this module needs numba
            t, sid, noise[a:b] if noise.shape[0] > 0 else noise[:0], a, n_m, min_r,
            reach_ground, reach_bark, range_units, range_mult, luts, signal32, clamp_signal,
            w_range[p0:p1], w_refl[p0:p1], w_nir[p0:p1],
            w_signal[p0:p1] if w_signal.shape[0] > 0 else w_signal[:0], refl_in_range,
            sid_out, t_out, ok_out)
        _fetch_add(counter, 2, 1)  # type: ignore[call-arg]
    if wait_all and go:
        _wait_blocks(counter, starts.shape[0])


@numba.njit(cache=True, nogil=True)
def cast_centre_blocks(fn: int, scene: int, beams: Any, mt: Any, oc: Any, starts: Any,
                       counter: Any, wait_all: bool, width: int, o_all: Any, d_all: Any,
                       template: Any, packets: Any, ts_words: Any, ts: Any, n_m: float,
                       reach: float, prim_all: Any, cn_all: Any, t_all: Any, stem_of_prim: Any,
                       material_of_prim: Any, normals: Any, refl: Any, r_near: float,
                       ambient: float, ss: Any, r: Any, e: Any, nir: Any) -> None:
    """:func:`cast_answer_blocks` for the physical sensor model: each block's packets
    copied from ``template`` and its column times written, its rays made (directions into
    ``d_all`` (W, H, 3), each column's origin into ``o_all[:, 0]``) and cast, and instead
    of the ideal answer the centre rays' echoes
    (:func:`~emulators.lidar._footprint.centre_echoes`, whole-frame (N,) column-major
    arrays from ``ss`` on) from the primitives hit (``prim_all``, -1 none; a curve's |cos
    incidence| into ``cn_all``) and distances
    (``t_all``, inf none or beyond ``reach`` from the lidar axis): the pixel words are the
    physics' to write."""
    H = beams.shape[0]
    o = np.empty((width, H, 3), np.float32)
    d = np.empty((width, H, 3), np.float32)
    d_flat = d_all.reshape(-1, 3)
    rf, ru, addr = new_rayhit()
    go = _wait_go(counter)
    while go:
        a = _take_block(counter, starts, width, template, packets, ts_words, ts, beams, mt,
                        oc, o, d)
        if a < 0:
            break
        b = a + width
        for c in range(width):
            for h in range(H):
                t, prim, cc = intersect1(fn, scene, rf, ru, addr, o[c, h, 0], o[c, h, 1],
                                         o[c, h, 2], d[c, h, 0], d[c, h, 1], d[c, h, 2])
                k = (a + c) * H + h
                cn_all[k] = cc
                tt = np.float64(t)
                rr = tt + n_m
                ok = rr >= 0.0 and rr <= reach
                t_all[k] = tt if ok else np.inf
                prim_all[k] = prim if ok else -1
                for q in range(3):
                    d_all[a + c, h, q] = d[c, h, q]
            for q in range(3):  # a column's beams all start at its origin
                o_all[a + c, 0, q] = o[c, 0, q]
        _centre_echoes(  # type: ignore[misc]  # compiled: this module needs numba
            prim_all, cn_all, t_all, d_flat, stem_of_prim, material_of_prim, normals, refl,
            True, n_m, r_near, ambient, a * H, b * H, ss, r, e, nir)
        _fetch_add(counter, 2, 1)  # type: ignore[call-arg]
    if wait_all and go:
        _wait_blocks(counter, starts.shape[0])

