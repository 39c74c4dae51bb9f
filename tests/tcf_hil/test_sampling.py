"""Surface sampling: exact counts, points on the true surfaces, uniform by area, PCD out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from protocols.pcd import decode_pcd
from tcf_hil.scenario import scenario_from_dict
from tcf_hil.world.forest import Forest, generate_forest
from tcf_hil.world.forest.sampling import sample_surfaces


def test_counts_and_ids(forest_iv: Forest) -> None:
    c = sample_surfaces(forest_iv, 500, 4.0)
    ids, counts = np.unique(c.stem_id, return_counts=True)
    assert ids[0] == 0 and counts[0] == round(4.0 * 20 * 40)
    assert np.all(counts[1:] == 500)
    assert len(ids) == len(forest_iv.stems) + 1


def test_points_lie_on_the_surfaces(forest_iv: Forest) -> None:
    c = sample_surfaces(forest_iv, 300, 2.0)
    st = forest_iv.stems
    for i in range(0, len(st), 9):
        p = c.xyz[c.stem_id == i + 1]
        s = np.arange(0.0, st.length[i], 0.001)
        cl = st.centre(np.full(len(s), i), s)
        r = st.radius(np.full(len(s), i), s)
        d, k = cKDTree(cl).query(p)
        np.testing.assert_allclose(d, r[k], atol=2e-4)
        assert np.all(p[:, 2] >= forest_iv.terrain.height(p[:, 0], p[:, 1]) - 1e-9)
    g = c.xyz[c.stem_id == 0]
    np.testing.assert_array_equal(g[:, 2], forest_iv.terrain.height(g[:, 0], g[:, 1]))


def test_uniform_by_area() -> None:
    """A straight cone-like stem: the share of points below mid-height equals the lateral
    area share (wide bottom gets more)."""
    f = generate_forest(scenario_from_dict({
        "stems": {"count": 1, "taper_exponent": 1.0, "class_mix": {"S": 1, "C": 0, "X": 0}},
        "terrain": {"kind": "flat"}, "distribution": {"corridor_half_width_m": 0.0}}))
    c = sample_surfaces(f, 200_000, 0.0)
    st = f.stems
    L = st.length[0]
    s = np.linspace(0, L, 20001)
    r = st.radius(np.zeros(len(s), dtype=np.int64), s)
    area_low = np.trapezoid(r[s <= L / 2], s[s <= L / 2]) / np.trapezoid(r, s)
    frac = float(np.mean(c.xyz[:, 2] - st.base[0, 2] <= L / 2))
    assert abs(frac - area_low) < 0.005


def test_pcd_bytes_carry_world_coordinates_and_ids(tmp_path: Path) -> None:
    f = generate_forest(scenario_from_dict({
        "stems": {"count": 5}, "plot": {"size_m": [20.0, 20.0],
                                        "origin_m": [500000.0, 6900000.0, 50.0]},
        "track": {"start_m": [0.0, -10.0, 2.0], "end_m": [0.0, 10.0, 2.0]}}))
    c = sample_surfaces(f, 100, 1.0)
    back = decode_pcd(c.to_pcd())
    np.testing.assert_array_equal(back["x"], c.xyz[:, 0])
    np.testing.assert_array_equal(back["stem_id"], c.stem_id)
    assert back["y"].min() > 6_899_980.0
    lossy = decode_pcd(c.to_pcd(float32=True))
    assert lossy["y"].dtype == np.float32


def test_same_seed_same_cloud(forest_ii: Forest) -> None:
    a = sample_surfaces(forest_ii, 50, 1.0)
    b = sample_surfaces(forest_ii, 50, 1.0)
    c = sample_surfaces(forest_ii, 50, 1.0, seed=123)
    assert a.to_pcd() == b.to_pcd()
    assert a.to_pcd() != c.to_pcd()
