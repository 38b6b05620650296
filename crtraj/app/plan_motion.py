"""Library call: admit a plan made in Python for a device, as `crtraj stream` admits a result file.

`crtraj.planning.plan_executable` returns an `ExecutablePlan` in memory; a device takes only an
`AdmittedMotion` (`crtraj.hardware.admission.admit`: the plan's own verdict first, then its exact frames at
the stream rate verified against the scene at their times). `admit_plan` joins the two without a result file.
"""

from __future__ import annotations

import math

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion, MotionRecord, admit
from crtraj.planning.context import PlanningContext
from crtraj.planning.pipeline import STREAM_RATE, ExecutablePlan
from crtraj.world.scene import Scene


def admit_plan(
    plan: ExecutablePlan,
    context: PlanningContext,
    *,
    scene: Scene | None = None,
    actuators: Actuators | None = None,
    time_scale: float = 1.0,
    rate: float = STREAM_RATE,
) -> AdmittedMotion:
    """The plan's motion admitted for a device (one-line `AdmissionError` when it may not drive one).

    context: the `PlanningContext` the plan was made with (its robot and, unless `scene` is given, its
    scene). actuators: the device's (default: the robot file's ``[robot.actuators]``). time_scale: play the
    motion this many times slower. rate: the stream rate (Hz) its frames are verified at; give the
    `StreamOptions.rate` the `Streamer` will use.
    """
    robot = context.robot
    if actuators is None:
        if robot.actuators is None:
            raise InputError(f"robot {robot.name!r}: robot.actuators: missing; add a [robot.actuators] table")
        actuators = Actuators.from_robot(robot)
    r = plan.result
    too_close = math.isfinite(r.min_clearance) and r.min_clearance < 0.0  # a plan inside D_sf is never sent
    record = MotionRecord(
        source=f"plan ({r.planner})",
        kind="plan",
        status=str(r.status),
        success=r.is_success(),
        safety=True,
        collisions=0,
        safety_violations=int(too_close),
        robot=robot,
        scene=context.scene if scene is None else scene,
        t=r.t,
        q=r.cables,
    )
    return admit(record, actuators, robot=robot, time_scale=time_scale, rate=rate)
