"""Meshes are tessellated from a tolerance: chord error bounded, watertight, ids kept."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from tcf_hil.world.forest import Forest, sides_for, stem_mesh, terrain_mesh
from tcf_hil.world.forest.output import mesh_ply


@pytest.mark.parametrize(("r", "tol"), [(0.15, 0.002), (0.3, 0.0005), (0.05, 0.001),
                                        (0.5, 0.01)])
def test_sides_for_is_the_smallest_count_within_tolerance(r: float, tol: float) -> None:
    n = sides_for(r, tol)
    assert r * (1 - math.cos(math.pi / n)) <= tol
    if n > 6:
        assert r * (1 - math.cos(math.pi / (n - 1))) > tol


def _surface_error(forest: Forest, mesh: trimesh.Trimesh, count: int = 4000) -> np.ndarray:
    """Distance from random points on the mesh to the true stem surface (dense centre line)."""
    st = forest.stems
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=1)
    sid = mesh.face_attributes["stem_id"][face] - 1
    err = np.empty(count)
    for i in np.unique(sid):
        m = sid == i
        s = np.arange(-st.below[i], st.length[i], 0.0005)
        c = st.centre(np.full(len(s), i), s)
        r = st.radius(np.full(len(s), i), s)
        d, k = cKDTree(c).query(pts[m])
        ok = (s[k] > -st.below[i] + 0.01) & (s[k] < st.length[i] - 0.01)  # not on the caps
        e = np.full(int(m.sum()), np.nan)
        e[ok] = r[k[ok]] - d[ok]
        err[m] = e
    return err[np.isfinite(err)]


@pytest.mark.parametrize("tol_mm", [2.0, 10.0])
def test_stem_mesh_stays_within_tolerance_of_the_true_surface(forest_iv: Forest,
                                                              tol_mm: float) -> None:
    tol = tol_mm / 1000
    mesh = stem_mesh(forest_iv.stems, tol)
    err = _surface_error(forest_iv, mesh)
    # Within the tolerance of the true surface either way (plus the 0.2 mm resolution of
    # the centre-line sampling used to measure it), and the tolerance is actually used.
    assert np.abs(err).max() <= tol + 0.0002
    assert np.percentile(err, 99) > tol / 4


def test_coarser_tolerance_gives_fewer_triangles(forest_ii: Forest) -> None:
    fine = stem_mesh(forest_ii.stems, 0.0005)
    coarse = stem_mesh(forest_ii.stems, 0.01)
    assert len(coarse.faces) < len(fine.faces) / 3


def test_stem_meshes_are_closed_and_carry_their_ids_through_ply(forest_ii: Forest) -> None:
    mesh = stem_mesh(forest_ii.stems, 0.002)
    ids = mesh.face_attributes["stem_id"]
    assert set(np.unique(ids)) == set(range(1, len(forest_ii.stems) + 1))
    for part in mesh.split(only_watertight=False)[:5]:
        assert part.is_watertight
    mesh.vertices += [500_000.0, 6_900_000.0, 0.0]  # UTM-sized: float64 must survive
    back = trimesh.load(io.BytesIO(mesh_ply(mesh)), file_type="ply", process=False)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    face = back.metadata["_ply_raw"]["face"]["data"]
    np.testing.assert_array_equal(face["stem_id"].ravel(), ids)
    mesh.vertices -= [500_000.0, 6_900_000.0, 0.0]
    # Every stem reaches below its base, so no gap opens where it meets the ground.
    for i, b in enumerate(forest_ii.stems.base):
        v = mesh.vertices[np.unique(mesh.faces[ids == i + 1])]
        assert v[:, 2].min() < b[2] - 0.4


def test_terrain_mesh_within_tolerance(forest_iv: Forest) -> None:
    tol = 0.02
    mesh = terrain_mesh(forest_iv.terrain, forest_iv.bounds(), tol)
    pts, _ = trimesh.sample.sample_surface(mesh, 20000, seed=2)
    err = np.abs(pts[:, 2] - forest_iv.terrain.height(pts[:, 0], pts[:, 1]))
    assert err.max() <= tol
    x0, y0, x1, y1 = forest_iv.bounds()
    np.testing.assert_array_equal(mesh.bounds[:, :2], [[x0, y0], [x1, y1]])


def test_volume_matches_the_mesh(forest_ii: Forest) -> None:
    """Analytic volume (above ground) against the closed mesh's volume minus its part below
    the base; a fine mesh converges to the analytic value."""
    st = forest_ii.stems
    mesh = stem_mesh(st, 0.0002)
    ids = mesh.face_attributes["stem_id"]
    vol = forest_ii.volume
    for i in range(0, len(st), 5):
        part = trimesh.Trimesh(mesh.vertices, mesh.faces[ids == i + 1], process=False)
        below = math.pi * st.radius(np.array([i]), np.array([0.0]))[0] ** 2 * st.below[i]
        assert part.volume - below == pytest.approx(vol[i], rel=0.01)
