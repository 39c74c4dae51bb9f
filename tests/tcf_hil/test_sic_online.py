"""The onboard SIC's parts without the bench around them: batch packet decoding against the
per-packet decoder (hypothesis), the pose track across the 32-bit time wrap, the world
transform against the emulator's own sensor poses, the incremental stem map against the
one-shot algorithm, and the recorder's publication channels."""

from __future__ import annotations

import json
import math
import os
import threading
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from protocols.ouster import (
    PROFILES,
    ProtocolError,
    decode_lidar_packet,
    decode_lidar_packets,
    encode_lidar_frame,
    os0_64_metadata,
)
from tcf_hil._rotations import rotation_ypr
from tcf_hil.run import sic_command
from tcf_hil.run.recorder import FileWatcher, Inbox, PublishServer
from tcf_hil.sic import identify_stems, stem_params
from tcf_hil.sic._map import StemMap
from tcf_hil.sic._online import OnboardSic, PoseTrack


@settings(max_examples=25, deadline=None)
@given(profile=st.sampled_from(sorted(PROFILES)), mode=st.sampled_from(["512x10", "1024x10"]),
       seed=st.integers(0, 2**32 - 1), frame_id=st.integers(0, 0xFFFF))
def test_batch_decode_equals_the_per_packet_decoder(profile: str, mode: str, seed: int,
                                                    frame_id: int) -> None:
    meta = os0_64_metadata(mode, profile, init_id=12345)
    fmt = meta.packet_format
    rng = np.random.default_rng(seed)
    H, W = fmt.pixels_per_column, fmt.columns_per_frame
    fields = {f.name: rng.integers(0, 1 << 20, (H, W)) for f in fmt.profile.fields}
    ts = 10**9 + np.arange(W, dtype=np.int64) * 97_000
    arr = encode_lidar_frame(fmt, fields, ts, frame_id=frame_id, init_id=meta.init_id,
                             prod_sn=meta.prod_sn)
    batch = decode_lidar_packets(fmt, arr, init_id=meta.init_id, prod_sn=meta.prod_sn)
    one = [decode_lidar_packet(fmt, row, init_id=meta.init_id, prod_sn=meta.prod_sn)
           for row in arr]
    assert (batch.frame_id == frame_id).all()
    np.testing.assert_array_equal(batch.timestamps_ns, np.stack([p.timestamps_ns for p in one]))
    np.testing.assert_array_equal(batch.measurement_id,
                                  np.stack([p.measurement_id for p in one]))
    for name in fmt.field_names:
        np.testing.assert_array_equal(batch.fields[name],
                                      np.concatenate([p.fields[name] for p in one], axis=1))


@settings(max_examples=200, deadline=None)
@given(data=st.binary(min_size=0, max_size=64), where=st.integers(0, 10**6),
       n=st.integers(1, 3))
def test_batch_decode_of_damaged_packets_raises_only_protocol_errors(data: bytes, where: int,
                                                                     n: int) -> None:
    meta = os0_64_metadata("512x10", "RNG19_RFL8_SIG16_NIR16", init_id=7)
    fmt = meta.packet_format
    arr = encode_lidar_frame(fmt, {"RANGE": np.ones((64, 512), np.int64)},
                             np.arange(512, dtype=np.int64), frame_id=1, init_id=7,
                             prod_sn=meta.prod_sn)[:n].copy()
    flat = arr.reshape(-1)
    pos = where % len(flat)
    chunk = np.frombuffer(data, np.uint8)[: len(flat) - pos]
    flat[pos:pos + len(chunk)] = chunk
    try:
        b = decode_lidar_packets(fmt, arr, init_id=7, prod_sn=meta.prod_sn)
    except ProtocolError:
        return
    assert b.fields["RANGE"].shape == (64, n * fmt.columns_per_packet)


def test_pose_track_interpolates_across_the_32_bit_time_wrap() -> None:
    tr = PoseTrack()
    wrap_us = 1 << 32
    t0_us = wrap_us - 5_000  # 5 ms before the count wraps
    for k in range(20):
        t_us = t0_us + k * 1000
        # 1 m/s north, heading 0 = north, turning 1 deg per sample through 359 -> 0
        tr.add(t_us % wrap_us, 0.0, k * 0.001, 0.0, (359.0 + k) % 360.0, 0.0, 0.0)
    q = np.array([(t0_us + 7_500) * 1000.0])  # a lidar time stamp (ns, not wrapped)
    assert tr.covers(float(q[0]))
    pos, rot = tr.at(q)
    assert pos[0, 1] == pytest.approx(0.0075, abs=1e-12)
    heading = (359.0 + 7.5) % 360.0
    yaw = math.radians(90.0 - heading)
    np.testing.assert_allclose(rot[0], rotation_ypr(np.array([yaw]), np.zeros(1),
                                                    np.zeros(1))[0], atol=1e-12)
    # beyond the last pose, the track does not cover the time yet
    assert not tr.covers((t0_us + 30_000) * 1000.0)


def test_pose_track_matches_lidar_time_a_wrap_ahead_of_the_pose_count() -> None:
    """The bus counts microseconds modulo 2^32 from the start; the lidar counts nanoseconds
    without wrapping: 5 s past one wrap, the pose count reads 5 s."""
    tr = PoseTrack(capacity=64, window=16)
    base_us = (1 << 32) + 5_000_000
    for k in range(100):  # also wraps the ring buffer (capacity 64)
        t_us = base_us + k * 10_000
        tr.add(t_us % (1 << 32), k * 0.01, 0.0, 0.0, 90.0, 0.0, 0.0)  # east at 1 m/s
    q = np.array([(base_us + 955_000) * 1000.0])
    assert tr.covers(float(q[0])) and tr.received == 100
    pos, _ = tr.at(q)
    assert pos[0, 0] == pytest.approx(0.955, abs=1e-9)


def test_the_drive_ends_only_as_far_as_the_lidar_has_shown_it() -> None:
    # 2 s at 1 m/s east, then 10 s standing (poses at 100 Hz, the count past one wrap)
    tr = PoseTrack()
    base_us = (1 << 32) + 1_000_000
    for k in range(1201):
        x = min(k, 200) * 0.01
        tr.add((base_us + k * 10_000) % (1 << 32), x, 0.0, 0.0, 90.0, 0.0, 0.0)
    # (it stands from within STILL_M of where it stopped: 1 pose, 10 ms, early)
    assert tr.stood_still_s() == pytest.approx(10.0, abs=0.02)  # by the bus alone
    stopped_ns = (base_us + 2_000_000) * 1000.0  # a lidar time stamp (not wrapped)
    # a sensor behind the bus: the lidar has shown 1 s of the standing, not 10
    assert tr.stood_still_s(stopped_ns + 1e9) == pytest.approx(1.0, abs=0.02)
    assert tr.stood_still_s(stopped_ns - 1e9) == 0.0  # still driving, as the lidar shows it
    assert tr.stood_still_s(stopped_ns + 60e9) == tr.stood_still_s()  # never past the bus
    fresh = PoseTrack()  # a machine that never drove has not ended a drive
    for k in range(1000):
        fresh.add(k * 10_000, 0.0, 0.0, 0.0, 90.0, 0.0, 0.0)
    assert fresh.stood_still_s(1e13) == 0.0


def test_world_points_land_where_the_sdk_ray_model_puts_them() -> None:
    meta = os0_64_metadata("512x10", "RNG19_RFL8_SIG16_NIR16")
    mount = np.array([1.5, -0.5, 2.0])
    mrot = rotation_ypr(np.radians([10.0]), np.radians([-3.0]), np.radians([2.0]))[0]
    rays = OnboardSic.mounted_rays(meta, mount, mrot)
    rng = np.random.default_rng(3)
    cols = np.array([0, 7, 300, 511])
    r = rng.integers(1000, 40000, (64, 4)).astype(np.uint32)
    r[5, 1] = 0  # no return
    pos = rng.normal(size=(4, 3)) * 10
    rot = rotation_ypr(rng.uniform(-3, 3, 4), rng.uniform(-0.2, 0.2, 4),
                       rng.uniform(-0.2, 0.2, 4))
    got = OnboardSic.world_points(r, cols, pos, rot, rays)
    from protocols.ouster import xyz_from_range

    full = np.zeros((64, 512), np.uint32)
    full[:, cols] = r
    sensor = xyz_from_range(meta, full)[:, cols]  # (64, 4, 3) in the sensor frame
    want = np.einsum("kij,hkj->hki", rot, sensor @ mrot.T + mount) + pos
    np.testing.assert_allclose(got, want[r > 0], atol=1e-9)
    assert len(got) == 64 * 4 - 1


def _cylinder_cloud(centres: list[tuple[float, float]], rng: np.random.Generator
                    ) -> np.ndarray:
    pts = []
    for cx, cy in centres:
        a = rng.uniform(0, 2 * np.pi, 6000)
        z = rng.uniform(0, 12, 6000)
        r = 0.15
        pts.append(np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a), z]))
    g = rng.uniform(-25, 25, (40000, 2))
    pts.append(np.column_stack([g, np.zeros(len(g))]))
    return np.concatenate(pts)


def test_incremental_map_finds_what_the_one_shot_algorithm_finds() -> None:
    rng = np.random.default_rng(0)
    # stems inside tiles and right on tile borders (10 m tiles)
    centres = [(-12.0, 3.0), (0.05, 0.05), (9.97, -4.0), (15.0, 15.0), (-5.0, -19.99)]
    cloud = _cylinder_cloud(centres, rng)
    prm = stem_params("tuned")
    smap = StemMap(prm, voxel_m=0.01)
    for chunk in np.array_split(rng.permutation(cloud), 7):  # arriving frame by frame
        smap.add(chunk)
        smap.update(0.0)  # one tile per frame
    smap.update()
    inc = smap.forest("t")
    one = identify_stems(cloud, prm)
    got = np.array(sorted((o["cp"][0], o["cp"][1]) for o in inc["objects"]))
    want = np.array(sorted((o["cp"][0], o["cp"][1]) for o in one["objects"]))
    assert len(got) == len(want) == len(centres)
    np.testing.assert_allclose(got, want, atol=0.02)
    np.testing.assert_allclose(got, sorted(centres), atol=0.03)
    for o in inc["objects"]:
        assert o["dbh"] == pytest.approx(0.30, abs=0.01)


def test_map_eviction_keeps_the_stems_of_dropped_tiles() -> None:
    rng = np.random.default_rng(1)
    cloud = _cylinder_cloud([(-20.0, 0.0), (20.0, 0.0)], rng)
    smap = StemMap(stem_params("tuned"), voxel_m=0.01, max_points=11_000)
    left, right = cloud[cloud[:, 0] < 0], cloud[cloud[:, 0] >= 0]
    smap.add(left, np.array([-20.0, 0.0]))
    smap.add(left, np.array([-20.0, 0.0]))  # seen again: duplicates, counted once
    smap.add(right, np.array([20.0, 0.0]))  # the machine moved: the left tiles go
    smap.update()
    assert smap.stats.evicted_points > 0
    held = sum(t.points for t in smap.tiles.values())
    assert smap.stats.points == held <= 11_000
    xs = sorted(round(o["cp"][0]) for o in smap.forest("t")["objects"])
    assert xs == [-20, 20]


def test_an_evicted_tile_keeps_its_stems_until_it_holds_more_points_again() -> None:
    """A tile that lost its points keeps the stems found on them: later returns run it
    again (and replace its stems) only once it holds more points than they were found on,
    not a few far ones, nor the same points again."""
    rng = np.random.default_rng(2)
    cloud = _cylinder_cloud([(-15.0, 5.0), (15.0, 5.0)], rng)  # tiles (-2, 0) and (1, 0)
    left, right = cloud[cloud[:, 0] < 0], cloud[cloud[:, 0] >= 0]
    stem = left[(left[:, 2] > 0.5)]  # the left stem's own points (the ground is not kept)
    smap = StemMap(stem_params("tuned"), voxel_m=0.01, max_points=11_000)
    smap.add(left, np.array([-15.0, 5.0]))
    smap.add(right, np.array([15.0, 5.0]))  # the left tiles go, their stems found first
    tile = smap.tiles[(-2, 0)]
    assert tile.evicted and tile.points == 0 and tile.basis > 1000
    kept = [o["dbh"] for o in tile.stems]
    assert len(kept) == 1
    smap.update()  # the right tiles
    smap.max_points = 10**6  # no more evictions
    runs = smap.stats.tile_runs
    smap.add(stem[::20], np.array([15.0, 5.0]))  # a few returns from afar: held, not run
    assert not tile.dirty
    smap.update()
    assert smap.stats.tile_runs == runs and [o["dbh"] for o in tile.stems] == kept
    smap.add(stem, np.array([15.0, 5.0]))  # all it was found on again: not more
    assert not tile.dirty
    more = _cylinder_cloud([(-15.0, 5.0)], rng)
    smap.add(more[more[:, 0] < 0], np.array([15.0, 5.0]))  # and new returns: more
    assert tile.dirty
    smap.update()
    assert not tile.evicted and tile.basis > 1.5 * len(stem)
    assert len(tile.stems) == 1 and tile.stems[0]["dbh"] == pytest.approx(0.30, abs=0.01)


@pytest.mark.parametrize("compiled", [True, False], ids=["hash-table", "sorted-runs"])
@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 400), min_size=1,
                                                      max_size=8))
def test_a_tile_holds_the_first_point_of_each_voxel_in_arrival_order(
        compiled: bool, seed: int, sizes: list[int]) -> None:
    """A tile's voxel set, frame after frame (the hash table and, without compiled
    kernels, the sorted runs): the same as one pass over all the points, the first of each
    voxel and kind (edge return or not) in the order they came, whatever the frames."""
    from tcf_hil.sic import _voxelset
    from tcf_hil.sic._map import _Tile

    rng = np.random.default_rng(seed)
    smap = StemMap(stem_params("tuned"), voxel_m=0.1)
    tile, seen = _Tile(), []
    if not compiled:
        tile.voxels = _voxelset.VoxelSet(compiled=False)
    for n in sizes:
        # a few voxels only, so that most points repeat one seen before
        pts = (rng.integers(0, 6, (n, 3)) * 0.1 + rng.uniform(0.01, 0.09, (n, 3)))
        # x, y, z and the edge half width: an edge return and a clean one share a voxel
        pts = np.column_stack([pts, rng.integers(0, 2, n) * 0.01]).astype(np.float32)
        new = tile.voxels.add(smap._keys_of(smap._voxels(pts)))
        tile.append(pts[new])
        seen.append(pts)
    allp = np.concatenate(seen)
    keys = smap._keys_of(smap._voxels(allp))
    _, first = np.unique(keys, return_index=True)
    np.testing.assert_array_equal(tile.held, allp[np.sort(first)])
    np.testing.assert_array_equal(tile.voxels.sorted(), np.unique(keys))
    assert len(tile.voxels) == tile.points == len(first)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), sizes=st.lists(st.integers(0, 3000), min_size=1,
                                                      max_size=12),
       step=st.integers(1, 5000))
def test_a_voxel_set_that_grows_moves_its_keys_a_step_at_a_time_and_loses_none(
        seed: int, sizes: list[int], step: int) -> None:
    """The hash table that grew keeps both tables until its keys moved (``step`` slots an
    add): whatever the moment, the masks are those of a set of every key seen."""
    from tcf_hil.sic._voxelset import VoxelSet, warm

    if not warm():
        pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")
    rng = np.random.default_rng(seed)
    v, ref = VoxelSet(), VoxelSet(compiled=False)
    v.step = step
    for n in sizes:
        keys = rng.integers(1, 3 * sum(sizes) + 2, n)
        np.testing.assert_array_equal(v.add(keys), ref.add(keys))
        assert len(v) == len(ref)
    np.testing.assert_array_equal(v.sorted(), ref.sorted())


def test_a_voxel_set_takes_more_keys_at_once_than_its_next_table_was_sized_for() -> None:
    """A next table sized at one add, still being zeroed when an add brings more keys than
    it holds: a bigger one is made (a full table would leave a probe no empty slot)."""
    from tcf_hil.sic._voxelset import VoxelSet, warm

    if not warm():
        pytest.skip("compiled kernels are off (TCF_HIL_NO_JIT or no numba)")
    v, ref = VoxelSet(), VoxelSet(compiled=False)
    for keys in (np.arange(1, 300_001), np.array([300_001]),
                 np.arange(300_002, 1_000_002)[::-1]):
        np.testing.assert_array_equal(v.add(keys), ref.add(keys))
    assert len(v) == len(ref) == 1_000_001


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 2000), spread=st.floats(0.05, 25.0),
       far=st.booleans())
@example(seed=15, n=279, spread=0.125, far=True)  # a voxel astride the tile edge y = -2000 m
def test_a_frame_goes_to_its_tiles_one_point_a_voxel_the_first_in_arrival_order(
        seed: int, n: int, spread: float, far: bool) -> None:
    """StemMap.add keeps the first point of each voxel of the frame, in arrival order, and
    hands each tile its own (the packed sort of offsets from the frame's corner against
    numpy's unique and lexsort of the map's global voxel keys): repeats, tile and voxel
    boundaries, a map kilometres from its datum."""
    rng = np.random.default_rng(seed)
    smap = StemMap(stem_params("tuned"), max_points=10**9)
    base = np.array([3000.0, -2000.0, 0.0]) if far else np.zeros(3)
    pts = base + np.column_stack([rng.uniform(-spread, spread, (n, 2)),
                                  rng.uniform(1.0, 9.0, n)])
    pts = np.round(pts / 0.015) * 0.015  # on the voxel and tile boundaries too
    pts[: n // 5] = pts[n // 5: 2 * (n // 5)]  # repeats
    g = np.arange(-spread - 1.0, spread + 1.0, 0.5)
    gx, gy = np.meshgrid(g, g)
    smap.add(base + np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]))
    # ^ flat ground under every cell: every point of the frame lies above it
    smap.tiles.clear()
    smap.add(pts)
    keys = smap._keys_of(smap._voxels(pts))
    # each tile holds its own voxels: a voxel that straddles a tile's edge (10 m is no
    # multiple of 3 cm) keeps its first point on each side
    tiles = np.floor(pts[:, :2] / smap.tile).astype(np.int64)
    _, first = np.unique(np.column_stack([tiles, keys]), axis=0, return_index=True)
    keep = pts[np.sort(first)]
    t = np.floor(keep[:, :2] / smap.tile).astype(np.int64)
    order = np.lexsort((t[:, 1], t[:, 0]))
    keep, t = keep[order], t[order]
    want: dict[tuple[int, int], list[np.ndarray]] = {}
    for p, (i, j) in zip(keep, t.tolist(), strict=True):
        want.setdefault((i, j), []).append(p)
    assert sorted(smap.tiles) == sorted(want)
    for tid, tile in smap.tiles.items():
        got = tile.held
        np.testing.assert_array_equal(got[:, :3], np.array(want[tid], dtype=np.float32))
        assert not got[:, 3].any()  # no edge widths given: none


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 300))
def test_ground_height_is_the_same_for_a_point_whatever_points_come_with_it(
        seed: int, n: int) -> None:
    """The sloped ground grid's height under points all inside it and under the same points
    among others outside it (inf there) agree to the bit."""
    from tcf_hil.sic._map import GroundGrid

    rng = np.random.default_rng(seed)
    grid = GroundGrid(1.0, slope=True)
    ground = rng.uniform(-8, 8, (200, 3))
    ground[:, 2] = 0.3 * ground[:, 0] - 0.1 * ground[:, 1] + rng.normal(0, 0.05, 200)
    grid.add(ground)
    xy = rng.uniform(-60, 60, (n, 2))  # the grid spans about -40..40 (its margin)
    inside = grid.height(xy)
    lo, hi = (np.array([grid.i0, grid.j0]), np.array([grid.i0, grid.j0]) + grid.z.shape)
    ok = np.all((np.floor(xy) >= lo) & (np.floor(xy) < hi), axis=1)
    assert np.all(np.isinf(inside[~ok]))
    np.testing.assert_array_equal(inside[ok], grid.height(xy[ok]))


def test_publications_over_http_and_file_are_kept_and_checked(tmp_path: Path) -> None:
    inbox = Inbox(tmp_path / "sic")
    server = PublishServer(inbox).start()
    target = tmp_path / "published.json"
    watcher = FileWatcher(inbox, target, period_s=0.02)
    watcher.start()
    try:
        def post(body: bytes, path: str = "/publish") -> tuple[int, dict]:
            url = server.url.replace("/publish", path)
            req = urllib.request.Request(url, data=body, method="POST")
            try:
                with urllib.request.urlopen(req) as r:
                    return r.status, json.loads(r.read())
            except urllib.error.HTTPError as e:
                return e.code, json.loads(e.read())

        ok = json.dumps({"objects": [{"cp": [1.0, 2.0, 0.0], "quality": 1}]}).encode()
        assert post(ok) == (200, {"n": 1, "valid": True, "error": None})
        code, body = post(b'{"objects": [{"cp": [1, 2, 3], "class": "Q"}]}')
        assert code == 400 and "class" in body["error"]
        assert post(ok, "/elsewhere")[0] == 404
        tmp = target.with_suffix(".tmp")
        tmp.write_text('{"objects": []}')
        tmp.replace(target)
        for _ in range(100):
            if len(inbox.items) == 3:
                break
            threading.Event().wait(0.02)
    finally:
        watcher.close()
        server.close()
        inbox.close()
    assert [(p.via, p.valid) for p in inbox.items] == [("http", True), ("http", False),
                                                       ("file", True)]
    assert (tmp_path / "sic" / "0002.json").read_bytes() == \
        b'{"objects": [{"cp": [1, 2, 3], "class": "Q"}]}'
    rows = [json.loads(x) for x in (tmp_path / "sic" / "index.ndjson").read_text()
            .splitlines()]
    assert [r["n"] for r in rows] == [1, 2, 3]
    assert inbox.valid[-1].objects == 0


def test_sic_command_fills_placeholders_without_a_shell() -> None:
    env = {"TCF_LIDAR_PORT": "7502", "TCF_METADATA": "/r/metadata.json"}
    argv = sic_command("my_sic --port {lidar_port} --meta '{metadata}' 'a b'", env, False)
    assert argv == ["my_sic", "--port", "7502", "--meta", "/r/metadata.json", "a b"]
    assert sic_command("x {lidar_port} | y", env, True) == "x 7502 | y"
    with pytest.raises(ValueError, match=r"unknown placeholder \{lidar_prot\}"):
        sic_command("x {lidar_prot}", env, False)
    # braces that are not placeholders stay (code passed to an interpreter)
    assert sic_command("p -c 'd = {\"a\": 1}; print(d)'", env, False) == \
        ["p", "-c", 'd = {"a": 1}; print(d)']
    with pytest.raises(ValueError, match="empty"):
        sic_command("  ", env, False)


def test_the_run_sensor_api_takes_a_new_destination_and_refuses_other_changes() -> None:
    """A scored run's sensor: set_config may redirect its stream (what ouster-sdk's
    SensorFrameSetSource(HOST) does: udp_dest @auto and its ports) without a new init_id;
    a new mode or profile, or a destination off loopback, is refused in the sensor's shape."""
    from emulators.lidar import SensorApi
    from emulators.lidar._http import _HttpError

    meta = os0_64_metadata("1024x10", "RNG19_RFL8_SIG16_NIR16", init_id=99)
    moved: list[Any] = []
    api = SensorApi(meta, "127.0.0.1", 0, fixed=True, on_redirect=moved.append)
    try:
        same = api.route("POST", "/api/v1/sensor/config", {"reinit": ["true"]},
                         lambda: {"udp_dest": "@auto"}, "127.0.0.1")
        assert same[0] == 200 and api.meta.init_id == 99 and moved == []
        ok = api.route("POST", "/api/v1/sensor/config", {"reinit": ["true"]},
                       lambda: {"udp_dest": "@auto", "udp_port_lidar": 7600,
                                "udp_port_imu": 7601}, "127.0.0.5")
        assert ok[0] == 200 and api.meta.init_id == 99
        assert [(m.udp_dest, m.udp_port_lidar, m.udp_port_imu) for m in moved] == \
            [("127.0.0.5", 7600, 7601)]
        with pytest.raises(_HttpError, match="fixed for the scored run") as err:
            api.route("POST", "/api/v1/sensor/config", {"reinit": ["true"]},
                      lambda: {"lidar_mode": "2048x10"}, "127.0.0.1")
        assert err.value.status == 400
        assert err.value.body() == {"error": {"title": "400 Bad Request",
                                              "description": err.value.message}}
        assert "lidar_mode" in err.value.message
        assert api.meta.mode == "1024x10" and api.meta.init_id == 99
        with pytest.raises(_HttpError, match="loopback"):
            api.route("POST", "/api/v1/sensor/config", {}, lambda: {"udp_dest": "@auto"},
                      "192.0.2.7")
        with pytest.raises(_HttpError, match="loopback"):  # the sender is IPv4
            api.route("POST", "/api/v1/sensor/config", {}, lambda: {"udp_dest": "::1"}, "::1")
        with pytest.raises(_HttpError, match=r"port 1 \.\. 65535"):  # sendto(port 0): EINVAL
            api.route("POST", "/api/v1/sensor/config", {"reinit": ["true"]},
                      lambda: {"udp_port_imu": 0}, "127.0.0.1")
        assert api.meta.udp_port_imu == 7601 and len(moved) == 1  # unchanged by the refusal
    finally:
        api.server.server_close()


def test_sdo_reads_of_a_silent_node_fail_with_context(caplog: pytest.LogCaptureFixture,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """canopen's "Transfer aborted by client with code 0x05040000" named neither node nor
    object: the SIC's own lines name both, and the bare one is held back."""
    import logging

    from tcf_hil.errors import SicError
    from tcf_hil.sic._online import CanPose, SicConfig

    cfg = SicConfig(can_interface="virtual", can_channel=f"sdo-silent-{os.getpid()}",
                    node_id=23)
    pose = CanPose(cfg, PoseTrack())
    try:
        with caplog.at_level(logging.INFO), pytest.raises(SicError) as err:
            pose.read_constants(timeout_s=0.5)
    finally:
        pose.net.disconnect()
    said = str(err.value)
    assert "node 23" in said and "0x2001" in said and "0x2002" in said and "tries" in said
    assert not [r for r in caplog.records if "Transfer aborted" in r.getMessage()]
    line = capsys.readouterr().err
    assert "from node 23" in line and "retrying while the node boots" in line
