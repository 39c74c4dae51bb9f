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

from tcf_hil.world.scene._backends import (
    AUTO,
    AUTO_ORDER,
    BACKEND_MODULES,
    BACKENDS,
    NO_COSINES,
    Caster,
    backend_unavailable,
    default_threads,
    make_caster,
    resolve_backend,
)
from tcf_hil.world.scene._scene import (
    FOLIAGE_AS,
    GEOMETRIES,
    JOINT_SPHERES,
    MATERIAL_BARK,
    MATERIAL_GROUND,
    Scene,
)

__all__ = ["AUTO", "AUTO_ORDER", "BACKENDS", "BACKEND_MODULES", "FOLIAGE_AS", "GEOMETRIES",
           "JOINT_SPHERES", "MATERIAL_BARK", "MATERIAL_GROUND", "NO_COSINES", "Caster", "Scene",
           "backend_unavailable", "default_threads", "make_caster", "resolve_backend"]
