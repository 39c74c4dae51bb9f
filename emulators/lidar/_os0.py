"""OS0-64 emulation: every column is cast from the sensor pose at its own time stamp.

The scene and the trajectory are injected (``RayScene``, ``PoseSource``): the emulator knows
the sensor, not the forest. Coordinates are the scene's local frame (metres, float64); the
caller adds any geographic origin.
"""

from __future__ import annotations

import itertools
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from protocols.ouster import SensorMetadata, beam_rays

FloatArray = NDArray[np.float64]


class RayScene(Protocol):
    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.floating], NDArray[np.int32]]:
        """(distance along each unit ray, inf on a miss; stem id: 0 terrain, -1 nothing),
        for rays in float64 or float32 (what the emulator passes)."""
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
    """Produces staggered frames for a sensor described by ``meta``.

    A pose source with a ``sensor_pose_dense(t_ns)`` (the same poses for many close times,
    faster; e.g. :class:`tcf_hil.trajectory.Trajectory`) is asked for a frame's column poses
    through it. Rays are made in float32, as the casters take them. A frame is worked in
    chunks of columns, each turned into rays, cast and answered on its own, spread over
    ``threads`` threads (numpy and the casters release the GIL): the results do not depend
    on the split."""

    MIN_RAYS_PER_CHUNK = 8192

    def __init__(self, meta: SensorMetadata, scene: RayScene, poses: PoseSource,
                 model: ReturnModel | None = None, *, seed: int = 0,
                 start_ns: int = 1_000_000_000, threads: int | None = None) -> None:
        self.meta = meta
        self.scene = scene
        self.poses = poses
        self._pose_at = getattr(poses, "sensor_pose_dense", None) or poses.sensor_pose
        self.model = model or ReturnModel()
        self.rng = np.random.default_rng([seed, 0x0500])
        self.start_ns = start_ns
        o, d = beam_rays(meta)  # sensor frame, (H, W, 3)
        # Column-major copies: a column's rays are cast together (coherent for the caster)
        # and turned by that column's pose with one batched product.
        self._origins_wh = np.ascontiguousarray(o.transpose(1, 0, 2))
        self._directions_wh = np.ascontiguousarray(d.transpose(1, 0, 2))
        # float32, origins homogeneous: (o, 1) @ [R^T; p] turns and moves them in one product
        h, w = meta.pixels, meta.columns
        self._origins_h32 = np.ones((w, h, 4), np.float32)
        self._origins_h32[:, :, :3] = self._origins_wh
        self._directions_wh32 = self._directions_wh.astype(np.float32)
        self.period_ns = 1_000_000_000 // meta.frequency_hz
        self.n_m = meta.lidar_origin_to_beam_origin_mm / 1000.0
        self.quantum_mm = 8 if meta.profile == "RNG15_RFL8_NIR8" else 1
        self.profile_fields = set(meta.packet_format.field_names)
        # By return class (0 none, 1 terrain, 2 stem): reflectance, reach, encoded values.
        m = self.model
        refl = np.array([0.0, m.reflectance["ground"], m.reflectance["bark"]])
        self._refl = refl
        self._reach = [float(m.max_range_m * min(1.0, math.sqrt(r / m.reference_reflectance)))
                       for r in refl[1:]]
        self._reflectivity = np.round(refl * 100.0).astype(np.uint32)
        nir = np.minimum(m.ambient * np.array([0.05, refl[1], refl[2]]), 65535.0
                         ).astype(np.uint32)
        if meta.profile == "RNG15_RFL8_NIR8":
            nir = np.minimum(nir, 4080) // 16 * 16
        self._nir = nir
        self.threads = max(1, threads or (len(os.sched_getaffinity(0))
                                          if hasattr(os, "sched_getaffinity")
                                          else (os.cpu_count() or 1)))
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0

    def column_times(self, k: int) -> NDArray[np.int64]:
        w = self.meta.columns
        return (self.start_ns + k * self.period_ns
                + (np.arange(w, dtype=np.int64) * self.period_ns) // w)

    @staticmethod
    def _affine(pos: FloatArray, rot: FloatArray) -> NDArray[np.float32]:
        """(W, 4, 3) float32 [R^T; p]: a row vector (x, y, z, 1) times it is R x + p."""
        m = np.empty((len(pos), 4, 3), np.float32)
        m[:, :3] = rot.transpose(0, 2, 1)
        m[:, 3] = pos
        return m

    def _turn(self, aff: NDArray[np.float32], a: int, b: int, o: NDArray[np.float32],
              d: NDArray[np.float32]) -> None:
        """Columns a..b's rays into o[a:b] and d[a:b], (columns, H, 3) float32."""
        np.matmul(self._origins_h32[a:b], aff[a:b], out=o[a:b])
        np.matmul(self._directions_wh32[a:b], aff[a:b, :3], out=d[a:b])

    def rays(self, k: int, dtype: type[np.floating] = np.float64
             ) -> tuple[NDArray[np.floating], NDArray[np.floating], FloatArray, FloatArray]:
        """Frame k's rays in the scene, column-major: origins and unit directions
        (W*H, 3) in ``dtype`` (float32: the very rays :meth:`frame` casts), and the
        per-column sensor positions (W, 3) and rotations (W, 3, 3), float64."""
        pos, rot = self._pose_at(self.column_times(k))
        # Rays of column c are in the sensor frame of column c's pose.
        if dtype == np.float32:
            o32 = np.empty(self._directions_wh32.shape, np.float32)
            d32 = np.empty_like(o32)
            self._turn(self._affine(pos, rot), 0, len(pos), o32, d32)
            return o32.reshape(-1, 3), d32.reshape(-1, 3), pos, rot
        rt = rot.transpose(0, 2, 1)
        o = np.matmul(self._origins_wh, rt) + pos[:, None, :]
        d = np.matmul(self._directions_wh, rt)
        return o.reshape(-1, 3), d.reshape(-1, 3), pos, rot

    def _chunks(self) -> list[tuple[int, int]]:
        H, W = self.meta.pixels, self.meta.columns
        n = min(4 * self.threads, W * H // self.MIN_RAYS_PER_CHUNK) if self.threads > 1 else 1
        n = max(1, n)
        cuts = [(W * i) // n for i in range(n + 1)]
        return list(itertools.pairwise(cuts))

    def frame(self, k: int) -> FrameResult:
        m = self.model
        H, W = self.meta.pixels, self.meta.columns
        ts = self.column_times(k)
        pos, rot = self._pose_at(ts)
        aff = self._affine(pos, rot)
        noise = (self.rng.normal(0.0, m.noise_sigma_m, (H, W)).T if m.noise_sigma_m > 0
                 else None)
        signal = "SIGNAL" in self.profile_fields  # only what the profile carries
        dual = "RANGE2" in self.profile_fields
        o = np.empty((W, H, 3), np.float32)
        d = np.empty((W, H, 3), np.float32)
        # column-major (W, H) results; the (H, W) images are their transposed views
        out = {"RANGE": np.empty((W, H), np.uint32),
               "REFLECTIVITY": np.empty((W, H), np.uint32),
               "NEAR_IR": np.empty((W, H), np.uint32)}
        if signal:
            out["SIGNAL"] = np.empty((W, H), np.uint32)
        sid_out = np.empty((W, H), np.int32)
        t_all = np.empty((W, H)) if dual else None
        ok_all = np.empty((W, H), bool) if dual else None

        def work(a: int, b: int) -> None:
            self._turn(aff, a, b, o, d)
            t, sid = self.scene.cast(o[a:b].reshape(-1, 3), d[a:b].reshape(-1, 3))
            t = np.asarray(t).reshape(b - a, H)
            sid = np.asarray(sid).reshape(b - a, H)
            if noise is not None:
                t = t + noise[a:b]
            # the encoded range counts from the lidar axis (inf: no hit)
            rng_m = np.add(t, self.n_m, dtype=np.float64)
            bark = sid > 0
            ok = rng_m >= m.min_range_m
            if self._reach[0] == self._reach[1]:
                ok &= rng_m <= self._reach[0]
            else:
                ok &= rng_m <= np.where(bark, self._reach[1], self._reach[0])
            ok &= sid >= 0
            cls = ok.astype(np.uint8)  # 0 none, 1 terrain, 2 stem
            cls += ok & bark
            q = self.quantum_mm
            r = np.zeros((b - a, H))
            np.multiply(rng_m, 1000.0 / q if q != 1 else 1000.0, out=r, where=ok)
            np.rint(r, out=r)
            if q != 1:
                r *= q
            np.copyto(out["RANGE"][a:b], r, casting="unsafe")
            np.take(self._reflectivity, cls, out=out["REFLECTIVITY"][a:b])
            np.take(self._nir, cls, out=out["NEAR_IR"][a:b])
            if signal:
                # no return: reflectance 0 (and the range inf or out of reach), 0 photons
                r2 = np.maximum(rng_m, 0.5, out=r)
                r2 *= r2
                sig = np.take(self._refl, cls)
                sig *= m.signal_scale
                sig /= r2
                np.minimum(sig, 65535.0, out=sig)
                np.copyto(out["SIGNAL"][a:b], sig, casting="unsafe")
            np.copyto(sid_out[a:b], np.where(ok, sid, -1), casting="unsafe")
            if t_all is not None and ok_all is not None:
                t_all[a:b] = t
                ok_all[a:b] = ok

        chunks = self._chunks()
        if len(chunks) == 1:
            work(*chunks[0])
        else:
            if self._pool is None or self._pool_pid != os.getpid():  # threads die in a fork
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="os0")
                self._pool_pid = os.getpid()
            for job in [self._pool.submit(work, a, b) for a, b in chunks]:
                job.result()
        fields = {name: v.T for name, v in out.items()}
        sid2 = None
        if dual and t_all is not None and ok_all is not None:  # only what the profile carries
            sid2 = self._second_return(o.reshape(-1, 3), d.reshape(-1, 3), t_all.T, ok_all.T,
                                       fields)
        return FrameResult(k, ts.astype(np.uint64), fields, sid_out.T, sid2, pos, rot)

    def _second_return(self, o: NDArray[np.floating], d: NDArray[np.floating], t1: FloatArray,
                       ok1: NDArray[np.bool_], fields: dict[str, NDArray[np.uint32]]
                       ) -> NDArray[np.int32]:
        """Four sub-rays at the beam's divergence half-angle: the farthest surface they hit
        at least ``second_return_gap_m`` behind the first return is the second return (a
        beam that grazes a stem and lands on what is behind it). The SDK places it along
        the central ray, as for a real sensor."""
        m = self.model
        H, W = self.meta.pixels, self.meta.columns
        dd = d.reshape(-1, 3).astype(np.float64)
        e1 = np.cross(dd, np.array([0.0, 0.0, 1.0]))
        e1 /= np.maximum(np.linalg.norm(e1, axis=1), 1e-12)[:, None]
        e2 = np.cross(dd, e1)
        a = m.divergence_rad
        subs = [dd + s * a * e for e in (e1, e2) for s in (1.0, -1.0)]
        oo = np.tile(o.reshape(-1, 3).astype(np.float64), (4, 1))
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
