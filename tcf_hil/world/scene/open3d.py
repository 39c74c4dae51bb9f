"""The ``open3d`` ray backend: open3d's ``RaycastingScene`` (the ``open3d`` extra)."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from emulators.embree import DirectScene

FloatArray = NDArray[np.float64]


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
