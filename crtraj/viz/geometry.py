"""Pose geometry of the view: quaternions, 4x4 transforms and the poses of the drawn robot parts.

crtraj works in mm; meshcat (three.js) in metres, so lengths are scaled by `M_PER_MM` on the way out. Quaternions
are (w, x, y, z); three.js cylinders lie along their y axis.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

M_PER_MM = 1e-3
# Rotation about x by +90 deg, (w, x, y, z): takes a three.js cylinder's y axis onto z.
Q_Y_TO_Z = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (..., 4) in (w, x, y, z) order."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def cylinder_quat(v: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) that turn a three.js cylinder (axis y) onto unit vectors v (..., 3).

    First y -> z, then the shortest arc z -> v. That arc is undefined only for
    v = -z (a chord pointing straight down), where a half turn about x is used.
    """
    q = np.stack([1.0 + v[..., 2], -v[..., 1], v[..., 0], np.zeros(v.shape[:-1])], axis=-1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    down = norm[..., 0] < 1e-9
    q = np.where(down[..., None], np.array([0.0, 1.0, 0.0, 0.0]), q / np.where(down[..., None], 1.0, norm))
    return quat_mul(q, Q_Y_TO_Z)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) in (w, x, y, z) order."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def transforms(pos_m: np.ndarray, quat: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """4x4 matrices (..., 4, 4): translate(pos) @ rotate(quat) @ diag(scale), as three.js composes them."""
    T = np.zeros((*pos_m.shape[:-1], 4, 4))
    T[..., :3, :3] = quat_to_matrix(quat) * scale[..., None, :]
    T[..., :3, 3] = pos_m
    T[..., 3, 3] = 1.0
    return T


def unit(v: np.ndarray) -> np.ndarray:
    """v (..., 3) scaled to unit length (a zero vector stays zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


@dataclasses.dataclass(frozen=True)
class RobotPoses:
    """Poses of every drawn robot part for N configurations (metres, quaternions w-x-y-z)."""

    joints: np.ndarray  # (N, J, 3) disc centres
    disc_quat: np.ndarray  # (N, J, 4)
    chord_mid: np.ndarray  # (N, C, 3)
    chord_quat: np.ndarray  # (N, C, 4)
    chord_len: np.ndarray  # (N, C)


def f32(a: Any) -> np.ndarray:
    """meshcat refuses int64 and sends float64 as float32 anyway: be explicit."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


def translation(p_m: np.ndarray) -> np.ndarray:
    """4x4 matrix of a translation by p_m (3,) metres."""
    T = np.eye(4)
    T[:3, 3] = p_m
    return T


def fit_view(P: np.ndarray, view: np.ndarray, fov_deg: float, aspect: float) -> tuple[np.ndarray, float]:
    """Aim point (3,) and camera distance of a perspective camera looking along -view (unit) that shows every
    point of P (K, 3) with a little margin, centred in a window of width/height `aspect` (vertical field of
    view fov_deg). Units of P."""
    right = unit(np.cross([0.0, 0.0, 1.0], view))
    if not np.any(right):
        right = np.array([1.0, 0.0, 0.0])
    up = np.cross(view, right)
    tan_v = math.tan(math.radians(fov_deg / 2))
    lo, hi = P.min(axis=0), P.max(axis=0)
    center = 0.5 * (lo + hi)
    floor = float(np.linalg.norm(np.maximum(0.5 * (hi - lo), 25.0)))  # never inside a small scene
    dist = floor
    for _ in range(4):  # perspective: re-aim at the middle of what the camera sees, then fit again
        rel = P - center
        need = rel @ view + np.maximum(np.abs(rel @ up) / tan_v, np.abs(rel @ right) / (tan_v * aspect))
        dist = max(1.06 * float(need.max()), floor)
        depth = dist - rel @ view
        for axis in (up, right):
            a = (rel @ axis) / depth  # tangent of each point's angle off the axis of view
            center = center + axis * 0.5 * (a.max() + a.min()) * dist
    rel = P - center
    need = rel @ view + np.maximum(np.abs(rel @ up) / tan_v, np.abs(rel @ right) / (tan_v * aspect))
    return center, max(1.06 * float(need.max()), floor)
