"""The checked inputs and clock of one planning query, shared by every planner."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.planning.goal import TipGoal
from crtraj.planning.stop import StopCondition


@dataclass(frozen=True)
class PlanQuery:
    """One query: goal tip (mm), start time t0 (s), stop condition and its running clock,
    absolute deadline (perf_counter s, inf without a time limit), the seeded generator and the goal
    with its tip direction cone, if any (`tip_goal.position` is `goal`)."""

    goal: np.ndarray
    t0: float
    stop: StopCondition
    clock: Any
    deadline: float
    rng: np.random.Generator
    tip_goal: TipGoal

    @classmethod
    def begin(
        cls,
        default_stop: StopCondition,
        goal: Any,
        *,
        t0: Any,
        goal_tolerance: float,
        start_config: Any,
        start_tip: Any,
        stop: StopCondition | None,
        seed: int | None,
    ) -> PlanQuery:
        """Validate a query's arguments (one-line `InputError`s) and start its clock."""
        tip_goal = goal if isinstance(goal, TipGoal) else TipGoal(check_array(goal, "goal", (3,)))
        goal = tip_goal.position
        t0 = float(check_array(t0, "t0", ()))
        if not goal_tolerance > 0:
            raise InputError(f"goal_tolerance: must be > 0 mm, got {goal_tolerance}")
        if (start_config is None) == (start_tip is None):
            raise InputError("start: give exactly one of start_config or start_tip")
        stop = default_stop if stop is None else stop
        stop.check_bounded()
        clock = stop.start()
        deadline = clock.t_start + (stop.time_limit if stop.time_limit is not None else np.inf)
        return cls(goal, t0, stop, clock, deadline, np.random.default_rng(seed), tip_goal)
