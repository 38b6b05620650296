"""Use case: plan a problem file's task and write the result document (`crtraj plan`)."""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj import __version__
from crtraj.core.fileio import atomic_write_json, to_jsonable
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.hardware.stream import StreamOptions
from crtraj.model.kinematics import Model
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.rate_limits import RateLimits
from crtraj.planning.registry import make_planner
from crtraj.planning.result import PlanResult
from crtraj.planning.retime import retime
from crtraj.planning.steer import SteerOptions
from crtraj.planning.validity import MotionValidator
from crtraj.world.scene import Scene


@dataclass(frozen=True)
class ProblemPlan:
    """One planning run of a problem file: the inputs, the result and the setup time (s)."""

    problem: Any
    model: Model
    scene: Any
    options: PlannerOptions
    steer_options: SteerOptions | None
    result: PlanResult
    setup_time: float
    timing: dict[str, Any] | None = None  # how the result was timed (`retime_result`)

    def document(self) -> dict[str, Any]:
        """The self-describing result file (kind "plan"; schema in the README), as plain JSON data."""
        p, r, model, scene = self.problem, self.result, self.model, self.scene
        waypoints = []
        if len(r.t):
            backbone = model.points(r.configs)
            centers, radii = scene.states(r.t)
            for k in range(len(r.t)):
                waypoints.append(
                    {
                        "t": float(r.t[k]),
                        "tip": r.tips[k],
                        "x": r.configs[k],
                        "q": r.cables[k],
                        "backbone": backbone[k],
                        "obstacles": {"centers": centers[k].reshape(-1, 3), "radii": radii[k].reshape(-1)},
                    }
                )
        options: dict[str, Any] = {"planner": self.options.to_dict()}
        if self.steer_options is not None:
            options["steer"] = self.steer_options.to_dict()
        doc: dict[str, Any] = {
            "kind": "plan",
            "crtraj_version": __version__,
            "casadi_version": ca.__version__,
            "numpy_version": np.__version__,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "problem": {"name": p.name, "path": None if p.path is None else str(p.path), "seed": r.seed},
            "robot": model.robot.to_dict(),
            "scene": scene.to_dict(),
            "task": p.require_task().to_dict(),
            "options": options,
            "status": str(r.status),
            "success": r.is_success(),
            "message": r.message,
            "timing": {**{f"{k}_s": v for k, v in r.timings.items()}, "setup_s": self.setup_time},
            "summary": {**r.summary(), **_executed(self.timing)},
            "retime": self.timing,
            "waypoints": waypoints,
            "tree": {"edges": r.tree_edges},
        }
        if r.raw_configs is not None and len(r.raw_configs):
            doc["raw_path"] = {"t": r.raw_t, "x": r.raw_configs, "tip": model.tip_position(r.raw_configs)}
        if r.goal_configs is not None and len(r.goal_configs):
            doc["goal_configs"] = r.goal_configs
        return to_jsonable(doc)

    def write(self, path: str | Path) -> Path:
        """Write `document()` as JSON, atomically."""
        return atomic_write_json(path, self.document())


def plan_problem(
    problem: Any,
    *,
    algorithm: str | None = None,
    seed: int | None = None,
    time_limit: float | None = None,
    model: Model | None = None,
) -> ProblemPlan:
    """Plan a problem file's task with its ``[scene]``, ``[planner]`` and ``[steer]`` sections.

    algorithm, seed, time_limit (s) override the file. The start is
    ``task.start_config`` when given, else a safe IK solution for ``task.start``.
    """
    task = problem.require_task()
    t1 = time.perf_counter()
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    changes: dict[str, Any] = {}
    if algorithm is not None:
        changes["algorithm"] = algorithm
    if time_limit is not None:
        changes["time_limit"] = float(time_limit)
    if changes:
        options = options.with_(**changes)
    steer_options = problem.options(SteerOptions, "steer")
    model = Model(problem.robot) if model is None else model
    actuators = Actuators.from_robot(problem.robot) if problem.robot.actuators is not None else None
    limits = None if actuators is None else actuators.rate_limits(problem.robot)
    planner = make_planner(model, scene, options, steer_options, rate_limits=limits)
    setup = time.perf_counter() - t1
    seed = problem.seed if seed is None else int(seed)
    start = {"start_config": task.start_config} if task.start_config is not None else {"start_tip": task.start}
    result = planner.plan(task.goal, seed=seed, goal_tolerance=task.goal_tolerance, **start)
    used_steer = getattr(planner, "steer_options", None)
    timing = None
    if actuators is not None and limits is not None:
        validator = getattr(planner, "validator", None) or options.validator(model, scene)
        rate = problem.options(StreamOptions, "stream").rate
        result, timing = retime_result(result, validator, options, actuators, limits, rate)
    return ProblemPlan(problem, model, scene, options, used_steer, result, setup, timing)


# Over 60 lines only by its docstring and the three outcomes, which read best in one place.
def retime_result(
    result: PlanResult,
    validator: MotionValidator,
    options: PlannerOptions,
    actuators: Actuators,
    limits: RateLimits,
    rate: float,
) -> tuple[PlanResult, dict[str, Any]]:
    """The result timed within `options.limit_fraction` of the actuator limits and max_speed.

    The verified geometry (the result's waypoints joined by straight motions) is kept exactly;
    its time-optimal law (`crtraj.planning.retime`) is sampled every 1/rate s (the stream rate)
    into the new waypoints, so a streamer sampling at that rate sends exactly them. Static scene:
    that law. Moving obstacles: the law is re-verified at its own times with the planner's
    validator; if it fails, the law that never runs a straight motion faster than the planner's
    verified timing is tried (verified too); if that fails as well, the planner's verified timing
    is kept (and the fractions below show by how much it exceeds the limits). Returns the result
    and a report: method, outcome, durations (s) and the largest velocity and acceleration as
    fractions of the full limits, measured as the streamer samples the motion.
    """
    before = result.duration
    info: dict[str, Any] = {"method": "closed-form rest-to-rest per straight motion", "rate_hz": rate}
    info["limit_fraction"] = options.limit_fraction
    if not result.has_path or len(result.t) < 2:
        return result, {**info, "outcome": "no motion", **_fractions(result, actuators, rate)}
    usable = limits.scaled(options.limit_fraction)
    metric = BodyMetric(validator.robot, options.max_speed)
    X, t0, period = result.configs, float(result.t[0]), 1.0 / rate
    candidates = [("retimed", None)]
    if not validator.static:
        candidates.append(("retimed, no faster than verified", np.diff(result.t)))
    out, outcome = result, "kept the verified timing (the retimed motion failed its collision check)"
    for name, floor in candidates:
        stamps, Y = retime(X, usable, metric, t0=t0, period=period, at_least=floor).sample()
        if validator.static or validator.path_valid(Y, stamps):
            model = validator.model
            clearance = result.min_clearance if validator.static else validator.path_clearance(Y, stamps)[0]
            out = replace(
                result,
                t=stamps,
                configs=Y,
                tips=model.tip_position(Y),
                cables=model.cables(Y),
                min_clearance=clearance,
            )
            outcome = name
            break
    info.update(outcome=outcome, verified_duration_s=before, vertices=len(X))
    return out, {**info, **_fractions(out, actuators, rate)}


def _fractions(result: PlanResult, actuators: Actuators, rate: float) -> dict[str, Any]:
    """Executed duration (s) and the largest |velocity| and |acceleration| over all actuators as
    fractions of their full limits, from the set-points the streamer samples (finite differences
    at 1/rate s from rest, as `crtraj.hardware.limits.LimitsGate` checks them)."""
    if len(result.t) < 2:
        return {"executed_duration_s": result.duration, "max_velocity_fraction": 0.0, "max_acceleration_fraction": 0.0}
    _, values = SetpointPath.from_actuation(result.t, result.cables, actuators).sample(rate)
    V = np.diff(values, axis=0) * rate
    A = np.diff(np.vstack([np.zeros((1, V.shape[1])), V]), axis=0) * rate
    return {
        "executed_duration_s": result.duration,
        "max_velocity_fraction": float(np.max(np.abs(V) / actuators.vmax)),
        "max_acceleration_fraction": float(np.max(np.abs(A) / actuators.amax)),
    }


def _executed(timing: dict[str, Any] | None) -> dict[str, Any]:
    keys = ("executed_duration_s", "max_velocity_fraction", "max_acceleration_fraction")
    return {} if timing is None else {k: timing[k] for k in keys if k in timing}
