"""`crtraj replan --plant cosserat`: the closed loop (planning with PCC) driving a simulated Cosserat rod.

`make_plant` builds the plant of a problem (`crtraj.control.rod_plant.RodPlant`, the robot file's
``[robot.mechanics]``), `attach_plant` hands it the loop's servo model and start, and `plant_lines` are
the summary lines: the plant's figures by the rod's shape beside PCC's own view. Units: mm, N, s.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.control.loop import ClosedLoop, ReplanRun
from crtraj.control.rod_plant import RodPlant
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.mocap import check_true_robot
from crtraj.io.problem import Problem
from crtraj.model.cosserat import RodDrive
from crtraj.model.robot import Robot
from crtraj.world.scene import Scene

# --plant choices: the rod with the robot file's gravity, or weightless
PLANTS = ("cosserat", "cosserat-weightless")
# mm per axis of the plant's tip readings: the paper's motion capture (as `SimulatedMocap`)
TIP_NOISE = 0.3
# N in every tendon at the straight pose
PRETENSION = 1.0


def make_plant(
    name: str, problem: Problem, true_robot: Robot | None = None, *, tip_noise: float = TIP_NOISE
) -> RodPlant:
    """The `RodPlant` of `problem` for --plant `name`; true_robot: the plant's robot file when it is not
    the problem's (--true-robot; e.g. the problem plans with a calibrated file): the loop's actuation
    becomes servo values through the problem robot's actuators and back through the true robot's.
    `InputError` (one line) for an unknown name or a robot file without ``[robot.mechanics]``."""
    if name not in PLANTS:
        raise InputError(f"--plant: unknown plant {name!r} (choose from {', '.join(PLANTS)})")
    robot = problem.robot if true_robot is None else true_robot
    if robot.mechanics is None:
        flag = "" if true_robot is None else " --true-robot"
        raise InputError(f"--plant {name}:{flag} robot {robot.name!r} has no [robot.mechanics] table (the rod)")
    to_plant = None
    if true_robot is not None:
        if problem.robot.actuators is None or true_robot.actuators is None:
            raise InputError("--true-robot: both robot files need [robot.actuators] to pass servo values between them")
        sent, true_act = Actuators.from_robot(problem.robot), Actuators.from_robot(true_robot)
        check_true_robot(true_robot, true_act, sent)

        def to_plant(q: np.ndarray) -> np.ndarray:
            return true_act.actuation(sent.command(q)).reshape(-1)

    drive = RodDrive(robot, pretension=PRETENSION, gravity=name == "cosserat")
    scene = Scene.from_table(problem.section("scene"))
    task = problem.require_task()
    return RodPlant(drive, scene, task.goal, tip_noise=tip_noise, seed=problem.seed, to_plant=to_plant)


def attach_plant(plant: RodPlant, loop: ClosedLoop) -> None:
    """Give the plant the loop's servo model, start actuation and control period."""
    q0 = loop.start_command()
    plant.attach(loop.servo, q0, loop.n_sub, loop.options.dt / loop.n_sub, loop.rate_limits)


def plant_lines(plant: RodPlant, run: ReplanRun) -> list[str]:
    """The plant's summary line and PCC's own view of the same run."""
    s = run.summary()
    pcc = (
        f"PCC's own view: final tip error {s['final_tip_error_mm']:.2f} mm, min clearance "
        f"{s['min_clearance_mm']:.2f} mm, collisions {s['collisions']} (D_sf breaches {s['safety_violations']})"
    )
    return [plant.summary_line(), pcc]


def plant_verdict(plant: RodPlant) -> str:
    """Why the run fails by the plant's shape ('' when the rod kept D_sf and every solve converged)."""
    d: dict[str, Any] = plant.describe()
    if d["failure"]:
        return d["failure"]
    if d["safety_violations"]:
        return (
            f"unsafe by the plant's shape: {d['safety_violations']} control periods closer than D_sf, "
            f"{d['collisions']} touching an obstacle"
        )
    return ""
