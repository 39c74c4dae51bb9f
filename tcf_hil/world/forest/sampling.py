"""Surface sampling: the paper's "without LiDAR" point clouds.

Stem points are uniform by area on the exact stem surface (not the mesh): the axial position
is drawn with density proportional to r(s)·|C'(s)| (the lateral area element), the angle
uniformly; points that fall under the terrain (the uphill side of a base on a slope) are
redrawn. Terrain points are uniform over the plot at their exact height.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from protocols.pcd import encode_pcd
from tcf_hil.world.forest.generate import Forest

FloatArray = NDArray[np.float64]
_STREAM_SAMPLE = 10
_GRID = 128


@dataclass(frozen=True)
class Cloud:
    """A point cloud in world coordinates (float64) with the stem id of every point (0 =
    terrain)."""

    xyz: FloatArray
    stem_id: NDArray[np.uint32]

    def __len__(self) -> int:
        return len(self.xyz)

    def to_pcd(self, *, float32: bool = False) -> bytes:
        """Binary PCD with fields x y z and stem_id (uint32).

        x y z are float64 by default: no loss at UTM-sized origins (CloudCompare, PCL and
        open3d's tensor reader ``open3d.t.io`` read them). ``float32=True`` writes float32 for
        readers that only take that (open3d's legacy ``open3d.io``); it costs precision far
        from the origin (0.5 m at northing 6.9e6).
        """
        xyz = self.xyz.astype(np.float32) if float32 else self.xyz
        return encode_pcd({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                           "stem_id": self.stem_id})


def _stem_points(forest: Forest, idx: NDArray[np.int64], rng: np.random.Generator) -> FloatArray:
    st = forest.stems
    n = len(st)
    # Inverse CDF of the area density on a per-stem grid; rows are searched together by
    # offsetting each row's normalised CDF by its row number.
    u = np.linspace(0.0, 1.0, _GRID)
    s_grid = u[None, :] * st.length[:, None]
    rows = np.repeat(np.arange(n), _GRID)
    dens = (st.radius(rows, s_grid.ravel()) * st.speed(rows, s_grid.ravel())).reshape(n, _GRID)
    cdf = np.concatenate([np.zeros((n, 1)), np.cumsum(0.5 * (dens[:, 1:] + dens[:, :-1]), 1)], 1)
    cdf /= cdf[:, -1:]
    flat = (cdf + np.arange(n)[:, None]).ravel()
    q = rng.uniform(0.0, 1.0, len(idx))
    k = np.clip(np.searchsorted(flat, q + idx, side="right") - 1, 0, n * _GRID - 2)
    k = np.minimum(k, idx * _GRID + _GRID - 2)
    c0, c1 = flat[k] - idx, flat[k + 1] - idx
    frac = np.where(c1 > c0, (q - c0) / np.where(c1 > c0, c1 - c0, 1.0), 0.0)
    j = k - idx * _GRID
    s = (u[j] + np.clip(frac, 0.0, 1.0) * (u[1] - u[0])) * st.length[idx]
    th = rng.uniform(0.0, 2.0 * math.pi, len(idx))
    e1, b = st.ring_frame(idx, s)
    r = st.radius(idx, s)
    return st.centre(idx, s) + r[:, None] * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * b)


def sample_surfaces(forest: Forest, points_per_stem: int | None = None,
                    terrain_density_per_m2: float | None = None,
                    seed: int | None = None) -> Cloud:
    """Sample the forest's stem surfaces and terrain.

    Args:
        forest: the generated forest.
        points_per_stem: default from the scenario (paper: 1000).
        terrain_density_per_m2: terrain points per m² of plot; default from the scenario.
        seed: sampling seed; default the forest's seed.
    """
    cfg = forest.scenario.sampling
    k = cfg.points_per_stem if points_per_stem is None else points_per_stem
    dens = cfg.terrain_density_per_m2 if terrain_density_per_m2 is None else terrain_density_per_m2
    rng = np.random.default_rng([forest.seed if seed is None else seed, _STREAM_SAMPLE])
    n = len(forest.stems)
    parts, ids = [], []
    if n and k:
        todo = np.repeat(np.arange(n), k)
        pts = np.empty((len(todo), 3))
        slots = np.arange(len(todo))
        for _ in range(50):
            p = _stem_points(forest, todo, rng)
            ok = p[:, 2] >= forest.terrain.height(p[:, 0], p[:, 1]) - 1e-9
            pts[slots[ok]] = p[ok]
            slots, todo = slots[~ok], todo[~ok]
            if len(slots) == 0:
                break
        keep = np.ones(len(pts), dtype=bool)
        keep[slots] = False  # pathological slopes: a few points fewer rather than buried ones
        parts.append(pts[keep])
        ids.append((np.repeat(np.arange(n), k) + 1)[keep].astype(np.uint32))
    w, h = forest.scenario.plot.size_m
    m = round(dens * w * h)
    if m:
        xy = rng.uniform((-w / 2, -h / 2), (w / 2, h / 2), size=(m, 2))
        parts.append(np.column_stack([xy, forest.terrain.height(xy[:, 0], xy[:, 1])]))
        ids.append(np.zeros(m, dtype=np.uint32))
    if not parts:
        return Cloud(np.zeros((0, 3)), np.zeros(0, dtype=np.uint32))
    xyz = np.vstack(parts) + forest.origin
    return Cloud(xyz, np.concatenate(ids))
