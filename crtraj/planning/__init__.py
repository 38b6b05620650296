"""Planners, their query/result/stop types, state and motion validity, steer and safe IK. Above: world.

Start here: `PlanningContext` (everything a planner is built from) and `plan_executable` (plan,
smooth, retime within the actuator limits, verify). Public names load on first use
(`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.context": ("PlanningContext",),
        "crtraj.planning.pipeline": ("ExecutablePlan", "plan_executable", "retime_result"),
        "crtraj.planning.options": ("PlannerOptions", "IKOptions", "CheckOptions", "CSpaceOptions", "RRTOptions"),
        "crtraj.planning.steer": ("SteerOptions",),
        "crtraj.planning.stop": ("StopCondition",),
        "crtraj.planning.result": ("PlanResult", "PlanStatus"),
        "crtraj.planning.base": ("Planner",),
        "crtraj.planning.planners": (
            "BUILTIN",
            "PlannerRegistry",
            "PlannerSpec",
            "make_planner",
        ),
    },
)
