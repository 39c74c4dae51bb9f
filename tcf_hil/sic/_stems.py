"""The paper's stem identification and classification algorithm (section 2.4), as pure
functions on an (n, 3) float64 point array, plus what its Algorithm 1 asks for but does not
explain: DBH from a robust circle fit on a slice at 1.3 m above local ground, maxcurve from a
centre line of slice fits, and the class from maxcurve.

Steps:
 1. ground removal: 1 x 1 m grid, points at most 0.20 m above their cell's minimum are ground;
 2. fixed-radius clustering (0.3 m; connected components of the radius graph) on the rest;
 3. clusters taller than 2.5 m (max z - min z) are trees: centre = mean x, y, height =
    max z - min z (paper preset) or refined (tuned preset).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from protocols.stems import QUALITY_BY_CLASS
from tcf_hil.sic._circle import fit_circle_algebraic, fit_circle_centre, slice_centres_kernel
from tcf_hil.sic._components import radius_components
from tcf_hil.sic._fast import column_min, finite_rows, offset_key, stable_argsort, unique_first
from tcf_hil.sic._params import PRESETS, StemParams, stem_params

__all__ = ["BREAST_HEIGHT_M", "PRESETS", "StemParams", "centre_line_curve", "cluster_points",
           "identify_stems", "merge_fragments", "remove_ground", "stem_params"]

FloatArray = NDArray[np.float64]
BREAST_HEIGHT_M = 1.3


def remove_ground(points: FloatArray, cell_m: float = 1.0, threshold_m: float = 0.2
                  ) -> tuple[NDArray[np.bool_], NDArray[np.int64], FloatArray]:
    """Grid ground filter.

    Returns:
        (ground mask, cell index of every point, minimum z of every cell index).
    """
    if len(points) == 0:
        return np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0)
    ij = np.floor((points[:, :2] - column_min(points[:, :2])) / cell_m).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    uniq, cell = np.unique(key, return_inverse=True)
    zmin = np.full(len(uniq), np.inf)
    np.minimum.at(zmin, cell, points[:, 2])
    ground = points[:, 2] <= zmin[cell] + threshold_m
    return ground, cell, zmin


def cluster_points(points: FloatArray, radius_m: float,
                   neighbors: Literal["scipy", "sklearn"] = "scipy",
                   voxel_m: float = 0.0) -> NDArray[np.int64]:
    """Connected components of the fixed-radius neighbour graph; a label per point.

    ``neighbors`` ``scipy``: where compiled kernels are on, the components found on a grid of
    cubes without listing the graph's pairs (:mod:`tcf_hil.sic._components`: the same labels,
    several times faster on dense clouds), else scipy's ``query_pairs``; ``sklearn``:
    scikit-learn's ``query_radius``, as the paper's algorithm does.

    ``voxel_m`` > 0 builds the graph on one representative point per voxel (the first) and
    gives every point its voxel's label: the number of neighbour pairs, which is what the
    exact graph costs on a dense accumulated map, falls with the square of the thinning,
    and distances change by at most a voxel diagonal.
    """
    n = len(points)
    if n == 0:
        return np.zeros(0, np.int64)
    if voxel_m > 0:
        key = offset_key(np.floor(points / voxel_m).astype(np.int64))
        _, first, inverse = unique_first(key)  # np.unique's, faster
        rep = cluster_points(points[first], radius_m, neighbors)
        return rep[inverse.reshape(-1)]
    if neighbors == "sklearn":
        from sklearn.neighbors import KDTree

        nb = KDTree(points).query_radius(points, r=radius_m)
        counts = np.fromiter((len(a) for a in nb), dtype=np.int64, count=n)
        rows = np.repeat(np.arange(n), counts)
        cols = np.concatenate(nb) if n else np.zeros(0, np.int64)
    else:
        labels = radius_components(points, radius_m)  # the same components, faster
        if labels is not None:
            return labels
        pairs = cKDTree(points).query_pairs(radius_m, output_type="ndarray")
        rows, cols = pairs[:, 0], pairs[:, 1]
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    return labels.astype(np.int64)


def merge_fragments(local: FloatArray, members: list[NDArray[np.int64]],
                    ground_z: FloatArray, prm: StemParams) -> list[NDArray[np.int64]]:
    """Join clusters that float above the ground onto the cluster whose top is right below
    them (within ``merge_radius_m`` horizontally and ``merge_gap_m`` vertically)."""
    n = len(members)
    if n < 2:
        return members
    band = 0.5
    qs = [local[m] for m in members]  # each cluster's points, gathered once
    zlo = np.array([q[:, 2].min() for q in qs])
    zhi = np.array([q[:, 2].max() for q in qs])
    bottom = np.array([q[q[:, 2] <= z + band, :2].mean(axis=0)
                       for q, z in zip(qs, zlo, strict=True)])
    top = np.array([q[q[:, 2] >= z - band, :2].mean(axis=0)
                    for q, z in zip(qs, zhi, strict=True)])
    del qs
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    tree = cKDTree(top)
    floating = np.flatnonzero(zlo - ground_z > 1.0)
    for i in floating[np.argsort(zlo[floating])]:
        best, best_gap = -1, math.inf
        for j in tree.query_ball_point(bottom[i], prm.merge_radius_m):
            gap = zlo[i] - zhi[j]
            if j != i and -0.5 <= gap <= prm.merge_gap_m and zlo[j] < zlo[i] and gap < best_gap:
                best, best_gap = j, gap
        if best >= 0:
            parent[find(int(i))] = find(best)
    groups: dict[int, list[NDArray[np.int64]]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(members[i])
    return [np.concatenate(g) for g in groups.values()]


def centre_line_curve(zs: FloatArray, cs: FloatArray, base: FloatArray | None = None,
                      top: FloatArray | None = None) -> float:
    """maxcurve: the largest distance of the centre line from its chord.

    The centre line is the slice centres ``cs`` (k, 2) at heights ``zs`` (k,), lightly
    smoothed (a running median of three, which keeps a real bow and drops a single bad fit),
    with the stem's ``base`` and ``top`` points (x, y, z) as its ends when given: slices
    thin out near the top, and a chord between the outermost slices alone would cut the
    bow short.
    """
    pts = np.column_stack([cs, zs]) if len(zs) else np.zeros((0, 3))
    if len(pts) >= 3:
        sm = pts.copy()
        for k in (0, 1):
            col = pts[:, k]
            sm[1:-1, k] = np.median(np.stack([col[:-2], col[1:-1], col[2:]]), axis=0)
        pts = sm
    if base is not None:
        pts = np.vstack([base[None, :], pts[pts[:, 2] > base[2]]])
    if top is not None:
        pts = np.vstack([pts[pts[:, 2] < top[2]], top[None, :]])
    if len(pts) < 3:
        return 0.0
    a, b = pts[0], pts[-1]
    chord = b - a
    L = float(np.linalg.norm(chord))
    if L == 0.0:
        return 0.0
    dev = np.linalg.norm(np.cross(pts - a, chord / L), axis=1)
    return float(dev.max())


def _centre_line(p: FloatArray, rel: FloatArray, ground_z: float, lo: float, hi: float,
                 prm: StemParams) -> tuple[list[float], list[tuple[float, float]]]:
    """Heights and centres of the slices every ``slice_step_m`` from ``lo`` to ``hi`` above
    the ground that hold ``min_slice_points``: the algebraic circle fit's centre where it
    is a stem's (radius at most ``max_dbh_m``, arc at least 90 degrees), else the mean."""
    half = prm.slice_thickness_m / 2.0
    order = np.argsort(rel)
    rs = rel[order]
    zc = np.arange(lo, hi + 1e-9, prm.slice_step_m)
    a, b = np.searchsorted(rs, zc - half), np.searchsorted(rs, zc + half)
    kernel = slice_centres_kernel()
    if kernel is not None:  # all slices in one compiled pass, the same numbers
        out = np.empty((len(zc), 2))
        kernel(np.ascontiguousarray(p[:, :2]), order, a, b, prm.min_slice_points,
               prm.max_dbh_m, float(np.finfo(np.float64).eps), out)
        kept = np.flatnonzero(~np.isnan(out[:, 0]))
        return ([zc[s] + ground_z for s in kept],
                [(float(out[s, 0]), float(out[s, 1])) for s in kept])
    zs: list[float] = []
    cs: list[tuple[float, float]] = []
    for s in range(len(zc)):
        if b[s] - a[s] < prm.min_slice_points:
            continue
        q = p[order[a[s]:b[s]], :2]
        fit = fit_circle_algebraic(q)
        if fit is not None and fit.r <= prm.max_dbh_m and fit.arc_deg >= 90.0:
            cs.append((fit.cx, fit.cy))
        else:
            cs.append(tuple(q.mean(axis=0)))
        zs.append(zc[s] + ground_z)
    return zs, cs


def _tree_properties(p: FloatArray, ground_z: float, prm: StemParams) -> dict[str, float]:
    zmax, zmin = float(p[:, 2].max()), float(p[:, 2].min())
    out = {"x": float(p[:, 0].mean()), "y": float(p[:, 1].mean()), "ground": ground_z,
           "h": zmax - zmin if prm.height == "extent" else zmax - ground_z}
    rel = p[:, 2] - ground_z
    half = prm.slice_thickness_m / 2.0
    sl = p[np.abs(rel - BREAST_HEIGHT_M) <= half]
    dbh = math.nan
    if len(sl) >= prm.min_slice_points:
        c = fit_circle_centre(sl[:, :2], prm.max_dbh_m / 2.0)
        if c is not None:
            dbh = 2.0 * c[2]
            if prm.centre == "breast_height":
                out["x"], out["y"] = c[0], c[1]
    out["dbh"] = dbh
    # Centre line from slices every slice_step, from 0.5 m above ground to the top.
    lo = max(0.5, float(rel.min()) + half)
    hi = float(rel.max()) - half
    zs, cs = _centre_line(p, rel, ground_z, lo, hi, prm) if hi > lo else ([], [])
    base = top = None
    if zs:
        # Ends of the centre line: the lowest slice's centre carried down to the ground and
        # the centre of the points in the top 0.3 m.
        base = np.array([cs[0][0], cs[0][1], ground_z])
        up = p[p[:, 2] >= zmax - 0.3]
        top = np.array([*up[:, :2].mean(axis=0), zmax])
    out["maxcurve"] = centre_line_curve(np.asarray(zs), np.asarray(cs).reshape(-1, 2), base, top)
    return out


def identify_stems(points: FloatArray, params: StemParams | None = None, *,
                   ground_z: FloatArray | None = None,
                   widths: FloatArray | None = None) -> dict[str, Any]:
    """Run the stem algorithm on an (n, 3) float64 cloud (world metres).

    ``ground_z`` (n,): the ground height under every point, when the caller keeps the ground
    grid itself (the onboard SIC keeps only the points above it); default: the paper's grid
    filter on ``points``. ``widths`` (n,): each point's edge half width (the field
    algorithm's; None: no edge returns known).

    Returns:
        The observed-forest document (paper's Algorithm 1 fields), objects ordered by x, y.
    """
    prm = params or StemParams()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fin = finite_rows(pts)
    finite = slice(None) if fin is None else fin
    pts = pts[finite]
    # Work in local offsets: circle fits at UTM-sized coordinates would lose precision.
    ref = np.array([*np.floor(column_min(pts[:, :2])), 0.0]) if len(pts) else np.zeros(3)
    local = pts - ref
    if ground_z is None:
        ground, cell, zmin = remove_ground(local, prm.ground_cell_m, prm.ground_threshold_m)
    else:
        zmin = np.asarray(ground_z, dtype=np.float64).reshape(-1)[finite] - ref[2]
        cell = np.arange(len(zmin))
        ground = local[:, 2] <= zmin + prm.ground_threshold_m
    if prm.algorithm == "field":
        return _field_document(local, ref, zmin[cell], widths, finite, prm)
    above = np.flatnonzero(~ground)
    labels = cluster_points(local[above], prm.cluster_radius_m, prm.neighbors,
                            prm.cluster_voxel_m)
    objects: list[dict[str, Any]] = []
    if len(above):
        order = stable_argsort(labels)
        starts = np.flatnonzero(np.r_[True, np.diff(labels[order]) != 0])
        ends = np.r_[starts[1:], len(order)]
        clusters = [above[order[a:b]] for a, b in zip(starts, ends, strict=True)]
        clusters = [m for m in clusters if len(m) >= 3]
        lows = np.array([m[int(np.argmin(local[m, 2]))] for m in clusters], dtype=np.int64)
        gz = zmin[cell[lows]] if len(lows) else np.zeros(0)
        if prm.merge_fragments:
            clusters = merge_fragments(local, clusters, gz, prm)
        trees = []
        for members in clusters:
            p = local[members]
            if len(members) < prm.min_points or float(np.ptp(p[:, 2])) <= prm.min_height_m:
                continue
            low = members[int(np.argmin(p[:, 2]))]
            trees.append(_tree_properties(p, float(zmin[cell[low]]), prm))
        trees.sort(key=lambda t: (round(t["x"], 6), round(t["y"], 6)))
        cx0, cy0 = prm.scene_centre
        for k, t in enumerate(trees, 1):
            mc = t["maxcurve"]
            cls = ("X" if mc >= prm.other_threshold_m else
                   "C" if mc >= prm.curve_threshold_m else "S")
            x, y, z = t["x"] + ref[0], t["y"] + ref[1], t["ground"] + ref[2]
            obj: dict[str, Any] = {
                "id": k, "name": f"tree_{k}", "h": round(t["h"], 4)}
            if math.isfinite(t["dbh"]):
                obj["dbh"] = round(t["dbh"], 4)
            obj.update({
                "maxcurve": round(mc, 4), "quality": QUALITY_BY_CLASS[cls], "class": cls,
                "cp": [round(x, 4), round(y, 4), round(z, 4)],
                "d": round(math.hypot(x - cx0, y - cy0), 4)})
            objects.append(obj)
    return {"timestamp": prm.timestamp, "total_objects_count": len(objects),
            "algorithm": {"name": "tcf-hil reference stem algorithm", "params": asdict(prm)},
            "objects": objects}


def _field_document(local: FloatArray, ref: FloatArray, ground: FloatArray,
                    widths: FloatArray | None, finite: Any, prm: StemParams) -> dict[str, Any]:
    """The field algorithm's stems (:func:`tcf_hil.sic._field.field_stems`) as the observed
    document, each with its stem curve ([z, x, y, diameter] from the base up)."""
    from tcf_hil.sic._field import field_stems

    w = (np.zeros(len(local)) if widths is None
         else np.asarray(widths, np.float64).reshape(-1)[finite])
    trees = field_stems(local, w, ground, prm) if len(local) else []
    trees.sort(key=lambda t: (round(t["x"], 6), round(t["y"], 6)))
    cx0, cy0 = prm.scene_centre
    objects: list[dict[str, Any]] = []
    for k, t in enumerate(trees, 1):
        mc = t["maxcurve"]
        cls = t["class"]
        x, y, z = t["x"] + ref[0], t["y"] + ref[1], t["ground"] + ref[2]
        objects.append({
            "id": k, "name": f"tree_{k}", "h": round(t["h"], 4), "dbh": round(t["dbh"], 4),
            "maxcurve": round(mc, 4), "quality": QUALITY_BY_CLASS[cls], "class": cls,
            "cp": [round(x, 4), round(y, 4), round(z, 4)],
            "d": round(math.hypot(x - cx0, y - cy0), 4),
            "stem_curve": [[round(zz + ref[2], 3), round(xx + ref[0], 4),
                            round(yy + ref[1], 4), dd] for zz, xx, yy, dd in t["curve"]]})
    return {"timestamp": prm.timestamp, "total_objects_count": len(objects),
            "algorithm": {"name": "tcf-hil reference stem algorithm (field)",
                          "params": asdict(prm)}, "objects": objects}
