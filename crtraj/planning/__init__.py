"""Planners, their query/result/stop types, state and motion validity, steer and safe IK. Above: world.

Start here: `PlanningContext` (everything a planner is built from) and `plan_executable` (plan,
smooth, retime within the actuator limits, verify).
"""

from crtraj.planning.context import PlanningContext
from crtraj.planning.pipeline import ExecutablePlan, plan_executable

__all__ = ["ExecutablePlan", "PlanningContext", "plan_executable"]
