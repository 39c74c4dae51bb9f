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

from emulators.embree import (
    PACKET,
    intersect1,
    intersect_packet,
    new_packet,
    new_rayhit,
    packet_ray,
)
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
def _open_block(a: int, b: int, packets: tuple[Any, ...], rays: tuple[Any, ...], o: Any,
                d: Any) -> None:
    """Columns a .. b (whole packets) begun: their packets copied from the template, their
    column times written (``packets``: ``template, packets, ts_words, ts``), their rays
    made into ``o``/``d`` (``rays``: ``beams, mt, oc``)."""
    template, out, ts_words, ts = packets
    beams, mt, oc = rays
    C = ts_words.shape[1]
    for p in range(a // C, b // C):  # element loops: numba's slice assignment is slower
        for q in range(out.shape[1]):
            out[p, q] = template[p, q]
    for c in range(a, b):
        ts_words[c // C, c % C] = ts[c]
    _make_rays(beams, mt, oc, a, o, d)  # type: ignore[misc]  # compiled: this module needs numba


@numba.njit(cache=True, nogil=True)
def _take_block(blocks: tuple[Any, ...], packets: tuple[Any, ...], rays: tuple[Any, ...],
                o: Any, d: Any) -> int:
    """The next block this thread takes (``blocks``: ``starts, counter, wait_all,
    width``), begun (:func:`_open_block`): its first column, or -1 when none is left."""
    starts, counter, _, width = blocks
    a = _next_block(counter, starts)
    if a >= 0:
        _open_block(a, a + width, packets, rays, o, d)
    return a


@numba.njit(cache=True, nogil=True)
def cast_answer_blocks(direct: tuple[Any, ...], rays: tuple[Any, ...],
                       blocks: tuple[Any, ...], packets: tuple[Any, ...],
                       kept: tuple[Any, ...], noise: Any, enc: tuple[Any, ...],
                       words: tuple[Any, ...], out: tuple[Any, ...]) -> None:
    """The blocks of columns of a frame, as many as this thread takes: several threads run
    this call on the same frame at once, each taking the next block when done. In groups
    (tuples, unpacked here; numba passes them as they are):

    - ``direct`` (``fn, scene, stem_of_prim``): ``fn`` is ``rtcIntersect1``, ``scene`` its
      handles, ``stem_of_prim`` the stem id by primitive with -1 last for a miss;
    - ``rays`` (``beams, mt, oc``): the beams' unit vectors and the frame's factors ``mt``
      (3, W, 3) and origins ``oc`` (W, 3);
    - ``blocks`` (``starts, counter, wait_all, width``): the blocks of ``width`` columns
      starting at ``starts``; ``counter`` (int64, shared): the next block; 0 while the
      caller still makes ``mt``/``oc`` (this call waits), 1 to go, 2 to stop at once; the
      blocks done (``wait_all``: return only once all are, not just those this call took);
    - ``packets`` (``template, packets, ts_words, ts``): the frame's packets with every
      column encoded at time 0 (:func:`protocols.ouster.encode_lidar_columns`), the frame's
      packets, their column time words
      (:meth:`protocols.ouster.PacketFormat.column_timestamps`) and the column times;
    - ``kept`` (``o_all, d_all``): (W, H, 3) where the rays are kept (DUAL), else (0, 0, 0);
    - ``noise`` (W, H) or (0, 0), and ``enc``, ``words`` (whole-frame word views (P, C,
      H); each block slices its own) and ``out``:
      :func:`~emulators.lidar._kernel.answer_chunk`'s.

    Each block: its packets copied from the template and its column times written, its rays
    made and each cast, then :func:`~emulators.lidar._kernel.answer_chunk`."""
    fn, scene, stem_of_prim = direct
    starts, counter, wait_all, width = blocks
    o_all, d_all = kept
    w_range, w_refl, w_nir, w_signal = words
    H = rays[0].shape[0]
    C = w_range.shape[1]
    keep = o_all.shape[0] > 0
    o = np.empty((width, H, 3), np.float32)
    d = np.empty((width, H, 3), np.float32)
    t = np.empty((width, H), np.float32)
    sid = np.empty((width, H), np.int32)
    rf, ru, addr = new_rayhit()
    pf, pu, paddr, valid, vaddr = new_packet()
    pt = np.empty(PACKET, np.float32)
    pp = np.empty(PACKET, np.int32)
    pc = np.empty(PACKET, np.float64)
    go = _wait_go(counter)
    while go:
        a = _take_block(blocks, packets, rays, o, d)
        if a < 0:
            break
        b = a + width
        p0, p1 = a // C, b // C
        if scene[3] != 0:  # packets of a beam's neighbouring columns (cast_centre_blocks)
            for h in range(H):
                for c0 in range(0, width, PACKET):
                    n = min(PACKET, width - c0)
                    for i in range(n):
                        c = c0 + i
                        packet_ray(pf, pu, i, o[c, h, 0], o[c, h, 1], o[c, h, 2], d[c, h, 0],
                                   d[c, h, 1], d[c, h, 2])
                    intersect_packet(scene, pf, pu, paddr, valid, vaddr, n, pt, pp, pc)
                    for i in range(n):
                        t[c0 + i, h] = pt[i]
                        sid[c0 + i, h] = stem_of_prim[pp[i]]
        else:
            for c in range(width):
                for h in range(H):
                    t[c, h], prim, _ = intersect1(fn, scene, rf, ru, addr, o[c, h, 0],
                                                  o[c, h, 1], o[c, h, 2], d[c, h, 0],
                                                  d[c, h, 1], d[c, h, 2])
                    sid[c, h] = stem_of_prim[prim]  # a miss -1, a curve's -2 - j: from the end
        if keep:
            for c in range(width):
                for h in range(H):
                    for q in range(3):
                        o_all[a + c, h, q] = o[c, h, q]
                        d_all[a + c, h, q] = d[c, h, q]
        _answer_chunk(  # type: ignore[misc]  # compiled: this module needs numba
            t, sid, noise[a:b] if noise.shape[0] > 0 else noise[:0], a, enc,
            (w_range[p0:p1], w_refl[p0:p1], w_nir[p0:p1],
             w_signal[p0:p1] if w_signal.shape[0] > 0 else w_signal[:0]), out)
        _fetch_add(counter, 2, 1)  # type: ignore[call-arg]
    if wait_all and go:
        _wait_blocks(counter, starts.shape[0])


@numba.njit(cache=True, nogil=True, inline="always")
def _keep_hit(k: int, t: Any, prim: Any, cc: Any, n_m: float, reach: float,
              hits: tuple[Any, ...]) -> None:
    """Centre ray ``k``'s hit kept (``hits``: ``prim_all, cn_all, t_all``): its distance
    and primitive where it is within ``reach`` of the lidar axis, else none."""
    prim_all, cn_all, t_all = hits
    cn_all[k] = cc
    tt = np.float64(t)
    rr = tt + n_m
    ok = rr >= 0.0 and rr <= reach
    t_all[k] = tt if ok else np.inf
    prim_all[k] = prim if ok else -1


@numba.njit(cache=True, nogil=True)
def cast_centre_blocks(direct: tuple[Any, ...], rays: tuple[Any, ...],
                       blocks: tuple[Any, ...], packets: tuple[Any, ...],
                       kept: tuple[Any, ...], consts: tuple[Any, ...], hits: tuple[Any, ...],
                       surfaces: tuple[Any, ...], echoes: tuple[Any, ...]) -> None:
    """:func:`cast_answer_blocks` for the physical sensor model: each block's packets
    copied from the template and its column times written, its rays made (directions into
    ``d_all`` (W, H, 3), each column's origin into ``o_all[:, 0]``; ``kept``: ``o_all,
    d_all``) and cast, and instead of the ideal answer the centre rays' echoes
    (:func:`~emulators.lidar._footprint.centre_echoes`). ``direct`` (``fn, scene``),
    ``rays``, ``blocks`` and ``packets`` as :func:`cast_answer_blocks`'; ``consts``
    (``n_m, reach, r_near, ambient``); ``hits`` (``prim_all, cn_all, t_all``, whole-frame
    (N,) column-major: the primitives hit, -1 none; a curve's |cos incidence|; the
    distances, inf none or beyond ``reach`` from the lidar axis); ``surfaces``
    (``stem_of_prim, material_of_prim, normals, refl``) and ``echoes`` (``ss, r, e, nir``,
    (N,)): the pixel words are the physics' to write."""
    fn, scene = direct
    starts, counter, wait_all, width = blocks
    o_all, d_all = kept
    n_m, reach, r_near, ambient = consts
    prim_all, cn_all, t_all = hits
    stem_of_prim, material_of_prim, normals, refl = surfaces
    ss, r, e, nir = echoes
    H = rays[0].shape[0]
    o = np.empty((width, H, 3), np.float32)
    d = np.empty((width, H, 3), np.float32)
    d_flat = d_all.reshape(-1, 3)
    rf, ru, addr = new_rayhit()
    pf, pu, paddr, valid, vaddr = new_packet()
    pt = np.empty(PACKET, np.float32)
    pp = np.empty(PACKET, np.int32)
    pc = np.empty(PACKET, np.float64)
    go = _wait_go(counter)
    while go:
        a = _take_block(blocks, packets, rays, o, d)
        if a < 0:
            break
        b = a + width
        if scene[3] != 0:  # packets of a beam's neighbouring columns (coherent rays:
            # about a tenth faster than ray by ray, the same hits)
            for h in range(H):
                for c0 in range(0, width, PACKET):
                    n = min(PACKET, width - c0)
                    for i in range(n):
                        c = c0 + i
                        packet_ray(pf, pu, i, o[c, h, 0], o[c, h, 1], o[c, h, 2], d[c, h, 0],
                                   d[c, h, 1], d[c, h, 2])
                    intersect_packet(scene, pf, pu, paddr, valid, vaddr, n, pt, pp, pc)
                    for i in range(n):
                        _keep_hit((a + c0 + i) * H + h, pt[i], pp[i], pc[i], n_m, reach,
                                  hits)
        else:
            for c in range(width):
                for h in range(H):
                    t, prim, cc = intersect1(fn, scene, rf, ru, addr, o[c, h, 0], o[c, h, 1],
                                             o[c, h, 2], d[c, h, 0], d[c, h, 1], d[c, h, 2])
                    _keep_hit((a + c) * H + h, t, prim, cc, n_m, reach, hits)
        for c in range(width):
            for h in range(H):
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

