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
import os
from typing import Any

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from numpy.typing import NDArray

from emulators.jit import jit_enabled, numba_module

numba = numba_module()  # its cache directory set before the kernels below are declared

# Embree 4's ABI (rtcore_*.h): enum values, and where RTCRayHit keeps its fields in 32-bit
# words (RTCRay: org xyz, tnear, dir xyz, time, tfar, mask, id, flags; RTCHit: Ng xyz, u, v,
# primID, geomID, instID[1], instPrimID[1]); the struct is 16-byte aligned.
GEOMETRY_TYPE_TRIANGLE = 0
BUFFER_TYPE_INDEX, BUFFER_TYPE_VERTEX = 0, 1
FORMAT_UINT3, FORMAT_FLOAT3 = 0x5003, 0x9003
SCENE_FLAG_ROBUST = 1 << 2
INVALID_ID = 0xFFFFFFFF
TNEAR, TIME, TFAR, MASK, RAY_ID, FLAGS = 3, 7, 8, 9, 10, 11
PRIM_ID, GEOM_ID, INST_ID = 17, 18, 19
RAYHIT_WORDS = 32  # 128 bytes: room for the largest RTCRayHit Embree 4 builds


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
                ("rtcReleaseGeometry", None, [vp])):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = res, args
        _LIB = lib
    return _LIB


class DirectScene:
    """One triangle mesh in an Embree scene of its own (robust mode), for compiled kernels:
    :attr:`intersect` (``rtcIntersect1``'s address) and :attr:`handle` (the ``RTCScene``)
    go to :func:`cast_rays` or :func:`intersect1`. Released with the object."""

    def __init__(self, vertices: NDArray[np.floating], faces: NDArray[np.integer]) -> None:
        lib = _lib()
        v = np.ascontiguousarray(vertices, np.float32)
        f = np.ascontiguousarray(faces, np.uint32)
        self._lib = lib
        self._device = lib.rtcNewDevice(None)
        if not self._device:
            raise OSError("rtcNewDevice failed")
        self._scene = lib.rtcNewScene(self._device)
        lib.rtcSetSceneFlags(self._scene, SCENE_FLAG_ROBUST)
        geom = lib.rtcNewGeometry(self._device, GEOMETRY_TYPE_TRIANGLE)
        for kind, fmt, arr in ((BUFFER_TYPE_VERTEX, FORMAT_FLOAT3, v),
                               (BUFFER_TYPE_INDEX, FORMAT_UINT3, f)):
            dst = lib.rtcSetNewGeometryBuffer(geom, kind, 0, fmt, 12, len(arr))
            if dst and arr.nbytes:
                ctypes.memmove(dst, arr.ctypes.data, arr.nbytes)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(self._scene, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self._scene)
        err = lib.rtcGetDeviceError(self._device)
        if err:
            raise OSError(f"Embree could not build the scene (RTCError {err})")
        self.handle: int = int(self._scene)
        self.intersect: int = int(ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value or 0)

    def __del__(self) -> None:
        lib = getattr(self, "_lib", None)
        if lib is not None:
            if getattr(self, "_scene", None):
                lib.rtcReleaseScene(self._scene)
            if getattr(self, "_device", None):
                lib.rtcReleaseDevice(self._device)

    def cast(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """Hit distance (inf on a miss) and triangle id (-1) of (N, 3) float32 rays, on the
        calling thread without the GIL."""
        o = np.ascontiguousarray(origins, np.float32)
        d = np.ascontiguousarray(directions, np.float32)
        t = np.empty(len(o), np.float32)
        prim = np.empty(len(o), np.int32)
        cast_rays(self.intersect, self.handle, o, d, t, prim)
        return t, prim


def direct_scene(vertices: NDArray[np.floating], faces: NDArray[np.integer]
                 ) -> DirectScene | None:
    """A :class:`DirectScene`, or None where compiled kernels are off or the library cannot
    be had (callers fall back to embreex)."""
    if not jit_enabled():
        return None
    try:
        return DirectScene(vertices, faces)
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
    """A 64-byte aligned RTCRayHit: its float32 and uint32 words, and its address."""
    raw = np.empty(RAYHIT_WORDS + 16, np.float32)
    skip = ((-raw.ctypes.data) % 64) // 4
    f = raw[skip:skip + RAYHIT_WORDS]
    return f, f.view(np.uint32), f.ctypes.data


@numba.njit(cache=True, nogil=True, inline="always")
def intersect1(fn: int, scene: int, rf: Any, ru: Any, addr: int, ox: float, oy: float,
               oz: float, dx: float, dy: float, dz: float) -> tuple[float, int]:
    """One ray through ``rtcIntersect1`` (``rf``/``ru``/``addr`` from :func:`new_rayhit`):
    its hit distance (inf on a miss) and triangle id (-1)."""
    rf[0], rf[1], rf[2], rf[TNEAR] = ox, oy, oz, 0.0
    rf[4], rf[5], rf[6], rf[TIME] = dx, dy, dz, 0.0
    rf[TFAR] = np.inf
    ru[MASK], ru[RAY_ID], ru[FLAGS] = INVALID_ID, 0, 0
    ru[PRIM_ID], ru[GEOM_ID], ru[INST_ID] = INVALID_ID, INVALID_ID, INVALID_ID
    _call_c(fn, scene, addr)  # type: ignore[call-arg]  # numba supplies typingctx
    return rf[TFAR], (np.int32(ru[PRIM_ID]) if ru[GEOM_ID] != INVALID_ID else np.int32(-1))


@_njit
def cast_rays(fn: int, scene: int, o: Any, d: Any, t: Any, prim: Any) -> None:
    """(N, 3) float32 rays into ``t`` (N,) float32 and ``prim`` (N,) int32."""
    rf, ru, addr = new_rayhit()
    for i in range(o.shape[0]):
        t[i], prim[i] = intersect1(fn, scene, rf, ru, addr, o[i, 0], o[i, 1], o[i, 2],
                                   d[i, 0], d[i, 1], d[i, 2])
