"""Round linear curves in the directly bound Embree scene (emulators.embree): hits on the
exact surface of a tapered tube, |cos incidence| from Embree's geometric normal, one
numbering for triangles (robust and loose) and curve segments, and loose triangles cast
without robust mode hitting what robust mode hits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.jit import jit_enabled

pytestmark = pytest.mark.skipif(not jit_enabled(), reason="compiled kernels are off here "
                                "(TCF_HIL_NO_JIT or no numba): no directly bound Embree")


def _tube(x: float, r0: float, r1: float, z0: float = -1.0, z1: float = 6.0,
          pieces: int = 1):  # type: ignore[no-untyped-def]
    """A vertical tapered tube at (x, 0) from z0 to z1 in ``pieces`` joined segments."""
    from emulators.embree import Curves

    u = np.linspace(0.0, 1.0, pieces + 1)
    pts = np.column_stack([np.full(pieces + 1, x), np.zeros(pieces + 1), z0 + u * (z1 - z0),
                           r0 + u * (r1 - r0)]).astype(np.float32)
    flags = np.full(pieces, 3, np.uint8)
    flags[0] &= 2
    flags[-1] &= 1
    return Curves(pts, np.arange(pieces, dtype=np.uint32), flags)


def _far_triangle() -> tuple[np.ndarray, np.ndarray]:
    return (np.array([[1e4, 1e4, 1e4], [1e4 + 1, 1e4, 1e4], [1e4, 1e4 + 1, 1e4]], np.float32),
            np.array([[0, 1, 2]]))


@settings(max_examples=25, deadline=None)
@given(x=st.floats(3.0, 40.0), r=st.floats(0.02, 0.4), z=st.floats(0.0, 4.0))
def test_a_round_curve_is_hit_on_its_exact_cylinder(x: float, r: float, z: float) -> None:
    """A vertical tube of radius r at distance x, in segments of 1.75 m as stems are cut
    (:func:`tcf_hil.world.forest.mesh.stem_curves`: 2 m at most): every hit within 0.15 mm of
    the analytic cylinder where the ray is not grazing (Embree's float32 intersector: 0.1
    mm at worst on a 2 cm tube 3.6 m away, measured), and its |cos incidence| that of the
    cylinder's normal."""
    from emulators.embree import DirectScene

    v, f = _far_triangle()
    ds = DirectScene(v, f, _tube(x, r, r, pieces=4))
    n = 801
    y = np.linspace(-1.2 * r, 1.2 * r, n)
    o = np.zeros((n, 3), np.float32)
    d = np.stack([np.full(n, x), y, np.full(n, z)], 1)
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    t, prim, cn = ds.cast_n(o, d)
    dd = d.astype(np.float64)
    a = dd[:, 0] ** 2 + dd[:, 1] ** 2
    b = -x * dd[:, 0]
    disc = b * b - a * (x * x - r * r)
    inside = disc > 0
    assert np.array_equal(np.isfinite(t) & inside, np.isfinite(t))  # no hit off the tube
    te = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    p = dd * te[:, None]
    nrm = np.stack([p[:, 0] - x, p[:, 1], np.zeros(n)], 1) / r
    cos = np.abs(np.einsum("ij,ij->i", nrm, dd))
    ok = np.isfinite(t) & (cos > 0.2)
    assert ok.sum() > n // 3
    assert np.all(prim[np.isfinite(t)] <= -2) and np.all(prim[~np.isfinite(t)] == -1)
    assert np.max(np.abs(t[ok] - te[ok])) < 1.5e-4
    assert np.max(np.abs(cn[ok] - cos[ok])) < 3e-3


def test_a_tapered_segment_is_the_cone_tangent_to_its_end_spheres() -> None:
    """Radius 0.2 at z = 0 to 0.1 at z = 4: hit horizontally at height z, the surface is
    at the cone's radius there divided by cos of its half-angle (tangent to the spheres)."""
    from emulators.embree import DirectScene

    v, f = _far_triangle()
    ds = DirectScene(v, f, _tube(10.0, 0.2, 0.1, 0.0, 4.0))
    z = np.linspace(0.5, 3.5, 7)
    o = np.column_stack([np.zeros(7), np.zeros(7), z]).astype(np.float32)
    d = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (7, 1))
    t, prim, _ = ds.cast_n(o, d)
    sin_a = 0.1 / 4.0
    # the tangent cone's radius at height z, from the sphere centres' radii
    r = (0.2 + (0.1 - 0.2) * z / 4.0) / math.sqrt(1.0 - sin_a**2)
    assert np.all(prim == -2)
    assert np.max(np.abs((10.0 - t) - r)) < 2e-4


def test_triangles_robust_and_loose_and_curves_share_one_numbering() -> None:
    """Triangles 0..k-1 (robust), k.. (loose, cast first) and curve segments -2 - j: each
    answers with its own number, and the nearest of them answers."""
    from emulators.embree import Curves, DirectScene

    # three walls facing -x at x = 5, 6, 7 (one triangle pair each, about y = 0, 3, 6), and
    # two tubes, at (9, -3) and at (4, 2), before the second wall
    v, f = [], []
    for k, (x, y) in enumerate(((5.0, 0.0), (6.0, 3.0), (7.0, 6.0))):
        v += [[x, y - 1, -1], [x, y + 1, -1], [x, y + 1, 1], [x, y - 1, 1]]
        f += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    curves = Curves(np.array([[9.0, -3.0, -1, 0.3], [9.0, -3.0, 1, 0.3],
                              [4.0, 2.0, -1, 0.3], [4.0, 2.0, 1, 0.3]], np.float32),
                    np.array([0, 2], np.uint32), np.zeros(2, np.uint8))
    ds = DirectScene(np.array(v, np.float32), np.array(f), curves, loose_from=2)
    o = np.zeros((4, 3), np.float32)
    d = np.array([[5.0, 0.1, 0.2], [6.0, 3.0, 0.0], [7.0, 6.2, -0.1], [9.0, -3.0, 0.0]])
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    t, prim, cn = ds.cast_n(o, d)
    # wall 0 (robust, triangles 0-1); the tube at (4, 2) stands before wall 1 (loose, 2-3):
    # curve segment 1; wall 2 (loose, 4-5); the tube at (9, -3): curve segment 0
    assert prim[0] in (0, 1) and prim[1] == -3 and prim[2] in (4, 5) and prim[3] == -2
    assert abs(t[1] - (math.hypot(4.0, 2.0) - 0.3)) < 1e-4 and cn[1] > 0.99
    assert cn[0] == 0.0 and cn[2] == 0.0


def test_loose_triangles_cast_without_robust_mode_hit_what_robust_mode_hits() -> None:
    """A cloud of 20,000 separate 10 cm facets, cast with and without robust mode: the same
    facet for every ray, at the same distance to within float32's rounding (robust mode
    computes it another way: 7 % of the hits differ in the last bits, by 0.5 ppm at most)."""
    from emulators.embree import DirectScene

    rng = np.random.default_rng(4)
    c = rng.uniform([5, -3, -2], [12, 3, 2], (20000, 3))
    v = (c[:, None, :] + rng.normal(0, 0.05, (20000, 3, 3))).reshape(-1, 3).astype(np.float32)
    f = np.arange(len(v)).reshape(-1, 3)
    robust = DirectScene(v, f)
    loose = DirectScene(v, f, loose_from=0)
    assert loose.handles[0].shape == (1, 4) and loose.handles[0][0, 1] == 0
    n = 50000
    d = rng.normal(0, 1, (n, 3)) * [0.1, 0.25, 0.2] + [1, 0, 0]
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    o = np.zeros((n, 3), np.float32)
    t0, p0 = robust.cast(o, d)
    t1, p1 = loose.cast(o, d)
    assert np.count_nonzero(p0 >= 0) > n // 4
    assert np.array_equal(p0, p1)
    hit = np.isfinite(t0)
    assert np.array_equal(hit, np.isfinite(t1))
    assert np.max(np.abs(t1[hit] - t0[hit]) / t0[hit]) < 2e-6
