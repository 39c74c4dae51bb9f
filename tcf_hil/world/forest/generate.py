"""Synthetic forest creation (SFC): scenario + seed -> terrain, stems and exact ground truth."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from protocols.stems import QUALITY_BY_CLASS
from tcf_hil.errors import ConfigError
from tcf_hil.scenario import CLASSES, Scenario
from tcf_hil.world.forest.classes import class_counts, classify
from tcf_hil.world.forest.dbh import draw_dbh
from tcf_hil.world.forest.placement import place_stems
from tcf_hil.world.forest.species import SPECIES
from tcf_hil.world.forest.stems import (
    BREAST_HEIGHT_M,
    StemSet,
    axial_samples,
    concat_stems,
    lean_axes,
    unit_perp,
)
from tcf_hil.world.terrain import Terrain
from tcf_hil.world.track import Trajectory

if TYPE_CHECKING:
    from tcf_hil.world.forest.natural import Natural
    from tcf_hil.world.forest.scenery import GroundObjects, Scenery

FloatArray = NDArray[np.float64]

QUALITY = QUALITY_BY_CLASS
"""Paper quality codes: 1 straight, 2 curved, 3 other."""

# Independent random streams, so changing the stem count leaves the terrain alone.
_STREAM_TERRAIN, _STREAM_PLACE, _STREAM_STEMS, _STREAM_FIX = 1, 2, 3, 4
_STREAM_NATURAL, _STREAM_NATURAL_FIX = 5, 6
_CLEARANCE_M = 0.02  # stems keep at least this gap between their surfaces


NATURAL_SCHEMA_VERSION = 2
"""Ground truth of natural stands carries ``schema_version`` 2 (species, suppressed,
defects, deciding_defect); the paper's forests write version 1, which has no such key, so
their documents stay byte-identical."""
NATURAL_RULE = ("X if the stem has a crook, a fork, a broken top or a double stem, or a sweep "
                "with magnitude_m >= other_threshold_m; else C if its sweep's magnitude_m >= "
                "curve_threshold_m; else S. deciding_defect: of the defects that give the "
                "class, the lowest on the stem (none for S); a lean never decides")
NATURAL_CONVENTIONS = {
    "maxcurve": "maximum distance of the centre line from its base-to-top chord, measured "
                "on the centre line (a crook adds to the bow's sweep)",
    "defects": "[{type, height_m (above the base), magnitude_m, ...}] lowest first: sweep "
               "(the bow's deviation from its chord; per_log_cm_per_m: each log's, from "
               "the base), crook (sideways shift over length_m), fork (the second leader's "
               "diameter where it leaves; its centerline and radii), broken_top (the "
               "diameter at the break; intact_height_m), double_stem (the second stem's "
               "diameter where they part; its centerline and radii), lean (horizontal "
               "offset of the top; lean_deg)",
    "h": "vertical height from base to top (to the break of a broken top)",
}


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


@dataclass
class Forest:
    """A generated forest in local coordinates (world = local + ``scenario.plot.origin_m``)."""

    scenario: Scenario
    seed: int
    terrain: Terrain
    stems: StemSet
    classes: NDArray[np.str_]
    lean_deg: FloatArray
    natural: Natural | None = None  # species, defects and parts of a natural stand
    _volume: FloatArray | None = field(default=None, repr=False)
    _scenery: Scenery | None = field(default=None, repr=False)
    _ground: GroundObjects | None = field(default=None, repr=False)
    _obstacles: Any = field(default=None, repr=False)
    _track: Trajectory | None = field(default=None, repr=False)

    def track(self) -> Trajectory:
        """The scenario's track over this terrain (built once, when first asked for: the
        scenery of a natural stand is detailed near it)."""
        if self._track is None:
            self._track = Trajectory.from_config(self.scenario.track, self.terrain)
        return self._track

    def obstacles(self) -> Any:
        """The index of every tube (stems and their parts) that keeps branches, foliage and
        ground objects clear of other trees (built once, when first asked for)."""
        if self._obstacles is None:
            from tcf_hil.world.forest.scenery import Obstacles

            tubes, owner = self.tubes()
            self._obstacles = Obstacles(tubes, owner)
        return self._obstacles

    def ground_objects(self, obstacles: Any = None) -> GroundObjects | None:
        """Understory, lying dead wood, stumps and boulders of a natural stand (drawn when
        first asked for; None for the paper's forests). ``obstacles``: the stems' index
        (default :meth:`obstacles`)."""
        if self.natural is None:
            return None
        if self._ground is None:
            from tcf_hil.world.forest.scenery import ground_objects

            self._ground = ground_objects(self, obstacles if obstacles is not None
                                          else self.obstacles())
        return self._ground

    def scenery(self) -> Scenery | None:
        """Branches, foliage, understory, dead wood, stumps and boulders of a natural stand
        (built when first asked for; None for the paper's forests)."""
        if self.natural is None:
            return None
        if self._scenery is None:
            from tcf_hil.world.forest.scenery import build_scenery

            self._scenery = build_scenery(self)
        return self._scenery

    def tubes(self) -> tuple[StemSet, NDArray[np.int32]]:
        """Every tube of the forest (the stems, then the parts of natural stems: second
        leaders and second stems) and the stem id (1-based) each belongs to."""
        n = len(self.stems)
        ids = np.arange(1, n + 1, dtype=np.int32)
        if self.natural is None or len(self.natural.parts) == 0:
            return self.stems, ids
        nat = self.natural
        return (concat_stems(self.stems, nat.parts),
                np.concatenate([ids, (nat.part_owner + 1).astype(np.int32)]))

    @property
    def origin(self) -> FloatArray:
        return np.asarray(self.scenario.plot.origin_m, dtype=np.float64)

    @property
    def ids(self) -> NDArray[np.int64]:
        return np.arange(1, len(self.stems) + 1)

    @property
    def volume(self) -> FloatArray:
        if self._volume is None:
            self._volume = self.stems.volume()
        return self._volume

    def positions(self) -> FloatArray:
        """Stem positions (n, 3), local: centre line at breast height in x, y; ground z."""
        n = len(self.stems)
        if n == 0:
            return np.zeros((0, 3))
        c = self.stems.centre(np.arange(n), np.full(n, BREAST_HEIGHT_M))
        c[:, 2] = self.stems.base[:, 2]
        return c

    def bounds(self, margin_m: float | None = None) -> tuple[float, float, float, float]:
        """Local (xmin, ymin, xmax, ymax) of the plot plus the terrain margin."""
        m = self.scenario.terrain.margin_m if margin_m is None else margin_m
        w, h = self.scenario.plot.size_m
        return (-w / 2 - m, -h / 2 - m, w / 2 + m, h / 2 + m)


def _conflicts(stems: StemSet, step: float = 0.1,
               only: NDArray[np.int64] | None = None,
               owner: NDArray[np.int64] | None = None,
               reach: FloatArray | None = None) -> list[tuple[int, int]]:
    """Pairs of stems whose surfaces come closer than the clearance (sampled centre lines).

    Args:
        only: check just the pairs that involve these stems.
        owner: the tree each tube belongs to; tubes of one tree (a stem and its second
            leader) never conflict.
        reach: :meth:`StemSet.max_reach` where the caller has it.
    """
    n = len(stems)
    if n < 2:
        return []
    reach = stems.max_reach() if reach is None else reach
    pairs = cKDTree(stems.base[:, :2]).query_pairs(2.0 * float(reach.max()) + _CLEARANCE_M,
                                                    output_type="ndarray")
    if len(pairs) == 0:
        return []
    d = np.hypot(*(stems.base[pairs[:, 0], :2] - stems.base[pairs[:, 1], :2]).T)
    pairs = pairs[d < reach[pairs[:, 0]] + reach[pairs[:, 1]] + _CLEARANCE_M]
    if only is not None:
        mark = np.zeros(n, dtype=bool)
        mark[only] = True
        pairs = pairs[mark[pairs[:, 0]] | mark[pairs[:, 1]]]
    if owner is not None:
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
    if len(pairs) == 0:
        return []
    # every stem in a pair sampled along its centre line, all at once
    used = np.unique(pairs)
    s, counts = axial_samples(-stems.below[used], stems.length[used] + step, step)
    rows = np.repeat(used, counts)
    c_all, r_all = stems.centre(rows, s), stems.radius(rows, s)
    at = np.zeros(n + 1, np.int64)
    at[used + 1] = counts
    at = np.cumsum(at)  # stem i's samples: at[i]:at[i + 1] (used stems only)
    trees: dict[int, cKDTree] = {}

    out = []
    for i, j in pairs.tolist():
        ci, ri = c_all[at[i]:at[i + 1]], r_all[at[i]:at[i + 1]]
        rj = r_all[at[j]:at[j + 1]]
        tj = trees.get(j)
        if tj is None:
            tj = trees[j] = cKDTree(c_all[at[j]:at[j + 1]])
        # Radii change slowly along a stem, so the nearest sample pair decides; the extra
        # step covers the sampling gap.
        dist, k = tj.query(ci, distance_upper_bound=float(ri.max() + rj.max()) + 1.0)
        hit = np.isfinite(dist)
        if np.any(dist[hit] < ri[hit] + rj[k[hit]] + _CLEARANCE_M + step):
            out.append((i, j))
    return out


def generate_forest(scn: Scenario, seed: int | None = None) -> Forest:
    """Generate terrain and stems for ``scn``; the same scenario and seed give the same forest.

    Raises:
        ConfigError: if the stems cannot be placed as configured.
    """
    seed = scn.seed if seed is None else seed
    st = scn.stems
    terrain = Terrain.generate(scn.terrain, _rng(seed, _STREAM_TERRAIN))
    xy = place_stems(scn, _rng(seed, _STREAM_PLACE))
    n = len(xy)
    if scn.stand.kind == "natural":
        return _natural_forest(scn, seed, terrain, xy)
    rng = _rng(seed, _STREAM_STEMS)
    counts = class_counts({c: getattr(st.class_mix, c) for c in CLASSES}, n)
    classes = np.array([c for c in CLASSES for _ in range(counts[c])], dtype="<U1")
    classes = classes[rng.permutation(n)] if n else classes
    height = rng.uniform(st.height_m[0], st.height_m[1], n)
    dbh = draw_dbh(scn.stems.dbh, n, rng)
    sweep = np.zeros(n)
    for c in CLASSES:
        lo, hi = getattr(st.sweep_m, c)
        m = classes == c
        sweep[m] = rng.uniform(lo, hi, int(m.sum()))
    peak = rng.uniform(0.35, 0.65, n)
    lean = rng.uniform(st.lean_deg[0], st.lean_deg[1], n)
    lean_az = rng.uniform(0.0, 2.0 * math.pi, n)
    bend_ang = rng.uniform(0.0, 2.0 * math.pi, n)

    base = np.column_stack([xy, terrain.height(xy[:, 0], xy[:, 1])]) if n else np.zeros((0, 3))
    axis = lean_axes(lean, lean_az)
    stems = StemSet(
        base=base, axis=axis, bend=unit_perp(axis, bend_ang),
        length=height / axis[:, 2], sweep=sweep, peak=peak, r_bh=dbh / 2.0,
        r_top=np.full(n, st.top_diameter_m / 2.0), taper=np.full(n, st.taper_exponent),
        below=np.full(n, st.below_ground_m))

    # Stems never intersect: turn a conflicting stem's bend (and lean) until it is clear.
    fix = _rng(seed, _STREAM_FIX)
    changed: NDArray[np.int64] | None = None
    reach = stems.max_reach()
    for _attempt in range(40):
        bad = sorted({j for _, j in _conflicts(stems, only=changed, reach=reach)})
        if not bad:
            break
        ix = changed = np.asarray(bad)
        lean_az[ix] = fix.uniform(0.0, 2.0 * math.pi, len(ix))
        axis[ix] = lean_axes(lean[ix], lean_az[ix])
        stems.bend[ix] = unit_perp(axis[ix], fix.uniform(0.0, 2.0 * math.pi, len(ix)))
        stems.length[ix] = height[ix] / axis[ix, 2]
        reach[ix] = stems.max_reach(ix)  # the others' stay as they were
    else:
        if scn.distribution.kind == "even":
            raise ConfigError("stems.count", scn.stems.count,
                              "fewer stems for this plot (or less distribution.jitter_m, "
                              "stems.lean_deg or stems.sweep_m): stems still intersect after "
                              "40 re-draws")
        raise ConfigError("distribution.min_spacing_m", scn.distribution.min_spacing_m,
                          "a larger spacing: stems intersect after 40 re-draws "
                          "(or reduce stems.lean_deg / stems.sweep_m)")
    return Forest(scenario=scn, seed=seed, terrain=terrain, stems=stems, classes=classes,
                  lean_deg=lean)


def _natural_forest(scn: Scenario, seed: int, terrain: Terrain, xy: FloatArray) -> Forest:
    """A natural stand (:mod:`tcf_hil.world.forest.natural`) on the placed bases."""
    from tcf_hil.world.forest import natural

    n = len(xy)
    base = np.column_stack([xy, terrain.height(xy[:, 0], xy[:, 1])]) if n else np.zeros((0, 3))
    dr = natural.draw(scn, base, _rng(seed, _STREAM_NATURAL))
    fix = _rng(seed, _STREAM_NATURAL_FIX)
    changed: NDArray[np.int64] | None = None
    reach: FloatArray | None = None
    for _attempt in range(40):
        stems, parts, owner, kinds = natural.build(scn, dr)
        tubes = concat_stems(stems, parts)
        who = np.concatenate([np.arange(n), owner]).astype(np.int64)
        only = None if changed is None else np.flatnonzero(np.isin(who, changed))
        if reach is None or only is None:
            reach = tubes.max_reach()
        else:  # a redrawn tree's tubes changed; the others' are built as before
            reach[only] = tubes.max_reach(only)
        bad = sorted({int(who[j]) for _, j in _conflicts(tubes, only=only, owner=who,
                                                            reach=reach)})
        if not bad:
            break
        ix = changed = np.asarray(bad)
        dr.lean_az[ix] = fix.uniform(0.0, 2.0 * math.pi, len(ix))
        dr.bend_ang[ix] = fix.uniform(0.0, 2.0 * math.pi, len(ix))
        dr.part_az[ix] = fix.uniform(0.0, 2.0 * math.pi, len(ix))
    else:
        raise ConfigError("distribution.min_spacing_m", scn.distribution.min_spacing_m,
                          "a larger spacing: natural stems (with their second leaders and "
                          "stems) intersect after 40 re-draws (or fewer stems.count, less "
                          "stems.lean_deg or stand.defects.x_double_stem)")
    origin = np.asarray(scn.plot.origin_m, dtype=np.float64)
    defects, deciding, classes = natural.defects_of(scn, dr, stems, parts, owner, kinds, origin)
    nat = natural.Natural(species=dr.species, suppressed=dr.suppressed, defects=defects,
                          deciding=deciding, parts=parts, part_owner=owner, part_kind=kinds)
    return Forest(scenario=scn, seed=seed, terrain=terrain, stems=stems, classes=classes,
                  lean_deg=dr.lean, natural=nat)


def ground_truth(forest: Forest) -> dict[str, Any]:
    """The ground-truth document (paper's Algorithm 1 / Table 3 fields plus geometry)."""
    scn = forest.scenario
    st = forest.stems
    n = len(st)
    origin = forest.origin
    pos = forest.positions()
    # Centre lines of all stems in one vectorised pass, vertices at most 0.5 m apart.
    # Vertices at most 0.5 m apart along the arc (see StemSet.centerline).
    counts = np.maximum(2, np.ceil(st.length * st.max_speed() / 0.5).astype(np.int64) + 1)
    idx = np.repeat(np.arange(n), counts)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n else np.zeros(0, np.int64)
    frac = (np.arange(len(idx)) - np.repeat(first, counts)) / np.repeat(counts - 1, counts)
    s_all = frac * st.length[idx]
    cl_all = np.round(st.centre(idx, s_all) + origin, 4).tolist()
    r_all = np.round(st.radius(idx, s_all), 5).tolist()
    def r4(a: FloatArray) -> list[Any]:
        out: list[Any] = np.round(a, 4).tolist()
        return out

    nat = forest.natural
    h, dbh = r4(st.height), r4(2.0 * st.r_bh)
    if nat is None:
        mc = r4(st.sweep)
        # A maxcurve that rounding would carry across a class threshold is written exactly:
        # the document's class always follows its own rule applied to its own maxcurve.
        flip = classify(np.asarray(mc, dtype=np.float64), scn.stems.curve_threshold_m,
                        scn.stems.other_threshold_m) != forest.classes if n else []
        for i in np.flatnonzero(flip).tolist():
            mc[i] = float(st.sweep[i])
    else:  # measured on the centre line: a crook adds to the bow
        from tcf_hil.world.forest.natural import maxcurve

        mc = r4(maxcurve(st))
    cp, base = r4(pos + origin), r4(st.base + origin)
    d = r4(np.hypot(pos[:, 0], pos[:, 1]))
    vol: list[float] = np.round(forest.volume, 5).tolist()
    lean: list[float] = np.round(forest.lean_deg, 3).tolist()
    objects = []
    for i in range(n):
        a, b = int(first[i]), int(first[i] + counts[i])
        cls = str(forest.classes[i])
        objects.append({
            "id": i + 1, "name": f"tree_{i + 1}", "h": h[i], "dbh": dbh[i],
            "maxcurve": mc[i], "quality": QUALITY[cls], "class": cls, "cp": cp[i], "d": d[i],
            "base": base[i], "centerline": cl_all[a:b], "radii": r_all[a:b],
            "volume": vol[i], "lean_deg": lean[i],
        })
        if nat is not None:
            k = int(nat.deciding[i])
            objects[-1].update({
                "species": SPECIES[int(nat.species[i])],
                "suppressed": bool(nat.suppressed[i]), "defects": nat.defects[i],
                "deciding_defect": None if k < 0 else nat.defects[i][k]["type"]})
    doc: dict[str, Any] = {
        "timestamp": scn.timestamp,
        "total_objects_count": len(objects),
        "scenario": {"name": scn.name, "seed": forest.seed},
        "classification": {
            "classes": list(CLASSES),
            "quality_codes": QUALITY,
            "curve_threshold_m": scn.stems.curve_threshold_m,
            "other_threshold_m": scn.stems.other_threshold_m,
            "rule": "S if maxcurve < curve_threshold_m, X if maxcurve >= other_threshold_m, "
                    "else C",
        },
        "conventions": {
            "cp": "centre line at breast height (1.3 m along the stem) in x, y; ground z at "
                  "the stem base",
            "d": "horizontal distance of cp from the plot centre (local origin)",
            "h": "vertical height from base to top",
            "maxcurve": "maximum distance of the centre line from its base-to-top chord",
        },
        "plot": {"size_m": list(scn.plot.size_m), "origin": [float(v) for v in origin]},
        "terrain": forest.terrain.to_doc(tuple(float(v) for v in origin)),  # type: ignore[arg-type]
        "objects": objects,
    }
    if nat is not None:
        go = forest.ground_objects()
        assert go is not None
        doc["ground_objects"] = go.records(origin)
        doc["object_ids"] = {
            "stems": [1, n], "branches": [n + 1, 2 * n], "foliage": [2 * n + 1, 3 * n],
            "ground_objects": [3 * n + 1, 3 * n + len(go)],
            "rule": "returns are counted by object id: 0 the ground, a stem's id (its second "
                    "leader and second stem too), n + id its branches, 2n + id its foliage, "
                    "then each ground object's own id"}
        doc = {"schema_version": NATURAL_SCHEMA_VERSION, **doc}
        doc["classification"]["rule"] = NATURAL_RULE
        doc["conventions"].update(NATURAL_CONVENTIONS)
    return doc
