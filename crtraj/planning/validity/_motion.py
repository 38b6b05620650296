"""Motion validity: conservative, vectorised collision checks of whole-body motions in configuration space.

`MotionValidator` answers the planners' two questions (OMPL's state validity
and motion validity): is configuration x safe over a time window
(`crtraj.planning.validity._state`), and is the straight motion from x_a to
x_b (linear in x) safe over the time it takes (here)? It is the one handle
the planners pass around, like OMPL's SpaceInformation: it also gives the
body-motion metric (`crtraj.planning.metric`) and the sampler
(`crtraj.planning.sampler`) its checks are built on.
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
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.metric import BodyMetric
from crtraj.planning.sampler import ConfigSampler
from crtraj.planning.validity._compiled import ValidityKernel, per_item
from crtraj.planning.validity._kernels import Kernels
from crtraj.planning.validity._rod_kernel import RodKernel
from crtraj.planning.validity._state import StateValidityChecker

# From this many obstacles on the compiled edge check runs its broad phase (below it, the one extra
# configuration per motion that the broad phase evaluates costs more than the distances it saves).
BROAD_MIN = 3


def _finite_times(T: Any, n: int, name: str) -> np.ndarray:
    """`per_item(T, n)`, refused (one line naming `name`) when a time is NaN or infinite: such a time would
    reach numpy's interval arithmetic (0 * inf) before the clearance check refuses it."""
    t = per_item(T, n)
    if not np.isfinite(t).all():
        raise InputError(f"{name}: contains NaN or infinity")  # as `Scene.swept_spheres` says it
    return t


@dataclass(frozen=True)
class _EdgeBatch:
    """Straight motions XA -> XA + step (E, nx) over [TA, TA + span] (s) to check: their body-motion bounds
    (mm), first interval counts, the finest interval (mm) and time window (s), and the prefix mode."""

    XA: np.ndarray
    step: np.ndarray
    bound: np.ndarray
    n0: np.ndarray
    TA: np.ndarray
    span: np.ndarray
    finest: float
    tres: float
    prefix: bool
    first: bool = False

    def parts(self) -> tuple[Any, ...]:
        """The fields in order (unpacked by the two edge-check loops)."""
        return (self.XA, self.step, self.bound, self.n0, self.TA, self.span, self.finest, self.tres, self.prefix)


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
    kernels: the compiled kernels and CasADi functions shared by a planner's validators (`Kernels`). rate_limits: usable
    actuator limits; with them every motion is timed within the actuators' speed limits too.
    compiled: check with the compiled kernel when a C compiler is available (same results, faster).
    broad_phase: the compiled edge check drops, per motion, the obstacles that cannot decide any of its
    samples (from `BROAD_MIN` obstacles on; the same verdicts, less work among many obstacles).
    early_exit: `first_valid` stops the compiled check at the first motion certified whole (the same
    answer; False: every motion of the batch is checked).

    Parts: `state` (`StateValidityChecker`), `space` (`BodyMetric`),
    `sampler` (`ConfigSampler`); the methods below that only forward to them
    keep the planners' code to one handle.
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
        kernels: Kernels | None = None,
        rate_limits: RateLimits | None = None,
        compiled: bool = True,
        broad_phase: bool = True,
        early_exit: bool = True,
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
        self.state = StateValidityChecker(model, scene, check_points, kernels, compiled)
        self.space = BodyMetric(self.robot, max_speed, rate_limits)
        self.sampler = ConfigSampler(self.robot)
        self.check_points = self.state.check_points
        self.resolution = float(resolution)
        self.max_speed = self.space.max_speed
        self.time_resolution = float(time_resolution)
        self.weights = self.space.weights
        self.metric_matrix = self.space.metric_matrix
        self.sagitta = self.state.sagitta
        self.inflate = self.state.inflate
        self.static = self.state.static
        # with a compiled kernel, run the edge refinement loop in C (False: the numpy loop, calling the kernel
        # for clearances only; the same numbers, kept for cross-checks)
        self.compiled_loop = True
        self.broad_phase = bool(broad_phase)
        self.early_exit = bool(early_exit)
        # adaptive edge checks start from intervals of this much body motion (mm)
        self.coarse = 16.0 * self.resolution

    def runs_compiled(self) -> bool:
        """Whether the checks run in the compiled C kernel (a C compiler was found; not in tip mode)."""
        return self.state.kernel is not None

    @property
    def n_samples(self) -> int:
        """Configurations checked so far (a statistic)."""
        return self.state.n_samples

    # ------------------------------------------------- forwarded to the parts
    def metric(self, x: np.ndarray) -> np.ndarray:
        """y = M x (mm): `BodyMetric.metric`."""
        return self.space.metric(x)

    def config_from_metric(self, y: np.ndarray) -> np.ndarray:
        """x from y = M x: `BodyMetric.config_from_metric`."""
        return self.space.config_from_metric(y)

    def motion_bound(self, dx: np.ndarray) -> np.ndarray:
        """Largest body-point motion (mm) for a change dx: `BodyMetric.motion_bound`."""
        return self.space.motion_bound(dx)

    def duration(self, dx: np.ndarray, bound: np.ndarray | None = None) -> np.ndarray:
        """Shortest constant-speed duration (s) of straight motions by dx: `BodyMetric.duration` (bound: their
        `motion_bound` (mm) when the caller has it)."""
        return self.space.duration(dx, bound)

    def durations(self, X: np.ndarray) -> np.ndarray:
        """Full-speed duration (s) of each motion of a path: `BodyMetric.durations`."""
        return self.space.durations(X)

    def times(self, X: np.ndarray, t0: float = 0.0) -> np.ndarray:
        """Full-speed waypoint times (s) from t0: `BodyMetric.times`."""
        return self.space.times(X, t0)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n configurations uniform within the limits: `ConfigSampler.sample`."""
        return self.sampler.sample(rng, n)

    def project_limits(self, X: np.ndarray) -> np.ndarray:
        """Configurations moved into the limits: `ConfigSampler.project_limits`."""
        return self.sampler.project_limits(X)

    @property
    def kernel(self) -> ValidityKernel | None:
        """The compiled validity kernel this validator checks with (None: the interpreted path)."""
        return self.state.kernel

    def within_limits(self, X: np.ndarray) -> np.ndarray:
        """True per configuration within every limit: `ConfigSampler.within_limits`."""
        return self.sampler.within_limits(X)

    def points(self, X: np.ndarray) -> np.ndarray:
        """Check points (N, check_points, 3) mm: `StateValidityChecker.points`."""
        return self.state.points(X)

    def clearance(
        self,
        X: np.ndarray,
        t_lo: float | np.ndarray = 0.0,
        t_hi: float | np.ndarray | None = None,
        margin: float | np.ndarray = 0.0,
    ) -> np.ndarray:
        """Conservative body clearance (mm, minus D_sf) over [t_lo, t_hi]: `StateValidityChecker.clearance`."""
        return self.state.clearance(X, t_lo, t_hi, margin)

    def state_valid(self, X: np.ndarray, t: float | np.ndarray = 0.0) -> np.ndarray:
        """Within limits and clear at time t: `StateValidityChecker.state_valid`."""
        return self.state.state_valid(X, t)

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
        TA = _finite_times(TA, E, "t0")
        TB = _finite_times(TB, E, "t1")
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
        first: bool = False,
        bound: np.ndarray | None = None,
        verdict: bool = False,
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
        interval and f only tells safe (1) from unsafe (< 1). first: the compiled check may stop after
        the first motion certified whole; the motions after it are then not checked (f -1). bound: the
        motions' body-motion bounds (E,) mm when the caller has them (`motion_bound(XB - XA)`, the same
        numbers), so they are not computed twice. verdict (with prefix=False): the compiled check stops a
        motion at its first unsafe interval, within a level too, so f < 1 marks an unsafe motion without
        being the fraction the full check gives, and lower is not the whole motion's (a safe motion: the same).
        """
        XA = np.atleast_2d(np.asarray(XA, dtype=float))
        XB = np.atleast_2d(np.asarray(XB, dtype=float))
        E = XA.shape[0]
        dX = XB - XA
        # numpy's product rounds one motion (a matrix-vector product) differently from a batch of them, whose
        # rows it computes alike whatever the batch: a caller's bounds of a batch are used from two motions on
        bound = self.motion_bound(dX) if bound is None or E < 2 else np.asarray(bound, dtype=float)
        finest = 0.5 * self.resolution * (1.0 + 1e-9)
        # static scenes: every window is irrelevant, so no split in time
        tres = np.inf if self.static else self.time_resolution * (1.0 + 1e-9)
        kernel = self.state.kernel
        # the compiled loop knows the spheres only: a scene with other shapes is checked by the numpy loop
        fast = kernel is not None and self.compiled_loop and self.scene.n_obstacles and E and not self.state.shapes
        if fast and self.static:
            # a static scene's compiled check needs no times: the loop in C, with the numpy loop's arithmetic,
            # entered without the batch the numpy loop needs (a query makes many small calls)
            out = kernel.check_edges(
                XA, dX, bound, self.coarse, self.state.static_slots, self.inflate, finest, prefix, self._broad(), first,
                verdict,
            )  # fmt: skip
            if out is not None:
                self.state.n_samples += out[2]
                return out[0], out[1]
        TA = _finite_times(TA, E, "t0")
        TB = _finite_times(TB, E, "t1")
        dT = TB - TA
        if fast and not self.static:
            scene = self.scene
            limits = (self.inflate, finest, self.state.enlargement_rate, tres)
            out = kernel.check_edges_moving(
                XA, dX, bound, self.coarse, TA, dT, scene.motion_table(), scene.time_origin, limits, prefix,
                self._broad(), first, verdict,
            )  # fmt: skip
            if out is not None:
                self.state.n_samples += out[2]
                return out[0], out[1]
        # the numpy loop: no compiled kernel (or no obstacle, or no motion), or a value that is not finite (the
        # compiled check refused it without checking anything; the numpy loop says which)
        n0 = np.maximum(1, np.ceil(bound / self.coarse)).astype(int)
        return self._refine_edges(_EdgeBatch(XA, dX, bound, n0, TA, dT, finest, tres, prefix, first))

    def _broad(self) -> int:
        """The compiled edge check's broad-phase threshold (obstacle count; 0: off)."""
        return BROAD_MIN if self.broad_phase else 0

    def _refine_edges(self, b: _EdgeBatch) -> tuple[np.ndarray, np.ndarray]:
        """`check_edges`' refinement loop in numpy (every motion's intervals halved together)."""
        XA, dX, bound, n0, TA, dT, finest, tres, prefix = b.parts()
        E = XA.shape[0]
        fail = np.ones(E)
        lower = np.full(E, np.inf)
        e = np.repeat(np.arange(E), n0)
        k = np.arange(n0.sum()) - np.repeat(np.concatenate([[0], np.cumsum(n0)[:-1]]), n0)
        ta = k / n0[e]
        tb = (k + 1) / n0[e]
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
            hopeless = c + self.state.enlargement_rate * dt < 0.0
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
        f, _ = self.check_edges(XA, XB, TA, TB, prefix=False, verdict=True)
        return f >= 1.0

    def tip_position(self, X: np.ndarray) -> np.ndarray:
        """Tip positions (N, 3) mm of configurations X (N, nx): the compiled kernel when there is one (one C call,
        no CasADi map built per batch size), else the model's."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        kernel = self.state.kernel
        if kernel is not None and len(X):
            return kernel.tip_positions(X) if isinstance(kernel, RodKernel) else kernel.tip_jacobian(X)[0]
        return self.model.tip_position(X)

    def first_valid(
        self,
        XA: np.ndarray,
        XB: np.ndarray,
        TA: np.ndarray | float = 0.0,
        TB: np.ndarray | float = 0.0,
        bound: np.ndarray | None = None,
    ) -> int:
        """Index of the first motion XA[i] -> XB[i] over [TA[i], TB[i]], in the order given, that `edges_valid`
        certifies; -1 when none is. Order the motions best first and this is the best valid one; with
        `early_exit` the compiled check stops there, so the motions after it cost nothing. bound: as in
        `check_edges`."""
        if not len(XA):
            return -1
        f, _ = self.check_edges(XA, XB, TA, TB, prefix=False, first=self.early_exit, bound=bound, verdict=True)
        ok = np.flatnonzero(f >= 1.0)
        return int(ok[0]) if len(ok) else -1

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
        if not np.isfinite(T).all():
            raise InputError("t: contains NaN or infinity")
        if len(X) == 1:
            c = self.clearance(X, T[0])
            return float(c[0]), c
        kernel = self.state.kernel
        if kernel is not None and self.scene.n_obstacles and not self.state.shapes and T.shape == (len(X),):
            # the same samples and minima in one compiled call, which skips per motion the obstacles that
            # cannot set its minimum
            sc = self.scene
            moving = (None, sc.motion_table(), sc.time_origin)
            obstacles = (self.state.static_slots, None, 0.0) if self.static else moving
            bound = self.motion_bound(np.diff(X, axis=0))
            out = kernel.path_clearance(
                X, T, bound, self.resolution, obstacles, self.inflate, self.state.enlargement_rate
            )
            if out is not None:
                self.state.n_samples += out[1]
                return float(out[0].min()), out[0]
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
