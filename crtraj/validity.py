"""Conservative, vectorised collision checks of whole-body motions in configuration space.

`MotionValidator` answers the planners' two questions (OMPL's state validity
and motion validity): is configuration x safe over a time window, and is the
straight motion from x_a to x_b (linear in x) safe over the time it takes?
"Safe" means the *continuous* body keeps the scene's safety distance D_sf
plus the disc radius from every obstacle, not only a few sampled points.
Three bounds make discrete checks imply that:

1. Backbone between check points. The n check points split the backbone
   into chords of arc length h = L / (n - 1). A curve of curvature at most
   kappa (= max theta_max / L_k over segments, the limit every valid
   configuration obeys) stays within the sagitta ``(1 - cos(kappa h / 2)) /
   kappa`` of its chord, so the distance from an obstacle centre to the
   chord *segment*, minus that sagitta, bounds the distance to the arc.

2. Body between configuration samples. No backbone point moves more than
   ``B(dx) = sum_k w_k |d u_bar_k| + |dz|`` (mm) when the configuration
   changes by dx (u_bar: the effective bending vectors), with
   ``w_k = L_k / 2 + sum_{j>k} L_j``: within its own segment a point at arc
   s turns its tangent by at most (s / L_k) |du| (the SO(3) exponential is
   1-Lipschitz), which integrates to ``L_k / 2 |du|``, and the rest of the
   robot turns rigidly by at most |du|. An edge is therefore sampled so
   that consecutive samples are at most `resolution` (mm) of body motion
   apart, and each sample must keep half that spacing as extra margin.

3. Obstacles between times. Each sample stands for the configurations of its
   half-intervals, which the robot occupies during a time window; the
   obstacle is replaced by one sphere that encloses everything it sweeps in
   that window (`Scene.swept`: exact capsule; enclosing sphere: centre in
   the middle, radius max R + half the capsule length).

`B` also times the motion: an edge lasts ``B(dx) / max_speed`` seconds, so no
point of the body moves faster than `max_speed` (mm/s). All limits in
crtraj are convex in x (discs in u_bar, cable strokes, z stroke), so a
straight motion between two configurations within limits stays within limits.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from crtraj.errors import InputError
from crtraj.model import Model

# Limits may be violated by solver round-off; above this a configuration is out of limits.
LIMIT_TOL = 1e-7


class MotionValidator:
    """Safety of configurations and straight motions among a scene's obstacles.

    model: the robot's `Model`. scene: a `crtraj.scene.Scene`. check_points:
    backbone points per configuration (chord bound 1 above). resolution:
    largest body motion between edge samples (mm). max_speed: largest speed
    of any body point (mm/s), which times every motion.
    """

    def __init__(
        self,
        model: Model,
        scene: Any,
        *,
        check_points: int = 21,
        resolution: float = 2.0,
        max_speed: float = 50.0,
    ) -> None:
        if check_points < 2:
            raise InputError(f"check_points: must be >= 2, got {check_points}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise InputError(f"resolution: must be > 0 mm, got {resolution}")
        if not (math.isfinite(max_speed) and max_speed > 0):
            raise InputError(f"max_speed: must be > 0 mm/s, got {max_speed}")
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.check_points = int(check_points)
        self.resolution = float(resolution)
        self.max_speed = float(max_speed)
        robot = self.robot
        n = robot.n_segments
        lengths = np.array([s.length for s in robot.segments])
        self.weights = lengths / 2.0 + (np.cumsum(lengths[::-1])[::-1] - lengths)  # w_k (mm/rad)
        # y = M x: blocks w_k u_bar_k, then z; body motion <= block-l1 norm of dy
        M = np.zeros((robot.nx, robot.nx))
        M[: 2 * n, : 2 * n] = np.repeat(self.weights, 2)[:, None] * robot.coupling_matrix()
        M[-1, -1] = 1.0
        self.metric_matrix = M
        self.metric_inverse = np.linalg.inv(M)
        h = robot.total_length / (self.check_points - 1)
        kappa = max(s.theta_max / s.length for s in robot.segments)
        half = min(kappa * h / 2.0, math.pi / 2.0)
        self.sagitta = float((1.0 - math.cos(half)) / kappa)
        self.inflate = float(robot.body_radius + scene.safety_distance + self.sagitta)
        speeds, rates = scene.speed_bounds()
        self.static = bool(np.all(speeds == 0.0) and np.all(rates == 0.0))
        if scene.n_obstacles:
            c, r = scene.states(0.0)
            self._static_c, self._static_r = c, r

    # ----------------------------------------------------------------- metric
    def metric(self, x: np.ndarray) -> np.ndarray:
        """y = M x (mm units): the space the planners measure distances in."""
        return np.asarray(x, dtype=float) @ self.metric_matrix.T

    def config_from_metric(self, y: np.ndarray) -> np.ndarray:
        """x from y = M x."""
        return np.asarray(y, dtype=float) @ self.metric_inverse.T

    def motion_bound(self, dx: np.ndarray) -> np.ndarray:
        """Upper bound (mm) on how far any body point moves for a change dx (..., nx)."""
        dy = np.asarray(dx, dtype=float) @ self.metric_matrix.T
        n = self.robot.n_segments
        blocks = np.linalg.norm(dy[..., : 2 * n].reshape(*dy.shape[:-1], n, 2), axis=-1)
        return blocks.sum(axis=-1) + np.abs(dy[..., -1])

    def durations(self, X: np.ndarray) -> np.ndarray:
        """Duration (s) of each straight motion between consecutive rows of X (K, nx) -> (K-1,)."""
        return self.motion_bound(np.diff(np.asarray(X, dtype=float), axis=0)) / self.max_speed

    def times(self, X: np.ndarray, t0: float = 0.0) -> np.ndarray:
        """Waypoint times (s) of a path through X starting at t0."""
        return t0 + np.concatenate([[0.0], np.cumsum(self.durations(X))])

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n configurations drawn uniformly within the limits (n, nx).

        Each effective bending vector is uniform in its disc |u_bar_k| <=
        theta_max_k and z uniform in its stroke; draws that break a cable
        stroke are redrawn (none do for the default robot).
        """
        robot = self.robot
        k = robot.n_segments
        tmax = np.array([s.theta_max for s in robot.segments])
        C_inv = np.linalg.inv(robot.coupling_matrix())
        out = np.empty((0, robot.nx))
        while len(out) < n:
            m = max(n - len(out), 8)
            rad = tmax * np.sqrt(rng.random((m, k)))
            ang = 2.0 * np.pi * rng.random((m, k))
            ub = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=-1).reshape(m, 2 * k)
            z = rng.uniform(robot.z_range[0], robot.z_range[1], size=(m, 1))
            X = np.concatenate([ub @ C_inv.T, z], axis=1)
            out = np.concatenate([out, X[self.within_limits(X)]])
        return out[:n]

    # -------------------------------------------------------------- clearance
    def within_limits(self, X: np.ndarray) -> np.ndarray:
        """True per configuration when it respects every limit (bool (N,))."""
        return self.robot.limit_violation(X) <= LIMIT_TOL

    def clearance(
        self,
        X: np.ndarray,
        t_lo: float | np.ndarray = 0.0,
        t_hi: float | np.ndarray | None = None,
        margin: float | np.ndarray = 0.0,
    ) -> np.ndarray:
        """Conservative clearance (mm, minus D_sf) of the continuous body of each configuration.

        X (N, nx), held over the window [t_lo, t_hi] (s; scalars or (N,),
        t_hi defaults to t_lo); `margin` (mm) is subtracted as well. >= 0 is safe.
        """
        X = np.atleast_2d(np.asarray(X, dtype=float))
        N = X.shape[0]
        if self.scene.n_obstacles == 0:
            return np.full(N, np.inf)
        P = self.model.points(X, self.check_points)  # (N, n, 3)
        if self.static:
            C = self._static_c[None]  # (1, M, 3)
            R = self._static_r[None]  # (1, M)
        else:
            lo = np.broadcast_to(np.asarray(t_lo, dtype=float), (N,))
            hi = lo if t_hi is None else np.broadcast_to(np.asarray(t_hi, dtype=float), (N,))
            a, b, rmax = self.scene.swept(lo, hi)  # (N, M, 3), (N, M)
            C = 0.5 * (a + b)
            R = rmax + 0.5 * np.linalg.norm(b - a, axis=-1)
        A = P[:, :-1, None, :]  # (N, n-1, 1, 3)
        AB = P[:, 1:, None, :] - A
        AC = C[:, None, :, :] - A  # (N, n-1, M, 3)
        den = np.maximum(np.sum(AB * AB, axis=-1), 1e-300)
        u = np.clip(np.sum(AC * AB, axis=-1) / den, 0.0, 1.0)
        d = np.linalg.norm(AC - u[..., None] * AB, axis=-1)  # (N, n-1, M)
        clear = np.min(d.min(axis=1) - R, axis=-1)
        return clear - self.inflate - margin

    def state_valid(self, X: np.ndarray, t: float | np.ndarray = 0.0) -> np.ndarray:
        """Within limits and clear at time t (bool (N,))."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return self.within_limits(X) & (self.clearance(X, t) >= 0.0)

    # ------------------------------------------------------------------ edges
    def _samples(
        self, XA: np.ndarray, XB: np.ndarray, TA: np.ndarray, TB: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Samples of many straight motions at once: (X, edge index, tau, t_lo, t_hi, margin)."""
        dX = XB - XA
        bound = self.motion_bound(dX)
        ns = np.maximum(1, np.ceil(bound / self.resolution)).astype(int)  # intervals per edge
        counts = ns + 1
        e = np.repeat(np.arange(len(ns)), counts)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        k = np.arange(counts.sum()) - np.repeat(starts, counts)
        nse = ns[e]
        tau = k / nse
        X = XA[e] + tau[:, None] * dX[e]
        half = 0.5 / nse
        dT = (TB - TA)[e]
        t_lo = TA[e] + np.clip(tau - half, 0.0, 1.0) * dT
        t_hi = TA[e] + np.clip(tau + half, 0.0, 1.0) * dT
        margin = 0.5 * bound[e] / nse
        return X, e, tau, t_lo, t_hi, margin

    def edge_clearance(
        self,
        XA: np.ndarray,
        XB: np.ndarray,
        TA: np.ndarray | float = 0.0,
        TB: np.ndarray | float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Check many straight motions XA[i] -> XB[i] (E, nx) during [TA[i], TB[i]] (s).

        Returns (min clearance per edge (E,) mm, per-sample clearance, per-sample
        edge index) — the last two let callers find the first unsafe sample.
        """
        XA = np.atleast_2d(np.asarray(XA, dtype=float))
        XB = np.atleast_2d(np.asarray(XB, dtype=float))
        E = XA.shape[0]
        TA = np.broadcast_to(np.asarray(TA, dtype=float), (E,))
        TB = np.broadcast_to(np.asarray(TB, dtype=float), (E,))
        X, e, _, t_lo, t_hi, margin = self._samples(XA, XB, TA, TB)
        c = self.clearance(X, t_lo, t_hi, margin)
        per_edge = np.full(E, np.inf)
        np.minimum.at(per_edge, e, c)
        return per_edge, c, e

    def valid_prefix(self, xa: np.ndarray, xb: np.ndarray, ta: float = 0.0, tb: float = 0.0) -> float:
        """Largest fraction f in [0, 1] such that the motion xa -> xa + f (xb - xa) is safe.

        Time runs linearly from ta to tb over the whole motion. Returns -1 when
        even xa itself is unsafe.
        """
        xa = np.asarray(xa, dtype=float)
        xb = np.asarray(xb, dtype=float)
        X, _, tau, t_lo, t_hi, margin = self._samples(xa[None], xb[None], np.array([ta]), np.array([tb]))
        ok = self.clearance(X, t_lo, t_hi, margin) >= 0.0
        if ok.all():
            return 1.0
        first_bad = int(np.argmin(ok))
        if first_bad == 0:
            return -1.0
        return float(tau[first_bad - 1])

    def path_clearance(self, X: np.ndarray, T: np.ndarray) -> tuple[float, np.ndarray]:
        """Min clearance (mm) along the piecewise-straight timed path (X (K, nx), T (K,)) and per edge."""
        X = np.asarray(X, dtype=float)
        T = np.asarray(T, dtype=float)
        if len(X) == 1:
            c = self.clearance(X, T[0])
            return float(c[0]), c
        per_edge, _, _ = self.edge_clearance(X[:-1], X[1:], T[:-1], T[1:])
        return float(per_edge.min()), per_edge

    def path_valid(self, X: np.ndarray, T: np.ndarray) -> bool:
        """Every waypoint within limits and every motion between them safe."""
        X = np.asarray(X, dtype=float)
        if not np.all(self.within_limits(X)):
            return False
        return self.path_clearance(X, T)[0] >= 0.0
