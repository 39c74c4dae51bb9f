"""Everything of a natural stand that is not a stem: branches, foliage, understory, dead
wood, stumps and boulders, as triangles with a material and an object id.

**Object ids** (what the lidar emulator reports per return, and what per-component return
counts are kept by): 0 the ground; 1..n the stems (with their second leaders and second
stems); n+1..2n tree i's branches (id n + i); 2n+1..3n tree i's foliage; after 3n one id per
understory plant, dead-wood log, stump and boulder (:attr:`Scenery.component_of_id`).

**Branches** are straight cones (exact with two rings), from the stem's centre line out,
in whorls on conifers (spacing, count and angle by species: :mod:`~.species`), living in the
crown (longest at its base on conifers, a cone; birch's crown an ellipsoid) and dead stubs
below it. A branch is cut short where it would come within the clearance of another tree's
stem.

**Foliage** is a turbid medium: porous crowns (a cone on conifers, an ellipsoid on birch,
and the saplings' and shrubs' crowns), each with the extinction coefficient sigma = STAR *
total leaf area / crown volume (total leaf area twice the one-sided area the foliage mass
and specific leaf weight give), as :class:`Foliage`. Where the ray backend casts them
(Embree bound directly: :mod:`emulators.media`), a ray draws its free path through them,
Beer-Lambert's law exp(-sigma L) as HELIOS++'s transmittive voxels draw it, but through
each crown's exact envelope; elsewhere (``stand.foliage_as = "facets"``, or open3d and
trimesh) the crowns are filled with facets, small randomly placed and oriented triangles at
N a / 2 = sigma per m^3 (a ray through them is stopped within a path L with probability
1 - exp(-N a/2 L): the same law), built only when asked for (:meth:`Scenery.facets`).
Measured on ``pine-thinning``: 3,400 crowns instead of 7.2 M facets, the same share of rays
stopped within sampling error (a test holds the two to it), the scene in 0.9 GB instead of
3.7 GB, and the cast a little faster (README).

Each object draws from its own random stream (a tree's branches, its foliage, a ground
object), so culling by ``stand.detail_range_m`` changes nothing of what it keeps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tcf_hil.world.forest import species as sp
from tcf_hil.world.forest.stems import StemSet, unit_perp

if TYPE_CHECKING:
    from emulators.media import Crowns
    from tcf_hil.world.forest.generate import Forest

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

COMPONENTS: tuple[str, ...] = ("ground", "stem", "branch", "foliage", "understory",
                               "dead_wood", "stump", "boulder")
"""Per-component return counts go by these (index = code)."""
GROUND, STEM, BRANCH, FOLIAGE, UNDERSTORY, DEAD_WOOD, STUMP, BOULDER = range(8)
# Materials as the lidar emulator numbers them (emulators.lidar MATERIALS).
MAT_GROUND, MAT_BARK, MAT_FOLIAGE, MAT_DEAD_WOOD, MAT_ROCK = 0, 1, 2, 3, 4
_CLEARANCE_M = 0.02
_BRANCH_SIDES = 5
_BOULDER_SHOWS = 0.7  # share of a boulder's height above the ground (assumption)
_SAPLING_BASE_DIAMETER_PER_M = 0.015  # a 2 m sapling is 3 cm thick at its foot (assumption)
_STREAM_SCENERY = 7


@dataclass(frozen=True)
class Rods:
    """Straight tapered rods (the branches), one per row: from ``base`` (k, 3) along the unit
    ``axis`` for ``length``, radius ``r0`` at the base and ``r1`` at the tip, an object id
    and a material each. Cast as
    round curves where the ray backend can (:meth:`curves`), else as 5-sided open cones
    (:meth:`mesh`)."""

    base: FloatArray
    axis: FloatArray
    length: FloatArray
    r0: FloatArray
    r1: FloatArray
    ids: NDArray[np.int32]
    material: NDArray[np.uint8]

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> Rods:
        z, e = np.zeros((0, 3)), np.zeros(0)
        return Rods(z, z, e, e, e, np.zeros(0, np.int32), np.zeros(0, np.uint8))

    def mesh(self) -> tuple[FloatArray, IntArray, NDArray[np.int32], NDArray[np.uint8]]:
        """Vertices, faces, and each face's object id and material: five sides, whose chord
        error 0.19 r is within 2 mm up to r = 1 cm (most branches); open ends (a branch's
        base is inside its stem and its tip is a few millimetres)."""
        v, f = cones(self.base, self.axis, self.length, self.r0, self.r1, _BRANCH_SIDES,
                     caps=False)
        per = 2 * _BRANCH_SIDES
        return v, f, np.repeat(self.ids, per), np.repeat(self.material, per)

    def curves(self) -> tuple[FloatArray, IntArray, NDArray[np.uint8]]:
        """As round linear curves: points (2k, 4) x, y, z, radius, one segment per rod
        (its first point) and no neighbours (flags 0)."""
        pts = np.empty((2 * len(self), 4))
        pts[0::2, :3] = self.base
        pts[1::2, :3] = self.base + self.length[:, None] * self.axis
        pts[0::2, 3], pts[1::2, 3] = self.r0, self.r1
        return pts, np.arange(0, 2 * len(self), 2, dtype=np.int64), np.zeros(len(self), np.uint8)


@dataclass
class Foliage:
    """Porous crowns (trees' foliage, saplings' and shrubs' crowns), one per row: their
    shapes and extinction (:class:`emulators.media.Crowns`), object ids and where each
    one's facets come from (the random stream ``part``, ``index`` of :func:`_object_rng`
    and ``count`` facets drawn in the whole envelope; a tree's ``tree`` row, whose facets
    above its broken top and inside other trees are dropped; -1 for the understory)."""

    crowns: Crowns
    ids: NDArray[np.int32]
    part: NDArray[np.int64]
    index: NDArray[np.int64]
    count: NDArray[np.int64]
    tree: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> Foliage:
        from emulators.media import Crowns

        z, e, i = np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        return Foliage(Crowns(z, z, e, e, e, np.zeros(0, np.int8), e),
                       np.zeros(0, np.int32), i, i, i, i)

    @staticmethod
    def concat(parts: list[Foliage]) -> Foliage:
        from emulators.media import Crowns

        parts = [f for f in parts if len(f)] or [Foliage.empty()]
        c = [f.crowns for f in parts]
        return Foliage(
            Crowns(*(np.concatenate([getattr(x, k) for x in c])
                     for k in ("apex", "axis", "length", "radius", "cut", "shape", "sigma"))),
            *(np.concatenate([getattr(f, k) for f in parts])
              for k in ("ids", "part", "index", "count", "tree")))


@dataclass
class Scenery:
    """Triangles in local coordinates with an object id and a material each (``tri_*``: the
    ground objects), the branches as :class:`Rods` and the foliage as porous crowns
    (:class:`Foliage`), which a ray backend that casts crowns draws as a turbid medium and
    any other as facets (:meth:`facets`); ``vertices``, ``faces``, ``face_id`` and
    ``face_material`` give it all as one mesh: the rods' cones, the triangles, the facets."""

    rods: Rods
    tri_vertices: FloatArray
    tri_faces: IntArray
    tri_id: NDArray[np.int32]
    tri_material: NDArray[np.uint8]
    component_of_id: NDArray[np.uint8]  # component code of every id 0..max
    counts: dict[str, int]  # objects drawn per kind (branches, crowns, logs, ...)
    foliage: Foliage = field(default_factory=Foliage.empty)
    _facet_maker: Any = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        """Triangles of the whole mesh (the foliage as facets, built for it: on a big stand
        that is millions; :attr:`solid_triangles` and ``len(foliage)`` cost nothing)."""
        return self.solid_triangles + len(self.facets()[1])

    def __bool__(self) -> bool:
        """A scenery is there (whatever it holds): truth must not build the facets."""
        return True

    @property
    def solid_triangles(self) -> int:
        """Triangles without the foliage: the branches meshed and the ground objects."""
        return len(self.rods) * 2 * _BRANCH_SIDES + len(self.tri_faces)

    def facets(self) -> tuple[FloatArray, IntArray, NDArray[np.int32]]:
        """The foliage as facets (built on first use): vertices, faces and object ids."""
        return self._facets

    @cached_property
    def _facets(self) -> tuple[FloatArray, IntArray, NDArray[np.int32]]:
        if self._facet_maker is None or not len(self.foliage):
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int32)
        out: tuple[FloatArray, IntArray, NDArray[np.int32]] = self._facet_maker(self)
        return out

    @cached_property
    def _mesh(self) -> tuple[FloatArray, IntArray, NDArray[np.int32], NDArray[np.uint8]]:
        v, f, ids, mat = self.rods.mesh()
        fv, ff, fid = self.facets()
        return (np.vstack([v, self.tri_vertices, fv]),
                np.vstack([f, self.tri_faces + len(v),
                           ff + len(v) + len(self.tri_vertices)]).astype(np.int64),
                np.concatenate([ids, self.tri_id, fid]).astype(np.int32),
                np.concatenate([mat, self.tri_material,
                                np.full(len(ff), MAT_FOLIAGE, np.uint8)]).astype(np.uint8))

    @property
    def vertices(self) -> FloatArray:
        return self._mesh[0]

    @property
    def faces(self) -> IntArray:
        return self._mesh[1]

    @property
    def face_id(self) -> NDArray[np.int32]:
        return self._mesh[2]

    @property
    def face_material(self) -> NDArray[np.uint8]:
        return self._mesh[3]


class _Parts:
    """Collects triangle batches."""

    def __init__(self) -> None:
        self.v: list[FloatArray] = []
        self.f: list[IntArray] = []
        self.ids: list[NDArray[np.int32]] = []
        self.mat: list[NDArray[np.uint8]] = []
        self.nv = 0

    def add(self, v: FloatArray, f: IntArray, ids: NDArray[np.int32] | int,
            mat: NDArray[np.uint8] | int) -> None:
        if len(f) == 0:
            return
        self.v.append(v)
        self.f.append(f + self.nv)
        self.ids.append(np.broadcast_to(np.asarray(ids, np.int32), (len(f),)).copy())
        self.mat.append(np.broadcast_to(np.asarray(mat, np.uint8), (len(f),)).copy())
        self.nv += len(v)


def cones(base: FloatArray, axis: FloatArray, length: FloatArray, r0: FloatArray,
          r1: FloatArray, sides: int, caps: bool = True) -> tuple[FloatArray, IntArray]:
    """Straight cones (frusta), ``sides`` sided, one per row: vertices and faces (each
    cone's rows in turn: two rings, then the two cap centres; ``caps=False``: open ends,
    for a branch whose base is inside its stem and whose tip is a few millimetres)."""
    k = len(base)
    ref = np.where(np.abs(axis[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(ref, axis)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(axis, e1)
    th = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    ring = np.cos(th)[None, :, None] * e1[:, None, :] + np.sin(th)[None, :, None] * e2[:, None, :]
    tip = base + length[:, None] * axis
    v = np.concatenate([base[:, None, :] + r0[:, None, None] * ring,
                        tip[:, None, :] + r1[:, None, None] * ring,
                        base[:, None, :], tip[:, None, :]], axis=1)  # (k, 2 sides + 2, 3)
    j = np.arange(sides)
    a0, a1 = j, (j + 1) % sides
    b0, b1 = a0 + sides, a1 + sides
    c0, c1 = 2 * sides, 2 * sides + 1
    tmpl = np.concatenate([np.stack([a0, a1, b1], -1), np.stack([a0, b1, b0], -1)]
                          + ([np.stack([np.full(sides, c0), a1, a0], -1),
                              np.stack([np.full(sides, c1), b0, b1], -1)] if caps else []))
    per = 2 * sides + 2
    faces = (tmpl[None, :, :] + (np.arange(k) * per)[:, None, None]).reshape(-1, 3)
    return v.reshape(-1, 3), faces.astype(np.int64)


class Obstacles:
    """Other trees' tubes, sampled along their centre lines, to keep branches, foliage and
    ground objects clear of them."""

    def __init__(self, tubes: StemSet, owner: NDArray[np.int32], step: float = 0.15) -> None:
        # every tube sampled from its base every ``step`` to its top (np.arange's samples,
        # the last clipped to the top), all at once
        length = np.asarray(tubes.length, np.float64)
        counts = np.ceil((length + step) / step).astype(np.int64)
        idx = np.repeat(np.arange(len(tubes)), counts)
        k = np.arange(len(idx)) - np.repeat(np.cumsum(counts) - counts, counts)
        s = np.minimum(k * step, length[idx])
        self.p = tubes.centre(idx, s) if len(idx) else np.zeros((0, 3))
        self.r = tubes.radius(idx, s) if len(idx) else np.zeros(0)
        self.own = np.asarray(owner)[idx] if len(idx) else np.zeros(0, np.int32)
        self.tree = cKDTree(self.p) if len(self.p) else None
        self.r_max = float(self.r.max()) if len(self.r) else 0.0
        self.step = step

    def blocked(self, q: FloatArray, radius: FloatArray | float, me: NDArray[np.int32] | int,
                k: int = 12) -> NDArray[np.bool_]:
        """Whether points ``q`` (with their own radius) come within the clearance of a tube
        of a tree other than ``me`` (0: of any tree)."""
        out: NDArray[np.bool_] = np.zeros(len(q), dtype=bool)
        if self.tree is None or len(q) == 0:
            return out
        k = min(k, len(self.p))
        rad = np.asarray(radius, dtype=np.float64)
        # the farthest a sample can be and still block (below), a hair more
        bound = self.r_max + float(np.max(rad, initial=0.0)) + _CLEARANCE_M \
            + 0.5 * self.step + 1e-9
        # points with no sample within reach need no more: one neighbour tells, and only
        # the others are asked for k
        d1, _ = self.tree.query(q, k=1, distance_upper_bound=bound, workers=-1)
        ask = np.flatnonzero(np.isfinite(d1))
        if len(ask) == 0:
            return out
        d, j = self.tree.query(q[ask], k=k, distance_upper_bound=bound, workers=-1)
        ok = np.isfinite(d)
        jj = np.where(ok, j, 0)
        mine = np.asarray(me)
        other = (self.own[jj] != mine[ask].reshape(-1, 1) if mine.ndim
                 else self.own[jj] != mine)
        rad = rad[ask].reshape(-1, 1) if rad.ndim else rad
        # a centre-line sample stands for the stretch half a step either side of it
        near = d < self.r[jj] + rad + _CLEARANCE_M + 0.5 * self.step
        out[ask] = np.any(ok & other & near, axis=1)
        return out


def track_distance(forest: Forest, xy: FloatArray) -> FloatArray:
    """Horizontal distance of points ``xy`` from the scenario's track (every pass), from
    its path sampled every 0.25 s: the nearest sample, which over-states the distance from
    a straight stretch by at most s^2 / (8 d) for samples s apart at distance d. It decides
    which trees get their detail and is kept as it is, so that the natural stands stay as
    they were built; a stem's exact distance from a run's driven path is
    :func:`tcf_hil.world.track.distance_to_track`'s."""
    tr = forest.track()
    t = np.arange(tr.t0_ns, tr.end_ns + 1, 250_000_000, dtype=np.int64)
    pos, _ = tr.sensor_pose(t)
    d, _ = cKDTree(pos[:, :2]).query(xy)
    out: FloatArray = d
    return out


def _near_track(forest: Forest, xy: FloatArray, reach: FloatArray | float) -> NDArray[np.bool_]:
    """Which of ``xy`` (objects reaching ``reach`` from there) ``stand.detail_range_m``
    keeps."""

    rng_m = forest.scenario.stand.detail_range_m
    if rng_m <= 0.0 or len(xy) == 0:
        return np.ones(len(xy), dtype=bool)
    out: NDArray[np.bool_] = track_distance(forest, xy) - reach <= rng_m
    return out


def _object_rng(seed: int, part: int, k: int) -> np.random.Generator:
    """The draws of one object (a tree's branches, its foliage, a ground object): its own
    stream, so that what is built of the others (``stand.detail_range_m``) changes nothing
    of it."""
    return np.random.default_rng([seed, _STREAM_SCENERY, part, k])


def _branches(forest: Forest, obstacles: Obstacles, counts: dict[str, int]) -> Rods:

    assert forest.natural is not None
    st, nat = forest.stems, forest.natural
    n = len(st)
    spc = nat.species
    intact = st.taper_length if st.taper_length is not None else st.length
    h_intact = intact * st.axis[:, 2]
    cl = sp.crown_length(spc, 2.0 * st.r_bh, h_intact) / st.axis[:, 2]
    cr = sp.crown_radius(spc, 2.0 * st.r_bh)
    # crowns of suppressed stems are narrower: at most half the distance to the nearest stem
    tree = cKDTree(st.base[:, :2])
    dn, _ = tree.query(st.base[:, :2], k=2)
    cr = np.minimum(cr, np.maximum(0.3, 0.75 * dn[:, 1])) if n > 1 else cr
    crown_base = intact - cl
    rows_i, rows_s, rows_len, rows_dead, rows_ang, rows_az = [], [], [], [], [], []
    near = _near_track(forest, st.base[:, :2], cr)
    counts["trees_detailed"] = int(near.sum())
    for i in np.flatnonzero(near).tolist():
        g = _object_rng(forest.seed, 1, i)  # a tree's own draws: culling others leaves them
        L = float(st.length[i])
        spacing = float(sp.WHORL_SPACING_M[spc[i]])
        start = float(sp.DEAD_ZONE_FROM_M[spc[i]])
        if start < 0:
            start = max(0.5, float(crown_base[i]) - 1.0)
        whorls = np.arange(start + g.uniform(0.0, spacing), L - 0.2, spacing)
        if len(whorls) == 0:
            continue
        per = int(sp.BRANCHES_PER_WHORL[spc[i]])
        s = np.repeat(whorls, per)
        t = np.clip((intact[i] - s) / cl[i], 0.0, 1.0)  # 0 at the top, 1 at the crown base
        dead = s < crown_base[i]
        if spc[i] == 2:  # birch: an ellipsoid crown
            shape = np.sqrt(np.clip(1.0 - (2.0 * t - 1.0) ** 2, 0.0, 1.0))
        else:  # conifers: a cone, longest at the crown base
            shape = t
        ln = cr[i] * np.maximum(shape, 0.08) * g.uniform(0.7, 1.0, len(s))
        ln[dead] = cr[i] * g.uniform(*sp.DEAD_LENGTH_SHARE, int(dead.sum()))
        lo, hi = sp.BRANCH_ANGLE_DEG[spc[i]]
        # azimuths: a whorl's branches evenly round, the whorl turned at random
        turn = np.repeat(g.uniform(0.0, 2.0 * math.pi, len(whorls)), per)
        k_in = np.tile(np.arange(per), len(whorls))
        rows_ang.append(np.radians(lo + (hi - lo) * g.uniform(0.0, 1.0, len(s))))
        rows_az.append(turn + 2.0 * math.pi * k_in / per + g.normal(0.0, 0.25, len(s)))
        rows_i.append(np.full(len(s), i))
        rows_s.append(s)
        rows_len.append(ln)
        rows_dead.append(dead)
    if not rows_i:
        return Rods.empty()
    idx = np.concatenate(rows_i)
    s = np.concatenate(rows_s)
    ln = np.concatenate(rows_len)
    dead = np.concatenate(rows_dead)
    ang = np.concatenate(rows_ang)
    az = np.concatenate(rows_az)
    m = len(idx)
    tangent = st.tangent(idx, s)
    direction = np.cos(ang)[:, None] * tangent + np.sin(ang)[:, None] * unit_perp(tangent, az)
    base = st.centre(idx, s)
    r_stem = st.radius(idx, s)
    r0 = np.minimum(sp.BRANCH_DIAMETER_SHARE * r_stem, sp.BRANCH_DIAMETER_MAX_M / 2.0)
    r0 = np.maximum(r0, 0.002)
    ln = np.maximum(ln, r_stem + 0.05)  # out of the bark at least
    # cut where another tree's stem is in the way (samples along each branch)
    fr = np.linspace(0.15, 1.0, 7)
    q = base[:, None, :] + (ln[:, None] * fr[None, :])[:, :, None] * direction[:, None, :]
    hit = obstacles.blocked(q.reshape(-1, 3), np.repeat(r0, len(fr)),
                            np.repeat(idx + 1, len(fr)).astype(np.int32)).reshape(m, len(fr))
    first_hit = np.where(hit.any(axis=1), hit.argmax(axis=1), len(fr))
    keep_frac = np.where(first_hit == 0, 0.0, fr[np.maximum(first_hit - 1, 0)])
    keep_frac = np.where(first_hit == len(fr), 1.0, keep_frac)
    ln = ln * keep_frac
    ok = ln > r_stem + 0.03
    counts["branches_cut"] = int(np.count_nonzero(keep_frac < 1.0))
    idx, base, direction, ln, r0, dead = idx[ok], base[ok], direction[ok], ln[ok], r0[ok], dead[ok]
    counts["branches"] = len(idx)
    counts["dead_branches"] = int(np.count_nonzero(dead))
    return Rods(base, direction, ln, r0, np.full(len(r0), 0.002),
                (n + idx + 1).astype(np.int32), np.full(len(idx), MAT_BARK, np.uint8))


def _facets(centres: FloatArray, edge: float, rng: np.random.Generator
            ) -> tuple[FloatArray, IntArray]:
    """Equilateral triangles of side ``edge`` about each centre, randomly oriented."""
    m = len(centres)
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    u = unit_perp(nrm, rng.uniform(0.0, 2.0 * math.pi, m))
    w = np.cross(nrm, u)
    rad = edge / math.sqrt(3.0)
    v = np.stack([centres + rad * (math.cos(a) * u + math.sin(a) * w)
                  for a in (0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0)], axis=1)
    return v.reshape(-1, 3), np.arange(3 * m, dtype=np.int64).reshape(m, 3)


def facet_density(sigma: FloatArray | float, edge: float) -> FloatArray | float:
    """Facets per m^3 that give extinction ``sigma`` (1/m): N a / 2 = sigma, a the facet's
    one-sided area (a randomly oriented flat facet's mean silhouette is half its area)."""
    area = math.sqrt(3.0) / 4.0 * edge**2
    return np.asarray(sigma) * 2.0 / area


def crown_points(rng: np.random.Generator, apex: FloatArray, axis: FloatArray,
                 length: float, radius: float, shape: str, count: int) -> FloatArray:
    """``count`` points uniform in a crown envelope below ``apex`` along ``-axis``: a cone
    (widest at its base) or an ellipsoid."""
    out = np.zeros((0, 3))
    need = count
    e1 = unit_perp(axis[None, :], np.zeros(1))[0]
    e2 = np.cross(axis, e1)
    while need > 0:
        m = max(64, int(need * 2.2))
        z = rng.uniform(0.0, 1.0, m)  # 0 apex, 1 base
        x, y = rng.uniform(-1.0, 1.0, (2, m))
        rr = np.hypot(x, y)
        if shape == "cone":
            inside = rr <= z
        else:
            inside = rr**2 + (2.0 * z - 1.0) ** 2 <= 1.0
        p = (apex[None, :] - (z * length)[:, None] * axis[None, :]
             + (radius * x)[:, None] * e1[None, :] + (radius * y)[:, None] * e2[None, :])
        out = np.vstack([out, p[inside][:need]])
        need = count - len(out)
    return out


def _foliage(forest: Forest, counts: dict[str, int], edge: float) -> Foliage:
    """The trees' crowns near the track (``stand.detail_range_m``), with their extinction."""
    from emulators.media import CONE, ELLIPSOID, Crowns

    assert forest.natural is not None
    st, nat = forest.stems, forest.natural
    n = len(st)
    spc = nat.species
    intact = st.taper_length if st.taper_length is not None else st.length
    dbh = 2.0 * st.r_bh
    h = intact * st.axis[:, 2]
    cl = sp.crown_length(spc, dbh, h) / st.axis[:, 2]
    cr = sp.crown_radius(spc, dbh)
    tree = cKDTree(st.base[:, :2])
    if n > 1:
        dn, _ = tree.query(st.base[:, :2], k=2)
        cr = np.minimum(cr, np.maximum(0.3, 0.75 * dn[:, 1]))
    # SLW is per one-sided (projected, hemi-surface) leaf area; STAR is silhouette over
    # total (all-sided) area, twice that (the flat leaf's STAR 0.25 then gives G = 0.5)
    area = 2.0 * sp.foliage_mass_kg(spc, dbh, h) * 1000.0 / sp.SLW_G_M2[spc]
    volume = np.where(spc == 2, 4.0 / 3.0 * math.pi * cr**2 * cl / 2.0,
                      math.pi * cr**2 * cl / 3.0)
    sigma = sp.STAR[spc] * area / volume
    want = np.rint(np.asarray(facet_density(sigma, edge)) * volume).astype(np.int64)
    idx = np.flatnonzero((want > 0) & _near_track(forest, st.base[:, :2], cr))
    apex = st.centre(idx, intact[idx])
    # a broken top keeps the crown below its break (none where it broke below the crown)
    cut = np.maximum(0.0, np.einsum("ij,ij->i", apex - st.base[idx], st.axis[idx])
                     - st.length[idx])
    left = cut < cl[idx]
    idx, apex, cut = idx[left], apex[left], cut[left]
    crowns = Crowns(apex, -st.axis[idx], cl[idx], cr[idx], cut,
                    np.where(spc[idx] == 2, ELLIPSOID, CONE).astype(np.int8), sigma[idx])
    counts["foliage_crowns"] = len(idx)
    if n:
        counts["foliage_sigma_median_per_m_x1000"] = round(1000 * float(np.median(sigma)))
    return Foliage(crowns, (2 * n + idx + 1).astype(np.int32), np.full(len(idx), 2, np.int64),
                   idx.astype(np.int64), want[idx], idx.astype(np.int64))


def _facet_maker(forest: Forest, edge: float) -> Any:
    """The function that draws a scenery's foliage as facets: each crown's own stream
    draws ``count`` points in its whole envelope and a facet about each; a tree's facets
    above its broken top or within ``edge``/2 of another tree's tubes are dropped."""
    from emulators.media import ELLIPSOID


    def make(sc: Scenery) -> tuple[FloatArray, IntArray, NDArray[np.int32]]:
        fol, st = sc.foliage, forest.stems
        c = fol.crowns
        v_all, ids_all, cen_all, own_all = [], [], [], []
        for j in range(len(fol)):
            g = _object_rng(forest.seed, int(fol.part[j]), int(fol.index[j]))
            shape = "ellipsoid" if c.shape[j] == ELLIPSOID else "cone"
            p = crown_points(g, c.apex[j], -c.axis[j], float(c.length[j]),
                             float(c.radius[j]), shape, int(fol.count[j]))
            v, _ = _facets(p, edge, g)  # every facet drawn, then those kept
            i = int(fol.tree[j])
            keep = (np.einsum("ij,j->i", p - st.base[i], st.axis[i]) <= st.length[i]
                    if i >= 0 else np.ones(len(p), bool))
            cen_all.append(p[keep])
            v_all.append(v.reshape(-1, 3, 3)[keep])
            ids_all.append(np.full(int(keep.sum()), fol.ids[j], np.int32))
            own_all.append(np.full(int(keep.sum()), i + 1, np.int32))  # 0: the understory's
        if not v_all:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int32)
        tri, ids, own = np.concatenate(v_all), np.concatenate(ids_all), np.concatenate(own_all)
        tree = own > 0
        clear = np.ones(len(tri), bool)
        if tree.any():
            clear[tree] = ~forest.obstacles().blocked(np.vstack(cen_all)[tree], edge / 2.0,
                                                      own[tree])
        tri, ids = tri[clear], ids[clear]
        sc.counts["foliage_facets"] = int(np.count_nonzero(ids <= 3 * len(st)))
        sc.counts["understory_facets"] = int(np.count_nonzero(ids > 3 * len(st)))
        return (tri.reshape(-1, 3), np.arange(3 * len(tri), dtype=np.int64).reshape(-1, 3),
                ids)

    return make


@dataclass
class GroundObjects:
    """Understory plants, lying logs, stumps and boulders: one row each, ids from 3n + 1 in
    this order (saplings, shrubs, logs, stumps, boulders)."""

    kind: list[str]  # "sapling", "shrub", "dead_wood", "stump", "boulder"
    base: FloatArray  # (k, 3): foot (sapling, shrub, stump, boulder centre) or a log's end
    tip: FloatArray  # (k, 3): top (sapling, shrub, stump, boulder top) or the log's other end
    radius: FloatArray  # (k,): base radius, crown/shrub radius, log radius, semi-axis
    species: IntArray  # (k,): saplings' species code, else -1
    first_id: int

    def __len__(self) -> int:
        return len(self.kind)

    def records(self, origin: FloatArray) -> list[dict[str, object]]:
        """Ground-truth rows: id, kind, and the shape in world coordinates."""
        out: list[dict[str, object]] = []
        for k, kind in enumerate(self.kind):
            row: dict[str, object] = {"id": self.first_id + k, "kind": kind}
            b = np.round(self.base[k] + origin, 4).tolist()
            t = np.round(self.tip[k] + origin, 4).tolist()
            r = round(float(self.radius[k]), 4)
            if kind == "dead_wood":
                row.update(ends=[b, t], diameter_m=round(2 * r, 4),
                           volume_m3=round(math.pi * r * r * float(np.linalg.norm(
                               self.tip[k] - self.base[k])), 5))
            elif kind == "boulder":
                c = self.tip[k] - np.array([0.0, 0.0, 0.6 * float(self.radius[k])])
                row.update(centre=np.round(c + origin, 4).tolist(), semi_axis_m=r,
                           height_m=round(float(self.tip[k, 2] - self.base[k, 2]), 4))
            else:
                row.update(base=b, height_m=round(float(self.tip[k, 2] - self.base[k, 2]), 4),
                           **({"diameter_m": round(2 * r, 4)} if kind == "stump" else
                              {"radius_m": r}))
                if self.species[k] >= 0:
                    row["species"] = sp.SPECIES[int(self.species[k])]
            out.append(row)
        return out


def _road_test(forest: Forest) -> Any:
    """A test of (x, y) points: on a strip road (within half a metre of its edge)."""
    from tcf_hil.world.forest.placement import region_for

    reg = region_for(forest.scenario)

    def on_road(xy: FloatArray) -> NDArray[np.bool_]:
        inside = np.zeros(len(xy), dtype=bool)
        for lo, hi in reg.cuts:
            inside |= (xy[:, reg.axis] >= lo - 0.5) & (xy[:, reg.axis] <= hi + 0.5)
        return inside

    return on_road


def _free_spots(forest: Forest, rng: np.random.Generator, count: int, clearance: float,
                obstacles: Obstacles, off_roads: bool) -> FloatArray:
    """Up to ``count`` (x, y) uniform in the plot, clear of every stem by ``clearance`` (and
    of the strip roads, ``off_roads``)."""

    w, h = forest.scenario.plot.size_m
    road = _road_test(forest)
    out = np.zeros((0, 2))
    for _ in range(20):
        need = count - len(out)
        if need <= 0:
            break
        xy = rng.uniform((-w / 2, -h / 2), (w / 2, h / 2), (2 * need + 16, 2))
        if off_roads:
            xy = xy[~road(xy)]
        z = forest.terrain.height(xy[:, 0], xy[:, 1])
        q = np.column_stack([xy, z + 0.3])
        xy = xy[~obstacles.blocked(q, clearance, 0)]
        out = np.vstack([out, xy[:need]])
    return out


def ground_objects(forest: Forest, obstacles: Obstacles | None = None) -> GroundObjects:
    """Draw the stand's understory, dead wood, stumps and boulders (own random stream)."""

    assert forest.natural is not None
    cfg = forest.scenario.stand
    rng = np.random.default_rng([forest.seed, _STREAM_SCENERY, 3])
    w, h = forest.scenario.plot.size_m
    ha = w * h / 10_000.0
    if obstacles is None:
        obstacles = forest.obstacles()
    terrain = forest.terrain
    kinds: list[str] = []
    base, tip, rad, spc = [], [], [], []

    def ground(xy: FloatArray) -> FloatArray:
        return np.column_stack([xy, terrain.height(xy[:, 0], xy[:, 1])])

    # saplings
    xy = _free_spots(forest, rng, round(cfg.saplings_per_ha * ha), 0.15, obstacles, True)
    g = ground(xy)
    hh = rng.uniform(*cfg.sapling_height_m, len(g))
    shares = np.array([getattr(cfg, n).share for n in sp.SPECIES])
    species = rng.choice(3, size=len(g), p=shares / shares.sum()) if len(g) else \
        np.zeros(0, np.int64)
    kinds += ["sapling"] * len(g)
    base.append(g)
    tip.append(g + np.column_stack([np.zeros((len(g), 2)), hh]))
    rad.append(_SAPLING_BASE_DIAMETER_PER_M * hh / 2.0)
    spc.append(species.astype(np.int64))
    # shrubs
    xy = _free_spots(forest, rng, round(cfg.shrubs_per_ha * ha), 0.3, obstacles, True)
    g = ground(xy)
    hh = rng.uniform(*cfg.shrub_height_m, len(g))
    kinds += ["shrub"] * len(g)
    base.append(g)
    tip.append(g + np.column_stack([np.zeros((len(g), 2)), hh]))
    rad.append(rng.uniform(0.5, 1.0, len(g)) * np.maximum(hh, 0.3))
    spc.append(np.full(len(g), -1, np.int64))
    # lying dead wood, up to the volume asked for
    want = cfg.dead_wood_m3_per_ha * ha
    vol = 0.0
    logs_b, logs_t, logs_r = [], [], []
    tries = 0
    road = _road_test(forest)
    while vol < want and tries < 2_000:
        tries += 1
        r = rng.uniform(*cfg.dead_wood_diameter_m) / 2.0
        ln = rng.uniform(*cfg.dead_wood_length_m)
        c = _free_spots(forest, rng, 1, r + 0.1, obstacles, True)
        if not len(c):
            continue
        ang = rng.uniform(0.0, math.pi)
        d = np.array([math.cos(ang), math.sin(ang)]) * ln / 2.0
        ends = np.array([c[0] - d, c[0] + d])
        e3 = ground(ends) + np.array([0.0, 0.0, r])
        samples = e3[0] + np.linspace(0.0, 1.0, 9)[:, None] * (e3[1] - e3[0])
        if obstacles.blocked(samples, r, 0).any() or road(samples[:, :2]).any():
            continue
        if np.any(np.abs(samples[:, :2]) > np.array([w / 2, h / 2])):
            continue
        logs_b.append(e3[0])
        logs_t.append(e3[1])
        logs_r.append(r)
        vol += math.pi * r * r * float(np.linalg.norm(e3[1] - e3[0]))
    kinds += ["dead_wood"] * len(logs_r)
    base.append(np.array(logs_b).reshape(-1, 3))
    tip.append(np.array(logs_t).reshape(-1, 3))
    rad.append(np.array(logs_r))
    spc.append(np.full(len(logs_r), -1, np.int64))
    # stumps: stump diameter 2 + 1.25 DBH cm (Laasasenaho 1975), DBH as the stand's
    xy = _free_spots(forest, rng, round(cfg.stumps_per_ha * ha), 0.3, obstacles, False)
    g = ground(xy)
    from tcf_hil.world.forest.dbh import draw_dbh

    d = draw_dbh(forest.scenario.stems.dbh, len(g), rng)
    kinds += ["stump"] * len(g)
    base.append(g)
    tip.append(g + np.column_stack([np.zeros((len(g), 2)),
                                    rng.uniform(*cfg.stump_height_m, len(g))]))
    rad.append((0.02 + 1.25 * d) / 2.0)
    spc.append(np.full(len(g), -1, np.int64))
    # boulders: an ellipsoid, 30 % of its height sunk
    xy = _free_spots(forest, rng, round(cfg.boulders_per_ha * ha), 0.9, obstacles, True)
    g = ground(xy)
    a = rng.uniform(*cfg.boulder_radius_m, len(g))
    kinds += ["boulder"] * len(g)
    base.append(g)  # the ground under its centre, and its top: 70 % of its 1.2 a height
    tip.append(g + np.column_stack([np.zeros((len(g), 2)), _BOULDER_SHOWS * 1.2 * a]))
    rad.append(a)
    spc.append(np.full(len(g), -1, np.int64))
    return GroundObjects(kinds, np.vstack(base), np.vstack(tip), np.concatenate(rad),
                         np.concatenate(spc), 3 * len(forest.stems) + 1)


def _ground_meshes(forest: Forest, go: GroundObjects, parts: _Parts, comp: list[int],
                   counts: dict[str, int], edge: float) -> Foliage:
    """The ground objects near the track as triangles, and the saplings' and shrubs'
    crowns."""
    from emulators.media import CONE, ELLIPSOID, Crowns
    from tcf_hil.world.forest.mesh import sides_for

    cfg = forest.scenario.stand
    tol = forest.scenario.stems.tolerance_mm / 1000.0
    up = np.array([0.0, 0.0, 1.0])
    near = _near_track(forest, go.base[:, :2], np.linalg.norm(go.tip - go.base, axis=1)
                       + go.radius)
    counts["ground_objects_culled"] = int(np.count_nonzero(~near))
    crowns: list[tuple[FloatArray, float, float, int, int, int, int]] = []
    for k, kind in enumerate(go.kind):
        oid = go.first_id + k
        if not near[k]:
            comp.append({"sapling": UNDERSTORY, "shrub": UNDERSTORY, "dead_wood": DEAD_WOOD,
                         "stump": STUMP}.get(kind, BOULDER))
            continue
        b, t, r = go.base[k], go.tip[k], float(go.radius[k])
        rng = _object_rng(forest.seed, 4, k)
        if kind in ("sapling", "shrub"):
            comp.append(UNDERSTORY)
            hgt = float(t[2] - b[2])
            if kind == "sapling":
                v, f = cones(b[None, :] - 0.1 * up, up[None, :], np.array([hgt + 0.1]),
                             np.array([r]), np.array([0.001]), 5)
                parts.add(v, f, oid, MAT_BARK)
                crown_r, crown_l, shape = 0.25 * hgt, 0.8 * hgt, "cone"
                apex = t
            else:
                crown_r, crown_l, shape = r, hgt, "ellipsoid"
                apex = t
            vol = (math.pi * crown_r**2 * crown_l / 3.0 if shape == "cone"
                   else 4.0 / 3.0 * math.pi * crown_r**2 * crown_l / 2.0)
            m = round(float(facet_density(cfg.understory_sigma_per_m, edge)) * vol)
            if m:  # its facets, where asked for, from its own stream (its crown's points)
                crowns.append((apex, crown_l, crown_r, ELLIPSOID if shape != "cone" else CONE,
                               oid, k, m))
        elif kind in ("dead_wood", "stump"):
            comp.append(DEAD_WOOD if kind == "dead_wood" else STUMP)
            if kind == "stump":
                b = b - 0.2 * up
            ax = t - b
            ln = float(np.linalg.norm(ax))
            n_sides = sides_for(r, 0.75 * tol)
            v, f = cones(b[None, :], (ax / ln)[None, :], np.array([ln]), np.array([r]),
                         np.array([r]), n_sides)
            parts.add(v, f, oid, MAT_DEAD_WOOD)
        else:
            comp.append(BOULDER)
            sph = trimesh.creation.icosphere(subdivisions=2)
            turn = rng.uniform(0.0, 2.0 * math.pi)
            squash = np.array([r, r * rng.uniform(0.6, 1.0), 0.6 * r])
            v = sph.vertices * squash
            c, s_ = math.cos(turn), math.sin(turn)
            v = v @ np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]]) + (t - 0.6 * r * up)
            parts.add(v, np.asarray(sph.faces, np.int64), oid, MAT_ROCK)
    for kind in ("sapling", "shrub", "dead_wood", "stump", "boulder"):
        counts[kind + "s" if not kind.endswith("d") else kind] = go.kind.count(kind)
    counts["understory_crowns"] = len(crowns)
    if not crowns:
        return Foliage.empty()
    k_ = len(crowns)
    apex = np.array([c[0] for c in crowns], np.float64).reshape(k_, 3)
    sigma = np.full(k_, float(cfg.understory_sigma_per_m))
    return Foliage(
        Crowns(apex, np.tile([0.0, 0.0, -1.0], (k_, 1)), np.array([c[1] for c in crowns]),
               np.array([c[2] for c in crowns]), np.zeros(k_),
               np.array([c[3] for c in crowns], np.int8), sigma),
        np.array([c[4] for c in crowns], np.int32), np.full(k_, 4, np.int64),
        np.array([c[5] for c in crowns], np.int64), np.array([c[6] for c in crowns], np.int64),
        np.full(k_, -1, np.int64))


def build_scenery(forest: Forest) -> Scenery:
    """The scenery of a natural forest (deterministic per scenario and seed)."""

    assert forest.natural is not None
    cfg = forest.scenario.stand
    n = len(forest.stems)
    obstacles = forest.obstacles()
    parts = _Parts()
    counts: dict[str, int] = {}
    rods = _branches(forest, obstacles, counts) if cfg.branches else Rods.empty()
    trees = _foliage(forest, counts, cfg.foliage_facet_m) if cfg.foliage else Foliage.empty()
    comp = [GROUND] + [STEM] * n + [BRANCH] * n + [FOLIAGE] * n
    go = forest.ground_objects(obstacles)
    assert go is not None
    under = _ground_meshes(forest, go, parts, comp, counts, cfg.foliage_facet_m)
    if parts.f:
        v = np.vstack(parts.v)
        f = np.vstack(parts.f)
        ids = np.concatenate(parts.ids)
        mat = np.concatenate(parts.mat)
    else:
        v, f = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        ids, mat = np.zeros(0, np.int32), np.zeros(0, np.uint8)
    return Scenery(rods, v, f, ids, mat, np.asarray(comp, np.uint8), counts,
                   Foliage.concat([trees, under]), _facet_maker(forest, cfg.foliage_facet_m))


def scenery_mesh(sc: Scenery) -> trimesh.Trimesh:
    """The scenery as one mesh with face attributes ``stem_id`` (the object id) and
    ``material``."""
    mesh = trimesh.Trimesh(sc.vertices, sc.faces, process=False)
    mesh.face_attributes["stem_id"] = sc.face_id
    mesh.face_attributes["material"] = sc.face_material.astype(np.int32)
    return mesh
