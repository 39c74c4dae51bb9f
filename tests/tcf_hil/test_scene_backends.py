"""Ray backends by name and ``auto`` (tcf_hil.world.scene.resolve_backend): Embree where embreex
imports, else open3d, else trimesh's numpy ray-triangle tests, which find Embree's first
hits. The fallbacks are forced by making the imports fail."""

from __future__ import annotations

import importlib.util
import json
import platform
import sys
from pathlib import Path

import numpy as np
import pytest

from tcf_hil.errors import ConfigError
from tcf_hil.scenario import scenario_from_dict
from tcf_hil.world.forest import generate_forest
from tcf_hil.world.scene import BACKENDS, Scene, make_caster, resolve_backend
from tcf_hil.world.scene.trimesh import TrimeshCaster

SCN = scenario_from_dict({
    "plot": {"size_m": [8.0, 8.0]}, "stems": {"count": 5},
    "terrain": {"kind": "rolling", "amplitude_m": 0.4, "wavelength_m": 6.0},
    "track": {"start_m": [0.0, -3.0, 2.0], "end_m": [0.0, 3.0, 2.0]}})
# what "embree" imports: embreex's modules, and the directly bound scene (which loads the
# library embreex ships, perhaps already loaded in this process)
NO_EMBREE = ("embreex", "embreex.rtcore_scene", "embreex.mesh_construction",
             "emulators.embree")
needs_embreex = pytest.mark.skipif(importlib.util.find_spec("embreex") is None,
                                   reason="embreex is not installed here")
needs_open3d = pytest.mark.skipif(importlib.util.find_spec("open3d") is None,
                                  reason="open3d is not installed here")


def _without(monkeypatch: pytest.MonkeyPatch, *modules: str) -> None:
    """Make importing these modules fail as if they were not installed."""
    for m in modules:
        monkeypatch.setitem(sys.modules, m, None)


@pytest.fixture(scope="module")
def small() -> Scene:
    """A small plot (about 17,000 triangles): trimesh's caster takes seconds on it."""
    forest = generate_forest(SCN)
    return Scene.from_forest(forest, backend="trimesh", stem_tolerance_m=0.01,
                             terrain_tolerance_m=0.05, margin_m=1.0)


def _sensor_rays(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Rays from near a sensor's place in all directions level and down (float32)."""
    rng = np.random.default_rng(seed)
    o = np.array([0.3, -0.2, 1.5]) + rng.normal(0.0, 0.2, (n, 3))
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2]) * 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def test_named_backends_are_themselves_and_unknown_names_are_config_errors(
        small: Scene) -> None:
    for name in BACKENDS:
        assert resolve_backend(name) == (name, None)
    with pytest.raises(ConfigError, match="allowed: auto, embree, open3d, trimesh"):
        resolve_backend("optix")
    with pytest.raises(ConfigError, match="ray backend = 'optix'"):
        make_caster("optix", small.vertices, small.faces)


@needs_embreex
def test_auto_is_embree_where_embreex_imports(small: Scene) -> None:
    assert resolve_backend("auto") == ("embree", None)
    scene = Scene(small.vertices, small.faces, small.stem_id,
                  make_caster("auto", small.vertices, small.faces))
    assert scene.backend == "embree" and not scene.threads_itself
    assert scene.threads is not None and scene.threads >= 1


@needs_open3d
def test_auto_falls_back_to_open3d_and_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    _without(monkeypatch, *NO_EMBREE)
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert resolve_backend("auto") == (
        "open3d", "ray backend: open3d (embreex is not installed here: Embree has no wheel "
        "for aarch64)")
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    assert resolve_backend("auto") == ("open3d",
                                       "ray backend: open3d (embreex is not installed here)")


def test_auto_falls_back_to_trimesh_last(monkeypatch: pytest.MonkeyPatch, small: Scene
                                         ) -> None:
    _without(monkeypatch, *NO_EMBREE, "open3d")
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    assert resolve_backend("auto") == (
        "trimesh", "ray backend: trimesh, pure numpy and slow (embreex is not installed here: "
        "Embree has no wheel for aarch64; open3d is not installed here)")
    scene = Scene(small.vertices, small.faces, small.stem_id,
                  make_caster("auto", small.vertices, small.faces))
    assert scene.backend == "trimesh" and scene.threads is None
    assert not scene.threads_itself and scene.direct() is None
    o, d = _sensor_rays(50)
    t, sid = scene.cast32(o, d)
    assert t.dtype == np.float32 and sid.dtype == np.int32 and np.isfinite(t).sum() > 20


def test_named_backends_that_do_not_import_are_config_errors(
        monkeypatch: pytest.MonkeyPatch, small: Scene) -> None:
    _without(monkeypatch, *NO_EMBREE, "open3d")
    for name in ("embree", "open3d"):
        with pytest.raises(ConfigError, match=f"ray backend = '{name}' is invalid; allowed: "
                                              "an installed backend"):
            make_caster(name, small.vertices, small.faces)


@needs_embreex
def test_trimesh_finds_embrees_first_hits(small: Scene) -> None:
    embree = make_caster("embree", small.vertices, small.faces)
    trimesh = small.caster
    assert isinstance(trimesh, TrimeshCaster)
    o, d = _sensor_rays(3000)
    t0, p0 = embree.cast(o, d)
    t1, p1 = trimesh.cast(o, d)
    assert t1.dtype == np.float32 and p1.dtype == np.int32
    hit = np.isfinite(t0)
    assert np.array_equal(hit, np.isfinite(t1)) and hit.sum() > 1500
    assert np.allclose(t1[hit], t0[hit], rtol=0.0, atol=2e-5)
    assert np.array_equal(p1, p0)  # the same triangles, -1 on a miss
    assert (small.stem_id[p1[hit]] > 0).sum() > 50  # stems among them, not only ground
    # Rays aimed exactly at vertices and edge midpoints: trimesh's test is not watertight
    # (Embree's robust mode is), so a few slip through to what lies behind.
    v = small.vertices.astype(np.float32)
    f = small.faces[::25]
    eye = np.array([0.3, -1.7, 2.5], np.float32)
    to = np.concatenate([v[f[:, 0]], (v[f[:, 0]] + v[f[:, 1]]) / 2]) - eye
    o2 = np.broadcast_to(eye, to.shape)
    d2 = (to / np.linalg.norm(to, axis=1, keepdims=True)).astype(np.float32)
    t0, _ = embree.cast(o2, d2)
    t1, _ = trimesh.cast(o2, d2)
    with np.errstate(invalid="ignore"):  # inf - inf: both missed
        same = np.where(np.isfinite(t0), np.abs(t1 - t0) <= 2e-5, np.isinf(t1))
    assert same.mean() > 0.98


def test_trimesh_answers_like_the_other_casters() -> None:
    """inf and -1 for a miss (a triangle behind the origin is one), float32 and int32, the
    nearer of two triangles, and nothing for no rays."""
    verts = np.array([[2.0, -1, -1], [2.0, 1, -1], [2.0, 0, 1],
                      [4.0, -1, -1], [4.0, 1, -1], [4.0, 0, 1]])
    faces = np.array([[3, 4, 5], [0, 1, 2]])
    c = TrimeshCaster(verts, faces)
    o = np.zeros((4, 3), np.float32)
    d = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [2, 0, 0]], np.float32)
    t, prim = c.cast(o, d)
    assert t.dtype == np.float32 and prim.dtype == np.int32
    assert t[0] == np.float32(2.0) and prim[0] == 1  # the nearer one, though listed second
    assert np.isinf(t[1]) and np.isinf(t[2]) and prim[1] == prim[2] == -1
    assert t[3] == np.float32(1.0) and prim[3] == 1  # in lengths of the direction, as Embree
    t, prim = c.cast(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert t.shape == prim.shape == (0,) and t.dtype == np.float32


@needs_embreex
@needs_open3d
def test_a_scene_declares_its_casters_threads(small: Scene) -> None:
    embree = Scene(small.vertices, small.faces, small.stem_id,
                   make_caster("embree", small.vertices, small.faces))
    assert embree.threads == embree.caster.threads
    embree.threads = 3
    assert embree.caster.threads == 3 and embree.threads == 3
    o3d = Scene(small.vertices, small.faces, small.stem_id,
                make_caster("open3d", small.vertices, small.faces))
    assert o3d.backend == "open3d" and o3d.threads is None and o3d.threads_itself
    assert o3d.direct() is None


def test_the_cli_offers_every_backend() -> None:
    from tcf_hil.cli._shared import BACKEND_CHOICES

    assert BACKEND_CHOICES == ("auto", *BACKENDS)


@needs_open3d
def test_lidar_pcap_says_once_which_backend_auto_took_and_records_it(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Where Embree cannot be had, the default (auto) works on open3d, says so once on
    stderr, and the recording names the backend that cast its rays."""
    from tcf_hil.cli import _shared, main
    from tcf_hil.scenario import scenario_to_toml

    _without(monkeypatch, *NO_EMBREE)
    monkeypatch.setattr(_shared, "_announced", set())
    toml = tmp_path / "small.toml"
    toml.write_text(scenario_to_toml(SCN))
    code = main(["lidar", "pcap", str(toml), "--mode", "512x10", "--frames", "2",
                 "--out", str(tmp_path / "o")])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert out.err.count("ray backend: open3d (embreex is not installed here") == 1
    assert "(open3d)" in out.out
    vis = json.loads((tmp_path / "o" / "visibility.json").read_text())
    assert vis["backend"] == "open3d" and vis["frames"] == 2
