"""The field-grade reference SIC (``tcf_hil.sic._field``): mixed edge returns found on the
range image, the footprint correction on a stem seen by the emulated OS0-64 from a passing
machine, circle fits against known shapes with noise and clutter (property tests), stems
told from branches and needles, and the class from the stem curve."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tcf_hil.sic import Circle, fit_circle, stem_params
from tcf_hil.sic._field import (
    arc_fill,
    divergence_of,
    edge_widths,
    field_stems,
    hyper_circle,
    ransac_circle,
    stem_circle,
    stem_form,
    trimmed_circle,
)

PRM = stem_params("field")


# ------------------------------------------------------------------------- edge returns
def test_edge_returns_are_those_within_a_footprint_of_a_range_jump() -> None:
    """A stem at 10 m in columns 100-110 of a row with nothing behind it: the returns of the
    stem's outermost column on each side are edge returns at 1024 columns (one column is
    0.35 deg, one FWHM), the two outermost at 2048; each carries theta/2 * r."""
    for columns, flagged in ((1024, {100, 110}), (2048, {100, 101, 109, 110})):
        rng = np.zeros((2, columns), np.uint32)
        rng[0, 100:111] = 10_000
        w = edge_widths(rng, np.arange(columns), columns, 0.35, 0.3)
        assert set(np.flatnonzero(w[0] > 0).tolist()) == flagged
        assert not w[1].any()  # no returns, no widths
        assert w[0, 100] == pytest.approx(0.5 * math.radians(0.35) * 10.0, rel=1e-5)


def test_a_missing_column_or_a_range_step_makes_its_neighbours_edge_returns() -> None:
    rng = np.full((1, 40), 8_000, np.uint32)
    rng[0, 20:] = 8_500  # a step of 0.5 m: another surface
    cols = np.r_[np.arange(10), np.arange(11, 41)]  # column 10 lost
    w = edge_widths(rng, cols, 1024, 0.35, 0.3)
    assert set(np.flatnonzero(w[0] > 0).tolist()) == {0, 9, 10, 19, 20, 39}


def test_the_datasheet_divergence_by_product_line() -> None:
    assert divergence_of("OS-0-64-U13") == 0.35
    assert divergence_of("OS-1-128") == 0.18
    assert divergence_of("something else") == 0.35


# ------------------------------------------------------------------------- circle fits
def _arc(rng: np.random.Generator, cx: float, cy: float, r: float, arc_deg: float, n: int,
         noise: float) -> np.ndarray:
    a0 = rng.uniform(0, 2 * math.pi)
    a = a0 + np.radians(rng.uniform(0, arc_deg, n))
    rr = r + rng.normal(0, noise, n)
    return np.column_stack([cx + rr * np.cos(a), cy + rr * np.sin(a)])


@settings(max_examples=60, deadline=None)
@given(st.floats(0.03, 0.35), st.floats(120.0, 360.0), st.floats(0.0, 0.03),
       st.integers(0, 2**31 - 1))
def test_circle_fits_find_a_noisy_arc(r: float, arc: float, rel_noise: float, seed: int
                                      ) -> None:
    """RANSAC, the geometric refinement, the hyper fit and the shell trimming all find the
    circle of points on an arc of 120 degrees or more with noise up to 3 % of the radius
    and 3 mm (a 3 cm stem seen over 120 degrees with 2 mm of noise is beyond them)."""
    noise = min(rel_noise * r, 0.003)
    g = np.random.default_rng(seed)
    xy = _arc(g, 3.0, -2.0, r, arc, 80, noise)
    # 80 uniform draws can leave a hole of 60 degrees (seed 16777217 on 302): two arcs, which
    # stem_circle rejects on purpose (one stem's bark is one arc); the claim is for one arc
    assume(arc_fill(xy, 3.0, -2.0, r) >= 0.5)
    rs = ransac_circle(xy, r_max=0.5, tol=max(4 * noise, 0.004))
    assert rs is not None
    assert math.hypot(rs[0] - 3.0, rs[1] + 2.0) < 0.02 + 4 * noise
    h = hyper_circle(xy)
    assert h is not None and abs(h.r - r) < 0.004 + 3 * noise
    f = stem_circle(xy, np.zeros(len(xy)), r_max=0.5, tol=0.012, min_points=6)
    assert f is not None
    assert abs(f[2] - r) < 0.004 + 3 * noise
    assert math.hypot(f[0] - 3.0, f[1] + 2.0) < 0.004 + 3 * noise


@settings(max_examples=40, deadline=None)
@given(st.floats(0.05, 0.3), st.integers(0, 2**31 - 1))
def test_the_bark_shell_is_kept_and_the_clutter_outside_it_dropped(r: float, seed: int
                                                                   ) -> None:
    """Needles and branch stubs lie outside a stem, never inside it: with a third of the
    points scattered up to 15 cm outside the bark, the fit stays on the bark."""
    g = np.random.default_rng(seed)
    bark = _arc(g, 0.0, 0.0, r, 200.0, 120, 0.002)
    a = g.uniform(0, 2 * math.pi, 60)
    d = r + g.uniform(0.02, 0.15, 60)
    clutter = np.column_stack([d * np.cos(a), d * np.sin(a)])
    xy = np.vstack([bark, clutter])
    f = stem_circle(xy, np.zeros(len(xy)), r_max=0.5, tol=0.012, min_points=6)
    assert f is not None
    assert abs(f[2] - r) < 0.006
    c = trimmed_circle(bark, hyper_circle(bark), tol=0.012)  # type: ignore[arg-type]
    assert abs(c.r - r) < 0.004


def _stem_in_a_crown(seed: int) -> tuple[np.ndarray, float]:
    """A slice of a stem inside its live crown: its bark (220 degrees of it) gives a tenth
    of the points, needles fill the rest up to 40 cm outside it (never inside)."""
    g = np.random.default_rng(seed)
    r = float(g.uniform(0.04, 0.12))
    bark = _arc(g, 1.0, 1.0, r, 220.0, 150, 0.003)
    n = 1350
    a = g.uniform(0, 2 * math.pi, n)
    d = r + 0.02 + 0.38 * np.sqrt(g.uniform(0, 1, n))
    needles = np.column_stack([1.0 + d * np.cos(a), 1.0 + d * np.sin(a)])
    return g.permutation(np.vstack([bark, needles])), r


def test_a_stem_inside_a_crown_is_found_among_ten_times_as_many_needles() -> None:
    """Drawn from the whole slice, three points all lie on the bark once in a thousand
    tries; with local sampling and the hollow-aware score the stem is found (centre within
    2 cm, radius within 1 cm) in at least 9 slices of 10, where uniform sampling alone and
    the plain MSAC score find it in fewer than half."""
    ok_field = ok_plain = 0
    for seed in range(30):
        xy, r = _stem_in_a_crown(seed)
        f = stem_circle(xy, np.zeros(len(xy)), r_max=0.5, tol=0.02, min_points=6,
                        near=np.array([1.0, 1.0]), outside=2.0)
        ok_field += f is not None and math.hypot(f[0] - 1.0, f[1] - 1.0) < 0.02 and abs(
            f[2] - r) < 0.01
        rs = ransac_circle(xy, r_max=0.5, tol=0.02, near=np.array([1.0, 1.0]), local_m=0.0,
                           hollow=False)
        ok_plain += rs is not None and math.hypot(rs[0] - 1.0, rs[1] - 1.0) < 0.02 and abs(
            rs[2] - r) < 0.01
    assert ok_field >= 27, ok_field
    assert ok_plain < 15, ok_plain


@contextlib.contextmanager
def _fits(compiled: bool) -> Iterator[None]:
    """The field fits compiled (:mod:`tcf_hil.sic._fitkernels`) or in numpy, then as they
    were (``use_compiled_fits`` is a process-wide switch)."""
    from tcf_hil.sic._circle import compiled_fits_wanted, use_compiled_fits

    was = compiled_fits_wanted()
    use_compiled_fits(compiled)
    try:
        yield
    finally:
        use_compiled_fits(was)


def _kernels_or_skip() -> None:
    from tcf_hil.sic._fitkernels import fit_kernels

    with _fits(True):
        if fit_kernels() is None:
            pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")


@settings(max_examples=200, deadline=None)
@given(n=st.integers(0, 5000), lo=st.integers(0, 9), scale=st.integers(-8, 8),
       seed=st.integers(0, 2**32 - 1), signs=st.booleans())
def test_the_compiled_sum_is_numpys_to_the_bit(n: int, lo: int, scale: int, seed: int,
                                               signs: bool) -> None:
    """numpy's pairwise summation, as the compiled fits add up: every length (below 8, one
    block of 128, halved above), any start, mixed magnitudes and signs."""
    _kernels_or_skip()
    from tcf_hil.sic import _fitkernels

    g = np.random.default_rng(seed)
    a = g.uniform(0.0, 1.0, n + lo) * 10.0 ** g.integers(scale - 4, scale + 4, n + lo)
    if signs:
        a -= a.mean() if len(a) else 0.0
    want = float(a[lo:].sum())
    assert _fitkernels.pairwise_sum(a, lo, n) == want or (n == 0 and want == 0.0)


def _slice(kind: int, seed: int, n: int) -> tuple[np.ndarray, float]:
    g = np.random.default_rng(seed)
    r = float(g.uniform(0.03, 0.4))
    if kind == 0:  # a noisy partial arc
        xy = _arc(g, 4.0, -3.0, r, float(g.uniform(30.0, 360.0)), n, 0.004)
    elif kind == 1:  # a stem inside its crown
        xy, r = _stem_in_a_crown(seed)
        xy = xy[: max(n, 3)]
    elif kind == 2:  # repeated points and a straight wall
        xy = _arc(g, 0.0, 0.0, r, 180.0, n, 0.002)
        xy[: n // 3] = xy[0]
        xy[n // 3: 2 * n // 3, 1] = 0.5
    else:  # a disc of needles
        rr = 0.3 * np.sqrt(g.uniform(0, 1, n))
        a = g.uniform(0, 2 * math.pi, n)
        xy = np.column_stack([rr * np.cos(a), rr * np.sin(a)])
    return xy, r


@settings(max_examples=120, deadline=None)
@given(kind=st.integers(0, 3), seed=st.integers(0, 2**31 - 1), n=st.integers(3, 900),
       tol=st.sampled_from([0.005, 0.012, 0.02, 0.04]), near=st.booleans())
def test_the_compiled_fits_are_the_numpy_ones(kind: int, seed: int, n: int, tol: float,
                                               near: bool) -> None:
    """RANSAC's pick, the geometric refit, the shell trimming and a whole slice's fit give
    the same numbers compiled and in numpy, to the bit: arcs, a stem among needles (local
    sampling), repeated points and a straight wall (singular steps), a clump with no
    hollow; ``None`` where numpy gives None."""
    from tcf_hil.sic._field import refine_circle

    _kernels_or_skip()
    xy, _r = _slice(kind, seed, n)
    c0 = np.array([xy[:, 0].mean(), xy[:, 1].mean()]) if near else None
    width = np.where(np.arange(len(xy)) % 4 == 0, 0.01, 0.0)
    got = []
    for compiled in (False, True):
        with _fits(compiled):
            rs = ransac_circle(xy, r_max=0.5, tol=tol, near=c0)
            ref = (refine_circle(xy[rs[3]], rs[0], rs[1], rs[2], huber_m=tol / 2)
                   if rs is not None and rs[3].sum() >= 3 else None)
            start = ref or hyper_circle(xy)
            tr = trimmed_circle(xy, start, tol=tol) if start is not None else None
            sc = stem_circle(xy, width, r_max=0.5, tol=tol, min_points=6, near=c0)
            got.append((_floats(rs[:3]) if rs else None, rs[3].tobytes() if rs else None,
                        _floats(ref), _floats(tr), _floats(sc)))
    assert got[0] == got[1]


def _floats(v: Any) -> tuple[float, ...] | None:
    """A fit's numbers as Python floats (numpy's scalars and floats compare by value; a
    float's repr is its bits)."""
    return None if v is None else tuple(repr(float(x)) for x in v)


def test_a_slice_generator_draws_as_a_fresh_one() -> None:
    """The fits' seeded generator, kept and set back to its seed, draws what a fresh
    ``default_rng(n)`` draws, however it was used before and whichever sizes came between."""
    from tcf_hil.sic._field import _slice_rng

    for n in (3, 250, 3, 4096, 250):
        g = _slice_rng(n)
        a = (g.integers(0, n, size=(256, 3)), g.random(7))
        f = np.random.default_rng(n)
        b = (f.integers(0, n, size=(256, 3)), f.random(7))
        assert (a[0] == b[0]).all() and (a[1] == b[1]).all()


def test_degenerate_slices_fit_alike_compiled_and_in_numpy() -> None:
    """Three points (the circle through them), repeated points (a singular step: None),
    collinear points, float32 and Fortran-ordered points (numpy's path): compiled or not,
    the same answers."""
    from tcf_hil.sic._field import refine_circle

    _kernels_or_skip()
    three = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
    h = hyper_circle(three)
    assert h is not None and h.r == pytest.approx(1.0) and abs(h.cx) < 1e-12
    cases = [three, np.repeat(three[:1], 12, axis=0), np.column_stack(
        [np.linspace(0, 1, 20), np.zeros(20)]), three.astype(np.float32),
             np.asfortranarray(np.vstack([three, three + 1e-3]))]
    for q in cases:
        got = []
        for compiled in (False, True):
            with _fits(compiled):
                ref = refine_circle(q, 0.1, 0.1, 0.9, huber_m=0.01)
                tr = trimmed_circle(q, Circle(0.1, 0.1, 0.9, 0.0, 0.0), tol=0.01)
                rs = ransac_circle(q, r_max=2.0, tol=0.01)
            got.append((_floats(ref), _floats(tr), _floats(rs[:3]) if rs else None))
        assert got[0] == got[1], q


def test_stems_found_with_compiled_fits_are_the_numpy_ones() -> None:
    """The whole field algorithm on stems among whorls and needles: the same stems, to the
    bit, whether its fits run compiled or in numpy."""
    _kernels_or_skip()
    g = np.random.default_rng(11)
    pts = np.vstack([_stem_with_whorls(g, 0.0, 0.0, 0.12), _stem_with_whorls(g, 3.0, 1.0, 0.05),
                     _stem_with_whorls(g, 1.5, -2.0, 0.2)])
    keep = pts[:, 2] > PRM.ground_threshold_m
    width = np.where(np.arange(int(keep.sum())) % 5 == 0, 0.008, 0.0)
    docs = []
    for compiled in (False, True):
        with _fits(compiled):
            docs.append(repr(field_stems(pts[keep], width, np.zeros(int(keep.sum())), PRM)))
    assert docs[0] == docs[1]
    assert docs[0].count("'dbh'") == 3


def test_a_circle_through_two_neighbouring_stems_is_no_stem() -> None:
    """Two thin stems 80 cm apart, each seen on its facing side: a 40 cm circle passes
    through both arcs with nothing inside it, but one stem's bark is one arc."""
    g = np.random.default_rng(5)
    a1 = np.radians(g.uniform(-40, 40, 60))
    left = np.column_stack([-0.40 + 0.03 * np.cos(a1), 0.03 * np.sin(a1)]) + [-0.03, 0.0]
    a2 = np.radians(g.uniform(140, 220, 60))
    right = np.column_stack([0.40 + 0.03 * np.cos(a2), 0.03 * np.sin(a2)]) + [0.03, 0.0]
    xy = np.vstack([left, right]) + g.normal(0, 0.002, (120, 2))
    assert arc_fill(xy, 0.0, 0.0, 0.4) < 0.5
    f = stem_circle(xy, np.zeros(len(xy)), r_max=0.5, tol=0.02, min_points=6,
                    near=np.array([0.0, 0.0]))
    assert f is None or f[2] < 0.1  # one of the stems, not the circle through both
    bark = _arc(g, 0.0, 0.0, 0.2, 200.0, 100, 0.002)
    assert arc_fill(bark, 0.0, 0.0, 0.2) > 0.9


def test_a_clump_of_needles_is_no_stem() -> None:
    """Points filling a disc (a shrub, a clump of needles) have no hollow inside: no stem."""
    g = np.random.default_rng(1)
    rr = 0.3 * np.sqrt(g.uniform(0, 1, 400))
    a = g.uniform(0, 2 * math.pi, 400)
    xy = np.column_stack([rr * np.cos(a), rr * np.sin(a)])
    assert stem_circle(xy, np.zeros(len(xy)), r_max=0.5, tol=0.02, min_points=6) is None


def test_edge_returns_alone_give_the_radius_less_their_footprint() -> None:
    """A stem seen only through edge returns: the fit on them less their half widths."""
    g = np.random.default_rng(4)
    wide = _arc(g, 0.0, 0.0, 0.12, 200.0, 60, 0.002)  # the returns lie 2 cm outside a 10 cm
    width = np.full(len(wide), 0.02 / PRM.edge_correction)  # radius: the footprint's share
    f = stem_circle(wide, width, r_max=0.5, tol=0.012, min_points=6,
                    edge_share=PRM.edge_correction)
    assert f is not None and f[5] == 1
    assert f[2] == pytest.approx(0.10, abs=0.004)


# ------------------------------------------------------------ the emulated OS0-64, a pass
class _Pass:
    """The sensor drives along y at x = 0, 1 m/s, from y = -length."""

    def __init__(self, length: float) -> None:
        self.length = length

    def sensor_pose(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y = -self.length + (np.asarray(t_ns, float) - 1e9) / 1e9
        pos = np.column_stack([np.zeros(len(y)), y, np.zeros(len(y))])
        return pos, np.tile(np.eye(3), (len(y), 1, 1))


def _dbh_from_a_pass(dist: float, dbh: float, *, correct: bool,
                     seeds: tuple[int, ...] = (3, 4, 5)) -> float | None:
    """The field fit's DBH of a 2 m stem at ``dist`` from the track, from 20 frames of a
    1024x10 rev7 OS0-64 driving past it (returns within 0.5 m of the stem's centre height),
    one pass for each of ``seeds`` pooled (one pass's fit at 15 m varies by about 1 cm
    with the sensor's noise draws)."""
    from emulators.lidar import SENSOR_PRESETS, Os0Emulator
    from protocols.ouster import beam_rays, os0_64_metadata
    from tests.emulators.test_physics import scene

    meta = os0_64_metadata(mode="1024x10")
    length = min(dist, 10.0)
    sensor = dataclasses.replace(SENSOR_PRESETS["os0-64-rev7"], false_positive_rate=0.0)
    o, d = beam_rays(meta)
    xy, ww = [], []
    frames = np.linspace(0, 20 * length - 1, 20).astype(int)
    emus = [Os0Emulator(meta, scene(dist, dbh), _Pass(length), sensor=sensor, seed=seed,
                        threads=1) for seed in seeds]
    for emu, k in ((emu, k) for emu in emus for k in frames):
        fr = emu.frame(int(k))
        rng = fr.fields["RANGE"]
        t = rng.astype(float) / 1000.0 - meta.lidar_origin_to_beam_origin_mm / 1000.0
        p = o + d * t[..., None] + fr.positions[None, :, :]
        w = edge_widths(rng, np.arange(meta.columns), meta.columns, 0.35, 0.3)
        near = (rng > 0) & (np.abs(p[..., 2]) < 0.5) & (np.hypot(p[..., 0] - dist,
                                                                 p[..., 1]) < 0.5)
        xy.append(p[near][:, :2])
        ww.append(w[near])
    if not correct:  # a plain circle fit to every return, as a naive program does
        c = fit_circle(np.vstack(xy))
        return None if c is None else 2.0 * c.r
    f = stem_circle(np.vstack(xy), np.concatenate(ww).astype(float), r_max=0.5, tol=0.012,
                    min_points=6, edge_share=PRM.edge_correction)
    return None if f is None else 2.0 * f[2]


@pytest.mark.parametrize("dist", [5.0, 10.0, 15.0])
def test_the_footprint_correction_on_a_stem_seen_from_a_pass(dist: float) -> None:
    """README ("The reference onboard SIC"): the rev7 footprint widens a 30 cm stem by 5-15
    cm in a plain circle fit (+2.5, +5.9, +10.5 cm at 5, 10, 15 m here, three passes
    pooled); with the edge returns kept out the DBH is within 2 cm (+0.6, +1.1, +0.9 cm;
    over four sets of three seeds +0.5..+0.6, +0.8..+1.4, -0.1..+1.6 cm)."""
    plain = _dbh_from_a_pass(dist, 0.3, correct=False)
    field = _dbh_from_a_pass(dist, 0.3, correct=True)
    print(f"{dist} m: plain {plain}, field {field}")
    assert plain is not None and field is not None
    assert plain - 0.3 > 0.02
    assert abs(field - 0.3) < min(0.02, (plain - 0.3) / 2)


# ------------------------------------------------------------------ stems and branches
def _stem_with_whorls(g: np.random.Generator, x: float, y: float, r: float
                      ) -> np.ndarray:
    """A vertical stem's front half (points every ~2 cm) from 0 to 6 m, with a whorl of six
    1.5 m branches every 1 m from 1.5 m up, and needles around them."""
    z = np.arange(0.0, 6.0, 0.02)
    a = np.radians(np.arange(-100.0, 100.0, 8.0))
    zz, aa = np.meshgrid(z, a)
    rr = r + g.normal(0, 0.002, zz.shape)
    stem = np.column_stack([x + (rr * np.cos(aa)).ravel(), y + (rr * np.sin(aa)).ravel(),
                            zz.ravel()])
    parts = [stem]
    for hz in np.arange(1.5, 6.0, 1.0):
        for b in np.radians(np.arange(0.0, 360.0, 60.0)):
            s = np.arange(r, 1.5, 0.02)
            br = np.column_stack([x + s * np.cos(b), y + s * np.sin(b), hz + 0.1 * s])
            needles = br[::3] + g.normal(0, 0.08, (len(br[::3]), 3))
            parts += [br, needles]
    return np.vstack(parts)


def test_stems_among_whorls_and_needles_are_found_once_and_branches_never() -> None:
    g = np.random.default_rng(7)
    pts = np.vstack([_stem_with_whorls(g, 0.0, 0.0, 0.12),
                     _stem_with_whorls(g, 3.0, 1.0, 0.05)])
    ground = np.zeros(len(pts))
    keep = pts[:, 2] > PRM.ground_threshold_m
    trees = field_stems(pts[keep], np.zeros(int(keep.sum())), ground[keep], PRM)
    assert len(trees) == 2, [(t["x"], t["y"], t["dbh"]) for t in trees]
    got = sorted(trees, key=lambda t: t["x"])
    for t, (x, y, dbh) in zip(got, ((0.0, 0.0, 0.24), (3.0, 1.0, 0.10)), strict=True):
        assert math.hypot(t["x"] - x, t["y"] - y) < 0.01
        assert t["dbh"] == pytest.approx(dbh, abs=0.01)
        assert t["class"] == "S"


def test_the_stem_is_not_followed_onto_something_wider_beside_it() -> None:
    """Up the stem, a slice must taper and stay on the line: a stem hidden above 4.5 m
    beside a wider clump 8 cm off (a neighbour's branches) is not followed onto it, which
    would bend its curve into a crook."""
    g = np.random.default_rng(3)
    a = np.radians(np.arange(-100.0, 100.0, 6.0))

    def half_cylinder(x: float, r: float, z0: float, z1: float) -> np.ndarray:
        zz, aa = np.meshgrid(np.arange(z0, z1, 0.02), a)
        rr = r + g.normal(0, 0.002, zz.shape)
        return np.column_stack([x + (rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel(),
                                zz.ravel()])

    pts = np.vstack([half_cylinder(0.0, 0.10, 0.3, 4.5), half_cylinder(0.08, 0.125, 4.5, 8.0)])
    trees = field_stems(pts, np.zeros(len(pts)), np.zeros(len(pts)), PRM)
    assert len(trees) == 1
    t = trees[0]
    assert max(c[0] for c in t["curve"]) < 4.6, t["curve"]
    assert t["class"] == "S" and t["dbh"] == pytest.approx(0.2, abs=0.01)


def test_a_stem_that_ends_in_the_band_is_no_tree() -> None:
    """A stem-sized cylinder with nothing above the band over it (a stump, a shrub's stem,
    a sapling) is no tree; the same cylinder going on above the band is one."""
    g = np.random.default_rng(5)
    a = np.radians(np.arange(-100.0, 100.0, 6.0))

    def stem(top: float) -> np.ndarray:
        zz, aa = np.meshgrid(np.arange(0.3, top, 0.02), a)
        rr = 0.06 + g.normal(0, 0.002, zz.shape)
        return np.column_stack([(rr * np.cos(aa)).ravel(), (rr * np.sin(aa)).ravel(),
                                zz.ravel()])

    for top, n in ((3.6, 0), (7.0, 1)):
        pts = stem(top)
        trees = field_stems(pts, np.zeros(len(pts)), np.zeros(len(pts)), PRM)
        assert len(trees) == n, (top, [(t["dbh"], t["h"]) for t in trees])


# ------------------------------------------------------------------------------ classes
def _curve(shape: str) -> tuple[np.ndarray, np.ndarray]:
    z = np.arange(0.75, 10.0, 0.5)
    x = np.zeros_like(z)
    if shape == "bow":  # a sweep of 8 cm over a 16 m stem, seen up to 10 m
        x = 0.08 * 4 * z * (16.0 - z) / 16.0**2
    elif shape == "crook":  # a 7 cm sideways step at 5 m
        x = np.where(z >= 5.0, 0.07, 0.0)
    elif shape == "lean":  # 2 degrees, straight
        x = z * math.tan(math.radians(2.0))
    g = np.random.default_rng(0)
    c = np.column_stack([x + g.normal(0, 0.004, len(z)), g.normal(0, 0.004, len(z))])
    return z, c


@pytest.mark.parametrize(("shape", "cls"), [("straight", "S"), ("lean", "S"), ("bow", "C"),
                                            ("crook", "X")])
def test_the_class_from_the_stem_curve(shape: str, cls: str) -> None:
    z, c = _curve(shape)
    bow, crook = stem_form(z, c, 16.0, PRM)
    got = ("X" if crook >= PRM.crook_m or bow >= PRM.other_threshold_m else
           "C" if bow >= PRM.curve_threshold_m else "S")
    assert got == cls, (bow, crook)


# ------------------------------------------------------------- a live natural stand
def pine_thinning_corner(path: Path, half_m: float) -> Path:
    """A 0.16 ha corner of ``pine-thinning`` (its 2,200 stems/ha: 352 on 40 x 40 m) as a
    scenario file at ``path``, the track ``half_m`` each side of the plot's centre line."""
    from tcf_hil.scenario import (
        load_scenario,
        scenario_from_dict,
        scenario_to_dict,
        scenario_to_toml,
    )

    d = scenario_to_dict(load_scenario("pine-thinning"))
    d["name"] = "pine-thinning-corner"
    d["plot"]["size_m"] = [40.0, 40.0]
    d["stems"]["count"] = 352
    d["track"]["start_m"], d["track"]["end_m"] = [0.0, -half_m, 2.0], [0.0, half_m, 2.0]
    path.write_text(scenario_to_toml(scenario_from_dict(d)))
    return path


@pytest.mark.slow  # about 3 minutes: .ci/run's second lane
def test_a_live_run_of_a_natural_stand_scores_above_the_floor(tmp_path: Path) -> None:
    """A regression guard, not the aim: a 0.16 ha corner of ``pine-thinning`` (2,200 stems/ha,
    branches, crowns, understory) driven 24 m at 1024x10 on the wire, the field SIC as its
    own process. Floors from a run measured on this 2-core machine under load: within 5 m
    of the track 43 of 47 stems found, DBH RMSE 1.6 cm; 5-10 m, 99 of 110 and 3.0 cm (the
    emulator streams natural stands below real time: half speed, and the SIC waits 20 s for
    a late packet instead of 3). The SIC's stem worker finishes its last tiles after the
    stream; with run's default 30 s grace it was killed with a third of the stems unpublished
    on a loaded machine, hence --grace 300 (it exits as soon as it is done)."""
    import json
    import subprocess
    import sys

    toml = pine_thinning_corner(tmp_path / "corner.toml", 12.0)
    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "tcf_hil.cli", "run", str(toml), "--mode",
                        "1024x10", "--speed", "0.5", "--sic",
                        "{python} -m tcf_hil.sic --idle 20", "--grace", "300",
                        "--out", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    score = json.loads((out / "score.json").read_text())
    bands = {b["from_m"]: b for b in score["by_distance"]["bands"]}
    sic = json.loads((out / "manifest.json").read_text())["sic"]
    assert sic["ended_by"] is None, sic  # the SIC published its final forest and exited
    assert sic["final_forest"] is True, sic
    assert bands[0.0]["detection"] >= 0.8, bands[0.0]
    assert bands[0.0]["dbh_rmse_m"] <= 0.04, bands[0.0]
    assert bands[5.0]["detection"] >= 0.75, bands[5.0]
    assert bands[5.0]["dbh_rmse_m"] <= 0.05, bands[5.0]
    assert score["all_trees"]["false_positives"] <= 0.1 * score["all_trees"]["n_observed"]
