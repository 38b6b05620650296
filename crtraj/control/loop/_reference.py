"""Reference paths of the closed loop: where the robot should go, and how fast.

A reference source ((configuration, time, obstacles) -> `ReferencePlan`) gives a path toward the goal:
`DirectReference` (the straight motion to a known goal configuration) or `PlannerReference` (crtraj's
planner from the current configuration). `TimedReference` times a path by the rate limits and tracks
the robot's progress along it by projection. Units: mm, rad, s.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.core.fields import check_array
from crtraj.planning.goal import TipGoal
from crtraj.planning.result import PlanStatus


@dataclass(frozen=True)
class ReferencePlan:
    """A reference path toward the goal, or why there is none.

    configs: (K, nx) configurations, straight motions in between (empty
    when the planner found nothing). status, message: the planner's (a
    direct reference is an exact "plan"). wall_time: s. tree_edges: (E, 2, 3)
    tip positions for drawing.
    """

    configs: np.ndarray
    status: PlanStatus
    message: str
    wall_time: float
    tree_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))

    def is_success(self) -> bool:
        """There is a path to follow (the planner reached the goal)."""
        return self.status is PlanStatus.EXACT and len(self.configs) >= 1


# (configuration (nx,), time s, the obstacles as known at that time: a Scene) -> ReferencePlan
ReferenceSource = Callable[[np.ndarray, float, Any], ReferencePlan]


class DirectReference:
    """Reference source without search: the straight motion to one known goal configuration (nx)."""

    def __init__(self, goal_config: Any) -> None:
        self.goal_config = np.array(check_array(goal_config, "goal_config", (None,)), dtype=float)

    def __call__(self, x: np.ndarray, t: float, scene: Any = None) -> ReferencePlan:
        X = np.stack([np.asarray(x, float), self.goal_config])
        return ReferencePlan(X, PlanStatus.EXACT, "direct: straight line", 0.0)


class PlannerReference:
    """Reference source backed by crtraj's planner: plans from the current configuration at time t.

    planner: a planner with ``plan(goal, start_config=, t0=, stop=, seed=, scene=, goal_tolerance=)``
    (`crtraj.planning.planners.make_planner`). goal: tip (mm), or a `crtraj.planning.goal.TipGoal` whose
    direction cone every plan's goal configuration keeps (a planner that honours it). stop: a bounded
    `crtraj.planning.stop.StopCondition` per plan. seed: base seed; each call uses the
    next one so runs reproduce exactly. scene: always plan among these
    obstacles (e.g. none, for a run without the collision-free terms);
    default: the obstacles the loop passes with each call.
    """

    def __init__(
        self,
        planner: Any,
        goal: Any,
        *,
        goal_tolerance: float,
        stop: Any,
        seed: int = 0,
        scene: Any = None,
    ) -> None:
        stop.check_bounded()
        self.planner = planner
        self.tip_goal = TipGoal.of(goal)
        self.goal = self.tip_goal.position
        self.goal_tolerance = float(goal_tolerance)
        self.stop = stop
        self.seed = int(seed)
        self.scene = scene
        self.calls = 0

    def retarget(self, goal: Any) -> None:
        """Plan toward another tip goal (mm) from the next call on: the closed loop's tip feedback aims the
        model's tip where the measured tip reaches the task's goal."""
        self.goal = check_array(goal, "goal", (3,))

    def __call__(self, x: np.ndarray, t: float, scene: Any = None) -> ReferencePlan:
        t1 = time.perf_counter()
        goal = self.goal if self.tip_goal.direction is None else replace(self.tip_goal, position=self.goal)
        res = self.planner.plan(
            goal,
            start_config=np.asarray(x, float),
            t0=float(t),
            stop=self.stop,
            seed=self.seed + self.calls,
            scene=self.scene if self.scene is not None else scene,
            goal_tolerance=self.goal_tolerance,
        )
        self.calls += 1
        configs = res.configs if res.is_success() else np.zeros((0, len(x)))
        return ReferencePlan(configs, res.status, res.message, time.perf_counter() - t1, res.tree_edges)


class TimedReference:
    """A reference path (configurations) timed by the rate limits; progress is tracked by projection,
    not by the clock."""

    def __init__(self, configs: np.ndarray, seconds_per: Callable[[np.ndarray], np.ndarray], metric: Any) -> None:
        X = np.asarray(configs, dtype=float)
        if len(X) == 1:
            X = np.concatenate([X, X])
        self.X = X
        self.s = np.concatenate([[0.0], np.cumsum(seconds_per(np.diff(X, axis=0)))])
        self.end = float(self.s[-1])
        self.Y = metric(X)  # body-motion units (mm) for projections
        self._metric = metric
        # per segment, computed once (the loop asks every step): its time span, configuration change,
        # metric change and the projection's denominator
        self._ds = self.s[1:] - self.s[:-1]
        self._dX = X[1:] - X[:-1]
        dY = self.Y[1:] - self.Y[:-1]
        self._dY = dY
        self._den = np.maximum((dY * dY).sum(axis=1), 1e-300)
        self._s_start, self._s_end = self.s[:-1].copy(), self.s[1:].copy()  # each segment's first and last time

    def at(self, s: np.ndarray) -> np.ndarray:
        """Configurations at path times s (s), clamped to the path."""
        # np.clip's numbers (maximum, then minimum) without its wrapper's cost (the loop asks every step)
        s = np.minimum(np.maximum(np.asarray(s, dtype=float), 0.0), self.end)
        if self.end == 0.0:
            return np.broadcast_to(self.X[-1], (*s.shape, self.X.shape[1])).copy()
        # s >= 0 = self.s[0] here, so the segment index is >= 0 already; only its top needs a cap
        i = np.minimum(self.s.searchsorted(s, side="right") - 1, len(self.X) - 2)
        seg = self._ds[i]
        u = np.divide(s - self.s[i], seg, out=np.zeros_like(s), where=seg > 0)
        return self.X[i] + u[..., None] * self._dX[i]

    def locate(self, x: np.ndarray, s_hint: float, back: float, ahead: float) -> float:
        """Path time of the point nearest to x (body-motion metric) within [s_hint - back, s_hint + ahead]."""
        if self.end == 0.0:
            return 0.0
        y = self._metric(np.asarray(x, dtype=float)[None])[0]
        lo, hi = s_hint - back, s_hint + ahead
        # the segments with s[i+1] >= lo and s[i] <= hi: s never decreases, so they are one run a..b-1, found by
        # bisection and taken as views (the same rows as a mask over the whole path, without its cost per step)
        a = int(self._s_end.searchsorted(lo, side="left"))
        b = int(self._s_start.searchsorted(hi, side="right"))
        if a >= b:
            a, b = 0, len(self.X) - 1
        A, AB = self.Y[a:b], self._dY[a:b]
        u = np.minimum(np.maximum(((y - A) * AB).sum(axis=1) / self._den[a:b], 0.0), 1.0)
        w = A + u[:, None] * AB - y
        # the distance as np.linalg.norm computes it (ties in argmin stay the same)
        d = np.sqrt((w * w).sum(axis=1))
        j = int(d.argmin())
        i = a + j
        return min(max(float(self.s[i] + u[j] * self._ds[i]), lo), hi)
