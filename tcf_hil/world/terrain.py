"""Terrain: flat, or rolling as a sum of random plane waves over several octaves.

The height at any (x, y) is a closed formula (written into the ground truth, so any consumer
can evaluate it without our code)::

    z(x, y) = elevation + gx * x + gy * y + sum_i a_i * cos(kx_i * x + ky_i * y + phase_i)

in local plot coordinates (metres; world = local + scenario origin). Each octave halves the
wavelength and multiplies the amplitude by the persistence, like Blender's Clouds/Musgrave
textures the paper displaced its plane with; the sum is smooth (C-infinity), so slopes and
curvatures are exact too. The plane term (gx, gy) tilts any terrain into a hillside
(``terrain.slope_deg``): a hard case for ground filters and for pitch and roll.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil.scenario import TerrainConfig

FloatArray = NDArray[np.float64]

_CHUNK = 1 << 18


EXACT_GRID_VERTICES = 2_000_000
"""Up to this many vertices :meth:`Terrain.grid` evaluates :meth:`Terrain.height` at each
(the paper's forests have 0.1-0.2 M: their terrain keeps its bytes); above it, the lattice
by matrix products (:meth:`Terrain.lattice_height`), tens of times faster."""


@dataclass(frozen=True)
class Terrain:
    """A terrain heightfield.

    Attributes:
        elevation_m: mean height.
        waves: (n, 4) float64 rows of (kx rad/m, ky rad/m, amplitude m, phase rad); empty = flat.
        tilt: (gx, gy), the plane's constant slope dz/dx and dz/dy.
    """

    elevation_m: float
    waves: FloatArray
    tilt: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def flat(cls, elevation_m: float = 0.0) -> Terrain:
        return cls(float(elevation_m), np.zeros((0, 4)))

    @classmethod
    def generate(cls, cfg: TerrainConfig, rng: np.random.Generator) -> Terrain:
        """Draw a terrain from its configuration (flat ignores the generator)."""
        az = math.radians(cfg.uphill_azimuth_deg)
        g = math.tan(math.radians(cfg.slope_deg))
        tilt = (g * math.sin(az), g * math.cos(az)) if cfg.slope_deg else (0.0, 0.0)
        if cfg.kind == "flat" or cfg.amplitude_m == 0.0:
            return cls(float(cfg.elevation_m), cls._rough(cfg, rng, np.zeros((0, 4))), tilt)
        rows = []
        for octave in range(cfg.octaves):
            lam = cfg.wavelength_m / 2.0**octave
            weight = cfg.persistence**octave
            for _ in range(cfg.waves_per_octave):
                wl = lam * rng.uniform(0.8, 1.25)
                ang = rng.uniform(0.0, 2.0 * math.pi)
                k = 2.0 * math.pi / wl
                rows.append((k * math.cos(ang), k * math.sin(ang), weight,
                             rng.uniform(0.0, 2.0 * math.pi)))
        waves = np.array(rows, dtype=np.float64)
        # Normalise so that the RMS height is amplitude/sqrt(2), as for one cosine.
        waves[:, 2] *= cfg.amplitude_m / math.sqrt(float(np.sum(waves[:, 2] ** 2)))
        return cls(float(cfg.elevation_m), cls._rough(cfg, rng, waves), tilt)

    @staticmethod
    def _rough(cfg: TerrainConfig, rng: np.random.Generator, waves: FloatArray) -> FloatArray:
        """``waves`` and the micro-relief's (``roughness_m`` > 0): 16 plane waves of
        0.7-1.4 times ``roughness_wavelength_m``, scaled to that RMS height. Drawn after the
        terrain's own, so a terrain without micro-relief is drawn as before."""
        if cfg.roughness_m <= 0.0:
            return waves
        rows = []
        for _ in range(16):
            k = 2.0 * math.pi / (cfg.roughness_wavelength_m * rng.uniform(0.7, 1.4))
            ang = rng.uniform(0.0, 2.0 * math.pi)
            rows.append((k * math.cos(ang), k * math.sin(ang), 1.0,
                         rng.uniform(0.0, 2.0 * math.pi)))
        rough = np.array(rows, dtype=np.float64)
        # the RMS of a sum of cosines is sqrt(sum a^2 / 2)
        rough[:, 2] *= cfg.roughness_m * math.sqrt(2.0 / len(rough))
        return np.vstack([waves, rough])

    @property
    def is_flat(self) -> bool:
        """Level everywhere (no waves, no tilt)."""
        return len(self.waves) == 0 and self.tilt == (0.0, 0.0)

    def _plane(self, x: FloatArray, y: FloatArray) -> Any:
        gx, gy = self.tilt
        return self.elevation_m + (gx * x + gy * y if (gx or gy) else 0.0)

    def height(self, x: Any, y: Any, *, pointwise: bool = False) -> FloatArray:
        """Ground height at local (x, y); arrays broadcast, float64 throughout.

        ``pointwise``: each point's waves summed on their own (one dot product a point, as
        for a point asked alone), so a point's height has the same bits whatever other points
        come with it; the default sums a chunk of points in one matrix product, whose
        rounding may differ in the last bit."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape)
        xf = np.broadcast_to(x, shape).ravel()
        yf = np.broadcast_to(y, shape).ravel()
        out = np.empty(xf.shape)
        out[:] = self._plane(xf, yf)
        if not len(self.waves):
            return out.reshape(shape)
        kx, ky, a, ph = self.waves.T
        for i in range(0, len(xf), _CHUNK):
            arg = np.multiply.outer(xf[i:i + _CHUNK], kx) + np.multiply.outer(yf[i:i + _CHUNK], ky)
            arg += ph
            if pointwise:
                out[i:i + _CHUNK] += np.matmul(np.cos(arg)[:, None, :], a)[:, 0]
            else:
                out[i:i + _CHUNK] += np.cos(arg) @ a
        return out.reshape(shape)

    def gradient(self, x: Any, y: Any) -> tuple[FloatArray, FloatArray]:
        """(dz/dx, dz/dy) at local (x, y)."""
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        y = np.atleast_1d(np.asarray(y, dtype=np.float64))
        gx, gy = self.tilt
        if not len(self.waves):
            z = np.zeros(np.broadcast_shapes(x.shape, y.shape))
            return z + gx, z + gy
        kx, ky, a, ph = self.waves.T
        s = -np.sin(np.multiply.outer(x, kx) + np.multiply.outer(y, ky) + ph)
        return s @ (a * kx) + gx, s @ (a * ky) + gy

    def max_curvature(self) -> float:
        """An upper bound of |second derivative| in any direction (1/m); a plane has none."""
        if not len(self.waves):
            return 0.0
        k2 = self.waves[:, 0] ** 2 + self.waves[:, 1] ** 2
        return float(np.sum(np.abs(self.waves[:, 2]) * k2))

    def grid_spacing(self, tolerance_m: float, max_spacing_m: float = 25.0) -> float:
        """Grid spacing whose linear interpolation stays within ``tolerance_m`` of the surface."""
        kappa = self.max_curvature()
        if kappa == 0.0:
            return max_spacing_m
        # Triangle interpolation error <= h^2 * kappa / 8 along an edge; diagonals are sqrt(2)h.
        return min(max_spacing_m, math.sqrt(8.0 * tolerance_m / kappa) / math.sqrt(2.0))

    def grid(self, bounds: tuple[float, float, float, float], tolerance_m: float,
             max_vertices: int = 16_000_000, *, coarsen: bool = False
             ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Vertex grid (xs, ys, z[ny, nx]) over ``bounds`` (xmin, ymin, xmax, ymax).

        Raises:
            ValueError: when the tolerance needs more than ``max_vertices`` (unless
                ``coarsen``, for pictures, where the grid is thinned instead).
        """
        x0, y0, x1, y1 = bounds
        h = self.grid_spacing(tolerance_m)
        nx = max(2, math.ceil((x1 - x0) / h) + 1)
        ny = max(2, math.ceil((y1 - y0) / h) + 1)
        if nx * ny > max_vertices:
            if not coarsen:
                need = tolerance_m * nx * ny / max_vertices
                raise ValueError(f"a {tolerance_m * 1000:g} mm terrain tolerance needs "
                                 f"{nx * ny} vertices over this area (at most {max_vertices});"
                                 f" use {need * 1000:.3g} mm or more")
            scale = math.sqrt(nx * ny / max_vertices)
            nx, ny = max(2, int(nx / scale)), max(2, int(ny / scale))
        xs = np.linspace(x0, x1, nx)
        ys = np.linspace(y0, y1, ny)
        if nx * ny <= EXACT_GRID_VERTICES:  # the paper's forests' terrain, bit for bit
            return xs, ys, self.height(xs[None, :], ys[:, None])
        return xs, ys, self.lattice_height(xs, ys)

    def lattice_height(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """:meth:`height` over the lattice ``xs`` by ``ys`` (z[ny, nx]), wave by wave as
        cos(kx x + ky y + phase) = cos(kx x) cos(ky y + phase) - sin(kx x) sin(ky y +
        phase): two matrix products of (ny, waves) by (waves, nx) instead of a cosine at
        every vertex and wave (a 50 ha stand's 13.5 M vertices times 40 waves took 20 s);
        the same heights to a few 1e-15 m (growing with the lattice's extent: the waves'
        phases are larger far out). :meth:`grid` takes it above
        :data:`EXACT_GRID_VERTICES`."""
        xs = np.asarray(xs, np.float64)
        ys = np.asarray(ys, np.float64)
        z = np.empty((len(ys), len(xs)))
        z[:] = self._plane(xs[None, :], ys[:, None])
        if not len(self.waves):
            return z
        kx, ky, a, ph = self.waves.T
        ax, ay = np.multiply.outer(kx, xs), np.multiply.outer(ky, ys) + ph[:, None]
        z += (np.cos(ay) * a[:, None]).T @ np.cos(ax) - (np.sin(ay) * a[:, None]).T @ np.sin(ax)
        return z

    def to_doc(self, origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, Any]:
        """The terrain as ground-truth JSON: enough to evaluate the height anywhere."""
        return {
            "kind": "flat" if self.is_flat else "waves",
            "formula": "z = origin[2] + elevation_m + tilt[0] * (x - origin[0]) + tilt[1] * "
                       "(y - origin[1]) + sum(a * cos(kx * (x - origin[0]) + ky * (y - "
                       "origin[1]) + phase) for kx, ky, a, phase in waves)",
            "origin": [float(v) for v in origin_m],
            "elevation_m": self.elevation_m,
            "tilt": [float(v) for v in self.tilt],
            "waves": [[float(v) for v in row] for row in self.waves],
        }

    @classmethod
    def from_doc(cls, doc: dict[str, Any]) -> Terrain:
        waves = np.asarray(doc.get("waves", []), dtype=np.float64).reshape(-1, 4)
        gx, gy = (float(v) for v in doc.get("tilt", (0.0, 0.0)))
        return cls(float(doc["elevation_m"]), waves, (gx, gy))
