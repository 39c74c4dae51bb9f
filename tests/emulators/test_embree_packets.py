"""Packets of rays (``rtcIntersect8``, emulators.embree.intersect_packet) answer each ray as
``rtcIntersect1`` answers it alone: traced as incoherent packets (ray by ray inside Embree)
bit for bit - distance, primitive and the curves' |cos incidence| - on robust triangles with
shared edges and vertices, round curves with their discs and joints, and the terrain grid;
traced as coherent packets (the default: the lidar's packets are a beam's neighbouring
columns) to a few float32 units in the last place, the same hit or miss, another primitive
only at a tie (a ray through an edge or vertex primitives share). And the lidar emulator's
fused kernels write the same packets with coherent packets, incoherent ones and ray by ray
(default and ideal sensor)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.jit import jit_enabled

pytestmark = pytest.mark.skipif(not jit_enabled(), reason="compiled kernels are off here "
                                "(TCF_HIL_NO_JIT or no numba): no directly bound Embree")


def _packet_kernel():
    """A compiled loop casting rays through :func:`intersect_packet` in packets of
    :data:`PACKET` (the last one partly filled)."""
    from emulators.embree import PACKET, intersect_packet, new_packet, packet_ray
    from emulators.jit import numba_module

    numba = numba_module()

    @numba.njit(nogil=True)
    def cast(scenes, o, d, t, prim, cn):
        pf, pu, paddr, valid, vaddr = new_packet()
        pt = np.empty(PACKET, np.float32)
        pp = np.empty(PACKET, np.int32)
        pc = np.empty(PACKET, np.float64)
        for a in range(0, o.shape[0], PACKET):
            n = min(PACKET, o.shape[0] - a)
            for j in range(n):
                packet_ray(pf, pu, j, o[a + j, 0], o[a + j, 1], o[a + j, 2], d[a + j, 0],
                           d[a + j, 1], d[a + j, 2])
            intersect_packet(scenes, pf, pu, paddr, valid, vaddr, n, pt, pp, pc)
            for j in range(n):
                t[a + j], prim[a + j], cn[a + j] = pt[j], pp[j], pc[j]

    return cast


_CAST = None


def _packets(ds, o, d, coherent: bool = False):
    """The rays cast in packets, incoherent (Embree answers each lane as the ray alone)
    unless ``coherent`` (the scene's own arguments, as the lidar's kernels cast)."""
    global _CAST
    if _CAST is None:
        _CAST = _packet_kernel()
    t = np.empty(len(o), np.float32)
    prim = np.empty(len(o), np.int32)
    cn = np.empty(len(o), np.float32)
    flags = ds.packet_args.view(np.uint32)
    own = int(flags[0])
    flags[0] = own if coherent else 0  # RTC_RAY_QUERY_FLAG_INCOHERENT
    try:
        _CAST(ds.handles, o, d, t, prim, cn)
    finally:
        flags[0] = own
    return t, prim, cn


def _ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many float32 steps apart (finite, positive distances)."""
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


def _scene(curves: bool, terrain: bool) -> Any:
    """A folded sheet of triangles sharing edges and vertices (robust), a few triangles cast
    loose after it, tapered tubes in joined segments with discs, and a terrain grid."""
    from emulators.embree import Curves, DirectScene, HeightGrid

    g = np.linspace(-4.0, 4.0, 9)
    xx, zz = np.meshgrid(g, g)
    v = np.column_stack([xx.ravel(), 6.0 + 0.5 * np.sin(xx.ravel() * zz.ravel()),
                         zz.ravel() + 2.0])
    faces = []
    for i in range(8):
        for j in range(8):
            a = i * 9 + j
            faces += [(a, a + 1, a + 9), (a + 1, a + 10, a + 9)]
    loose = np.array([[-1.0, 3.0, 0.5], [1.0, 3.0, 0.5], [0.0, 3.0, 2.5]])
    v = np.vstack([v, loose]).astype(np.float32)
    f = np.array(faces + [(81, 82, 83)], np.int64)
    cv = None
    if curves:
        pts = []
        for x, r in ((-2.0, 0.3), (1.5, 0.15), (3.0, 0.4)):
            u = np.linspace(0.0, 1.0, 4)
            pts.append(np.column_stack([np.full(4, x), np.full(4, 4.0), -1.0 + 5.0 * u,
                                        r * (1.0 - 0.4 * u)]))
        p = np.vstack(pts).astype(np.float32)
        seg = np.array([0, 1, 2, 4, 5, 6, 8, 9, 10], np.uint32)
        flags = np.tile(np.array([2, 3, 1], np.uint8), 3)
        discs = np.array([[-2.0, 4.0, -1.0, 0.3], [1.5, 4.0, -1.0, 0.15]], np.float32)
        cv = Curves(p, seg, flags, discs, np.array([[0, 0, -1], [0, 0, -1]], np.float32),
                    p[[1, 2, 5, 6, 9, 10]])
    hg = None
    if terrain:
        xs = np.linspace(-20.0, 20.0, 41)
        z = 0.3 * np.sin(xs[None, :] * 0.7) * np.cos(xs[:, None] * 0.4) - 1.5
        hg = HeightGrid.lattice(xs, xs, z)
    return DirectScene(v, f, cv, loose_from=len(f) - 1, terrain=hg)


def _rays(seed: int, n: int, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays from near the origin: neighbours a little apart (``spread`` radians, as a
    beam's columns are) about random directions, some aimed at the sheet's vertices."""
    rng = np.random.default_rng(seed)
    o = (rng.normal(0.0, 0.05, (n, 3)) + [0.0, -1.0, 1.0]).astype(np.float32)
    base = rng.normal(0.0, 1.0, (n // 8 + 1, 3)).repeat(8, axis=0)[:n]
    d = base / np.linalg.norm(base, axis=1)[:, None] + rng.normal(0.0, spread, (n, 3))
    aim = rng.random(n) < 0.25  # at a vertex of the sheet (near it: float32 directions)
    verts = np.array([[x, 6.0 + 0.5 * np.sin(x * z), z + 2.0] for x in range(-4, 5)
                      for z in range(-4, 5)])
    d[aim] = verts[rng.integers(0, len(verts), aim.sum())] - o[aim]
    d /= np.linalg.norm(d, axis=1)[:, None]
    return o, d.astype(np.float32)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 300),
       spread=st.sampled_from([0.0, 1e-4, 3e-3, 0.3]), curves=st.booleans(),
       terrain=st.booleans())
def test_packets_answer_each_ray_as_it_is_answered_alone(seed: int, n: int, spread: float,
                                                         curves: bool, terrain: bool) -> None:
    ds = _scene(curves, terrain)
    if ds.handles[3] == 0:
        pytest.skip("this Embree traces no native packets of 8 here: rays go one by one")
    o, d = _rays(seed, n, spread)
    t1, p1, c1 = ds.cast_n(o, d)
    t8, p8, c8 = _packets(ds, o, d)
    if n >= 100:  # aimed at the scene: some hit (an empty comparison proves nothing)
        assert (p1 != -1).sum() >= n // 10
    assert t1.tobytes() == t8.tobytes()
    assert np.array_equal(p1, p8)
    if len(c1):
        assert c1.tobytes() == c8.tobytes()
    # coherent packets: the same hits and misses, distances a few units in the last place
    # apart (so where the primitive is another, the two are tied to those units)
    tc, pc, cc = _packets(ds, o, d, coherent=True)
    hit = np.isfinite(t1)
    assert np.array_equal(hit, np.isfinite(tc)) and np.array_equal(hit, pc != -1)
    assert (_ulps(t1[hit], tc[hit]) <= 4).all()
    same = p1 == pc
    if len(c1):
        assert np.allclose(c1[same & hit], cc[same & hit], atol=1e-5)


def test_ties_go_as_they_go_ray_by_ray() -> None:
    """Exact ties: a square of two triangles and a coincident copy of it (other indices),
    hit by axis-aligned rays with exact coordinates along the shared diagonal, through the
    corners and the edges, and across the whole square; each lane's primitive is the one
    the ray alone gets (incoherent packets; coherent ones hit the square at the same
    distance)."""
    from emulators.embree import DirectScene

    sq = np.array([[0, 5, 0], [1, 5, 0], [1, 5, 1], [0, 5, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    ds = DirectScene(np.vstack([sq, sq]), f)
    if ds.handles[3] == 0:
        pytest.skip("this Embree traces no native packets of 8 here")
    g = np.linspace(0.0, 1.0, 17, dtype=np.float32)  # exact in float32 (sixteenths)
    xs, zs = np.meshgrid(g, g)
    o = np.column_stack([xs.ravel(), np.zeros(xs.size), zs.ravel()]).astype(np.float32)
    diag = np.column_stack([g, np.zeros(17), g]).astype(np.float32)
    o = np.vstack([diag, o, diag[::-1]])
    d = np.tile(np.array([0, 1, 0], np.float32), (len(o), 1))
    t1, p1, _ = ds.cast_n(o, d)
    t8, p8, _ = _packets(ds, o, d)
    assert (p1 >= 0).all()  # every ray meets the square
    assert t1.tobytes() == t8.tobytes() and np.array_equal(p1, p8)
    tc, pc, _ = _packets(ds, o, d, coherent=True)  # coherent: a tie may go the other way
    assert (pc >= 0).all() and (_ulps(t1, tc) <= 4).all()


def test_a_scene_with_crowns_casts_ray_by_ray() -> None:
    """Porous crowns answer through a callback that takes one ray: no packets there."""
    from emulators.embree import DirectScene
    from emulators.media import Crowns

    v = np.array([[0, 5, 0], [1, 5, 0], [0, 5, 1]], np.float32)
    crowns = Crowns(np.array([[0.0, 8.0, 6.0]]), np.array([[0.0, 0.0, -1.0]]),
                    np.array([4.0]), np.array([1.5]), np.array([0.0]),
                    np.array([1], np.int8), np.array([0.8]))
    ds = DirectScene(v, np.array([[0, 1, 2]]), crowns=crowns)
    assert ds.handles[3] == 0


def test_fused_frames_are_the_same_with_and_without_packets_coherent_or_not() -> None:
    """The lidar emulator's fused kernels (the physical sensor's centre rays, the ideal
    sensor's answer) with incoherent packets and ray by ray: the same packets and stem
    ids; with coherent packets (the default) the same but for a pixel in thousands whose
    distance, a few float32 units in the last place away, rounds to the next millimetre."""
    from emulators.lidar import Os0Emulator, ReturnModel, SensorModel
    from protocols.ouster import os0_64_metadata
    from tcf_hil.scenario import scenario_from_dict
    from tcf_hil.world.forest import generate_forest
    from tcf_hil.world.scene import Scene
    from tcf_hil.world.track import Trajectory

    scn = scenario_from_dict({
        "plot": {"size_m": [20.0, 30.0]}, "stems": {"count": 30, "lean_deg": [0.0, 8.0]},
        "terrain": {"kind": "rolling", "amplitude_m": 0.6, "wavelength_m": 12.0},
        "track": {"start_m": [0.0, -20.0, 2.0], "end_m": [0.0, 20.0, 2.0]}})
    forest = generate_forest(scn)
    track = Trajectory.from_config(scn.track, forest.terrain)
    meta = os0_64_metadata("512x10")
    for geometry in ("curves", "mesh"):
        scene = Scene.from_forest(forest, geometry=geometry)
        ds = scene.caster.direct_scene
        assert ds is not None
        if ds.handles[3] == 0:
            pytest.skip("this Embree traces no native packets of 8 here")
        for sensor in (SensorModel(), None):  # the realistic sensor, the ideal
            frames = []
            flags = ds.packet_args.view(np.uint32)
            for how in ("coherent packets", "incoherent packets", "single rays"):
                handles, coherent = ds.handles, int(flags[0])
                if how == "single rays":
                    ds.handles = (*handles[:3], 0, handles[4])
                elif how == "incoherent packets":
                    flags[0] = 0  # RTC_RAY_QUERY_FLAG_INCOHERENT
                try:
                    emu = Os0Emulator(meta, scene, track, ReturnModel(), seed=3,
                                      start_ns=track.t0_ns, sensor=sensor, threads=2)
                    frames.append([emu.frame(k) for k in (4, 5)])
                finally:
                    ds.handles, flags[0] = handles, coherent
            for a, b in zip(frames[1], frames[2], strict=True):  # incoherent: to the bit
                assert np.array_equal(a.packets, b.packets)
                assert np.array_equal(a.stem_id, b.stem_id)
            for a, b in zip(frames[0], frames[2], strict=True):  # coherent: a few pixels'
                # distance crosses a millimetre's rounding (or a tie goes the other way)
                fa, fb = a.fields, b.fields
                assert (a.stem_id != b.stem_id).mean() < 1e-3
                for name in fa:
                    assert (fa[name] != fb[name]).mean() < 1e-3
                both = (fa["RANGE"] > 0) & (fb["RANGE"] > 0)
                gap = np.abs(fa["RANGE"][both].astype(np.int64) - fb["RANGE"][both])
                assert (gap <= 1).all()  # mm
            assert (frames[0][0].stem_id > 0).sum() > 100
