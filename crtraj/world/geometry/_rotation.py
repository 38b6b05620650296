"""Unit quaternions (w, x, y, z; scalar first) as rotations: validation, matrices, slerp, angles.

A rotation is stored as a normalised quaternion tuple. Input must be a unit quaternion within
`QUAT_TOL` (so that a typo such as a missing component is caught, while four decimals typed by hand
pass), and is then normalised exactly.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_vec

# | |q| - 1 | allowed for a rotation given by hand: [0.7071, 0, 0, 0.7071] has |q| - 1 = -1e-5.
QUAT_TOL = 1.0e-3
IDENTITY = (1.0, 0.0, 0.0, 0.0)


def check_unit(v: Any, name: str, n: int) -> tuple[float, ...]:
    """A unit vector of `n` finite numbers (|v| = 1 within `QUAT_TOL`), returned normalised."""
    vals = check_vec(v, name, n)
    norm = math.sqrt(sum(x * x for x in vals))
    if abs(norm - 1.0) > QUAT_TOL:
        what = "a unit quaternion (w, x, y, z)" if n == 4 else "a unit vector"
        raise InputError(f"{name}: must be {what} within {QUAT_TOL:g}, got norm {norm:.6g}; normalise it")
    return tuple(x / norm for x in vals)


def matrix(q: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """The 3x3 rotation matrix of the unit quaternion q = (w, x, y, z)."""
    w, x, y, z = (float(c) for c in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def angle(q0: np.ndarray, q1: np.ndarray) -> float:
    """The rotation angle (rad, 0..pi) of q1 relative to q0 (the shortest way, q and -q alike)."""
    d = min(1.0, abs(float(np.dot(q0, q1))))
    return 2.0 * math.acos(d)


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation from q0 (u = 0) to q1 (u = 1) the short way, at constant angular
    speed angle(q0, q1) per unit of u."""
    d = float(np.dot(q0, q1))
    if d < 0.0:  # q and -q are the same rotation: turn the short way
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    half = math.acos(min(1.0, d))
    s = math.sin(half)
    return (math.sin((1.0 - u) * half) * q0 + math.sin(u * half) * q1) / s
