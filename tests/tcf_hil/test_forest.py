"""Forest generation invariants: stems never intersect, bases on the terrain, determinism per
seed, class counts as the preset says, ground truth consistent with the geometry."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs
from scipy.spatial import cKDTree

from tcf_hil.errors import ConfigError
from tcf_hil.scenario import load_scenario, scenario_from_dict
from tcf_hil.world.forest import Forest, Terrain, class_counts, generate_forest, ground_truth
from tcf_hil.world.forest.output import FILES, write_forest
from tcf_hil.world.forest.placement import region_for

STRESS = {
    "name": "stress", "plot": {"size_m": [20.0, 20.0]},
    "terrain": {"kind": "rolling", "amplitude_m": 1.0, "wavelength_m": 12.0},
    "stems": {"count": 120, "lean_deg": [0.0, 12.0],
              "sweep_m": {"S": [0.0, 0.04], "C": [0.1, 0.24], "X": [0.3, 0.6]}},
    "distribution": {"kind": "uneven", "min_spacing_m": 0.9, "corridor_half_width_m": 0.0},
}


def _min_surface_gaps(f: Forest, step: float = 0.05) -> list[float]:
    """Independent check: surface gap for every pair of nearby stems (dense sampling)."""
    st = f.stems
    n = len(st)
    reach = st.max_reach()
    gaps = []
    for i, j in cKDTree(st.base[:, :2]).query_pairs(max(3.0, 2 * reach.max())):
        far = np.hypot(*(st.base[i, :2] - st.base[j, :2]))
        if far > 3.0 and far > reach[i] + reach[j]:
            continue  # cannot touch: farther apart than both reaches (checked in test_reach)
        si = np.arange(0.0, st.length[i], step)
        sj = np.arange(0.0, st.length[j], step)
        ci, cj = st.centre(np.full(len(si), i), si), st.centre(np.full(len(sj), j), sj)
        ri, rj = st.radius(np.full(len(si), i), si), st.radius(np.full(len(sj), j), sj)
        d, k = cKDTree(cj).query(ci)
        gaps.append(float(np.min(d - ri - rj[k])))
    assert n
    return gaps


@pytest.mark.parametrize("scn", ["forest-iv", "forest-vii", STRESS])
def test_no_two_stems_intersect(scn: str | dict) -> None:
    s = load_scenario(scn) if isinstance(scn, str) else scenario_from_dict(scn)
    f = generate_forest(s)
    gaps = _min_surface_gaps(f)
    assert gaps, "the check must see some neighbouring stems"
    assert min(gaps) > 0.0


def test_reach_bounds_every_surface_point() -> None:
    f = generate_forest(scenario_from_dict(STRESS))
    st = f.stems
    reach = st.max_reach()
    for i in range(0, len(st), 7):
        s = np.linspace(0.0, st.length[i], 400)
        c = st.centre(np.full(len(s), i), s)
        r = st.radius(np.full(len(s), i), s)
        horiz = np.hypot(c[:, 0] - st.base[i, 0], c[:, 1] - st.base[i, 1]) + r
        assert horiz.max() <= reach[i] + 1e-3


def test_stress_scenario_needed_fixing() -> None:
    """The stress scene is dense enough that unconstrained bends would collide, so the check
    above is not vacuous: with the bends before fixing, some gaps are negative."""
    from tcf_hil.world.forest.generate import _conflicts

    f = generate_forest(scenario_from_dict(STRESS))
    assert _conflicts(f.stems) == []
    st = f.stems
    # Point every stem's bend (and lean) at its nearest neighbour: now some must touch.
    _, nn = cKDTree(st.base[:, :2]).query(st.base[:, :2], k=2)
    towards = st.base[nn[:, 1], :2] - st.base[:, :2]
    towards /= np.linalg.norm(towards, axis=1)[:, None]
    st.bend[:] = np.column_stack([towards, np.zeros(len(st))])
    st.axis[:] = [0.0, 0.0, 1.0]
    st.sweep[:] = 0.6
    assert _conflicts(st)


@pytest.mark.parametrize("name", ["forest-i", "forest-iv", "forest-x"])
def test_every_base_sits_on_the_terrain(name: str) -> None:
    f = generate_forest(load_scenario(name))
    st = f.stems
    np.testing.assert_array_equal(st.base[:, 2], f.terrain.height(st.base[:, 0], st.base[:, 1]))
    # And by the ground truth's own formula, evaluated from the JSON alone.
    doc = ground_truth(f)
    t = doc["terrain"]
    for o in doc["objects"]:
        x, y, z = o["base"]
        zz = t["origin"][2] + t["elevation_m"] + sum(
            a * math.cos(kx * (x - t["origin"][0]) + ky * (y - t["origin"][1]) + ph)
            for kx, ky, a, ph in t["waves"])
        assert z == pytest.approx(zz, abs=1e-4)
        assert o["cp"][2] == pytest.approx(z, abs=1e-9)


def test_rolling_terrain_is_not_flat() -> None:
    f = generate_forest(load_scenario("forest-x"))
    assert not f.terrain.is_flat
    assert np.ptp(f.stems.base[:, 2]) > 1.0


def test_same_seed_same_bytes_other_seed_other_forest(tmp_path: Path) -> None:
    s = load_scenario("forest-iv")
    write_forest(generate_forest(s, 3), tmp_path / "a")
    write_forest(generate_forest(s, 3), tmp_path / "b")
    write_forest(generate_forest(s, 4), tmp_path / "c")
    for name in FILES:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert (tmp_path / "a" / "ground_truth.json").read_bytes() != \
        (tmp_path / "c" / "ground_truth.json").read_bytes()


def test_terrain_does_not_depend_on_stem_count() -> None:
    a = generate_forest(scenario_from_dict({"terrain": {"kind": "rolling"},
                                            "stems": {"count": 10}}), 5)
    b = generate_forest(scenario_from_dict({"terrain": {"kind": "rolling"},
                                            "stems": {"count": 20}}), 5)
    np.testing.assert_array_equal(a.terrain.waves, b.terrain.waves)


@pytest.mark.parametrize("name", ["forest-i", "forest-v", "forest-vii"])
def test_class_counts_as_the_preset_says(name: str) -> None:
    s = load_scenario(name)
    f = generate_forest(s)
    mix = s.stems.class_mix
    want = class_counts({"S": mix.S, "C": mix.C, "X": mix.X}, s.stems.count)
    got = {c: int(np.sum(f.classes == c)) for c in "SCX"}
    assert got == want
    if name == "forest-i":
        assert got == {"S": 1, "C": 9, "X": 0}


def test_class_counts_largest_remainder() -> None:
    assert class_counts({"S": 0.5, "C": 0.4, "X": 0.1}, 550) == {"S": 275, "C": 220, "X": 55}
    assert sum(class_counts({"S": 1, "C": 1, "X": 1}, 100).values()) == 100
    assert class_counts({"S": 1, "C": 0, "X": 0}, 0) == {"S": 0, "C": 0, "X": 0}


def _polyline_maxcurve(cl: np.ndarray) -> float:
    a, b = cl[0], cl[-1]
    u = (b - a) / np.linalg.norm(b - a)
    return float(np.max(np.linalg.norm(np.cross(cl - a, u), axis=1)))


def test_ground_truth_agrees_with_its_geometry(forest_iv: Forest) -> None:
    doc = ground_truth(forest_iv)
    s = forest_iv.scenario
    assert doc["total_objects_count"] == len(doc["objects"]) == s.stems.count
    assert doc["scenario"] == {"name": s.name, "seed": forest_iv.seed}
    for o in doc["objects"]:
        cl = np.asarray(o["centerline"])
        r = np.asarray(o["radii"])
        assert len(cl) == len(r)
        assert np.all(np.linalg.norm(np.diff(cl, axis=0), axis=1) <= 0.5)
        np.testing.assert_allclose(cl[0], o["base"], atol=1e-4)
        assert o["h"] == pytest.approx(cl[-1, 2] - cl[0, 2], abs=2e-4)
        assert 11.0 <= o["h"] <= 27.0
        # maxcurve is the polyline's largest distance from its chord (vertices 0.5 m apart
        # may miss the exact peak by a little).
        assert _polyline_maxcurve(cl) == pytest.approx(o["maxcurve"], abs=2e-3)
        th_c, th_x = s.stems.curve_threshold_m, s.stems.other_threshold_m
        want = "X" if o["maxcurve"] >= th_x else "C" if o["maxcurve"] >= th_c else "S"
        assert o["class"] == want
        assert o["quality"] == {"S": 1, "C": 2, "X": 3}[want]
        # DBH is twice the radius at breast height (1.3 m along the stem).
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(cl, axis=0), axis=1))])
        assert 2 * np.interp(1.3, arc, r) == pytest.approx(o["dbh"], abs=2e-3)
        # Volume: frustums along the polyline.
        seg = np.linalg.norm(np.diff(cl, axis=0), axis=1)
        frus = math.pi / 3 * seg * (r[:-1] ** 2 + r[:-1] * r[1:] + r[1:] ** 2)
        assert o["volume"] == pytest.approx(float(frus.sum()), rel=0.01)
        assert o["d"] == pytest.approx(math.hypot(o["cp"][0], o["cp"][1]), abs=1e-3)


def test_distributions_respect_spacing_plot_and_corridor() -> None:
    for name in ("forest-v", "forest-vi", "forest-vii", "forest-x"):
        s = load_scenario(name)
        f = generate_forest(s)
        xy = f.stems.base[:, :2]
        w, h = s.plot.size_m
        m = s.distribution.edge_margin_m
        assert np.all(np.abs(xy[:, 0]) <= w / 2 - m + 1e-9)
        assert np.all(np.abs(xy[:, 1]) <= h / 2 - m + 1e-9)
        assert np.all(np.abs(xy[:, 0]) >= s.distribution.corridor_half_width_m)
        if s.distribution.kind != "even":
            d, _ = cKDTree(xy).query(xy, k=2)
            assert d[:, 1].min() >= s.distribution.min_spacing_m
    r = region_for(load_scenario("forest-v"))
    assert r.cut == pytest.approx(4.0)


def test_clustered_is_more_clumped_than_uneven() -> None:
    def nn_mean(name: str) -> float:
        xy = generate_forest(load_scenario(name)).stems.base[:, :2]
        d, _ = cKDTree(xy).query(xy, k=2)
        return float(d[:, 1].mean())

    assert nn_mean("forest-vii") < 0.8 * nn_mean("forest-vi")


def test_impossible_spacing_is_a_clear_config_error() -> None:
    s = scenario_from_dict({"plot": {"size_m": [10.0, 10.0]},
                            "stems": {"count": 500},
                            "distribution": {"kind": "uneven", "min_spacing_m": 1.0}})
    with pytest.raises(ConfigError, match=r"distribution\.min_spacing_m"):
        generate_forest(s)


def test_utm_origin_shifts_outputs_exactly() -> None:
    base = {"stems": {"count": 30}, "plot": {"size_m": [40.0, 40.0]},
            "terrain": {"kind": "rolling"}, "track": {"start_m": [0.0, -20.0, 2.0],
                                                     "end_m": [0.0, 20.0, 2.0]}}
    a = ground_truth(generate_forest(scenario_from_dict(base), 1))
    utm = dict(base, plot={"size_m": [40.0, 40.0], "origin_m": [500000.0, 6900000.0, 100.0]})
    b = ground_truth(generate_forest(scenario_from_dict(utm), 1))
    for oa, ob in zip(a["objects"], b["objects"], strict=True):
        np.testing.assert_allclose(np.subtract(ob["cp"], oa["cp"]), [500000.0, 6900000.0, 100.0],
                                   atol=1e-4)
        assert oa["d"] == ob["d"]
        assert oa["class"] == ob["class"]


def test_empty_forest() -> None:
    f = generate_forest(scenario_from_dict({"stems": {"count": 0}}))
    doc = ground_truth(f)
    assert doc["objects"] == [] and doc["total_objects_count"] == 0


def test_terrain_gradient_matches_finite_differences() -> None:
    t = Terrain.generate(load_scenario("forest-x").terrain, np.random.default_rng(1))
    x, y = np.array([3.1, -20.0, 44.4]), np.array([-7.0, 12.5, 0.3])
    gx, gy = t.gradient(x, y)
    e = 1e-5
    np.testing.assert_allclose(gx, (t.height(x + e, y) - t.height(x - e, y)) / (2 * e),
                               rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(gy, (t.height(x, y + e) - t.height(x, y - e)) / (2 * e),
                               rtol=1e-5, atol=1e-7)
    # RMS height is amplitude / sqrt(2) by construction.
    xs = np.random.default_rng(2).uniform(-2000, 2000, (20000, 2))
    rms = float(np.sqrt(np.mean((t.height(xs[:, 0], xs[:, 1]) - t.elevation_m) ** 2)))
    assert rms == pytest.approx(1.0 / math.sqrt(2), rel=0.1)


def test_centerline_vertices_at_most_half_a_metre_on_short_crooked_stems() -> None:
    s = scenario_from_dict({"plot": {"size_m": [30.0, 30.0]},
                            "stems": {"count": 60, "height_m": [2.0, 3.0],
                                      "class_mix": {"S": 0, "C": 0, "X": 1},
                                      "sweep_m": {"X": [0.8, 1.0]}},
                            "track": {"start_m": [0.0, -15.0, 2.0], "end_m": [0.0, 15.0, 2.0]}})
    for o in ground_truth(generate_forest(s))["objects"]:
        cl = np.asarray(o["centerline"])
        assert np.linalg.norm(np.diff(cl, axis=0), axis=1).max() <= 0.5 + 1e-4


def test_centre_line_has_no_kink_at_the_base(forest_iv: Forest) -> None:
    st = forest_iv.stems
    idx = np.arange(len(st))
    eps = 1e-6
    below = (st.centre(idx, np.zeros(len(st))) - st.centre(idx, np.full(len(st), -eps))) / eps
    above = (st.centre(idx, np.full(len(st), eps)) - st.centre(idx, np.zeros(len(st)))) / eps
    np.testing.assert_allclose(below, above, atol=1e-4)


def test_too_fine_a_terrain_tolerance_is_a_config_error() -> None:
    from tcf_hil.world.forest import terrain_mesh

    f = generate_forest(load_scenario("forest-x"))
    with pytest.raises(ConfigError, match=r"terrain\.tolerance_mm"):
        terrain_mesh(f.terrain, f.bounds(), 0.00001)


def test_no_meshes_removes_another_forests_meshes(tmp_path: Path) -> None:
    write_forest(generate_forest(load_scenario("forest-i")), tmp_path)
    assert (tmp_path / "stems.ply").exists()
    write_forest(generate_forest(load_scenario("forest-ii")), tmp_path, meshes=False)
    assert not (tmp_path / "stems.ply").exists() and not (tmp_path / "terrain.ply").exists()


@given(hs.lists(hs.tuples(hs.floats(-5.0, 5.0), hs.floats(-5.0, 40.0)), min_size=1,
                max_size=30), hs.sampled_from([0.01, 0.05, 0.1, 0.15]))
@settings(max_examples=200, deadline=None)
def test_axial_samples_are_each_rows_arange(rows: list[tuple[float, float]],
                                            step: float) -> None:
    from tcf_hil.world.forest.stems import axial_samples

    lo = np.array([r[0] for r in rows])
    hi = np.array([r[1] for r in rows])
    s, counts = axial_samples(lo, hi, step)
    want = [np.arange(a, b, step) for a, b in zip(lo, hi, strict=True)]
    assert counts.tolist() == [len(w) for w in want]
    assert np.array_equal(s, np.concatenate(want))


def _rings_one_by_one(stems, i, tolerance_m, max_ring_step_m=2.0, probe_step_m=0.05):  # type: ignore[no-untyped-def]
    """The ring positions as :func:`ring_positions` found them stem by stem before they
    were probed for all stems at once (at 646b767), kept here as the reference."""
    L = float(stems.length[i])
    lo = -float(stems.below[i])
    probe = np.arange(lo, L, probe_step_m)
    idx = np.full(len(probe), i)
    bend = stems.curvature_bound(idx, probe) + stems.radius_d2(idx, probe)
    step = np.minimum(max_ring_step_m, np.sqrt(8.0 * tolerance_m / np.maximum(bend, 1e-12)))
    density = np.concatenate([[0.0], np.cumsum(probe_step_m / step)])
    grid = np.concatenate([probe, [L]])
    count = max(1, math.ceil(density[-1]))
    s = np.interp(np.linspace(0.0, density[-1], count + 1), density, grid)
    s[0], s[-1] = lo, L
    return np.unique(np.concatenate([s, [0.0]]))


def test_ring_positions_of_all_stems_at_once_are_each_stems_own() -> None:
    """The rings found for stems probed together (batched by length) are those the old
    stem-by-stem loop found, bit for bit, on a natural stand (crooks, species taper) and a
    paper one, at the curves' 1 cm probes and the meshes' 5 cm."""
    from tcf_hil.world.forest.mesh import all_ring_positions

    for name in ("forest-x", "pine-thinning"):
        st = generate_forest(load_scenario(name)).stems
        pick = np.arange(0, len(st), max(1, len(st) // 40))
        for tol, probe in ((1e-4, 0.01), (5e-4, 0.05)):
            together = all_ring_positions(st, tol, probe_step_m=probe)
            for i in pick.tolist():
                assert np.array_equal(together[i], _rings_one_by_one(st, i, tol,
                                                                     probe_step_m=probe))


def test_the_terrain_lattice_is_its_heights() -> None:
    """:meth:`Terrain.lattice_height` (waves separated into x and y) against
    :meth:`Terrain.height` at every vertex, with the micro-relief's short waves."""
    t = generate_forest(load_scenario("pine-thinning")).terrain
    assert len(t.waves) > 16
    xs, ys = np.linspace(-70.0, 55.0, 301), np.linspace(-40.0, 80.0, 257)
    assert np.allclose(t.lattice_height(xs, ys), t.height(xs[None, :], ys[:, None]),
                       rtol=0, atol=5e-14)
