"""Configurations within the robot's limits: uniform sampling, projection, the limit test.

All limits in crtraj are convex in x (discs in the effective bending vectors
u_bar, cable strokes, z stroke), so a straight motion between two
configurations within limits stays within limits.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# Limits may be violated by solver round-off; above this a configuration is out of limits.
LIMIT_TOL = 1e-7


class ConfigSampler:
    """Samples and projections within the limits of `robot` (units rad, mm)."""

    def __init__(self, robot: Any) -> None:
        self.robot = robot
        # what every call needs and a robot never changes: computed once (the same numbers each call)
        self._coupling = robot.coupling_matrix()
        self._coupling_inv = np.linalg.inv(self._coupling)
        self._tmax = np.array([s.theta_max for s in robot.segments])
        self._cables = robot.cable_matrix()[0]
        self._strokes = np.repeat([robot.cable_stroke(k) for k in range(robot.n_segments)], 3)

    def within_limits(self, X: np.ndarray) -> np.ndarray:
        """True per configuration when it respects every limit (bool (N,)): `Robot.limit_violation`'s
        arithmetic, operation for operation, on matrices kept from construction (it rebuilds them per call)."""
        x = np.atleast_2d(np.asarray(X, dtype=float))
        n = self.robot.n_segments
        sq = x[..., : 2 * n] @ self._coupling.T
        sq *= sq
        # each disc's radius as np.linalg.norm computes it (sqrt of the summed squares), and maximum.reduce for
        # np.max: the same numbers without their wrappers (a query tests limits many times, often of one x)
        v_theta = np.maximum.reduce(np.sqrt(sq[:, 0 : 2 * n : 2] + sq[:, 1 : 2 * n : 2]) - self._tmax, axis=-1)
        v_cable = np.maximum.reduce(np.abs((x @ self._cables.T)[:, : 3 * n]) - self._strokes, axis=-1)
        lo, hi = self.robot.z_range
        z = x[:, -1]
        v_z = np.maximum(lo - z, z - hi)
        return np.maximum(np.maximum(v_theta, v_cable), v_z) <= LIMIT_TOL

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n configurations drawn uniformly within the limits (n, nx).

        Each effective bending vector is uniform in its disc |u_bar_k| <=
        theta_max_k and z uniform in its stroke; draws that break a cable
        stroke are redrawn (none do for the default robot).
        """
        robot = self.robot
        k = robot.n_segments
        tmax, C_inv = self._tmax, self._coupling_inv
        out = np.empty((0, robot.nx))
        while len(out) < n:
            m = max(n - len(out), 8)
            rad = tmax * np.sqrt(rng.random((m, k)))
            ang = 2.0 * np.pi * rng.random((m, k))
            ub = np.empty((m, k, 2))
            ub[..., 0] = rad * np.cos(ang)
            ub[..., 1] = rad * np.sin(ang)
            z = rng.uniform(robot.z_range[0], robot.z_range[1], size=(m, 1))
            X = np.empty((m, robot.nx))
            X[:, : 2 * k] = ub.reshape(m, 2 * k) @ C_inv.T
            X[:, 2 * k :] = z
            ok = self.within_limits(X)
            if not len(out) and ok.all():  # the usual case: one draw, all within limits
                return X[:n]
            out = np.concatenate([out, X[ok]])
        return out[:n]

    def project_limits(self, X: np.ndarray) -> np.ndarray:
        """Configurations (N, nx) moved into the bending discs |u_bar_k| <= theta_max_k and the z stroke.

        Radial scaling of each effective bending vector and clipping of z:
        the nearest such point in those coordinates; solver round-off
        (~1e-8 outside a limit) becomes exactly inside. Cable strokes are
        not projected; with the default strokes (2 r theta_max) the discs imply them.
        """
        X = np.atleast_2d(np.asarray(X, dtype=float))
        robot = self.robot
        n = robot.n_segments
        C, tmax = self._coupling, self._tmax
        ub = (X[:, : 2 * n] @ C.T).reshape(-1, n, 2)
        # each disc's radius as np.linalg.norm computes it (sqrt of the summed squares), at a fraction of its cost
        norm = np.sqrt(ub[..., 0] * ub[..., 0] + ub[..., 1] * ub[..., 1])
        ub = ub * np.minimum(1.0, tmax / np.maximum(norm, 1e-300))[..., None]
        out = X.copy()
        out[:, : 2 * n] = ub.reshape(-1, 2 * n) @ self._coupling_inv.T
        out[:, -1] = np.clip(X[:, -1], robot.z_range[0], robot.z_range[1])
        return out
