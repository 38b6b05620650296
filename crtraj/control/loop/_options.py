"""The ``[loop]`` problem section: options of the closed loop (`crtraj.control.loop.ClosedLoop`).

The horizon NLP's own options stay in ``[replan]`` (`crtraj.control.horizon.ReplanOptions`).
Units: mm, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME
from crtraj.core.options import Options, option

# Most closed-loop steps of one run (duration / replan.dt): each is one NLP solve.
MAX_STEPS = 100_000


@dataclass(frozen=True)
class LoopOptions(Options):
    """The ``[loop]`` problem section (units mm, s).

    duration (s of simulated time at most), replan_period (s between
    periodic reference replans; 0 = only when needed), planner_time (s
    budget of one reference plan), stall_time (s without progress before
    the reference is replanned), reference_speed (fraction of the rate
    limits and of max_body_speed the reference is timed with),
    max_body_speed (mm/s, fastest body point motion the reference asks for,
    measured by `crtraj.planning.validity.MotionValidator.motion_bound`),
    check_resolution (mm of body motion between verification samples),
    check_points (backbone points of the verification), settle_time (s the
    tip must stay within the goal tolerance before the run ends),
    reference_delay (s from asking the reference planner for a path to using
    it; 0 = plan inside the control step, which waits for the planner and is
    charged its time; > 0 = plan in a worker process beside the loop
    (`crtraj.control.loop._reference_worker`), the path taken over at the first
    step at least this long after the request, while the steps in between
    go on with the reference they have).
    """

    SECTION: ClassVar[str] = "loop"

    duration: float = option(60.0, gt=0.0, le=MAX_TIME)
    replan_period: float = option(0.0, ge=0.0, le=MAX_TIME)
    planner_time: float = option(1.0, gt=0.0, le=3600.0)
    stall_time: float = option(3.0, gt=0.0, le=MAX_TIME)
    reference_speed: float = option(0.7, gt=0.0, le=1.0)
    max_body_speed: float = option(50.0, gt=0.0)
    check_resolution: float = option(1.0, ge=0.01, le=MAX_LENGTH)
    check_points: int = option(21, ge=2, le=1000)
    settle_time: float = option(0.5, ge=0.0, le=MAX_TIME)
    reference_delay: float = option(0.0, ge=0.0, le=60.0)

    def handover_steps(self, dt: float) -> int:
        """Steps of dt s from a reference request to the step that takes its path over (>= 1), or 0 when
        references are planned inside the control step (reference_delay = 0)."""
        if self.reference_delay == 0.0:
            return 0
        return max(1, math.ceil(self.reference_delay / dt - 1e-9))

    def steps(self, dt: float) -> int:
        """Control steps of a full run with steps of dt s (the replanner's); `InputError` above MAX_STEPS,
        so a huge run is refused before any work."""
        n = math.ceil(self.duration / dt - 1e-9)
        if n > MAX_STEPS:
            raise InputError(
                f"loop.duration: {self.duration:g} s is {n} steps of replan.dt {dt:g} s, more than {MAX_STEPS}; "
                "shorten it or raise dt"
            )
        return n
