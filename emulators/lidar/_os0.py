"""OS0-64 emulation: every column is cast from the sensor pose at its own time stamp.

The scene and the trajectory are injected (``RayScene``, ``PoseSource``): the emulator knows
the sensor, not the forest. Coordinates are the scene's local frame (metres, float64); the
caller adds any geographic origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from protocols.ouster import SensorMetadata, beam_rays

FloatArray = NDArray[np.float64]


class RayScene(Protocol):
    def cast(self, origins: FloatArray, directions: FloatArray
             ) -> tuple[FloatArray, NDArray[np.int32]]:
        """(distance along each unit ray, inf on a miss; stem id: 0 terrain, -1 nothing)."""
        ...


class PoseSource(Protocol):
    def sensor_pose(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Sensor frame in the scene at times t: (positions (n, 3), rotations (n, 3, 3))."""
        ...


@dataclass(frozen=True)
class ReturnModel:
    """How surfaces answer.

    Attributes:
        noise_sigma_m: Gaussian range noise (0: exact).
        max_range_m: range cap for a target of ``reference_reflectance`` or brighter; darker
            targets reach ``max_range_m * sqrt(reflectance / reference_reflectance)``.
        min_range_m: returns nearer than this (from the lidar axis) are dropped.
        reflectance: by stem id class: ``ground`` (id 0) and ``bark`` (ids > 0), 0..1.
        signal_scale: photons at 1 m from a reflectance-1 target hit square on.
        ambient: near-IR counts of a reflectance-1 surface in daylight.
    """

    noise_sigma_m: float = 0.0
    max_range_m: float = 50.0
    reference_reflectance: float = 0.1
    min_range_m: float = 0.3
    reflectance: dict[str, float] = field(default_factory=lambda: {"ground": 0.25,
                                                                   "bark": 0.45})
    signal_scale: float = 20000.0
    ambient: float = 1200.0
    divergence_rad: float = 0.0016  # half-angle of the beam, for the DUAL second return
    second_return_gap_m: float = 0.5  # a second return lies at least this far behind


@dataclass(frozen=True)
class FrameResult:
    frame_index: int
    timestamps_ns: NDArray[np.uint64]  # (W,)
    fields: dict[str, NDArray[np.uint32]]  # staggered (H, W)
    stem_id: NDArray[np.int32]  # (H, W): -1 no return, 0 terrain, else the stem
    stem_id2: NDArray[np.int32] | None  # the DUAL profile's second return, else None
    positions: FloatArray  # (W, 3) sensor position per column
    rotations: FloatArray  # (W, 3, 3)


class Os0Emulator:
    """Produces staggered frames for a sensor described by ``meta``."""

    def __init__(self, meta: SensorMetadata, scene: RayScene, poses: PoseSource,
                 model: ReturnModel | None = None, *, seed: int = 0,
                 start_ns: int = 1_000_000_000) -> None:
        self.meta = meta
        self.scene = scene
        self.poses = poses
        self.model = model or ReturnModel()
        self.rng = np.random.default_rng([seed, 0x0500])
        self.start_ns = start_ns
        o, d = beam_rays(meta)  # sensor frame, (H, W, 3)
        # Column-major copies: a column's rays are cast together (coherent for the caster)
        # and turned by that column's pose with one batched 3x3 product.
        self._origins_wh = np.ascontiguousarray(o.transpose(1, 0, 2))
        self._directions_wh = np.ascontiguousarray(d.transpose(1, 0, 2))
        self.period_ns = 1_000_000_000 // meta.frequency_hz
        self.n_m = meta.lidar_origin_to_beam_origin_mm / 1000.0
        self.quantum_mm = 8 if meta.profile == "RNG15_RFL8_NIR8" else 1
        self.profile_fields = set(meta.packet_format.field_names)

    def column_times(self, k: int) -> NDArray[np.int64]:
        w = self.meta.columns
        return (self.start_ns + k * self.period_ns
                + (np.arange(w, dtype=np.int64) * self.period_ns) // w)

    def rays(self, k: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Frame k's rays in the scene, column-major: origins and unit directions
        (W*H, 3), and the per-column sensor positions (W, 3) and rotations (W, 3, 3)."""
        pos, rot = self.poses.sensor_pose(self.column_times(k))
        # Rays of column c are in the sensor frame of column c's pose.
        rt = rot.transpose(0, 2, 1)
        o = np.matmul(self._origins_wh, rt) + pos[:, None, :]
        d = np.matmul(self._directions_wh, rt)
        return o.reshape(-1, 3), d.reshape(-1, 3), pos, rot

    def frame(self, k: int) -> FrameResult:
        m = self.model
        H, W = self.meta.pixels, self.meta.columns
        ts = self.column_times(k)
        o, d, pos, rot = self.rays(k)
        t, sid = self.scene.cast(o, d)
        t = t.reshape(W, H).T
        sid = sid.reshape(W, H).T
        refl = np.where(sid > 0, m.reflectance["bark"], m.reflectance["ground"])
        if m.noise_sigma_m > 0:
            t = t + self.rng.normal(0.0, m.noise_sigma_m, t.shape)
        rng_m = t + self.n_m  # the encoded range counts from the lidar axis
        reach = m.max_range_m * np.minimum(1.0, np.sqrt(refl / m.reference_reflectance))
        ok = np.isfinite(t) & (sid >= 0) & (rng_m >= m.min_range_m) & (rng_m <= reach)
        q = self.quantum_mm
        rng_mm = np.where(ok, np.round(np.where(ok, rng_m, 0.0) * 1000.0 / q) * q, 0.0)
        nir = np.where(ok, m.ambient * refl, m.ambient * 0.05)
        fields = {
            "RANGE": rng_mm.astype(np.uint32),
            "REFLECTIVITY": np.where(ok, np.round(refl * 100.0), 0.0).astype(np.uint32),
            "NEAR_IR": np.minimum(nir, 65535.0).astype(np.uint32),
        }
        if "SIGNAL" in self.profile_fields:  # only what the profile carries
            r2 = np.maximum(np.where(ok, rng_m, 1.0), 0.5) ** 2
            fields["SIGNAL"] = np.where(ok, np.minimum(65535.0, m.signal_scale * refl / r2),
                                        0.0).astype(np.uint32)
        if self.meta.profile == "RNG15_RFL8_NIR8":
            fields["NEAR_IR"] = np.minimum(fields["NEAR_IR"], 4080) // 16 * 16
        sid = np.where(ok, sid, -1).astype(np.int32)
        sid2 = None
        if "RANGE2" in self.profile_fields:  # model only what the profile carries
            sid2 = self._second_return(o, d, t, ok, fields)
        return FrameResult(k, ts.astype(np.uint64), fields, sid, sid2, pos, rot)

    def _second_return(self, o: FloatArray, d: FloatArray, t1: FloatArray,
                       ok1: NDArray[np.bool_], fields: dict[str, NDArray[np.uint32]]
                       ) -> NDArray[np.int32]:
        """Four sub-rays at the beam's divergence half-angle: the farthest surface they hit
        at least ``second_return_gap_m`` behind the first return is the second return (a
        beam that grazes a stem and lands on what is behind it). The SDK places it along
        the central ray, as for a real sensor."""
        m = self.model
        H, W = self.meta.pixels, self.meta.columns
        dd = d.reshape(-1, 3)
        e1 = np.cross(dd, np.array([0.0, 0.0, 1.0]))
        e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-12)[:, None]
        e2 = np.cross(dd, e1)
        a = m.divergence_rad
        subs = [dd + s * a * e for e in (e1, e2) for s in (1.0, -1.0)]
        oo = np.tile(o.reshape(-1, 3), (4, 1))
        dirs = np.vstack(subs)
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        t, sid = self.scene.cast(oo, dirs)
        t = t.reshape(4, W, H).transpose(0, 2, 1)
        sid = sid.reshape(4, W, H).transpose(0, 2, 1)
        first = np.where(ok1, t1, np.inf)
        behind = np.isfinite(t) & (sid >= 0) & (t >= first[None] + m.second_return_gap_m)
        behind &= ok1[None]  # a second return needs a first one
        t2 = np.where(behind, t, -np.inf).max(axis=0)
        pick = np.argmax(np.where(behind, t, -np.inf), axis=0)
        s2 = np.take_along_axis(sid, pick[None], axis=0)[0]
        frac = behind.sum(axis=0) / 4.0
        refl = np.where(s2 > 0, m.reflectance["bark"], m.reflectance["ground"])
        rng_m = t2 + self.n_m
        reach = m.max_range_m * np.minimum(1.0, np.sqrt(refl / m.reference_reflectance))
        ok = np.isfinite(t2) & (rng_m <= reach)
        fields["RANGE2"] = np.where(ok, np.round(np.where(ok, rng_m, 0.0) * 1000.0), 0.0
                                    ).astype(np.uint32)
        fields["REFLECTIVITY2"] = np.where(ok, np.round(refl * 100.0), 0.0).astype(np.uint32)
        r2 = np.maximum(np.where(ok, rng_m, 1.0), 0.5) ** 2
        fields["SIGNAL2"] = np.where(ok, np.minimum(65535.0, m.signal_scale * refl * frac / r2),
                                     0.0).astype(np.uint32)
        return np.where(ok, s2, -1).astype(np.int32)
