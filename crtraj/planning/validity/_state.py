"""State validity: the conservative clearance of the continuous body of configurations.

A configuration's body is checked at `check_points` backbone points: the
distance from each obstacle centre to each *chord* between neighbouring
points, minus the sagitta of the arc over the chord (bound 1 in
`crtraj.planning.validity._motion`), minus the disc radius and the scene's safety
distance D_sf, is a lower bound of the true clearance. Held over a time
window, each obstacle is replaced by the sphere enclosing everything it
sweeps in that window (bound 3). Obstacles of other shapes (`Scene.shapes`) are bounded per chord by
`crtraj.world.geometry.chord_clearance` (tangent lines of convex distances, or samples along the chord for
meshes and point clouds) over the same windows, with the same sagitta and inflation. Units mm, s.
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.planning.sampler import ConfigSampler
from crtraj.planning.validity._compiled import per_item
from crtraj.planning.validity._kernels import Kernels
from crtraj.world import margin, packing
from crtraj.world.geometry import chord_clearance

# How fast (mm/s) a moving shape's surface may move when its motion has no finite bound (a turning half
# space): the edge check then never calls a window hopeless from its middle alone (it splits it instead).
_UNBOUNDED = 1.0e12


def shape_enlargement(scene: Any) -> float:
    """The largest speed (mm/s) of any point of the scene's moving shapes over all time (0 when none
    moves): how much a shape's clearance over a window can exceed its clearance at an instant, per second."""
    rate = 0.0
    for ms in scene.shapes:
        if not ms.static:
            rate = max(rate, ms.surface_speed(-MAX_WINDOW, MAX_WINDOW))
    return rate if math.isfinite(rate) else _UNBOUNDED


MAX_WINDOW = 1.0e6  # s: the span over which `shape_enlargement` bounds the shapes' speeds


class StateValidityChecker:
    """Clearance and validity of configurations among a scene's obstacles.

    model: the robot's `Model`. scene: a `crtraj.world.scene.Scene`.
    check_points: backbone points per configuration (>= 2). kernels: the
    compiled kernels and CasADi functions (`crtraj.planning.validity.Kernels`),
    shared by all validators of one planner so that scenes share them (None: this
    checker's own). compiled: evaluate with the compiled kernel
    (`crtraj.planning.validity._compiled`) when a C compiler is available; the
    interpreted CasADi path gives the same numbers (to rounding), slower.
    """

    def __init__(
        self,
        model: Model,
        scene: Any,
        check_points: int = 15,
        kernels: Kernels | None = None,
        compiled: bool = True,
    ) -> None:
        if check_points < 2:
            raise InputError(f"check_points: must be >= 2, got {check_points}")
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.check_points = int(check_points)
        self.limits = ConfigSampler(self.robot)
        robot = self.robot
        h = robot.total_length / (self.check_points - 1)
        kappa = max(s.theta_max / s.length for s in robot.segments)
        half = kappa * h / 2.0
        # An arc of curvature <= kappa strays at most (1 - cos(kappa h/2))/kappa from the chord between
        # two points h apart, but only while kappa h/2 <= pi/2; beyond that fall back to h/2, which always
        # holds: every body point is within h/2 of arc length (so of distance) from a check point.
        sag = (1.0 - math.cos(half)) / kappa if half <= math.pi / 2.0 else h / 2.0
        self.sagitta = float(sag)
        self.inflate = float(margin.inflation(scene.safety_distance, robot.body_radius, self.sagitta))
        self.n_samples = 0  # configurations checked so far (a statistic)
        self.kernels = Kernels() if kernels is None else kernels
        speeds, rates = scene.speed_bounds()
        self.static = bool(np.all(speeds == 0.0) and np.all(rates == 0.0))
        self.spheres_static = self.static  # the spheres alone (the compiled kernel's static slots)
        # how much the sphere swept over a window of dt seconds can exceed the sphere at any one of its
        # instants: capsule length plus radius growth, <= (speed + rate) dt (mm/s)
        self.enlargement_rate = float(np.max(speeds + rates)) if scene.n_obstacles else 0.0
        self.shapes = tuple(getattr(scene, "shapes", ()))
        if self.shapes:
            self.static = self.static and scene.shapes_static
            self.enlargement_rate = max(self.enlargement_rate, shape_enlargement(scene))
        self.kernel = self.kernels.validity_kernel(model, self.check_points) if compiled else None
        if scene.n_obstacles:
            c, r = scene.states(0.0)
            self._static_c, self._static_r = c, r
            self.static_slots = packing.pack(c, r, scene.n_obstacles)

    # -------------------------------------------------------------- kinematics
    def _mapped(self, kind: str, size: int) -> Any:
        """The per-configuration function `kind` mapped over `size` configurations (built once)."""
        n, M = self.check_points, self.scene.n_obstacles
        m = M if kind == "clearance" else 0

        def single() -> Any:
            return self._clearance_function(n, M) if kind == "clearance" else self.model.backbone_function(n)

        def mapped() -> Any:
            return self.kernels.function((kind, n, m, 1), single).map(size, "serial")

        return self.kernels.function((kind, n, m, size), mapped)

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

    @staticmethod
    def _batches(N: int) -> list[tuple[int, int, int]]:
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
        if self.kernel is not None:
            return self.kernel.points(X)
        n = self.check_points
        out = np.empty((X.shape[0], n, 3))
        for start, take, size in self._batches(X.shape[0]):
            block = np.zeros((self.robot.nx, size))
            block[:, :take] = X[start : start + take].T
            res = self._mapped("backbone", size)(block).full()  # 3 x (size * n)
            out[start : start + take] = res.reshape(3, size, n).transpose(1, 2, 0)[:take]
        return out

    # -------------------------------------------------------------- clearance
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
        if not self.shapes:
            return self._sphere_clearance(X, t_lo, t_hi) - self.inflate - margin
        out = np.full(N, np.inf) if self.scene.n_obstacles == 0 else self._sphere_clearance(X, t_lo, t_hi)
        lo = per_item(t_lo, N)
        hi = lo if t_hi is None else per_item(t_hi, N)
        for name, t in (("t0", lo), ("t1", hi)):
            if not np.isfinite(t).all():
                raise InputError(f"{name}: contains NaN or infinity")
        if self.scene.n_obstacles == 0:
            self.n_samples += N
        P = self.points(X)
        origin = self.scene.time_origin
        out = np.minimum(out, chord_clearance(self.shapes, P, lo + origin, hi + origin))
        return out - self.inflate - margin

    def _sphere_clearance(self, X: np.ndarray, t_lo: Any, t_hi: Any) -> np.ndarray:
        """The spheres' chord clearance (mm, before inflation) of configurations X (N, nx) over their windows."""
        N = X.shape[0]
        if self.scene.n_obstacles == 0:
            return np.full(N, np.inf)
        M = self.scene.n_obstacles
        if self.kernel is not None:
            self.n_samples += N
            return self._compiled_clearance(X, t_lo, t_hi)
        if self.spheres_static:
            C = self._static_c.T  # (3, M): broadcast to every configuration
            R = self._static_r[None, :]
        else:
            lo = per_item(t_lo, N)
            hi = lo if t_hi is None else per_item(t_hi, N)
            centers, radii = self.scene.swept_spheres(lo, hi)  # (N, M, 3), (N, M)
            C = centers.transpose(2, 0, 1).reshape(3, N * M)  # M columns per configuration
            R = radii.reshape(1, N * M)
        out = np.empty(N)
        self.n_samples += N
        for start, take, size in self._batches(N):
            block = np.zeros((self.robot.nx, size))
            block[:, :take] = X[start : start + take].T
            if self.spheres_static:
                Cb, Rb = C, R
            else:
                Cb = np.zeros((3, size * M))
                Rb = np.zeros((1, size * M))
                Cb[:, : take * M] = C[:, start * M : (start + take) * M]
                Rb[:, : take * M] = R[:, start * M : (start + take) * M]
            out[start : start + take] = self._mapped("clearance", size)(block, Cb, Rb).full().ravel()[:take]
        return out

    def _compiled_clearance(self, X: np.ndarray, t_lo: Any, t_hi: Any) -> np.ndarray:
        """Chord clearance (mm, before inflation) by the compiled kernel: static slots shared by every
        configuration, or each configuration's swept spheres over its window."""
        assert self.kernel is not None
        if self.spheres_static:
            return self.kernel.clearance(X, self.static_slots)
        N = X.shape[0]
        lo = per_item(t_lo, N)
        hi = lo if t_hi is None else per_item(t_hi, N)
        for name, t in (("t0", lo), ("t1", hi)):
            if not np.isfinite(t).all():
                raise InputError(f"{name}: contains NaN or infinity")  # as `Scene.swept_spheres` says it
        # each window's swept spheres in C (`Scene.swept_spheres`, operation for operation)
        return self.kernel.clearance_windows(X, self.scene.motion_table(), self.scene.time_origin, lo, hi)

    def state_valid(self, X: np.ndarray, t: float | np.ndarray = 0.0) -> np.ndarray:
        """Within limits and clear at time t (bool (N,))."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        return self.limits.within_limits(X) & (self.clearance(X, t) >= 0.0)
