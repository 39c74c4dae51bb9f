"""Rotations as arrays: about one axis, yaw-pitch-roll, and unit quaternions. A small shared
helper: the track's poses, the lidar's recorded poses and the reference SIC (which may import
rotations, errors and the CRC besides its own package and :mod:`protocols`) use the same."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ["quaternions", "rot_x", "rot_y", "rot_z", "rotation_ypr"]


def rot_z(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1),
                     np.stack([z, z, o], -1)], -2)


def rot_y(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1),
                     np.stack([-s, z, c], -1)], -2)


def rot_x(a: FloatArray) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1),
                     np.stack([z, s, c], -1)], -2)


def rotation_ypr(yaw: FloatArray, pitch: FloatArray, roll: FloatArray) -> FloatArray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), radians, arrays of rotations (n, 3, 3)."""
    result: FloatArray = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    return result


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
