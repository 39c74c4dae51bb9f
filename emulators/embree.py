"""Embree 4 called from compiled kernels: the library the embreex wheel ships, bound with
ctypes, and ``rtcIntersect1`` called from numba with no Python in between.

embreex builds its scene in a Cython object that keeps the ``RTCScene`` handle to itself,
and its ``run`` loop answers whole arrays only. A lidar kernel that casts its rays and
answers them in one call without the GIL needs the handle and the call, so this module
builds the same scene (one triangle mesh, ``RTC_SCENE_FLAG_ROBUST``: rays do not slip
through the edges two triangles share) from the same library, and calls ``rtcIntersect1``
per ray as embreex's loop does: the same hits, bit for bit (a test holds the two to it).

Imported lazily (it imports numba): :func:`direct_scene` gives None where numba or the
library is missing, or ``TCF_HIL_NO_JIT`` is set; callers then use embreex.
"""

from __future__ import annotations

import ctypes
import glob
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from numpy.typing import NDArray

from emulators import media
from emulators.jit import jit_enabled, numba_module

numba = numba_module()  # its cache directory set before the kernels below are declared

# Embree 4's ABI (rtcore_*.h): enum values, and where RTCRayHit keeps its fields in 32-bit
# words (RTCRay: org xyz, tnear, dir xyz, time, tfar, mask, id, flags; RTCHit: Ng xyz, u, v,
# primID, geomID, instID[1], instPrimID[1]); the struct is 16-byte aligned.
GEOMETRY_TYPE_TRIANGLE, GEOMETRY_TYPE_GRID, GEOMETRY_TYPE_ROUND_LINEAR_CURVE = 0, 2, 16
GEOMETRY_TYPE_SPHERE_POINT, GEOMETRY_TYPE_ORIENTED_DISC_POINT, GEOMETRY_TYPE_USER = 50, 52, 120
BUFFER_TYPE_INDEX, BUFFER_TYPE_VERTEX, BUFFER_TYPE_NORMAL, BUFFER_TYPE_GRID = 0, 1, 3, 8
BUFFER_TYPE_FLAGS = 32
FORMAT_UCHAR, FORMAT_UINT, FORMAT_UINT3 = 0x1001, 0x5001, 0x5003
FORMAT_FLOAT3, FORMAT_FLOAT4, FORMAT_GRID = 0x9003, 0x9004, 0xA001
GRID_TILE = 512  # cells a side of one RTCGrid (their borders shared)
CURVE_FLAG_NEIGHBOR_LEFT, CURVE_FLAG_NEIGHBOR_RIGHT = 1, 2
SCENE_FLAG_ROBUST = 1 << 2
INVALID_ID = 0xFFFFFFFF
TNEAR, TIME, TFAR, MASK, RAY_ID, FLAGS = 3, 7, 8, 9, 10, 11
NG_X, NG_Y, NG_Z, PRIM_ID, GEOM_ID, INST_ID = 12, 13, 14, 17, 18, 19
RAYHIT_WORDS = 32  # 128 bytes: room for the largest RTCRayHit Embree 4 builds
PACKET = 8  # rays a packet (RTCRayHit8: each field 8 words, the fields in RTCRayHit's order)
PACKET_WORDS = 24 * PACKET  # room for the largest RTCRayHit8
DEVICE_NATIVE_RAY8 = 33  # RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED
RAY_QUERY_FLAG_COHERENT = 1 << 16  # RTCRayQueryFlags (rtcore_ray.h); INCOHERENT is 0
FEATURE_FLAG_ALL = 0xFFFFFFFF  # RTCFeatureFlags: what rtcInitIntersectArguments sets
SCRATCH_WORDS = 4
"""After the RTCRayHit: the ray's key (:func:`emulators.media.ray_key`) and the struct's
address, which tells :func:`_crown_hit` that the struct it is given is this one."""


def _library_path() -> str | None:
    """libembree4 as the embreex wheel ships it (``embreex.libs/`` beside the package on
    Linux, ``.dylibs`` inside it on macOS), or None."""
    import embreex

    here = os.path.dirname(embreex.__file__)
    for pattern in (here + ".libs/libembree4*", here + "/.dylibs/libembree4*",
                    here + "/libembree4*"):
        found = sorted(glob.glob(pattern))
        if found:
            return found[0]
    return None


_LIB: Any = None


def _lib() -> Any:
    global _LIB
    if _LIB is None:
        path = _library_path()
        if path is None:
            raise OSError("the embreex wheel ships no libembree4 beside it")
        lib = ctypes.CDLL(path)
        vp, cint, uint, size = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_size_t
        for name, res, args in (
                ("rtcNewDevice", vp, [ctypes.c_char_p]), ("rtcReleaseDevice", None, [vp]),
                ("rtcGetDeviceError", cint, [vp]), ("rtcNewScene", vp, [vp]),
                ("rtcReleaseScene", None, [vp]), ("rtcSetSceneFlags", None, [vp, cint]),
                ("rtcCommitScene", None, [vp]), ("rtcNewGeometry", vp, [vp, cint]),
                ("rtcSetNewGeometryBuffer", vp, [vp, cint, uint, cint, size, size]),
                ("rtcCommitGeometry", None, [vp]), ("rtcAttachGeometry", uint, [vp, vp]),
                ("rtcAttachGeometryByID", None, [vp, vp, uint]),
                ("rtcReleaseGeometry", None, [vp]),
                ("rtcSetGeometryUserPrimitiveCount", None, [vp, uint]),
                ("rtcSetGeometryUserData", None, [vp, vp]),
                ("rtcSetGeometryBoundsFunction", None, [vp, vp, vp]),
                ("rtcSetGeometryIntersectFunction", None, [vp, vp]),
                ("rtcGetDeviceProperty", ctypes.c_ssize_t, [vp, cint])):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = res, args
        _LIB = lib
    return _LIB


@dataclass(frozen=True)
class HeightGrid:
    """A regular grid of vertices (a terrain), cast as Embree's grid geometry (``GRID``:
    the vertices and a few tile records, no triangles stored; each cell two triangles, in
    robust mode watertight as a mesh): ``vertices`` (ny, nx, 3) float32, row by row
    (:meth:`lattice`). A hit on it answers one primitive, the terrain's, and its |cos
    incidence| from the normal Embree reports."""

    vertices: NDArray[np.float32]

    @staticmethod
    def lattice(xs: NDArray[np.floating], ys: NDArray[np.floating],
                z: NDArray[np.floating]) -> HeightGrid:
        """The heights ``z`` (ny, nx) over the lattice ``xs`` by ``ys``, laid out so that
        Embree splits each cell along the diagonal from (x_i, y_j) to (x_i+1, y_j+1) (as
        :func:`tcf_hil.world.forest.mesh.terrain_mesh` does): each row reversed."""
        v = np.empty((len(ys), len(xs), 3), np.float32)
        v[:, :, 0] = np.asarray(xs, np.float64)[None, ::-1]
        v[:, :, 1] = np.asarray(ys, np.float64)[:, None]
        v[:, :, 2] = np.asarray(z, np.float64)[:, ::-1]
        return HeightGrid(v)

    def tiles(self) -> NDArray[np.uint32]:
        """RTCGrid records (startVertexID, stride, width | height << 16) of at most
        :data:`GRID_TILE` cells a side, sharing their borders."""
        ny, nx = self.vertices.shape[:2]
        rows = []
        for j in range(0, max(ny - 1, 1), GRID_TILE):
            for i in range(0, max(nx - 1, 1), GRID_TILE):
                w, h = min(GRID_TILE + 1, nx - i), min(GRID_TILE + 1, ny - j)
                rows.append((j * nx + i, nx, w | (h << 16)))
        return np.array(rows, np.uint32)


@dataclass(frozen=True)
class Curves:
    """Round linear curves (Embree's ``ROUND_LINEAR_CURVE``): tubes swept by a sphere whose
    radius changes linearly along each segment, exact surfaces rather than tessellations.
    ``points`` (m, 4) float32 x, y, z and radius; ``segments`` (k,) uint32, each segment's
    first point (it ends at the next); ``flags`` (k,) uint8, where a segment has a neighbour
    before (:data:`CURVE_FLAG_NEIGHBOR_LEFT`) or after (``..._RIGHT``) it sharing the joint
    (Embree reads that point: it must be there), which Embree then joins without a sphere:
    a segment flagged with a neighbour after it that no segment is ends open. ``discs``
    (q, 4) float32 centre and radius and ``disc_normals`` (q, 3): flat discs (Embree's
    ``ORIENTED_DISC_POINT``), e.g. to close such ends; numbered after the segments.
    ``joints`` (p, 4) float32 centre and radius, p at most the segments: spheres (Embree's
    ``SPHERE_POINT``) that fill where two joined segments meet, sphere ``j`` answering as
    segment ``j`` (no primitives of their own): where Embree cuts two segments' tubes at
    their joint a ray grazing the surface there can slip through the cut, and a sphere
    inside the surface stops it."""

    points: NDArray[np.float32]
    segments: NDArray[np.uint32]
    flags: NDArray[np.uint8]
    discs: NDArray[np.float32] | None = None
    disc_normals: NDArray[np.float32] | None = None
    joints: NDArray[np.float32] | None = None

    def __len__(self) -> int:
        """Primitives: the segments and the discs."""
        return len(self.segments) + (0 if self.discs is None else len(self.discs))


class DirectScene:
    """A triangle mesh and, optionally, round linear curves (:class:`Curves`), porous crowns
    (:class:`emulators.media.Crowns`) and a terrain grid (:class:`HeightGrid`), for
    compiled kernels: :attr:`intersect` (``rtcIntersect1``'s address) and :attr:`handles`
    go to :func:`cast_rays` or :func:`intersect1`, which answer a triangle by its index in
    ``faces``, curve primitive ``j`` (segments, then discs) as ``-2 - j``, crown ``c`` as
    ``-2 - curve_count - c``, the terrain as :attr:`terrain_prim` (after the crowns) and a
    miss as -1. Released with the object (the scenes :attr:`handles` names, and the crowns'
    rows their callbacks read: keep the object while its handles are in use).

    A ray goes through up to three Embree scenes, in turn, each no farther than what it
    hit in the one before: the porous crowns, as user primitives (:func:`_crown_hit`: where
    a ray would stop in their foliage); the loose triangles that share no edge (foliage
    facets, where foliage is facets) and the curves, without robust mode; then the
    triangles ``faces[:loose_from]`` and the terrain grid in robust mode (rays do not slip
    between two triangles through the edge they share: closed meshes need it). Robust mode
    costs 40 % of a cast through a natural stand's foliage facets (``pine-thinning``, one
    thread: 82.6 ms robust, 58.6 ms not), and the curves do not need it (a curve's surface
    is one primitive's). What stops rays soonest goes first: Embree keeps each kind of
    primitive in a hierarchy of its own within a scene and walks them in an order of its
    own, and a ray walks each with the length the one before left it (crowns in a scene of
    their own, before the branches: ``pine-thinning``, one thread, 116 ms a frame's rays,
    against 163 ms for the crowns marched on a grid of their own before the branches,
    and more in one scene with them)."""

    def __init__(self, vertices: NDArray[np.floating], faces: NDArray[np.integer],
                 curves: Curves | None = None, loose_from: int | None = None,
                 crowns: media.Crowns | None = None, terrain: HeightGrid | None = None
                 ) -> None:
        lib = _lib()
        self._lib = lib
        self._scenes: list[Any] = []
        self._device = lib.rtcNewDevice(None)
        if not self._device:
            raise OSError("rtcNewDevice failed")
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        cut = len(f) if loose_from is None else int(loose_from)
        self.curve_count = 0 if curves is None else len(curves)
        rows = []
        n_seg = 0 if curves is None else len(curves.segments)
        self.crown_count = 0 if crowns is None else len(crowns)
        self.terrain = terrain is not None
        self.terrain_prim = -2 - self.curve_count - self.crown_count
        """The primitive every terrain hit answers (after the curves and the crowns)."""
        self._crown_rows = (None if crowns is None or not len(crowns)
                            else _crown_geometry(crowns))  # kept: the callbacks read it
        if self._crown_rows is not None:
            rows.append([self._scene_of(0, v, f[:0], None, None, self._crown_rows), 0, 0, 0])
        if cut < len(f) or self.curve_count:
            rows.append([self._scene_of(0, v, f[cut:], curves), cut, n_seg, 0])
        if cut > 0 or not rows or terrain is not None:
            rows.append([self._scene_of(SCENE_FLAG_ROBUST, v, f[:cut], None, terrain), 0, 0,
                         self.terrain_prim])
        # packets of rays where the library traces them natively and no crowns' callback
        # (which answers one ray at a time) is in the scene
        packets = 0
        if not self.crown_count and lib.rtcGetDeviceProperty(self._device,
                                                             DEVICE_NATIVE_RAY8) == 1:
            packets = int(ctypes.cast(lib.rtcIntersect8, ctypes.c_void_p).value or 0)
        # RTCIntersectArguments for the packets (flags, feature mask, then the context,
        # filter and intersect pointers, all NULL: Embree's defaults): the rays of a packet
        # are coherent (one beam, neighbouring columns), which lets Embree trace them as a
        # packet all the way down (RTC_RAY_QUERY_FLAG_COHERENT, Embree's rtcIntersect8
        # docs) instead of ray by ray: a frame's cast at 2048x10 on forest-x about a
        # quarter faster, its hits to a few float32 units in the last place (coherent).
        self.packet_args = np.zeros(8, np.uint64)
        flags = self.packet_args.view(np.uint32)
        flags[0], flags[1] = RAY_QUERY_FLAG_COHERENT, FEATURE_FLAG_ALL
        self.handles: tuple[Any, ...] = (np.array(rows, np.int64), self.crown_count,
                                         self.curve_count, packets,
                                         self.packet_args.ctypes.data)
        """What the kernels cast through: (k, 4) each scene's handle, the index in ``faces``
        of its first triangle, the number of its curve segments (its discs' numbers
        follow them) and the primitive its terrain grid answers, in the order a ray enters
        them; then the number of porous crowns and of the curve primitives before them
        (crown ``c`` is primitive ``-2 - curve_count - c``), ``rtcIntersect8``'s
        address where :func:`intersect_packet` may be used (else 0) and the address of
        the packets' RTCIntersectArguments (:attr:`packet_args`)."""
        self.intersect: int = int(ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value or 0)

    def _scene_of(self, flags: int, v: NDArray[np.float32], f: NDArray[np.uint32],
                  curves: Curves | None, terrain: HeightGrid | None = None,
                  user: NDArray[np.float64] | None = None) -> int:
        """A committed scene (``flags``): the triangles ``f`` of ``v`` as geometry 0, the
        curves' segments as geometry 1, their discs as geometry 2, the terrain's grid as
        geometry 3 and the curves' joint spheres as geometry 5, each copied into buffers
        Embree owns, and ``user``, porous crowns (:func:`_crown_geometry`), as user
        geometry 4; its handle."""
        lib = self._lib
        scene = lib.rtcNewScene(self._device)
        self._scenes.append(scene)
        lib.rtcSetSceneFlags(scene, flags)
        geoms: list[tuple[int, int, tuple[tuple[int, int, int, NDArray[Any]], ...]]] = []
        if len(f):
            geoms.append((0, GEOMETRY_TYPE_TRIANGLE, (
                (BUFFER_TYPE_VERTEX, FORMAT_FLOAT3, 12, v),
                (BUFFER_TYPE_INDEX, FORMAT_UINT3, 12, f))))
        if curves is not None and len(curves.segments):
            geoms.append((1, GEOMETRY_TYPE_ROUND_LINEAR_CURVE, (
                (BUFFER_TYPE_VERTEX, FORMAT_FLOAT4, 16,
                 np.ascontiguousarray(curves.points, np.float32)),
                (BUFFER_TYPE_INDEX, FORMAT_UINT, 4,
                 np.ascontiguousarray(curves.segments, np.uint32)),
                (BUFFER_TYPE_FLAGS, FORMAT_UCHAR, 1,
                 np.ascontiguousarray(curves.flags, np.uint8)))))
        if curves is not None and curves.discs is not None and len(curves.discs):
            if curves.disc_normals is None or len(curves.disc_normals) != len(curves.discs):
                raise ValueError("Curves: every disc needs a normal (disc_normals)")
            geoms.append((2, GEOMETRY_TYPE_ORIENTED_DISC_POINT, (
                (BUFFER_TYPE_VERTEX, FORMAT_FLOAT4, 16,
                 np.ascontiguousarray(curves.discs, np.float32)),
                (BUFFER_TYPE_NORMAL, FORMAT_FLOAT3, 12,
                 np.ascontiguousarray(curves.disc_normals, np.float32)))))
        if curves is not None and curves.joints is not None and len(curves.joints):
            if len(curves.joints) > len(curves.segments):
                raise ValueError("Curves: more joint spheres than segments")
            geoms.append((5, GEOMETRY_TYPE_SPHERE_POINT, (
                (BUFFER_TYPE_VERTEX, FORMAT_FLOAT4, 16,
                 np.ascontiguousarray(curves.joints, np.float32)),)))
        if terrain is not None:
            geoms.append((3, GEOMETRY_TYPE_GRID, (
                (BUFFER_TYPE_VERTEX, FORMAT_FLOAT3, 12,
                 np.ascontiguousarray(terrain.vertices, np.float32).reshape(-1, 3)),
                (BUFFER_TYPE_GRID, FORMAT_GRID, 12, terrain.tiles()))))
        if user is not None:
            geom = lib.rtcNewGeometry(self._device, GEOMETRY_TYPE_USER)
            lib.rtcSetGeometryUserPrimitiveCount(geom, len(user))
            lib.rtcSetGeometryUserData(geom, user.ctypes.data)
            bounds, hit = crown_callbacks()
            lib.rtcSetGeometryBoundsFunction(geom, bounds, None)
            lib.rtcSetGeometryIntersectFunction(geom, hit)
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometryByID(scene, geom, 4)
            lib.rtcReleaseGeometry(geom)
        for gid, kind, buffers in geoms:
            geom = lib.rtcNewGeometry(self._device, kind)
            for btype, fmt, stride, arr in buffers:
                dst = lib.rtcSetNewGeometryBuffer(geom, btype, 0, fmt, stride, len(arr))
                if dst and arr.nbytes:
                    ctypes.memmove(dst, arr.ctypes.data, arr.nbytes)
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometryByID(scene, geom, gid)
            lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(scene)
        err = lib.rtcGetDeviceError(self._device)
        if err:
            raise OSError(f"Embree could not build the scene (RTCError {err})")
        return int(scene)

    def __del__(self) -> None:
        lib = getattr(self, "_lib", None)
        if lib is not None:
            for scene in getattr(self, "_scenes", []):
                lib.rtcReleaseScene(scene)
            if getattr(self, "_device", None):
                lib.rtcReleaseDevice(self._device)

    @property
    def coherent(self) -> bool:
        """Whether packets are traced as coherent (the default; see :attr:`handles`).
        Incoherent packets answer each ray as ``rtcIntersect1`` does, bit for bit;
        coherent ones to a few float32 units in the last place (a distance may round to
        the next millimetre, a tie go to the other primitive). Set it False where a cast
        must be the single ray's to the bit (paths compared byte for byte)."""
        return bool(self.packet_args.view(np.uint32)[0] & RAY_QUERY_FLAG_COHERENT)

    @coherent.setter
    def coherent(self, on: bool) -> None:
        self.packet_args.view(np.uint32)[0] = RAY_QUERY_FLAG_COHERENT if on else 0

    def cast(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """Hit distance (inf on a miss) and primitive (-1; see the class doc for the rest) of
        (N, 3) float32 rays of unit direction (a crown's free path is measured along it),
        on the calling thread without the GIL."""
        t, prim, _ = self.cast_n(origins, directions, False)
        return t, prim

    def cast_n(self, origins: NDArray[np.float32], directions: NDArray[np.float32],
               cosines: bool = True
               ) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]]:
        """:meth:`cast`, and |cos| of the incidence on what is not a triangle (curves and the
        terrain grid: from Embree's geometric normal; crowns: drawn; 0 on triangles, whose
        normal the caller knows; an empty array without ``cosines``)."""
        o = np.ascontiguousarray(origins, np.float32)
        d = np.ascontiguousarray(directions, np.float32)
        t = np.empty(len(o), np.float32)
        prim = np.empty(len(o), np.int32)
        cn = np.empty(len(o) if cosines else 0, np.float32)
        cast_rays(self.intersect, self.handles, o, d, t, prim, cn)
        return t, prim, cn


def direct_scene(vertices: NDArray[np.floating], faces: NDArray[np.integer],
                 curves: Curves | None = None, loose_from: int | None = None,
                 crowns: media.Crowns | None = None, terrain: HeightGrid | None = None
                 ) -> DirectScene | None:
    """A :class:`DirectScene`, or None where compiled kernels are off or the library cannot
    be had (callers fall back to embreex)."""
    if not jit_enabled():
        return None
    try:
        return DirectScene(vertices, faces, curves, loose_from, crowns, terrain)
    except OSError:
        return None


@intrinsic
def _call_c(typingctx: Any, fn: Any, scene: Any, rayhit: Any) -> Any:
    """``((void (*)(void*, void*, void*)) fn)(scene, rayhit, NULL)``: the address is an
    argument, not a constant, so the kernels that call it stay in numba's on-disk cache."""
    sig = types.void(types.intp, types.intp, types.intp)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(args[1], i8p), builder.inttoptr(args[2], i8p),
                         ir.Constant(i8p, None)])
        return context.get_dummy_value()

    return sig, codegen


_njit = numba.njit(cache=True, nogil=True)


@_njit
def new_rayhit() -> tuple[Any, Any, int]:
    """A 64-byte aligned RTCRayHit: its float32 and uint32 words (and after them, the ray's
    key and the struct's own address: :func:`_crown_hit` reads them), and its address."""
    raw = np.empty(RAYHIT_WORDS + SCRATCH_WORDS + 16, np.float32)
    skip = ((-raw.ctypes.data) % 64) // 4
    f = raw[skip:skip + RAYHIT_WORDS + SCRATCH_WORDS]
    return f, f.view(np.uint32), f.ctypes.data


@numba.njit(cache=True, nogil=True, inline="always")
def intersect1(fn: int, scenes: Any, rf: Any, ru: Any, addr: int, ox: float, oy: float,
               oz: float, dx: float, dy: float, dz: float) -> tuple[float, int, float]:
    """One ray (unit direction) through ``rtcIntersect1`` into each Embree scene of
    ``scenes`` (:attr:`DirectScene.handles`; ``rf``/``ru``/``addr`` from
    :func:`new_rayhit`) in turn, no farther than what it met before: its hit distance (inf
    on a miss), primitive (-1 none; a triangle's index; ``-2 - j`` for curve primitive
    ``j``, a segment or a disc after the segments; a crown after them; the terrain grid
    last) and, on what is not a triangle, |cos| of the incidence (from the geometric normal
    Embree reports; on a crown drawn; 0 on a triangle, whose normal the caller knows)."""
    rf[0], rf[1], rf[2], rf[TNEAR] = ox, oy, oz, 0.0
    rf[4], rf[5], rf[6], rf[TIME] = dx, dy, dz, 0.0
    rf[TFAR] = np.inf
    ru[MASK], ru[RAY_ID], ru[FLAGS] = INVALID_ID, 0, 0
    ru[PRIM_ID], ru[INST_ID] = INVALID_ID, INVALID_ID
    prim: Any = np.int32(-1)
    c = 0.0
    key = np.uint64(0)
    if scenes[1] > 0:  # porous crowns draw from the ray's key: made once a ray
        key = media.ray_key(ru)
        own = _u64(addr + RAYHIT_WORDS * 4, 2)
        own[0], own[1] = key, np.uint64(addr)
    rows = scenes[0]
    for k in range(rows.shape[0]):
        ru[GEOM_ID] = INVALID_ID  # tfar stays: only a nearer hit answers
        _call_c(fn, rows[k, 0], addr)  # type: ignore[call-arg]  # numba: typingctx
        g = ru[GEOM_ID]
        if g == 0:
            prim = np.int32(rows[k, 1] + np.int64(ru[PRIM_ID]))
            c = 0.0
        elif g == 4:  # a porous crown: the foliage faces it at a random orientation
            prim = np.int32(-2 - scenes[2] - np.int64(ru[PRIM_ID]))
            c = math.sqrt(media.uniform(key, 2))
        elif g != INVALID_ID:  # a curve segment (1) or its joint's sphere (5: answers as
            # the segment), a disc (2, numbered after them), the terrain (3: one primitive)
            prim = np.int32(rows[k, 3] if g == 3 else
                            -2 - np.int64(ru[PRIM_ID]) - (rows[k, 2] if g == 2 else 0))
            nx, ny, nz = np.float64(rf[NG_X]), np.float64(rf[NG_Y]), np.float64(rf[NG_Z])
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            c = min(abs(nx * dx + ny * dy + nz * dz) / nn, 1.0) if nn > 0.0 else 1.0
    return rf[TFAR], prim, c


@intrinsic
def _call_c4(typingctx: Any, fn: Any, valid: Any, scene: Any, rayhit: Any, args: Any) -> Any:
    """``((void (*)(void*, void*, void*, void*)) fn)(valid, scene, rayhit, args)``: a
    packet call (``rtcIntersect8``), the addresses arguments as in :func:`_call_c`."""
    sig = types.void(types.intp, types.intp, types.intp, types.intp, types.intp)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        i8p = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i8p, i8p, i8p])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(args[1], i8p), builder.inttoptr(args[2], i8p),
                         builder.inttoptr(args[3], i8p), builder.inttoptr(args[4], i8p)])
        return context.get_dummy_value()

    return sig, codegen


@_njit
def new_packet() -> tuple[Any, Any, int, Any, int]:
    """A 64-byte aligned RTCRayHit8 (its float32 and uint32 words and its address) and
    its 64-byte aligned valid mask (int32 words and address), for :func:`intersect_packet`."""
    raw = np.empty(PACKET_WORDS + 16, np.float32)
    skip = ((-raw.ctypes.data) % 64) // 4
    f = raw[skip:skip + PACKET_WORDS]
    vraw = np.empty(PACKET + 16, np.int32)
    vskip = ((-vraw.ctypes.data) % 64) // 4
    valid = vraw[vskip:vskip + PACKET]
    return f, f.view(np.uint32), f.ctypes.data, valid, valid.ctypes.data


@numba.njit(cache=True, nogil=True, inline="always")
def packet_ray(pf: Any, pu: Any, i: int, ox: float, oy: float, oz: float, dx: float,
               dy: float, dz: float) -> None:
    """Lane ``i`` of a packet (:func:`new_packet`) set to the ray from (ox, oy, oz) along
    the unit (dx, dy, dz), as :func:`intersect1` sets its one ray."""
    P = PACKET
    pf[i], pf[P + i], pf[2 * P + i], pf[TNEAR * P + i] = ox, oy, oz, 0.0
    pf[4 * P + i], pf[5 * P + i], pf[6 * P + i], pf[TIME * P + i] = dx, dy, dz, 0.0
    pf[TFAR * P + i] = np.inf
    pu[MASK * P + i], pu[RAY_ID * P + i], pu[FLAGS * P + i] = INVALID_ID, 0, 0
    pu[PRIM_ID * P + i], pu[INST_ID * P + i] = INVALID_ID, INVALID_ID


@numba.njit(cache=True, nogil=True)
def intersect_packet(scenes: Any, pf: Any, pu: Any, addr: int, valid: Any, vaddr: int,
                     n: int, t: Any, prim: Any, cn: Any) -> None:
    """The first ``n`` lanes of a packet (:func:`packet_ray`) through ``rtcIntersect8``
    (``scenes[3]``, coherent: ``scenes[4]``'s arguments; a scene without crowns) into
    each Embree scene of ``scenes`` in turn,
    as :func:`intersect1` casts one ray (the same hits, to the bit: Embree answers each
    lane as it answers the ray alone): their distances, primitives and |cos| into ``t``,
    ``prim`` and ``cn`` (n,)."""
    P = PACKET
    for i in range(P):
        valid[i] = -1 if i < n else 0
        prim[i] = -1
        cn[i] = 0.0
    rows = scenes[0]
    for k in range(rows.shape[0]):
        for i in range(n):
            pu[GEOM_ID * P + i] = INVALID_ID  # tfar stays: only a nearer hit answers
        _call_c4(scenes[3], vaddr, rows[k, 0], addr, scenes[4])  # type: ignore[call-arg]
        for i in range(n):
            g = pu[GEOM_ID * P + i]
            if g == 0:
                prim[i] = np.int32(rows[k, 1] + np.int64(pu[PRIM_ID * P + i]))
                cn[i] = 0.0
            elif g != INVALID_ID:  # as intersect1 (no crowns here)
                prim[i] = np.int32(rows[k, 3] if g == 3 else
                                   -2 - np.int64(pu[PRIM_ID * P + i])
                                   - (rows[k, 2] if g == 2 else 0))
                nx = np.float64(pf[NG_X * P + i])
                ny = np.float64(pf[NG_Y * P + i])
                nz = np.float64(pf[NG_Z * P + i])
                nn = math.sqrt(nx * nx + ny * ny + nz * nz)
                dx, dy, dz = pf[4 * P + i], pf[5 * P + i], pf[6 * P + i]
                cn[i] = min(abs(nx * dx + ny * dy + nz * dz) / nn, 1.0) if nn > 0.0 else 1.0
    for i in range(n):
        t[i] = pf[TFAR * P + i]


@intrinsic
def _to_ptr(typingctx: Any, addr: Any) -> Any:
    """An address (int) as a ``void*``, for :func:`numba.carray`."""
    sig = types.voidptr(types.intp)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        return builder.inttoptr(args[0], ir.IntType(8).as_pointer())

    return sig, codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _f64(addr: int, shape: Any) -> Any:
    """The float64 array of ``shape`` at ``addr`` (no reference counted: see
    :attr:`DirectScene.handles`)."""
    return numba.carray(_to_ptr(addr), shape, np.float64)  # type: ignore[call-arg]


@numba.njit(cache=True, nogil=True, inline="always")
def _u64(addr: int, n: int) -> Any:
    """The uint64 array of ``n`` at ``addr``."""
    return numba.carray(_to_ptr(addr), n, np.uint64)  # type: ignore[call-arg]


@_njit
def cast_rays(fn: int, scenes: Any, o: Any, d: Any, t: Any, prim: Any, cn: Any) -> None:
    """(N, 3) float32 rays into ``t`` (N,) float32 and ``prim`` (N,) int32, and the curve
    hits' |cos incidence| into ``cn`` (N,) float32 where it is not empty."""
    rf, ru, addr = new_rayhit()
    keep = cn.shape[0] > 0
    for i in range(o.shape[0]):
        t[i], prim[i], c = intersect1(fn, scenes, rf, ru, addr, o[i, 0], o[i, 1], o[i, 2],
                                      d[i, 0], d[i, 1], d[i, 2])
        if keep:
            cn[i] = c


def _crown_geometry(c: media.Crowns) -> NDArray[np.float64]:
    """The crowns as Embree user primitives, rows of :data:`CROWN_WORDS` float64: their
    table (:meth:`emulators.media.Crowns.table`), each crown's own 64-bit key in the last
    of its columns (a hash of its row), and its box (lower xyz, upper xyz), for
    :func:`_crown_hit` and :func:`_crown_bounds` (both read the geometry's user data)."""
    t = np.zeros((len(c), CROWN_WORDS))
    t[:, :media.COLUMNS] = c.table()
    t.view(np.uint64)[:, media.COLUMNS - 1] = media.row_keys(t[:, :media.COLUMNS])
    v32, _ = c.envelopes()
    v = v32.reshape(len(c), -1, 3)
    t[:, media.COLUMNS:media.COLUMNS + 3] = v.min(axis=1)
    t[:, media.COLUMNS + 3:media.COLUMNS + 6] = v.max(axis=1)
    return t


CROWN_WORDS = media.COLUMNS + 6


def _crown_bounds(args: Any) -> None:
    """RTCBoundsFunction: crown ``primID``'s box (``RTCBoundsFunctionArguments``: the
    geometry's user data, primID and timeStep, the output ``RTCBounds``)."""
    w = numba.carray(args, 3, np.uint64)
    prim = np.int64(w[1] & np.uint64(0xFFFFFFFF))
    src = _f64(np.int64(w[0]) + (prim * CROWN_WORDS + media.COLUMNS) * 8, (6,))
    dst = numba.carray(_to_ptr(np.int64(w[2])), 8, np.float32)  # type: ignore[call-arg]
    for i in range(3):
        dst[i] = np.float32(src[i])
        dst[4 + i] = np.float32(src[3 + i])


def _crown_hit(args: Any) -> None:
    """RTCIntersectFunctionN for one ray (``rtcIntersect1``): where the ray stops in crown
    ``primID`` on its own, its entry plus an exponential free path of the crown's
    extinction drawn from the ray's and the crown's keys, reported as a hit where that is
    inside the crown and nearer than what the ray holds. Overlapping crowns each draw their
    own: the nearest stop of independent exponential paths is the free path of their summed
    extinction, and the crown it falls in is each one's with the share of its density
    there (competing exponentials), so the ray's stop is Beer-Lambert's through them all."""
    w = numba.carray(args, 6, np.uint64)
    valid = numba.carray(_to_ptr(np.int64(w[0])), 1, np.int32)  # type: ignore[call-arg]
    if valid[0] == 0:
        return
    prim = np.int64(w[2] & np.uint64(0xFFFFFFFF))
    row_at = np.int64(w[1]) + prim * (CROWN_WORDS * 8)
    row = _f64(row_at, (media.COLUMNS,))
    sigma = row[media.SIGMA]
    if not sigma > 0.0:
        return
    rh = np.int64(w[4])
    rf = numba.carray(_to_ptr(rh), RAYHIT_WORDS, np.float32)
    ru = numba.carray(_to_ptr(rh), RAYHIT_WORDS, np.uint32)
    ox, oy, oz = np.float64(rf[0]), np.float64(rf[1]), np.float64(rf[2])
    dx, dy, dz = np.float64(rf[4]), np.float64(rf[5]), np.float64(rf[6])
    u, v = media.interval(row, ox, oy, oz, dx, dy, dz)
    a = max(u, np.float64(rf[TNEAR]), 0.0)
    if not v > a:
        return
    kept = _u64(rh + RAYHIT_WORDS * 4, 2)  # the key the caster put after its RTCRayHit,
    # where Embree hands over the caller's struct (else it is made again here)
    key = kept[0] if kept[1] == np.uint64(rh) else media.ray_key(ru)
    mine_key = _u64(row_at + (media.COLUMNS - 1) * 8, 1)[0]
    stop = np.float32(a - math.log(media.uniform(key ^ mine_key, 0)) / sigma)
    if not np.float64(stop) <= v:
        return
    held = rf[TFAR]
    if stop > held:
        return
    if stop == held:  # a tie in float32: the crown of the lower key, whatever the order
        if ru[GEOM_ID] != np.uint32(w[5] >> np.uint64(32)):
            return  # what the ray holds is no crown (not in this scene: never)
        other = np.int64(w[1]) + np.int64(ru[PRIM_ID]) * (CROWN_WORDS * 8)
        if not mine_key < _u64(other + (media.COLUMNS - 1) * 8, 1)[0]:
            return
    rf[TFAR] = stop
    rf[NG_X], rf[NG_Y], rf[NG_Z] = -rf[4], -rf[5], -rf[6]
    rf[NG_Z + 1], rf[NG_Z + 2] = 0.0, 0.0
    ru[PRIM_ID] = np.uint32(prim)
    ru[GEOM_ID] = np.uint32(w[5] >> np.uint64(32))
    ru[INST_ID] = INVALID_ID


_CALLBACKS: list[tuple[int, int]] = []


def crown_callbacks() -> tuple[int, int]:
    """The addresses of :func:`_crown_bounds` and :func:`_crown_hit` compiled as C
    callbacks (numba's ``cfunc``; compiled, or loaded from its cache, on first use: a
    ``cfunc`` compiles where it is declared, and the module imports without compiled
    kernels too)."""
    if not _CALLBACKS:
        sig = types.void(types.voidptr)
        _CALLBACKS.append((numba.cfunc(sig, cache=True)(_crown_bounds).address,
                           numba.cfunc(sig, cache=True)(_crown_hit).address))
    return _CALLBACKS[0]
