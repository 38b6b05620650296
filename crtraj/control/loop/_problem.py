"""A closed loop from a problem file (`ClosedLoop.from_problem`): its robot, scene, task and the
``[replan]``, ``[loop]``, ``[tracking]``, ``[planner]``, ``[steer]``, ``[feed]`` sections, the robot's
actuator limits, a safe start configuration and a first reference. Units: mm, rad, s.

The problem is typed by what is read from it (`ProblemLike`), so control does not import `crtraj.io`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._reference import PlannerReference, ReferencePlan
from crtraj.control.loop._setup import LoopSpec
from crtraj.control.ports import TipSensor
from crtraj.control.tracking import TrackingOptions
from crtraj.core.clock import Clock, WallClock
from crtraj.core.errors import InputError
from crtraj.core.fields import Table, check_array
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.body import model_record, planning_model, planning_scene
from crtraj.planning.goal import TipGoal
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import make_planner
from crtraj.planning.result import PlanStatus
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition
from crtraj.world.feed import FeedOptions
from crtraj.world.scene import Scene
from crtraj.world.sources import FeedObstacles

# s a live feed is given to deliver the first snapshot the start configuration is found among
FIRST_SNAPSHOT_WAIT = 2.0


class ProblemLike(Protocol):
    """What `ClosedLoop.from_problem` reads from a problem (`crtraj.io.problem.Problem` is one)."""

    robot: Any
    seed: int

    def require_task(self) -> Any:
        """The task (start, goal, start_config, goal_tolerance); `InputError` without one."""
        ...

    def options(self, cls: Any, section: str) -> Any:
        """The section's options as `cls` (defaults when the section is missing)."""
        ...

    def section(self, name: str) -> Table:
        """A raw section of the problem file."""
        ...

    def rate_limits(self) -> RateLimits | None:
        """The robot's actuator speed and acceleration limits on configuration motion (None without any)."""
        ...


class UnsolvableTaskError(Exception):
    """A well-formed task the loop cannot start: `status` is `PlanStatus.INVALID_START` (no safe start
    configuration) or `PlanStatus.INVALID_GOAL` (no configuration can ever put the tip on the goal safely).
    Not an input error: the command exits 1 with the status, as `crtraj plan` does."""

    def __init__(self, status: PlanStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class ProblemRun:
    """How to run a problem's loop.

    safety: False drops the collision-free terms (NLP constraints, verification, and obstacles in the
    reference planner), as in the paper's Fig. 4(b); None: the problem's. seed: overrides the problem's.
    options, loop_options: override the ``[replan]`` / ``[loop]`` sections. feed: a
    `crtraj.world.feed.ObstacleFeed`: obstacle states come from it, live (`FeedObstacles`; the scene's
    obstacle names are the feed ids; the ``[feed]`` section configures it). lead: s the device executes
    each step after it is computed, so the feed is predicted that far ahead. start_config: (nx,) the
    configuration the run starts from instead of the task's start (a live device's measured one).
    tip_sensor, tip_feedback: see `crtraj.control.loop._tip_sensing.TipSensing`. clock: the loop's one clock.
    body: the body the loop keeps D_sf from, "pcc" or "rod" (`crtraj.planning.body`; None: ``[planner] model``);
    with "rod" the whole loop (reference planner, horizon NLP, step verification) sees the rod's body and keeps
    D_sf plus the rod model's error bound.
    """

    safety: bool | None = None
    seed: int | None = None
    options: ReplanOptions | None = None
    loop_options: LoopOptions | None = None
    feed: Any = None
    lead: float = 0.0
    start_config: Any = None
    tip_sensor: TipSensor | None = None
    tip_feedback: bool = False
    clock: Clock = field(default_factory=WallClock)
    body: str | None = None


def spec_from_problem(problem: ProblemLike, run: ProblemRun) -> LoopSpec:
    """The `LoopSpec` of a problem's loop: references from the ``[planner] algorithm``
    (`crtraj.planning.planners.make_planner`), each limited to ``loop.planner_time`` seconds; the start
    configuration is the task's ``start_config``, `run.start_config`, or the planner's safe IK for the
    start tip. `InputError` for bad input, `UnsolvableTaskError` for a task that cannot be run."""
    task = problem.require_task()
    tip_goal = TipGoal.of(
        task.goal, getattr(task, "goal_direction", None), getattr(task, "goal_cone", None), prefix="task."
    )
    seed = problem.seed if run.seed is None else int(run.seed)
    if seed < 0:
        raise InputError(f"--seed: must be >= 0, got {seed}")
    opts = problem.options(ReplanOptions, "replan") if run.options is None else run.options
    if run.safety is not None:
        opts = replace(opts, safety=bool(run.safety))
    lopts = problem.options(LoopOptions, "loop") if run.loop_options is None else run.loop_options
    lopts.steps(opts.dt)  # refuse a huge run before any planning
    tracking = problem.options(TrackingOptions, "tracking")
    popts = problem.options(PlannerOptions, "planner")
    sopts = problem.options(SteerOptions, "steer")
    scene = Scene.from_table(problem.section("scene"))
    feed_options = problem.options(FeedOptions, "feed")  # checked even without a feed
    model = planning_model(problem.robot, popts.model if run.body is None else run.body)
    scene = planning_scene(scene, model)
    planner = make_planner(model, scene, popts, sopts)
    if tip_goal.has_direction and not getattr(planner, "honours_direction", False):
        raise InputError(
            f"task.goal_direction: the {popts.algorithm} planner does not honour a tip direction goal; "
            'plan with [planner] algorithm = "cspace"'
        )
    source: FeedObstacles | None = None
    scene0 = scene
    extra: dict[str, Any] = {"planner": popts, "steer": sopts, "body": model_record(model)}
    if run.feed is not None:
        run.feed.configure(feed_options)  # the problem's velocity bound and timestamp window
        extra["feed"] = feed_options
        window = max(2.0 * opts.horizon * opts.dt, 2.0) + 2.0 * opts.dt
        source = FeedObstacles(run.feed, scene, window=window, lead=run.lead)
        scene0 = _start_scene(source, run.clock)
    if run.start_config is not None:
        x0, first, res = check_array(run.start_config, "start_config", (problem.robot.nx,)), None, None
    else:
        x0, first, res = _start_config(planner, task, tip_goal, scene0, seed, opts.safety)
    moving = run.feed is not None or any(o.amplitude != 0.0 or o.to is not None for o in scene.obstacles)
    moving = moving or not scene.shapes_static
    _check_goal(planner, task, tip_goal, x0, scene0, seed, res, among_obstacles=opts.safety and not moving)
    reference = PlannerReference(
        planner,
        tip_goal,
        goal_tolerance=task.goal_tolerance,
        stop=popts.stop() | StopCondition(time_limit=lopts.planner_time),
        seed=seed,
        scene=None if opts.safety else scene.with_obstacles(()),
    )
    return LoopSpec(
        model, scene, tip_goal, x0, options=opts, loop_options=lopts, tracking=tracking, reference=reference,
        goal_tolerance=task.goal_tolerance, initial_reference=None if run.feed is not None else first,
        extra_options=extra, obstacles=source, rate_limits=problem.rate_limits(), tip_sensor=run.tip_sensor,
        tip_feedback=run.tip_feedback, clock=run.clock,
    )  # fmt: skip


def _start_scene(source: FeedObstacles, clock: Clock) -> Any:
    """The obstacles to find a start configuration among, from a live feed's first snapshot: everything
    the obstacles may cover over the next half second (the run starts a moment after the snapshot)."""
    t_end = clock.now() + FIRST_SNAPSHOT_WAIT
    snap, why = source.at(0.0)
    while snap is None and clock.now() < t_end:
        clock.sleep(0.01)
        snap, why = source.at(0.0)
    if snap is None:
        raise InputError(f"--feed: {why}")
    a, b, rmax = snap.swept(0.0, 0.5)
    return snap.with_obstacles(
        replace(
            o,
            center=tuple(0.5 * (a[i] + b[i])),
            radius=float(rmax[i] + 0.5 * np.linalg.norm(b[i] - a[i])),
            amplitude=0.0,
            omega=0.0,
            phase=0.0,
            to=None,
        )
        for i, o in enumerate(snap.obstacles)
    )


def _start_config(
    planner: Any, task: Any, tip_goal: TipGoal, scene0: Any, seed: int, safety: bool
) -> tuple[np.ndarray, ReferencePlan | None, Any]:
    """(start configuration, a first reference plan from it or None, the planner's result or None).

    The task's start_config, else the planner's safe IK for the start tip among `scene0`; its plan to
    the goal (`tip_goal`: with its direction cone) is reused as the first reference when it succeeded (with
    the safety terms only)."""
    if task.start_config is not None:
        return np.asarray(task.start_config, dtype=float), None, None
    tol = task.goal_tolerance
    res = planner.plan(tip_goal, start_tip=task.start, t0=0.0, seed=seed, goal_tolerance=tol, scene=scene0)
    if res.status is PlanStatus.INVALID_START:
        raise UnsolvableTaskError(PlanStatus.INVALID_START, f"task.start: {res.message}")
    if not res.has_path:
        only = planner.plan(task.start, start_tip=task.start, t0=0.0, seed=seed, goal_tolerance=1.0, scene=scene0)
        if not only.has_path:
            raise UnsolvableTaskError(PlanStatus.INVALID_START, f"task.start: {only.message}")
        return only.configs[0], None, res
    first = None
    if res.is_success() and safety:
        first = ReferencePlan(res.configs, res.status, res.message, res.timings.get("total", 0.0), res.tree_edges)
    return res.configs[0], first, res


def _check_goal(
    planner: Any,
    task: Any,
    tip_goal: TipGoal,
    x0: np.ndarray,
    scene: Any,
    seed: int,
    res: Any,
    *,
    among_obstacles: bool,
) -> None:
    """Fail fast, as `crtraj plan` does, when no configuration can ever put the tip on the goal safely
    (`UnsolvableTaskError` "invalid_goal"), instead of running the loop until its duration ends.

    among_obstacles (static obstacles, with the safety terms): the planner's goal IK among them
    decides. Obstacles that move or breathe, or come from a live feed, may uncover the goal later,
    so then only a goal the robot cannot reach even with no obstacles at all is refused. res: the
    planner's result from x0 among `scene`, when there is one.
    """
    if res is not None and res.status not in (PlanStatus.INVALID_GOAL, PlanStatus.INVALID_START):
        return  # the goal IK found a safe goal configuration: reachable
    if not among_obstacles:
        scene, res = scene.with_obstacles(()), None
    if res is None:  # the goal IK runs before any search; one search iteration bounds the cost
        res = planner.plan(
            tip_goal,
            start_config=x0,
            t0=0.0,
            seed=seed,
            goal_tolerance=task.goal_tolerance,
            scene=scene,
            stop=StopCondition(max_iterations=1),
        )
    if res.status is PlanStatus.INVALID_GOAL:
        raise UnsolvableTaskError(PlanStatus.INVALID_GOAL, f"task.goal: {res.message}")
