"""The ray backends' registry: by name, imported lazily, as python-can keeps its interfaces
(one module each: :mod:`.embree`, :mod:`.open3d`, :mod:`.trimesh`); what every caster
offers (:class:`Caster`); ``auto``'s choice (:func:`resolve_backend`) and the factory
(:func:`make_caster`)."""

from __future__ import annotations

import importlib
import os
import platform
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from tcf_hil.errors import ConfigError

if TYPE_CHECKING:
    from emulators.embree import DirectScene

FloatArray = NDArray[np.float64]

BACKENDS: dict[str, tuple[str, str]] = {
    "embree": ("tcf_hil.world.scene.embree", "EmbreeCaster"),
    "open3d": ("tcf_hil.world.scene.open3d", "Open3dCaster"),
    "trimesh": ("tcf_hil.world.scene.trimesh", "TrimeshCaster"),
}
AUTO = "auto"
AUTO_ORDER = ("embree", "open3d", "trimesh")
"""What ``auto`` takes: the first of these whose modules (:data:`BACKEND_MODULES`) import."""
BACKEND_MODULES: dict[str, tuple[str, ...]] = {
    "embree": ("embreex", "embreex.rtcore_scene", "embreex.mesh_construction"),
    "open3d": ("open3d",),
    "trimesh": ("trimesh", "trimesh.ray.ray_triangle"),
}
NO_COSINES = np.zeros(0, np.float32)
"""The cosines a caster without them hands on (empty)."""


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
