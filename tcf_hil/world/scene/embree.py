"""The ``embree`` ray backend: Embree in robust mode through embreex, bound directly where
compiled kernels are on (:mod:`emulators.embree`)."""

from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from tcf_hil.world.scene._backends import NO_COSINES, default_threads

if TYPE_CHECKING:
    from emulators.embree import Curves, DirectScene, HeightGrid
    from emulators.media import Crowns

FloatArray = NDArray[np.float64]


class EmbreeCaster:
    """Embree in robust mode (without it rays slip through edges shared by two triangles),
    from the library the embreex wheel ships: bound directly (:mod:`emulators.embree`: the
    scene handle and ``rtcIntersect1`` from compiled code, so the lidar emulator casts and
    answers its rays in one call without the GIL) where compiled kernels are on, else
    through embreex's own scene; the same hits either way. A batch is traced on one core
    with the GIL released, so a large one is split over ``threads`` threads (about 1.6x on
    2 cores)."""

    name = "embree"
    threads_itself = False
    MIN_RAYS_PER_THREAD = 2048  # a part's rays at least (handing one over costs ~40 us)
    PARTS_PER_THREAD = 4

    def __init__(self, vertices: FloatArray, faces: NDArray[np.int64],
                 threads: int | None = None, direct: bool = True,
                 curves: Curves | None = None, loose_from: int | None = None,
                 crowns: Crowns | None = None, terrain: HeightGrid | None = None) -> None:
        """``curves``: round curves beside the triangles, ``crowns``: porous crowns
        (:mod:`emulators.media`), both where Embree is bound directly only;
        ``terrain``: a grid cast as Embree's grid geometry, Embree bound directly only;
        ``loose_from``: the triangles from there on share no edges (foliage facets) and are
        cast without robust mode where Embree is bound directly (:class:`DirectScene`)."""
        from emulators.jit import jit_enabled

        self.direct_scene: DirectScene | None = None
        if direct and jit_enabled():
            from emulators.embree import direct_scene

            self.direct_scene = direct_scene(vertices, faces, curves, loose_from, crowns,
                                             terrain)
        if self.direct_scene is None and (curves is not None or crowns is not None
                                          or terrain is not None):
            raise OSError("round curves, porous crowns and grids need Embree bound directly "
                          "(compiled kernels on)")
        if self.direct_scene is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene(robust=True)
            TriangleMesh(scene=self._scene, vertices=vertices.astype(np.float32),
                         indices=faces.astype(np.int32))
        self.threads: int | None = threads or default_threads()
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0
        self._pool_lock = threading.Lock()

    def _run(self, o: NDArray[np.float32], d: NDArray[np.float32], t: NDArray[np.float32],
             prim: NDArray[np.int32], cn: NDArray[np.float32] | None = None) -> None:
        if self.direct_scene is not None:
            from emulators.embree import cast_rays

            cast_rays(self.direct_scene.intersect, self.direct_scene.handles, o, d, t, prim,
                      cn if cn is not None else NO_COSINES)
            return
        # t comes in as inf and is traced in place: the hit distance, inf on a miss (and the
        # primitive RTC_INVALID_GEOMETRY_ID, -1 as int32)
        t.fill(np.inf)
        r = self._scene.run(o, d, dists=t, output=1)
        prim[:] = r["primID"]
        if r["tfar"] is not t:
            t[:] = r["tfar"]

    def cast1(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
              ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """:meth:`cast` on the calling thread: for callers that spread their rays over
        threads themselves."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        if self.direct_scene is not None:
            return self.direct_scene.cast(o, d)
        t = np.full(len(o), np.inf, np.float32)
        r = self._scene.run(o, d, dists=t, output=1)
        return r["tfar"], r["primID"]

    def cast1_n(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
                ) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]]:
        """:meth:`cast1`, and the round curves' |cos incidence| as :meth:`cast_n` gives."""
        if self.direct_scene is not None:
            ds = self.direct_scene
            return ds.cast_n(origins, directions, ds.curve_count + ds.crown_count > 0
                             or ds.terrain)
        return (*self.cast1(origins, directions), NO_COSINES)

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        t, prim, _ = self.cast_n(origins, directions, False)
        return t, prim

    def cast_n(self, origins: NDArray[np.floating], directions: NDArray[np.floating],
               cosines: bool = True
               ) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]]:
        """:meth:`cast`, and the |cos incidence| of the round curves hit (0 elsewhere; an
        empty array without ``cosines`` or where the scene has no curves)."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        n = len(o)
        t = np.empty(n, np.float32)
        prim = np.empty(n, np.int32)
        ds = self.direct_scene
        curves = ds is not None and (ds.curve_count + ds.crown_count > 0 or ds.terrain)
        cn = np.empty(n if cosines and curves else 0, np.float32)
        part = (lambda a, b: cn[a:b]) if len(cn) else (lambda a, b: cn)
        threads = self.threads or 1
        # a few parts a thread: rays cost by what they meet (a stem's silhouette several
        # times the sky), and two halves of a set of rays are rarely alike
        parts = min(self.PARTS_PER_THREAD * threads, n // self.MIN_RAYS_PER_THREAD)
        if parts <= 1 or threads == 1:  # (one thread: here, with no hand-over)
            self._run(o, d, t, prim, cn)
        else:
            with self._pool_lock:  # casts may come from several threads (column chunks)
                if self._pool is None or self._pool_pid != os.getpid():  # threads die in a fork
                    self._pool = ThreadPoolExecutor(threads, thread_name_prefix="embree")
                    self._pool_pid = os.getpid()
            cuts = np.linspace(0, n, parts + 1).astype(int)
            jobs = [self._pool.submit(self._run, o[a:b], d[a:b], t[a:b], prim[a:b], part(a, b))
                    for a, b in itertools.pairwise(cuts.tolist())]
            for j in jobs:
                j.result()
        return t, prim, cn
