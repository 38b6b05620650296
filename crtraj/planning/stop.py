"""When a planner stops: wall time, iterations, first solution, combinable.

Like OMPL's ``PlannerTerminationCondition``: a `StopCondition` is a frozen
description; `StopCondition.start()` returns a `StopClock` that a planner polls
once per iteration. Conditions combine with ``|`` (stop when either fires):

    StopCondition(time_limit=0.5) | StopCondition(max_iterations=2000)

A condition with no limit at all never stops a planner by itself, so
planners refuse it (`StopCondition.check_bounded`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from crtraj.core.errors import InputError


@dataclass(frozen=True)
class StopCondition:
    """Stop a planner after `time_limit` seconds of wall time, after
    `max_iterations` iterations, or as soon as a first exact solution exists
    (`first_solution`). Any limit left None is not checked. cpu_time: the
    time limit counts this process's CPU time instead (a benchmark on a shared
    machine: the budget then does not shrink with the load); planners that
    hand a wall-clock deadline to a library (OMPL, IK stages) still use wall time there."""

    time_limit: float | None = None
    max_iterations: int | None = None
    first_solution: bool = False
    cpu_time: bool = False

    def __post_init__(self) -> None:
        if self.time_limit is not None and not (math.isfinite(self.time_limit) and self.time_limit > 0):
            raise InputError(f"time_limit: must be a finite number > 0 (s), got {self.time_limit}")
        if self.max_iterations is not None and (
            isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) or self.max_iterations < 1
        ):
            raise InputError(f"max_iterations: must be an integer >= 1, got {self.max_iterations!r}")

    def __or__(self, other: StopCondition) -> StopCondition:
        """Stop when either condition fires (the tighter of each limit)."""

        def tighter(a: float | None, b: float | None) -> float | None:
            if a is None:
                return b
            if b is None:
                return a
            return min(a, b)

        return StopCondition(
            time_limit=tighter(self.time_limit, other.time_limit),
            max_iterations=tighter(self.max_iterations, other.max_iterations),  # type: ignore[arg-type]
            first_solution=self.first_solution or other.first_solution,
            cpu_time=self.cpu_time or other.cpu_time,
        )

    @property
    def bounded(self) -> bool:
        """True when at least the time or the iteration count is limited."""
        return self.time_limit is not None or self.max_iterations is not None

    def check_bounded(self) -> None:
        """Raise `InputError` when nothing but a first solution would stop a planner."""
        if not self.bounded:
            raise InputError("stop: set time_limit or max_iterations; a planner could otherwise run forever")

    def start(self) -> StopClock:
        """Begin timing now."""
        return StopClock(self, time.perf_counter())

    def to_dict(self) -> dict[str, object]:
        return {
            "time_limit": self.time_limit,
            "max_iterations": self.max_iterations,
            "first_solution": self.first_solution,
            "cpu_time": self.cpu_time,
        }


class StopClock:
    """A running `StopCondition`: counts iterations, measures wall time (s)."""

    def __init__(self, cond: StopCondition, t_start: float) -> None:
        self.cond = cond
        self.t_start = t_start
        # the budget's clock: CPU time of this process when cond.cpu_time, else the wall clock
        self._clock = time.process_time if cond.cpu_time else time.perf_counter
        self._budget_start = self._clock() if cond.cpu_time else t_start
        self.iterations = 0
        self.reason = ""

    def elapsed(self) -> float:
        """Time since `start` (s) on the budget's clock (wall time, or CPU time with cond.cpu_time)."""
        return self._clock() - self._budget_start

    def tick(self) -> None:
        """Count one planner iteration."""
        self.iterations += 1

    def should_stop(self, solved: bool = False) -> bool:
        """True when a limit is reached; records which one in `reason`."""
        c = self.cond
        if c.first_solution and solved:
            self.reason = "first solution"
        elif c.max_iterations is not None and self.iterations >= c.max_iterations:
            self.reason = f"iteration limit ({c.max_iterations})"
        elif c.time_limit is not None and self.elapsed() >= c.time_limit:
            self.reason = f"time limit ({c.time_limit:g} s)"
        else:
            return False
        return True

    def time_left(self) -> float:
        """Seconds until the time limit (inf without one)."""
        if self.cond.time_limit is None:
            return math.inf
        return self.cond.time_limit - self.elapsed()
