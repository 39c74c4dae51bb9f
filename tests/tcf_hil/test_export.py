"""``tcf-hil export``: the cloud read back by laspy (LAS and LAZ), open3d (PCD) and trimesh
(PLY) lands where ouster-sdk puts the same capture, at UTM-sized coordinates without losing
millimetres; every return's label agrees with the ground truth's return counts; the DUAL
profile's two returns are numbered by range; GPS time follows the run's clock; the stems
come out as GeoJSON and CSV; bad input is one clear line."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import laspy
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from ouster.sdk import core
from ouster.sdk import pcap as opcap
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from protocols.labels import (
    LabelsError,
    encode_labels_header,
    encode_labels_record,
    read_labels,
)
from tcf_hil.cli import main
from tcf_hil.devices.offline import record_pcap
from tcf_hil.results.export import (
    GPS_MINUS_UNIX_S,
    PCD_DTYPE,
    _rotations,
    export,
)
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.world.track import distance_to_track

UTM = (512_345.0, 6_912_345.0, 120.0)


def _natural() -> dict:
    """``pine-thinning`` (stems, branches, foliage, understory, dead wood, stumps, boulders) on
    24 x 24 m at a UTM origin, the realistic sensor (footprint, noise, false returns)."""
    d = scenario_to_dict(load_scenario("pine-thinning"))
    d["name"] = "export-small"
    d["plot"] = {"size_m": [24.0, 24.0], "origin_m": list(UTM)}
    d["stems"] = {**d["stems"], "count": 127}  # 2,200 per ha
    d["track"] = {**d["track"], "start_m": [0.0, -10.0, 2.0], "end_m": [0.0, 10.0, 2.0],
                  "speed_m_s": 2.0}
    return d


@pytest.fixture(scope="module")
def natural_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("export") / "run"
    record_pcap(scenario_from_dict(_natural()), out, mode="512x10", max_frames=3)
    return out


def _sdk_world(run: Path) -> np.ndarray:
    src = opcap.PcapFrameSetSource(str(run / "lidar.pcap"), meta=[str(run / "metadata.json")])
    lut = core.XYZLut(src.sensor_info[0], use_extrinsics=False)
    rows = list(csv.reader((run / "sensor_poses.csv").open()))[1:]
    poses = {int(r[0]): np.array([float(v) for v in r[1:]]) for r in rows}
    pts = []
    for fs in src:
        fr = fs[0]
        pose = np.array([poses[int(t)] for t in fr.timestamp])
        rot = Rotation.from_quat(pose[:, [4, 5, 6, 3]]).as_matrix()
        world = np.einsum("wij,hwj->hwi", rot, lut(fr)) + pose[None, :, :3]
        pts.append(world[fr.field("RANGE") > 0])
    return np.vstack(pts)


def test_las_points_are_ouster_sdks_points_at_a_utm_origin(natural_run: Path,
                                                           tmp_path: Path) -> None:
    las_path = tmp_path / "cloud.las"
    assert main(["export", str(natural_run), "--out", str(las_path)]) == 0
    las = laspy.read(las_path)
    h = las.header
    assert (h.version.major, h.version.minor) == (1, 4) and h.point_format.id == 6
    assert np.allclose(h.scales, 0.001)
    # the offset is near the data (UTM-sized coordinates fit int32 at 1 mm)
    assert np.all(np.abs(h.offsets[:2] - np.array(UTM[:2])) < 1000.0)
    xyz = np.column_stack([las.x, las.y, las.z])
    sdk = _sdk_world(natural_run)
    assert len(xyz) == len(sdk) > 10_000
    assert np.all(np.abs(xyz[:, :2] - np.array(UTM[:2])) < 100.0)
    for p, q in ((xyz, sdk), (sdk, xyz)):  # every point has its twin within LAS's 1 mm grid
        d, _ = cKDTree(q).query(p)
        assert d.max() <= 0.0005 * np.sqrt(3) + 1e-6
    assert np.allclose(h.mins, xyz.min(axis=0)) and np.allclose(h.maxs, xyz.max(axis=0))
    assert h.generating_software.startswith("tcf-hil")
    assert set(las.point_format.extra_dimension_names) == {"stem_id", "component", "ring"}
    assert h.parse_crs() is None  # no --epsg: no coordinate system claimed


@pytest.mark.parametrize("suffix", ["las", "laz"])
def test_epsg_goes_into_the_las_wkt_record(natural_run: Path, tmp_path: Path,
                                           suffix: str) -> None:
    """--epsg 3067 (ETRS-TM35FIN, Finland's national grid) as LAS 1.4's OGC coordinate
    system WKT record, read back by laspy and pyproj; the points are unchanged."""
    path = tmp_path / f"cloud.{suffix}"
    assert main(["export", str(natural_run), "--out", str(path), "--every", "5",
                 "--epsg", "3067"]) == 0
    h = laspy.read(path).header
    assert h.global_encoding.wkt
    rec = [v for v in h.vlrs if v.record_id == 2112]
    assert len(rec) == 1 and rec[0].user_id == "LASF_Projection"
    assert rec[0].string.startswith('PROJCS["ETRS89 / TM35FIN(E,N)"')  # WKT 1 (OGC 01-009)
    assert h.parse_crs().to_epsg() == 3067
    plain = tmp_path / f"plain.{suffix}"
    assert main(["export", str(natural_run), "--out", str(plain), "--every", "5"]) == 0
    a, b = laspy.read(path), laspy.read(plain)
    assert np.array_equal(a.points.array, b.points.array)


def test_labels_agree_with_the_ground_truths_return_counts(natural_run: Path,
                                                           tmp_path: Path) -> None:
    export(natural_run, tmp_path / "c.laz")
    las = laspy.read(tmp_path / "c.laz")
    gt = json.loads((natural_run / "ground_truth.json").read_text())
    comp, sid, cls = (np.asarray(las[k]) for k in ("component", "stem_id", "classification"))
    per_stem = np.bincount(sid[comp == 1], minlength=len(gt["objects"]) + 1)
    for o in gt["objects"]:
        assert per_stem[o["id"]] == o["returns"], o["id"]
        assert np.count_nonzero((sid == o["id"]) & (comp == 2)) == \
            o["returns_by_component"]["branch"]
    by = gt["returns_by_component"]
    assert np.count_nonzero(comp == 0) == by["ground"]
    assert np.count_nonzero(comp == 3) == by["foliage"]
    # the classes follow the components; a return that hit nothing is noise
    expect = {0: 2, 1: 64, 2: 5, 3: 5, 4: 3, 5: 1, 6: 1, 7: 1, 255: 7}
    for c, k in expect.items():
        assert set(np.unique(cls[comp == c]).tolist()) <= {k}
    assert by["stem"] > 0 and by["foliage"] > 0
    # LAZ is LAS compressed: the same points
    export(natural_run, tmp_path / "c.las")
    plain = laspy.read(tmp_path / "c.las")
    assert np.array_equal(plain.points.array, las.points.array)


def test_pcd_and_ply_carry_the_same_points(natural_run: Path, tmp_path: Path) -> None:
    import open3d as o3d
    import trimesh

    export(natural_run, tmp_path / "c.las")
    las = laspy.read(tmp_path / "c.las")
    ref = np.column_stack([las.x, las.y, las.z])
    export(natural_run, tmp_path / "c.pcd")
    # float32 from the offset its header states (open3d reads float64 PCD coordinates as 0)
    head, body = (tmp_path / "c.pcd").read_bytes().split(b"DATA binary\n", 1)
    line = next(ln for ln in head.decode().splitlines() if ln.startswith("# tcf-hil offset"))
    off = np.array([float(v) for v in line.split()[3:6]])
    assert np.allclose(off, las.header.offsets)
    pcd = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "c.pcd")).points) + off
    export(natural_run, tmp_path / "c.ply")
    ply = trimesh.load(tmp_path / "c.ply", process=False)
    for pts in (pcd, np.asarray(ply.vertices)):
        assert len(pts) == len(ref)
        assert np.abs(pts - ref).max() <= 0.0005 + 1e-4  # against LAS's 1 mm grid
    rec = np.frombuffer(body, PCD_DTYPE)
    assert np.array_equal(rec["stem_id"], np.asarray(las.stem_id))
    assert np.array_equal(rec["classification"], np.asarray(las.classification))


def test_dual_returns_are_numbered_by_range(tmp_path: Path) -> None:
    scn = scenario_from_dict(_natural())
    record_pcap(scn, tmp_path / "run", mode="512x10", max_frames=2,
                profile="RNG19_RFL8_SIG16_NIR16_DUAL")
    export(tmp_path / "run", tmp_path / "d.las")
    las = laspy.read(tmp_path / "d.las")
    rn, nr = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert set(np.unique(nr).tolist()) <= {1, 2} and np.any(nr == 2)
    assert np.all(rn <= nr)
    # per pixel (same GPS time and ring), return 1 is the nearer, from its own column's pose
    # (no manifest: GPS time is the simulation clock's seconds, i.e. the column's time stamp)
    rows = list(csv.reader((tmp_path / "run" / "sensor_poses.csv").open()))[1:]
    poses = {int(r[0]): np.array([float(v) for v in r[1:4]]) for r in rows}
    t, ring = np.asarray(las.gps_time), np.asarray(las.ring)
    pos = np.column_stack([las.x, las.y, las.z])
    pairs: dict[tuple[float, int], list[int]] = {}
    for i in np.flatnonzero(nr == 2).tolist():
        pairs.setdefault((t[i], ring[i]), []).append(i)
    checked = 0
    for (ti, _), idx in pairs.items():
        assert len(idx) == 2 and sorted(rn[idx].tolist()) == [1, 2]
        sensor = poses[round(ti * 1e9)]
        i1, i2 = sorted(idx, key=lambda i: rn[i])
        assert np.linalg.norm(pos[i1] - sensor) <= np.linalg.norm(pos[i2] - sensor) + 0.002
        checked += 1
    assert checked > 100


def test_gps_time_follows_the_runs_clock(natural_run: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    for f in natural_run.iterdir():
        (run / f.name).symlink_to(f)
    unix0 = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z at simulation time t0
    t0 = int(next(csv.reader(io.StringIO(
        (natural_run / "sensor_poses.csv").read_text().splitlines()[1])))[0])
    (run / "manifest.json").write_text(json.dumps(
        {"clock": {"sim_t0_ns": t0, "unix_ns_at_sim_t0": unix0, "speed": 1.0}}))
    r = export(run, tmp_path / "g.las")
    assert r.gps_adjusted
    las = laspy.read(tmp_path / "g.las")
    assert las.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
    gps = np.asarray(las.gps_time)
    start = 1_767_225_600 - GPS_MINUS_UNIX_S - 1e9  # adjusted standard GPS time at t0
    assert start == pytest.approx(451_260_818.0)  # 2026-01-01: GPS leads UTC by 18 s
    assert gps.min() >= start - 1e-6 and gps.max() <= start + 0.31  # three frames


def test_every_nth_frame(natural_run: Path, tmp_path: Path) -> None:
    a = export(natural_run, tmp_path / "a.pcd").count
    b = export(natural_run, tmp_path / "b.pcd", every=2).count
    assert 0 < b < a


def test_stems_as_geojson_and_csv(natural_run: Path, tmp_path: Path) -> None:
    assert main(["export", str(natural_run), "--out", str(tmp_path / "s.geojson"),
                 "--epsg", "3067"]) == 0
    doc = json.loads((tmp_path / "s.geojson").read_text())
    gt = json.loads((natural_run / "ground_truth.json").read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["crs"]["properties"]["name"].endswith("EPSG::3067")
    feats = doc["features"]
    assert len(feats) == len(gt["objects"])  # no SIC ran: the truth, all missed
    f0, o0 = feats[0], gt["objects"][0]
    assert f0["geometry"]["coordinates"] == pytest.approx(o0["cp"], abs=1e-4)
    assert f0["properties"]["dbh_m"] == o0["dbh"]
    outcomes = {f["properties"]["outcome"] for f in feats}
    assert outcomes <= {"missed_seen", "missed_unseen"} and len(outcomes) == 2
    seen = {f["properties"]["id"] for f in feats if f["properties"]["outcome"] == "missed_seen"}
    assert seen == {o["id"] for o in gt["objects"] if o["returns"] > 0}
    # the distance from the driven track (world coordinates, as the stems'): against every
    # recorded pose (the track is straight, so its polyline and its poses agree)
    rows = list(csv.reader((natural_run / "sensor_poses.csv").open()))[1:]
    track = np.array([[float(r[1]), float(r[2])] for r in rows])
    for f in feats:
        xy = np.array(f["geometry"]["coordinates"][:2])
        near = np.hypot(*(track - xy).T).min()
        assert abs(f["properties"]["distance_to_track_m"] - near) < 0.01
    assert main(["export", str(natural_run), "--out", str(tmp_path / "s.csv")]) == 0
    rows = list(csv.DictReader((tmp_path / "s.csv").open()))
    assert len(rows) == len(gt["objects"]) and rows[0]["source"] == "truth"
    assert float(rows[0]["x"]) == pytest.approx(o0["cp"][0], abs=1e-4)


def test_bad_input_is_one_line_and_writes_nothing(natural_run: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "x.las"
    assert main(["export", str(tmp_path / "nothing"), "--out", str(out)]) == 1
    assert main(["export", str(natural_run), "--out", str(tmp_path / "x.xyz")]) == 1
    run = tmp_path / "run"
    run.mkdir()
    for f in natural_run.iterdir():
        if f.name != "lidar_labels.bin":
            (run / f.name).symlink_to(f)
    data = (natural_run / "lidar_labels.bin").read_bytes()
    (run / "lidar_labels.bin").write_bytes(b"NOTLABEL" + data[8:])
    assert main(["export", str(run), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 3
    assert "nothing" in lines[0] and ".xyz" in lines[1]
    assert "lidar_labels.bin" in lines[2] and "magic" in lines[2]
    assert not out.exists() and not list(tmp_path.glob(".*part*"))
    # a capture whose poses end after its first frame fails while writing: nothing is left
    (run / "lidar_labels.bin").unlink()
    (run / "lidar_labels.bin").symlink_to(natural_run / "lidar_labels.bin")
    (run / "sensor_poses.csv").unlink()
    lines = (natural_run / "sensor_poses.csv").read_text().splitlines(keepends=True)
    (run / "sensor_poses.csv").write_text("".join(lines[:1 + 512]))
    for suffix in ("las", "ply", "pcd"):
        assert main(["export", str(run), "--out", str(tmp_path / f"cut.{suffix}")]) == 1
        assert not (tmp_path / f"cut.{suffix}").exists()
    err = capsys.readouterr().err
    assert "sensor_poses.csv" in err and "no pose for the column time stamp" in err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    # a malformed pose line is named
    (run / "sensor_poses.csv").write_text("".join(lines[:5]) + "1,2,x,4,5,6,7,8\n")
    assert main(["export", str(run), "--out", str(out)]) == 1
    assert "sensor_poses.csv at line 6" in capsys.readouterr().err
    # --epsg: PLY, PCD and CSV have no place for it (a usage error); a code PROJ does not
    # know is one line naming --epsg, and nothing is written
    for suffix in ("ply", "pcd", "csv"):
        assert main(["export", str(natural_run), "--out", str(tmp_path / f"c.{suffix}"),
                     "--epsg", "3067"]) == 2
    assert "--epsg" in capsys.readouterr().err
    assert main(["export", str(natural_run), "--out", str(out), "--epsg", "999999"]) == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and "--epsg" in lines[0] and "EPSG:999999" in lines[0]
    assert not out.exists()
    (run / "sensor_poses.csv").unlink()
    (run / "sensor_poses.csv").symlink_to(natural_run / "sensor_poses.csv")
    # without labels (a run recorded before them): points, unclassified
    (run / "lidar_labels.bin").unlink()
    r = export(run, out)
    assert r.count > 0 and not r.labelled
    assert set(np.unique(laspy.read(out).classification).tolist()) == {1}


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 8), st.integers(1, 40), st.booleans(),
       st.lists(st.integers(0, 7), min_size=1, max_size=30), st.data())
def test_labels_codec_round_trips(rows: int, cols: int, dual: bool, comp: list[int],
                                  data: st.DataObject) -> None:
    frames = data.draw(st.lists(arrays(np.int32, (2 if dual else 1, rows, cols),
                                       elements=st.integers(-1, 2**31 - 1)),
                                min_size=0, max_size=4))
    blob = encode_labels_header(rows, cols, dual, 3, np.array(comp))
    for k, f in enumerate(frames):
        blob += encode_labels_record(10 * k, 10 * k + 9, f[0], f[1] if dual else None)
    head, recs = read_labels(io.BytesIO(blob))
    assert (head.rows, head.columns, head.dual, head.n_stems) == (rows, cols, dual, 3)
    assert head.component_of_id.tolist() == comp
    got = list(recs)
    assert len(got) == len(frames)
    for k, (g, f) in enumerate(zip(got, frames, strict=True)):
        assert (g.first_ns, g.last_ns) == (10 * k, 10 * k + 9)
        assert np.array_equal(g.ids, f[0])
        assert (g.ids2 is None) != dual and (not dual or np.array_equal(g.ids2, f[1]))
    # a record cut short (a crash while writing) ends the records; a bad body raises
    if frames:
        assert len(list(read_labels(io.BytesIO(blob[:-1]))[1])) == len(frames) - 1
    with pytest.raises(LabelsError, match="magic"):
        read_labels(io.BytesIO(b"X" * 40))


@settings(max_examples=50, deadline=None)
@given(arrays(np.float64, (5, 4), elements=st.floats(-1, 1)))
def test_rotations_are_scipys(q: np.ndarray) -> None:
    n = np.linalg.norm(q, axis=1)
    q = q[n > 1e-3] / n[n > 1e-3, None]
    if not len(q):
        return
    ref = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    assert np.allclose(_rotations(q), ref, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (12, 2), elements=st.floats(-50, 50)),
       arrays(np.float64, (7, 2), elements=st.floats(-60, 60)))
def test_distance_to_track_is_the_nearest_segments(track: np.ndarray, xy: np.ndarray) -> None:
    """Against brute force over every segment, for tracks with segments of any length."""
    got = distance_to_track(xy, track)
    a, b = track[:-1], track[1:]
    ab = b - a
    ap = xy[:, None, :] - a[None]
    u = np.clip(np.sum(ap * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0, 1)
    brute = np.linalg.norm(ap - u[..., None] * ab, axis=-1).min(axis=1)
    assert np.allclose(got, brute, atol=1e-9)


def test_sampled_frames_are_the_captures_own(tmp_path: Path) -> None:
    """``run_cloud(sample=...)`` reads frames from windows of the capture (a resync on the
    record boundaries, the poses found by bisection, the labels skipped uninflated): every
    frame it gives is one the full read gives, point for point, label for label."""
    from tcf_hil.results.export import run_cloud

    d = _natural()
    d["stems"] = {**d["stems"], "count": 40}
    out = tmp_path / "run"
    record_pcap(scenario_from_dict(d), out, mode="512x10", max_frames=12)
    full = [f for f in run_cloud(out)[1]]
    assert len(full) >= 11
    for k in (1, 3, 5, 12):
        got = [f for f in run_cloud(out, sample=(k, 12))[1]]
        # (windows three frames long: as many as the capture has frames overlap, and the
        # frames two windows share come once)
        assert len(got) >= (k - 1 if k < 12 else 6), (k, len(got))
        for f in got:
            assert any(len(f) == len(g) and np.array_equal(f, g) for g in full), k
