"""The planner interface: the `Planner` protocol and the one query prologue every planner shares.

Every planner (configuration-space, task-space RRT/RRT*, the OMPL adapter)
answers the same call::

    plan(goal, *, start_config=None, start_tip=None, t0=0.0, stop=None,
         seed=None, scene=None, goal_tolerance=1.0) -> PlanResult

(goal tip and tolerance in mm, t0 in s; `PlanResult.is_success()` tells an
exact solution). The goal may be a `crtraj.planning.goal.TipGoal` with a tip
direction cone; a planner whose `honours_direction` is False refuses a goal
with a direction (one-line `InputError`). Every planner is built from a
`PlanningContext` (`crtraj.planning.context`). `PlannerBase` holds what they all do before
they search: check the query (`PlanQuery.begin`), pick the validator of the
query's scene, grow the NLPs' obstacle slots, and resolve the start
configuration (given, or safe IK for a start tip), timed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.context import PlanningContext
from crtraj.planning.ik import SafeIK, resolve_start
from crtraj.planning.options import PlannerOptions
from crtraj.planning.postprocess import empty_result
from crtraj.planning.query import PlanQuery
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator


@runtime_checkable
class Planner(Protocol):
    """What every planner offers: a name and one `plan` call (see the module docstring)."""

    name: str

    def plan(
        self,
        goal: Any,
        *,
        start_config: Any = None,
        start_tip: Any = None,
        t0: float = 0.0,
        stop: StopCondition | None = None,
        seed: int | None = None,
        scene: Any = None,
        goal_tolerance: float = 1.0,
    ) -> PlanResult: ...


@dataclass
class QueryStart:
    """A checked query with its validator and start configuration (None: invalid start, see `why`).

    timings (s) and counts collect the run's figures from here on.
    """

    query: PlanQuery
    validator: MotionValidator
    x_start: np.ndarray | None
    why: str
    goal_tolerance: float
    seed: int | None
    samples0: int  # the validator's sample count when the query began (for the run's statistics)
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def fail(
        self,
        status: PlanStatus,
        message: str,
        *,
        planner: str,
        robot: Any,
        tree_edges: np.ndarray | None = None,
        goal_configs: np.ndarray | None = None,
    ) -> PlanResult:
        """A result without a path, with the run's timings and counts."""
        clock = self.query.clock
        self.counts.setdefault("iterations", clock.iterations)
        self.timings["total"] = time.perf_counter() - clock.t_start
        return empty_result(
            status,
            message,
            planner=planner,
            seed=self.seed,
            robot=robot,
            goal_configs=goal_configs,
            tree_edges=tree_edges,
            timings=self.timings,
            counts=self.counts,
        )


class PlannerBase:
    """Shared construction and query prologue of crtraj's planners (subclasses set `name`).

    context: the `PlanningContext` (model, default scene, options, validity, rate limits and
    kernels); with rate limits every motion is timed within `options.limit_fraction` of them.
    """

    name: str = ""  # a class attribute of each planner (OMPL's: per instance, by algorithm)
    # the planner keeps a goal's tip direction cone (`crtraj.planning.goal.TipGoal`); others refuse such a goal
    honours_direction: bool = False

    def __init__(self, context: PlanningContext) -> None:
        self.context = context
        self.model: Model = context.model
        self.robot = context.model.robot
        self.scene = context.scene
        self.options: PlannerOptions = context.options
        self.rate_limits: RateLimits | None = context.rate_limits
        self.validator: MotionValidator = context.validator
        self.ik: SafeIK  # set by the subclass (its obstacle slots)

    def _prepare(self, validator: MotionValidator) -> None:
        """Before the start is resolved: grow the NLPs to the scene's obstacles, reset warm starts."""

    def _begin(
        self,
        goal: Any,
        *,
        start_config: Any,
        start_tip: Any,
        t0: Any,
        stop: StopCondition | None,
        seed: int | None,
        scene: Any,
        goal_tolerance: float,
        counts: dict[str, int] | None = None,
    ) -> QueryStart:
        """Check the query, pick its validator and resolve the start (one-line `InputError`s)."""
        o = self.options
        query = PlanQuery.begin(
            o.stop(),
            goal,
            t0=t0,
            goal_tolerance=goal_tolerance,
            start_config=start_config,
            start_tip=start_tip,
            stop=stop,
            seed=seed,
        )
        if query.tip_goal.has_direction and not self.honours_direction:
            raise InputError(
                f"goal_direction: the {self.name} planner does not honour a tip direction goal; "
                'plan with [planner] algorithm = "cspace"'
            )
        v = self.context.validity_for(scene)
        self._prepare(v)
        start = QueryStart(query, v, None, "", goal_tolerance, seed, v.n_samples, counts=dict(counts or {}))
        t1 = time.perf_counter()
        xs, why, n_ik = resolve_start(
            self.ik,
            v,
            start_config=start_config,
            start_tip=start_tip,
            t0=query.t0,
            rng=query.rng,
            seeds=o.ik.seeds,
            iterations=o.ik.iterations,
            deadline=query.deadline,
            tip_tolerance=min(1e-3, goal_tolerance),
            max_nlp=o.ik.nlp_solves,
        )
        start.timings["start_ik"] = time.perf_counter() - t1
        start.counts["ik_solves_start"] = n_ik
        start.x_start, start.why = xs, why
        return start
