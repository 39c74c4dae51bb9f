"""Numerical hard cases (issue 7): each is one test that breaks if the bench loses precision,
lets a ray slip through geometry, or mishandles a wrap.

The whole-path cases go through the wire's bytes: the emulator's Ouster packets (CRC and all)
and the harvester's CANopen TPDOs, decoded by the reference SIC as it decodes them live
(``tcf_hil.experiments.offline``), then scored against the ground truth.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from emulators.jit import jit_enabled
from protocols.harvester._codec import encode_pose
from protocols.ouster import decode_lidar_packet
from tcf_hil.devices.harvester import HarvesterModel
from tcf_hil.devices.lidar import LidarRun, sensor_metadata
from tcf_hil.devices.offline import record_pcap
from tcf_hil.experiments.offline import OfflineSic, run_offline
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.sic import identify_stems
from tcf_hil.sic._circle import fit_circle
from tcf_hil.world.forest import Forest, generate_forest, ground_truth
from tcf_hil.world.forest.generate import classify
from tcf_hil.world.forest.sampling import sample_surfaces
from tcf_hil.world.forest.stems import StemSet
from tcf_hil.world.scene import Scene
from tcf_hil.world.terrain import Terrain
from tcf_hil.world.track import Trajectory

BACKENDS = ["embree", "open3d"]
UTM = (500_000.0, 6_900_000.0, 120.0)


def _metrics(res):  # type: ignore[no-untyped-def]
    return res.scores.all.metrics


def _small(extra: dict | None = None) -> dict:
    """Forest II (24 stems, 20 x 40 m, a 50 s track: quick to run whole), with the tables
    of ``extra`` merged in, seen by the ``ideal`` sensor: these cases hold exact geometry
    (the realistic default's noise and footprint are the sensor tests' business)."""
    base = scenario_to_dict(load_scenario("forest-ii"))
    base["sensor"] = {"preset": "ideal"}
    for k, v in (extra or {}).items():
        base[k] = {**base[k], **v} if isinstance(v, dict) else v
    return base


# ----------------------------------------------------------------- geographic origin (UTM)
@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_utm_origin_scores_the_same_through_the_whole_wire_path() -> None:
    """Forest II at (0, 0) and at UTM easting 500 000 m, northing 6 900 000 m: the packets,
    the CAN poses (int32 mm relative to the node's datum), the SIC's map and its JSON keep
    float64 metres, so the scores agree and every stem lands within a millimetre of where the
    same stem lands at the origin."""
    at0 = run_offline(scenario_from_dict(_small()), mode="512x10", max_frames=250)
    utm = run_offline(scenario_from_dict(_small({"plot": {"size_m": [20.0, 40.0],
                                                          "origin_m": list(UTM)}})),
                      mode="512x10", max_frames=250)
    m0, m1 = _metrics(at0), _metrics(utm)
    assert m0["total_matches"] == m1["total_matches"] >= 12
    assert m0["em"]["matrix"] == m1["em"]["matrix"]
    assert abs(m0["position_rmse_m"] - m1["position_rmse_m"]) < 1e-3
    assert m1["position_rmse_m"] < 0.02  # a float32 anywhere would smear this to decimetres
    a = sorted(o["cp"] for o in at0.forest_doc["objects"])
    b = sorted(np.subtract(o["cp"], UTM).tolist() for o in utm.forest_doc["objects"])
    assert len(a) == len(b)
    np.testing.assert_allclose(np.array(b)[:, :2], np.array(a)[:, :2], atol=1e-3)
    for oa, ob in zip(sorted(at0.forest_doc["objects"], key=lambda o: o["cp"]),
                      sorted(utm.forest_doc["objects"], key=lambda o: o["cp"]), strict=True):
        assert abs(oa["dbh"] - ob["dbh"]) < 1e-3 and oa["class"] == ob["class"]


# ------------------------------------------------------------------------- grazing rays
def _inside_bounds(forest: Forest, o: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Both ends over the terrain mesh (so the segment is) and the origin above the ground."""
    x0, y0, x1, y1 = forest.bounds()
    ok = np.ones(len(o), bool)
    for p in (o, target):
        ok &= (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)
    return ok & (o[:, 2] > forest.terrain.height(o[:, 0], o[:, 1]) + 0.05)


def _grazing_rays(scene: Scene, forest: Forest, rng: np.random.Generator, n: int,
                  depth_m: float = 2e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays that graze stem silhouettes: each runs parallel to a stem triangle, ``depth_m``
    behind it (inside the stem), so it can only enter through a neighbouring face, edge or
    vertex at a grazing angle; from 3-30 m away. Returns origins, directions, and the
    distance to that inside point (a hit must come no later)."""
    stem_faces = np.flatnonzero(scene.stem_id > 0)
    f = stem_faces[rng.integers(0, len(stem_faces), 2 * n)]
    tri = scene.vertices[scene.faces[f]]
    c = tri.mean(axis=1)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(nrm, axis=1)
    sid = (scene.stem_id[f] - 1).astype(np.int64)
    st = forest.stems
    s = np.einsum("ij,ij->i", c - st.base[sid], st.axis[sid])
    out = c - st.centre(sid, s)
    keep = (area2 > 1e-8) & (np.linalg.norm(out, axis=1) > 0.01)
    nrm = nrm / np.maximum(area2, 1e-300)[:, None]
    nrm *= np.sign(np.einsum("ij,ij->i", nrm, out))[:, None]  # outward
    target = c - depth_m * nrm
    o, d, dist = _across(target, nrm, st.tangent(sid, s), rng)
    keep &= _inside_bounds(forest, o, target)
    k = np.flatnonzero(keep)[:n]
    return o[k], d[k], dist[k]


def _across(target: np.ndarray, nrm: np.ndarray, ax: np.ndarray, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays to ``target`` from 3-30 m away, each in the plane normal to ``nrm``, across the
    stem whose axis is ``ax`` (as a lidar ray meets it) and tilted up or down by up to 17
    degrees (along the stem it would start inside it): origins, directions, distances."""
    m = len(target)
    e = np.cross(nrm, ax) * rng.choice([-1.0, 1.0], m)[:, None]
    e += rng.uniform(-0.3, 0.3, m)[:, None] * ax
    d = e - np.einsum("ij,ij->i", e, nrm)[:, None] * nrm
    d /= np.linalg.norm(d, axis=1)[:, None]
    dist = rng.uniform(3.0, 30.0, m)
    return target - dist[:, None] * d, d, dist


def _terrain_edge_rays(scene: Scene, forest: Forest, rng: np.random.Generator, n: int,
                       depth_m: float = 2e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays at 2-6 degrees below the horizontal aimed just under the terrain mesh's shared
    edges and vertices (where a caster that is not watertight lets rays slip through): the
    terrain as :func:`~tcf_hil.world.forest.terrain_mesh` triangulates it, which the scene's
    triangles or (round curves beside it) its Embree grid follow."""
    from tcf_hil.world.forest import terrain_mesh

    tm = terrain_mesh(forest.terrain, forest.bounds(),
                      forest.scenario.terrain.tolerance_mm / 1000.0)
    f = np.asarray(tm.faces)[rng.integers(0, len(tm.faces), 2 * n)]
    a, b = tm.vertices[f[:, 0]], tm.vertices[f[:, 1]]
    w = rng.choice([0.0, 0.5, 1.0], 2 * n)[:, None]  # a vertex, an edge midpoint, the other
    target = a + w * (b - a)
    target[:, 2] -= depth_m
    az = rng.uniform(0, 2 * math.pi, 2 * n)
    el = np.radians(rng.uniform(2.0, 6.0, 2 * n))
    d = np.column_stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), -np.sin(el)])
    dist = rng.uniform(5.0, 40.0, 2 * n)
    o = target - dist[:, None] * d
    k = np.flatnonzero(_inside_bounds(forest, o, target))[:n]
    return o[k], d[k], dist[k]


def _grazing_curve_rays(forest: Forest, rng: np.random.Generator, n: int,
                        depth_m: float = 2e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_grazing_rays` for the true surface (what round curves cast): each ray runs in
    the plane tangent to a stem at a random point, ``depth_m`` inside it."""
    st = forest.stems
    sid = rng.integers(0, len(st), 2 * n)
    s = rng.uniform(0.0, 0.95, 2 * n) * st.length[sid]
    u, b = st.ring_frame(sid, s)
    th = rng.uniform(0.0, 2.0 * math.pi, 2 * n)[:, None]
    out = np.cos(th) * u + np.sin(th) * b
    target = st.centre(sid, s) + (st.radius(sid, s) - depth_m)[:, None] * out
    o, d, dist = _across(target, out, st.tangent(sid, s), rng)
    k = np.flatnonzero(_inside_bounds(forest, o, target))[:n]
    return o[k], d[k], dist[k]


# Embree's round linear curves with neighbour flags cut two segments' tubes at their joint, and a
# ray grazing the surface there could slip through the cut (4 of 400,000 rays 0.2 mm inside
# forest-iv's stems, each caught about 6 mm on): a sphere inside the surface at each joint
# (stem_curves' joints) closes it. Natural stems show it more often (the test below).
@pytest.mark.parametrize("backend", [*BACKENDS, "embree-curves"])
def test_grazing_rays_never_pass_through_geometry(backend: str, forest_iv: Forest) -> None:
    """Rays grazing stem silhouettes and skimming the terrain across its shared mesh edges,
    each aimed 0.2 mm inside the geometry: every one must report a hit no later than that
    point (a watertight caster; Embree runs in robust mode for exactly this). Stems as
    meshes on every backend, and as Embree's round curves, aimed inside the true surface."""
    curves = backend == "embree-curves"
    if curves and not jit_enabled():
        pytest.skip("round curves need compiled kernels (TCF_HIL_NO_JIT or no numba)")
    scene = Scene.from_forest(forest_iv, backend="embree" if curves else backend,
                              geometry="curves" if curves else "mesh")
    rng = np.random.default_rng(7)
    stems = ([_grazing_curve_rays(forest_iv, rng, 40_000) for _ in range(10)] if curves
             else [_grazing_rays(scene, forest_iv, rng, 40_000)])
    for o, d, dist in [*stems, _terrain_edge_rays(scene, forest_iv, rng, 40_000)]:
        assert len(o) > 30_000
        t, sid = scene.cast(o, d)
        through = ~(t <= dist + 1e-4)
        assert not through.any(), (
            f"{backend}: {int(through.sum())} of {len(t)} rays passed through, e.g. origin "
            f"{o[through][0].tolist()} direction {d[through][0].tolist()}")
        assert (sid >= 0).all()


@pytest.mark.skipif(not jit_enabled(), reason="round curves need compiled kernels")
def test_grazing_rays_never_slip_through_natural_stems_as_curves() -> None:
    """400,000 rays each grazing natural stems 0.2 mm inside the true surface (test_curves'
    stand: butt swell, crooks, bows, broken tops), from the ground to the top: none passes
    through. Without the joint spheres 12–15 did here; with them but the rings spaced for a
    crook only from where it starts, 2 (crossing a stem whole, just before a crook)."""
    from test_curves import NATURAL  # tests/tcf_hil: the natural stand of the curve tests

    forest = generate_forest(scenario_from_dict(NATURAL))
    scene = Scene.from_forest(forest, backend="embree", geometry="curves")
    rng = np.random.default_rng(11)
    for _ in range(10):
        o, d, dist = _grazing_curve_rays(forest, rng, 40_000)
        assert len(o) > 30_000
        t, _ = scene.cast(o, d)
        through = ~(t <= dist + 1e-4)
        assert not through.any(), f"{int(through.sum())} of {len(t)} rays passed through"


# ------------------------------------------------------------ sensor inside a bounding box
def _leaning_pair() -> Forest:
    """Two stems leaning 30 degrees over a track along y at x = 0 (the sensor passes inside
    their bounding boxes, under the stems), and one stem standing on the track itself."""
    scn = scenario_from_dict({"plot": {"size_m": [20.0, 20.0]}, "stems": {"count": 0},
                              "sensor": {"preset": "ideal"},
                              "track": {"start_m": [0.0, -8.0, 2.0], "end_m": [0.0, 8.0, 2.0]}})
    lean = math.radians(30.0)
    axis = np.array([[-math.sin(lean), 0.0, math.cos(lean)], [math.sin(lean), 0.0, math.cos(lean)],
                     [0.0, 0.0, 1.0]])
    base = np.array([[3.0, -3.0, 0.0], [-3.0, 3.0, 0.0], [0.0, 6.0, 0.0]])
    bend = np.array([[0.0, 1.0, 0.0]] * 3)
    n = 3
    stems = StemSet(base=base, axis=axis, bend=bend, length=np.array([16.0, 16.0, 12.0]),
                    sweep=np.zeros(n), peak=np.full(n, 0.5), r_bh=np.full(n, 0.15),
                    r_top=np.full(n, 0.015), taper=np.full(n, 0.8), below=np.full(n, 0.5))
    return Forest(scenario=scn, seed=0, terrain=Terrain.flat(), stems=stems,
                  classes=np.array(["S", "S", "S"]), lean_deg=np.array([30.0, 30.0, 0.0]))


def _assert_on_true_surfaces(forest: Forest, o: np.ndarray, d: np.ndarray, t: np.ndarray,
                             sid: np.ndarray) -> None:
    """Every stem hit lies within the 2 mm mesh tolerance of the true surface of the stem it
    is labelled with, and nearer to that stem's surface than to any other stem's (centre
    lines sampled every 2 mm; the buried end and the last 0.3 m below the tip, where the
    mesh closes, are left out)."""
    st = forest.stems
    cs, rs, ids, ss = [], [], [], []
    for i in range(len(st)):
        s = np.arange(-st.below[i], st.length[i], 0.002)
        cs.append(st.centre(np.full(len(s), i), s))
        rs.append(st.radius(np.full(len(s), i), s))
        ids.append(np.full(len(s), i + 1))
        ss.append(s)
    tree = cKDTree(np.vstack(cs))
    radii, owner, along = np.concatenate(rs), np.concatenate(ids), np.concatenate(ss)
    p = o + t[:, None] * d
    dist, k = tree.query(p, k=64)
    gap = np.abs(dist - radii[k])  # distance from each sampled stem's surface
    best = np.argmin(gap, axis=1)
    kb = k[np.arange(len(p)), best]
    body = (along[kb] > 0.0) & (along[kb] < st.length[owner[kb] - 1] - 0.3)
    assert body.mean() > 0.9
    assert np.all(owner[kb][body] == sid[body])  # the return counts for the stem it hit
    assert gap[np.arange(len(p)), best][body].max() < 0.002 + 0.0003


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_sensor_inside_stem_bounding_boxes_and_inside_a_stem(backend: str) -> None:
    """The sensor drives under two leaning stems (inside their axis-aligned bounding boxes)
    and straight through a third stem standing on the track. Returns from the leaning stems
    lie on their true surfaces; while the sensor is inside the third stem, most of its inner
    wall is nearer than the minimum range and dropped, and what is returned lies on that wall
    at its true range (no negative or wrapped ranges); the frames still decode."""
    forest = _leaning_pair()
    run = LidarRun(forest.scenario, mode="512x10", backend=backend, forest=forest)
    st = forest.stems
    boxes = []
    for i in (0, 1):  # the leaning stems' axis-aligned bounding boxes
        c = st.centre(np.full(200, i), np.linspace(-st.below[i], st.length[i], 200))
        boxes.append((c.min(axis=0) - st.r_bh[i] * 1.2, c.max(axis=0) + st.r_bh[i] * 1.2))
    seen_inside_box = inside_stem = False
    for k, (fr, dgs) in enumerate(run.datagrams()):
        pos = fr.positions
        for lo, hi in boxes:
            seen_inside_box |= bool(np.all((pos >= lo) & (pos <= hi), axis=1).any())
        o, d, _, _ = run.emu.rays(k, np.float32)  # the very rays the frame cast
        t, sid = run.scene.cast(o, d)
        o, d = o.astype(np.float64), d.astype(np.float64)
        H, W = run.meta.pixels, run.meta.columns
        got = fr.stem_id.T.reshape(-1)  # column-major like the rays
        rng_mm = fr.fields["RANGE"].T.reshape(-1).astype(np.float64)
        # the range reported is the hit distance plus the beam-origin offset, in mm
        back = got >= 0
        np.testing.assert_allclose(rng_mm[back], np.round((t[back] + run.emu.n_m) * 1000.0),
                                   atol=1.0)
        lean = np.flatnonzero(np.isin(got, [1, 2]))
        if len(lean):
            _assert_on_true_surfaces(forest, o[lean], d[lean], t[lean], sid[lean])
        p = pos[np.arange(W).repeat(H)]
        r3 = forest.stems.radius(np.full(len(p), 2), p[:, 2])  # stem 3 stands upright at z 0
        in_stem3 = np.hypot(p[:, 0] - 0.0, p[:, 1] - 6.0) < r3 - 0.03
        inside_stem |= bool(in_stem3.any())
        if in_stem3.any():
            # the inner wall is mostly nearer than the minimum range: dropped; what is
            # returned lies on the (inside of the) true surface, at its true range
            cast3 = in_stem3 & (sid == 3)
            kept3 = in_stem3 & (got == 3)
            assert kept3.sum() < 0.5 * cast3.sum()
            if kept3.any():
                _assert_on_true_surfaces(forest, o[kept3], d[kept3], t[kept3], sid[kept3])
        assert np.all(rng_mm[got < 0] == 0) and np.all(rng_mm[got >= 0] >= 300)
        for dg in dgs:
            if dg.port == run.meta.udp_port_lidar:
                decode_lidar_packet(run.meta.packet_format, dg.payload)
    assert seen_inside_box and inside_stem
    counts = run.counts
    assert counts[1] > 100 and counts[2] > 100  # the leaning stems were seen from under them


# --------------------------------------------------------------------------- 30 degree slope
@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_stems_on_a_30_degree_slope_are_found_with_bounded_error() -> None:
    """A 30 degree hillside (rising to the east; the track runs along the contour, so the
    machine rolls 30 degrees): the ground filter must not eat the uphill side of the stems or
    turn the slope into stems, and DBH at breast height stays within a few centimetres."""
    scn = scenario_from_dict(_small({"terrain": {"kind": "flat", "slope_deg": 30.0,
                                                 "uphill_azimuth_deg": 90.0}}))
    f = generate_forest(scn)
    assert f.terrain.height(1.0, 0.0) - f.terrain.height(0.0, 0.0) == pytest.approx(
        math.tan(math.radians(30.0)))
    tr = Trajectory.from_config(scn.track, f.terrain, 0)
    st = tr.vehicle_state(np.array([tr.t0_ns + 5 * 10**9]))
    assert abs(abs(float(np.degrees(st.roll[0]))) - 30.0) < 0.5
    res = run_offline(scn, mode="1024x10")
    m = _metrics(res)
    assert m["completeness"] >= 0.9 and m["correctness"] >= 0.9
    assert m["position_rmse_m"] < 0.05
    assert m["dbh_rmse_m"] < 0.03


@pytest.mark.parametrize("azimuth_deg", [0.0, 37.0, 90.0, 225.0])
def test_the_onboard_ground_grid_follows_a_30_degree_hillside(azimuth_deg: float) -> None:
    """The SIC's ground grid on a 30 degree plane: with ``slope`` the height under any point
    is the plane's (the cell minimum alone is up to 0.8 m low, which is what made hillside
    ground pass for stems); a cell whose lowest point is a stem (no ground seen there) does
    not lift its neighbours' ground above the true ground (they fall back to the minimum)."""
    from tcf_hil.sic._map import GroundGrid

    rng = np.random.default_rng(5)
    g = math.tan(math.radians(30.0))
    az = math.radians(azimuth_deg)
    gx, gy = g * math.sin(az), g * math.cos(az)
    xy = rng.uniform(-10, 10, (400_000, 2)) + [500.0, -300.0]
    z = 100.0 + gx * xy[:, 0] + gy * xy[:, 1]
    pts = np.column_stack([xy, z])
    plain, hill = GroundGrid(1.0), GroundGrid(1.0, slope=True)
    for grid in (plain, hill):
        grid.add(pts)
        grid.add(np.array([[503.5, -296.5, 105.0 + gx * 503.5 - gy * 296.5]]))  # a stem
    q = rng.uniform(-8, 8, (5000, 2)) + [500.0, -300.0]
    truth = 100.0 + gx * q[:, 0] + gy * q[:, 1]
    assert np.max(truth - plain.height(q)) > 0.5
    err = np.abs(hill.height(q) - truth)  # only as far as the lowest sample is off the
    assert np.median(err) < 0.02 and err.max() < 0.08  # cell's downhill corner
    # a cell that saw only a stem (its minimum 2 m above the ground) next to ground cells
    stem_only = GroundGrid(1.0, slope=True)
    stem_only.add(pts[~((np.floor(pts[:, 0]) == 502) & (np.floor(pts[:, 1]) == -298))])
    stem_only.add(np.array([[502.5, -297.5, 102.0 + gx * 502.5 + gy * -297.5]]))
    near = q[(np.abs(q[:, 0] - 502.5) < 1.5) & (np.abs(q[:, 1] + 297.5) < 1.5)
             & ~((np.floor(q[:, 0]) == 502) & (np.floor(q[:, 1]) == -298))]
    t_near = 100.0 + gx * near[:, 0] + gy * near[:, 1]
    # its neighbours fall back at worst to the plain minimum, never above the ground, and
    # cells two or more away keep their planes
    assert np.all(stem_only.height(near) <= t_near + 0.06)
    far = q[(np.abs(q[:, 0] - 502.5) > 2.5) | (np.abs(q[:, 1] + 297.5) > 2.5)]
    t_far = 100.0 + gx * far[:, 0] + gy * far[:, 1]
    assert np.median(np.abs(stem_only.height(far) - t_far)) < 0.02


# --------------------------------------------------------------- the class threshold
def test_maxcurve_at_the_class_threshold_keeps_a_consistent_class() -> None:
    """Stems drawn right at the S/C threshold (just below and exactly at it): the ground
    truth's class always follows its own rule applied to its own written maxcurve (rounding
    to 0.1 mm must not carry a stem across), and the same forest at a UTM origin keeps every
    class."""
    thr = 0.05
    doc = {"stems": {"count": 40, "class_mix": {"S": 20, "C": 20, "X": 0},
                     "sweep_m": {"S": [thr - 1e-4, thr - 1e-12], "C": [thr, thr + 1e-6]}},
           "plot": {"size_m": [30.0, 30.0]}, "distribution": {"kind": "even"}}
    a = ground_truth(generate_forest(scenario_from_dict(doc), 3))
    b = ground_truth(generate_forest(scenario_from_dict(
        dict(doc, plot={"size_m": [30.0, 30.0], "origin_m": list(UTM)})), 3))
    a = json.loads(json.dumps(a))  # what a reader of the file gets
    for oa, ob in zip(a["objects"], b["objects"], strict=True):
        assert classify(oa["maxcurve"], thr, 0.25) == oa["class"]
        assert ob["class"] == oa["class"]
    assert {o["class"] for o in a["objects"]} == {"S", "C"}
    # rounding would have flipped some: they are written exactly
    assert any(o["class"] == "S" and round(o["maxcurve"], 4) >= thr for o in a["objects"])
    # The stem algorithm's class of such stems is a property of the points alone: the same
    # cloud shifted to UTM, or shuffled, gives the same classes and maxcurves.
    forest = generate_forest(scenario_from_dict(doc), 3)
    cloud = sample_surfaces(forest, points_per_stem=3000, terrain_density_per_m2=20.0)
    runs = []
    for shift, order in ((np.zeros(3), None), (np.array(UTM), None),
                         (np.zeros(3), np.random.default_rng(1).permutation(len(cloud.xyz)))):
        pts = cloud.xyz if order is None else cloud.xyz[order]
        out = identify_stems(pts + shift)
        runs.append([(o["class"], o["maxcurve"], *np.subtract(o["cp"], shift)[:2])
                     for o in out["objects"]])
    assert len(runs[0]) >= 35
    for other in runs[1:]:
        assert [r[0] for r in other] == [r[0] for r in runs[0]]
        np.testing.assert_allclose(np.array([r[1:] for r in other], dtype=float),
                                   np.array([r[1:] for r in runs[0]], dtype=float), atol=1e-6)


# --------------------------------------------------------------- DBH from a one-sided arc
@pytest.mark.parametrize("arc_deg", [60.0, 90.0, 180.0])
def test_dbh_from_a_short_arc_has_bounded_error(arc_deg: float) -> None:
    """The SIC's circle fit on a 60 degree arc (a stem seen from one side only), with 2 mm of
    range noise, at UTM coordinates: the radius error stays bounded (no blow-up on short arcs)
    and shrinks as the arc grows."""
    rng = np.random.default_rng(11)
    errs = []
    for _ in range(200):
        r = rng.uniform(0.06, 0.25)
        c = np.array(UTM[:2]) + rng.uniform(-50, 50, 2)
        a0 = rng.uniform(0, 2 * math.pi)
        ang = a0 + np.radians(rng.uniform(0, arc_deg, 40))
        rr = r + rng.normal(0, 0.002, 40)
        xy = c + np.column_stack([rr * np.cos(ang), rr * np.sin(ang)])
        fit = fit_circle(xy)
        assert fit is not None
        errs.append(abs(fit.r - r))
        assert math.hypot(fit.cx - c[0], fit.cy - c[1]) < 0.1  # never a wild centre
    p90 = float(np.percentile(errs, 90))
    bound = {60.0: 0.03, 90.0: 0.015, 180.0: 0.003}[arc_deg]
    assert p90 < bound, f"{arc_deg} degree arc: radius error p90 {p90 * 1000:.1f} mm"


# ------------------------------------------------------------------ heading wraps
@pytest.mark.parametrize(("where", "plot", "track"), [
    # compass heading across north: the bus's uint16 0.01-degree heading goes 359.99 -> 0
    ("north", [20.0, 40.0], {"start_m": [1.0, -25.0, 2.0], "end_m": [1.0, 25.0, 2.0],
                             "waypoints_m": [[-1.0, 0.0]]}),
    # heading across west: yaw (counter-clockwise from east) goes through +/-180 degrees
    ("west", [40.0, 20.0], {"start_m": [25.0, 1.0, 2.0], "end_m": [-25.0, 1.0, 2.0],
                            "waypoints_m": [[0.0, -1.0]]}),
])
@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_heading_wraps_keep_every_stem_sharp(where: str, plot: list[float],
                                             track: dict) -> None:
    """The machine drives a kinked track whose heading crosses a wrap of the bus encoding
    (north) or of the angle the SIC interpolates (west, yaw +/-180 degrees): poses
    interpolated across the wrap must not swing the long way round, so every stem stays
    sharp."""
    scn = scenario_from_dict(_small({"plot": {"size_m": plot},
                                     "track": {**track, "turn_radius_m": 3.0}}))
    tr = Trajectory.from_config(scn.track, generate_forest(scn).terrain, 0)
    st = tr.vehicle_state(np.arange(tr.t0_ns, tr.end_ns, 10**8))
    wrapped = np.degrees(st.yaw) if where == "west" else np.asarray(st.heading_deg)
    wrapped = (wrapped + 180.0) % 360.0 - 180.0 if where == "west" else wrapped
    assert (wrapped > 355).any() if where == "north" else (wrapped > 175).any()
    assert (wrapped < 5).any() if where == "north" else (wrapped < -175).any()
    # The SIC's pose track, fed the node's TPDOs (decoded by canopen) around the crossing,
    # gives the true yaw at every millisecond in between, not a swing the long way round.
    t = np.arange(tr.t0_ns, tr.end_ns, 10**8)
    k = int(np.argmax(np.abs(np.diff(wrapped)) > 180.0))
    t_wrap = int(t[k])
    model = HarvesterModel.from_scenario(scn, generate_forest(scn).terrain, 0, 0)
    ncfg = model.node_config()
    sic = OfflineSic("tuned", sensor_metadata(scn), ncfg)
    try:
        for tp in range(t_wrap - 10**9, t_wrap + 10**9, 10**7):  # 100 Hz, as the node sends
            for cob, data in encode_pose(model.bus_pose(tp), ncfg.node_id):
                sic.can_frame(cob, data, tp / 1e9)
        q = np.arange(t_wrap - 5 * 10**8, t_wrap + 5 * 10**8, 10**6)
        got = sic.track.at(q.astype(np.float64))
    finally:
        sic.can.close()
    assert got is not None
    yaw = np.arctan2(got[1][:, 1, 0], got[1][:, 0, 0])
    true_yaw = model.trajectory.vehicle_state(q).yaw
    err = np.degrees(np.abs((yaw - true_yaw + np.pi) % (2 * np.pi) - np.pi))
    assert err.max() < 0.05, f"yaw off by up to {err.max():.1f} degrees at the wrap"
    # and the whole run through the wire: every stem sharp
    res = run_offline(scn, mode="512x10")
    m = _metrics(res)
    assert m["n_ground_truth"] >= 20
    assert m["f1"] >= 0.95
    assert m["position_rmse_m"] < 0.01


# ------------------------------------------------------- 32-bit CAN time, 16-bit frame_id
@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_can_time_and_frame_id_wrap_mid_run() -> None:
    """The CAN pose time (32-bit microseconds) wraps 20 s into the track and the lidar's
    16-bit frame_id wraps 5 frames in: the SIC unwraps both and scores as without wraps."""
    scn = scenario_from_dict(_small())
    t0 = (1 << 32) * 1000 - 20 * 10**9  # ns: the pose count wraps 20 s after the start
    ref = run_offline(scn, mode="512x10")
    wrap = run_offline(scn, mode="512x10", t0_ns=t0, first_frame_id=65531)
    assert wrap.poses >= ref.poses - 1
    assert wrap.forest_doc["sic"]["frames"] == ref.forest_doc["sic"]["frames"] == ref.frames
    assert wrap.forest_doc["sic"]["frames_without_pose"] == 0
    m0, m1 = _metrics(ref), _metrics(wrap)
    assert m1["em"]["matrix"] == m0["em"]["matrix"]
    assert abs(m1["position_rmse_m"] - m0["position_rmse_m"]) < 1e-3


def test_frame_id_wrap_reaches_ouster_sdk_without_a_dropped_frame(tmp_path: Path) -> None:
    """Frames 65533..65535, 0, 1, 2 in a pcap: ouster-sdk's own frame batcher reads six
    whole frames, with the frame ids as sent."""
    from ouster.sdk import pcap as opcap

    r = record_pcap(scenario_from_dict(_small()), tmp_path, mode="512x10", max_frames=6,
                    first_frame_id=65533)
    assert r.frames == 6
    src = opcap.PcapFrameSetSource(str(tmp_path / "lidar.pcap"),
                                   meta=[str(tmp_path / "metadata.json")])
    frames = [fs[0] for fs in src]
    assert all(f.complete() for f in frames)
    assert [int(f.frame_id) for f in frames] == [65533, 65534, 65535, 0, 1, 2]


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_frame_id_wrap_at_the_sics_receiver_over_udp() -> None:
    """The reference SIC's receiver on a real UDP socket gets frames 65533..65535, 0, 1, 2
    and then, after a real gap, frame 4, with duplicated packets and each frame's last packet
    overtaken by the next frame's first: it hands on seven whole frames in order, skips every
    duplicate, and counts exactly the one frame that never came as lost (not 65 530)."""
    import socket

    from tcf_hil.sic._online import LidarReceiver

    run = LidarRun(scenario_from_dict(_small()), mode="512x10", max_frames=8,
                   first_frame_id=65533)
    rx = LidarReceiver(run.meta, "127.0.0.1", 0)
    port = rx.sock.getsockname()[1]
    rx.start()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    wire: list[bytes] = []
    for k, (_fr, dgs) in enumerate(run.datagrams()):
        if k != 6:  # frame_id 3 is lost on the way
            wire += [bytes(d.payload) for d in dgs if d.port == run.meta.udp_port_lidar]
    ppf = run.meta.packet_format.packets_per_frame
    # and the network misbehaves: every 7th packet arrives twice (once again much later),
    # and the last packet of each frame is overtaken by the next frame's first
    for i in range(ppf - 1, len(wire) - 1, ppf):
        wire[i], wire[i + 1] = wire[i + 1], wire[i]
    wire = [p for i, p in enumerate(wire) for _ in range(2 if i % 7 == 0 else 1)]
    wire.insert(3 * ppf, wire[5])
    try:
        for i, payload in enumerate(wire):
            tx.sendto(payload, ("127.0.0.1", port))
            if i % 16 == 15:
                time.sleep(0.002)
        deadline = time.monotonic() + 30.0  # a loaded machine may take a while to read them
        while rx.stats.packets < len(wire) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        tx.close()
        rx.close()
    got = []
    while True:
        item = rx.frames.get(timeout=1.0)
        if item is None:
            break
        got.append((item[0], len(item[1])))
    assert got == [(f, ppf) for f in (65533, 65534, 65535, 0, 1, 2, 4)]
    assert rx.stats.frames_lost == 1 and rx.stats.incomplete == 0
    assert rx.stats.duplicates == len(wire) - 7 * ppf


# ---------------------------------------------------------------------------- empty forest
def test_an_empty_forest_runs_scores_and_says_so(tmp_path: Path) -> None:
    """No stems at all: the emulator sends terrain only, the SIC publishes an empty forest,
    and the evaluation reports zero matches without dividing by zero."""
    scn = scenario_from_dict(_small({"stems": {"count": 0}}))
    res = run_offline(scn, mode="512x10", max_frames=100)
    assert res.forest_doc["objects"] == [] and res.forest_doc["total_objects_count"] == 0
    m = _metrics(res)
    assert m["total_matches"] == 0 and m["n_ground_truth"] == 0 and m["n_observed"] == 0
    for k, v in m.items():
        if isinstance(v, float):
            assert math.isfinite(v), k


# --------------------------------------------------------------------- stems 5 cm apart
def _close_pair_forest() -> Forest:
    """Forest II's plot with two extra pairs: stems whose bark is 5 cm apart at breast
    height, and two leaning stems whose tops touch (2 cm apart, the generator's clearance)."""
    scn = scenario_from_dict(_small({"stems": {"count": 0}}))
    r = 0.15
    gap = 0.05
    lean = math.atan2(0.5 * (2.0 - 2 * 0.015 - 0.02), 14.0)
    base = np.array([[3.0, -5.0, 0.0], [3.0 + 2 * r + gap, -5.0, 0.0],
                     [-3.0, 5.0, 0.0], [-5.0, 5.0, 0.0]])
    axis = np.array([[0, 0, 1.0], [0, 0, 1.0],
                     [-math.sin(lean), 0, math.cos(lean)], [math.sin(lean), 0, math.cos(lean)]])
    n = 4
    stems = StemSet(base=base, axis=axis, bend=np.array([[0.0, 1.0, 0.0]] * n),
                    length=np.array([18.0, 17.0, 14.0, 14.0]) / axis[:, 2] * axis[:, 2],
                    sweep=np.zeros(n), peak=np.full(n, 0.5), r_bh=np.full(n, r),
                    r_top=np.full(n, 0.015), taper=np.full(n, 1.0), below=np.full(n, 0.5))
    return Forest(scenario=scn, seed=0, terrain=Terrain.flat(), stems=stems,
                  classes=np.array(["S"] * n), lean_deg=np.degrees([0, 0, lean, lean]))


def test_stems_5_cm_apart_and_touching_tops_keep_exact_returns_and_fair_scores() -> None:
    """Two stems 5 cm apart and two whose tops touch (our stems have no crowns: their tops
    come within 2 cm): the meshes do not intersect, every return is attributed to the stem
    whose true surface it lies on, all four stems are hit, and the evaluation never matches
    one stem twice, whatever the SIC makes of the pairs."""
    forest = _close_pair_forest()
    st = forest.stems
    for i, j, want in ((0, 1, 0.05), (2, 3, 0.02)):
        si = np.arange(-0.5, st.length[i], 0.005)
        sj = np.arange(-0.5, st.length[j], 0.005)
        ci, cj = st.centre(np.full(len(si), i), si), st.centre(np.full(len(sj), j), sj)
        dist, k = cKDTree(cj).query(ci, k=8)
        gap = dist - st.radius(np.full(len(si), i), si)[:, None] - st.radius(
            np.full(len(sj), j), sj)[k]
        assert 0.015 < gap.min() < want + 0.01  # close, and the meshes do not touch
    run = LidarRun(forest.scenario, mode="512x10", forest=forest, max_frames=200)
    for k, _frame in enumerate(run.datagrams()):
        if k % 20:
            continue
        o, d, _, _ = run.emu.rays(k)
        t, sid = run.scene.cast(o, d)
        hit = np.flatnonzero(sid > 0)
        _assert_on_true_surfaces(forest, o[hit], d[hit], t[hit], sid[hit])
    assert (run.counts[1:] > 50).all()
    # The reference SIC's 0.3 m radius clusters cannot split such pairs (it reports each
    # pair as one thick stem between the two); the evaluation must still be fair: each
    # reported stem matches at most one true stem, and nothing is invented.
    res = run_offline(forest.scenario, mode="512x10", forest=forest)
    ev = res.scores.all
    m = ev.metrics
    assert 2 <= m["n_observed"] <= 4
    assert m["total_matches"] == len(ev.pairs) >= 2
    assert len(set(ev.pairs[:, 0].tolist())) == len(set(ev.pairs[:, 1].tolist())) == len(ev.pairs)
    gxy = np.array([o["cp"][:2] for o in res.ground_truth["objects"]])
    for o in res.forest_doc["objects"]:
        assert np.min(np.hypot(*(gxy - o["cp"][:2]).T)) < 1.0
