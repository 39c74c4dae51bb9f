"""The OS0-64 as physics: what a pulse of finite width sees and what the sensor makes of it.

A :class:`SensorModel` holds every figure as a key (a scenario's ``[sensor]`` table), and
:data:`SENSOR_PRESETS` the sensors by name: ``os0-64-rev7`` (the default), ``os0-64-rev6``
and ``ideal`` (one pencil ray per pixel, no noise: the emulator's exact geometry, with
:class:`~emulators.lidar._os0.ReturnModel`'s constants, byte for byte what it wrote before
the physics existed). Where each figure comes from is in the README ("The sensor model");
figures we could not find are said to be assumptions there and in the field docs below.

:class:`Physics` is the model prepared for one sensor mode, run once per frame on the first
cast (:meth:`Physics.respond`), in numpy, after whichever execution path cast the centre
rays, so every path gives the same bytes:

1. **The footprint.** The beam is a Gaussian of the divergence (FWHM, horizontal and
   vertical), sampled on a lattice fixed to the sensor (:class:`FootprintGrid`,
   ``footprint_samples`` a FWHM): along the beam's row every column spacing or a
   power-of-two fraction of it out to one FWHM, so the neighbouring columns' own centre
   rays are samples (in 2048x10 all of them: nothing more is cast for a vertical edge
   such as a stem's side), and in rows above and below out to half the FWHM. Each
   lattice ray is cast once a frame and serves every pixel whose footprint reaches it.
   ``adaptive``: the row where a column within one FWHM hits another object (or nothing)
   than the pixel, the grid where the beam above or below sees another object (a
   horizontal edge: a stem's top, the horizon); ``edges``: the grid at those same
   pixels; ``full``: the grid at every pixel; ``off``: the centre ray alone.
2. **Echoes.** A footprint that one object fills (every sample hits the object its centre
   ray hits) answers as its centre ray does: inside one surface the sub-rays would only
   average its curvature over the beam (a mm or two, under the noise floor), so only
   where a footprint straddles an edge do they count. There, each sub-ray's hit carries
   the energy ``w ρ cos(i) / r²`` (its weight in the beam, the material's reflectance,
   the incidence angle, the range). Hits sorted by range join one echo while the gap to
   the next is within ``range_resolution_m``: the echo's range is their energy-weighted
   mean, so an echo of a stem edge and the wall behind it lies between them (a mixed
   pixel). The echoes are ordered as the sensor's
   ``return_order`` says; the first is the return, the DUAL profiles' second the next.
3. **Signal and detection.** ``SIGNAL`` is the echo's energy times a scale fixed by the
   datasheet's reach (a 10 %-reflectance target at ``reach_10pct_m`` in 1024x10 detected
   with probability ``detection_probability``), the mode's reach factor squared and
   ``signal_multiplier``. An echo is detected with a probability that rises with its
   signal around the threshold (log-normal, width ``detection_width``), drawn per pixel.
4. **Range noise** falls with the signal, ``σ = max(σ_min, σ_thr S^-b)`` with ``S`` the
   signal over the median detection threshold (the one published table of range
   repeatability by SNR, the OS1's, fitted: b = 0.625; the threshold taken as its lowest
   SNR, 12, and SNR as proportional to signal in 100 klx sunlight: assumptions), zero-mean.
5. **What is written.** RANGE from the lidar axis (nearer than ``min_range_m``: none);
   REFLECTIVITY the calibrated reflectance the sensor infers from signal and range (the
   target's for a full, square-on hit; less at grazing incidence or a partial hit);
   NEAR_IR the ambient light the centre ray's surface reflects; ambient false returns at
   ``false_positive_rate`` per pixel with no return, at a random range with a weak signal.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

MATERIALS: tuple[str, ...] = ("ground", "bark", "foliage", "dead_wood", "rock")
"""Materials by index: a scene's triangles name theirs (0 ground, 1 bark, ...)."""
RETURN_ORDERS = ("STRONGEST_TO_WEAKEST", "NEAREST_TO_FARTHEST", "FARTHEST_TO_NEAREST")
MODE_COLUMNS_PER_S = {"512x10": 5120, "1024x10": 10240, "2048x10": 20480, "512x20": 10240,
                      "1024x20": 20480, "4096x5": 20480}
"""Columns a second: what a mode's reach factor goes by (the dwell time per column)."""


def _f(default: Any, doc: str, **limits: Any) -> Any:
    """A field with its documentation and limits (as the scenario loader reads them)."""
    return field(default=default, metadata={"doc": doc, **limits})


@dataclass(frozen=True, slots=True)
class Reflectance:
    """Reflectance at the sensor's 865 nm by material, 0..1 (see the README for sources)."""

    ground: float = _f(0.25, "forest floor (assumption: no 865 nm figure found)", ge=0.0,
                       le=1.0)
    bark: float = _f(0.45, "stem bark (assumption: no 865 nm figure found)", ge=0.0, le=1.0)
    foliage: float = _f(0.517, "needles (HELIOS++ conifer spectrum at 860 nm)", ge=0.0,
                        le=1.0)
    dead_wood: float = _f(0.35, "lying dead wood, stumps (assumption)", ge=0.0, le=1.0)
    rock: float = _f(0.3, "boulders (assumption)", ge=0.0, le=1.0)

    def table(self) -> FloatArray:
        return np.array([getattr(self, m) for m in MATERIALS])


@dataclass(frozen=True, slots=True)
class SensorModel:
    """The emulated sensor's physics; :data:`SENSOR_PRESETS` by name, every figure a key."""

    preset: str = _f("os0-64-rev7", "the sensor this starts from (keys given override it)")
    ideal: bool = _f(False, "one exact pencil ray per pixel, no noise, fixed reach (the "
                     "emulator's exact geometry)")
    divergence_h_deg: float = _f(0.35, "beam divergence, horizontal (FWHM)", ge=0.0, le=5.0)
    divergence_v_deg: float = _f(0.35, "beam divergence, vertical (FWHM)", ge=0.0, le=5.0)
    footprint: Literal["adaptive", "edges", "full", "off"] = _f(
        "adaptive", "where to sample the footprint: 'adaptive' where it can straddle an "
        "edge (along the row at a vertical one, fastest), 'edges' the same pixels with "
        "the whole grid (as 'full' to the range quantum), 'full' everywhere, 'off' never")
    footprint_samples: int = _f(
        2, "footprint samples per FWHM, out to one FWHM each side (horizontally at least "
        "every column: the neighbouring columns' own rays are samples)", ge=1, le=16)
    range_resolution_m: float = _f(
        0.3, "hits closer in range than this merge into one echo (Isaac Sim's "
        "minDistBetweenEchos; no Ouster figure found)", gt=0.0, le=10.0)
    min_range_m: float = _f(0.5, "returns nearer than this are not reported", ge=0.0,
                            le=10.0)
    firmware: Literal["2.0", "2.1", "2.2", "2.3", "2.4", "2.5", "3.0", "3.1"] = _f(
        "3.1", "the firmware the sensor runs (protocols.ouster.FIRMWARES): the profiles it "
        "has, its packet footer (a CRC from 2.5), its revision strings and, before 3.0, the "
        "legacy flat metadata file")
    return_order: Literal["STRONGEST_TO_WEAKEST", "NEAREST_TO_FARTHEST",
                          "FARTHEST_TO_NEAREST"] = _f(
        "STRONGEST_TO_WEAKEST", "which echo is the first return")
    signal_multiplier: float = _f(1.0, "the sensor's signal_multiplier: 0.25, 0.5, 1, 2 or 3 "
                                  "(reach x multiplier^0.25)", ge=0.25, le=3.0)
    reach_10pct_m: float = _f(35.0, "a 10 % lambertian target is detected to here with "
                              "detection_probability (1024x10, 1x, 100 klx)", gt=0.0, le=500.0)
    reach_80pct_m: float = _f(75.0, "the datasheet's reach for 80 % (reported beside the "
                              "model's, which follows 1/r^2 from reach_10pct_m)", gt=0.0,
                              le=500.0)
    detection_probability: float = _f(0.9, "detection probability at the reach", gt=0.5,
                                      le=0.999)
    detection_width: float = _f(
        0.45, "spread of the detection threshold in log signal (rev6's 10 % target: 90 % "
        "at 15 m, 50 % at 20 m)", gt=0.0, le=3.0)
    reach_factor_5120: float = _f(1.19, "reach factor of 512x10 (5120 columns a second)",
                                  gt=0.0, le=3.0)
    reach_factor_10240: float = _f(1.0, "reach factor of 1024x10 and 512x20", gt=0.0, le=3.0)
    reach_factor_20480: float = _f(0.84, "reach factor of 2048x10 and 1024x20", gt=0.0,
                                   le=3.0)
    range_sigma_m: float = _f(0.10, "range noise (1 sigma) at the median detection threshold "
                              "(OS1 datasheet: 10 cm at SNR 12)", ge=0.0, le=1.0)
    range_sigma_exponent: float = _f(0.625, "noise falls as signal^-exponent (fit to the OS1 "
                                     "datasheet's 1.5/3/10 cm at SNR 250/100/12)", ge=0.0,
                                     le=2.0)
    range_sigma_min_m: float = _f(0.003, "range noise (1 sigma) of strong returns (a real "
                                  "OS0-128's, fw 3.0.1: 3.1 mm frame to frame at SIGNAL "
                                  "> 1000; see the README)", ge=0.0, le=1.0)
    false_positive_rate: float = _f(1e-4, "ambient false returns per pixel and frame (OS1 "
                                    "datasheet: 1/10,000 at 100 klx)", ge=0.0, le=0.1)
    ambient: float = _f(1200.0, "NEAR_IR counts of a reflectance-1 surface in daylight",
                        ge=0.0, le=65535.0)
    reflectance: Reflectance = field(default_factory=Reflectance,
                                     metadata={"doc": "reflectance by material"})

    def reach_factor(self, mode: str) -> float:
        cps = MODE_COLUMNS_PER_S.get(mode, 10240)
        return {5120: self.reach_factor_5120, 10240: self.reach_factor_10240}.get(
            cps, self.reach_factor_20480)


SIGNAL_MULTIPLIERS = (0.25, 0.5, 1.0, 2.0, 3.0)
_REV7 = SensorModel()
SENSOR_PRESETS: dict[str, SensorModel] = {
    "os0-64-rev7": _REV7,
    "os0-64-rev6": replace(_REV7, preset="os0-64-rev6", min_range_m=0.3, reach_10pct_m=15.0,
                           reach_80pct_m=45.0),
    "ideal": replace(_REV7, preset="ideal", ideal=True, footprint="off", min_range_m=0.3,
                     false_positive_rate=0.0, range_sigma_m=0.0, range_sigma_min_m=0.0),
}
DEFAULT_SENSOR = "os0-64-rev7"


@dataclass(frozen=True)
class Surfaces:
    """What a scene tells about the primitives its casts hit (``prim``: a triangle ``>= 0``,
    -1 a miss, ``-2 - j`` the round curve segment ``j`` where the scene has curves): the
    stem id by primitive, triangles first, then the curve segments last to first, then -1
    for the miss (so a negative ``prim`` indexes from the end); the triangles' unit normals;
    the material index (:data:`MATERIALS`) in the stem id's order; and its casts answering
    primitives, returning the distance, the primitive and the curve hits' |cos incidence|
    (an empty array where the scene has no curves): ``cast`` spread over threads as the
    backend does, ``cast1`` on the calling thread."""

    stem_of_prim: NDArray[np.int32]  # (n + m + 1,)
    normals: NDArray[np.float32]  # (n, 3)
    material_of_prim: NDArray[np.uint8]  # (n + m + 1,), ground last (unused: misses)
    cast: Any
    cast1: Any


def _gauss(x: Any) -> FloatArray:
    """A Gaussian of FWHM 1, 1 at 0."""
    return np.exp(-4.0 * math.log(2.0) * x * x)


@dataclass(frozen=True)
class FootprintGrid:
    """Where the footprint is sampled: a lattice fixed to the sensor, horizontally every
    ``step`` radians (the column spacing over a power of two ``sub``, no wider than FWHM /
    ``samples``: "virtual columns", ``sub`` to a column), vertically in rows every FWHM /
    ``samples`` about each beam. A pixel's samples are the lattice's rays about its own:
    its row out to one FWHM each side, and the rows above and below out to half the FWHM
    (and as far sideways: the corners beyond carry under 1 % of the beam each). A lattice
    ray is cast once a frame, when a pixel needs it, and serves every pixel whose footprint
    reaches it; those of the centre row on a column are the centre rays themselves, cast
    already (in 2048x10 a stem's side costs no ray at all). Slots: the centre, the row's
    others (``row_j`` virtual columns away), the other rows' (``grid_j``, ``grid_i``).
    ``weights[flags]``: each slot's share of the beam's energy, the Gaussian's, for a pixel
    sampled along its row (flag 1: the rows above and below taken as the centre row) or
    over the grid (flag 3). The Gaussian is separable, and every row takes the centre
    row's horizontal profile; the other rows' corners beyond half the FWHM sideways (under
    1 % of the beam each) are not cast but taken as the centre row's sample of the same
    column, so a vertical edge (a stem's side) splits the beam between its objects in the
    same shares whether the row or the grid is sampled."""

    step: float
    sub: int
    reach: int  # columns either side a horizontal edge can be seen from
    rows: int  # V: rows either side
    b_step: float  # radians between rows
    row_j: NDArray[np.int64]
    grid_j: NDArray[np.int64]
    grid_i: NDArray[np.int64]
    weights: FloatArray  # (4, slots)

    @classmethod
    def of(cls, samples: int, fwhm_h: float, fwhm_v: float, columns: int) -> FootprintGrid:
        spacing = 2.0 * math.pi / columns
        sub = 1
        while fwhm_h > 0 and spacing / sub > fwhm_h / samples * 1.01 and sub < 64:
            sub *= 2
        step = spacing / sub
        J = math.floor(fwhm_h * 1.01 / step + 1e-9) if fwhm_h > 0 else 0
        V = max(1, samples // 2) if fwhm_v > 0 else 0
        js = np.array([j for j in range(-J, J + 1) if j], np.int64)
        ch = _gauss(np.arange(-J, J + 1) * step / fwhm_h) if J else np.ones(1)
        ch /= ch.sum()
        rv = _gauss(np.arange(-V, V + 1) / samples) if V else np.ones(1)
        rv /= rv.sum()
        Jv = min(J, math.floor(fwhm_h * 0.505 / step + 1e-9)) if fwhm_h > 0 else 0
        ii, jj = np.meshgrid([i for i in range(-V, V + 1) if i], np.arange(-Jv, Jv + 1),
                             indexing="ij")
        K = 1 + len(js) + ii.size
        w = np.zeros((4, K))
        w[1, 0], w[1, 1:1 + len(js)] = ch[J], np.delete(ch, J)
        # the centre row: its share of the beam; beyond Jv sideways, the whole column's
        # (the other rows' corners there are taken as the centre row's sample)
        col = np.where(np.abs(np.arange(-J, J + 1)) <= Jv, rv[V], 1.0) * ch
        w[3, 0], w[3, 1:1 + len(js)] = col[J], np.delete(col, J)
        w[3, 1 + len(js):] = (rv[ii + V] * ch[jj + J]).reshape(-1)
        w[2] = w[3]
        w[0, 0] = 1.0
        return cls(step, sub, max(1, -(-J // sub)), V, fwhm_v / samples, js,
                   jj.reshape(-1).astype(np.int64), ii.reshape(-1).astype(np.int64), w)

    def needed(self, idx: NDArray[np.intp], fl: NDArray[np.uint8], W: int, H: int,
               kernels: Any = None, run: Any = None, cast: NDArray[np.intp] | None = None
               ) -> tuple[NDArray[np.intp], NDArray[np.int32]]:
        """The lattice rays the flagged pixels ``idx`` (flags ``fl``) sample and that are
        not centre rays, as flat lattice indices ((virtual column x H + beam) x (2 rows +
        1) + row + rows), in order, less those ``cast`` already (lattice indices); and the
        position of each by lattice index in ``cast`` followed by that list (-1: not cast).
        ``kernels``/``run``: marked by the compiled kernel over threads."""
        S, V = self.sub, self.rows
        WS, NR = W * S, 2 * V + 1
        need, pos = _lattice_scratch(WS * H * NR)
        try:
            return self._needed(idx, fl, W, H, kernels, run, cast, need, pos)
        except BaseException:
            need[:] = False
            pos[:] = -1
            _SCRATCH.touched = []
            raise

    def _needed(self, idx: NDArray[np.intp], fl: NDArray[np.uint8], W: int, H: int,
                kernels: Any, run: Any, cast: NDArray[np.intp] | None, need: NDArray[np.bool_],
                pos: NDArray[np.int32]) -> tuple[NDArray[np.intp], NDArray[np.int32]]:
        S, V = self.sub, self.rows
        WS, NR = W * S, 2 * V + 1
        if S == 1:  # a row's samples are all centre rays: only the grid's are cast
            grid = (fl & 2) != 0
            idx, fl = idx[grid], fl[grid]
        if kernels is not None and run is not None:
            run(kernels.mark_lattice, [(idx, fl, self.row_j, self.grid_j, self.grid_i, S, V,
                                        W, H, a, b, need) for a, b in _parts(len(idx), 1, 8)])
        else:
            c, h = idx // H, idx % H
            for bit, jl, il in ((1, self.row_j, np.zeros(len(self.row_j), np.int64)),
                                (2, self.grid_j, self.grid_i)):
                sel = (fl & bit) != 0
                for j, i in zip(jl.tolist(), il.tolist(), strict=True):
                    if i == 0 and j % S == 0:
                        continue  # a centre ray
                    x = (c[sel] * S + j) % WS
                    need[(x * H + h[sel]) * NR + i + V] = True
        n0 = 0
        if cast is not None:
            need[cast] = False
            n0 = len(cast)
        ent = np.flatnonzero(need)
        need[ent] = False  # all clear again for the next frame
        touched = [ent]
        if cast is not None:
            pos[cast] = np.arange(n0, dtype=np.int32)
            touched.append(cast)
        pos[ent] = np.arange(n0, n0 + len(ent), dtype=np.int32)
        _SCRATCH.touched = touched
        return ent, pos


_SCRATCH = threading.local()
"""A thread's lattice buffers (:func:`_lattice_scratch`), and the entries of ``pos`` the
last :meth:`FootprintGrid.needed` set (``touched``)."""


def _lattice_scratch(size: int) -> tuple[NDArray[np.bool_], NDArray[np.int32]]:
    """This thread's ``need`` (all False) and ``pos`` (all -1) of ``size`` lattice slots for
    :meth:`FootprintGrid.needed`: kept from frame to frame (megabytes a frame, written in
    a few places) and cleared where the last frame wrote them; the ``pos`` the last call
    returned is this one, so a caller reads it before the thread's next call."""
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None or len(bufs[0]) != size:
        bufs = _SCRATCH.bufs = (np.zeros(size, bool), np.full(size, -1, np.int32))
        _SCRATCH.touched = []
    for at in _SCRATCH.touched:
        bufs[1][at] = -1
    _SCRATCH.touched = []
    return bufs



@dataclass(frozen=True)
class _Frame:
    """What the phases of :meth:`Physics.respond` share about one frame's cast."""

    o: NDArray[np.float32]  # (W, 3) each column's origin
    d: NDArray[np.float32]  # (N, 3) column-major ray directions
    cast: Any  # float32 rays -> (distance, primitive or stem id, the curve hits' |cos|)
    n_m: float
    run: Callable[[Any, list[tuple[Any, ...]]], None]  # fn over calls, spread over threads
    k: Any  # the compiled kernels, or None
    surf: bool  # the scene tells primitives (surfaces)
    sop: Any  # the surfaces' stem of each primitive
    mop: Any  # and material
    nrm: Any  # and normal
    parts: list[tuple[int, int]]  # the frame's pixels in parts, whole columns


class Physics:
    """A :class:`SensorModel` prepared for one sensor mode and pixel grid (see the module
    doc): ``shape`` (W, H), ``row_step`` (H - 1,) the column of beam h + 1's pixel nearest
    in angle to column 0's of beam h (from the metadata's pixel shifts), ``quantum_mm`` the
    profile's range quantum."""

    R_NEAR = 0.5  # signal stops growing nearer than this (the receiver saturates)
    ORDERS: ClassVar[dict[str, int]] = {o: k for k, o in enumerate(RETURN_ORDERS)}

    def __init__(self, model: SensorModel, mode: str, carried_m: float,
                 shape: tuple[int, int] = (1024, 64), row_step: Any = None,
                 quantum_mm: int = 1) -> None:
        self.model = m = model
        self.refl = m.reflectance.table()
        if m.signal_multiplier not in SIGNAL_MULTIPLIERS:
            raise ValueError(f"signal_multiplier {m.signal_multiplier}: the sensor takes "
                             f"{', '.join(f'{v:g}' for v in SIGNAL_MULTIPLIERS)}")
        # reach goes as the mode's factor and multiplier^(1/4) (Ouster's table), and as
        # sqrt(signal) for a target filling the beam (1/r^2)
        gain = m.reach_factor(mode) ** 2 * math.sqrt(m.signal_multiplier)
        # scale: the signal of a 10 % target square on at the reach (1024x10, 1x) sits
        # where the detection probability is detection_probability
        z = _norm_ppf(m.detection_probability)
        self.threshold = 1.0  # signal units: the threshold's median
        s_reach = math.exp(z * m.detection_width)  # a 10 % target at the reach
        self.scale = s_reach * m.reach_10pct_m ** 2 / 0.1
        self.gain = gain
        self.sg = self.scale * self.gain
        self.carried_m = carried_m
        self.shape = shape
        H = shape[1]
        self.row_step = (np.zeros(H - 1, np.int64) if row_step is None
                         else np.asarray(row_step, np.int64))
        self.quantum_mm = quantum_mm
        self.grid = FootprintGrid.of(m.footprint_samples, math.radians(m.divergence_h_deg),
                                     math.radians(m.divergence_v_deg), shape[0])
        # photons: SIGNAL written as counts; one signal unit at the threshold is this many
        self.photons = 5.0  # SIGNAL counts per threshold unit: see the README (anecdotal)
        self.far_m = min(carried_m, m.reach_80pct_m * math.sqrt(gain) * 1.5)
        self.jit = True  # the compiled kernels (numba), where they can be had
        self.last_flagged = 0  # pixels supersampled in the last frame
        self.last_cast = 0  # and the sub-rays cast for them
        self.last_probed = 0  # of which probes of vertical edges
        self.last_flags = np.zeros(shape, np.uint8)  # (W, H): 1 the row sampled, 3 the grid
        self._turns: tuple[float, int] | None = None  # the first frame's column and row turns

    # ---- the reach this model gives ---------------------------------------------------
    def reach_m(self, reflectance: float, probability: float = 0.5) -> float:
        """Range at which a square-on target of this reflectance is detected with this
        probability."""
        z = _norm_ppf(probability)
        s = math.exp(z * self.model.detection_width)
        return math.sqrt(self.scale * self.gain * reflectance / s)

    # ---- one frame -------------------------------------------------------------------
    def respond(self, o: NDArray[np.float32], d: NDArray[np.float32], t: FloatArray,
                prim: NDArray[np.int32], surfaces: Surfaces | None, cast: Any, n_m: float,
                rng: np.random.Generator, dual: bool,
                run: Callable[[Any, list[tuple[Any, ...]]], None] | None = None,
                centre: tuple[Any, ...] | None = None,
                cn: NDArray[np.float32] | None = None) -> dict[str, Any]:
        """The frame's returns from the centre cast: ``o`` (W, 3) each column's origin (every
        beam of a column starts there), ``d`` (N, 3) column-major ray directions,
        ``t`` (N,) distances (inf: a miss), ``prim`` (N,) the primitive hit (or the stem id
        where the scene tells no primitives, ``surfaces`` None) and ``cn`` (N,) the curve
        hits' |cos incidence| (where the scene has curves); ``cast`` casts float32 rays
        to (distance, primitive or stem id as ``prim``, the curve hits' |cos|);
        ``run(fn, calls)`` calls ``fn(*c)`` for each of ``calls``, spread over threads
        (here, by default); ``centre``: the centre rays' echoes where the cast made them
        already (``ss, r, e, nir``, as :func:`~emulators.lidar._footprint.centre_echoes`
        writes them; ``t`` and ``prim`` are then not read).
        Returns the pixel words as (H, W) uint32 images ``RANGE`` (mm, 0 none), ``SIGNAL``,
        ``REFLECTIVITY``, ``NEAR_IR`` and, with ``dual``, ``RANGE2``, ``SIGNAL2``,
        ``REFLECTIVITY2``; and the stem ids (W, H) ``sid`` (-1 none) and ``sid2``."""
        W, H = self.shape
        N = W * H
        if run is None:
            def run(fn: Any, calls: list[tuple[Any, ...]]) -> None:
                for c in calls:
                    fn(*c)
        sop, mop, nrm = ((surfaces.stem_of_prim, surfaces.material_of_prim, surfaces.normals)
                         if surfaces is not None else _NO_SURFACES)
        f = _Frame(o, d, cast, n_m, run, _kernels() if self.jit else None,
                   surfaces is not None, sop, mop, nrm, _parts(N, H, 8))
        keys = rng.bit_generator.random_raw(2)  # 0. before anything: the rng's order (the
        # draws of detection and noise of each return, by pixel: pixel_uniforms)
        ss, r, e, nir = self._centre_echoes(f, t, prim, cn, centre)  # 1.
        e1, r1, s1 = e, r, ss  # the first return: the centre's, changed where sampled
        e2, r2, s2 = ((np.zeros(N), np.full(N, np.inf), np.full(N, -1, np.int32)) if dual
                      else (np.empty(0), np.empty(0), np.empty(0, np.int32)))
        flags, lat = self._flag_footprint(f, ss)  # 2. where the footprint can straddle an edge
        idx = np.flatnonzero(flags.reshape(-1) != 0)
        self.last_flagged = len(idx)
        self.last_flags = flags
        self.last_cast = self.last_probed
        if len(idx):
            echoes = self._sample_footprint(f, idx, flags, lat, ss, r, e)
            # the centre's no longer read: the sampled pixels' echoes go in its place
            e1[idx], r1[idx], s1[idx] = echoes[:3]
            if dual:
                e2[idx], r2[idx], s2[idx] = echoes[3:]
        # 3. detection, noise, the words; then ambient false returns where none was detected
        out, flat = self._detect_words(f, nir, ((e1, r1, s1), (e2, r2, s2)), keys, dual)
        self._false_returns(flat, rng)
        return out

    def _centre_echoes(self, f: _Frame, t: FloatArray, prim: NDArray[np.int32],
                       cn: NDArray[np.float32] | None, centre: tuple[Any, ...] | None
                       ) -> tuple[Any, ...]:
        """The centre rays' echoes ``ss, r, e, nir`` (or as the cast made them)."""
        if centre is not None:
            return centre
        N = self.shape[0] * self.shape[1]
        ss, r, e = np.empty(N, np.int32), np.empty(N), np.empty(N)
        nir = np.empty(N, np.uint32)
        cn0 = cn if cn is not None else np.zeros(0, np.float32)
        m = self.model
        if f.k is not None:
            f.run(f.k.centre_echoes, [(prim, cn0, t, f.d, f.sop, f.mop, f.nrm, self.refl,
                                       f.surf, f.n_m, self.R_NEAR, m.ambient, a, b, ss, r, e,
                                       nir) for a, b in f.parts])
        else:
            self._centre_np(prim, cn0, t, f.d, f.sop, f.mop, f.nrm, f.surf, f.n_m, ss, r, e,
                            nir)
        return ss, r, e, nir

    def _flag_footprint(self, f: _Frame, ss: NDArray[np.int32]
                        ) -> tuple[NDArray[np.uint8], list[tuple[Any, ...]]]:
        """Which pixels' footprints are sampled (W, H): 1 the row, 3 the grid; and the
        lattice rays cast to probe vertical edges (``ent, oo, dd, ts, ps``)."""
        m, g = self.model, self.grid
        W, H = self.shape
        flags = np.zeros((W, H), np.uint8)
        if m.footprint == "full":
            flags[:] = 3
        elif m.footprint in ("adaptive", "edges"):
            every = m.footprint == "edges"
            # the next beam's pixels about the nearest in angle: within the row's reach
            # (one FWHM sideways) for adaptive, the three nearest for edges
            vw = 1 if every else g.reach
            if f.k is not None:
                f.run(f.k.flag_edges, [(ss.reshape(W, H), self.row_step, g.reach, vw, every,
                                        a, b, flags) for a, b in _parts(W, 1, 8, H)])
            else:
                self._flag_np(ss.reshape(W, H), g.reach, vw, every, flags)
        if g.weights.shape[1] == 1:
            flags[:] = 0
        if self._turns is None:  # which way columns and beams go: the sensor's, for good
            self._turns = (_column_turn(f.d, W, H), _row_turn(f.d, W, H, self.row_step))
        self.last_probed = 0
        lat: list[tuple[Any, ...]] = []  # lattice rays cast: (ent, oo, dd, ts, ps)
        if g.rows and m.footprint == "adaptive":
            self._probe_edges(f, ss, flags, lat)
        if self.last_probed == 0:  # vertical edges not probed (no rows, edges): the grid
            flags[(flags & 6) != 0] = 3
        if m.footprint == "edges":  # the grid, not the row, at a vertical edge too
            flags[flags == 1] = 3
        return flags, lat

    def _probe_edges(self, f: _Frame, ss: NDArray[np.int32], flags: NDArray[np.uint8],
                     lat: list[tuple[Any, ...]]) -> None:
        """A vertical edge lies somewhere in the 1.4 degrees to the next beam: probe the
        footprint's outer row on the edge's side, and sample the grid only where a probe
        sees another object than the centre (most see the same: the edge passes beyond the
        footprint)."""
        g = self.grid
        W, H = self.shape
        assert self._turns is not None
        turn, down = self._turns[0], self._turns[1] * g.rows  # down: the row to beam h + 1
        NR = 2 * g.rows + 1
        fv = flags.reshape(-1)
        if f.k is not None:  # the same, compiled
            ent_p, who = np.empty(2 * len(fv), np.int64), np.empty(2 * len(fv), np.int64)
            pv = np.empty(len(fv), np.int64)
            n, m = f.k.probe_entries(fv, H, g.sub, g.rows, down, ent_p, who, pv)
            if not m:
                return
            ent_p, who, pv = ent_p[:n], who[:n], pv[:m]
            hits = self._lattice_cast(f.o, f.d, ent_p, W, H, turn, f.cast, f.k, f.run)
            lat.append((ent_p, *hits))
            f.k.probe_verdicts(fv, pv, who, ss, hits[2], hits[3], f.sop, f.surf)
            self.last_probed = len(ent_p)
            return
        pv = np.flatnonzero((fv & 6) != 0)
        if not len(pv):
            return
        sides = fv[pv]
        has2 = (sides & 2) != 0
        has4 = (sides & 4) != 0
        base = ((pv // H) * g.sub * H + pv % H) * NR + g.rows
        ent_p = np.concatenate([base[has2] + down, base[has4] - down])
        who = np.concatenate([np.flatnonzero(has2), np.flatnonzero(has4)])
        o_p = np.argsort(ent_p, kind="stable")
        ent_p, who = ent_p[o_p], who[o_p]
        hits = self._lattice_cast(f.o, f.d, ent_p, W, H, turn, f.cast, f.k, f.run)
        lat.append((ent_p, *hits))
        pr = hits[3]
        sid_p = f.sop[pr] if f.surf else pr  # -1 (and a curve's -2 - j) from the end
        sid_p = np.where(np.isfinite(hits[2]), sid_p, -1)
        differs = np.zeros(len(pv), bool)
        differs[who[sid_p != ss[pv[who]]]] = True
        fv[pv] = np.where(differs, 3, fv[pv] & 1)
        self.last_probed = len(ent_p)

    def _sample_footprint(self, f: _Frame, idx: NDArray[np.intp], flags: NDArray[np.uint8],
                          lat: list[tuple[Any, ...]], ss: NDArray[np.int32], r: FloatArray,
                          e: FloatArray) -> tuple[Any, ...]:
        """The flagged pixels' echoes from their footprint's sub-rays: ``e1 r1 s1 e2 r2 s2``
        of ``idx``."""
        m, g = self.model, self.grid
        W, H = self.shape
        assert self._turns is not None
        fl = flags.reshape(-1)[idx]
        M = len(idx)
        echoes = (np.empty(M), np.empty(M), np.empty(M, np.int32), np.empty(M),
                  np.empty(M), np.empty(M, np.int32))  # e1 r1 s1 e2 r2 s2 of idx
        ent, pos = g.needed(idx, fl, W, H, f.k, f.run, lat[0][0] if lat else None)
        self.last_cast += len(ent)
        lat.append((ent, *self._lattice_cast(f.o, f.d, ent, W, H, self._turns[0], f.cast,
                                             f.k, f.run)))
        dd, ts, ps, cs = (np.concatenate([x[n] for x in lat]) if len(lat) > 1
                          else lat[0][n] for n in range(2, 6))
        args = ((g.weights, g.row_j, g.grid_j, g.grid_i, g.sub, g.rows, pos, H), (ss, r, e),
                (ts, ps, cs, dd), (f.sop, f.mop, f.nrm, self.refl, f.surf),
                (f.n_m, self.R_NEAR, m.range_resolution_m, self.ORDERS[m.return_order]),
                echoes)
        if f.k is not None:
            f.run(f.k.footprint_echoes, [(idx, fl, a, b, *args)
                                         for a, b in _parts(len(idx), 1, 8)])
        else:
            self._echoes_np(idx, fl, *args)
        return echoes

    def _detect_words(self, f: _Frame, nir: NDArray[np.uint32],
                      returns: tuple[tuple[Any, Any, Any], ...], keys: NDArray[np.uint64],
                      dual: bool) -> tuple[dict[str, Any], dict[str, Any]]:
        """Detection, noise and the pixel words of each return: the (H, W) images (views of
        column-major (W, H) arrays, as the packets hold them) and the flat words."""
        m = self.model
        W, H = self.shape
        N = W * H
        q = self.quantum_mm
        out: dict[str, Any] = {"NEAR_IR": nir.reshape(W, H).T}
        flat: dict[str, Any] = {}
        # above s_sure ln(s) / width > 9.5, more than any draw under 9; above s_floor the
        # noise is sigma_min: neither is computed there (the same bits)
        s_sure = math.exp(9.5 * m.detection_width)
        s_floor = ((m.range_sigma_m / m.range_sigma_min_m) ** (1.0 / m.range_sigma_exponent)
                   * 1.001 if m.range_sigma_min_m > 0 and m.range_sigma_exponent > 0
                   else math.inf)
        for n_ret, (ee, rr, sd) in enumerate(returns):
            if n_ret == 1 and not dual:
                break
            words = [np.empty(N, np.uint32) for _ in range(3)]
            sid_out = np.empty(N, np.int32)
            echo = (ee, rr, sd, keys[n_ret])
            consts: tuple[Any, ...] = (
                self.scale, self.gain, self.sg, m.detection_width, s_sure,
                m.range_sigma_min_m, m.range_sigma_m, m.range_sigma_exponent, s_floor,
                m.min_range_m, self.carried_m, self.photons, self.R_NEAR, q)
            out_words = (*words, sid_out)
            if f.k is not None:
                f.run(f.k.detect, [(echo, a, b, consts, out_words) for a, b in f.parts])
            else:
                self._detect_np(echo, consts, out_words)
            sfx = "2" if n_ret else ""
            for name, w in zip(("RANGE", "SIGNAL", "REFLECTIVITY"), words, strict=True):
                flat[name + sfx] = w
                out[name + sfx] = w.reshape(W, H).T
            out["sid" + sfx] = sid_out.reshape(W, H)
        return out, flat

    def _false_returns(self, flat: dict[str, Any], rng: np.random.Generator) -> None:
        """Ambient false returns, where no return was detected (in place, in ``flat``)."""
        m = self.model
        if m.false_positive_rate <= 0:
            return
        q = self.quantum_mm
        empty = np.flatnonzero(flat["RANGE"] == 0)
        n_fp = int(rng.binomial(len(empty), m.false_positive_rate))
        if n_fp:
            at = empty[rng.choice(len(empty), n_fp, replace=False)]
            lo = max(m.min_range_m, 0.0)
            rf = lo + rng.random(n_fp) * (self.far_m - lo)
            rn = np.maximum(rf, self.R_NEAR)
            for name, v in (("RANGE", np.rint(rf * (1000.0 / q)) * q),
                            ("SIGNAL", np.full(n_fp, min(self.threshold * self.photons,
                                                         65535.0))),
                            ("REFLECTIVITY", np.clip(np.rint(
                                self.threshold * (rn * rn) / self.sg * 100.0), 0.0, 255.0))):
                flat[name][at] = v.astype(np.uint32)

    def _lattice_cast(self, o: NDArray[np.float32], d: NDArray[np.float32],
                      ent: NDArray[np.intp], W: int, H: int, turn: float, cast: Any,
                      k: Any, run: Any) -> tuple[NDArray[np.float32], NDArray[np.float32],
                                                 FloatArray, NDArray[np.int32],
                                                 NDArray[np.float32]]:
        """The lattice rays ``ent`` (flat lattice indices, see :meth:`FootprintGrid.needed`)
        made and cast: their origins, directions, distances, primitives hit and the curve
        hits' |cos incidence| (empty where the cast tells none)."""
        g = self.grid
        n_sub = len(ent)
        oo = np.empty((n_sub, 3), np.float32)
        dd = np.empty((n_sub, 3), np.float32)
        NR = 2 * g.rows + 1
        xs, rest = np.divmod(ent, H * NR)
        pix = (xs // g.sub) * H + rest // NR
        ra = (xs % g.sub) * (g.step * turn)
        rb = (rest % NR - g.rows) * g.b_step
        if k is not None:
            run(k.lattice_rays, [(o, d, pix, ra, rb, a, b, oo, dd)
                                 for a, b in _parts(n_sub, 1, 8)])
        else:
            self._rays_np(o, d, pix, ra, rb, oo, dd)
        res: tuple[Any, ...] = (cast(oo, dd) if n_sub
                                else (np.empty(0), np.empty(0, np.int32)))
        ts, ps = res[0], res[1]
        cs = res[2] if len(res) > 2 else np.zeros(0, np.float32)
        return (oo, dd, np.ascontiguousarray(ts, np.float64),
                np.ascontiguousarray(ps, np.int32), np.ascontiguousarray(cs, np.float32))

    # ---- the numpy path: what the kernels of emulators.lidar._footprint compute -------
    def _centre_np(self, prim: NDArray[np.int32], cn: NDArray[np.float32], t: FloatArray,
                   d: NDArray[np.float32], sop: Any, mop: Any, nrm: Any, surf: bool,
                   n_m: float, ss: Any, r: Any, e: Any, nir: Any) -> None:
        sid, mt, cos = _surface_np(prim, cn, d, sop, mop, nrm, surf)
        hit = np.isfinite(t) & (sid >= 0)
        rr = np.where(hit, t + n_m, np.inf)
        rn = np.maximum(rr, self.R_NEAR)
        ss[:] = np.where(hit, sid, -1)
        r[:] = rr
        e[:] = np.where(hit, self.refl[mt] * cos / (rn * rn), 0.0)
        amb = self.model.ambient
        nir[:] = np.where(hit, np.minimum(amb * self.refl[mt], 65535.0),
                          min(amb * 0.05, 65535.0))

    def _flag_np(self, ss: NDArray[np.int32], reach: int, vw: int, every: bool,
                 out: NDArray[np.uint8]) -> None:
        W, H = ss.shape
        for j in range(1, reach + 1):
            edge = ss != np.roll(ss, -j, axis=0)  # column c against c + j
            out[edge] |= 1
            out[np.roll(edge, j, axis=0)] |= 1
        cols = (np.arange(W)[:, None] + self.row_step[None, :]) % W  # (W, H - 1)
        beams = np.broadcast_to(np.arange(1, H)[None, :], cols.shape)
        lo, hi = ss[:, :-1], ss[cols, beams]  # beam h, and h + 1 nearest in angle
        n_up = sum((lo != ss[(cols + k) % W, beams]).astype(np.int64)
                   for k in range(-vw, vw + 1))
        n_dn = sum((hi != np.roll(ss, -k, axis=0)[:, :-1]).astype(np.int64)
                   for k in range(-vw, vw + 1))
        full = 2 * vw + 1
        up = (n_up > 0) if every else (n_up == full)
        down = (n_dn > 0) if every else (n_dn == full)
        out[:, :-1][up] |= 2
        out[cols[down], beams[down]] |= 4

    def _rays_np(self, o: NDArray[np.float32], d: NDArray[np.float32], pix: NDArray[np.intp],
                 ra: FloatArray, rb: FloatArray, oo: NDArray[np.float32],
                 dd: NDArray[np.float32]) -> None:
        dx = d[pix].astype(np.float64)
        ex = np.stack([-dx[:, 1], dx[:, 0], np.zeros(len(dx))], axis=1)  # horizontal, ⟂ d
        nn = np.sqrt(ex[:, 0] * ex[:, 0] + ex[:, 1] * ex[:, 1] + ex[:, 2] * ex[:, 2])
        ex[nn < 1e-9] = (1.0, 0.0, 0.0)
        nn = np.maximum(np.sqrt(ex[:, 0] * ex[:, 0] + ex[:, 1] * ex[:, 1]
                                + ex[:, 2] * ex[:, 2]), 1e-12)
        ex /= nn[:, None]
        fx = np.stack([dx[:, 1] * ex[:, 2] - dx[:, 2] * ex[:, 1],
                       dx[:, 2] * ex[:, 0] - dx[:, 0] * ex[:, 2],
                       dx[:, 0] * ex[:, 1] - dx[:, 1] * ex[:, 0]], axis=1)
        v = (dx + ra[:, None] * ex) + rb[:, None] * fx
        n = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
        dd[:] = v / n[:, None]
        oo[:] = o[pix // (len(d) // len(o))]

    def _echoes_np(self, idx: NDArray[np.intp], fl: NDArray[np.uint8],
                   grid: tuple[Any, ...], centre: tuple[Any, ...], lattice: tuple[Any, ...],
                   surfaces: tuple[Any, ...], consts: tuple[Any, ...],
                   out: tuple[Any, ...]) -> None:
        """:func:`~emulators.lidar._footprint.footprint_echoes` in numpy, the same groups."""
        wt, row_j, grid_j, grid_i, S, V, pos, H = grid
        ss, r, e = centre
        ts, ps, cs, dd = lattice
        sop, mop, nrm, refl, surf = surfaces
        n_m, r_near, resolution, order = consts
        e1, r1, s1, e2, r2, s2 = out
        K = wt.shape[1]
        M = len(idx)
        W = len(ss) // H
        WS, NR = W * S, 2 * V + 1
        w = wt[fl]  # (M, K)
        rk = np.full((M, K), np.inf)
        ek = np.zeros((M, K))
        sk = np.full((M, K), -1, np.int32)
        c, h = idx // H, idx % H
        # each slot's sample: a centre ray (the pixel's own, a neighbouring column's) or a
        # lattice ray cast this frame
        src = np.full((M, K), -1, np.intp)
        row = np.full((M, K), -1, np.intp)
        src[:, 0] = idx
        slots = [(1, j, 0) for j in row_j.tolist()] + \
            [(2, j, i) for j, i in zip(grid_j.tolist(), grid_i.tolist(), strict=True)]
        for kk, (bit, j, i) in enumerate(slots, start=1):
            on = (fl & bit) != 0
            x = (c * S + j) % WS
            if i == 0 and j % S == 0:
                src[:, kk] = np.where(on, (x // S) * H + h, -1)
            else:
                row[:, kk] = np.where(on, pos[(x * H + h) * NR + i + V], -1)
        use = src >= 0
        sr = np.where(use, src, 0)
        hit = use & (ss[sr] >= 0)
        rk = np.where(hit, r[sr], rk)
        with np.errstate(invalid="ignore"):
            ek = np.where(hit, w * e[sr], ek)
        sk = np.where(hit, ss[sr], sk)
        at = np.flatnonzero(row.reshape(-1) >= 0)
        if len(at):
            rw = row.reshape(-1)[at]
            sid, mt, cos = _surface_np(ps[rw], cs[rw] if len(cs) else cs, dd[rw], sop, mop,
                                       nrm, surf)
            tt = ts[rw]
            ok = np.isfinite(tt) & (sid >= 0)
            rr = np.where(ok, tt + n_m, np.inf)
            rn2 = np.maximum(rr, r_near)
            rk.reshape(-1)[at] = rr
            ek.reshape(-1)[at] = np.where(ok, w.reshape(-1)[at] * refl[mt] * cos / (rn2 * rn2),
                                          0.0)
            sk.reshape(-1)[at] = np.where(ok, sid, -1)
        # a footprint one object fills (every sample it takes hits the centre's object)
        # answers as its centre ray does
        filled = np.all(~(use | (row >= 0)) | (sk == ss[idx][:, None]), axis=1) \
            & (ss[idx] >= 0)
        # echoes: sort by range, split where the gap exceeds the range resolution
        srt = np.argsort(rk, axis=1, kind="stable")
        rk = np.take_along_axis(rk, srt, 1)
        ek = np.take_along_axis(ek, srt, 1)
        sk = np.take_along_axis(sk, srt, 1)
        new = np.ones((M, K), bool)
        with np.errstate(invalid="ignore"):  # inf - inf: misses, each its own "echo"
            new[:, 1:] = ~(np.diff(rk, axis=1) <= resolution)
        group = np.cumsum(new, axis=1) - 1  # echo index within the pixel
        flat = (np.arange(M)[:, None] * K + group).reshape(-1)
        valid = np.isfinite(rk).reshape(-1)
        ge = np.zeros(M * K)
        ger = np.zeros(M * K)
        np.add.at(ge, flat[valid], ek.reshape(-1)[valid])  # in order: as the kernel sums
        np.add.at(ger, flat[valid], (ek * np.where(np.isfinite(rk), rk, 0.0)).reshape(-1)[valid])
        # each echo's stem id: that of its strongest hit, the nearest on a tie
        best = np.full(M * K, -1.0)
        np.maximum.at(best, flat[valid], ek.reshape(-1)[valid])
        is_best = valid & (ek.reshape(-1) == best[flat]) & (ek.reshape(-1) > 0)
        gs = np.full(M * K, -1, np.int32)
        gs[flat[is_best][::-1]] = sk.reshape(-1)[is_best][::-1]
        ge2, ger2, gs2 = ge.reshape(M, K), ger.reshape(M, K), gs.reshape(M, K)
        with np.errstate(invalid="ignore", divide="ignore"):
            gr = np.where(ge2 > 0, ger2 / np.where(ge2 > 0, ge2, 1.0), np.inf)
        if order == 0:
            key = -ge2
        elif order == 1:
            key = np.where(ge2 > 0, gr, np.inf)
        else:
            key = np.where(ge2 > 0, -gr, np.inf)
        rank = np.argsort(key, axis=1, kind="stable")[:, :2]
        rows = np.arange(M)[:, None]
        for n_ret, (ea, ra, sa) in enumerate(((e1, r1, s1), (e2, r2, s2))):
            pick = rank[:, n_ret:n_ret + 1]
            ea[:], ra[:], sa[:] = ge2[rows, pick][:, 0], gr[rows, pick][:, 0], \
                gs2[rows, pick][:, 0]
            f_at = idx[filled]
            ea[filled], ra[filled], sa[filled] = ((e[f_at], r[f_at], ss[f_at]) if n_ret == 0
                                                  else (0.0, np.inf, -1))

    def _detect_np(self, echo: tuple[Any, ...], model: tuple[Any, ...],
                   words: tuple[Any, ...]) -> None:
        """:func:`~emulators.lidar._footprint.detect` in numpy, the same groups."""
        from emulators.lidar._footprint import pixel_normals_np  # (imports numba: not at once)

        e, r, sid, key = echo
        u, z = pixel_normals_np(key, len(e))
        (scale, gain, sg, width, s_sure, sigma_min, sigma0, exponent, _s_floor, min_r, max_r,
         photons, r_near, q) = model
        w_range, w_signal, w_refl, sid_out = words
        s = e * scale * gain
        with np.errstate(divide="ignore"):
            ls = np.log(np.where(s > 0, s, 1.0))
        ok = (s > 0) & ((s > s_sure) | (ls / width > u))
        sigma = np.maximum(sigma_min, sigma0 * np.where(ok, s, 1.0) ** -exponent)
        rr = np.where(ok, r + z * sigma, 0.0)
        ok &= (rr >= min_r) & (rr <= max_r)
        rn = np.maximum(rr, r_near)
        w_range[:] = np.where(ok, np.rint(rr * (1000.0 / q)) * q, 0.0)
        w_signal[:] = np.where(ok, np.minimum(s * photons, 65535.0), 0.0)
        w_refl[:] = np.where(ok, np.minimum(np.maximum(np.rint(s * (rn * rn) / sg * 100.0),
                                                       0.0), 255.0), 0.0)
        sid_out[:] = np.where(ok, sid, -1)


_NO_SURFACES = (np.full(1, -1, np.int32), np.zeros(1, np.uint8), np.zeros((1, 3), np.float32))


def _column_turn(d: NDArray[np.float32], W: int, H: int) -> float:
    """+1 where the next column lies along the rays' horizontal perpendicular ``(-dy, dx,
    0)`` (turning left), -1 where it lies the other way (the OS0's columns turn right),
    from this frame's centre rays: the median over the beams of one column pair."""
    a = d.reshape(W, H, 3)[0].astype(np.float64)
    b = d.reshape(W, H, 3)[1 % W].astype(np.float64)
    side = -a[:, 1] * b[:, 0] + a[:, 0] * b[:, 1]
    return 1.0 if float(np.median(side)) >= 0.0 else -1.0


def _row_turn(d: NDArray[np.float32], W: int, H: int, step: NDArray[np.int64]) -> int:
    """+1 where the next beam's pixel nearest in angle lies along the lattice's vertical
    ``rb`` (the perpendicular to the ray with z >= 0: up), -1 where it lies below (the
    OS0's beams count downwards), from this frame's centre rays: the median over the
    beam pairs of column 0."""
    dd = d.reshape(W, H, 3)
    if H < 2:
        return -1
    c2 = step % W
    dz = dd[c2, np.arange(1, H), 2].astype(np.float64) - dd[0, :-1, 2].astype(np.float64)
    return 1 if float(np.median(dz)) > 0.0 else -1


PART_MIN = 4096  # items: fewer go in one part (handing a part to a thread costs ~40 us)


def _parts(n: int, align: int, k: int, size: int = 1) -> list[tuple[int, int]]:
    """``n`` items (of ``size`` pixels each) in up to ``k`` contiguous parts, each a
    multiple of ``align`` long and, but for the last, at least :data:`PART_MIN` pixels."""
    units = -(-n // align)
    step = max(1, -(-units // k), -(-PART_MIN // (align * size))) * align
    return [(a, min(a + step, n)) for a in range(0, n, step)]


def _surface_np(prim: NDArray[np.int32], cn: NDArray[np.float32], d: NDArray[np.float32],
                sop: Any, mop: Any, nrm: Any, surf: bool
                ) -> tuple[NDArray[np.int32], NDArray[np.intp], FloatArray]:
    """Stem id, material index and |cos incidence| of each hit (-1: none; ``-2 - j`` curve
    segment ``j``, its |cos| in ``cn``, which may be empty where there is none)."""
    if not surf:
        sid = prim.astype(np.int32)
        return sid, np.where(sid > 0, 1, 0), np.ones(len(sid))
    if len(nrm):
        n = nrm[np.maximum(prim, 0)].astype(np.float64)
        dd = d.astype(np.float64)
        cos = np.abs(n[:, 0] * dd[:, 0] + n[:, 1] * dd[:, 1] + n[:, 2] * dd[:, 2])
        cos[prim == -1] = 0.0  # nothing hit (the compiled kernels' value)
    else:  # no triangles
        cos = np.zeros(len(prim))
    curve = prim < -1
    if curve.any():
        cos = np.where(curve, cn.astype(np.float64) if len(cn) else 0.0, cos)
    return sop[prim], mop[prim].astype(np.intp), np.minimum(cos, 1.0)


class _Kernels:
    def __init__(self, mod: Any) -> None:
        from emulators.jit import compiled

        for name in ("centre_echoes", "flag_edges", "probe_entries", "probe_verdicts",
                     "mark_lattice", "lattice_rays", "footprint_echoes", "detect"):
            setattr(self, name, compiled(getattr(mod, name)))

    centre_echoes: Any
    flag_edges: Any
    probe_entries: Any
    probe_verdicts: Any
    mark_lattice: Any
    lattice_rays: Any
    footprint_echoes: Any
    detect: Any


_kernels_built: list[_Kernels | None] = []


def _kernels() -> _Kernels | None:
    """The compiled kernels of :mod:`emulators.lidar._footprint`, or None where compiled
    kernels are off (numba missing, ``TCF_HIL_NO_JIT``)."""
    from emulators.jit import jit_enabled

    if not jit_enabled():
        return None
    if not _kernels_built:
        from emulators.lidar import _footprint

        _kernels_built.append(_Kernels(_footprint))
    return _kernels_built[0]


def _norm_ppf(p: float) -> float:
    """The standard normal quantile (bisection on erf: exact enough for a calibration)."""
    lo, hi = -10.0, 10.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if 0.5 * (1.0 + math.erf(mid / math.sqrt(2.0))) < p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
