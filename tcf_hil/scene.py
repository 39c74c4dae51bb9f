"""The scene the lidar sees: terrain and stem meshes in local coordinates, and ray backends.

Backends by name (python-can style registry, imported lazily): ``embree`` (embreex, robust
mode), ``open3d`` (``RaycastingScene``) and ``trimesh`` (trimesh's ray-triangle tests in
numpy: slow, for where neither of the others can be had); ``auto`` (the default) is the first
of those three that imports here (:func:`resolve_backend`). Each computes in float32 (trimesh
in float64, answering in float32), so the scene stays in local plot coordinates (metres from
the plot centre) and callers add the geographic origin back in float64.

Every caster declares what it offers beyond a cast (:class:`Caster`), with a value for "not
here": a cast on the calling thread (``cast1``; the plain cast where the backend spreads its
casts by itself, ``threads_itself``), the threads it splits a large cast over (``threads``,
None where it does not split casts itself) and an Embree scene bound for compiled kernels
(``direct_scene``, None but for Embree's). :class:`Scene` passes them on to the lidar
emulator as its :class:`emulators.lidar.FastRayScene`.
"""

from __future__ import annotations

import importlib
import itertools
import os
import platform
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from tcf_hil.errors import ConfigError
from tcf_hil.forest import Forest, stem_mesh, terrain_mesh

if TYPE_CHECKING:
    from emulators.embree import Curves, DirectScene, HeightGrid
    from emulators.lidar import FastRayScene, Surfaces
    from emulators.media import Crowns

FloatArray = NDArray[np.float64]

BACKENDS: dict[str, tuple[str, str]] = {
    "embree": ("tcf_hil.scene", "EmbreeCaster"),
    "open3d": ("tcf_hil.scene", "Open3dCaster"),
    "trimesh": ("tcf_hil.scene", "TrimeshCaster"),
}
AUTO = "auto"
AUTO_ORDER = ("embree", "open3d", "trimesh")
"""What ``auto`` takes: the first of these whose modules (:data:`BACKEND_MODULES`) import."""
BACKEND_MODULES: dict[str, tuple[str, ...]] = {
    "embree": ("embreex", "embreex.rtcore_scene", "embreex.mesh_construction"),
    "open3d": ("open3d",),
    "trimesh": ("trimesh", "trimesh.ray.ray_triangle"),
}
MATERIAL_GROUND, MATERIAL_BARK = 0, 1
_NO_COS = np.zeros(0, np.float32)
GEOMETRIES = ("auto", "curves", "mesh")
FOLIAGE_AS = ("auto", "volume", "facets")


class Caster(Protocol):
    """Casts rays against one triangle mesh. Every member is required; a backend without a
    capability declares its "not here" value (see the module doc)."""

    name: str  # its name in BACKENDS
    threads_itself: bool  # a cast spreads over the CPUs by itself: callers cast from one thread
    threads: int | None  # threads a large cast is split over here; None: not split here
    direct_scene: DirectScene | None  # an Embree scene bound for compiled kernels, or None

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.integer]]:
        """Hit distance along each unit direction (inf on a miss) and triangle id (-1)."""
        ...

    def cast1(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
              ) -> tuple[NDArray[np.float32], NDArray[np.integer]]:
        """:meth:`cast` on the calling thread, for callers that spread their rays over
        threads themselves; the plain :meth:`cast` where the backend spreads a cast by
        itself (``threads_itself``)."""
        ...


def backend_unavailable(backend: str) -> str | None:
    """Why a backend cannot be had here (its modules do not import), or None."""
    for module in BACKEND_MODULES[backend]:
        try:
            importlib.import_module(module)
        except Exception as err:  # not installed, or its shared libraries are missing
            top = module.split(".")[0]
            if isinstance(err, ModuleNotFoundError) and (err.name or "").split(".")[0] == top:
                why = f"{top} is not installed here"
                machine = platform.machine()
                if backend == "embree" and machine.lower() not in ("x86_64", "amd64"):
                    why += f": Embree has no wheel for {machine}"
                return why
            return f"{top} does not import here ({type(err).__name__}: {err})"
    return None


def resolve_backend(name: str) -> tuple[str, str | None]:
    """The concrete backend for ``name`` and, where ``auto`` did not get Embree, a line to
    say once at start, e.g. ``ray backend: open3d (embreex is not installed here: Embree has
    no wheel for aarch64)``. A named backend is returned as it is (:func:`make_caster` then
    imports it, a ConfigError where it is missing); ``auto`` takes the first of
    :data:`AUTO_ORDER` that imports here (trimesh, a dependency, always does)."""
    if name != AUTO:
        if name not in BACKENDS:
            raise ConfigError("ray backend", name, ", ".join([AUTO, *BACKENDS]))
        return name, None
    why: list[str] = []
    for backend in AUTO_ORDER:
        reason = backend_unavailable(backend)
        if reason is None:
            if not why:
                return backend, None
            slow = ", pure numpy and slow" if backend == "trimesh" else ""
            return backend, f"ray backend: {backend}{slow} ({'; '.join(why)})"
        why.append(reason)
    raise ConfigError("ray backend", name, "an installed backend: " + "; ".join(why))


def default_threads() -> int:
    """Threads for one cast: the CPUs this process may use (``TCF_HIL_RAY_THREADS`` sets it)."""
    env = os.environ.get("TCF_HIL_RAY_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
               else (os.cpu_count() or 1))


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
                      cn if cn is not None else _NO_COS)
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
        return (*self.cast1(origins, directions), _NO_COS)

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
        if parts <= 1:
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


class Open3dCaster:
    """open3d's ``RaycastingScene``: a cast spreads over the CPUs by itself."""

    name = "open3d"
    threads_itself = True
    threads: int | None = None
    direct_scene: DirectScene | None = None

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

    def cast1(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
              ) -> tuple[NDArray[np.float32], NDArray[np.integer]]:
        """:meth:`cast`: open3d spreads every cast over the CPUs itself."""
        return self.cast(origins, directions)


class _BoxGrid:
    """The r-tree trimesh's ray path asks for (``bounds``, ``intersection(box)``: the
    triangles whose boxes meet a box), in numpy: each triangle listed under the cell of an xy
    grid that holds its box's low corner (about eight a cell); a query reaches back by the
    widest box."""

    def __init__(self, lo: FloatArray, hi: FloatArray) -> None:
        n = len(lo)
        self._lo, self._hi = lo, hi
        self.bounds = np.concatenate([lo.min(axis=0), hi.max(axis=0)]) if n else np.zeros(6)
        self._origin = self.bounds[:2]
        extent = np.maximum(self.bounds[3:5] - self._origin, 1e-9)
        self._cell = max(float(np.sqrt(extent.prod() / max(1, n // 8))), 1e-3)
        self._shape = np.floor(extent / self._cell).astype(np.int64) + 1
        widest = (hi[:, :2] - lo[:, :2]).max(axis=0) if n else np.zeros(2)
        self._reach = np.ceil(widest / self._cell).astype(np.int64)
        ij = self._cells(lo[:, :2])
        cell = ij[:, 0] * self._shape[1] + ij[:, 1]
        self._tri = np.argsort(cell, kind="stable")
        self._start = np.searchsorted(cell[self._tri], np.arange(self._shape.prod() + 1))

    def _cells(self, xy: FloatArray) -> NDArray[np.int64]:
        ij = np.floor((xy - self._origin) / self._cell).astype(np.int64)
        return np.clip(ij, 0, self._shape - 1)

    def intersection(self, query: NDArray[np.floating]) -> NDArray[np.int64]:
        box = np.asarray(query, np.float64)  # min xyz, max xyz
        if np.any(box[:3] > self.bounds[3:]) or np.any(box[3:] < self.bounds[:3]):
            return np.zeros(0, np.int64)
        x0, y0 = np.maximum(self._cells(box[None, :2])[0] - self._reach, 0).tolist()
        x1, y1 = self._cells(box[None, 3:5])[0].tolist()
        ny, start = int(self._shape[1]), self._start
        cand = np.concatenate([self._tri[start[x * ny + y0]:start[x * ny + y1 + 1]]
                               for x in range(x0, x1 + 1)])  # a row's cells are contiguous
        meets = np.all(self._lo[cand] <= box[3:], axis=1) & np.all(self._hi[cand] >= box[:3],
                                                                    axis=1)
        found: NDArray[np.int64] = cand[meets]
        return found


class TrimeshCaster:
    """trimesh's ray-triangle tests (:func:`trimesh.ray.ray_triangle.ray_triangle_id`, numpy in
    float64), for where neither Embree nor open3d can be had: the same answers as theirs
    (float32 distance, inf on a miss; triangle id, -1), the nearest hit at a distance of at
    least 0 (equally near ones: the lowest triangle id), and orders of magnitude slower.
    trimesh's broad phase wants an r-tree (rtree, which tcf-hil does not depend on):
    :class:`_BoxGrid` stands in for it. Rays go in batches of ``RAYS_PER_BATCH``, which bounds
    the candidate triangles held at once; a ray within about 1e-5 rad of a triangle's plane
    does not hit it (trimesh's test)."""

    name = "trimesh"
    threads_itself = False
    threads: int | None = None
    direct_scene: DirectScene | None = None
    RAYS_PER_BATCH = 64

    def __init__(self, vertices: FloatArray, faces: NDArray[np.int64]) -> None:
        from trimesh.ray import ray_triangle

        self._ray_triangle_id = ray_triangle.ray_triangle_id
        tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # (n, 3, 3)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(normal, axis=1)
        ok = norm > 0.0  # a degenerate triangle keeps a zero normal: never hit
        normal[ok] /= norm[ok, None]
        self._triangles, self._normals = tri, normal
        self._tree = _BoxGrid(tri.min(axis=1), tri.max(axis=1))

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        n = len(o)
        t = np.full(n, np.inf)
        prim = np.full(n, -1, np.int32)
        if n == 0 or len(self._triangles) == 0:
            return t.astype(np.float32), prim
        for a in range(0, n, self.RAYS_PER_BATCH):
            b = min(n, a + self.RAYS_PER_BATCH)
            tri, ray, loc = self._ray_triangle_id(
                self._triangles, o[a:b], d[a:b], triangles_normal=self._normals,
                tree=self._tree, multiple_hits=True)
            if not len(tri):
                continue
            ray = np.asarray(ray, np.int64) + a
            dist = np.einsum("ij,ij->i", loc - o[ray], d[ray]) / np.einsum(
                "ij,ij->i", d[ray], d[ray])  # along the direction, in its lengths
            ahead = dist >= 0.0
            tri, ray, dist = np.asarray(tri)[ahead], ray[ahead], dist[ahead]
            order = np.lexsort((tri, dist, ray))  # by ray, nearest first, then lowest id
            first = order[np.unique(ray[order], return_index=True)[1]]
            t[ray[first]] = dist[first]
            prim[ray[first]] = tri[first]
        return t.astype(np.float32), prim

    def cast1(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
              ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """:meth:`cast`, which runs on the calling thread."""
        return self.cast(origins, directions)


def _loose_last(faces: NDArray[np.int64], ids: NDArray[np.int32], mat: NDArray[np.uint8]
                ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.uint8], int]:
    """The triangles reordered (stably) so that the foliage's, loose facets that share no
    edge, come last; and where they begin (:class:`EmbreeCaster`'s ``loose_from``)."""
    from emulators.lidar import MATERIALS

    loose = mat == MATERIALS.index("foliage")
    order = np.argsort(loose, kind="stable")
    return faces[order], ids[order], mat[order], int(len(loose) - np.count_nonzero(loose))


def make_caster(name: str, vertices: FloatArray, faces: NDArray[np.int64],
                loose_from: int | None = None) -> Caster:
    """Build the named backend, or ``auto``'s (:func:`resolve_backend`; imports it only
    now). A named backend that cannot be imported is a ConfigError. ``loose_from``: the
    triangles from there on share no edges (Embree casts them without robust mode)."""
    name = resolve_backend(name)[0]
    module, cls = BACKENDS[name]
    try:
        factory = getattr(importlib.import_module(module), cls)
        caster: Caster = (factory(vertices, faces, loose_from=loose_from)
                          if name == "embree" and loose_from is not None
                          else factory(vertices, faces))
        return caster
    except ImportError as err:
        raise ConfigError("ray backend", name, f"an installed backend ({err})") from err


JOINT_SPHERES = True
"""Round curves' stems get a sphere inside the surface at each joint (:attr:`TubeCurves.joints
<tcf_hil.forest.mesh.TubeCurves>`); False: without them, the side-by-side reference of
``benchmarks/bench_curve_joints.py``."""


@dataclass
class Scene:
    """Terrain plus stems in local coordinates: triangles with per-triangle object ids and,
    where the stems and branches are round curves (``stems.geometry``), the object ids and
    materials of the other primitives the caster's Embree scene holds (``curve_id``,
    ``curve_material``): the curve segments, the discs closing stem tops, the porous crowns
    (``stand.foliage_as``) and last the terrain, cast there as one grid primitive (Embree's
    grid geometry: its vertices only, no triangles stored), so ``vertices``/``faces`` hold
    only what is left as triangles (ground objects, foliage facets)."""

    vertices: FloatArray
    faces: NDArray[np.int64]
    stem_id: NDArray[np.int32]  # per triangle: the object id, 0 = terrain (as triangles)
    caster: Caster
    material: NDArray[np.uint8] | None = None  # per triangle; None: terrain ground, else bark
    curve_id: NDArray[np.int32] | None = None  # per other primitive: the object id
    curve_material: NDArray[np.uint8] | None = None  # per other primitive
    _sid_of_prim: tuple[NDArray[np.int32], NDArray[np.int32]] | None = field(
        default=None, init=False, repr=False, compare=False)
    _surfaces: tuple[NDArray[np.int32], Surfaces] | None = field(
        default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_forest(cls, forest: Forest, backend: str = AUTO,
                    stem_tolerance_m: float | None = None,
                    terrain_tolerance_m: float | None = None,
                    margin_m: float | None = None, geometry: str | None = None,
                    foliage_as: str | None = None) -> Scene:
        """The forest's scene. ``geometry`` (default the scenario's ``stems.geometry``, or
        ``mesh`` where ``stem_tolerance_m`` asks for a tessellation):
        ``curves`` casts stems and branches as Embree's round linear curves (exact to
        :data:`~tcf_hil.forest.mesh.CURVE_TOLERANCE_M`; Embree bound directly, i.e. the
        embree backend with compiled kernels on, else a ConfigError), ``mesh`` tessellates
        them (``stems.tolerance_mm``; every backend casts meshes), ``auto`` takes curves
        where they can be cast and meshes elsewhere (open3d and trimesh cast no curves).
        ``foliage_as`` (default the scenario's ``stand.foliage_as``): a natural stand's
        foliage as porous crowns (``volume``, beside round curves only), as facets, or
        ``auto``: crowns where the stems are curves, facets elsewhere."""
        scn = forest.scenario
        geometry = geometry or ("mesh" if stem_tolerance_m is not None
                                else scn.stems.geometry)
        if geometry not in GEOMETRIES:
            raise ConfigError("stems.geometry", geometry, ", ".join(GEOMETRIES))
        foliage = foliage_as or scn.stand.foliage_as
        if foliage not in FOLIAGE_AS:
            raise ConfigError("stand.foliage_as", foliage, ", ".join(FOLIAGE_AS))
        if foliage == "volume" and geometry == "mesh":
            raise ConfigError("stand.foliage_as", "volume", "'auto' or 'facets' where stems "
                              "are meshes (stems.geometry = 'mesh'): porous crowns are cast "
                              "beside round curves")
        bounds = forest.bounds(margin_m)
        tol = (terrain_tolerance_m if terrain_tolerance_m is not None
               else scn.terrain.tolerance_mm / 1000.0)
        sc = forest.scenery()
        if geometry != "mesh":
            scene = cls._with_curves(forest, (bounds, tol), backend, geometry == "curves",
                                     foliage)
            if scene is not None:
                return scene
        tr = terrain_mesh(forest.terrain, bounds, tol)
        if foliage == "volume":
            raise ConfigError("stand.foliage_as", "volume", "'auto' or 'facets' here (stems "
                              "are meshes on this backend, and porous crowns are cast beside "
                              "round curves only)")
        tubes, ids = forest.tubes()
        st = stem_mesh(tubes, stem_tolerance_m if stem_tolerance_m is not None
                       else scn.stems.tolerance_mm / 1000.0, ids=ids)
        verts = np.vstack([tr.vertices, st.vertices])
        faces = np.vstack([tr.faces, st.faces + len(tr.vertices)]).astype(np.int64)
        ids = np.concatenate([np.zeros(len(tr.faces), np.int32),
                              np.asarray(st.face_attributes.get("stem_id", []), np.int32)])
        if sc is None or len(sc) == 0:
            return cls(verts, faces, ids, make_caster(backend, verts, faces))
        # natural stands: branches, foliage, ... after the stems, with their materials
        from emulators.lidar import MATERIALS

        mat = np.concatenate([np.full(len(tr.faces), MATERIALS.index("ground"), np.uint8),
                              np.full(len(st.faces), MATERIALS.index("bark"), np.uint8),
                              sc.face_material])
        faces = np.vstack([faces, sc.faces + len(verts)])
        verts = np.vstack([verts, sc.vertices])
        ids = np.concatenate([ids, sc.face_id])
        faces, ids, mat, loose_from = _loose_last(faces, ids, mat)
        return cls(verts, faces, ids, make_caster(backend, verts, faces, loose_from), mat)

    @classmethod
    def _with_curves(cls, forest: Forest, terrain: tuple[Any, float], backend: str,
                     required: bool, foliage: str = "auto") -> Scene | None:
        """The scene with stems and branches as round curves, (``foliage`` auto or volume)
        the foliage as porous crowns and the terrain (over ``terrain``'s bounds, at its
        tolerance) as Embree's grid geometry, or None where they cannot be cast here (a
        ConfigError where ``required``)."""
        from emulators.jit import jit_enabled

        name = resolve_backend(backend)[0]
        why = (f"the {name} backend casts no curves" if name != "embree"
               else None if jit_enabled() else "compiled kernels are off (TCF_HIL_NO_JIT)")
        if why is None and backend_unavailable("embree") is not None:
            why = backend_unavailable("embree")
        if why is not None:
            if required:
                raise ConfigError("stems.geometry", "curves",
                                  f"'auto' or 'mesh' here ({why})")
            return None
        from emulators.embree import Curves, HeightGrid
        from emulators.lidar import MATERIALS
        from tcf_hil.forest.mesh import stem_curves, terrain_grid

        tubes, ids = forest.tubes()
        tc = stem_curves(tubes, ids)
        pts, seg, flags, seg_id = tc.points, tc.segments, tc.flags, tc.segment_id
        bark = MATERIALS.index("bark")
        grid = HeightGrid.lattice(*terrain_grid(forest.terrain, *terrain))
        verts, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        tri_id = np.zeros(0, np.int32)
        tri_mat = np.zeros(0, np.uint8)
        sc = forest.scenery()
        seg_mat = np.full(len(seg), bark, np.uint8)
        crowns = None
        if sc is not None:
            rp, rs, rf = sc.rods.curves()
            seg = np.concatenate([seg, rs + len(pts)])
            pts = np.vstack([pts, rp])
            flags = np.concatenate([flags, rf])
            seg_id = np.concatenate([seg_id, sc.rods.ids])
            seg_mat = np.concatenate([seg_mat, sc.rods.material])
            tv, tf, ti, tm = sc.tri_vertices, sc.tri_faces, sc.tri_id, sc.tri_material
            if foliage == "facets":
                fv, ff, fi = sc.facets()
                tf = np.vstack([tf, ff + len(tv)])
                tv = np.vstack([tv, fv])
                ti = np.concatenate([ti, fi])
                tm = np.concatenate([tm, np.full(len(ff), MATERIALS.index("foliage"),
                                                 np.uint8)])
            elif len(sc.foliage):
                crowns = sc.foliage.crowns
            faces = np.vstack([faces, tf + len(verts)])
            verts = np.vstack([verts, tv])
            tri_id = np.concatenate([tri_id, ti])
            tri_mat = np.concatenate([tri_mat, tm])
        # curve primitives: the segments, the tops' discs, then the porous crowns
        seg_id = np.concatenate([seg_id, tc.disc_id])
        seg_mat = np.concatenate([seg_mat, np.full(len(tc.disc_id), bark, np.uint8)])
        if crowns is not None and sc is not None:
            seg_id = np.concatenate([seg_id, sc.foliage.ids])
            seg_mat = np.concatenate([seg_mat, np.full(len(crowns), MATERIALS.index("foliage"),
                                                       np.uint8)])
        # and last, one primitive for the whole terrain
        seg_id = np.concatenate([seg_id, [0]])
        seg_mat = np.concatenate([seg_mat, [MATERIALS.index("ground")]]).astype(np.uint8)
        curves = Curves(pts.astype(np.float32), seg.astype(np.uint32), flags,
                        tc.discs.astype(np.float32), tc.disc_normals.astype(np.float32),
                        tc.joints.astype(np.float32) if JOINT_SPHERES else None)
        faces, tri_id, tri_mat, loose_from = _loose_last(faces, tri_id, tri_mat)
        try:
            caster = EmbreeCaster(verts, faces, curves=curves, loose_from=loose_from,
                                  crowns=crowns, terrain=grid)
        except OSError as err:
            if required:
                raise ConfigError("stems.geometry", "curves", f"'auto' or 'mesh' here ({err})"
                                  ) from err
            return None
        return cls(verts, faces, tri_id, caster, tri_mat, seg_id.astype(np.int32), seg_mat)

    @property
    def curve_count(self) -> int:
        """Primitives in the scene other than triangles: round segments, the discs closing
        stem tops, the porous crowns and the terrain grid, numbered in that order (0: all
        triangles)."""
        return 0 if self.curve_id is None else len(self.curve_id)

    @property
    def crown_count(self) -> int:
        """Porous crowns in the scene (foliage cast as a turbid medium; 0: none, or the
        foliage is facets)."""
        ds = self.caster.direct_scene
        return 0 if ds is None else ds.crown_count

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
        """(distance, stem id of the hit: 0 terrain, -1 nothing) for local-frame rays."""
        t, prim = self.caster.cast(origins, directions)
        return t.astype(np.float64), self._stem_ids(prim)

    @property
    def backend(self) -> str:
        """The ray backend casting here (``auto`` resolved: embree, open3d or trimesh)."""
        return self.caster.name

    @property
    def threads(self) -> int | None:
        """Threads the caster splits a large cast over (Embree's), or None where it does not
        split casts itself (open3d spreads them over the CPUs by itself; trimesh casts on
        the calling thread). Settable; on a backend that does not split casts the value is
        kept but changes nothing."""
        return self.caster.threads

    @threads.setter
    def threads(self, n: int | None) -> None:
        self.caster.threads = n

    @property
    def threads_itself(self) -> bool:
        """Whether a cast spreads over the CPUs by itself (open3d): callers then cast from
        one thread. Embree's :meth:`cast32` runs on the calling thread."""
        return self.caster.threads_itself

    def cast32(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """:meth:`cast` for float32 rays with the distance in float32 (the casters' own
        precision), on the calling thread where the backend allows it (Embree): the lidar
        emulator spreads a frame's column chunks over its own threads."""
        t, prim = self.caster.cast1(origins, directions)
        return t, self._stem_ids(prim)

    def direct(self) -> tuple[int, tuple[Any, ...], NDArray[np.int32]] | None:
        """For compiled kernels that cast themselves (the lidar emulator's): ``(address of
        rtcIntersect1, what they cast through (:attr:`emulators.embree.DirectScene.handles`),
        object id by primitive as :meth:`_stem_table` lays it out)``, or None where the
        backend has no directly bound Embree scene (:class:`EmbreeCaster`)."""
        ds = self.caster.direct_scene
        if ds is None:
            return None
        return ds.intersect, ds.handles, self._stem_table()

    def surfaces(self) -> Surfaces:
        """For the physical sensor model: the object id and material of every primitive
        (triangles, then the other primitives last to first: the terrain grid, crowns, discs,
        curve segments; then the miss), the triangles' unit normals, and the caster's casts
        that answer primitives (:class:`emulators.lidar.Surfaces`)."""
        from emulators.lidar import Surfaces

        if self._surfaces is None or self._surfaces[0] is not self.stem_id:
            v = self.vertices[self.faces]
            n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1), 1e-30)[:, None]
            tri = (np.where(self.stem_id > 0, 1, 0) if self.material is None
                   else self.material)
            cm = (self.curve_material[::-1] if self.curve_material is not None
                  else np.zeros(0, np.uint8))
            mat = np.concatenate([tri, cm, [0]]).astype(np.uint8)
            c = self.caster
            cast: Any = c.cast_n if isinstance(c, EmbreeCaster) \
                else (lambda o, d: (*c.cast(o, d), _NO_COS))
            cast1: Any = c.cast1_n if isinstance(c, EmbreeCaster) \
                else (lambda o, d: (*c.cast1(o, d), _NO_COS))
            self._surfaces = (self.stem_id, Surfaces(
                self._stem_table(), n.astype(np.float32), mat, cast, cast1))
        return self._surfaces[1]

    def _stem_table(self) -> NDArray[np.int32]:
        """Object id by primitive: the triangles', then the curve segments' last to first,
        then -1 last, so a miss (-1) and curve segment j (-2 - j) look themselves up from
        the end."""
        if self._sid_of_prim is None or self._sid_of_prim[0] is not self.stem_id:
            curves = self.curve_id[::-1] if self.curve_id is not None else np.zeros(0, np.int32)
            self._sid_of_prim = (self.stem_id, np.concatenate(
                [self.stem_id, curves, [-1]]).astype(np.int32))
        return self._sid_of_prim[1]

    def _stem_ids(self, prim: NDArray[np.integer]) -> NDArray[np.int32]:
        sid: NDArray[np.int32] = self._stem_table()[prim]
        return sid


if TYPE_CHECKING:  # every caster is a Caster, and a Scene the lidar emulator's FastRayScene
    def _declared(e: EmbreeCaster, o: Open3dCaster, t: TrimeshCaster, s: Scene
                  ) -> tuple[Caster, Caster, Caster, FastRayScene]:
        return e, o, t, s
