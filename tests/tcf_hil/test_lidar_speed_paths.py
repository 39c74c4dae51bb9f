"""The lidar emulator's fast paths give what the plain ones give: interpolated column poses
(Trajectory.sensor_pose_dense) against the exact ones on real tracks, float32 rays against
float64, and the chunked, threaded frame against a plain reference of the return model."""

from __future__ import annotations

import numpy as np
import pytest

from emulators.lidar import Os0Emulator, ReturnModel
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import TerrainConfig, TrackConfig, load_scenario, scenario_from_dict
from tcf_hil.world.forest import Terrain, generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.track import Trajectory

T0 = 1_000_000_000
ROLLING = Terrain.generate(TerrainConfig(kind="rolling", amplitude_m=0.8, wavelength_m=15.0),
                           np.random.default_rng(3))
ROUGH = Terrain.generate(TerrainConfig(kind="rolling", amplitude_m=1.0, wavelength_m=10.0,
                                       octaves=5), np.random.default_rng(1))

TRACKS = {
    # corners with speed ramps, U-turns between three passes, an offset and tilted mount
    "corners-ramps-uturns": (TrackConfig(
        start_m=(0, -20, 2), end_m=(15, 20, 2), waypoints_m=((0, 0), (10, 5), (-5, 10)),
        turn_radius_m=3.0, speed_m_s=2.0, accel_m_s2=0.8, passes=3, pass_offset_m=4.0,
        mount_xy_m=(1.5, -0.5), mount_rpy_deg=(3, 10, 20)), ROLLING),
    # the same road driven back in reverse gear, constant speed (the speed jumps), a corner
    "reverse-passes": (TrackConfig(
        start_m=(0, -15, 2), end_m=(0, 15, 2), waypoints_m=((3, 0),), turn_radius_m=4.0,
        speed_m_s=1.5, passes=3, stop_s=0.5), ROLLING),
    # tight U-turns on rough ground: the knots close up
    "tight-uturns-rough": (TrackConfig(
        start_m=(0, -10, 2), end_m=(0, 10, 2), speed_m_s=1.0, passes=3, pass_offset_m=2.0,
        turn_radius_m=0.5), ROUGH),
    # fast and rough: too little time between knots, so the exact poses are used
    "fast-rough": (TrackConfig(
        start_m=(0, -20, 2), end_m=(0, 20, 2), waypoints_m=((5, 0),), turn_radius_m=1.0,
        speed_m_s=30.0, accel_m_s2=10.0, passes=3, stop_s=0.0), ROUGH),
}
POS_TOL_M = 1e-7
ROT_TOL = 1e-8  # rotation matrix entries (~ radians) and orthonormality


def _frames(tr: Trajectory, columns: int, hz: int) -> list[np.ndarray]:
    period = 10**9 // hz
    n = int(tr.duration_ns // period) + 3
    step = 1 + n // 400  # long tracks: every few frames
    return [tr.t0_ns + k * period + (np.arange(columns, dtype=np.int64) * period) // columns
            for k in range(-2, n, step)]


def _errors(tr: Trajectory, columns: int, hz: int) -> tuple[float, float, float]:
    ep = er = orth = 0.0
    for t in _frames(tr, columns, hz):
        p0, r0 = tr.sensor_pose(t)
        p1, r1 = tr.sensor_pose_dense(t)
        ep = max(ep, float(np.abs(p1 - p0).max()))
        er = max(er, float(np.abs(r1 - r0).max()))
        orth = max(orth, float(np.abs(r1 @ r1.transpose(0, 2, 1) - np.eye(3)).max()))
    return ep, er, orth


def _knots_used(tr: Trajectory, columns: int, hz: int, monkeypatch: pytest.MonkeyPatch
                ) -> int:
    """The most poses one dense call asks for exactly over a track's frames."""
    sizes: list[int] = []
    exact = Trajectory.sensor_pose

    def spy(self: Trajectory, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sizes.append(len(t_ns))
        return exact(self, t_ns)

    with monkeypatch.context() as mp:
        mp.setattr(Trajectory, "sensor_pose", spy)
        for t in _frames(tr, columns, hz):
            tr.sensor_pose_dense(t)
    return max(sizes)


@pytest.mark.parametrize("name", ["forest-x", "strip-road", *TRACKS])
@pytest.mark.parametrize(("columns", "hz"), [(2048, 10), (1024, 20), (512, 10)])
def test_dense_poses_match_the_exact_ones_along_whole_tracks(
        name: str, columns: int, hz: int, monkeypatch: pytest.MonkeyPatch) -> None:
    if name in TRACKS:
        cfg, terrain = TRACKS[name]
        tr = Trajectory(cfg, terrain, T0)
    else:
        forest = generate_forest(load_scenario(name))
        tr = Trajectory.from_config(forest.scenario.track, forest.terrain, T0)
    ep, er, orth = _errors(tr, columns, hz)
    assert ep < POS_TOL_M and er < ROT_TOL and orth < ROT_TOL, (ep, er, orth)
    used = _knots_used(tr, columns, hz, monkeypatch)
    if name == "fast-rough":
        assert used == columns  # falls back to the exact poses
    elif columns >= 1024:
        assert used <= columns // 2  # the fast path did the work


def test_the_breaks_are_what_keeps_the_interpolation_exact() -> None:
    """Without the breaks (corners, speed jumps, ramps) the quadratic runs over kinks: the
    error shows, so the test above can fail."""
    cfg, terrain = TRACKS["reverse-passes"]
    tr = Trajectory(cfg, terrain, T0)
    assert _errors(tr, 2048, 10)[0] < POS_TOL_M
    object.__setattr__(tr, "breaks_ns", np.zeros(0, np.int64))  # shadows the cached one
    ep, er, _ = _errors(tr, 2048, 10)
    assert ep > 100 * POS_TOL_M and er > 100 * ROT_TOL


def test_breaks_bracket_leg_ends_ramps_and_corner_joints() -> None:
    cfg, terrain = TRACKS["corners-ramps-uturns"]
    tr = Trajectory(cfg, terrain, T0)
    b = tr.breaks_ns
    assert np.all(np.diff(b) > 0)
    for start, leg in zip(tr.leg_start_s.tolist(), tr.legs, strict=True):
        taus = [0.0, leg.t_acc, leg.t_acc + leg.t_cruise, leg.duration_s,
                *leg.time_at(leg.s0[1:]).tolist()]
        for tau in taus:
            t = T0 + (start + tau) * 1e9
            assert np.min(np.abs(b - t)) <= 1.0
        # time_at inverts distance
        s = np.linspace(0.0, leg.length, 50)
        np.testing.assert_allclose(leg.distance(leg.time_at(s))[0], s, atol=1e-9)


def test_dense_poses_fall_back_for_few_or_unordered_times() -> None:
    cfg, terrain = TRACKS["corners-ramps-uturns"]
    tr = Trajectory(cfg, terrain, T0)
    t = np.array([T0 + 5 * 10**9, T0, T0 + 2 * 10**9] * 5, np.int64)
    for ts in (t, t[:3]):
        p0, r0 = tr.sensor_pose(ts)
        p1, r1 = tr.sensor_pose_dense(ts)
        assert np.array_equal(p0, p1) and np.array_equal(r0, r1)


SCN = scenario_from_dict({
    "name": "speed-paths", "plot": {"size_m": [20.0, 30.0]},
    "terrain": {"kind": "rolling", "amplitude_m": 0.6, "wavelength_m": 15.0},
    "stems": {"count": 30},
    "track": {"start_m": [0.0, -20.0, 2.0], "end_m": [0.0, 20.0, 2.0], "speed_m_s": 2.0,
              "waypoints_m": [[2.0, 0.0]], "turn_radius_m": 3.0}})


@pytest.fixture(scope="module")
def world() -> tuple[Scene, Trajectory]:
    forest = generate_forest(SCN)
    return Scene.from_forest(forest), Trajectory.from_config(SCN.track, forest.terrain)


def test_float32_rays_are_the_float64_ones_rounded(world: tuple[Scene, Trajectory]) -> None:
    scene, track = world
    emu = Os0Emulator(os0_64_metadata("1024x10"), scene, track, start_ns=track.t0_ns)
    o64, d64, p64, r64 = emu.rays(40)
    o32, d32, p32, r32 = emu.rays(40, np.float32)
    assert o32.dtype == d32.dtype == np.float32
    assert np.array_equal(p64, p32) and np.array_equal(r64, r32)
    assert np.abs(o32 - o64).max() < 1e-5  # 30 m from the plot centre: float32's ulp 2e-6
    assert np.abs(d32 - d64).max() < 1e-6


@pytest.mark.parametrize("profile", ["RNG19_RFL8_SIG16_NIR16", "RNG15_RFL8_NIR8",
                                     "RNG19_RFL8_SIG16_NIR16_DUAL"])
def test_frames_do_not_depend_on_the_thread_split(world: tuple[Scene, Trajectory],
                                                  profile: str) -> None:
    scene, track = world
    meta = os0_64_metadata("2048x10", profile=profile)
    model = ReturnModel(noise_sigma_m=0.01)
    frames = []
    for threads in (1, 2, 3, 8):
        emu = Os0Emulator(meta, scene, track, model, seed=5, start_ns=track.t0_ns,
                          threads=threads)
        frames.append(emu.frame(30))
    ref = frames[0]
    for fr in frames[1:]:
        assert fr.fields.keys() == ref.fields.keys()
        for name, img in ref.fields.items():
            assert img.shape == (64, 2048) and np.array_equal(fr.fields[name], img), name
        assert np.array_equal(fr.stem_id, ref.stem_id)
        if ref.stem_id2 is not None:
            assert fr.stem_id2 is not None and np.array_equal(fr.stem_id2, ref.stem_id2)


def _reference_frame(emu: Os0Emulator, k: int) -> dict[str, np.ndarray]:
    """The return model written plainly: exact poses, float64 rays, (H, W) images."""
    m, meta = emu.model, emu.meta
    H, W = meta.pixels, meta.columns
    pos, rot = emu.poses.sensor_pose(emu.column_times(k))
    rt = rot.transpose(0, 2, 1)
    o = (np.matmul(emu._origins_wh, rt) + pos[:, None, :]).reshape(-1, 3)
    d = np.matmul(emu._directions_wh, rt).reshape(-1, 3)
    t, sid = emu.scene.cast(o, d)
    t, sid = t.reshape(W, H).T, sid.reshape(W, H).T
    refl = np.where(sid > 0, m.reflectance["bark"], m.reflectance["ground"])
    rng_m = t + emu.n_m
    reach = m.max_range_m * np.minimum(1.0, np.sqrt(refl / m.reference_reflectance))
    ok = np.isfinite(t) & (sid >= 0) & (rng_m >= m.min_range_m) & (rng_m <= reach)
    q = emu.quantum_mm
    out = {"RANGE": np.where(ok, np.round(np.where(ok, rng_m, 0.0) * 1000.0 / q) * q, 0.0),
           "REFLECTIVITY": np.where(ok, np.round(refl * 100.0), 0.0),
           "NEAR_IR": np.minimum(np.where(ok, m.ambient * refl, m.ambient * 0.05), 65535.0),
           "SIGNAL": np.where(ok, np.minimum(65535.0, m.signal_scale * refl / np.maximum(
               np.where(ok, rng_m, 1.0), 0.5) ** 2), 0.0),
           "sid": np.where(ok, sid, -1)}
    if q == 8:
        out["NEAR_IR"] = np.minimum(out["NEAR_IR"].astype(np.uint32), 4080) // 16 * 16
    return {name: v.astype(np.int64) for name, v in out.items()}


@pytest.mark.parametrize("profile", ["RNG19_RFL8_SIG16_NIR16", "RNG15_RFL8_NIR8"])
@pytest.mark.parametrize("model", [ReturnModel(), ReturnModel(
    max_range_m=12.0, reflectance={"ground": 0.05, "bark": 0.6}, min_range_m=1.0)])
def test_frames_match_a_plain_reference(world: tuple[Scene, Trajectory], profile: str,
                                        model: ReturnModel) -> None:
    scene, track = world
    emu = Os0Emulator(os0_64_metadata("1024x10", profile=profile), scene, track, model,
                      start_ns=track.t0_ns)
    for k in (3, 25, 60):
        fr = emu.frame(k)
        ref = _reference_frame(emu, k)
        same = fr.stem_id == ref["sid"]
        # rays differ by float32 rounding (micrometres): a ray grazing an edge may flip
        assert same.mean() > 0.9995
        assert (ref["sid"] >= 0).sum() > 10_000
        for name in fr.fields:
            got = fr.fields[name].astype(np.int64)[same]
            want = ref[name][same]
            if name == "RANGE":  # one range quantum at a rounding tie, no more
                assert np.abs(got - want).max() <= emu.quantum_mm
                assert (got != want).mean() < 0.01
            elif name == "SIGNAL":
                assert np.abs(got - want).max() <= 1 + 1e-4 * want.max()
            else:
                assert np.array_equal(got, want), name


@pytest.mark.parametrize("profile", ["LEGACY", "RNG19_RFL8_SIG16_NIR16", "RNG15_RFL8_NIR8",
                                     "RNG19_RFL8_SIG16_NIR16_DUAL"])
@pytest.mark.parametrize("model", [ReturnModel(), ReturnModel(
    noise_sigma_m=0.02, max_range_m=12.0, reflectance={"ground": 0.05, "bark": 0.6},
    min_range_m=1.0, signal_scale=2e6)])
def test_the_compiled_answer_is_the_numpy_one_byte_for_byte(
        world: tuple[Scene, Trajectory], profile: str, model: ReturnModel) -> None:
    """The numba kernel and the numpy path (where numba is missing) write the same packets,
    stem ids and second returns: every profile, noise, a short reach that differs by
    material, a signal that saturates."""
    from emulators.lidar._kernel import answer_kernel

    if answer_kernel() is None:
        pytest.skip("numba is not installed here: only the numpy path runs")
    scene, track = world
    ds = scene.caster.direct_scene
    if ds is not None:  # the same cast on both paths: packets traced ray by ray (Embree
        ds.coherent = False  # answers each lane then as the numpy path's rays, to the bit)
    try:
        _compiled_and_numpy_agree(scene, track, profile, model)
    finally:
        if ds is not None:
            ds.coherent = True


def _compiled_and_numpy_agree(scene: Scene, track: Trajectory, profile: str,
                              model: ReturnModel) -> None:
    meta = os0_64_metadata("1024x10", profile=profile)
    jit = Os0Emulator(meta, scene, track, model, seed=3, start_ns=track.t0_ns, threads=2)
    plain = Os0Emulator(meta, scene, track, model, seed=3, start_ns=track.t0_ns, threads=1)
    plain.jit = False
    for k in (4, 5, 33):
        a, b = jit.frame(k), plain.frame(k)
        assert a.packets is not None and b.packets is not None
        assert np.array_equal(a.packets, b.packets)
        assert np.array_equal(a.stem_id, b.stem_id)
        assert (a.stem_id2 is None) == (b.stem_id2 is None)
        if a.stem_id2 is not None:
            assert np.array_equal(a.stem_id2, b.stem_id2)
    got = a.fields
    assert (got["RANGE"] > 0).sum() > 10_000 and set(got) >= {"RANGE", "REFLECTIVITY"}
    if "SIGNAL" in got and model.signal_scale > 1e6:
        assert got["SIGNAL"].max() == 65535  # saturated near the sensor


def test_frames_read_in_order_are_the_frames_read_alone(
        world: tuple[Scene, Trajectory]) -> None:
    """Read in order, column poses come from pieces built for two seconds of frames at once;
    read alone, from a frame's own: the same knots, so the same poses up to the last bits
    of the exact poses at them (numpy's vector maths may round a time differently in a
    longer batch), and the same returns bar a grazing ray's flip."""
    scene, track = world
    meta = os0_64_metadata("1024x20")
    run = Os0Emulator(meta, scene, track, start_ns=track.t0_ns)
    frames = {k: run.frame(k) for k in range(18, 64)}  # 18 alone, then 19-58 and 59-98
    for k in (18, 19, 30, 58, 59, 63):
        alone = Os0Emulator(meta, scene, track, start_ns=track.t0_ns).frame(k)
        assert np.abs(alone.positions - frames[k].positions).max() < 1e-12
        assert np.abs(alone.rotations - frames[k].rotations).max() < 1e-12
        assert (alone.stem_id != frames[k].stem_id).sum() <= 4
        assert (alone.fields["RANGE"] != frames[k].fields["RANGE"]).sum() <= 4
    exact_p, exact_r = track.sensor_pose(run.column_times(30))
    assert np.abs(frames[30].positions - exact_p).max() < POS_TOL_M
    assert np.abs(frames[30].rotations - exact_r).max() < ROT_TOL


def test_compiled_pose_pieces_are_numpys(world: tuple[Scene, Trajectory],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The pieces are evaluated by a numba kernel where numba is installed: the same bits as
    the numpy evaluation, in order or not."""
    import tcf_hil.world.track as trajectory

    _, track = world
    if trajectory._pieces_kernel() is None:
        pytest.skip("numba is not installed here: only the numpy path runs")
    h = track.dense_knot_ns()
    lo = track.t0_ns + 1_234_567_890
    pieces = track.dense_poses(lo // h * h, (lo + 2_000_000_000) // h * h + h, h)
    t = lo + np.arange(4096, dtype=np.int64) * 488_281
    shuffled = np.random.default_rng(2).permutation(t)
    compiled = [pieces.at(t), pieces.at(shuffled)]
    monkeypatch.setattr(trajectory, "_pieces_kernel", lambda: None)
    for (p, r), times in zip(compiled, (t, shuffled), strict=True):
        p0, r0 = pieces.at(times)
        assert np.array_equal(p, p0) and np.array_equal(r, r0)
