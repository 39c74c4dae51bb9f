"""Sensor trajectories. Here: the paper's straight pass at constant speed, the sensor a fixed
height above the terrain, level, facing along the track (the harvester issue brings strip
roads, turns and terrain-following attitude)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tcf_hil.forest import Terrain
from tcf_hil.scenario import TrackConfig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class StraightTrack:
    """Constant-velocity pass from ``start`` to ``end`` (local x, y), sensor ``height_m``
    above the terrain. Before ``t0_ns`` it waits at the start, after the end at the end."""

    start: tuple[float, float]
    end: tuple[float, float]
    height_m: float
    speed_m_s: float
    terrain: Terrain
    t0_ns: int = 1_000_000_000

    @classmethod
    def from_config(cls, track: TrackConfig, terrain: Terrain,
                    t0_ns: int = 1_000_000_000) -> StraightTrack:
        return cls((track.start_m[0], track.start_m[1]), (track.end_m[0], track.end_m[1]),
                   track.start_m[2], track.speed_m_s, terrain, t0_ns)

    @property
    def length_m(self) -> float:
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])

    @property
    def duration_ns(self) -> int:
        return round(self.length_m / self.speed_m_s * 1e9)

    @property
    def heading_rad(self) -> float:
        return math.atan2(self.end[1] - self.start[1], self.end[0] - self.start[0])

    def sensor_pose(self, t_ns: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Positions (n, 3) and rotations (n, 3, 3): sensor x forward, z up."""
        t = (np.asarray(t_ns, dtype=np.int64) - self.t0_ns).astype(np.float64) / 1e9
        L = self.length_m
        s = np.clip(t * self.speed_m_s, 0.0, L)
        u = (np.array(self.end) - np.array(self.start)) / L if L > 0 else np.zeros(2)
        xy = np.asarray(self.start)[None, :] + s[:, None] * u[None, :]
        z = self.terrain.height(xy[:, 0], xy[:, 1]) + self.height_m
        pos = np.column_stack([xy, z])
        c, si = math.cos(self.heading_rad), math.sin(self.heading_rad)
        rot = np.broadcast_to(np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]]),
                              (len(s), 3, 3)).copy()
        return pos, rot


def quaternions(rot: FloatArray) -> FloatArray:
    """(n, 4) unit quaternions (w, x, y, z), w >= 0, from rotation matrices (n, 3, 3)."""
    r = np.asarray(rot, dtype=np.float64)
    tr = r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]
    q = np.empty((len(r), 4))
    q[:, 0] = np.sqrt(np.maximum(0.0, 1.0 + tr)) / 2.0
    q[:, 1] = np.copysign(np.sqrt(np.maximum(0.0, 1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]))
                          / 2.0, r[:, 2, 1] - r[:, 1, 2])
    q[:, 2] = np.copysign(np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2]))
                          / 2.0, r[:, 0, 2] - r[:, 2, 0])
    q[:, 3] = np.copysign(np.sqrt(np.maximum(0.0, 1.0 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]))
                          / 2.0, r[:, 1, 0] - r[:, 0, 1])
    return q / np.linalg.norm(q, axis=1)[:, None]
