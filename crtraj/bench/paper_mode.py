"""The paper's Table I in its own terms: RRT and RRT* planning with the paper's check, on the paper's scenes.

Planners ``rrt-paper`` and ``rrtstar-paper`` are the registry's ``rrt`` and
``rrtstar`` built with ``[planner.check] mode = "paper"``
(`crtraj.planning.validity._paper_check`: the robot's ten collision points at the ends
of 1-s time steps only), not a fork of the planner. Every run of every
planner is judged twice (`crtraj.bench.runner.judge`): by the paper's check
(`crtraj.bench.check.paper_check`) and by the strict dense check; the report
counts the paper-mode successes the strict check rejects.

`PAPER_SCENES` are the scenario generator's bounds as the paper states them
(sec. IV-B): A ~ U[30, 50] mm, B ~ U[10, 20] mm, radius A + B sin(t); linear
motion over L ~ U[50, 100] mm shaped by sin or cos, with a mean speed "under
15 mm/s" -- U(0, 15) here, where the generator's default draws U[5, 15). The
remaining choices (where the motion sits between start and goal, the screens
that keep a query solvable) are the generator's; the paper does not state
them. Both modes run on these same scenes, so the rejection count compares
like with like.
"""

from __future__ import annotations

from functools import partial

from crtraj.bench.scenarios import ScenarioOptions
from crtraj.planning.base import Planner
from crtraj.planning.context import PlanningContext
from crtraj.planning.planners import BUILTIN, PlannerSpec
from crtraj.planning.steer import SteerOptions

# The lowest mean speed drawn (mm/s): the paper gives only the upper bound; a floor keeps the motion's
# duration L / v finite (at most 100 mm / 0.01 mm/s = 1e4 s, within the obstacle's bounds).
_MIN_SPEED = 0.01

PAPER_SCENES = ScenarioOptions(mean_speed=(_MIN_SPEED, 15.0))


def _paper(
    name: str, context: PlanningContext, *, steer_options: SteerOptions | None = None, max_obstacles: int | None = None
) -> Planner:
    # task-space edges keep full-speed timing (as the registry's rrt and rrtstar)
    paper = context.with_options(context.options.with_(check={"mode": "paper"}))
    return BUILTIN.create(name, paper, steer_options, max_obstacles=max_obstacles)


PAPER_SPECS = (
    PlannerSpec("rrt-paper", partial(_paper, "rrt"), description="RRT (Alg. 1), paper check"),
    PlannerSpec("rrtstar-paper", partial(_paper, "rrtstar"), description="RRT* (Alg. 1), paper check"),
)
# The planner's own motion check, by bench planner name (others: "strict").
CHECK_MODES = {s.name: "paper" for s in PAPER_SPECS}
# The two modes' tables: the paper mode's rows, and the strict mode's rows they compare with.
PAPER_ROWS = ("rrt-paper", "rrtstar-paper", "cspace", "ompl-rrtstar", "ompl-rrtconnect")
STRICT_ROWS = ("rrt", "rrtstar", "cspace", "ompl-rrtstar", "ompl-rrtconnect")
