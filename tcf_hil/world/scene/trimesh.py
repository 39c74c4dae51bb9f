"""The ``trimesh`` ray backend: trimesh's ray-triangle tests in numpy, for where neither
Embree nor open3d can be had."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from emulators.embree import DirectScene

FloatArray = NDArray[np.float64]


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
