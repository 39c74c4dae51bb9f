"""Meshes from a geometric tolerance: stems as closed tubes, terrain as a grid.

Stem tessellation splits the tolerance between the two directions, so their sum is bounded:
the polygon inscribed in a circle of radius r with n sides has a chord error (sagitta) of
r(1 - cos(pi/n)); n is the smallest count that keeps it within 3/4 of the tolerance at the
stem's largest radius. Rings are spaced so that the straight segments between them stay within
1/4 of it from the curved, tapered surface, (|C''| + |r''|) * ds² / 8, and never more than
``max_ring_step_m`` apart. Points of the mesh are then within the tolerance of the true
surface: inside it on a straight stretch, possibly outside on the inner side of a bend.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
from numpy.typing import NDArray

from tcf_hil.forest.stems import StemSet
from tcf_hil.forest.terrain import Terrain

FloatArray = NDArray[np.float64]


def sides_for(radius_m: float, tolerance_m: float, minimum: int = 6) -> int:
    """Polygon sides so that the inscribed polygon's chord error stays within tolerance."""
    if radius_m <= tolerance_m:
        return minimum
    return max(minimum, math.ceil(math.pi / math.acos(1.0 - tolerance_m / radius_m)))


def ring_positions(stems: StemSet, i: int, tolerance_m: float,
                   max_ring_step_m: float = 2.0, probe_step_m: float = 0.05) -> FloatArray:
    """Axial positions of the rings of stem ``i`` from ``-below`` to the top."""
    L = float(stems.length[i])
    lo = -float(stems.below[i])
    probe = np.arange(lo, L, probe_step_m)
    idx = np.full(len(probe), i)
    bend = stems.curvature_bound(idx, probe) + stems.radius_d2(idx, probe)
    step = np.minimum(max_ring_step_m, np.sqrt(8.0 * tolerance_m / np.maximum(bend, 1e-12)))
    # Ring density 1/step integrated along s; a ring at every whole unit.
    density = np.concatenate([[0.0], np.cumsum(probe_step_m / step)])
    grid = np.concatenate([probe, [L]])
    count = max(1, math.ceil(density[-1]))
    targets = np.linspace(0.0, density[-1], count + 1)
    s = np.interp(targets, density, grid)
    s[0], s[-1] = lo, L
    # Keep a ring at the base (s = 0), where the stem meets the ground.
    return np.unique(np.concatenate([s, [0.0]]))


_RADIAL_SHARE = 0.75


def _tube(stems: StemSet, i: int, tolerance_m: float) -> tuple[FloatArray, NDArray[np.int64]]:
    s = ring_positions(stems, i, (1.0 - _RADIAL_SHARE) * tolerance_m)
    idx = np.full(len(s), i)
    n = sides_for(float(stems.radius(idx[:1], s[:1])[0]), _RADIAL_SHARE * tolerance_m)
    c = stems.centre(idx, s)
    t = stems.tangent(idx, s)
    b = np.broadcast_to(stems.binormal[i], t.shape)
    u = np.cross(b, t)
    r = stems.radius(idx, s)
    th = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    ring = (np.cos(th)[None, :, None] * u[:, None, :] + np.sin(th)[None, :, None] * b[:, None, :])
    verts = (c[:, None, :] + r[:, None, None] * ring).reshape(-1, 3)
    m = len(s)
    k = np.arange(m - 1)[:, None] * n
    j = np.arange(n)[None, :]
    a0, a1 = k + j, k + (j + 1) % n
    b0, b1 = a0 + n, a1 + n
    side = np.concatenate([np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)],
                          axis=1).reshape(-1, 3)
    bottom_c, top_c = m * n, m * n + 1
    jj = np.arange(n)
    bottom = np.stack([np.full(n, bottom_c), (jj + 1) % n, jj], -1)
    top = np.stack([np.full(n, top_c), (m - 1) * n + jj, (m - 1) * n + (jj + 1) % n], -1)
    verts = np.vstack([verts, c[0], c[-1]])
    return verts, np.vstack([side, bottom, top]).astype(np.int64)


def stem_mesh(stems: StemSet, tolerance_m: float,
              origin: FloatArray | None = None) -> trimesh.Trimesh:
    """All stems as one mesh; face attribute ``stem_id`` (1-based) tells which stem a face is.

    Args:
        stems: the forest's stems (local coordinates).
        tolerance_m: maximum chord error.
        origin: added to every vertex (world = local + origin), float64.
    """
    verts, faces, ids = [], [], []
    offset = 0
    for i in range(len(stems)):
        v, f = _tube(stems, i, tolerance_m)
        verts.append(v)
        faces.append(f + offset)
        ids.append(np.full(len(f), i + 1, dtype=np.int32))
        offset += len(v)
    if not verts:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    vv = np.vstack(verts)
    if origin is not None:
        vv = vv + origin
    mesh = trimesh.Trimesh(vv, np.vstack(faces), process=False)
    mesh.face_attributes["stem_id"] = np.concatenate(ids)
    return mesh


def terrain_mesh(terrain: Terrain, bounds: tuple[float, float, float, float],
                 tolerance_m: float, origin: FloatArray | None = None) -> trimesh.Trimesh:
    """The terrain over ``bounds`` as a regular triangulated grid (float64 vertices)."""
    xs, ys, z = terrain.grid(bounds, tolerance_m)
    nx, ny = len(xs), len(ys)
    X, Y = np.meshgrid(xs, ys)
    verts = np.column_stack([X.ravel(), Y.ravel(), z.ravel()])
    if origin is not None:
        verts = verts + origin
    k = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([k, k + 1, k + nx + 1], -1),
                            np.stack([k, k + nx + 1, k + nx], -1)])
    return trimesh.Trimesh(verts, faces, process=False)
