"""The body-motion metric of configuration space, and the timing it implies.

No backbone point moves more than ``B(dx) = sum_k w_k |d u_bar_k| + |dz|``
(mm) when the configuration changes by dx (u_bar: the effective bending
vectors, ``w_k = L_k / 2 + sum_{j>k} L_j``; the proof is bound 2 in
`crtraj.planning.validity._motion`). In ``y = M x`` (blocks ``w_k u_bar_k``, then
z) B is the block-l1 norm of dy, so the planners measure distances in y
(mm). A straight motion lasts ``B(dx) / max_speed`` seconds: no point of the
body moves faster than `max_speed` (mm/s).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.rate_limits import RateLimits


def body_weights(robot: Any) -> np.ndarray:
    """w_k = L_k / 2 + sum_{j>k} L_j (mm/rad): how far a unit bend of segment k moves the body at most."""
    lengths = np.array([s.length for s in robot.segments])
    return lengths / 2.0 + (np.cumsum(lengths[::-1])[::-1] - lengths)


def metric_matrix(robot: Any) -> np.ndarray:
    """M of y = M x (blocks w_k u_bar_k, then z): the body-motion bound is the block-l1 norm of M dx."""
    n = robot.n_segments
    M = np.zeros((robot.nx, robot.nx))
    M[: 2 * n, : 2 * n] = np.repeat(body_weights(robot), 2)[:, None] * robot.coupling_matrix()
    M[-1, -1] = 1.0
    return M


class BodyMetric:
    """Body-motion bound, metric coordinates and full-speed timing of one robot.

    robot: the `Robot`. max_speed: largest speed of any body point (mm/s). rate_limits: the
    usable actuator limits (`RateLimits`); when given, no straight motion is timed faster than
    its actuators' speed limits allow either.
    """

    def __init__(self, robot: Any, max_speed: float, rate_limits: RateLimits | None = None) -> None:
        if not (math.isfinite(max_speed) and max_speed > 0):
            raise InputError(f"max_speed: must be > 0 mm/s, got {max_speed}")
        self.robot = robot
        self.max_speed = float(max_speed)
        self.rate_limits = rate_limits
        self.weights = body_weights(robot)  # w_k (mm/rad)
        self.metric_matrix = metric_matrix(robot)
        self.metric_inverse = np.linalg.inv(self.metric_matrix)
        self._bend = 2 * robot.n_segments  # bending coordinates of y: (u_bar_k x, u_bar_k y) per segment

    def metric(self, x: np.ndarray) -> np.ndarray:
        """y = M x (mm units): the space the planners measure distances in."""
        return np.asarray(x, dtype=float) @ self.metric_matrix.T

    def config_from_metric(self, y: np.ndarray) -> np.ndarray:
        """x from y = M x."""
        return np.asarray(y, dtype=float) @ self.metric_inverse.T

    def motion_bound(self, dx: np.ndarray) -> np.ndarray:
        """Upper bound (mm) on how far any body point moves for a change dx (..., nx)."""
        dy = np.asarray(dx, dtype=float) @ self.metric_matrix.T
        m = self._bend
        # each block's Euclidean length as np.linalg.norm computes it (sqrt of the summed squares), for a
        # fraction of its cost on the control loop's single changes; add.reduce is sum without its wrapper
        sq = dy * dy
        blocks = np.sqrt(sq[..., 0:m:2] + sq[..., 1:m:2])
        return np.add.reduce(blocks, axis=-1) + np.abs(dy[..., -1])

    def duration(self, dx: np.ndarray, bound: np.ndarray | None = None) -> np.ndarray:
        """Shortest duration (s) of straight motions by dx (..., nx) at constant speed: the body-motion
        bound over max_speed, and, with rate limits, max_i |J_i dx| / vmax_i. bound: `motion_bound(dx)` when
        the caller has it (mm)."""
        dx = np.asarray(dx, dtype=float)
        t = (self.motion_bound(dx) if bound is None else bound) / self.max_speed
        if self.rate_limits is not None:
            t = np.maximum(t, np.max(np.abs(dx @ self.rate_limits.jacobian.T) / self.rate_limits.vmax, axis=-1))
        return t

    def durations(self, X: np.ndarray) -> np.ndarray:
        """Duration (s) of each straight motion between consecutive rows of X (K, nx) -> (K-1,)."""
        return self.duration(np.diff(np.asarray(X, dtype=float), axis=0))

    def times(self, X: np.ndarray, t0: float = 0.0) -> np.ndarray:
        """Waypoint times (s) of a path through X starting at t0."""
        return t0 + np.concatenate([[0.0], np.cumsum(self.durations(X))])
