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

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.world import margin

# Limits may be violated by solver round-off; above this a configuration is out of limits.
LIMIT_TOL = 1e-7


class MotionValidator:
    """Safety of configurations and straight motions among a scene's obstacles.

    model: the robot's `Model`. scene: a `crtraj.world.scene.Scene`. check_points:
    backbone points per configuration (chord bound 1 above). resolution:
    largest body motion between edge samples (mm). max_speed: largest speed
    of any body point (mm/s), which times every motion at full speed (a
    motion may take longer: waits and slow motions are checked over their
    own times). time_resolution: moving obstacles only: an uncertified edge
    interval longer than this (s) is split in time before it is declared
    unsafe (waits and slow motions sweep obstacles over long windows).
    """

    def __init__(
        self,
        model: Model,
        scene: Any,
        *,
        check_points: int = 15,
        resolution: float = 3.0,
        max_speed: float = 50.0,
        time_resolution: float = 0.25,
        functions: dict[Any, Any] | None = None,
    ) -> None:
        if check_points < 2:
            raise InputError(f"check_points: must be >= 2, got {check_points}")
        if not (math.isfinite(resolution) and resolution > 0):
            raise InputError(f"resolution: must be > 0 mm, got {resolution}")
        if not (math.isfinite(max_speed) and max_speed > 0):
            raise InputError(f"max_speed: must be > 0 mm/s, got {max_speed}")
        if not (math.isfinite(time_resolution) and time_resolution > 0):
            raise InputError(f"time_resolution: must be > 0 s, got {time_resolution}")
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.check_points = int(check_points)
        self.resolution = float(resolution)
        self.max_speed = float(max_speed)
        self.time_resolution = float(time_resolution)
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
        half = kappa * h / 2.0
        # An arc of curvature <= kappa strays at most (1 - cos(kappa h/2))/kappa from the chord between
        # two points h apart, but only while kappa h/2 <= pi/2; beyond that fall back to h/2, which always
        # holds: every body point is within h/2 of arc length (so of distance) from a check point.
        sag = (1.0 - math.cos(half)) / kappa if half <= math.pi / 2.0 else h / 2.0
        self.sagitta = float(sag)
        self.inflate = float(margin.inflation(scene.safety_distance, robot.body_radius, self.sagitta))
        # adaptive edge checks start from intervals of this much body motion (mm)
        self.coarse = 16.0 * self.resolution
        self.n_samples = 0  # configurations checked so far (a statistic)
        # CasADi functions by (kind, check points, obstacles, batch size); a
        # planner passes one dict to all its validators so scenes share them
        self._fns: dict[Any, Any] = {} if functions is None else functions
        speeds, rates = scene.speed_bounds()
        self.static = bool(np.all(speeds == 0.0) and np.all(rates == 0.0))
        # how much the sphere swept over a window of dt seconds can exceed the sphere at any one of its
        # instants: capsule length plus radius growth, <= (speed + rate) dt (mm/s)
        self._enl_rate = float(np.max(speeds + rates)) if scene.n_obstacles else 0.0
        if scene.n_obstacles:
            c, r = scene.states(0.0)
            self._static_c, self._static_r = c, r

    # -------------------------------------------------------------- kinematics
    def _mapped(self, kind: str, size: int) -> Any:
        """The per-configuration function `kind` mapped over `size` configurations (built once)."""
        n, M = self.check_points, self.scene.n_obstacles
        key = (kind, n, M if kind == "clearance" else 0, size)
        f = self._fns.get(key)
        if f is None:
            base = self._fns.get((kind, n, key[2], 1))
            if base is None:
                base = self._clearance_function(n, M) if kind == "clearance" else self.model.backbone_function(n)
                self._fns[(kind, n, key[2], 1)] = base
            f = base.map(size, "serial")
            self._fns[key] = f
        return f

    def _clearance_function(self, n: int, M: int) -> Any:
        """CasADi x (nx), C (3 x M), R (1 x M) -> min over chords and obstacles of dist - R (mm).

        The chords join n backbone points evenly spread in arc length; the
        distance is from each obstacle centre to each chord *segment*. One
        fused SX function: the numbers never leave CasADi's VM per point.
        """
        x = ca.SX.sym("x", self.robot.nx)
        C = ca.SX.sym("C", 3, M)
        R = ca.SX.sym("R", 1, M)
        P = self.model.backbone_function(n)(x)  # 3 x n
        A = P[:, :-1]
        AB = P[:, 1:] - A
        den = ca.fmax(ca.sum1(AB * AB), 1e-300)
        per = []
        for j in range(M):
            AC = ca.repmat(C[:, j], 1, n - 1) - A
            u = ca.fmin(ca.fmax(ca.sum1(AC * AB) / den, 0.0), 1.0)
            D = AC - AB * ca.repmat(u, 3, 1)
            per.append(ca.mmin(ca.sqrt(ca.sum1(D * D))) - R[j])
        return ca.Function("chord_clearance", [x, C, R], [ca.mmin(ca.horzcat(*per))], ["x", "C", "R"], ["d"])

    def _batches(self, N: int) -> list[tuple[int, int, int]]:
        """(start, count, map size) blocks covering N configurations; sizes are powers of two.

        A map evaluates every column, so small calls (the adaptive edge checks
        make many) use small maps rather than padding.
        """
        out = []
        start = 0
        while start < N:
            left = N - start
            size = min(1024, 1 << int(np.ceil(np.log2(left))))
            take = min(size, left)
            out.append((start, take, size))
            start += take
        return out

    def points(self, X: np.ndarray) -> np.ndarray:
        """Check points (N, check_points, 3) of configurations X (N, nx), mm."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        n = self.check_points
        out = np.empty((X.shape[0], n, 3))
        for start, take, size in self._batches(X.shape[0]):
            block = np.zeros((self.robot.nx, size))
            block[:, :take] = X[start : start + take].T
            res = self._mapped("backbone", size)(block).full()  # 3 x (size * n)
            out[start : start + take] = res.reshape(3, size, n).transpose(1, 2, 0)[:take]
        return out

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
        C = robot.coupling_matrix()
        tmax = np.array([s.theta_max for s in robot.segments])
        ub = (X[:, : 2 * n] @ C.T).reshape(-1, n, 2)
        norm = np.linalg.norm(ub, axis=-1)
        ub = ub * np.minimum(1.0, tmax / np.maximum(norm, 1e-300))[..., None]
        out = X.copy()
        out[:, : 2 * n] = ub.reshape(-1, 2 * n) @ np.linalg.inv(C).T
        out[:, -1] = np.clip(X[:, -1], robot.z_range[0], robot.z_range[1])
        return out

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
        M = self.scene.n_obstacles
        if self.static:
            C = self._static_c.T  # (3, M): broadcast to every configuration
            R = self._static_r[None, :]
        else:
            lo = np.broadcast_to(np.asarray(t_lo, dtype=float), (N,))
            hi = lo if t_hi is None else np.broadcast_to(np.asarray(t_hi, dtype=float), (N,))
            a, b, rmax = self.scene.swept(lo, hi)  # (N, M, 3), (N, M)
            C = (0.5 * (a + b)).transpose(2, 0, 1).reshape(3, N * M)  # M columns per configuration
            R = (rmax + 0.5 * np.linalg.norm(b - a, axis=-1)).reshape(1, N * M)
        out = np.empty(N)
        self.n_samples += N
        for start, take, size in self._batches(N):
            block = np.zeros((self.robot.nx, size))
            block[:, :take] = X[start : start + take].T
            if self.static:
                Cb, Rb = C, R
            else:
                Cb = np.zeros((3, size * M))
                Rb = np.zeros((1, size * M))
                Cb[:, : take * M] = C[:, start * M : (start + take) * M]
                Rb[:, : take * M] = R[:, start * M : (start + take) * M]
            out[start : start + take] = self._mapped("clearance", size)(block, Cb, Rb).full().ravel()[:take]
        return out - self.inflate - margin

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

    def check_edges(
        self,
        XA: np.ndarray,
        XB: np.ndarray,
        TA: np.ndarray | float = 0.0,
        TB: np.ndarray | float = 0.0,
        *,
        prefix: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Adaptive check of many straight motions XA[i] -> XB[i] (E, nx) during [TA[i], TB[i]] (s).

        Each motion is split into intervals of at most `coarse` mm of body
        motion. An interval is certified when the configuration at its middle
        keeps a clearance c (over the interval's time window) of at least the
        body motion h to either end: every configuration of the interval is
        then clear (bound 2 of the module docstring). Intervals that are
        neither certified nor already unsafe (c < 0) are halved, down to
        `resolution`; what is still uncertified there is unsafe. So motions
        far from obstacles cost a few samples and only the parts near
        obstacles are sampled finely. With moving obstacles an uncertified
        interval longer than `time_resolution` is split rather than declared
        unsafe (the swept obstacle of a long window is large; a wait, x_a =
        x_b, is certified piece by piece in time), unless its middle
        configuration collides at every instant of the window.

        Returns (f, lower): f (E,) in [0, 1], the motion is certified safe from
        its start to the fraction f (1: the whole motion); lower (E,), a lower
        bound of the clearance over the certified part (mm). With
        prefix=False a motion stops being refined at its first unsafe
        interval and f only tells safe (1) from unsafe (< 1).
        """
        XA = np.atleast_2d(np.asarray(XA, dtype=float))
        XB = np.atleast_2d(np.asarray(XB, dtype=float))
        E = XA.shape[0]
        TA = np.broadcast_to(np.asarray(TA, dtype=float), (E,))
        TB = np.broadcast_to(np.asarray(TB, dtype=float), (E,))
        dX = XB - XA
        dT = TB - TA
        bound = self.motion_bound(dX)
        fail = np.ones(E)
        lower = np.full(E, np.inf)
        n0 = np.maximum(1, np.ceil(bound / self.coarse)).astype(int)
        e = np.repeat(np.arange(E), n0)
        k = np.arange(n0.sum()) - np.repeat(np.concatenate([[0], np.cumsum(n0)[:-1]]), n0)
        ta = k / n0[e]
        tb = (k + 1) / n0[e]
        finest = 0.5 * self.resolution * (1.0 + 1e-9)
        # static scenes: every window is irrelevant, so no split in time
        tres = np.inf if self.static else self.time_resolution * (1.0 + 1e-9)
        while len(e):
            tm = 0.5 * (ta + tb)
            h = 0.5 * bound[e] * (tb - ta)
            X = XA[e] + tm[:, None] * dX[e]
            c = self.clearance(X, TA[e] + ta * dT[e], TA[e] + tb * dT[e])
            ok = c >= h
            np.minimum.at(lower, e[ok], (c - h)[ok])
            # An uncertified interval is unsafe when its middle configuration collides at every time of
            # the window (c + enl < 0: each instant's sphere lies within enl of the swept one) or when
            # it is as fine as it gets in motion (h) and in time; otherwise it is split.
            dt = dT[e] * (tb - ta)
            hopeless = c + self._enl_rate * dt < 0.0
            bad = ~ok & (hopeless | (((c < 0.0) | (h <= finest)) & (dt <= tres)))
            np.minimum.at(fail, e[bad], ta[bad])
            split = ~ok & ~bad
            split &= ta < fail[e] if prefix else fail[e] >= 1.0
            e, ta, tm, tb = e[split], ta[split], tm[split], tb[split]
            e = np.repeat(e, 2)
            ta, tb = np.stack([ta, tm], axis=1).ravel(), np.stack([tm, tb], axis=1).ravel()
        return fail, lower

    def edges_valid(
        self, XA: np.ndarray, XB: np.ndarray, TA: np.ndarray | float = 0.0, TB: np.ndarray | float = 0.0
    ) -> np.ndarray:
        """True per motion XA[i] -> XB[i] that is certified safe over [TA[i], TB[i]] (bool (E,))."""
        f, _ = self.check_edges(XA, XB, TA, TB, prefix=False)
        return f >= 1.0

    def valid_prefix(self, xa: np.ndarray, xb: np.ndarray, ta: float = 0.0, tb: float = 0.0) -> float:
        """Largest certified fraction f in [0, 1] of the motion xa -> xb (time linear from ta to tb).

        The motion xa -> xa + f (xb - xa) is safe; 0 when nothing is certified.
        """
        f, _ = self.check_edges(np.asarray(xa)[None], np.asarray(xb)[None], np.array([ta]), np.array([tb]))
        return float(f[0])

    def path_clearance(self, X: np.ndarray, T: np.ndarray) -> tuple[float, np.ndarray]:
        """Smallest body clearance (mm, minus D_sf) along a timed piecewise-straight path, and per motion.

        A measurement for reports, not a certificate (`path_valid` is): the
        configurations every `resolution` mm of body motion, each at its own
        time, with the continuous-body (chord and sagitta) bound and no
        sampling margin.
        """
        X = np.atleast_2d(np.asarray(X, dtype=float))
        T = np.atleast_1d(np.asarray(T, dtype=float))
        if len(X) == 1:
            c = self.clearance(X, T[0])
            return float(c[0]), c
        S, e, tau, _, _, _ = self._samples(X[:-1], X[1:], T[:-1], T[1:])
        ts = T[:-1][e] + tau * (T[1:] - T[:-1])[e]
        c = self.clearance(S, ts, ts)
        per_edge = np.full(len(X) - 1, np.inf)
        np.minimum.at(per_edge, e, c)
        return float(per_edge.min()), per_edge

    def path_valid(self, X: np.ndarray, T: np.ndarray) -> bool:
        """Every waypoint within limits and every motion between them certified safe."""
        X = np.asarray(X, dtype=float)
        T = np.asarray(T, dtype=float)
        if not np.all(self.within_limits(X)):
            return False
        if len(X) == 1:
            return bool(self.clearance(X, T[0])[0] >= 0.0)
        return bool(np.all(self.edges_valid(X[:-1], X[1:], T[:-1], T[1:])))
