"""Porous crowns (:mod:`emulators.media`): exact ray intervals, Beer-Lambert's law drawn per
ray in the compiled cast, overlaps, solids in front, and draws that belong to the ray."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

pytest.importorskip("numba")
pytest.importorskip("embreex")

from emulators.embree import direct_scene
from emulators.media import CONE, ELLIPSOID, Crowns, interval

FAR_WALL = (np.array([[200.0, -300.0, -300.0], [200.0, 300.0, -300.0], [200.0, 0.0, 300.0]]),
            np.array([[0, 1, 2]]))


def crowns(rows: list[tuple[tuple[float, float, float], tuple[float, float, float], float,
                            float, float, int, float]]) -> Crowns:
    """Crowns from (apex, axis, length, radius, cut, shape, sigma) rows."""
    cols = list(zip(*rows, strict=True))
    return Crowns(np.array(cols[0], float), np.array(cols[1], float), np.array(cols[2]),
                  np.array(cols[3]), np.array(cols[4]), np.array(cols[5], np.int8),
                  np.array(cols[6]))


def scene(c: Crowns, vertices: np.ndarray = FAR_WALL[0], faces: np.ndarray = FAR_WALL[1]
          ) -> object:
    ds = direct_scene(vertices, faces, crowns=c)
    if ds is None:
        pytest.skip("Embree is not bound directly here (compiled kernels off)")
    return ds


def along_x(m: int, seed: int, half_width: float, z: tuple[float, float]
            ) -> tuple[np.ndarray, np.ndarray]:
    """``m`` rays along +x from x = -5 m, y within ``half_width``, z uniform in ``z``."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([np.full(m, -5.0), rng.uniform(-half_width, half_width, m),
                         rng.uniform(*z, m)])
    return o, np.tile([1.0, 0.0, 0.0], (m, 1))


def intervals(c: Crowns, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(m, 2): each ray's exact interval in the first crown."""
    row = c.table()[0]
    return np.array([interval(row, *o[i], *d[i]) for i in range(len(o))])


def inside(row: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Whether points p (n, 3) lie in the crown ``row`` (a :meth:`Crowns.table` row)."""
    apex, w = row[0:3], row[3:6]
    L, R, cut, shape = row[6], row[7], row[8], row[9]
    q = p - apex
    s = q @ w
    rho = np.linalg.norm(q - s[:, None] * w, axis=1)
    slab = (s >= max(cut, 0.0)) & (s <= L)
    if shape == CONE:
        return slab & (rho <= R * s / L)
    h = L / 2.0
    return slab & ((rho / R) ** 2 + ((s - h) / h) ** 2 <= 1.0)


@settings(max_examples=150, deadline=None)
@given(shape=hs.sampled_from([CONE, ELLIPSOID]), length=hs.floats(0.5, 12.0),
       radius=hs.floats(0.2, 3.0), cut=hs.one_of(hs.floats(0.0, 0.6), hs.floats(0.95, 1.5)),
       tilt=hs.floats(0.0, 0.5), seed=hs.integers(0, 2**32 - 1))
def test_a_rays_interval_in_a_crown_is_where_its_points_are_inside(
        shape: int, length: float, radius: float, cut: float, tilt: float, seed: int) -> None:
    """The exact interval (float64) against the crown sampled every 0.5 mm along the ray:
    a cone (its apex a singular point), an ellipsoid, leaning, cut across its axis (or cut
    at or below its base: nothing left)."""
    rng = np.random.default_rng(seed)
    axis = np.array([math.sin(tilt), 0.0, -math.cos(tilt)])
    c = crowns([((0.0, 0.0, 10.0), tuple(axis), length, radius, cut * length, shape, 1.0)])
    row = c.table()[0]
    o = np.array([0.0, 0.0, 10.0]) + axis * length * rng.uniform(-0.2, 1.2) \
        + rng.uniform(-1.5, 1.5, 3) * radius
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    t0, t1 = interval(row, *o, *d)
    span = 2.0 * (length + radius) + 10.0
    ts = np.arange(-span, span, 5e-4)
    ins = inside(row, o + ts[:, None] * d)
    if ins.any():
        assert t1 > t0
        assert abs(ts[ins].min() - t0) < 1e-3 and abs(ts[ins].max() - t1) < 1e-3
        assert ins[(ts > t0 + 1e-3) & (ts < t1 - 1e-3)].all()  # one interval: convex
    else:
        assert t1 - t0 < 1e-3


@pytest.mark.parametrize("shape", [CONE, ELLIPSOID])
def test_crowns_stop_rays_as_beer_lambert_says(shape: int) -> None:
    """Parallel rays across a crown: each stops within its chord c with probability
    1 - exp(-sigma c), and where it stops is the exponential law truncated to the chord
    (the transformed depths are uniform: a Kolmogorov-Smirnov test); |cos| of the foliage
    hit is sqrt(U), mean 2/3."""
    from scipy import stats

    sigma = 0.6
    c = crowns([((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, shape, sigma)])
    ds = scene(c)
    o, d = along_x(60_000, 1, 2.0, (2.0, 10.0))
    t, prim, cn = ds.cast_n(o.astype(np.float32), d.astype(np.float32))
    iv = intervals(c, o, d)
    chord = np.maximum(iv[:, 1] - iv[:, 0], 0.0)
    stopped = prim == -2
    assert set(np.unique(prim).tolist()) <= {-2, 0}
    want = float(np.sum(1.0 - np.exp(-sigma * chord)))
    assert abs(stopped.sum() - want) < 4.0 * math.sqrt(want) + 10
    x = t[stopped] - iv[stopped, 0]
    assert (x >= -1e-4).all() and (x <= chord[stopped] + 1e-4).all()
    u = (1.0 - np.exp(-sigma * x)) / (1.0 - np.exp(-sigma * chord[stopped]))
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    assert float(cn[stopped].mean()) == pytest.approx(2.0 / 3.0, abs=0.01)


def test_overlapping_crowns_add_their_density_and_share_the_hits() -> None:
    """Two crowns in one place stop rays as one of their summed extinction would (as many,
    at depths of the same law: each crown draws its own path and the nearer stops the ray),
    and each takes its share of the stops."""
    from scipy import stats

    a = ((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, ELLIPSOID, 0.2)
    b = ((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, ELLIPSOID, 0.6)
    ds = scene(crowns([a, b]))
    one = scene(crowns([a[:6] + (0.8,)]))
    o64, d64 = along_x(40_000, 2, 1.0, (4.0, 8.0))
    o, d = o64.astype(np.float32), d64.astype(np.float32)
    t2, p2, _ = ds.cast_n(o, d)
    t1, p1, _ = one.cast_n(o, d)
    crown = (p2 == -2) | (p2 == -3)
    n1, n2 = np.count_nonzero(p1 == -2), np.count_nonzero(crown)
    assert abs(n2 - n1) < 4.0 * math.sqrt(n1)
    assert stats.ks_2samp(t1[p1 == -2], t2[crown]).pvalue > 1e-3
    first = np.count_nonzero(p2 == -2)
    assert first / n2 == pytest.approx(0.25, abs=0.015)


def test_a_crowns_draws_are_its_own_whatever_it_is_numbered() -> None:
    """A crown draws from its own key (a hash of its row), not from its number: the same
    crowns listed in another order, or after another crown the rays never meet (a stand
    culled to the track numbers its crowns afresh), stop every ray at the same place in the
    same crown."""
    a = ((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, ELLIPSOID, 0.4)
    b = ((0.5, 0.3, 9.0), (0.0, 0.1, -1.0), 7.0, 1.5, 0.5, CONE, 0.9)
    far = ((90.0, 90.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, CONE, 1.0)
    o64, d64 = along_x(20_000, 7, 2.0, (3.0, 9.0))
    o, d = o64.astype(np.float32), d64.astype(np.float32)
    t, p, _ = scene(crowns([a, b])).cast_n(o, d)
    for order, named in (([b, a], {-2: -3, -3: -2}), ([far, a, b], {-2: -3, -3: -4})):
        t2, p2, _ = scene(crowns(order)).cast_n(o, d)
        assert np.array_equal(t2, t)
        want = p.copy()
        for old, new in named.items():
            want[p == old] = new
        assert np.array_equal(p2, want)
    assert np.count_nonzero(p == -2) > 1000 and np.count_nonzero(p == -3) > 1000


def test_a_solid_in_front_hides_the_crown_and_one_inside_it_cuts_the_path() -> None:
    """A wall across the crown: no ray stops in the foliage beyond it; before it, as many
    stop as the part of the chord in front of it says."""
    sigma = 0.8
    c = crowns([((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, ELLIPSOID, sigma)])
    wall = (np.array([[0.0, -50.0, -50.0], [0.0, 50.0, -50.0], [0.0, 0.0, 50.0]]),
            np.array([[0, 1, 2]]))
    ds = scene(c, *wall)
    o, d = along_x(40_000, 4, 1.5, (4.0, 8.0))
    t, prim, _ = ds.cast_n(o.astype(np.float32), d.astype(np.float32))
    stopped = prim == -2
    assert (t[stopped] <= 5.0 + 1e-4).all() and (t[~stopped] == pytest.approx(5.0, abs=1e-4))
    iv = intervals(c, o, d)
    front = np.clip(np.minimum(iv[:, 1], 5.0) - iv[:, 0], 0.0, None)
    want = float(np.sum(1.0 - np.exp(-sigma * front)))
    assert abs(stopped.sum() - want) < 4.0 * math.sqrt(want) + 10


def test_a_ray_that_starts_inside_a_crown_meets_it_from_there() -> None:
    sigma = 0.5
    c = crowns([((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, CONE, sigma)])
    ds = scene(c)
    rng = np.random.default_rng(5)
    m = 40_000
    o = np.column_stack([rng.uniform(-0.01, 0.01, (m, 2)), np.full(m, 4.0)]).astype(np.float32)
    d = np.tile(np.float32([1.0, 0.0, 0.0]), (m, 1))
    _, prim, _ = ds.cast_n(o, d)
    want = 1.0 - math.exp(-sigma * 1.5)  # the cone's radius 6 m below its apex
    assert float(np.mean(prim == -2)) == pytest.approx(want, abs=4.0 * math.sqrt(want / m))


def test_a_rays_draw_is_its_own_whatever_it_is_cast_with() -> None:
    """The draws are a hash of the ray: the same ray stops at the same place cast alone, in
    another batch, in another order; two rays a float32 step apart draw apart."""
    c = crowns([((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 8.0, 2.0, 0.0, CONE, 0.7),
                ((1.0, 0.5, 9.0), (0.1, 0.0, -1.0), 6.0, 1.5, 1.0, ELLIPSOID, 1.1)])
    ds = scene(c)
    rng = np.random.default_rng(6)
    m = 5000
    o = np.column_stack([np.full(m, -5.0), rng.uniform(-2, 2, m), rng.uniform(3, 9, m)])
    d = rng.normal([1.0, 0.0, 0.0], 0.1, (m, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    o, d = o.astype(np.float32), d.astype(np.float32)
    t, prim, cn = ds.cast_n(o, d)
    perm = rng.permutation(m)
    tp, pp, cp = ds.cast_n(o[perm], d[perm])
    assert np.array_equal(tp, t[perm]) and np.array_equal(pp, prim[perm])
    assert np.array_equal(cp, cn[perm])
    for i in range(0, m, 500):
        ti, pi, _ = ds.cast_n(o[i:i + 1], d[i:i + 1])
        assert ti[0] == t[i] and pi[0] == prim[i]
    nudged = o.copy()
    nudged[:, 2] = np.nextafter(nudged[:, 2], np.float32(np.inf))
    tn, pn, _ = ds.cast_n(nudged, d)
    both = (prim < -1) & (pn < -1)
    assert np.mean(np.abs(tn[both] - t[both]) > 1e-3) > 0.5
