"""Stem base placement: even (grid with jitter), uneven (random with a minimum spacing) and
clustered (a Matérn cluster process with a minimum spacing).

Positions are drawn in a rectangle from which the strip-road corridor along the sensor track
has been cut out: points are drawn in the "collapsed" rectangle and the part beyond the
corridor is shifted across it. The shift never shortens a distance, so a minimum spacing drawn
in the collapsed rectangle holds in the plot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tcf_hil.errors import ConfigError
from tcf_hil.scenario import Scenario

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Region:
    """Axis-aligned rectangle with corridors (strip roads) cut out across ``axis``."""

    lo: tuple[float, float]
    hi: tuple[float, float]
    axis: int = 0  # coordinate across the corridors (0: corridors run along y)
    cuts: tuple[tuple[float, float], ...] = ()  # (lo, hi) along ``axis``, sorted, disjoint

    @property
    def cut(self) -> float:
        return sum(max(0.0, b - a) for a, b in self.cuts)

    @property
    def size(self) -> tuple[float, float]:
        w = [self.hi[0] - self.lo[0], self.hi[1] - self.lo[1]]
        w[self.axis] -= self.cut
        return (w[0], w[1])

    def expand(self, pts: FloatArray) -> FloatArray:
        """Map points from the collapsed rectangle (origin at ``lo``) to plot coordinates:
        each corridor, from the lowest up, shifts what lies at or beyond it by its width."""
        out = pts + np.asarray(self.lo)
        a = self.axis
        for c_lo, c_hi in self.cuts:
            beyond = out[:, a] >= c_lo
            out[beyond, a] += c_hi - c_lo
        return out


def region_for(scn: Scenario) -> Region:
    """The placement region of a scenario: plot minus edge margin minus the corridors of
    its strip roads (the track's and ``distribution.strip_roads - 1`` more, each
    ``track.pass_offset_m`` further to the left)."""
    w, h = scn.plot.size_m
    m = scn.distribution.edge_margin_m
    lo, hi = (-w / 2 + m, -h / 2 + m), (w / 2 - m, h / 2 - m)
    c = scn.distribution.corridor_half_width_m
    t0, t1 = scn.track.start_m, scn.track.end_m
    if c <= 0:
        return Region(lo, hi)
    axis = 0 if t0[0] == t1[0] else 1  # validated: the track is parallel to an axis
    # left of start -> end: -x when driving +y, +y when driving +x
    d = (t1[1] - t0[1]) if axis == 0 else (t1[0] - t0[0])
    left = (-1.0 if d > 0 else 1.0) if axis == 0 else (1.0 if d > 0 else -1.0)
    cuts = []
    for k in range(scn.distribution.strip_roads):
        centre = t0[axis] + left * k * scn.track.pass_offset_m
        cut_lo, cut_hi = max(lo[axis], centre - c), min(hi[axis], centre + c)
        if cut_hi > cut_lo:
            cuts.append((cut_lo, cut_hi))
    cuts.sort()
    merged: list[tuple[float, float]] = []
    for a, b in cuts:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(b, merged[-1][1]))
        else:
            merged.append((a, b))
    if sum(b - a for a, b in merged) >= hi[axis] - lo[axis]:
        raise ConfigError("distribution.corridor_half_width_m", c,
                          "corridors narrower than the plot")
    return Region(lo, hi, axis, tuple(merged))


class _DartGrid:
    """Accepts points that keep a minimum distance to all accepted ones (background grid)."""

    def __init__(self, size: tuple[float, float], spacing: float) -> None:
        self.r2 = spacing * spacing
        self.cell = max(spacing / math.sqrt(2.0), 1e-9) if spacing > 0 else 1.0
        self.spacing = spacing
        self.grid: dict[tuple[int, int], tuple[float, float]] = {}
        self.points: list[tuple[float, float]] = []
        self.size = size

    def try_add(self, x: float, y: float) -> bool:
        if not (0.0 <= x <= self.size[0] and 0.0 <= y <= self.size[1]):
            return False
        if self.spacing > 0:
            ci, cj = int(x // self.cell), int(y // self.cell)
            g = self.grid
            for di in (-2, -1, 0, 1, 2):
                for dj in (-2, -1, 0, 1, 2):
                    q = g.get((ci + di, cj + dj))
                    if q is not None and (q[0] - x) ** 2 + (q[1] - y) ** 2 < self.r2:
                        return False
            g[(ci, cj)] = (x, y)
        self.points.append((x, y))
        return True


def _fail(scn: Scenario, n: int, placed: int) -> ConfigError:
    d = scn.distribution
    return ConfigError("distribution.min_spacing_m", d.min_spacing_m,
                       f"a spacing that fits {n} stems (only {placed} placed; lower "
                       "min_spacing_m or stems.count, or enlarge the plot/clusters)")


def place_even(n: int, size: tuple[float, float], jitter: float,
               rng: np.random.Generator) -> FloatArray:
    """A near-square grid over ``size`` with ``n`` cells kept (surplus cells dropped at random),
    each point jittered uniformly by up to ``jitter`` (kept inside the rectangle)."""
    if n == 0:
        return np.zeros((0, 2))
    w, h = size
    nx = max(1, round(math.sqrt(n * w / h)))
    ny = math.ceil(n / nx)
    gx = (np.arange(nx) + 0.5) * (w / nx)
    gy = (np.arange(ny) + 0.5) * (h / ny)
    pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    keep = np.sort(rng.choice(len(pts), size=n, replace=False))
    pts = pts[keep]
    j = min(jitter, 0.49 * w / nx, 0.49 * h / ny)
    pts = pts + rng.uniform(-j, j, size=pts.shape)
    return np.clip(pts, 0.0, [w, h])


def place_uneven(n: int, size: tuple[float, float], spacing: float,
                 rng: np.random.Generator, scn: Scenario) -> FloatArray:
    """Uniform random points, rejecting any closer than ``spacing`` to an accepted one."""
    dart = _DartGrid(size, spacing)
    attempts = 0
    limit = 50 * n + 1000
    while len(dart.points) < n and attempts < limit:
        cand = rng.uniform((0.0, 0.0), size, size=(1024, 2))
        for x, y in cand:
            attempts += 1
            if dart.try_add(float(x), float(y)) and len(dart.points) == n:
                break
    if len(dart.points) < n:
        raise _fail(scn, n, len(dart.points))
    return np.asarray(dart.points, dtype=np.float64).reshape(-1, 2)


def place_clustered(n: int, size: tuple[float, float], spacing: float, clusters: int,
                    radius: float, rng: np.random.Generator, scn: Scenario) -> FloatArray:
    """Matérn cluster process: parents uniform, children uniform in a disc around a parent
    chosen uniformly, children closer than ``spacing`` rejected."""
    k = clusters if clusters > 0 else max(1, math.ceil(n / 40))
    parents = rng.uniform((0.0, 0.0), size, size=(k, 2))
    dart = _DartGrid(size, spacing)
    attempts = 0
    limit = 200 * n + 1000
    while len(dart.points) < n and attempts < limit:
        which = rng.integers(0, k, size=1024)
        rr = radius * np.sqrt(rng.uniform(0.0, 1.0, size=1024))
        th = rng.uniform(0.0, 2.0 * math.pi, size=1024)
        cand = parents[which] + np.stack([rr * np.cos(th), rr * np.sin(th)], axis=1)
        for x, y in cand:
            attempts += 1
            if dart.try_add(float(x), float(y)) and len(dart.points) == n:
                break
    if len(dart.points) < n:
        raise _fail(scn, n, len(dart.points))
    return np.asarray(dart.points, dtype=np.float64).reshape(-1, 2)


def place_stems(scn: Scenario, rng: np.random.Generator) -> FloatArray:
    """Stem base positions (n, 2) in local plot coordinates."""
    n = scn.stems.count
    region = region_for(scn)
    size = region.size
    d = scn.distribution
    if n == 0:
        return np.zeros((0, 2))
    if d.kind == "even":
        pts = place_even(n, size, d.jitter_m, rng)
    elif d.kind == "uneven":
        pts = place_uneven(n, size, d.min_spacing_m, rng, scn)
    else:
        pts = place_clustered(n, size, d.min_spacing_m, d.clusters, d.cluster_radius_m, rng, scn)
    return region.expand(pts)
