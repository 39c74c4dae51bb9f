"""The scene the lidar sees: terrain and stem meshes in local coordinates, and ray backends.

Backends by name (python-can style registry, imported lazily): ``embree`` (embreex, robust
mode; the default) and ``open3d`` (``RaycastingScene``). Both compute in float32, so the scene
stays in local plot coordinates (metres from the plot centre) and callers add the geographic
origin back in float64.
"""

from __future__ import annotations

import importlib
import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from tcf_hil.errors import ConfigError
from tcf_hil.forest import Forest, stem_mesh, terrain_mesh

FloatArray = NDArray[np.float64]

BACKENDS: dict[str, tuple[str, str]] = {
    "embree": ("tcf_hil.scene", "EmbreeCaster"),
    "open3d": ("tcf_hil.scene", "Open3dCaster"),
}
MATERIAL_GROUND, MATERIAL_BARK = 0, 1


class Caster(Protocol):
    """Casts rays against one triangle mesh."""

    name: str

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.integer]]:
        """Hit distance along each unit direction (inf on a miss) and triangle id (-1)."""
        ...


def default_threads() -> int:
    """Threads for one cast: the CPUs this process may use (``TCF_HIL_RAY_THREADS`` sets it)."""
    env = os.environ.get("TCF_HIL_RAY_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else (os.cpu_count() or 1))


class EmbreeCaster:
    """Embree in robust mode (without it rays slip through edges shared by two triangles),
    from the library the embreex wheel ships: bound directly (:mod:`emulators._embree`: the
    scene handle and ``rtcIntersect1`` from compiled code, so the lidar emulator casts and
    answers its rays in one call without the GIL) where compiled kernels are on, else
    through embreex's own scene; the same hits either way. A batch is traced on one core
    with the GIL released, so a large one is split over ``threads`` threads (about 1.6x on
    2 cores)."""

    name = "embree"
    MIN_RAYS_PER_THREAD = 16384

    def __init__(self, vertices: FloatArray, faces: NDArray[np.int64],
                 threads: int | None = None, direct: bool = True) -> None:
        from emulators._jit import jit_enabled

        self.direct_scene: Any = None
        if direct and jit_enabled():
            from emulators._embree import direct_scene

            self.direct_scene = direct_scene(vertices, faces)
        if self.direct_scene is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene(robust=True)
            TriangleMesh(scene=self._scene, vertices=vertices.astype(np.float32),
                         indices=faces.astype(np.int32))
        self.threads = threads or default_threads()
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0
        self._pool_lock = threading.Lock()

    def _run(self, o: NDArray[np.float32], d: NDArray[np.float32], t: NDArray[np.float32],
             prim: NDArray[np.int32]) -> None:
        if self.direct_scene is not None:
            from emulators._embree import cast_rays

            cast_rays(self.direct_scene.intersect, self.direct_scene.handle, o, d, t, prim)
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

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        n = len(o)
        t = np.empty(n, np.float32)
        prim = np.empty(n, np.int32)
        parts = min(self.threads, n // self.MIN_RAYS_PER_THREAD)
        if parts <= 1:
            self._run(o, d, t, prim)
        else:
            with self._pool_lock:  # casts may come from several threads (column chunks)
                if self._pool is None or self._pool_pid != os.getpid():  # threads die in a fork
                    self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="embree")
                    self._pool_pid = os.getpid()
            cuts = np.linspace(0, n, parts + 1).astype(int)
            jobs = [self._pool.submit(self._run, o[a:b], d[a:b], t[a:b], prim[a:b])
                    for a, b in itertools.pairwise(cuts.tolist())]
            for j in jobs:
                j.result()
        return t, prim


class Open3dCaster:
    name = "open3d"

    def __init__(self, vertices: FloatArray, faces: NDArray[np.int64]) -> None:
        o3d: Any = importlib.import_module("open3d")  # untyped for mypy: its stubs lag
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                                  o3d.core.Tensor(faces.astype(np.uint32)))

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.integer]]:
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        ans = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float32)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t)
        prim[miss] = -1
        t[miss] = np.inf
        return t, prim


def make_caster(name: str, vertices: FloatArray, faces: NDArray[np.int64]) -> Caster:
    """Build the named backend (imports it only now)."""
    if name not in BACKENDS:
        raise ConfigError("ray backend", name, ", ".join(BACKENDS))
    module, cls = BACKENDS[name]
    try:
        factory = getattr(importlib.import_module(module), cls)
        caster: Caster = factory(vertices, faces)
        return caster
    except ImportError as err:
        raise ConfigError("ray backend", name, f"an installed backend ({err})") from err


@dataclass
class Scene:
    """Terrain plus stems as one mesh in local coordinates, with per-triangle stem ids."""

    vertices: FloatArray
    faces: NDArray[np.int64]
    stem_id: NDArray[np.int32]  # per triangle; 0 = terrain
    caster: Caster
    _sid_of_prim: tuple[NDArray[np.int32], NDArray[np.int32]] | None = field(
        default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_forest(cls, forest: Forest, backend: str = "embree",
                    stem_tolerance_m: float | None = None,
                    terrain_tolerance_m: float | None = None,
                    margin_m: float | None = None) -> Scene:
        scn = forest.scenario
        st = stem_mesh(forest.stems, stem_tolerance_m if stem_tolerance_m is not None
                       else scn.stems.tolerance_mm / 1000.0)
        tr = terrain_mesh(forest.terrain, forest.bounds(margin_m),
                          terrain_tolerance_m if terrain_tolerance_m is not None
                          else scn.terrain.tolerance_mm / 1000.0)
        verts = np.vstack([tr.vertices, st.vertices])
        faces = np.vstack([tr.faces, st.faces + len(tr.vertices)]).astype(np.int64)
        ids = np.concatenate([np.zeros(len(tr.faces), np.int32),
                              np.asarray(st.face_attributes.get("stem_id", []), np.int32)])
        return cls(verts, faces, ids, make_caster(backend, verts, faces))

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
        """(distance, stem id of the hit: 0 terrain, -1 nothing) for local-frame rays."""
        t, prim = self.caster.cast(origins, directions)
        return t.astype(np.float64), self._stem_ids(prim)

    @property
    def threads_itself(self) -> bool:
        """Whether a cast spreads over the CPUs by itself (open3d): callers then cast from
        one thread. Embree's :meth:`cast32` runs on the calling thread."""
        return not hasattr(self.caster, "cast1")

    def cast32(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """:meth:`cast` for float32 rays with the distance in float32 (the casters' own
        precision), on the calling thread where the backend allows it (Embree): the lidar
        emulator spreads a frame's column chunks over its own threads."""
        one = getattr(self.caster, "cast1", None)
        t, prim = (one or self.caster.cast)(origins, directions)
        return t, self._stem_ids(prim)

    def direct(self) -> tuple[int, int, NDArray[np.int32]] | None:
        """For compiled kernels that cast themselves (the lidar emulator's): ``(address of
        rtcIntersect1, the RTCScene, stem id by triangle with -1 last)``, or None where the
        backend has no directly bound Embree scene (:class:`EmbreeCaster`)."""
        ds = getattr(self.caster, "direct_scene", None)
        if ds is None:
            return None
        return ds.intersect, ds.handle, self._stem_table()

    def _stem_table(self) -> NDArray[np.int32]:
        """Stem id by triangle, then -1 last: a miss (triangle -1) looks itself up."""
        if self._sid_of_prim is None or self._sid_of_prim[0] is not self.stem_id:
            self._sid_of_prim = (self.stem_id,
                                 np.append(self.stem_id, np.int32(-1)).astype(np.int32))
        return self._sid_of_prim[1]

    def _stem_ids(self, prim: NDArray[np.integer]) -> NDArray[np.int32]:
        sid: NDArray[np.int32] = self._stem_table()[prim]
        return sid
