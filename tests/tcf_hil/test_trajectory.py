"""Trajectory: straight pass, rounded corners, multi-pass (reverse and U-turn), speed profile,
terrain following, IMU signals and the pose error model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from tcf_hil._rotations import rotation_ypr
from tcf_hil.errors import ConfigError
from tcf_hil.scenario import PoseErrorConfig, TrackConfig
from tcf_hil.world.forest import Terrain
from tcf_hil.world.track import GRAVITY_M_S2, PoseError, Trajectory

T0 = 1_000_000_000
FLAT = Terrain.flat(3.0)


def _times(tr: Trajectory, step_ns: int = 10_000_000) -> np.ndarray:
    return np.arange(tr.t0_ns - step_ns * 10, tr.end_ns + step_ns * 10, step_ns, dtype=np.int64)


def _ramp(slope_x: float, slope_y: float) -> Terrain:
    """Practically a plane: sin waves with a 60 km wavelength (curvature < 1e-7 / m)."""
    k = 1e-4
    waves = [(k, 0.0, slope_x / k, -math.pi / 2), (0.0, k, slope_y / k, -math.pi / 2)]
    return Terrain(0.0, np.array([w for w in waves if w[2] != 0.0]).reshape(-1, 4))


def test_paper_pass_is_constant_speed_north_at_the_mount_height() -> None:
    tr = Trajectory(TrackConfig(), FLAT, T0)
    assert tr.duration_ns == 100 * 10**9
    t = np.array([0, T0, T0 + 25 * 10**9, T0 + 100 * 10**9, T0 + 500 * 10**9])
    pos, rot = tr.sensor_pose(t)
    np.testing.assert_allclose(pos[:, 1], [-50, -50, -25, 50, 50], atol=1e-12)
    np.testing.assert_allclose(pos[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(pos[:, 2], 5.0)  # ground 3 m + mount 2 m
    st = tr.vehicle_state(t)
    np.testing.assert_allclose(st.heading_deg, 0.0, atol=1e-9)  # north
    np.testing.assert_allclose(st.speed, [0, 1, 1, 0, 0])
    np.testing.assert_allclose(rot[:, :, 0], np.tile([0.0, 1.0, 0.0], (5, 1)), atol=1e-12)


def test_corners_are_arcs_of_the_turn_radius_and_the_path_is_continuous() -> None:
    cfg = TrackConfig(start_m=(0, -40, 2), end_m=(40, 40, 2), waypoints_m=((0.0, 0.0),),
                      turn_radius_m=5.0, speed_m_s=2.0)
    tr = Trajectory(cfg, FLAT, T0)
    # a 45 degree corner: the tangents lose 2 R tan(22.5 deg), the arc adds R pi/4
    turn = math.radians(45)
    assert tr.length_m == pytest.approx(
        40 + math.hypot(40, 40) - 2 * 5 * math.tan(turn / 2) + 5 * turn, rel=1e-12)
    t = _times(tr, 5_000_000)
    st = tr.vehicle_state(t)
    step = np.hypot(*np.diff(st.position[:, :2], axis=0).T)
    assert step.max() <= 2.0 * 0.005 + 1e-9  # never jumps
    dh = np.abs((np.diff(st.heading_deg) + 180) % 360 - 180)
    assert dh.max() < 1.0  # heading continuous (5 ms steps at 2 m/s on R = 5 m: 0.11 deg)
    _, _, w = tr.sensor_kinematics(t)
    turning = np.abs(w[:, 2]) > 1e-6
    assert turning.any()
    np.testing.assert_allclose(np.abs(w[turning, 2])[5:-5].max(), 2.0 / 5.0, rtol=1e-3)


def test_corner_radius_shrinks_when_the_legs_are_short() -> None:
    cfg = TrackConfig(start_m=(0, 0, 2), end_m=(4, 4, 2), waypoints_m=((0.0, 4.0),),
                      turn_radius_m=50.0)
    tr = Trajectory(cfg, FLAT, T0)
    # legs of 4 m: the whole of both legs becomes one quarter circle of radius 4
    assert tr.length_m == pytest.approx(4 * math.pi / 2, rel=1e-9)
    pos, _ = tr.sensor_pose(np.array([tr.end_ns]))
    np.testing.assert_allclose(pos[0, :2], [4, 4], atol=1e-9)


def test_the_same_road_back_is_driven_in_reverse_after_a_stop() -> None:
    cfg = TrackConfig(start_m=(0, -10, 2), end_m=(0, 10, 2), passes=3, stop_s=2.0)
    tr = Trajectory(cfg, FLAT, T0)
    assert tr.duration_ns == (60 + 2 * 2) * 10**9
    s = 10**9
    st = tr.vehicle_state(np.array([T0 + 10 * s, T0 + 21 * s, T0 + 32 * s, T0 + 50 * s,
                                    T0 + 70 * s]))
    np.testing.assert_allclose(st.position[:, 1], [0, 10, 0, -4, 10], atol=1e-9)
    np.testing.assert_allclose(st.speed, [1, 0, -1, 1, 0])
    np.testing.assert_allclose(st.heading_deg % 360, 0.0, atol=1e-9)  # it faces north all along
    np.testing.assert_array_equal(st.pass_no, [0, 0, 1, 2, 2])


def test_offset_passes_are_joined_by_u_turns() -> None:
    cfg = TrackConfig(start_m=(0, -20, 2), end_m=(0, 20, 2), passes=2, pass_offset_m=8.0,
                      turn_radius_m=10.0)
    tr = Trajectory(cfg, FLAT, T0)
    assert len(tr.legs) == 1
    assert tr.length_m == pytest.approx(2 * (40 - 4) + math.pi * 4, rel=1e-9)
    end = tr.vehicle_state(np.array([tr.end_ns]))
    np.testing.assert_allclose(end.position[0, :2], [-8, -20], atol=1e-9)  # left of north
    assert end.heading_deg[0] == pytest.approx(180.0)


def test_speed_profile_and_imu_on_flat_ground() -> None:
    cfg = TrackConfig(start_m=(0, 0, 2), end_m=(20, 0, 2), speed_m_s=2.0, accel_m_s2=0.5)
    tr = Trajectory(cfg, FLAT, T0)
    # 4 s up to speed (4 m), 6 s cruise (12 m), 4 s braking (4 m)
    assert tr.duration_ns == 14 * 10**9
    st = tr.vehicle_state(np.array([T0 + 2 * 10**9, T0 + 7 * 10**9, T0 + 12 * 10**9]))
    np.testing.assert_allclose(st.speed, [1.0, 2.0, 1.0])
    np.testing.assert_allclose(st.position[:, 0], [1.0, 4.0 + 6.0, 20.0 - 1.0])
    acc, gyro = tr.imu(np.array([T0 + 2 * 10**9, T0 + 7 * 10**9, T0 + 12 * 10**9]))
    np.testing.assert_allclose(acc[:, 0], np.array([0.5, 0.0, -0.5]) / GRAVITY_M_S2, atol=1e-6)
    np.testing.assert_allclose(acc[:, 2], 1.0, atol=1e-9)  # gravity included
    np.testing.assert_allclose(gyro, 0.0, atol=1e-9)


@pytest.mark.parametrize("heading", ["north", "east"])
def test_pitch_and_roll_follow_a_sloped_plane(heading: str) -> None:
    g = 0.3  # ground rises 0.3 m per m to the north
    end = (0.0, 40.0) if heading == "north" else (40.0, 0.0)
    cfg = TrackConfig(start_m=(0, 0, 2), end_m=(*end, 2), speed_m_s=1.0)
    tr = Trajectory(cfg, _ramp(0.0, g), T0)
    t = np.array([T0 + 10 * 10**9])
    st = tr.vehicle_state(t)
    if heading == "north":  # nose up (REP-103 pitch negative), level sideways
        assert st.pitch[0] == pytest.approx(-math.atan(g), abs=1e-6)
        assert st.roll[0] == pytest.approx(0.0, abs=1e-9)
    else:  # driving east, the left (north) side is up
        assert st.pitch[0] == pytest.approx(0.0, abs=1e-9)
        assert st.roll[0] == pytest.approx(math.atan(g), abs=1e-6)
    # the lidar sits 2 m up the machine's own z axis
    pos, rot = tr.sensor_pose(t)
    np.testing.assert_allclose(pos[0], st.position[0] + 2.0 * rot[0][:, 2], atol=1e-9)
    # the IMU of a machine moving at constant speed on a plane feels only gravity
    acc, gyro = tr.imu(t)
    np.testing.assert_allclose(acc[0], rot[0].T @ [0, 0, 1.0], atol=1e-6)
    assert np.linalg.norm(acc[0]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(gyro[0], 0.0, atol=1e-4)  # the ramp curves by < 1e-7 / m


def test_level_machine_when_terrain_following_is_off() -> None:
    cfg = TrackConfig(follow_terrain=False)
    tr = Trajectory(cfg, _ramp(0.2, 0.1), T0)
    st = tr.vehicle_state(np.array([T0 + 5 * 10**9]))
    assert st.pitch[0] == 0.0 and st.roll[0] == 0.0


def test_mount_pose_is_applied_in_the_machine_frame() -> None:
    cfg = TrackConfig(mount_xy_m=(1.5, -0.5), mount_rpy_deg=(0.0, 10.0, 90.0))
    tr = Trajectory(cfg, FLAT, T0)
    t = np.array([T0 + 10 * 10**9])
    st = tr.vehicle_state(t)
    pos, rot = tr.sensor_pose(t)
    # machine faces north: forward = +y, left = -x
    np.testing.assert_allclose(pos[0] - st.position[0], [0.5, 1.5, 2.0], atol=1e-12)
    expect = st.rotation[0] @ rotation_ypr(np.array([math.pi / 2]), np.array([math.radians(10)]),
                                           np.array([0.0]))[0]
    np.testing.assert_allclose(rot[0], expect, atol=1e-12)


def test_a_standing_machine_and_impossible_offsets() -> None:
    tr = Trajectory(TrackConfig(start_m=(1, 2, 2), end_m=(1, 2, 2)), FLAT, T0)
    assert tr.duration_ns == 0
    pos, _ = tr.sensor_pose(np.array([T0, T0 + 10**9]))
    np.testing.assert_allclose(pos[:, :2], [[1, 2], [1, 2]])
    with pytest.raises(ConfigError, match="pass_offset_m"):
        Trajectory(TrackConfig(start_m=(1, 2, 2), end_m=(1, 2, 2), passes=2,
                               pass_offset_m=3.0), FLAT, T0)


def test_pose_error_is_deterministic_and_has_its_statistics() -> None:
    cfg = PoseErrorConfig(position_sd_m=0.05, heading_sd_deg=0.5, bias_m=(1.0, -2.0, 0.5),
                          drift_m_per_s=0.01)
    err = PoseError(cfg, seed=7, t0_ns=T0)
    t = T0 + np.arange(4000, dtype=np.int64) * 10_000_000
    pos = np.zeros((len(t), 3))
    hd = np.full(len(t), 359.9)
    p1, h1 = err.apply(pos, hd, t)
    p2, h2 = err.apply(pos, hd, t)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(h1, h2)
    drift = 0.01 * (t - T0) / 1e9
    r = p1 - np.array(cfg.bias_m)
    horiz = np.hypot(r[:, 0], r[:, 1])
    assert np.median(horiz[-200:]) == pytest.approx(drift[-1], abs=0.03)
    np.testing.assert_allclose(np.std(r[:, 2]), 0.05, rtol=0.1)
    dh = (h1 - 359.9 + 180) % 360 - 180
    np.testing.assert_allclose(np.std(dh), 0.5, rtol=0.1)
    assert ((h1 >= 0) & (h1 < 360)).all()
    other = PoseError(cfg, seed=8, t0_ns=T0).apply(pos, hd, t)[0]
    assert not np.allclose(other, p1)
    assert not PoseError(PoseErrorConfig()).active


def test_trajectory_matches_the_config_it_was_built_from() -> None:
    cfg = dataclasses.replace(TrackConfig(), speed_m_s=4.0)
    assert Trajectory.from_config(cfg, FLAT).duration_ns == 25 * 10**9


@settings(max_examples=40, deadline=None)
@given(seed=hs.integers(0, 2**32 - 1), n=hs.integers(1, 40))
def test_a_pointwise_height_has_the_bits_of_the_point_asked_alone(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    k = rng.uniform(-0.5, 0.5, (int(rng.integers(1, 60)), 2))
    waves = np.column_stack([k, rng.uniform(0.0, 0.5, len(k)), rng.uniform(0, 2 * math.pi,
                                                                           len(k))])
    terrain = Terrain(float(rng.uniform(-5, 5)), waves, tilt=(0.01, -0.02))
    x, y = rng.uniform(-200, 200, n), rng.uniform(-200, 200, n)
    alone = np.array([terrain.height(x[i:i + 1], y[i:i + 1])[0] for i in range(n)])
    assert terrain.height(x, y, pointwise=True).tobytes() == alone.tobytes()
    np.testing.assert_allclose(terrain.height(x, y), alone, rtol=0, atol=1e-12)


def test_bus_poses_together_are_the_bus_poses_one_by_one() -> None:
    """An offline run evaluates a frame's poses together; the TPDOs must be the node's."""
    from tcf_hil.devices.harvester import HarvesterModel
    from tcf_hil.scenario import load_scenario
    from tcf_hil.world.forest import generate_forest

    scn = load_scenario("forest-iv-natural")
    scn = dataclasses.replace(scn, harvester=dataclasses.replace(
        scn.harvester, pose_error=PoseErrorConfig(position_sd_m=0.05, heading_sd_deg=0.5,
                                                  drift_m_per_s=0.01)))
    forest = generate_forest(scn)
    assert not forest.terrain.is_flat
    model = HarvesterModel.from_scenario(scn, forest.terrain, forest.seed)
    t = [T0 - 10**9 + k * 10_000_000 + 777 for k in range(0, 5200, 3)]
    together = [p for a in range(0, len(t), 11) for p in model.bus_poses(t[a:a + 11])]
    assert together == [model.bus_pose(x) for x in t]
    assert model.bus_poses([]) == []
