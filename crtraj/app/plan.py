"""Use case: plan a problem file's task and write the result document (`crtraj plan`)."""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj import __version__
from crtraj.core.fileio import atomic_write_json, to_jsonable
from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import make_planner
from crtraj.planning.result import PlanResult
from crtraj.planning.steer import SteerOptions
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
            "summary": r.summary(),
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
    planner = make_planner(model, scene, options, steer_options)
    setup = time.perf_counter() - t1
    seed = problem.seed if seed is None else int(seed)
    start = {"start_config": task.start_config} if task.start_config is not None else {"start_tip": task.start}
    result = planner.plan(task.goal, seed=seed, goal_tolerance=task.goal_tolerance, **start)
    used_steer = getattr(planner, "steer_options", None)
    return ProblemPlan(problem, model, scene, options, used_steer, result, setup)
