"""The directly bound Embree scene (emulators.embree) gives embreex's hits bit for bit, and
the lidar emulator's fused kernel (rays, that cast and the answer in one compiled call)
writes the packets the step-by-step path writes through embreex."""

from __future__ import annotations

import numpy as np
import pytest

from emulators.jit import jit_enabled
from emulators.lidar import Os0Emulator, ReturnModel
from protocols.ouster import os0_64_metadata
from tcf_hil.scenario import scenario_from_dict
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import Scene
from tcf_hil.world.scene.embree import EmbreeCaster
from tcf_hil.world.track import Trajectory

pytestmark = pytest.mark.skipif(not jit_enabled(), reason="compiled kernels are off here "
                                "(TCF_HIL_NO_JIT or no numba): embreex alone is used")

SCN = scenario_from_dict({
    "plot": {"size_m": [20.0, 30.0]}, "stems": {"count": 30, "lean_deg": [0.0, 8.0]},
    "terrain": {"kind": "rolling", "amplitude_m": 0.6, "wavelength_m": 12.0},
    "track": {"start_m": [0.0, -20.0, 2.0], "end_m": [0.0, 20.0, 2.0]}})


@pytest.fixture(scope="module")
def world() -> tuple[Scene, Scene, Trajectory]:
    """The forest twice: cast directly (the default) and through embreex's own scene."""
    forest = generate_forest(SCN)
    direct = Scene.from_forest(forest, geometry="mesh")  # embreex casts no curves
    plain = Scene(direct.vertices, direct.faces, direct.stem_id,
                  EmbreeCaster(direct.vertices, direct.faces, direct=False))
    return direct, plain, Trajectory.from_config(SCN.track, forest.terrain)


def _embreex(scene: Scene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.full(len(o), np.inf, np.float32)
    r = scene.caster._scene.run(np.ascontiguousarray(o, np.float32),  # type: ignore[attr-defined]
                                np.ascontiguousarray(d, np.float32), dists=t, output=1)
    return r["tfar"], r["primID"]


def test_direct_hits_are_embreexs_bit_for_bit(world: tuple[Scene, Scene, Trajectory]
                                              ) -> None:
    direct, plain, track = world
    assert direct.direct() is not None and plain.direct() is None
    emu = Os0Emulator(os0_64_metadata("1024x10"), direct, track, start_ns=track.t0_ns)
    o, d, _, _ = emu.rays(20, np.float32)
    # and rays aimed exactly at mesh vertices and edge midpoints, where robust mode matters
    v = direct.vertices.astype(np.float32)
    f = direct.faces[::7]
    targets = np.concatenate([v[f[:, 0]], (v[f[:, 0]] + v[f[:, 1]]) / 2])
    eye = np.array([0.3, -1.7, 2.5], np.float32)
    to = targets - eye
    o2 = np.broadcast_to(eye, to.shape)
    d2 = (to / np.linalg.norm(to, axis=1, keepdims=True)).astype(np.float32)
    for oo, dd in ((o, d), (o2, d2)):
        t1, p1 = direct.caster.cast(oo, dd)
        t0, p0 = _embreex(plain, oo, dd)
        assert np.array_equal(t1, t0) and np.array_equal(p1, p0)
        assert np.isfinite(t1).sum() > len(t1) // 4 and (p1 >= 0).sum() > len(t1) // 4
    assert (p1 == -1).sum() < len(p1) // 50  # aimed at the mesh: nearly all hit


@pytest.mark.parametrize("profile", ["LEGACY", "RNG19_RFL8_SIG16_NIR16", "RNG15_RFL8_NIR8",
                                     "RNG19_RFL8_SIG16_NIR16_DUAL"])
def test_fused_frames_are_the_step_by_step_frames_through_embreex(
        world: tuple[Scene, Scene, Trajectory], profile: str) -> None:
    """The fused kernel (threads taking blocks of columns in turn, packets copied from a
    template) against numpy rays, embreex's cast, numpy answers and the protocol's column
    encoder: the same bytes, stem ids and second returns, with noise and without."""
    direct, plain, track = world
    meta = os0_64_metadata("512x20", profile=profile)
    for model in (ReturnModel(), ReturnModel(noise_sigma_m=0.01, max_range_m=15.0)):
        fused = Os0Emulator(meta, direct, track, model, seed=5, start_ns=track.t0_ns,
                            threads=3)
        steps = Os0Emulator(meta, plain, track, model, seed=5, start_ns=track.t0_ns,
                            threads=2)
        steps.jit = False
        for k in (7, 8, 40):
            a, b = fused.frame(k), steps.frame(k)
            assert np.array_equal(a.packets, b.packets)
            assert np.array_equal(a.stem_id, b.stem_id)
            if a.stem_id2 is not None or b.stem_id2 is not None:
                assert a.stem_id2 is not None and b.stem_id2 is not None
                assert np.array_equal(a.stem_id2, b.stem_id2)
        assert (a.stem_id > 0).sum() > 500 and (a.fields["RANGE"] > 0).mean() > 0.3


def test_no_jit_falls_back_to_embreex(monkeypatch: pytest.MonkeyPatch,
                                      world: tuple[Scene, Scene, Trajectory]) -> None:
    direct, _, _ = world
    monkeypatch.setenv("TCF_HIL_NO_JIT", "1")
    caster = EmbreeCaster(direct.vertices, direct.faces)
    assert caster.direct_scene is None
    o = np.tile(np.array([0, 0, 5], np.float32), (3, 1))
    d = np.array([[0, 0, -1], [0, 0, 1], [1, 0, 0]], np.float32)
    t, p = caster.cast(o, d)
    t1, p1 = direct.caster.cast(o, d)
    assert np.array_equal(t, t1) and np.array_equal(p, p1)
    assert np.isfinite(t[0]) and not np.isfinite(t[1])  # the ground below, the sky above


def test_a_forked_emulator_makes_the_same_frames(world: tuple[Scene, Scene, Trajectory]
                                                 ) -> None:
    """The helper threads of the fused frame stay in the parent: a forked copy (the live
    stream's frame producer) starts its own, does not wait on the parent's futures, and
    writes the same bytes."""
    import multiprocessing as mp

    direct, _, track = world
    emu = Os0Emulator(os0_64_metadata("1024x10"), direct, track, start_ns=track.t0_ns,
                      threads=2)
    want = emu.frame(5).packets.copy()
    emu.frame(6)  # its helper's return may be outstanding at the fork (a race: not forced)
    ctx = mp.get_context("fork")
    q = ctx.Queue()

    def child() -> None:
        q.put(bool(np.array_equal(emu.frame(5).packets, want)))

    proc = ctx.Process(target=child)
    proc.start()
    assert q.get(timeout=60) is True
    proc.join(10)
    assert proc.exitcode == 0
