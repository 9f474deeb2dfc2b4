"""Rotations as the engines hold them: quaternions (x, y, z, w) and fixed-axis roll-pitch-yaw."""
from __future__ import annotations

import math

import numpy as np


def rpy_to_quat(rpy) -> np.ndarray:
    """Quaternion (x, y, z, w) of fixed-axis roll, pitch, yaw (rad)."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r / 2), math.sin(r / 2), math.cos(p / 2), math.sin(p / 2), \
        math.cos(y / 2), math.sin(y / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def quat_to_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quat_to_rpy(q) -> np.ndarray:
    """Fixed-axis roll, pitch, yaw (rad) of a quaternion (x, y, z, w): the inverse of rpy_to_quat, pitch in
    [-pi/2, pi/2]."""
    m = quat_to_matrix(np.asarray(q, float) / np.linalg.norm(q))
    return np.array([math.atan2(m[2, 1], m[2, 2]), math.asin(float(np.clip(-m[2, 0], -1.0, 1.0))),
                     math.atan2(m[1, 0], m[0, 0])])
