"""The scene itself: the terrain, stem and scenery meshes (or Embree's curves and height
grid) assembled in local coordinates for one of the ray backends (:mod:`._backends`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.errors import ConfigError
from tcf_hil.world.forest import Forest, stem_mesh, terrain_mesh
from tcf_hil.world.scene._backends import (
    AUTO,
    NO_COSINES,
    Caster,
    backend_unavailable,
    make_caster,
    resolve_backend,
)
from tcf_hil.world.scene.embree import EmbreeCaster

if TYPE_CHECKING:
    from emulators.lidar import FastRayScene, Surfaces
    from tcf_hil.world.scene.open3d import Open3dCaster
    from tcf_hil.world.scene.trimesh import TrimeshCaster

FloatArray = NDArray[np.float64]
MATERIAL_GROUND, MATERIAL_BARK = 0, 1
GEOMETRIES = ("auto", "curves", "mesh")
FOLIAGE_AS = ("auto", "volume", "facets")


def _loose_last(faces: NDArray[np.int64], ids: NDArray[np.int32], mat: NDArray[np.uint8]
                ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.uint8], int]:
    """The triangles reordered (stably) so that the foliage's, loose facets that share no
    edge, come last; and where they begin (:class:`~tcf_hil.world.scene.embree.EmbreeCaster`'s
    ``loose_from``)."""
    from emulators.lidar import MATERIALS

    loose = mat == MATERIALS.index("foliage")
    order = np.argsort(loose, kind="stable")
    return faces[order], ids[order], mat[order], int(len(loose) - np.count_nonzero(loose))


JOINT_SPHERES = True
"""Round curves' stems get a sphere inside the surface at each joint (:attr:`TubeCurves.joints
<tcf_hil.world.forest.mesh.TubeCurves>`); False: without them, the side-by-side reference of
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
        :data:`~tcf_hil.world.forest.mesh.CURVE_TOLERANCE_M`; Embree bound directly, i.e. the
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
        from tcf_hil.world.forest.mesh import stem_curves, terrain_grid

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
                else (lambda o, d: (*c.cast(o, d), NO_COSINES))
            cast1: Any = c.cast1_n if isinstance(c, EmbreeCaster) \
                else (lambda o, d: (*c.cast1(o, d), NO_COSINES))
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
