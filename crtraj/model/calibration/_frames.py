"""Rotations and the rigid alignment of the capture frame with the robot frame (rad, mm)."""

from __future__ import annotations

import math

import numpy as np


def rotation_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector w (rad)."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + math.sin(th) / th * W + (1 - math.cos(th)) / th**2 * W @ W


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix R (angle in [0, pi])."""
    c = max(-1.0, min(1.0, (np.trace(R) - 1) / 2))
    th = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return v / 2
    if th > math.pi - 1e-6:  # sin th ~ 0: the axis from the symmetric part
        M = (R + np.eye(3)) / 2
        axis = M[:, int(np.argmax(np.diag(M)))]
        axis = axis / np.linalg.norm(axis)
        return th * axis
    return th / (2 * math.sin(th)) * v


def align(m: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, spread ratio) of the rigid motion best taking points m to p (Kabsch), both (K, 3) mm.

    spread ratio: RMS distance of p from its centroid over that of m (1 when both are in mm).
    """
    cm, cp = m.mean(axis=0), p.mean(axis=0)
    A, B = m - cm, p - cp
    U, _, Vt = np.linalg.svd(A.T @ B)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0)])
    R = Vt.T @ D @ U.T
    sm = float(np.sqrt(np.mean(np.sum(A**2, axis=1))))
    sp = float(np.sqrt(np.mean(np.sum(B**2, axis=1))))
    return R, cp - R @ cm, (sp / sm) if sm > 0 else math.inf
