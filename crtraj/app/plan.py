"""Use case: plan a problem file's task and write the result document (`crtraj plan`)."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crtraj.core.errors import InputError
from crtraj.core.fileio import (
    StagedFile,
    atomic_write_json,
    check_output_file,
    failed_sibling,
    is_successful_result,
    json_document,
    to_jsonable,
)
from crtraj.core.lazy import lazy_module
from crtraj.hardware.stream import StreamOptions
from crtraj.io.problem import Problem
from crtraj.io.results import plan_document, relative_shape_files
from crtraj.model.kinematics import Model
from crtraj.planning.body import margin_of, model_record, planning_model, planning_scene
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.pipeline import plan_executable
from crtraj.planning.result import PlanResult
from crtraj.planning.steer import SteerOptions
from crtraj.world.scene import Scene

# the 3-D view (meshcat, zmq: about 0.2 s to import) loads only for --html or --view
view = lazy_module("crtraj.app.view")


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
        """The result document (kind "plan", `crtraj.io.results`), as plain JSON data."""
        options: dict[str, Any] = {"planner": self.options.to_dict()}
        if self.steer_options is not None:
            options["steer"] = self.steer_options.to_dict()
        options["body"] = model_record(self.model)
        doc = plan_document(self.problem, self.model, self.scene, self.result, options, self.setup_time)
        if self.timing is not None:
            doc["summary"] = {**doc["summary"], **to_jsonable(_executed(self.timing))}
            doc["retime"] = to_jsonable(self.timing)
        return doc

    def write(self, path: str | Path) -> Path:
        """Write `document()` as JSON, atomically (its shapes' data files relative to the file's folder)."""
        return atomic_write_json(path, relative_shape_files(self.document(), Path(path).parent))


def plan_problem(
    problem: Any,
    *,
    algorithm: str | None = None,
    seed: int | None = None,
    time_limit: float | None = None,
    model: Model | None = None,
    body: str | None = None,
    scene: Scene | None = None,
) -> ProblemPlan:
    """Plan a problem file's task with its ``[scene]``, ``[planner]``, ``[steer]`` and ``[stream]`` sections
    (`crtraj.planning.pipeline.plan_executable`).

    algorithm, seed, time_limit (s) and scene (a `Scene` instead of the file's) override the file; body: the
    ``[planner] model`` ("pcc" or "rod", `crtraj.planning.body`); model: the `Model` to plan with instead (its
    body and margin). The planner keeps D_sf plus the model's margin (`planning_scene`); the result records the
    problem's scene. The start is ``task.start_config`` when given, else a safe IK solution for ``task.start``.
    """
    task = problem.require_task()
    t1 = time.perf_counter()
    scene = problem.options(Scene, "scene") if scene is None else scene
    options = problem.options(PlannerOptions, "planner")
    changes: dict[str, Any] = {}
    if algorithm is not None:
        changes["algorithm"] = algorithm
    if time_limit is not None:
        changes["time_limit"] = float(time_limit)
    if body is not None:
        changes["model"] = body
    elif model is not None:  # the options record the body of the model given
        changes["model"] = model_record(model)["kind"]
    if changes:
        options = options.with_(**changes)
    steer_options = problem.options(SteerOptions, "steer")
    rate = problem.options(StreamOptions, "stream").rate
    model = planning_model(problem.robot, options.model) if model is None else model
    context = PlanningContext.build(model, planning_scene(scene, model), options)
    setup = time.perf_counter() - t1
    seed = problem.seed if seed is None else int(seed)
    start = {"start_config": task.start_config} if task.start_config is not None else {"start_tip": task.start}
    run = plan_executable(
        context,
        task.tip_goal(),
        seed=seed,
        goal_tolerance=task.goal_tolerance,
        steer_options=steer_options,
        rate=rate,
        **start,
    )
    result = run.result
    return ProblemPlan(problem, model, scene, options, run.steer_options, result, setup + run.setup_time, run.timing)


def _margin_text(model: Model) -> str:
    """' + 0.53 mm for the rod model's error' for a rod plan; '' for PCC."""
    extra = margin_of(model)
    return "" if extra == 0.0 else f" + {extra:.2f} mm for the rod model's error"


def _angle_text(r: PlanResult, problem: Problem) -> str:
    """', tip tangent 3.1 deg from goal_direction (cone 10 deg)' for a direction goal; '' otherwise."""
    if not math.isfinite(r.goal_angle) or problem.task is None or problem.task.goal_cone is None:
        return ""
    return (
        f", tip tangent {math.degrees(r.goal_angle):.2f} deg from goal_direction (cone {problem.task.goal_cone:g} deg)"
    )


def _executed(timing: dict[str, Any] | None) -> dict[str, Any]:
    keys = ("executed_duration_s", "max_velocity_fraction", "max_acceleration_fraction")
    return {} if timing is None else {k: timing[k] for k in keys if k in timing}


def _check_plan_args(args: argparse.Namespace) -> tuple[Problem, Path]:
    """Validate the flags and the problem before the (possibly long) plan; returns (problem, --out)."""
    if args.seed is not None and args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.time_limit is not None and not (math.isfinite(args.time_limit) and args.time_limit > 0):
        raise InputError(f"--time-limit: must be a number > 0 (s), got {args.time_limit}")
    problem = Problem.load(args.problem)
    out = Path(args.out) if args.out else Path("out") / f"plan-{problem.name}.json"
    check_output_file(out, "--out")
    if args.html:
        check_output_file(args.html, "--html")
        if Path(args.html).resolve() == out.resolve():
            raise InputError(f"--html: {args.html} is the same file as --out; choose another file")
    return problem, out


def _write_outputs(doc: dict[str, Any], success: bool, out: Path, args: argparse.Namespace) -> Path:
    """Write the result (and --html of a successful plan), both staged; returns where the result went."""
    # a failed plan never replaces a successful one unless asked: it goes beside it
    dest = out
    if not success and not args.overwrite_failed and is_successful_result(out):
        dest = failed_sibling(out)
    with contextlib.ExitStack() as stack:
        staged = [stack.enter_context(StagedFile(dest))]
        # its shapes' data files relative to its folder (it moves with them); the view reads them where they are
        staged[0].write(json_document(relative_shape_files(doc, dest.parent)).encode("utf-8"))
        if args.html and success:
            staged.append(stack.enter_context(StagedFile(args.html)))
            staged[1].write(view.static_html(doc).encode("utf-8"))
        for f in staged:  # both complete before either replaces anything
            f.commit()
    return dest


def plan_command(args: argparse.Namespace) -> int:
    """`crtraj plan PROBLEM ...` (arguments from `crtraj.cli`); returns the exit code."""
    problem, out = _check_plan_args(args)
    body = getattr(args, "model", None)
    run = plan_problem(problem, algorithm=args.planner, seed=args.seed, time_limit=args.time_limit, body=body)
    r = run.result
    doc = run.document()
    dest = _write_outputs(doc, r.is_success(), out, args)
    print(f"{problem.name}: {r.status} with {r.planner} (seed {r.seed}) in {r.timings.get('total', 0.0) * 1e3:.1f} ms")
    print(f"  {r.message}")
    if r.has_path:
        print(
            f"  tip path {r.length:.1f} mm over {r.duration:.2f} s, {len(r.t)} waypoints, "
            f"min clearance {r.min_clearance:.2f} mm (beyond D_sf {run.scene.safety_distance:g} mm"
            f"{_margin_text(run.model)}), goal error {r.goal_error:.3f} mm{_angle_text(r, problem)}"
        )
    if run.timing is not None and r.has_path:
        tm = run.timing
        print(
            f"  executed {tm['executed_duration_s']:.2f} s ({tm.get('outcome', '')}); largest actuator velocity "
            f"{tm['max_velocity_fraction']:.2f}, acceleration {tm['max_acceleration_fraction']:.2f} of the limits"
        )
    steps = ", ".join(f"{k} {v * 1e3:.1f}" for k, v in r.timings.items() if k != "total")
    print(f"  time (ms): {steps}; setup {run.setup_time * 1e3:.0f} ms")
    if dest != out:
        print(f"  wrote {dest} (failed; {out} holds a successful plan and was kept: --overwrite-failed replaces it)")
    else:
        print(f"  wrote {dest}")
    if args.html:
        print(f"  wrote {args.html}" if r.is_success() else f"  no HTML written: the plan failed ({r.status})")
    if r.is_success() and args.view:
        view.serve(doc, str(out), not args.no_browser)
    elif args.view:
        print(f"  not viewed: the plan failed ({r.status})")
    if not r.is_success():
        print(f"crtraj: plan failed: {r.status}: {r.message} (result in {dest})", file=sys.stderr)
    return 0 if r.is_success() else 1
