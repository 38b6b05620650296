"""The planners and their registry: the configuration-space planner (RRT-Connect), the paper's RRT and RRT*
(Algorithm 1), OMPL's planners, and the search trees and nearest-neighbour index they grow.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.planners._ompl": (
            "OMPLPlanner",
            "import_ompl",
        ),
        "crtraj.planning.planners._registry": (
            "BUILTIN",
            "PlannerRegistry",
            "PlannerSpec",
            "make_planner",
        ),
        "crtraj.planning.planners._rrt": ("RRT",),
    },
)
