"""OS0-64 emulation: every column is cast from the sensor pose at its own time stamp.

The scene and the trajectory are injected (``RayScene``, ``PoseSource``): the emulator knows
the sensor, not the forest. Coordinates are the scene's local frame (metres, float64); the
caller adds any geographic origin.

What the emulator can use beyond a cast and a pose is declared as protocols, not probed
for: a scene that is a :class:`FastRayScene` (every member; each has a value for "not
here") is cast through as it declares, any other :class:`RayScene` as a plain cast
(:func:`fast_scene`); a pose source that is a :class:`DensePoseSource` gives its poses in
pieces for many frames at once, any other :class:`PoseSource` one frame at a time.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from emulators.jit import jit_enabled
from emulators.lidar._kernel import answer_kernel, frames_kernel, rays_kernel
from emulators.lidar._physics import Physics, SensorModel, Surfaces
from protocols.ouster import (
    EMULATED_PROFILES,
    Field,
    PacketFormat,
    SensorMetadata,
    beam_rays,
    encode_lidar_columns,
    encode_pixel_fields,
)

FloatArray = NDArray[np.float64]


DirectCast = tuple[int, tuple[Any, ...], NDArray[np.int32]]
"""An Embree scene the emulator's compiled kernel casts through itself
(:mod:`emulators.embree`): rtcIntersect1's address, what a ray is cast through
(:attr:`emulators.embree.DirectScene.handles`: its scenes in the order a ray enters them,
the crowns' first), and the stem id by primitive: the triangles', the other primitives' last to
first, then -1 (the miss), so that a miss (-1) and primitive j (-2 - j) index it from the
end."""


def _fused_kernel() -> Callable[..., None] | None:
    """:func:`emulators.lidar._fused.cast_answer_blocks` (blocks of columns encoded, their
    rays made, cast through Embree and answered in one call), or None where compiled kernels
    are off."""
    if not jit_enabled():
        return None
    from emulators.lidar._fused import cast_answer_blocks

    kernel: Callable[..., None] = cast_answer_blocks
    return kernel


class RayScene(Protocol):
    """The least a scene offers: a cast."""

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.floating], NDArray[np.int32]]:
        """(distance along each unit ray, inf on a miss; stem id: 0 terrain, -1 nothing),
        for rays in float64 or float32 (what the emulator passes)."""
        ...


@runtime_checkable
class FastRayScene(RayScene, Protocol):
    """A scene that declares the emulator's faster ways to cast through it, each member
    with an answer for "not here" (as :class:`tcf_hil.world.scene.Scene` does)."""

    @property
    def threads_itself(self) -> bool:
        """True where a cast spreads over the CPUs by itself (the emulator then casts from
        one thread), else False (it spreads its column chunks over its own threads)."""
        ...

    def cast32(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        """:meth:`cast` for float32 rays with float32 distances, on the calling thread
        unless ``threads_itself`` (else the plain cast)."""
        ...

    def direct(self) -> DirectCast | None:
        """The Embree scene the compiled kernel casts through itself, or None."""
        ...

    def surfaces(self) -> Surfaces | None:
        """What the triangles a cast hits are (stem, normal, material) and casts that answer
        triangles, for the physical sensor model; or None (then the hits are stem ids, seen
        square on, bark or ground)."""
        ...


class _CastOnly:
    """A :class:`RayScene` that declares nothing more, as a :class:`FastRayScene`: cast
    from the emulator's threads, no Embree scene of its own."""

    threads_itself = False

    def __init__(self, scene: RayScene) -> None:
        self._scene = scene

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.floating], NDArray[np.int32]]:
        return self._scene.cast(origins, directions)

    def cast32(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        t, sid = self._scene.cast(origins, directions)
        return np.asarray(t, np.float32), np.asarray(sid, np.int32)

    def direct(self) -> DirectCast | None:
        return None

    def surfaces(self) -> Surfaces | None:
        return None


def fast_scene(scene: RayScene) -> FastRayScene:
    """``scene`` where it is a :class:`FastRayScene` (it has every member), else the same
    casts with nothing more declared. Checked once, when an emulator is made."""
    return scene if isinstance(scene, FastRayScene) else _CastOnly(scene)


class PoseSource(Protocol):
    """The least a pose source offers: the sensor pose at any times."""

    def sensor_pose(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Sensor frame in the scene at times t: (positions (n, 3), rotations (n, 3, 3))."""
        ...


class PosePieces(Protocol):
    """A stretch of the sensor pose, cheap to evaluate (:meth:`DensePoseSource.dense_poses`)."""

    def at(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Positions (n, 3) and rotations (n, 3, 3) at times within the stretch."""
        ...


@runtime_checkable
class DensePoseSource(PoseSource, Protocol):
    """A pose source that also gives many close, ascending times' poses fast, from pieces
    it builds for a stretch of time (as :class:`tcf_hil.world.track.Trajectory` does): the
    emulator builds them for two seconds of frames at a time while frames are read in
    order."""

    def sensor_pose_dense(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """:meth:`sensor_pose` at a frame's column times, fast."""
        ...

    def dense_knot_ns(self) -> int:
        """The pieces' grid spacing, ns: a stretch starts and ends on it."""
        ...

    def dense_poses(self, lo_ns: int, hi_ns: int, knot_ns: int | None = None) -> PosePieces:
        """The pieces for times in [lo_ns, hi_ns)."""
        ...

    def dense_pieces(self, t_ns: NDArray[np.int64], knot_ns: int | None = None,
                     pieces: Any = None) -> PosePieces | None:
        """The pieces :meth:`sensor_pose_dense` evaluates at these times (``pieces`` where
        they cover them), or None where it takes the exact poses."""
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
    """One frame: its column times, the emulated returns and the poses they were cast from.

    ``packets`` holds the frame's lidar packets with every column encoded (the packet
    headers and CRCs are the caller's: :func:`protocols.ouster.finish_lidar_packets`, once it
    has chosen the frame_id). :attr:`fields`, the staggered (H, W) images of what the
    sensor measured, is read back from them when first asked for: the emulator writes only
    packets."""

    frame_index: int
    timestamps_ns: NDArray[np.uint64]  # (W,)
    stem_id: NDArray[np.int32]  # (H, W): -1 no return, 0 terrain, else the stem
    stem_id2: NDArray[np.int32] | None  # the DUAL profile's second return, else None
    positions: FloatArray  # (W, 3) sensor position per column
    rotations: FloatArray  # (W, 3, 3)
    packets: NDArray[np.uint8]  # (packets_per_frame, packet_bytes)
    packet_format: PacketFormat
    field_names: tuple[str, ...]  # the fields the emulator modelled

    @cached_property
    def fields(self) -> dict[str, NDArray[np.uint32]]:
        return self.packet_format.pixel_fields(self.packets, self.field_names)


class _Nothing:
    """A scene with nothing in it; with ``embree``, an Embree scene of one triangle far away
    that it hands over (``direct``), as :class:`tcf_hil.world.scene.Scene` does."""

    threads_itself = False

    def __init__(self, embree: bool = False) -> None:
        self._embree: Any = None
        if embree and jit_enabled():
            from emulators.embree import direct_scene

            far = np.array([[1e6, 0.0, 0.0], [1e6, 1.0, 0.0], [1e6, 0.0, 1.0]])
            self._embree = direct_scene(far, np.array([[0, 1, 2]]))

    def cast(self, origins: NDArray[np.floating], directions: NDArray[np.floating]
             ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        return np.full(len(origins), np.inf, np.float32), np.full(len(origins), -1, np.int32)

    def cast32(self, origins: NDArray[np.float32], directions: NDArray[np.float32]
               ) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
        return self.cast(origins, directions)

    def direct(self) -> DirectCast | None:
        e = self._embree
        return None if e is None else (e.intersect, e.handles, np.array([0, -1], np.int32))

    def surfaces(self) -> Surfaces | None:
        return None


class _Still:
    """A sensor that never moves."""

    def sensor_pose(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        return np.zeros((len(t_ns), 3)), np.tile(np.eye(3), (len(t_ns), 1, 1))


def warm_up(meta: SensorMetadata, model: ReturnModel | None = None,
            sensor: SensorModel | None = None) -> None:
    """Compile the emulator's kernels (numba; or load them from its on-disk cache) for this
    sensor and return model now, not in the first frame of a live stream (seconds, the first
    time on a machine): one frame of a still sensor in an empty scene, cast by the scene
    (open3d's way) and through a directly bound Embree scene (the fused kernel)."""
    for embree in (False, True):
        Os0Emulator(meta, _Nothing(embree), _Still(), model, threads=1,
                    sensor=sensor).frame(0)


def carried_range_m(fmt: PacketFormat) -> float:
    """The longest range a profile's RANGE field can carry, in metres."""
    f = fmt.profile.field("RANGE")
    most_mm = f.mask >> f.shift if f.shift >= 0 else f.mask << -f.shift
    return float(most_mm) / 1000.0


@dataclass(frozen=True)
class _FrameJob:
    """What a frame's column chunks share: the ray factors, the noise, and where they write."""

    mt: NDArray[np.float32]  # (3, W, 3) ray factors (Os0Emulator._column_rays)
    oc: NDArray[np.float32]  # (W, 3) beam origins
    noise: FloatArray | None  # (W, H)
    sid: NDArray[np.int32]  # (W, H) stem id out
    packets: NDArray[np.uint8]
    views: list[NDArray[Any]]  # Os0Emulator._views(packets)
    ts: NDArray[np.int64]
    o_all: NDArray[np.float32] | None  # DUAL: the rays and first returns, (W, H, ...)
    d_all: NDArray[np.float32] | None
    t_all: FloatArray | None
    ok_all: NDArray[np.bool_] | None
    cn_all: NDArray[np.float32] | None = None  # (W, H) the curve hits' |cos|, physics only


class Os0Emulator:
    """Produces staggered frames for a sensor described by ``meta``.

    The SDK's ray model factors: beam ``h`` of column ``c`` points along
    ``L Rz(theta_c) b_h`` from ``L Rz(theta_c) (n, 0, 0) + t_L`` (``L, t_L`` the
    lidar-to-sensor transform, ``theta_c`` the encoder angle, ``b_h`` the beam's unit vector,
    ``n`` the beam-origin offset). With the sensor pose ``(R_c, p_c)`` of the column, its rays
    in the scene are ``M_c b_h`` with ``M_c = R_c L Rz(theta_c)``: per ray, three products
    and two sums in float32 (as the casters take rays), ``M_c`` made once per column.

    Column poses come from pieces the pose source builds for two seconds of frames at once
    while frames are read in order (where it is a :class:`DensePoseSource`, e.g.
    :class:`tcf_hil.world.track.Trajectory`; else ``sensor_pose`` per frame); a frame's poses
    and ``M_c`` are made first. Then, where the scene hands over an Embree scene
    (:meth:`FastRayScene.direct`) and numba is here, one compiled call per thread (this one and
    ``threads - 1`` more) takes blocks of columns in turn and, without the GIL, encodes
    their packets' columns, makes their rays, casts them and answers each into its pixel
    (:func:`emulators.lidar._fused.cast_answer_blocks`). Otherwise chunks of columns are
    spread over ``threads`` threads (one at a time where the scene's cast spreads over the
    CPUs by itself, ``threads_itself``: open3d), each encoded (:func:`protocols.ouster.
    encode_lidar_columns`), its rays made, cast by the scene and answered (compiled kernels
    in :mod:`emulators.lidar._kernel`, or numpy where numba is missing). Every path writes
    the same bytes whatever the split (the tests hold them to it)."""

    FUSED_BLOCK_COLUMNS = 16  # the fused kernel's unit of work, taken by the threads in turn
    MIN_RAYS_PER_CHUNK = 8192  # the other path's chunks: about RAYS_PER_CHUNK rays each,
    RAYS_PER_CHUNK = 32768  # whole blocks of BLOCK_COLUMNS columns (whole packets)
    BLOCK_COLUMNS = 128

    def __init__(self, meta: SensorMetadata, scene: RayScene, poses: PoseSource,
                 model: ReturnModel | None = None, *, seed: int = 0,
                 start_ns: int = 1_000_000_000, threads: int | None = None,
                 sensor: SensorModel | None = None) -> None:
        """``sensor``: the physical sensor model (:mod:`emulators.lidar._physics`); None or an
        ideal one: one exact ray per pixel answered by ``model``."""
        if meta.profile not in EMULATED_PROFILES or meta.header_type not in ("", "STANDARD"):
            raise ValueError(f"udp_profile_lidar {meta.profile} (header_type "
                             f"{meta.header_type or 'as the profile'}) is read and replayed, "
                             f"not emulated; the emulator writes "
                             f"{', '.join(EMULATED_PROFILES)}")
        self.meta = meta
        self.sensor = sensor
        if sensor is not None and sensor.ideal and model is None:
            model = ReturnModel(min_range_m=sensor.min_range_m, ambient=sensor.ambient,
                                reflectance={"ground": sensor.reflectance.ground,
                                             "bark": sensor.reflectance.bark})
        self._seed = seed
        self.scene = scene
        self.poses = poses
        self._scene = fast_scene(scene)
        self._dense = poses if isinstance(poses, DensePoseSource) else None
        self._pose_at = (self._dense.sensor_pose_dense if self._dense is not None
                         else poses.sensor_pose)
        self.model = model or ReturnModel()
        self.rng = np.random.default_rng([seed, 0x0500])
        self.start_ns = start_ns
        w = meta.columns
        o, d = beam_rays(meta)  # sensor frame, (H, W, 3): the plain model, for float64 rays
        self._origins_wh = np.ascontiguousarray(o.transpose(1, 0, 2))
        self._directions_wh = np.ascontiguousarray(d.transpose(1, 0, 2))
        # the factored model (see the class doc)
        theta = 2.0 * np.pi * (1.0 - np.arange(w) / w)
        self._cos, self._sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
        az = -np.radians(np.asarray(meta.beam_azimuth_deg, np.float64))
        alt = np.radians(np.asarray(meta.beam_altitude_deg, np.float64))
        self._beams32 = np.stack([np.cos(az) * np.cos(alt), np.sin(az) * np.cos(alt),
                                  np.sin(alt)], axis=1).astype(np.float32)
        lts = np.asarray(meta.lidar_to_sensor, dtype=np.float64).reshape(4, 4)
        self._l_rot, self._l_tr = lts[:3, :3].copy(), lts[:3, 3] / 1000.0
        self._block = math.gcd(w, self.BLOCK_COLUMNS)
        self.period_ns = 1_000_000_000 // meta.frequency_hz
        self._col_offsets = (np.arange(w, dtype=np.int64) * self.period_ns) // w
        self.n_m = meta.lidar_origin_to_beam_origin_mm / 1000.0
        self.quantum_mm = 8 if meta.profile == "RNG15_RFL8_NIR8" else 1
        self._fmt = meta.packet_format
        self.profile_fields = set(self._fmt.field_names)
        # By return class (0 none, 1 terrain, 2 stem): reflectance, reach, encoded values.
        m = self.model
        refl = np.array([0.0, m.reflectance["ground"], m.reflectance["bark"]])
        self._refl_signal = refl * m.signal_scale
        self._reach = [float(m.max_range_m * min(1.0, math.sqrt(r / m.reference_reflectance)))
                       for r in refl[1:]]
        self._min_r = m.min_range_m
        self.physics: Physics | None = None
        if sensor is not None and not sensor.ideal:
            carried = carried_range_m(self._fmt)
            # beam h + 1's pixel nearest in angle to beam h's: from the beams' azimuths
            # (the pixel shifts are rounded, in 2048x10 to even columns: up to 2 off)
            az = np.asarray(meta.beam_azimuth_deg, np.float64)
            step = np.rint((az[:-1] - az[1:]) * (meta.columns / 360.0)).astype(np.int64)
            self.physics = Physics(sensor, meta.mode, carried, (meta.columns, meta.pixels),
                                   step, self.quantum_mm)
            # the cast keeps every hit the profile can carry; the physics answers them
            self._reach = [carried - 0.01, carried - 0.01]
            self._min_r = 0.0
        self._surfaces: Surfaces | None = None
        self._surfaces_asked = False
        self._reflectivity = np.round(refl * 100.0).astype(np.uint32)
        nir = np.minimum(m.ambient * np.array([0.05, refl[1], refl[2]]), 65535.0
                         ).astype(np.uint32)
        if meta.profile == "RNG15_RFL8_NIR8":
            nir = np.minimum(nir, 4080) // 16 * 16
        self._nir = nir
        self._layout(self._fmt)
        self.threads = max(1, threads or (len(os.sched_getaffinity(0))
                                          if hasattr(os, "sched_getaffinity")
                                          else (os.cpu_count() or 1)))
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid = 0
        self._pose_block: tuple[int, int, PosePieces] | None = None
        self.jit = True  # the compiled per-ray kernel (numba), where it can be had
        self._direct: DirectCast | None = None
        self._direct_asked = False
        self._template: NDArray[np.uint8] | None = None
        self._view_geometry: list[tuple[Any, ...]] | None = None
        self._pending: list[Any] = []  # helper calls of the last fused frame

    def _layout(self, fmt: PacketFormat) -> None:
        """Where the first return's fields go in a pixel, and their values by return class
        (0 none, 1 terrain, 2 stem) already shifted into place; the range must fit."""
        fields = {f.name: f for f in fmt.profile.fields}
        want = ["RANGE", "REFLECTIVITY", "NEAR_IR"] + (["SIGNAL"] if "SIGNAL" in fields
                                                        else [])
        self._field_names = tuple(want) + tuple(
            x for x in ("RANGE2", "REFLECTIVITY2", "SIGNAL2") if x in fields)
        self._word_of = {x: (fields[x].offset, fields[x].dtype) for x in want}

        def place(f: Field, v: NDArray[np.integer]) -> NDArray[np.uint32]:
            w = v.astype(np.uint32)
            w = w << np.uint32(f.shift) if f.shift >= 0 else w >> np.uint32(-f.shift)
            if np.any(w & ~np.uint32(f.mask)) or not np.array_equal(
                    (w >> np.uint32(f.shift)) if f.shift >= 0 else w << np.uint32(-f.shift), v):
                raise ValueError(f"{f.name} values {v.tolist()} do not fit {fmt.profile.name}")
            return w

        # REFLECTIVITY and NEAR_IR words by class, in the word's type
        self._luts: dict[str, NDArray[np.generic]] = {name: place(fields[name], values).astype(
            np.dtype(fields[name].dtype).newbyteorder("="))
            for name, values in (("REFLECTIVITY", self._reflectivity), ("NEAR_IR", self._nir))}
        self._signal32 = self._refl_signal.astype(np.float32)
        # the same for the compiled kernel: the words it writes, the values by class
        names = [x for x in ("RANGE", "REFLECTIVITY", "NEAR_IR", "SIGNAL") if x in self._word_of]
        self._kernel: dict[str, Any] = {
            "words": [self._word_of[x] for x in names],
            "luts": np.array([self._luts[x] for x in ("REFLECTIVITY", "NEAR_IR")], np.int64),
            "clamp": bool(self._signal32.max() > 65535.0 * 0.25)}
        # range in quanta of quantum_mm; the word holds mm shifted by the field's shift
        f = fields["RANGE"]
        q = self.quantum_mm
        self._range_units = 1000.0 / q
        self._range_mult = q << f.shift if f.shift >= 0 else q >> -f.shift
        most = math.ceil(max(self._reach) * 1000.0 / q) * self._range_mult
        if self._range_mult << max(0, -f.shift) != q << max(0, f.shift) or most > f.mask:
            raise ValueError(f"max_range_m {self.model.max_range_m}: {fmt.profile.name} "
                             f"carries ranges up to {carried_range_m(fmt):.0f} m")

    def warm_up(self) -> None:
        """:func:`warm_up` for this sensor and return model, and this scene's tables made
        (the direct scene's stem ids, the physics' surfaces: a third of a second at 2048x10
        on forest-x), before a fork: the renderer processes share them instead of each
        making its own in its first frame."""
        warm_up(self.meta, self.model, self.sensor)
        if self.physics is not None:
            self._scene_surfaces()
        self._direct_scene()

    def column_times(self, k: int) -> NDArray[np.int64]:
        return self._col_offsets + (self.start_ns + k * self.period_ns)

    def column_poses(self, k: int) -> tuple[FloatArray, FloatArray]:
        """Frame k's sensor pose per column: positions (W, 3), rotations (W, 3, 3)."""
        pieces, ts = self._pose_pieces(k)
        if pieces is None:
            return self._pose_at(ts)
        pos, rot = pieces.at(ts)
        return pos, rot

    def _pose_pieces(self, k: int) -> tuple[PosePieces | None, NDArray[np.int64]]:
        """How frame k's column poses are had: (pieces to evaluate at the column times, or
        None for the pose source's own ``sensor_pose``/``sensor_pose_dense``), the times.

        A :class:`DensePoseSource` (a :class:`tcf_hil.world.track.Trajectory`) builds its
        pieces for two seconds of frames at a time while frames are read in order: the same
        knots as one frame at a time, so the same poses up to the last bits of the exact
        poses at the knots (numpy's vector maths may round differently in a longer batch)."""
        ts = self.column_times(k)
        dense = self._dense
        if dense is None:
            return None, ts
        blk = self._pose_block
        if blk is None or not blk[0] <= k < blk[1]:
            nf = 2 * self.meta.frequency_hz if blk is not None and k == blk[1] else 1
            lo, hi = int(ts[0]), int(self.column_times(k + nf - 1)[-1])
            h = dense.dense_knot_ns()
            blk = self._pose_block = (k, k + nf,
                                      dense.dense_poses(lo // h * h, (hi // h + 1) * h, h))
        return dense.dense_pieces(ts, pieces=blk[2]), ts

    def _column_rays(self, pos: FloatArray, rot: FloatArray,
                     out: tuple[NDArray[np.float32], NDArray[np.float32]] | None = None
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The frame's ray factors from its column poses ((W, 3), (W, 3, 3)): (3, W, 3)
        float32 with [j, c, i] = M_c[i, j], and the beam origins (W, 3) float32 in the scene
        (into ``out`` where given). Sums written out, left to right (the compiled kernel and
        numpy alike, no BLAS): the same bits whatever the split into blocks."""
        n = len(pos)
        cos, sin = self._cos[:, 0], self._sin[:, 0]
        mt, oc = out if out is not None else (np.empty((3, n, 3), np.float32),
                                              np.empty((n, 3), np.float32))
        kernel = frames_kernel() if self.jit else None
        if kernel is not None:
            kernel(pos, rot, cos, sin, self._l_rot, self._l_tr, self.n_m, mt, oc)
            return mt, oc
        lr, lt = self._l_rot, self._l_tr
        for i in range(3):
            r0, r1, r2 = rot[:, i, 0], rot[:, i, 1], rot[:, i, 2]
            a0 = r0 * lr[0, 0] + r1 * lr[1, 0] + r2 * lr[2, 0]
            a1 = r0 * lr[0, 1] + r1 * lr[1, 1] + r2 * lr[2, 1]
            a2 = r0 * lr[0, 2] + r1 * lr[1, 2] + r2 * lr[2, 2]
            m0 = a0 * cos + a1 * sin
            mt[0, :, i] = m0
            mt[1, :, i] = a1 * cos - a0 * sin
            mt[2, :, i] = a2
            oc[:, i] = pos[:, i] + (r0 * lt[0] + r1 * lt[1] + r2 * lt[2]) + self.n_m * m0
        return mt, oc

    def _make_rays(self, mt: NDArray[np.float32], oc: NDArray[np.float32], col0: int,
                   o: NDArray[np.float32], d: NDArray[np.float32]) -> None:
        """The rays of columns col0 .. col0 + n of the frame's ``mt``/``oc``
        (:meth:`_column_rays`), column-major, into ``o``/``d`` (n, H, 3) float32:
        ``d[c, h] = M_c b_h`` summed left to right, one rounding per operation
        (:func:`emulators.lidar._kernel.make_rays`, or numpy: the same bits)."""
        kernel = rays_kernel() if self.jit else None
        if kernel is not None:
            kernel(self._beams32, mt, oc, col0, o, d)
            return
        cols = slice(col0, col0 + len(o))
        b = self._beams32[None, :, :, None]  # (1, H, 3, 1)
        np.multiply(b[:, :, 0], mt[0, cols][:, None, :], out=d)
        d += b[:, :, 1] * mt[1, cols][:, None, :]
        d += b[:, :, 2] * mt[2, cols][:, None, :]
        o[...] = oc[cols, None, :]

    def _direct_scene(self) -> DirectCast | None:
        """What the fused kernel casts through (``rtcIntersect1``, the handles, stem id by
        triangle), where the scene offers it (``direct()``) and compiled kernels are on."""
        if not self.jit:
            return None
        if not self._direct_asked:
            self._direct = self._scene.direct()
            self._direct_asked = True
            surfaces = self._scene_surfaces() if self.physics is not None else None
            if self._direct is not None and surfaces is not None:  # answer primitives
                n = len(surfaces.normals)  # triangles; then curve segments, the miss last
                m = len(surfaces.stem_of_prim) - n - 1
                self._direct = (*self._direct[:2], np.concatenate(
                    [np.arange(n, dtype=np.int32), np.arange(-1 - m, 0, dtype=np.int32)]))
        return self._direct

    def rays(self, k: int, dtype: type[np.floating] = np.float64
             ) -> tuple[NDArray[np.floating], NDArray[np.floating], FloatArray, FloatArray]:
        """Frame k's rays in the scene, column-major: origins and unit directions
        (W*H, 3) in ``dtype`` (float32: the very rays :meth:`frame` casts), and the
        per-column sensor positions (W, 3) and rotations (W, 3, 3), float64."""
        pos, rot = self.column_poses(k)
        # Rays of column c are in the sensor frame of column c's pose.
        if dtype == np.float32:
            o32 = np.empty((len(pos), self.meta.pixels, 3), np.float32)
            d32 = np.empty_like(o32)
            self._make_rays(*self._column_rays(pos, rot), 0, o32, d32)
            return o32.reshape(-1, 3), d32.reshape(-1, 3), pos, rot
        rt = rot.transpose(0, 2, 1)
        o = np.matmul(self._origins_wh, rt) + pos[:, None, :]
        d = np.matmul(self._directions_wh, rt)
        return o.reshape(-1, 3), d.reshape(-1, 3), pos, rot

    def _chunks(self) -> list[tuple[int, int]]:
        """Whole blocks of columns, about ``RAYS_PER_CHUNK`` rays each (their arrays stay in
        a core's cache), at least one per thread."""
        H, W = self.meta.pixels, self.meta.columns
        n = max(W * H // self.RAYS_PER_CHUNK, self.threads)
        n = max(1, min(n, W // self._block, W * H // self.MIN_RAYS_PER_CHUNK))
        cuts = sorted({round(W * i / n / self._block) * self._block for i in range(n + 1)})
        return list(itertools.pairwise(cuts))

    def frame(self, k: int, packets: NDArray[np.uint8] | None = None) -> FrameResult:
        """Frame k, written into packets: ``packets`` (the frame's (packets_per_frame,
        packet_bytes) uint8 array) or a new array, :attr:`FrameResult.packets` either way.
        Every column is encoded (:func:`protocols.ouster.encode_lidar_columns`, then the
        pixel words straight from the return model); the packet headers and CRCs are left to
        the caller (:func:`protocols.ouster.finish_lidar_packets`), who chooses the
        frame_id. The DUAL profile's second return is cast over the whole frame after the
        first."""
        m = self.model
        H, W = self.meta.pixels, self.meta.columns
        fmt = self._fmt
        shape = (fmt.packets_per_frame, fmt.packet_bytes)
        if packets is None:
            packets = np.empty(shape, np.uint8)
        elif packets.shape != shape or packets.dtype != np.uint8:
            raise ValueError(f"packet array of shape {packets.shape} and dtype "
                             f"{packets.dtype}; expected {shape} uint8")
        arr = packets
        self._settle()
        pieces, ts = self._pose_pieces(k)
        physics = self.physics
        noise = (self.rng.normal(0.0, m.noise_sigma_m, (H, W)).T
                 if m.noise_sigma_m > 0 and physics is None else None)
        dual = "RANGE2" in self.profile_fields  # only what the profile carries
        keep = dual or physics is not None  # the rays and first hits, for what follows
        sid_out = np.empty((W, H), np.int32)  # column-major; stem_id is its transposed view
        o_all = np.empty((W, H, 3), np.float32) if keep else None
        d_all = np.empty((W, H, 3), np.float32) if keep else None
        t_all = np.empty((W, H)) if keep else None
        ok_all = np.empty((W, H), bool) if keep else None
        mt, oc = np.empty((3, W, 3), np.float32), np.empty((W, 3), np.float32)
        job = _FrameJob(mt, oc, noise, sid_out, arr, self._views(arr), ts, o_all, d_all, t_all,
                        ok_all, np.zeros((W, H), np.float32) if physics is not None else None)
        direct = self._direct_scene()
        fused = _fused_kernel() if direct is not None else None
        centre: tuple[Any, ...] | None = None
        surfaces = self._scene_surfaces() if physics is not None else None
        if direct is not None and fused is not None and physics is not None \
                and surfaces is not None and job.cn_all is not None:
            # cast and the centre rays' echoes in one call (the physics writes the words)
            from emulators.lidar._fused import cast_centre_blocks

            N = W * H
            centre = (np.empty(N, np.int32), np.empty(N), np.empty(N), np.empty(N, np.uint32))
            prim_all, t_phys = np.empty(N, np.int32), np.empty(N)
            tail = ((self.n_m, float(self._reach[0]), physics.R_NEAR, physics.model.ambient),
                    (prim_all, job.cn_all.reshape(-1), t_phys),
                    (surfaces.stem_of_prim, surfaces.material_of_prim, surfaces.normals,
                     physics.refl), centre)
            pos, rot = self._fused_frame(cast_centre_blocks, direct[:2], job, pieces, tail)
        elif direct is not None and fused is not None:
            pos, rot = self._fused_frame(fused, direct, job, pieces)
        else:
            pos, rot = self._poses(job, pieces)
            chunks = [(job, a, b) for a, b in self._chunks()]
            if self._scene.threads_itself:  # one cast at a time (open3d)
                for c in chunks:
                    self._chunk(*c)
            else:
                self._run(self._chunk, chunks)
        sid2 = None
        if physics is not None and o_all is not None and d_all is not None \
                and t_all is not None and ok_all is not None:
            sid_out, sid2 = self._physical(physics, k, arr, o_all, d_all, t_all, ok_all,
                                           sid_out, dual, centre, job.cn_all)
        elif o_all is not None and d_all is not None and t_all is not None \
                and ok_all is not None:  # only what the profile carries
            second: dict[str, NDArray[np.uint32]] = {}
            sid2 = self._second_return(o_all.reshape(-1, 3), d_all.reshape(-1, 3), t_all.T,
                                       ok_all.T, second)
            encode_pixel_fields(fmt, arr, 0, second)
        return FrameResult(k, ts.astype(np.uint64), sid_out.T, sid2, pos, rot, arr, fmt,
                           self._field_names)

    def _scene_surfaces(self) -> Surfaces | None:
        if not self._surfaces_asked:
            self._surfaces = self._scene.surfaces()
            self._surfaces_asked = True
        return self._surfaces

    def _physical(self, physics: Physics, k: int, arr: NDArray[np.uint8],
                  o_all: NDArray[np.float32], d_all: NDArray[np.float32], t_all: FloatArray,
                  ok_all: NDArray[np.bool_], hits: NDArray[np.int32], dual: bool,
                  centre: tuple[Any, ...] | None = None,
                  cn_all: NDArray[np.float32] | None = None
                  ) -> tuple[NDArray[np.int32], NDArray[np.int32] | None]:
        """The physical sensor's answer to frame k's first cast (``hits`` (W, H): the
        triangle hit where the scene tells triangles, else the stem id; -1 none; or the
        centre rays' echoes ``centre`` the fused cast made): every pixel's fields rewritten
        into the packets. Returns the stem ids of the first and (DUAL) second returns,
        (W, H) column-major."""
        surfaces = self._scene_surfaces()
        cast = surfaces.cast if surfaces is not None else self._scene.cast
        t = np.where(ok_all, t_all, np.inf).reshape(-1) if centre is None else t_all
        rng = np.random.default_rng([self._seed, 0x0501, k])
        physics.jit = self.jit
        out = physics.respond(o_all[:, 0], d_all.reshape(-1, 3), t, hits.reshape(-1),
                              surfaces, cast, self.n_m, rng, dual, self._run, centre,
                              cn=cn_all.reshape(-1) if cn_all is not None else None)
        if self.meta.profile == "RNG15_RFL8_NIR8":
            out["NEAR_IR"] = np.minimum(out["NEAR_IR"], 4080) // 16 * 16
        encode_pixel_fields(self._fmt, arr, 0, {n: v for n, v in out.items()
                                                if n in self.profile_fields})
        sid2 = np.ascontiguousarray(out["sid2"].T) if dual else None  # (H, W), as FrameResult's
        return out["sid"], sid2

    def _poses(self, job: _FrameJob, pieces: PosePieces | None) -> tuple[FloatArray, FloatArray]:
        """The frame's column poses (from ``pieces``, or exact), and from them its ray
        factors into ``job.mt``/``job.oc``."""
        pos, rot = pieces.at(job.ts) if pieces is not None else self._pose_at(job.ts)
        self._column_rays(pos, rot, out=(job.mt, job.oc))
        return pos, rot

    def _pool_here(self) -> ThreadPoolExecutor:
        if self._pool is None or self._pool_pid != os.getpid():  # threads die in a fork
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="os0")
            self._pool_pid = os.getpid()
            self._pending = []
        return self._pool

    def _run(self, fn: Any, calls: list[tuple[Any, ...]]) -> None:
        """``fn(*c)`` for every ``c`` of ``calls``, spread over the pool's threads (or here,
        for one thread or one call)."""
        if self.threads == 1 or len(calls) == 1:
            for c in calls:
                fn(*c)
            return
        pool = self._pool_here()
        for f in [pool.submit(fn, *c) for c in calls]:
            f.result()

    def _settle(self) -> None:
        """Wait for the helper calls of the last fused frame to have returned (their blocks
        are done by then; only their return may be outstanding), and raise what they
        raised."""
        pending, self._pending = self._pending, []
        if self._pool_pid != os.getpid():
            return  # a forked copy: those threads and their futures stayed in the parent
        for f in pending:
            f.result()

    def _template_here(self) -> NDArray[np.uint8]:
        """The frame's packets with every column encoded at time 0 (the fused kernels copy
        each block's from it)."""
        if self._template is None:
            fmt, W = self._fmt, self.meta.columns
            self._template = np.empty((fmt.packets_per_frame, fmt.packet_bytes), np.uint8)
            encode_lidar_columns(fmt, self._template, 0, {}, np.zeros(W, np.int64))
        return self._template

    def _fused_frame(self, fused: Callable[..., None],
                     direct: tuple[Any, ...],
                     job: _FrameJob, pieces: PosePieces | None,
                     tail: tuple[Any, ...] | None = None) -> tuple[FloatArray, FloatArray]:
        """The frame through :func:`emulators.lidar._fused.cast_answer_blocks`: one call per
        thread, each taking the next block of columns until none is left, so the threads
        finish together. The helper threads' calls start first and wait (spinning, without
        the GIL) while this thread makes the column poses and ray factors, then this thread
        joins them and returns once every block is done, without waiting for their calls to
        return (:meth:`_settle`). Returns the column poses."""
        fmt, W = self._fmt, self.meta.columns
        width = math.lcm(math.gcd(W, self.FUSED_BLOCK_COLUMNS), fmt.columns_per_packet)
        none3 = np.zeros((0, 0, 0), np.float32)
        rays = (self._beams32, job.mt, job.oc)
        packets = (self._template_here(), job.packets, job.views[-1], job.ts)
        kept = (job.o_all if job.o_all is not None else none3,
                job.d_all if job.d_all is not None else none3)
        if tail is None:  # the ideal answer's: answer_chunk's, whole-frame (each block
            tail = self._answer_args(job, 0, W)  # slices its own words)
            tail = (tail[0], *tail[2:])
        starts = np.arange(0, W, width)
        counter = np.zeros(3, np.int64)  # the next block, go (1) or stop (2), blocks done
        n = min(self.threads, len(starts))
        pool = self._pool_here() if n > 1 else None
        helpers = [pool.submit(fused, direct, rays, (starts, counter, False, width), packets,
                               kept, *tail)
                   for _ in range(n - 1)] if pool is not None else []
        try:
            pos, rot = self._poses(job, pieces)
            counter[1] = 1
        except BaseException:
            counter[1] = 2
            for f in helpers:
                f.result()
            raise
        self._pending = helpers
        fused(direct, rays, (starts, counter, True, width), packets, kept, *tail)
        return pos, rot

    def _chunk(self, job: _FrameJob, a: int, b: int) -> None:
        """Columns a..b of a frame where the cast is the scene's own (not an Embree scene
        it hands over): column headers, rays, the cast, returns into their packets."""
        H, n = self.meta.pixels, b - a
        encode_lidar_columns(self._fmt, job.packets, a, {}, job.ts[a:b])
        if job.o_all is not None and job.d_all is not None:  # DUAL keeps the rays
            o, d = job.o_all[a:b], job.d_all[a:b]
        else:
            o = np.empty((n, H, 3), np.float32)
            d = np.empty_like(o)
        self._make_rays(job.mt, job.oc, a, o, d)
        surfaces = self._scene_surfaces() if self.physics is not None else None
        cast32 = surfaces.cast1 if surfaces is not None else self._scene.cast32
        got: tuple[Any, ...] = cast32(o.reshape(-1, 3), d.reshape(-1, 3))
        t32, sid_cm = got[0], got[1]
        if len(got) > 2 and len(got[2]) and job.cn_all is not None:  # physics: curve hits
            job.cn_all[a:b] = np.asarray(got[2]).reshape(n, H)
        t = np.asarray(t32, np.float32).reshape(n, H)  # column-major, as cast
        sid = np.asarray(sid_cm, np.int32).reshape(n, H)
        kernel = answer_kernel() if self.jit else None
        if kernel is not None:
            kernel(t, sid, *self._answer_args(job, a, b))
        else:
            self._answer_numpy(job, a, b, t, sid)

    def _views(self, packets: NDArray[np.uint8]) -> list[NDArray[Any]]:
        """The frame's pixel words the kernels write (:attr:`_kernel` ``words``, each
        (P, C, H)) and its column time stamps (P, C): protocols' views
        (:meth:`protocols.ouster.PacketFormat.pixel_word`, ``column_timestamps``), remade
        on each frame's packets from their offsets and strides (a fraction of the time)."""
        fmt = self._fmt
        if self._view_geometry is None:
            probe = np.zeros((fmt.packets_per_frame, fmt.packet_bytes), np.uint8)
            base = probe.__array_interface__["data"][0]
            views = [fmt.pixel_word(probe, off, dt) for off, dt in self._kernel["words"]]
            views.append(fmt.column_timestamps(probe))
            self._view_geometry = [(v.shape, v.dtype, v.__array_interface__["data"][0] - base,
                                    v.strides) for v in views]
        if not packets.flags.c_contiguous:
            return [fmt.pixel_word(packets, off, dt) for off, dt in self._kernel["words"]] \
                + [fmt.column_timestamps(packets)]
        return [np.ndarray(shape, dt, buffer=packets, offset=off, strides=st)
                for shape, dt, off, st in self._view_geometry]

    def _answer_args(self, job: _FrameJob, a: int, b: int) -> tuple[Any, ...]:
        """:func:`emulators.lidar._kernel.answer_chunk`'s arguments after ``t`` and ``sid``,
        for columns a..b."""
        C = self._fmt.columns_per_packet
        k = self._kernel
        none2 = np.zeros((0, 0))
        words = [v[a // C:b // C] for v in job.views[:-1]]
        enc = (self.n_m, self._min_r, self._reach[0], self._reach[1], self._range_units,
               self._range_mult, k["luts"], self._signal32, k["clamp"],
               k["words"][0] == k["words"][1])
        out = (job.sid, job.t_all if job.t_all is not None else none2,
               job.ok_all if job.ok_all is not None else np.zeros((0, 0), bool))
        return (job.noise[a:b] if job.noise is not None else none2, a, enc,
                (*words[:3], words[3] if len(words) == 4 else words[2][:0]), out)

    def _answer_numpy(self, job: _FrameJob, a: int, b: int, t: NDArray[np.float32],
                      sid: NDArray[np.int32]) -> None:
        """The compiled kernel's work in numpy (where numba is missing; the tests hold the
        two to the same bytes): ``t``/``sid`` (n, H), column-major as the packets."""
        H, n = self.meta.pixels, b - a
        fmt = self._fmt
        C = fmt.columns_per_packet
        # the encoded range counts from the lidar axis (a miss is inf: never in reach)
        tt = t.astype(np.float64)
        if job.noise is not None:
            tt += job.noise[a:b]
        r = tt + self.n_m
        ok = r >= self._min_r
        bark = sid > 0
        if self._reach[0] == self._reach[1]:
            ok &= r <= self._reach[0]
        else:
            ok &= r <= np.where(bark, self._reach[1], self._reach[0])
        bark &= ok
        np.bitwise_or(sid, ok.view(np.int8) - 1, out=job.sid[a:b])  # -1: no return
        rows = job.packets[a // C:b // C]
        for (off, dt), v in self._pixel_words(r, ok, bark).items():
            np.copyto(fmt.pixel_word(rows, off, dt), v.reshape(n // C, C, H), casting="unsafe")
        if job.t_all is not None and job.ok_all is not None:
            job.t_all[a:b] = tt
            job.ok_all[a:b] = ok

    def _pixel_words(self, r: FloatArray, ok: NDArray[np.bool_], bark: NDArray[np.bool_]
                     ) -> dict[tuple[int, str], NDArray[np.generic]]:
        """The first return's pixel words for (n, H) column-major answers: range from the
        lidar axis in metres ``r``, whether it came back ``ok``, and whether from bark;
        each field's value already shifted into its place in the word (:meth:`_layout`);
        REFLECTIVITY, NEAR_IR and SIGNAL's reflectance looked up by return class."""
        words: dict[tuple[int, str], NDArray[np.generic]] = {}
        ok8, bark8 = ok.view(np.uint8), bark.view(np.uint8)

        def put(name: str, v: NDArray[np.generic]) -> None:
            key = self._word_of[name]
            if key in words:  # fields sharing a word: integers, each in its own bits
                words[key] = words[key] | v.astype(words[key].dtype, copy=False)
            else:
                words[key] = v

        u = r * self._range_units  # range quanta
        np.rint(u, out=u)
        with np.errstate(invalid="ignore"):  # inf (no return) is zeroed by ok just below
            ui = u.astype(np.int32)
        ui *= ok
        put("RANGE", ui.view(np.uint32) if self._range_mult == 1 else ui.view(np.uint32)
            * np.uint32(self._range_mult))
        cls = ok8 + bark8  # 0 none, 1 terrain, 2 stem
        for name, lut in self._luts.items():
            put(name, np.take(lut, cls, mode="clip"))
        if "SIGNAL" in self._word_of:
            # photons: reflectance over range squared (no return: reflectance 0)
            den = np.empty(r.shape, np.float32)
            np.maximum(r, 0.5, out=den, casting="same_kind")
            den *= den
            sig = np.take(self._signal32, cls, mode="clip")
            sig /= den
            if self._kernel["clamp"]:  # can saturate (nearer than 0.5 m)
                np.minimum(sig, np.float32(65535.0), out=sig)
            put("SIGNAL", sig)  # written truncated, as the sensor counts photons
        return words

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
