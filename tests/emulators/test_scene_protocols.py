"""What the lidar emulator uses beyond a cast and a pose is declared (FastRayScene,
DensePoseSource), not probed for: tcf-hil's Scene and Trajectory declare all of it, and a
scene or pose source that declares less is used through its plain cast or pose, with the
same packets."""

from __future__ import annotations

import numpy as np
import pytest

from emulators.lidar import Os0Emulator, ReturnModel
from emulators.lidar._os0 import DensePoseSource, FastRayScene, fast_scene
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import scenario_from_dict
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.track import Trajectory

SCN = scenario_from_dict({
    "plot": {"size_m": [20.0, 30.0]}, "stems": {"count": 20},
    "track": {"start_m": [0.0, -20.0, 2.0], "end_m": [0.0, 20.0, 2.0]}})


@pytest.fixture(scope="module")
def world() -> tuple[Scene, Trajectory]:
    forest = generate_forest(SCN)
    return Scene.from_forest(forest), Trajectory.from_config(SCN.track, forest.terrain)


class _CastOnly:
    """A scene that offers a cast and nothing else."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene

    def cast(self, origins: np.ndarray, directions: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        return self.scene.cast(origins, directions)


class _Partial(_CastOnly):
    """A scene with some of FastRayScene's members but not all: a plain cast, then."""

    def direct(self) -> None:
        raise AssertionError("a scene that is not a FastRayScene is not asked")


class _PosesOnly:
    def __init__(self, track: Trajectory) -> None:
        self.track = track

    def sensor_pose(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.track.sensor_pose(t_ns)


def test_scene_and_trajectory_declare_every_fast_path(world: tuple[Scene, Trajectory]
                                                      ) -> None:
    scene, track = world
    assert isinstance(scene, FastRayScene) and fast_scene(scene) is scene
    assert isinstance(track, DensePoseSource)
    emu = Os0Emulator(os0_64_metadata("512x10"), scene, track, start_ns=track.t0_ns)
    assert emu.scene is scene and emu.poses is track


@pytest.mark.parametrize("profile", ["LEGACY", "RNG19_RFL8_SIG16_NIR16_DUAL"])
def test_a_scene_that_only_casts_gives_the_same_packets(world: tuple[Scene, Trajectory],
                                                         profile: str) -> None:
    scene, track = world
    for plain in (_CastOnly(scene), _Partial(scene)):
        assert not isinstance(plain, FastRayScene)
        fast = fast_scene(plain)
        assert fast.direct() is None and not fast.threads_itself
    meta = os0_64_metadata("512x10", profile=profile)
    model = ReturnModel(noise_sigma_m=0.01)
    a = Os0Emulator(meta, scene, track, model, seed=2, start_ns=track.t0_ns, threads=2)
    b = Os0Emulator(meta, _Partial(scene), track, model, seed=2, start_ns=track.t0_ns,
                    threads=2)
    for k in (3, 4):
        fa, fb = a.frame(k), b.frame(k)
        assert np.array_equal(fa.packets, fb.packets)
        assert np.array_equal(fa.stem_id, fb.stem_id)


def test_a_pose_source_without_dense_poses_is_asked_for_exact_poses(
        world: tuple[Scene, Trajectory]) -> None:
    scene, track = world
    emu = Os0Emulator(os0_64_metadata("512x10"), scene, _PosesOnly(track),
                      start_ns=track.t0_ns)
    pos, rot = emu.column_poses(7)
    want_pos, want_rot = track.sensor_pose(emu.column_times(7))
    assert np.array_equal(pos, want_pos) and np.array_equal(rot, want_rot)
    assert (emu.frame(7).stem_id > 0).sum() > 100
