"""A run's scene in Foxglove's schemas (foxglove-sdk): the same channels for a live view over
Foxglove's WebSocket protocol and for an MCAP file of a finished run.

Topics (frame ``world``: the scenario's world coordinates less the kilometre offset the
channels' metadata names, ``offset_m``, so that float32 points keep millimetres):

``/lidar/points``      ``foxglove.PointCloud``: a frame's returns in ``world``; x, y, z,
                       intensity (reflectivity), ring, component and stem_id (what the
                       return hit, where the truth is known) and red, green, blue, alpha
                       (the colour of what it hit: ``COMPONENT_COLOURS``; grey by intensity
                       where the truth is not known)
``/tf``                ``foxglove.FrameTransforms``: ``world`` -> ``os_sensor`` (the
                       sensor's pose at the frame's time: a finished run's at its last
                       return, from a pose sampled four times a frame; live, at its middle)
                       and ``world`` -> ``harvester`` (the machine's pose: a finished run's
                       as its CANopen node sent it, ``can.log``; live, from the track)
``/sensor/pose``       ``foxglove.PoseInFrame``: the same pose, for the Plot panel
``/track``             ``foxglove.SceneUpdate``: the sensor's track as a line
``/stems/truth``       ``foxglove.SceneUpdate``: the ground-truth stems as cylinders (DBH
                       wide, as tall as the tree), coloured by their outcome
``/stems/sic``         ``foxglove.SceneUpdate``: the SIC's latest stems, coloured by outcome
                       (matched dark grey, false positive blue)
``/score``             JSON: the latest publication's score (``wc_all``, ``wc_seen``,
                       ``f1_all``, ``f1_seen``, ``objects``, ``n``)

The outcome colours are the report's (:data:`tcf_hil.results.report.OUTCOMES`). A layout for
Foxglove ships with the package (:func:`layout_bytes`, ``report_assets/foxglove-layout.json``):
the 3D panel following ``os_sensor`` with the cloud in its own colours (colour mode "RGBA
(separate fields)"), the track and both sets of stems; a Plot of ``/score.wc_all`` and
``/score.wc_seen``; the latest score as a raw message.
"""

from __future__ import annotations

import contextlib
import heapq
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil._io import atomic_path, read_json, write_bytes_atomic
from tcf_hil.errors import InputError
from tcf_hil.recording.rundir import RunDir

__all__ = ["COMPONENT_COLOURS", "SCORE_SCHEMA", "TOPICS", "LiveView", "SceneChannels",
           "frame_time", "harvester_poses", "layout_bytes", "publication_rows", "publications",
           "write_mcap"]

WORLD = "world"
SENSOR = "os_sensor"  # ouster-ros's name for the sensor frame
HARVESTER = "harvester"  # the machine's base point (its CANopen pose)

TOPICS: dict[str, str] = {
    "/lidar/points": "foxglove.PointCloud", "/tf": "foxglove.FrameTransforms",
    "/sensor/pose": "foxglove.PoseInFrame", "/track": "foxglove.SceneUpdate",
    "/stems/truth": "foxglove.SceneUpdate", "/stems/sic": "foxglove.SceneUpdate",
    "/score": "json"}
"""Every topic the scene's channels carry and its schema."""

#: component (the labels' code, :data:`tcf_hil.results.export.CLOUD_DTYPE`'s ``component``)
#: -> RGB: ground grey, stem dark red, branches sienna, foliage green, understory light
#: green, dead wood tan, stump brown, boulder slate (the report's map: stems dark red,
#: vegetation green, ground grey)
COMPONENT_COLOURS: dict[int, tuple[int, int, int]] = {
    0: (150, 150, 150), 1: (139, 26, 26), 2: (160, 82, 45), 3: (34, 139, 34),
    4: (124, 200, 80), 5: (205, 170, 125), 6: (120, 70, 30), 7: (110, 120, 140)}

SCORE_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "tcf_hil.Score",
    "properties": {k: {"type": ["number", "null"]} for k in
                   ("n", "objects", "wc_all", "wc_seen", "f1_all", "f1_seen")}}
"""The JSON schema of ``/score``."""

_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<u2"),
                   ("ring", "u1"), ("component", "u1"), ("stem_id", "<u4"), ("red", "u1"),
                   ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])
#: name -> (dtype, byte offset) of each of a point's fields
_POINT_FIELDS: dict[str, tuple[np.dtype[Any], int]] = {
    n: (_POINT.fields[n][0], int(_POINT.fields[n][1]))  # type: ignore[index]
    for n in _POINT.names or ()}
_LUT = np.zeros((256, 3), np.uint8)
for _code, _rgb in COMPONENT_COLOURS.items():
    _LUT[_code] = _rgb


def layout_bytes() -> bytes:
    """The Foxglove layout that ships with the package (import it in Foxglove: Layouts,
    Import from file)."""
    from importlib import resources

    return (resources.files("tcf_hil") / "report_assets" / "foxglove-layout.json").read_bytes()


def outcome_rgba(outcome: Any, alpha: float) -> tuple[float, float, float, float]:
    """The report's colour of a stem's outcome (grey where it has none), 0-1 each."""
    from tcf_hil.results.report import OUTCOMES

    c = OUTCOMES.get(str(outcome), ("", "#8C8C8C"))[1]
    return _rgba(c, alpha)


def _rgba(colour: str, alpha: float) -> tuple[float, float, float, float]:
    c = colour.lstrip("#")
    return int(c[0:2], 16) / 255, int(c[2:4], 16) / 255, int(c[4:6], 16) / 255, alpha


def _hex(colour: str, alpha: float = 1.0) -> Any:
    from foxglove.messages import Color

    r, g, b, a = _rgba(colour, alpha)
    return Color(r=r, g=g, b=b, a=a)


def _stamp(t_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(int(t_ns) // 1_000_000_000, int(t_ns) % 1_000_000_000)


class SceneChannels:
    """The scene's channels on one foxglove-sdk ``Context`` (a live server's or an MCAP
    writer's): each method logs one message at ``t_ns`` (Unix nanoseconds)."""

    def __init__(self, context: Any, offset: NDArray[np.float64]) -> None:
        import foxglove
        from foxglove import channels as ch

        self.offset = np.asarray(offset, np.float64)
        meta = {"offset_m": " ".join(f"{v:.3f}" for v in self.offset),
                "frame": f"{WORLD}: world coordinates less offset_m"}
        self.points = ch.PointCloudChannel("/lidar/points", context=context, metadata=meta)
        self.tf = ch.FrameTransformsChannel("/tf", context=context, metadata=meta)
        self.pose = ch.PoseInFrameChannel("/sensor/pose", context=context, metadata=meta)
        self.track_ch = ch.SceneUpdateChannel("/track", context=context, metadata=meta)
        self.truth_ch = ch.SceneUpdateChannel("/stems/truth", context=context, metadata=meta)
        self.sic_ch = ch.SceneUpdateChannel("/stems/sic", context=context, metadata=meta)
        self.score_ch = foxglove.Channel("/score", schema=SCORE_SCHEMA, context=context)

    # ----------------------------------------------------------------------- messages
    def cloud(self, t_ns: int, pts: NDArray[np.void], labelled: bool = True) -> None:
        """A frame's returns (:data:`~tcf_hil.results.export.CLOUD_DTYPE` records)."""
        from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

        out = np.zeros(len(pts), _POINT)
        for i, k in enumerate("xyz"):
            out[k] = pts[k] - self.offset[i]
        out["intensity"], out["ring"] = pts["intensity"], pts["ring"]
        out["component"], out["stem_id"] = pts["component"], pts["stem_id"]
        if labelled:
            rgb = _LUT[pts["component"]]
            unknown = pts["component"] == 255
            if unknown.any():
                rgb[unknown] = _grey(pts["intensity"][unknown])
        else:
            rgb = _grey(pts["intensity"])
        out["red"], out["green"], out["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
        out["alpha"] = 255
        types = {"f4": PackedElementFieldNumericType.Float32,
                 "u2": PackedElementFieldNumericType.Uint16,
                 "u1": PackedElementFieldNumericType.Uint8,
                 "u4": PackedElementFieldNumericType.Uint32}
        fields = [PackedElementField(name=n, offset=off, type=types[dt.str[1:]])
                  for n, (dt, off) in _POINT_FIELDS.items()]
        self.points.log(PointCloud(timestamp=_stamp(t_ns), frame_id=WORLD,
                                   point_stride=_POINT.itemsize, fields=fields,
                                   data=out.tobytes()), log_time=int(t_ns))

    def sensor(self, t_ns: int, pose: NDArray[np.float64]) -> None:
        """The sensor's pose (x, y, z, qw, qx, qy, qz in world coordinates)."""
        from foxglove.messages import (
            FrameTransform,
            FrameTransforms,
            Pose,
            PoseInFrame,
            Quaternion,
            Vector3,
        )

        x, y, z = (float(v) for v in np.asarray(pose[:3]) - self.offset)
        qw, qx, qy, qz = (float(v) for v in pose[3:7])
        stamp = _stamp(t_ns)
        self.tf.log(FrameTransforms(transforms=[FrameTransform(
            timestamp=stamp, parent_frame_id=WORLD, child_frame_id=SENSOR,
            translation=Vector3(x=x, y=y, z=z),
            rotation=Quaternion(x=qx, y=qy, z=qz, w=qw))]), log_time=int(t_ns))
        self.pose.log(PoseInFrame(timestamp=stamp, frame_id=WORLD, pose=Pose(
            position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))),
            log_time=int(t_ns))

    def harvester(self, t_ns: int, xyz: NDArray[np.float64], q: NDArray[np.float64]) -> None:
        """The machine's pose (its base point, world coordinates; ``q`` w, x, y, z) as the
        transform ``world`` -> ``harvester``."""
        from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Vector3

        x, y, z = (float(v) for v in np.asarray(xyz) - self.offset)
        self.tf.log(FrameTransforms(transforms=[FrameTransform(
            timestamp=_stamp(t_ns), parent_frame_id=WORLD, child_frame_id=HARVESTER,
            translation=Vector3(x=x, y=y, z=z),
            rotation=Quaternion(w=float(q[0]), x=float(q[1]), y=float(q[2]),
                                z=float(q[3])))]), log_time=int(t_ns))

    def track(self, t_ns: int, xyz: NDArray[np.float64]) -> None:
        """The sensor's track (n, 3), as one line a little above the sensor's path."""
        from foxglove.messages import (
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            SceneEntity,
            SceneUpdate,
        )

        pts = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
               for p in np.asarray(xyz, np.float64) - self.offset]
        line = LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=3.0,
                             scale_invariant=True, points=pts, color=_hex("#E69F00"))
        self.track_ch.log(SceneUpdate(entities=[SceneEntity(
            timestamp=_stamp(t_ns), frame_id=WORLD, id="track", lines=[line])]),
            log_time=int(t_ns))

    def stems(self, t_ns: int, rows: Iterable[dict[str, Any]], sic: bool) -> None:
        """Stems as cylinders (rows as :func:`~tcf_hil.results.export.stem_outcomes` gives
        them: ``x``, ``y``, ``z``, ``dbh_m``, ``height_m``, ``outcome``, ``id``), coloured by
        outcome; the whole set replaces the channel's previous one."""
        from foxglove.messages import (
            Color,
            CylinderPrimitive,
            Pose,
            Quaternion,
            SceneEntity,
            SceneEntityDeletion,
            SceneEntityDeletionType,
            SceneUpdate,
            Vector3,
        )

        cyl = []
        for r in rows:
            c = stem_cylinder(r, self.offset, sic)
            if c is None:
                continue
            (x, y, z), (d, h), (cr, cg, cb, ca) = c
            cyl.append(CylinderPrimitive(
                pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(w=1.0)),
                size=Vector3(x=d, y=d, z=h), bottom_scale=1.0, top_scale=1.0,
                color=Color(r=cr, g=cg, b=cb, a=ca)))
        name = "sic" if sic else "truth"
        stamp = _stamp(t_ns)
        ch = self.sic_ch if sic else self.truth_ch
        ch.log(SceneUpdate(
            deletions=[SceneEntityDeletion(timestamp=stamp,
                                           type=SceneEntityDeletionType.All)],
            entities=[SceneEntity(timestamp=stamp, frame_id=WORLD, id=name, cylinders=cyl)]),
            log_time=int(t_ns))

    def score(self, t_ns: int, row: dict[str, Any]) -> None:
        """A publication's score (:data:`SCORE_SCHEMA`; what is not known, null)."""
        out: dict[str, Any] = {}
        for k in SCORE_SCHEMA["properties"]:
            v = row.get(k)
            out[k] = float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None
        self.score_ch.log(out, log_time=int(t_ns))


def stem_cylinder(r: dict[str, Any], offset: NDArray[np.float64], sic: bool
                  ) -> tuple[tuple[float, float, float], tuple[float, float],
                             tuple[float, float, float, float]] | None:
    """A stem row's cylinder: its centre (world less ``offset``), diameter and height (the
    DBH and the tree's height; 0.2 m and 2 m (a SIC's stem) or 10 m (a tree) where a row
    has none) and its outcome's colour; None for a row without a finite position."""
    try:
        x, y, z = (float(r[k]) - offset[i] for i, k in enumerate("xyz"))
    except (KeyError, TypeError, ValueError):
        return None
    if not all(math.isfinite(v) for v in (x, y, z)):
        return None
    d = _finite(r.get("dbh_m"), 0.2)
    h = _finite(r.get("height_m"), 2.0 if sic else 10.0)
    return (x, y, z + h / 2), (d, h), outcome_rgba(r.get("outcome"), 0.9 if sic else 0.6)


def _finite(v: Any, default: float) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return default
    return f if math.isfinite(f) and f > 0 else default


def _grey(intensity: NDArray[np.integer]) -> NDArray[np.uint8]:
    g = np.clip(60 + np.sqrt(intensity.astype(np.float64)) * 0.75, 0, 255).astype(np.uint8)
    return np.repeat(g[:, None], 3, axis=1)


# ------------------------------------------------------------------------- MCAP export
@dataclass(frozen=True)
class McapResult:
    path: Path
    layout: Path
    frames: int
    points: int
    publications: int
    labelled: bool


def write_mcap(run_dir: str | Path, out: str | Path, *, every: int = 1,
               progress: Callable[[int, int], None] | None = None) -> McapResult:
    """The run in ``run_dir`` as an MCAP file of the scene's channels (see the module), each
    message at the time it had in the run: the frames at their last column's time, the
    SIC's publications at their arrival (where the run's index recorded it; older runs: the
    run's start plus the arrival's offset), the track and the ground truth at the first
    frame. ``every``: every N-th frame. Written to a temporary name and renamed; the
    package's Foxglove layout beside it (``<name>.layout.json``)."""
    import foxglove

    from tcf_hil.results.export import (
        kilometre_offset,
        run_cloud,
        run_truth,
        sensor_poses,
        stem_outcomes,
        track_xy,
    )

    run = RunDir(run_dir).require(RunDir.LIDAR, RunDir.METADATA, RunDir.POSES,
                                  missing="not a run directory with its lidar recorded")
    has_truth = (run / RunDir.GROUND_TRUTH).exists() or (run / RunDir.INVENTORY).exists()
    facts = None
    truth: list[dict[str, Any]] = []
    if has_truth:  # the truth, its final outcomes and the track read once
        gt_doc, _path = run_truth(run.path)
        track = track_xy(run.path)
        truth, _sic = stem_outcomes(run.path, gt_doc, track)
        facts = (gt_doc, track)
    pubs = publications(run)
    man = run.manifest()
    poses = sensor_poses(run.path, step=max(1, _columns(run) // 4))
    info, frames = run_cloud(run.path, every=every, progress=progress)  # (opens files: last)
    off = kilometre_offset(info.first_position)
    ctx = foxglove.Context()
    n_frames = n_points = 0
    try:
        with atomic_path(Path(out)) as tmp:
            writer = foxglove.open_mcap(tmp, context=ctx, allow_overwrite=True)
            try:
                scene = SceneChannels(ctx, off)
                # the publications and the machine's poses, in time order, between the frames
                events = heapq.merge(((t, 0, (n, row)) for t, n, row in pubs),
                                     ((t, 1, (xyz, q)) for t, xyz, q in
                                      _on_capture(harvester_poses(run), man)),
                                     key=lambda e: (e[0], e[1]))
                ev = next(events, None)
                first = True
                for pts in frames:
                    t = frame_time(pts, info.gps_adjusted)
                    if first:  # the scene's fixtures, at its first message
                        t_first = min(t, ev[0]) if ev is not None else t
                        scene.track(t_first,
                                    poses[:, 1:4] if len(poses) else np.zeros((0, 3)))
                        if has_truth:
                            scene.stems(t_first, truth, sic=False)
                        first = False
                    while ev is not None and ev[0] <= t:
                        _log_event(scene, run, ev, facts)
                        ev = next(events, None)
                    if len(poses):
                        scene.sensor(t, pose_at(poses, t, info.gps_adjusted))
                    scene.cloud(t, pts, info.labelled)
                    n_frames += 1
                    n_points += len(pts)
                while ev is not None:
                    _log_event(scene, run, ev, facts)
                    ev = next(events, None)
            finally:
                writer.close()
    finally:
        frames.close()  # type: ignore[attr-defined]
    layout = Path(out).with_suffix(".layout.json")
    write_bytes_atomic(layout, layout_bytes())
    return McapResult(Path(out), layout, n_frames, n_points, len(pubs), info.labelled)


def frame_time(pts: NDArray[np.void], gps_adjusted: bool) -> int:
    """A frame's last return's time, Unix ns (where the run's clock is known; else its
    simulation time)."""
    from tcf_hil.results.export import GPS_MINUS_UNIX_S

    g = float(pts["gps_time"].max())
    if gps_adjusted:
        return round((g + 1e9 + GPS_MINUS_UNIX_S) * 1e6) * 1000
    return round(g * 1e6) * 1000


def pose_at(poses: NDArray[np.float64], t_unix: int, gps_adjusted: bool
             ) -> NDArray[np.float64]:
    """The first sampled sensor pose at or after ``t_unix`` (the last there is after it; the
    poses' own time is the run's simulation time, ``poses[:, 8]`` their Unix time where the
    clock is known)."""
    col = 8 if gps_adjusted and poses.shape[1] > 8 else 0
    i = int(np.clip(np.searchsorted(poses[:, col], t_unix), 0, len(poses) - 1))
    return poses[i, 1:8]


def publications(run: RunDir, wall: bool = False) -> list[tuple[int, int, dict[str, Any]]]:
    """(Unix ns, n, index row) of every valid publication with its timeline score, on the
    capture's clock (``--speed`` stretches it as it stretches the frames' time stamps) or,
    ``wall``, at the wall-clock time it arrived."""
    index = run / "sic" / "index.ndjson"
    if not index.exists():
        return []
    import json

    man = run.manifest()
    start = _iso_ns(man.get("started"))
    score = read_json(run / RunDir.SCORE) if (run / RunDir.SCORE).exists() else {}
    by_n = {int(r["n"]): r for r in score.get("timeline", []) if "n" in r}
    out = []
    for i, line in enumerate(index.read_text(encoding="utf-8", errors="replace").splitlines()):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            n = int(row["n"])
            if not row.get("valid"):
                continue
            t = row.get("unix_ns")
            t = start + round(float(row.get("arrival_s", 0.0)) * 1e9) if t is None else int(t)
        except (ValueError, KeyError, TypeError) as err:
            raise InputError(str(index), f"line {i + 1}", f"not an index row ({err})") from err
        out.append((_on_capture_clock(int(t), man, wall), n, {**row, **by_n.get(n, {})}))
    out.sort(key=lambda e: e[0])
    return out


def _on_capture(poses: Iterator[tuple[int, Any, Any]], man: dict[str, Any]
                ) -> Iterator[tuple[int, Any, Any]]:
    """The machine's poses (on the wall clock, as the CAN log keeps them) on the capture's."""
    for t, xyz, q in poses:
        yield _on_capture_clock(t, man, False), xyz, q


def _on_capture_clock(t: int, man: dict[str, Any], wall: bool) -> int:
    """A publication's wall-clock arrival on the time line of the run's frames: the capture's
    Unix time (Unix time at t0 plus simulation time, as the exports give a frame's), or with
    ``wall`` the wall clock of the recorded run; a replay's publications arrive on its own
    wall clock, mapped back through where its first event went out (``replay_clock``)."""
    clock = man.get("clock") or {}
    try:
        t0, unix0 = int(clock.get("sim_t0_ns", 0)), int(clock.get("unix_ns_at_sim_t0", 0))
        speed = float(clock.get("speed", 1.0)) or 1.0
        rc = man.get("replay_clock")
        if rc:  # the replay's wall clock -> the recording's time -> the capture's Unix time
            rec = int(rc["recording_ns"]) + round((t - int(rc["unix_ns"])) *
                                                  float(rc.get("speed", 1.0)))
            sim_unix = unix0 + (rec - t0)
        elif speed != 1.0:  # the capture's clock runs at the run's --speed
            sim_unix = unix0 + round((t - unix0) * speed)
        else:
            return t
    except (KeyError, TypeError, ValueError):
        return t
    return unix0 + round((sim_unix - unix0) / speed) if wall else sim_unix


def _iso_ns(text: Any) -> int:
    from datetime import datetime

    try:
        return round(datetime.fromisoformat(str(text)).timestamp() * 1e9)
    except ValueError:
        return 0


def harvester_poses(run: RunDir) -> Iterator[tuple[int, NDArray[np.float64],
                                                   NDArray[np.float64]]]:
    """(wall-clock Unix ns, base point (3,) in world coordinates, quaternion w, x, y, z) of
    every pose the machine's node sent (``can.log``, its TPDOs decoded by the pose profile,
    relative to the datum the manifest names; the compass heading turned to REP-103's yaw:
    x east, counter-clockwise). None without a CAN log or a node in the manifest."""
    import can

    from protocols.harvester import PoseAssembler
    from tcf_hil._rotations import quaternions, rotation_ypr

    path = run / "can.log"
    man = run.manifest()
    node = man.get("can_node") or {}
    if not path.exists() or "node_id" not in node:
        return
    datum = np.asarray(node.get("datum_mm", [0, 0, 0]), np.float64) / 1000.0
    asm = PoseAssembler(int(node["node_id"]))
    with can.LogReader(str(path)) as reader:
        for m in reader:
            if m.is_error_frame:
                continue
            pose = asm.feed(m.arbitration_id, bytes(m.data))
            if pose is None:
                continue
            rot = rotation_ypr(np.array([math.radians(90.0 - pose.heading_deg)]),
                               np.array([math.radians(pose.pitch_deg)]),
                               np.array([math.radians(pose.roll_deg)]))
            yield (round(m.timestamp * 1e9),
                   np.array([pose.x_m, pose.y_m, pose.z_m]) + datum, quaternions(rot)[0])


def _columns(run: RunDir) -> int:
    """A frame's columns (from ``metadata.json``; 1024 where it cannot say)."""
    from protocols.ouster import MetadataError, SensorMetadata

    try:
        return SensorMetadata.loads((run / RunDir.METADATA).read_text(encoding="utf-8")).columns
    except (OSError, MetadataError):
        return 1024


def _log_event(scene: SceneChannels, run: RunDir, ev: tuple[int, int, Any],
               facts: tuple[dict[str, Any], NDArray[np.float64]] | None) -> None:
    """A publication's stems and its score (kind 0), or the machine's pose (kind 1)."""
    t, kind, what = ev
    if kind == 1:
        scene.harvester(t, *what)
        return
    n, row = what
    scene.stems(t, publication_rows(run, n, row, facts), sic=True)
    scene.score(t, row)


def publication_rows(run: RunDir, n: int, row: dict[str, Any],
                     facts: tuple[dict[str, Any], NDArray[np.float64]] | None = None
                     ) -> list[dict[str, Any]]:
    """Publication ``n``'s stems, each with its outcome as the run's scoring matches it
    against the truth (``facts``: the truth document and the track, read once by the
    caller; None: no truth, all ``matched``)."""
    path = run / "sic" / str(row.get("file", f"{n:04d}.json"))
    rows = _scored_rows(run, path, facts) if facts is not None else None
    return rows if rows is not None else [dict(r, outcome="matched") for r in _stem_rows(path)]


def _stem_rows(path: Path) -> list[dict[str, Any]]:
    from tcf_hil.recording.stems_json import stem_table

    try:
        obs = stem_table(read_json(path), str(path), "observed")
    except InputError:
        return []
    return [{"id": obs.ids[j], "x": obs.xyz[j, 0], "y": obs.xyz[j, 1], "z": obs.xyz[j, 2],
             "dbh_m": obs.dbh[j], "height_m": obs.h[j]} for j in range(len(obs.ids))]


def _scored_rows(run: RunDir, path: Path, facts: tuple[dict[str, Any], NDArray[np.float64]]
                 ) -> list[dict[str, Any]] | None:
    """A publication's stems with ``matched``/``false_positive`` as the run's scoring
    matches them (its configuration from ``score.json``)."""
    from tcf_hil.results.export import publication_outcomes

    try:
        return publication_outcomes(run.path, path, facts[0], facts[1])
    except InputError:
        return None



# --------------------------------------------------------------------------- live view
class _TrackPoses:
    """The sensor's pose at column times from the run's track (world coordinates): what
    ``sensor_poses.csv`` will hold at the end, for a view while the run is under way. Times
    outside the track take its end poses (the machine standing)."""

    first_t = None  # (standing frames are shown too)

    def __init__(self, track: Any, origin: NDArray[np.float64]) -> None:
        self.track, self.origin = track, np.asarray(origin, np.float64)

    def at(self, ts: NDArray[np.integer]) -> NDArray[np.float64]:
        from tcf_hil._rotations import quaternions

        t = np.clip(np.asarray(ts, np.int64), self.track.t0_ns, self.track.end_ns)
        pos, rot = self.track.sensor_pose(t)
        return np.hstack([pos + self.origin, quaternions(rot)])

    def machine(self, t_ns: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The machine's base point (world) and its rotation (w, x, y, z) at ``t_ns``."""
        from tcf_hil._rotations import quaternions

        t = np.clip(np.array([t_ns], np.int64), self.track.t0_ns, self.track.end_ns)
        st = self.track.vehicle_state(t)
        return st.position[0] + self.origin, quaternions(st.rotation)[0]

    def skip_to(self, _t: int) -> None:
        pass


class LiveView:
    """A run in Foxglove while it runs: a WebSocket server (Foxglove's protocol, foxglove-sdk)
    on ``host:port`` (0: a free port; :attr:`port` says which) carrying the scene's channels
    (see the module). :meth:`watch` hands it the run's live figures; a thread of its own,
    twice a second, follows the run directory as the run writes it (the last whole frame of
    ``lidar.pcap`` with its labels, the SIC's publications), takes the track and the truth
    from the run's world, and matches each new publication against the truth for its
    colours and its score. A view never stops a run: its errors are counted
    (:attr:`errors`, the first in :attr:`first_error`), not raised."""

    PERIOD_S = 0.5

    def __init__(self, port: int = 8765, host: str = "127.0.0.1") -> None:
        import foxglove

        self.ctx = foxglove.Context()
        self.server = foxglove.start_server(name="tcf-hil", host=host, port=port,
                                            context=self.ctx)
        self.port: int = self.server.port
        self.scene: SceneChannels | None = None
        self.errors = 0
        self.first_error = ""
        self.frames = 0
        self._fig: Any = None
        self._last_frame_id: int | None = None
        self._last_pub: int | None = None
        self._size = -1
        self._static_at = 0.0
        self._end = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove view", daemon=True)
        self._thread.start()

    def watch(self, fig: Any) -> None:
        """Take the run's :class:`~tcf_hil.run.LiveFigures` (with ``world`` and ``run_dir``);
        the view's thread publishes what is new."""
        self._fig = fig

    def _run(self) -> None:
        while not self._end.wait(self.PERIOD_S):
            self.update()

    def update(self) -> None:
        """Publish what is new since the last update (the view's thread calls it)."""
        fig = self._fig
        if fig is None:
            return
        try:
            if self.scene is None:
                if getattr(fig, "world", None) is None or getattr(fig, "run_dir", None) is None:
                    return
                self._bind(fig.world, Path(fig.run_dir))
                if self.scene is None:
                    return
            self._frame()
            self._publication(fig)
            if time.monotonic() - self._static_at > 2.0:  # (no latching: a client that
                self._static()                            # joins later gets them too)
        except Exception as err:  # a view never stops a run
            self.errors += 1
            self.first_error = self.first_error or f"{type(err).__name__}: {err}"

    def _bind(self, world: Any, run: Path) -> None:
        from protocols.ouster import SensorMetadata
        from tcf_hil.results.export import FrameDecoder, kilometre_offset
        from tcf_hil.world.forest import ground_truth

        meta_path = run / RunDir.METADATA
        if not meta_path.exists():
            return
        self.run, self.world = run, world
        self.meta = SensorMetadata.loads(meta_path.read_text(encoding="utf-8"))
        origin = np.asarray(world.forest.origin, np.float64)
        self.poses = _TrackPoses(world.track, origin)
        tr = world.track
        t = np.linspace(tr.t0_ns, tr.end_ns, 400).astype(np.int64)
        track = self.poses.at(t)[:, :3]
        self.track_xy = track[:, :2].copy()
        off = kilometre_offset(track[0])

        self.decoder = FrameDecoder(self.meta)
        self.gt = ground_truth(world.forest)
        self.truth_rows = [{"id": o["id"], "x": o["cp"][0], "y": o["cp"][1], "z": o["cp"][2],
                            "dbh_m": o.get("dbh"), "height_m": o.get("h"),
                            "outcome": "missed_unseen"} for o in self.gt["objects"]]
        self.track = track
        self.scene = SceneChannels(self.ctx, off)
        self._static()

    def _static(self) -> None:
        """The track and the truth (with its outcomes so far), again."""
        assert self.scene is not None
        now = time.time_ns()
        self.scene.track(now, self.track)
        self.scene.stems(now, self.truth_rows, sic=False)
        self._static_at = time.monotonic()

    def _frame(self) -> None:
        from tcf_hil.results.export import LabelsReader, last_frame

        assert self.scene is not None
        pcap = self.run / RunDir.LIDAR
        try:
            size = pcap.stat().st_size
        except OSError:
            return
        if size == self._size:
            return
        self._size = size
        fr = last_frame(pcap, self.meta)
        if fr is None or fr.frame_id == self._last_frame_id:
            return
        self._last_frame_id = fr.frame_id
        labels = None
        lpath = self.run / RunDir.LABELS
        if lpath.exists():
            with contextlib.suppress(InputError):
                labels = LabelsReader(lpath, self.meta)
        try:
            pts = self.decoder.points(fr, self.poses, labels, pcap, skip=True)
            rec_known = labels is not None and labels.missing == 0
        finally:
            if labels is not None:
                labels.close()
        if not len(pts):
            return
        now = time.time_ns()
        t_mid = int(np.median(pts["gps_time"]) * 1e9)  # simulation ns (no clock given)
        self.scene.sensor(now, self.poses.at(np.array([t_mid]))[0])
        xyz, q = self.poses.machine(t_mid)
        self.scene.harvester(now, xyz, q)
        self.scene.cloud(now, pts, labelled=rec_known)
        self.frames += 1

    def _publication(self, fig: Any) -> None:
        assert self.scene is not None
        pub = getattr(fig, "latest_publication", None)
        if pub is None or pub == self._last_pub:
            return
        self._last_pub = pub
        path = self.run / "sic" / f"{int(pub):04d}.json"
        from tcf_hil.results.export import live_outcomes

        self.truth_rows, sic, score = live_outcomes(self.gt, path, self.track_xy)
        now = time.time_ns()
        self.scene.stems(now, self.truth_rows, sic=False)
        self.scene.stems(now, sic, sic=True)
        self.scene.score(now, {"n": pub, "objects": len(sic), **score})

    def close(self) -> None:
        self._end.set()
        self._thread.join(10.0)
        with contextlib.suppress(Exception):
            self.server.stop()
