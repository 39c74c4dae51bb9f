"""The reference stem algorithm: circle fits, ground filter, clustering, whole-forest runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcf_hil.evaluation import evaluate
from tcf_hil.recording.stems_json import stem_table
from tcf_hil.scenario import scenario_from_dict
from tcf_hil.sic import (
    cluster_points,
    fit_circle,
    fit_circle_algebraic,
    identify_stems,
    remove_ground,
    stem_params,
)
from tcf_hil.world.forest import Forest, generate_forest, ground_truth
from tcf_hil.world.forest.sampling import sample_surfaces


def _arc(cx: float, cy: float, r: float, deg: float, n: int, noise: float,
         seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, math.radians(deg), n)
    rr = r + rng.normal(0, noise, n)
    return np.column_stack([cx + rr * np.cos(a), cy + rr * np.sin(a)])


@settings(max_examples=100, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(0.03, 0.9))
def test_full_circle_is_exact(cx: float, cy: float, r: float) -> None:
    c = fit_circle(_arc(cx, cy, r, 360.0, 50, 0.0), r_max=1.0)
    assert c is not None
    assert c.r == pytest.approx(r, abs=1e-6)
    assert math.hypot(c.cx - cx, c.cy - cy) < 1e-6
    assert c.arc_deg > 300


@pytest.mark.parametrize("deg", [60.0, 90.0, 180.0])
def test_partial_arcs_stay_sane(deg: float) -> None:
    """One-sided scans: with 2 mm noise the radius error stays bounded and the centre lies
    behind the visible arc (on the far side from a sensor looking at it)."""
    errs = []
    for seed in range(30):
        pts = _arc(0.0, 0.0, 0.15, deg, 80, 0.002, seed)
        c = fit_circle(pts, r_max=0.75)
        assert c is not None
        assert 0.01 <= c.r <= 0.75
        errs.append(abs(c.r - 0.15))
    bound = {60.0: 0.06, 90.0: 0.03, 180.0: 0.005}[deg]
    assert float(np.median(errs)) < bound


def test_degenerate_inputs_give_none() -> None:
    assert fit_circle(np.zeros((2, 2))) is None
    assert fit_circle_algebraic(np.column_stack([np.arange(5.0), np.arange(5.0)])) is None


def test_robust_fit_resists_outliers() -> None:
    pts = _arc(1.0, 2.0, 0.2, 360.0, 100, 0.001)
    pts[:8] += 0.3  # branches / noise
    c = fit_circle(pts)
    assert c is not None and abs(c.r - 0.2) < 0.01
    k = fit_circle_algebraic(pts)
    assert k is not None and abs(k.r - 0.2) > abs(c.r - 0.2)


def test_ground_filter_is_the_papers_rule() -> None:
    rng = np.random.default_rng(1)
    g = np.column_stack([rng.uniform(0, 10, (5000, 2)), rng.uniform(0, 0.3, 5000)])
    mask, cell, zmin = remove_ground(g, 1.0, 0.2)
    # Ground iff at most 0.20 m above the minimum of its own 1 x 1 m cell.
    ij = np.floor(g[:, :2] - g[:, :2].min(0)).astype(int)
    for k in range(0, 5000, 97):
        same = np.all(ij == ij[k], axis=1)
        assert mask[k] == (g[k, 2] <= g[same, 2].min() + 0.2)
        assert zmin[cell[k]] == g[same, 2].min()


def test_sklearn_and_scipy_give_the_same_clusters() -> None:
    rng = np.random.default_rng(2)
    pts = np.vstack([rng.normal(c, 0.15, (300, 3)) for c in ([0, 0, 0], [2, 0, 0], [2, 0.5, 0])])
    a = cluster_points(pts, 0.3, "scipy")
    b = cluster_points(pts, 0.3, "sklearn")
    # Same partition (labels may be numbered differently).
    pairs = set(zip(a.tolist(), b.tolist(), strict=True))
    assert len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))
    assert len(set(a.tolist())) < 10


def _pairs_components(pts: np.ndarray, r: float) -> np.ndarray:
    """The neighbour graph's components as listed pairs give them (scipy)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(pts).query_pairs(r, output_type="ndarray")
    g = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])),
                   shape=(len(pts), len(pts)))
    return connected_components(g, directed=False)[1].astype(np.int64)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 600),
       r=st.sampled_from([0.05, 0.3, 0.7]), spread=st.floats(0.01, 3.0),
       lattice=st.booleans())
def test_the_cube_grid_gives_the_components_and_labels_listed_pairs_give(
        seed: int, n: int, r: float, spread: float, lattice: bool) -> None:
    """The components found on a grid of cubes (tcf_hil.sic._components) are those of the
    listed pairs, numbered alike: blobs and scattered points, duplicates, points on a
    lattice of the radius itself (pairs at exactly r, and just over it), far offsets."""
    from tcf_hil.sic._components import radius_components

    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5.0, 5.0, (max(1, n // 100), 3)) + 1000.0
    pts = centres[rng.integers(0, len(centres), n)] + rng.normal(0.0, spread, (n, 3))
    if lattice:
        pts[: n // 2] = np.round(pts[: n // 2] / r) * r
    pts[: n // 10] = pts[n // 10: 2 * (n // 10)]  # duplicates
    got = radius_components(pts, r)
    if got is None:
        pytest.skip("compiled kernels are off here")
    assert np.array_equal(got, _pairs_components(pts, r))


@settings(max_examples=150, deadline=None)
@given(keys=st.lists(st.integers(-(2**62), 2**62 - 1), max_size=300),
       small=st.booleans(), offset=st.integers(-(2**40), 2**40))
def test_the_packed_sort_is_numpys_stable_argsort_and_unique(keys: list[int], small: bool,
                                                              offset: int) -> None:
    """tcf_hil.sic._fast (each key's index packed below it, sorted as plain integers)
    gives np.argsort(kind="stable") and np.unique(return_index, return_inverse) exactly:
    repeated keys, negative and offset keys, and keys too wide to pack (numpy's own)."""
    from tcf_hil.sic._fast import sorted_with_order, stable_argsort, unique_first

    k = np.array(keys, dtype=np.int64)
    if small:  # few distinct values, many repeats: what voxel and cube keys are
        k = k % 7 + offset
    order = np.argsort(k, kind="stable")
    sk, got = sorted_with_order(k)
    assert np.array_equal(got, order) and np.array_equal(sk, k[order])
    assert np.array_equal(stable_argsort(k), order)
    want = np.unique(k, return_index=True, return_inverse=True)
    for a, b in zip(unique_first(k), want, strict=True):
        assert np.array_equal(a, b.reshape(-1))


@settings(max_examples=150, deadline=None)
@given(rows=st.lists(st.tuples(*[st.integers(-50, 50)] * 3), min_size=1, max_size=200),
       offset=st.integers(-(2**30), 2**30))
def test_offset_keys_order_rows_as_lexsort_and_runs_start_at_new_rows(
        rows: list[tuple[int, int, int]], offset: int) -> None:
    """_fast.offset_key orders voxel rows lexicographically (equal keys exactly for equal
    rows), wherever the rows lie; _fast.run_starts marks the first of each run."""
    from tcf_hil.sic._fast import offset_key, run_starts

    v = np.array(rows, dtype=np.int64) + offset
    key = offset_key(v)
    order = np.argsort(key, kind="stable")
    want = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    assert np.array_equal(order, want)
    sv = v[order]
    new_row = np.r_[True, np.any(sv[1:] != sv[:-1], axis=1)]
    assert np.array_equal(run_starts(key[order]), new_row)
    assert key.min() >= 0 and int(key.max()) < 101**3


def test_the_tuned_sic_clusters_a_natural_cloud_as_listed_pairs_do() -> None:
    """On a natural stand's cloud (branches and foliage about the stems), cluster_points
    gives the same labels as the listed pairs."""
    from tcf_hil.sic._components import radius_components

    rng = np.random.default_rng(3)
    stems = rng.uniform(0, 20, (40, 2))
    pts = np.vstack([np.column_stack([s + rng.normal(0, 0.8, (800, 2)),
                                      rng.uniform(0, 12, 800)]) for s in stems])
    if radius_components(pts, 0.3) is None:
        pytest.skip("compiled kernels are off here")
    assert np.array_equal(cluster_points(pts, 0.3, "scipy"), _pairs_components(pts, 0.3))


def _score(f: Forest, preset: str, **kw: object) -> dict:
    cloud = sample_surfaces(f)
    s = f.scenario.stems
    doc = identify_stems(cloud.xyz, stem_params(preset, curve_threshold_m=s.curve_threshold_m,
                                                other_threshold_m=s.other_threshold_m, **kw))
    return evaluate(stem_table(ground_truth(f), "gt", "ground_truth"),
                    stem_table(doc, "obs")).metrics


def test_finds_and_measures_every_stem(forest_iv: Forest) -> None:
    m = _score(forest_iv, "tuned")
    assert m["missed"] == 0 and m["false_positives"] == 0
    assert m["position_rmse_m"] < 0.01
    assert m["dbh_rmse_m"] < 0.005
    assert m["height_rmse_m"] < 0.5
    assert m["evaluation_score_percent"] > 90.0


def test_paper_preset_uses_mean_centre_and_extent_height(forest_ii: Forest) -> None:
    cloud = sample_surfaces(forest_ii)
    paper = identify_stems(cloud.xyz, stem_params("paper"))["objects"]
    tuned = identify_stems(cloud.xyz, stem_params("tuned"))["objects"]
    assert len(paper) >= len(forest_ii.stems)
    # The paper's height is max z - min z of the cluster after ground removal: shorter than
    # the tuned height above the local ground.
    hp = np.median([o["h"] for o in paper])
    ht = np.median([o["h"] for o in tuned])
    assert hp < ht


def test_utm_origin_gives_the_same_answer() -> None:
    base = {"stems": {"count": 20}, "plot": {"size_m": [30.0, 30.0]},
            "terrain": {"kind": "rolling"},
            "track": {"start_m": [0.0, -15.0, 2.0], "end_m": [0.0, 15.0, 2.0]}}
    origin = [500_000.0, 6_900_000.0, 120.0]
    a = generate_forest(scenario_from_dict(base), 2)
    b = generate_forest(scenario_from_dict(
        {**base, "plot": {"size_m": [30.0, 30.0], "origin_m": origin}}), 2)
    oa = identify_stems(sample_surfaces(a).xyz)["objects"]
    ob = identify_stems(sample_surfaces(b).xyz)["objects"]
    assert len(oa) == len(ob) == 20
    for x, y in zip(oa, ob, strict=True):
        np.testing.assert_allclose(np.subtract(y["cp"], x["cp"]), origin, atol=1e-3)
        assert x["class"] == y["class"]
        assert x["dbh"] == pytest.approx(y["dbh"], abs=1e-3)


def test_empty_and_ground_only_clouds() -> None:
    assert identify_stems(np.zeros((0, 3)))["objects"] == []
    g = np.column_stack([np.random.default_rng(0).uniform(0, 20, (2000, 2)), np.zeros(2000)])
    doc = identify_stems(g)
    assert doc["total_objects_count"] == 0


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ValueError, match="cluster_radius_m"):
        stem_params("tuned", cluster_radius_m=0.0)
    with pytest.raises(ValueError, match="unknown SIC preset"):
        stem_params("fast")


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), bow=st.floats(0.0, 0.6), arc=st.floats(5.0, 360.0),
       noise=st.floats(0.0, 0.05), height=st.floats(1.5, 25.0))
def test_the_compiled_centre_line_is_the_numpy_one(seed: int, bow: float, arc: float,
                                                   noise: float, height: float) -> None:
    """Every slice's fit, fallback to the mean and skip, compiled or slice by slice in numpy:
    the same numbers (the same LAPACK solver; partial arcs, a bow, straight walls, repeats)."""
    import tcf_hil.sic._stems as stems
    from tcf_hil.sic._circle import slice_centres_kernel, use_compiled_fits

    use_compiled_fits()
    if slice_centres_kernel() is None:
        pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 3000))
    z = rng.uniform(0.0, height, n)
    ang = rng.uniform(0.0, math.radians(arc), n)
    r = 0.02 + 0.3 * (1.0 - z / 30.0)
    pts = np.column_stack([50 + bow * np.sin(z / height * math.pi) + r * np.cos(ang),
                           20 + r * np.sin(ang), z])
    pts[:, :2] += rng.normal(0.0, noise + 1e-9, (n, 2))
    if seed % 3 == 0:  # a straight wall (collinear) and repeated points
        pts[: n // 2, 1] = 20.0
        pts[n // 2: n // 2 + 20] = pts[n // 2]
    prm = stem_params("tuned", min_slice_points=int(rng.integers(1, 8)))
    rel = pts[:, 2] - 0.0
    args = (pts, rel, 0.0, 0.5, float(rel.max()) - 0.15, prm)
    compiled = stems._centre_line(*args)
    try:
        stems.slice_centres_kernel = lambda: None  # type: ignore[assignment]
        numpy_path = stems._centre_line(*args)
    finally:
        stems.slice_centres_kernel = slice_centres_kernel
    assert np.asarray(compiled[0]).tobytes() == np.asarray(numpy_path[0]).tobytes()
    assert (np.asarray(compiled[1], np.float64).tobytes()
            == np.asarray(numpy_path[1], np.float64).tobytes())


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), arc=st.floats(2.0, 360.0), noise=st.floats(0.0, 0.05),
       n=st.integers(1, 400), repeats=st.booleans())
def test_the_compiled_dbh_fit_is_fit_circle(seed: int, arc: float, noise: float, n: int,
                                            repeats: bool) -> None:
    """The breast-height fit compiled gives fit_circle's centre and radius to the bit, and
    None where it does (short arcs, repeated points, fewer than three points)."""
    from tcf_hil.sic._circle import fit_circle_centre, slice_centres_kernel, use_compiled_fits

    use_compiled_fits()
    if slice_centres_kernel() is None:
        pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")
    rng = np.random.default_rng(seed)
    xy = _arc(float(rng.uniform(-80, 80)), float(rng.uniform(-80, 80)),
              float(rng.uniform(0.02, 0.6)), arc, n, noise, int(seed))
    if repeats:
        xy[: n // 2] = xy[0]
    c = fit_circle(xy, r_max=0.75)
    assert fit_circle_centre(xy, 0.75) == (None if c is None else (c.cx, c.cy, c.r))
