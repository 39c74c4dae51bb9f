"""One-to-one matching of observed trees to ground-truth trees within a distance (x-y plane).

``greedy``: all (gt, observed) pairs within d, sorted by distance (ties by gt id rank, then
observed id rank), taken while both trees are free. This is the paper's nearest-neighbour rule
made independent of object order.

``optimal``: among matchings of maximum size, the one of minimum total distance (scipy's
``linear_sum_assignment`` on each connected component of the within-d graph; a non-edge costs
more than any whole component's distances, so the size comes first).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

MatchMethod = Literal["greedy", "optimal"]
IntArray = NDArray[np.int64]


def _id_rank(keys: list[Any]) -> IntArray:
    """Rank of every object in a total order given by its sort key (see
    ``StemTable.sort_keys``)."""
    order = sorted(range(len(keys)), key=lambda i: keys[i])
    rank = np.empty(len(keys), dtype=np.int64)
    rank[order] = np.arange(len(keys))
    return rank


def candidate_pairs(gt_xy: NDArray[np.float64], obs_xy: NDArray[np.float64],
                    max_distance: float) -> tuple[IntArray, IntArray, NDArray[np.float64]]:
    """All (gt index, observed index, distance) with distance <= max_distance."""
    if len(gt_xy) == 0 or len(obs_xy) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    # Local offsets keep precision at UTM-sized coordinates. The reference is a whole-metre
    # corner of both sets: subtracting it is exact, so distances (and their ties, and a tree
    # exactly at the radius) do not depend on the data's mean or order.
    ref = np.floor(np.minimum(gt_xy.min(axis=0), obs_xy.min(axis=0)))
    sdm = cKDTree(gt_xy - ref).sparse_distance_matrix(
        cKDTree(obs_xy - ref), max_distance, output_type="ndarray")
    return sdm["i"].astype(np.int64), sdm["j"].astype(np.int64), sdm["v"].astype(np.float64)


def match(gt_xy: NDArray[np.float64], obs_xy: NDArray[np.float64], max_distance: float,
          method: MatchMethod = "greedy", gt_ids: list[Any] | None = None,
          obs_ids: list[Any] | None = None) -> tuple[IntArray, NDArray[np.float64]]:
    """Match trees; returns (pairs (k, 2) of [gt index, observed index], distances (k,)).

    Pairs are sorted by gt index.
    """
    gi, oi, dist = candidate_pairs(gt_xy, obs_xy, max_distance)
    if len(gi) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    if method == "greedy":
        pairs, d = _greedy(gi, oi, dist, len(gt_xy), len(obs_xy), gt_ids, obs_ids)
    elif method == "optimal":
        gr = _id_rank(gt_ids) if gt_ids is not None else np.arange(len(gt_xy))
        orank = _id_rank(obs_ids) if obs_ids is not None else np.arange(len(obs_xy))
        pairs, d = _optimal(gi, oi, dist, len(gt_xy), gr, orank)
    else:
        raise ValueError(f"unknown matching method {method!r}; use 'greedy' or 'optimal'")
    order = np.argsort(pairs[:, 0], kind="stable")
    return pairs[order], d[order]


def _greedy(gi: IntArray, oi: IntArray, dist: NDArray[np.float64], n_gt: int, n_obs: int,
            gt_ids: list[Any] | None, obs_ids: list[Any] | None
            ) -> tuple[IntArray, NDArray[np.float64]]:
    gr = _id_rank(gt_ids) if gt_ids is not None else np.arange(n_gt)
    orank = _id_rank(obs_ids) if obs_ids is not None else np.arange(n_obs)
    order = np.lexsort((orank[oi], gr[gi], dist))
    gi, oi, dist = gi[order], oi[order], dist[order]
    # Fast path: pairs whose trees appear in no other candidate pair are always taken.
    gcount = np.bincount(gi, minlength=n_gt)
    ocount = np.bincount(oi, minlength=n_obs)
    lone = (gcount[gi] == 1) & (ocount[oi] == 1)
    keep = lone.copy()
    gfree = np.ones(n_gt, dtype=bool)
    ofree = np.ones(n_obs, dtype=bool)
    for k in np.flatnonzero(~lone).tolist():
        g, o = gi[k], oi[k]
        if gfree[g] and ofree[o]:
            gfree[g] = ofree[o] = False
            keep[k] = True
    return np.column_stack([gi[keep], oi[keep]]), dist[keep]


def _optimal(gi: IntArray, oi: IntArray, dist: NDArray[np.float64], n_gt: int,
             grank: IntArray, orank: IntArray) -> tuple[IntArray, NDArray[np.float64]]:
    # Bipartite graph: gt nodes 0..n_gt-1, observed nodes n_gt + j (compacted).
    uo, oi_c = np.unique(oi, return_inverse=True)
    ug, gi_c = np.unique(gi, return_inverse=True)
    ng, no = len(ug), len(uo)
    graph = coo_matrix((np.ones(len(gi)), (gi_c, ng + oi_c)), shape=(ng + no, ng + no))
    _, label = connected_components(graph, directed=False)
    comp = label[gi_c]
    sizes = np.bincount(comp)
    single = sizes[comp] == 1  # a component with one edge: take it
    keep = single.copy()
    multi = np.flatnonzero(~single)
    if len(multi):
        order = multi[np.argsort(comp[multi], kind="stable")]
        bounds = np.flatnonzero(np.diff(comp[order])) + 1
        for block in np.split(order, bounds):
            # Rows and columns in rank order: equal-cost optima then resolve the same way
            # whatever the documents' object order.
            g_loc, g_inv = np.unique(grank[gi[block]], return_inverse=True)
            o_loc, o_inv = np.unique(orank[oi[block]], return_inverse=True)
            big = 1.0 + float(dist[block].sum()) * 2.0 + 1.0
            cost = np.full((len(g_loc), len(o_loc)), big)
            cost[g_inv, o_inv] = dist[block]
            edge = np.full(cost.shape, -1, dtype=np.int64)
            edge[g_inv, o_inv] = block
            r, c = linear_sum_assignment(cost)
            chosen = edge[r, c]
            keep[chosen[chosen >= 0]] = True
    return np.column_stack([gi[keep], oi[keep]]), dist[keep]
