"""Shortcuts, spline smoothing and result assembly for timed configuration paths.

Every planner hands its raw path (configurations joined by straight motions)
to a `PathPostprocessor`, which

- shortcuts it: batches of random shortcuts between two points of the path,
  verified in one vectorised call, keeping the one that saves most body
  motion (in a scene with moving obstacles the rest of the path is reached
  earlier, so it is re-verified at its new times);
- smooths it: a clamped cubic B-spline (`crtraj.core.splines`, numpy) whose control polygon is the
  path with extra control points `corner` mm of body motion either side of
  each corner, so straight runs stay straight and only corners are rounded.
  Spline points are convex combinations of configurations within limits,
  hence within limits (every limit is convex). The returned motion, straight
  between spline samples every `waypoint_step` mm, is verified again; if it
  is unsafe the corners are halved once, then the unsmoothed path is kept;
- times it (each straight motion lasts its body-motion bound / max_speed)
  and builds the `PlanResult` (tips, cable lengths, tip travel, measured
  minimum clearance).

Paths among moving obstacles may wait or move slower than max_speed, so
they carry their own waypoint times T (the `*_timed` methods): their
shortcuts keep the times of both ends (the new straight motion takes the
time the detour took, never faster than max_speed since the body-motion
bound is a norm), so only the new motion needs checking; their spline
interpolates the times with the configurations (a B-spline's derivative is
a convex combination of its control polygon's, so it keeps the polygon's
speed bound), and it is verified at its own times.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from crtraj.core.splines import BSplineCurve
from crtraj.planning.goal import TipGoal, tip_tangents
from crtraj.planning.options import PlannerOptions
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.validity import MotionValidator

# Timed shortcuts are verified this many at a time, most saving first.
SHORTCUT_CHUNK = 4


class PathPostprocessor:
    """Post-processing of one query's path. validator: the query's checks; options:
    `PlannerOptions` (shortcut_rounds, shortcut_batch, smooth, corner,
    waypoint_step); rng: the query's seeded generator; t0: start time (s)."""

    def __init__(
        self, validator: MotionValidator, options: PlannerOptions, rng: np.random.Generator, t0: float = 0.0
    ) -> None:
        self.v = validator
        self.o = options
        self.rng = rng
        self.t0 = float(t0)
        self.counts: dict[str, int] = {}

    # ------------------------------------------------------------------ basics
    def times(self, X: np.ndarray) -> np.ndarray:
        """Waypoint times (s) of the path X starting at t0."""
        return self.v.times(X, self.t0)

    def valid(self, X: np.ndarray) -> bool:
        """The timed path is within limits and certified safe."""
        return self.v.path_valid(X, self.times(X))

    def clearance(self, X: np.ndarray) -> float:
        """Measured minimum clearance along the timed path (mm, minus D_sf)."""
        return self.v.path_clearance(X, self.times(X))[0]

    def resample(self, X: np.ndarray, step: float | None = None) -> np.ndarray:
        """Insert waypoints on each straight motion so none is longer than `step` (mm, default waypoint_step)."""
        step = self.o.waypoint_step if step is None else step
        if len(X) < 2:
            return X
        dX = np.diff(X, axis=0)
        n = np.maximum(1, np.ceil(self.v.motion_bound(dX) / step)).astype(int)
        e = np.repeat(np.arange(len(n)), n)
        k = np.arange(n.sum()) - np.repeat(np.concatenate([[0], np.cumsum(n)[:-1]]), n) + 1
        return np.concatenate([X[:1], X[e] + (k / n[e])[:, None] * dX[e]])

    # --------------------------------------------------------------- shortcuts
    def shortcut(self, X: np.ndarray, deadline: float | None = None) -> np.ndarray:
        """Batched random shortcuts; each round keeps the verified one that saves most."""
        v, o, rng = self.v, self.o, self.rng
        checked = 0
        for _ in range(o.shortcut_rounds):
            if len(X) <= 2 or (deadline is not None and time.perf_counter() > deadline):
                break
            s = np.concatenate([[0.0], np.cumsum(v.motion_bound(np.diff(X, axis=0)))])
            B = o.shortcut_batch
            u = np.sort(rng.random((B, 2)) * s[-1], axis=1)
            # a third of the candidates join two waypoints (skip whole vertices)
            k = B // 3
            if k:
                u[:k] = s[np.sort(rng.integers(0, len(X), size=(k, 2), dtype=np.int64), axis=1)]
            u = u[(u[:, 1] - u[:, 0]) > v.resolution]
            if not len(u):
                continue
            # both ends of every candidate in one pass (the same numbers as one pass per end)
            P = _at(X, s, np.concatenate([u[:, 0], u[:, 1]]))
            P1, P2 = P[: len(u)], P[len(u) :]
            bound = v.motion_bound(P2 - P1)
            saving = (u[:, 1] - u[:, 0]) - bound
            good = saving > 1e-6
            checked += int(np.count_nonzero(good))
            if v.static:  # only the new straight motion needs checking: no candidate path is built
                # the valid one that saves most: the first valid in the order of saving (ties: lowest
                # index, as argmax), so the check can stop there
                order = np.flatnonzero(good)
                if not len(order):
                    continue
                order = order[np.argsort(-saving[order], kind="stable")]
                k = v.first_valid(P1[order], P2[order], bound=bound[order])
                best = int(order[k]) if k >= 0 else -1
            else:
                u, P1, P2, saving = u[good], P1[good], P2[good], saving[good]
                if not len(u):
                    continue
                ok = self._batch_ok([_splice(X, s, a, b, p1, p2) for a, b, p1, p2 in zip(*u.T, P1, P2, strict=True)])
                best = int(np.flatnonzero(ok)[np.argmax(saving[ok])]) if ok.any() else -1
            if best >= 0:
                X = dedup(_splice(X, s, u[best, 0], u[best, 1], P1[best], P2[best])[0])
        self.counts["shortcut_checks"] = self.counts.get("shortcut_checks", 0) + checked
        return dedup(X)

    def _batch_ok(self, cands: list[tuple[np.ndarray, int]]) -> np.ndarray:
        """Which candidate paths are safe, in one vectorised check.

        Static scenes: only the new straight motion needs checking. Moving
        obstacles: everything from the new motion on, at its new times.
        """
        v = self.v
        XA, XB, TA, TB, owner = [], [], [], [], []
        for c_i, (C, k) in enumerate(cands):
            T = self.times(C)
            last = k + 1 if v.static else len(C) - 1
            XA.append(C[k:last])
            XB.append(C[k + 1 : last + 1])
            TA.append(T[k:last])
            TB.append(T[k + 1 : last + 1])
            owner.append(np.full(last - k, c_i))
        ok = v.edges_valid(np.concatenate(XA), np.concatenate(XB), np.concatenate(TA), np.concatenate(TB))
        good = np.ones(len(cands), dtype=bool)
        np.logical_and.at(good, np.concatenate(owner), ok)
        return good

    # ------------------------------------------------------------ timed paths
    def resample_timed(self, X: np.ndarray, T: np.ndarray, step: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`resample` of a timed path: times (s) interpolated linearly with the configurations."""
        step = self.o.waypoint_step if step is None else step
        if len(X) < 2:
            return X, T
        dX = np.diff(X, axis=0)
        n = np.maximum(1, np.ceil(self.v.motion_bound(dX) / step)).astype(int)
        e = np.repeat(np.arange(len(n)), n)
        k = np.arange(n.sum()) - np.repeat(np.concatenate([[0], np.cumsum(n)[:-1]]), n) + 1
        f = k / n[e]
        return (
            np.concatenate([X[:1], X[e] + f[:, None] * dX[e]]),
            np.concatenate([T[:1], T[e] + f * np.diff(T)[e]]),
        )

    def shortcut_timed(
        self, X: np.ndarray, T: np.ndarray, deadline: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Batched time-preserving shortcuts: the motion between the configurations at times a < b
        (s) is replaced by one straight motion over [a, b]; only that motion is verified."""
        v, o, rng = self.v, self.o, self.rng
        checked = 0
        for _ in range(o.shortcut_rounds):
            if len(X) <= 2 or (deadline is not None and time.perf_counter() > deadline):
                break
            s = np.concatenate([[0.0], np.cumsum(v.motion_bound(np.diff(X, axis=0)))])
            B = o.shortcut_batch
            u = np.sort(T[0] + rng.random((B, 2)) * (T[-1] - T[0]), axis=1)
            k = B // 3
            if k:  # a third of the candidates join two waypoints
                u[:k] = T[np.sort(rng.integers(0, len(X), size=(k, 2), dtype=np.int64), axis=1)]
            # both ends of every candidate in one pass (the same numbers as one pass per end)
            P = _at(X, T, np.concatenate([u[:, 0], u[:, 1]]))
            P1, P2 = P[:B], P[B:]
            dP = P2 - P1
            bound = v.motion_bound(dP)
            saving = np.interp(u[:, 1], T, s) - np.interp(u[:, 0], T, s) - bound
            # the new motion must not be faster than max_speed and the actuators' speed limits allow
            good = (saving > 1e-6) & (v.space.duration(dP, bound) <= (u[:, 1] - u[:, 0]) * (1.0 - 1e-9))
            u, P1, P2, saving, bound = u[good], P1[good], P2[good], saving[good], bound[good]
            if not len(u):
                continue
            # most saving first: the round keeps the best valid one whose cut pieces verify (of at most 3)
            if v.early_exit:
                found = self._timed_first(P1, P2, u, saving, bound)
            else:
                found = self._timed_chunks(P1, P2, u, saving)
            # the pieces of the old motions that the splice cuts are checked as well, so every motion of
            # the result is certified as it stands (a piece of a certified motion need not be)
            for best in found:
                a, b = u[best]
                i = int(np.searchsorted(T, a, side="right"))
                j = int(np.searchsorted(T, b, side="left"))
                Xn = np.concatenate([X[:i], P1[best][None], P2[best][None], X[j:]])
                Tn = np.concatenate([T[:i], [a, b], T[j:]])
                checked += 2
                ends = v.edges_valid(Xn[[i - 1, i + 1]], Xn[[i, i + 2]], Tn[[i - 1, i + 1]], Tn[[i, i + 2]])
                if ends.all():
                    X, T = dedup_timed(Xn, Tn)
                    break
        self.counts["shortcut_checks"] = self.counts.get("shortcut_checks", 0) + checked
        return dedup_timed(X, T)

    def _timed_chunks(self, P1: np.ndarray, P2: np.ndarray, u: np.ndarray, saving: np.ndarray) -> Iterator[int]:
        """Timed shortcut candidates P1 -> P2 over [u0, u1] (s), most saving first, SHORTCUT_CHUNK checked at
        a time: the valid ones of the first chunk that has any (at most 3), most saving first."""
        order = np.argsort(-saving)
        ok = np.zeros(len(u), dtype=bool)
        for k0 in range(0, len(order), SHORTCUT_CHUNK):
            idx = order[k0 : k0 + SHORTCUT_CHUNK]
            self.counts["shortcut_checks"] = self.counts.get("shortcut_checks", 0) + len(idx)
            ok[idx] = self.v.edges_valid(P1[idx], P2[idx], u[idx, 0], u[idx, 1])
            if ok[idx].any():
                break
        yield from (int(i) for i in np.flatnonzero(ok)[np.argsort(-saving[ok])][:3])

    def _timed_first(
        self, P1: np.ndarray, P2: np.ndarray, u: np.ndarray, saving: np.ndarray, bound: np.ndarray
    ) -> Iterator[int]:
        """As `_timed_chunks`, with the validator's early exit: the first valid candidate in the order of
        saving (ties: lowest index), then, when the caller asks again, the next valid one after it (at most 3);
        the candidates after the one returned are not checked until then. bound: the candidates' body-motion
        bounds (mm)."""
        order = np.argsort(-saving, kind="stable")
        pos = 0
        for _ in range(3):
            rest = order[pos:]
            k = self.v.first_valid(P1[rest], P2[rest], u[rest, 0], u[rest, 1], bound[rest])
            self.counts["shortcut_checks"] = self.counts.get("shortcut_checks", 0) + (k + 1 if k >= 0 else len(rest))
            if k < 0:
                return
            yield int(rest[k])
            pos += k + 1

    def smooth_timed(self, X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """`smooth` of a timed path; returns (path, times, smoothed?)."""
        if not self.o.smooth or len(X) < 3:
            return (*self.resample_timed(X, T), False)
        corner = self.o.corner
        for _ in range(2):
            Y, TY = self.spline_timed(X, T, corner)
            self.counts["smooth_checks"] = self.counts.get("smooth_checks", 0) + 1
            if self.v.path_valid(Y, TY):
                return Y, TY, True
            corner /= 2.0
        return (*self.resample_timed_verified(X, T), False)

    def resample_timed_verified(self, X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`resample_timed`, verified; the path as it is when its pieces are not all certified."""
        Y, TY = self.resample_timed(X, T)
        if len(Y) == len(X) or self.v.path_valid(Y, TY):
            return Y, TY
        return X, T

    def spline_timed(self, X: np.ndarray, T: np.ndarray, corner: float) -> tuple[np.ndarray, np.ndarray]:
        """The corner-rounding B-spline of `spline` through (configuration, time) jointly; samples
        at most waypoint_step mm of body motion and waypoint_step / max_speed s apart."""
        v = self.v
        XT = np.concatenate([X, T[:, None]], axis=1)
        A, D = XT[:-1], np.diff(XT, axis=0)
        L = v.motion_bound(D[:, :-1])
        c = (np.minimum(corner, L / 3.0) / np.maximum(L, 1e-300))[:, None]
        legs = np.stack([A + c * D, XT[1:] - c * D, XT[1:]], axis=1)
        P = np.concatenate([XT[:1], legs.reshape(-1, XT.shape[1])])
        k, n = 3, len(P)
        knots = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, n - k + 1), np.ones(k)])
        spl = self._curve(knots, P, k)
        uu = np.linspace(0.0, 1.0, 40 * n)
        F = spl(uu)
        dF = np.diff(F, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.maximum(v.motion_bound(dF[:, :-1]), v.max_speed * dF[:, -1]))])
        m = max(2, int(np.ceil(s[-1] / self.o.waypoint_step)) + 1)
        Y = spl(np.interp(np.linspace(0.0, s[-1], m), s, uu))
        Y[0], Y[-1] = XT[0], XT[-1]
        TY = np.maximum.accumulate(Y[:, -1])  # nondecreasing up to round-off
        return Y[:, :-1], TY

    # --------------------------------------------------------------- smoothing
    def _curve(self, knots: np.ndarray, P: np.ndarray, k: int) -> Callable[[np.ndarray], np.ndarray]:
        """The B-spline curve (`BSplineCurve`, which checks its input) as a function of its parameter: evaluated
        in the validator's compiled kernel when it has one (the same numbers, without numpy's per-step arrays)."""
        spl = BSplineCurve(knots, P, k)
        kernel = self.v.state.kernel
        if kernel is None:
            return spl
        return lambda x: kernel.bspline(spl.knots, spl.coeffs, spl.k, x)

    def smooth(self, X: np.ndarray) -> tuple[np.ndarray, bool]:
        """B-spline corner rounding, verified; returns (path, smoothed?)."""
        if not self.o.smooth or len(X) < 3:
            return self.resample(X), False
        corner = self.o.corner
        for _ in range(2):
            Y = self.spline(X, corner)
            self.counts["smooth_checks"] = self.counts.get("smooth_checks", 0) + 1
            if self.valid(Y):
                return Y, True
            corner /= 2.0
        return self.resample(X), False

    def spline(self, X: np.ndarray, corner: float) -> np.ndarray:
        """Samples (every waypoint_step mm of body motion) of the corner-rounding B-spline through X's ends."""
        v = self.v
        A, D = X[:-1], np.diff(X, axis=0)
        L = v.motion_bound(D)
        c = (np.minimum(corner, L / 3.0) / np.maximum(L, 1e-300))[:, None]
        legs = np.stack([A + c * D, X[1:] - c * D, X[1:]], axis=1)  # (legs, 3, nx)
        P = np.concatenate([X[:1], legs.reshape(-1, X.shape[1])])
        k, n = 3, len(P)
        knots = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, n - k + 1), np.ones(k)])
        spl = self._curve(knots, P, k)
        uu = np.linspace(0.0, 1.0, 40 * n)
        F = spl(uu)
        s = np.concatenate([[0.0], np.cumsum(v.motion_bound(np.diff(F, axis=0)))])
        m = max(2, int(np.ceil(s[-1] / self.o.waypoint_step)) + 1)
        Y = spl(np.interp(np.linspace(0.0, s[-1], m), s, uu))
        Y[0], Y[-1] = X[0], X[-1]  # the clamped spline meets the ends up to round-off; make it exact
        return Y

    # ------------------------------------------------------------------ result
    def result(
        self,
        *,
        status: PlanStatus,
        message: str,
        planner: str,
        seed: int | None,
        goal: np.ndarray | TipGoal,
        X: np.ndarray,
        raw: np.ndarray,
        smoothed: bool,
        cost: float,
        goal_configs: np.ndarray | None,
        tree_edges: np.ndarray,
        timings: dict[str, float],
        counts: dict[str, int],
        T: np.ndarray | None = None,
        raw_t: np.ndarray | None = None,
    ) -> PlanResult:
        """Assemble a `PlanResult` for the final path X (already verified); T, raw_t: the
        waypoint times of a timed path (default: full speed from t0). goal: the goal tip (mm), or a `TipGoal`
        (with a direction, the result records the final tip tangent's angle to it)."""
        model = self.v.model
        goal = TipGoal.of(goal)
        angle = float(goal.angles(tip_tangents(model, X[-1:]))[0]) if goal.has_direction else float("nan")
        tips = self.v.tip_position(X)
        dense = self.resample(X, self.v.resolution)
        length = float(np.sum(np.linalg.norm(np.diff(self.v.tip_position(dense), axis=0), axis=1)))
        counts = {**counts, **self.counts}
        T = self.times(X) if T is None else T
        return PlanResult(
            status=status,
            message=message,
            planner=planner,
            seed=seed,
            t=T,
            configs=X,
            tips=tips,
            cables=model.cables(X),
            length=length,
            cost=cost,
            min_clearance=self.v.path_clearance(X, T)[0],
            goal_error=float(np.linalg.norm(tips[-1] - goal.position)),
            goal_angle=angle,
            smoothed=smoothed,
            raw_configs=raw,
            raw_t=self.times(raw) if raw_t is None else raw_t,
            goal_configs=goal_configs,
            tree_edges=tree_edges,
            timings=timings,
            counts=counts,
        )


def empty_result(
    status: PlanStatus,
    message: str,
    *,
    planner: str,
    seed: int | None,
    robot: Any,
    goal_configs: np.ndarray | None = None,
    tree_edges: np.ndarray | None = None,
    timings: dict[str, float] | None = None,
    counts: dict[str, int] | None = None,
) -> PlanResult:
    """A `PlanResult` without a path (invalid start or goal, timeout)."""
    return PlanResult(
        status=status,
        message=message,
        planner=planner,
        seed=seed,
        t=np.zeros(0),
        configs=np.zeros((0, robot.nx)),
        tips=np.zeros((0, 3)),
        cables=np.zeros((0, robot.nq)),
        goal_configs=goal_configs if goal_configs is not None and len(goal_configs) else None,
        tree_edges=np.zeros((0, 2, 3)) if tree_edges is None else tree_edges,
        timings=dict(timings or {}),
        counts=dict(counts or {}),
    )


def tree_edges(model: Any, trees: list[Any], tips: list[np.ndarray] | None = None) -> np.ndarray:
    """(E, 2, 3) tip positions (mm) of every tree edge, for drawing (model: anything with `tip_position`, the
    model or a validator)."""
    parts = []
    for i, tr in enumerate(trees):
        if len(tr) < 2:
            continue
        tp = model.tip_position(tr.x) if tips is None else tips[i]
        par, child = tr.edges()
        parts.append(np.stack([tp[par], tp[child]], axis=1))
    return np.concatenate(parts) if parts else np.zeros((0, 2, 3))


def _splice(X: np.ndarray, s: np.ndarray, a: float, b: float, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, int]:
    """X with the part between arc positions a < b replaced by p1 -> p2; (path, index of p1)."""
    i = int(np.searchsorted(s, a, side="right"))  # waypoints up to a: X[:i]
    j = int(np.searchsorted(s, b, side="left"))  # waypoints from b on: X[j:]
    # p1 may repeat X[i-1] and p2 X[j]: zero-length motions are harmless and removed later
    return np.concatenate([X[:i], p1[None], p2[None], X[j:]]), i


def _at(X: np.ndarray, s: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points at arc positions u along the polyline X with cumulative arc s (non-decreasing): every coordinate
    as `np.interp` computes it (slope (X[j+1] - X[j]) / (s[j+1] - s[j]) times (u - s[j]) plus X[j], X[j] at
    u = s[j], the end points beyond the ends), in one pass for all coordinates."""
    n = len(s)
    if n < 2:
        return np.repeat(X[:1], len(u), axis=0)
    j = np.minimum(np.maximum(s.searchsorted(u, side="right") - 1, 0), n - 2)
    Xj, sj = X[j], s[j]
    den = s[j + 1] - sj
    # a zero-length piece is only ever picked for u before the start or at / beyond the end, whose rows are
    # replaced below: dividing by 1 there spares the division warnings (and numpy's error-state switch)
    den[den == 0.0] = 1.0
    out = (X[j + 1] - Xj) / den[:, None] * (u - sj)[:, None] + Xj
    at = u == sj
    out[at] = Xj[at]
    out[u >= s[-1]] = X[-1]
    out[u < s[0]] = X[0]
    return out


def dedup_timed(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop consecutive duplicate waypoints of a timed path (a wait, same configuration at a later time, stays)."""
    if len(X) < 2:
        return X, T
    moved = np.any(np.abs(np.diff(X, axis=0)) > 1e-12, axis=1) | (np.diff(T) > 1e-12)
    keep = np.concatenate([[True], moved])
    return X[keep], T[keep]


def dedup(X: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate waypoints."""
    if len(X) < 2:
        return X
    keep = np.concatenate([[True], np.any(np.abs(np.diff(X, axis=0)) > 1e-12, axis=1)])
    return X[keep]
