"""One run of the reference SIC on the wire's bytes, unpaced, in one process.

The emulator makes the same lidar packets as a live run
(:class:`tcf_hil.devices.lidar.LidarRun`) and
the harvester model the same TPDO frames as its CANopen node (``encode_pose``); the reference
SIC decodes them exactly as it does from UDP and CAN: packets through
:func:`protocols.ouster.decode_lidar_packets` with the CRC check, TPDOs through canopen and the
EDS (frames handed to the network's ``notify``). Nothing is paced and nothing can be lost, so a
cell is deterministic: the same scenario, mode and seed give the same stems.

The datum and the lidar mount, which a live SIC reads by SDO, come from the node's object
dictionary values (the same quantised integers its SDO server answers).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocols.harvester import encode_pose
from tcf_hil._crc import fast_crc_rows
from tcf_hil._rotations import rotation_ypr
from tcf_hil.devices.harvester import HarvesterModel
from tcf_hil.devices.lidar import LidarRun
from tcf_hil.evaluation import EvalConfig
from tcf_hil.evaluation.scoring import Scores, score_forest
from tcf_hil.recording.stems_json import stem_table
from tcf_hil.run import RUN_T0_NS  # as a live run: CAN time never goes negative
from tcf_hil.scenario import Scenario
from tcf_hil.sic import CanPose, LidarStats, OnboardSic, PoseTrack, SicConfig, StemMap
from tcf_hil.world.forest import Forest

LEAD_NS = 1_000_000_000  # poses on the bus before the first column


@dataclass
class OfflineResult:
    scores: Scores
    forest_doc: dict[str, Any]
    ground_truth: dict[str, Any]
    frames: int
    sim_seconds: float
    emulator_s: float  # raycast + packet encode, all frames
    sic_frame_ms: list[float] = field(default_factory=list)  # decode + pose + map, per frame
    stem_s: float = 0.0  # the stem algorithm over the whole map
    poses: int = 0
    packets: int = 0
    stems_seen: int = 0
    from_store: bool = False  # the frames came from the render store (emulator_s: reading)

    def sic_ms(self, q: float) -> float:
        return float(np.percentile(self.sic_frame_ms, q)) if self.sic_frame_ms else 0.0


class OfflineSic:
    """The reference SIC (one preset) fed in process: pose frames through canopen, lidar
    packets through the batch decoder, the map, and at the end the stem algorithm."""

    def __init__(self, preset: str, meta: Any, ncfg: Any, *, voxel_m: float | None = None
                 ) -> None:
        import canopen  # the SIC's own decoder of the TPDOs

        from tcf_hil.sic import use_compiled_fits

        use_compiled_fits()  # nothing is paced here: a cold compile costs no frames
        self.meta = meta
        self.cfg = SicConfig(preset=preset, node_id=ncfg.node_id, voxel_m=voxel_m)
        self.sic = OnboardSic(self.cfg)
        self.sic.meta = meta  # a live SIC reads it at start (the edge returns' geometry)
        self.track = PoseTrack()
        self.net = canopen.Network()
        can = CanPose(self.cfg, self.track, network=self.net)
        can.datum = tuple(v / 1000.0 for v in ncfg.datum_mm)
        can.mount = np.array(ncfg.mount_mm, dtype=np.float64) / 1000.0
        yaw, pitch, roll = np.radians(np.array(ncfg.mount_cdeg, dtype=np.float64) / 100.0)
        can.mount_rot = rotation_ypr(np.array([yaw]), np.array([pitch]), np.array([roll]))[0]
        self.can = can
        self.rays = self.sic.mounted_rays(meta, can.mount, can.mount_rot)
        self.smap = StemMap(self.sic.params, voxel_m=self.sic.voxel_m,
                            max_points=self.cfg.max_points, datum=can.datum)
        self.crc = fast_crc_rows()
        self.stats = LidarStats()
        self.frame_ms: list[float] = []
        self.stem_s = 0.0

    def can_frame(self, cob: int, data: bytes, t_s: float) -> None:
        self.net.notify(cob, bytearray(data), t_s)

    def lidar_frame(self, fid: int, arr: NDArray[np.uint8]) -> None:
        self.stats.packets += len(arr)
        t1 = time.perf_counter()
        self.sic._frame((fid, arr), self.meta.packet_format, self.meta, self.crc, self.track,
                        self.rays, self.smap, self.stats)
        self.frame_ms.append((time.perf_counter() - t1) * 1000.0)

    def finish(self) -> dict[str, Any]:
        """Every tile through the stem algorithm; the final forest as JSON would bring it."""
        t2 = time.perf_counter()
        self.smap.update(math.inf)
        self.stem_s = time.perf_counter() - t2
        doc = self.sic._document(self.smap, self.stats, self.track, final=True)
        self.can.close()
        out: dict[str, Any] = json.loads(json.dumps(doc))
        return out


def drive(run: LidarRun, model: HarvesterModel, sics: list[OfflineSic],
          progress: Callable[[int, int], None] | None = None) -> tuple[int, float]:
    """Feed every frame's packets, and the poses up to one SYNC past its last column (what
    a live SIC holds by then), to each SIC; returns (frames, emulator seconds)."""
    ncfg = model.node_config()
    period_ns = round(1e9 / ncfg.rate_hz)
    next_pose = run.track.t0_ns - LEAD_NS
    lp = run.meta.udp_port_lidar
    frames, emu_s = 0, 0.0
    it = run.rendered()
    while True:
        t0 = time.perf_counter()
        try:
            dgs = next(it).datagrams
        except StopIteration:
            break
        emu_s += time.perf_counter() - t0
        # a lidar packet leaves at its last column's time: the frame's last is the latest
        last = max((d.t_ns for d in dgs if d.port == lp), default=None)
        if last is None:
            last = max((d.t_ns for d in dgs), default=next_pose - period_ns)
        t_end = int(last) + period_ns
        times = []
        while next_pose <= t_end:
            times.append(next_pose)
            next_pose += period_ns
        for t_pose, pose in zip(times, model.bus_poses(times), strict=True):
            for cob, data in encode_pose(pose, ncfg.node_id):
                for s in sics:
                    s.can_frame(cob, data, t_pose / 1e9)
        payload = [d.payload for d in dgs if d.port == lp]
        arr = np.frombuffer(b"".join(payload), dtype=np.uint8).reshape(len(payload), -1)
        for s in sics:
            s.lidar_frame(frames & 0xFFFF, arr)
        frames += 1
        if progress is not None:
            progress(frames, run.frames)
    return frames, emu_s


def run_offline(scn: Scenario, *, mode: str = "1024x10",
                profile: str = "RNG19_RFL8_SIG16_NIR16", seed: int | None = None,
                backend: str = "auto", preset: str = "field", max_frames: int | None = None,
                eval_cfg: EvalConfig | None = None, voxel_m: float | None = None,
                progress: Callable[[int, int], None] | None = None,
                forest: Forest | None = None, t0_ns: int = RUN_T0_NS,
                first_frame_id: int = 0, render: str = "live") -> OfflineResult:
    """Emulate ``scn`` at ``mode``, feed every packet and pose frame to the reference SIC
    (``preset``), score its final forest against all and against seen trees.

    ``forest``: a hand-built forest instead of the one ``scn`` generates; ``t0_ns``: the
    simulation time the track starts at (the CAN pose time is its microseconds modulo 2^32);
    ``first_frame_id``: the sensor's first frame_id. ``render``: where the frames come from
    (:data:`tcf_hil.devices.lidar.RENDER_MODES`; ``fill``: the render store's frames where
    it holds them, else rendered and kept there for the next cell of the same scene)."""
    from tcf_hil.recording.store import RenderStore

    run = LidarRun(scn, mode=mode, profile=profile, seed=seed, backend=backend,
                   max_frames=max_frames, t0_ns=t0_ns, faults=False, forest=forest,
                   first_frame_id=first_frame_id, keep_poses=False,  # no sidecar files here
                   store=RenderStore() if render != "live" else None, render=render)
    model = HarvesterModel.from_scenario(scn, run.forest.terrain, run.forest.seed, t0_ns)
    sic = OfflineSic(preset, run.meta, model.node_config(), voxel_m=voxel_m)
    frames, emu_s = drive(run, model, [sic], progress)
    doc = sic.finish()
    table = stem_table(doc, "<reference SIC>", "observed")
    gt = run.ground_truth()
    scores = score_forest(gt, table, eval_cfg)
    return OfflineResult(scores=scores, forest_doc=doc, ground_truth=gt, frames=frames,
                         sim_seconds=frames * run.emu.period_ns / 1e9, emulator_s=emu_s,
                         sic_frame_ms=sic.frame_ms, stem_s=sic.stem_s,
                         poses=sic.track.received, packets=sic.stats.packets,
                         stems_seen=run.stems_seen(), from_store=run.stored is not None)
