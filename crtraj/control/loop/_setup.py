"""What a closed loop is built from: `LoopSpec` (everything a caller gives), `LoopConfig` (the frozen
options the coordinator reads), `LoopParts` (the parts with one job each) and `assemble`, which checks
the spec and builds the parts once. Units: mm, rad, s."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.control.horizon import INTERPOLATION_GAIN, Replanner, ReplanOptions
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._pacer import Pacer
from crtraj.control.loop._recorder import RecorderSetup, RunRecorder
from crtraj.control.loop._reference import DirectReference, ReferencePlan, ReferenceSource
from crtraj.control.loop._reference_manager import ReferenceManager, ReferenceSetup
from crtraj.control.loop._scene_checks import SceneChecks
from crtraj.control.loop._step_motion import StepMotion
from crtraj.control.loop._step_policy import StepPolicy
from crtraj.control.loop._tip_sensing import TipSensing
from crtraj.control.ports import ObstacleSource, TipSensor
from crtraj.control.tracking import ServoModel, TrackingController, TrackingOptions
from crtraj.core.clock import Clock, WallClock
from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.goal import TipGoal
from crtraj.world.sources import SceneObstacles


@dataclass(frozen=True)
class LoopSpec:
    """Everything a closed loop is built from (`assemble`).

    model: the robot's `Model`. scene: `crtraj.world.scene.Scene` (obstacle truth and prediction). goal:
    tip position (3,) mm, or a `crtraj.planning.goal.TipGoal` (with a direction cone the goal is held only
    with the tip tangent within it). start_config: (nx,) the robot's configuration at t = 0 (servos settled).
    options: `ReplanOptions` (the horizon NLP). loop_options: `LoopOptions` (this loop: duration,
    reference timing, verification, settling). tracking: `TrackingOptions` (its dt must divide the
    replanner's dt). reference: a `ReferenceSource` ((x, t, scene) -> `ReferencePlan`); default: the
    straight motion to `goal_config`. replanner: a prebuilt `Replanner` (tests inject failures this way).
    goal_tolerance: mm. goal_config: used by the default reference. initial_reference: a reference
    already planned from start_config at t = 0 (saves the first planner call). extra_options: more
    option sections (name -> object with ``to_dict``) recorded in result files. obstacles: where the
    obstacle states come from each step, an `ObstacleSource`: default `SceneObstacles` (the scene's
    known time functions), or `crtraj.world.sources.FeedObstacles` (a live feed). rate_limits: the
    actuators' speed and acceleration limits (`RateLimits`): the NLP, the tracking set-points and the
    reference timing keep within ``replan.limit_fraction`` of them; None: only the mm/s rate limits.
    tip_sensor, tip_feedback, tip_gain: see `crtraj.control.loop._tip_sensing.TipSensing`. clock: the one
    clock that times every iteration (judged against ``replan.step_deadline``), paces a real-time run
    and bounds the wait for a live feed's first states (default `WallClock`; tests inject a virtual one).
    """

    model: Model
    scene: Any
    goal: Any
    start_config: Any
    options: ReplanOptions = field(default_factory=ReplanOptions)
    loop_options: LoopOptions = field(default_factory=LoopOptions)
    tracking: TrackingOptions = field(default_factory=TrackingOptions)
    reference: ReferenceSource | None = None
    replanner: Replanner | None = None
    goal_tolerance: float = 0.5
    goal_config: Any = None
    initial_reference: ReferencePlan | None = None
    extra_options: dict[str, Any] = field(default_factory=dict)
    obstacles: ObstacleSource | None = None
    rate_limits: RateLimits | None = None
    tip_sensor: TipSensor | None = None
    tip_feedback: bool = False
    tip_gain: float = 0.5
    clock: Clock = field(default_factory=WallClock)


@dataclass(frozen=True)
class LoopConfig:
    """The frozen options of one closed loop: goal (3,) mm, start configuration (nx,), goal tolerance
    (mm), ``[replan]``, ``[loop]`` and ``[tracking]`` options, tracking periods per step (n_sub), the
    actuator rate limits (or None), and every option section recorded in result files besides
    ``replan`` and ``tracking`` (``loop`` first). tip_goal: the goal with its direction cone
    (`crtraj.planning.goal.TipGoal`; no cone without a direction goal)."""

    goal: np.ndarray
    x_start: np.ndarray
    goal_tolerance: float
    options: ReplanOptions
    loop_options: LoopOptions
    tracking_options: TrackingOptions
    n_sub: int
    rate_limits: RateLimits | None
    extra_options: dict[str, Any]
    tip_goal: TipGoal = field(default_factory=lambda: TipGoal(np.zeros(3)))


@dataclass(frozen=True)
class LoopParts:
    """The parts of a closed loop, one job each: the model and scene, where obstacle states come from,
    the checks against the current obstacles, the tracking controller, its servo model and the step's
    motion, the horizon NLP's replanner, the step policy (choose, verify, fall back; it solves with the same
    replanner), the reference manager, the tip sensing, the pacer (one clock) and the run recorder."""

    model: Model
    scene: Any
    obstacles: ObstacleSource
    checks: SceneChecks
    tracker: TrackingController
    servo: ServoModel
    motion: StepMotion
    replanner: Replanner
    policy: StepPolicy
    references: ReferenceManager
    tip: TipSensing
    pacer: Pacer
    recorder: RunRecorder


def _config(spec: LoopSpec) -> LoopConfig:
    """The checked options of `spec`; `InputError` naming the bad field."""
    o, lo = spec.options, spec.loop_options
    lo.steps(o.dt)  # refuse a huge run before building anything
    tip_goal = TipGoal.of(spec.goal)
    goal = tip_goal.position
    x_start = check_array(spec.start_config, "start_config", (spec.model.robot.nx,))
    if not spec.goal_tolerance > 0:
        raise InputError(f"goal_tolerance: must be > 0 mm, got {spec.goal_tolerance}")
    n_sub = control_periods(o, spec.tracking)
    # the loop's own section is recorded in result files beside the others
    extra = {"loop": lo, **(spec.extra_options or {})}
    return LoopConfig(
        goal, x_start, float(spec.goal_tolerance), o, lo, spec.tracking, n_sub, spec.rate_limits, extra, tip_goal
    )


def _reference(spec: LoopSpec) -> ReferenceSource:
    """The spec's reference source, or the straight motion to its goal configuration."""
    if spec.reference is not None:
        return spec.reference
    if spec.goal_config is None:
        raise InputError("reference: give a reference source or a goal_config")
    return DirectReference(check_array(spec.goal_config, "goal_config", (spec.model.robot.nx,)))


def assemble(spec: LoopSpec) -> tuple[LoopParts, LoopConfig]:
    """Check `spec` and build the loop's parts once (CasADi functions, solvers, compiled kernels)."""
    cfg = _config(spec)
    model, scene, o = spec.model, spec.scene, spec.options
    # the full actuator limits (reports). The executed motion's samples keep the speeds and the
    # accelerations over the interpolation gain (the set-points enforce that); the NLP plans within
    # limit_fraction of them, which leaves the tracking room to catch up with its plan.
    limits = spec.rate_limits
    sampled = None if limits is None else replace(limits, amax=limits.amax / INTERPOLATION_GAIN)
    tracker = TrackingController(
        model, spec.tracking, rate_limits=None if sampled is None else set_point_limits(model, o, sampled)
    )
    reference = _reference(spec)
    replanner = spec.replanner
    if replanner is None:
        # a scene of more obstacles than qp_obstacles: the QP gets that many slots, filled by the broad phase
        slots = scene.n_obstacles if not o.qp_obstacles else min(scene.n_obstacles, o.qp_obstacles)
        replanner = Replanner(
            model, o, max_obstacles=slots, safety_distance=scene.safety_distance, rate_limits=sampled,
            shapes=scene.shapes,
        )  # fmt: skip
    if replanner.options.dt != o.dt or o.horizon != replanner.N:
        raise InputError("replanner: its dt and horizon must match the loop's options")
    obstacles: ObstacleSource = SceneObstacles(scene) if spec.obstacles is None else spec.obstacles
    checks = SceneChecks(model, scene, spec.loop_options)
    # a hold while moving is a stop within the same limits as the executed motion's samples
    motion = StepMotion(tracker, checks, o.dt, cfg.n_sub, spec.loop_options.check_resolution, brake_limits=sampled)
    # the tip sensor is always read and recorded; with tip_feedback the loop also corrects its model's
    # error: a low-pass estimate of measured minus model tip shifts the goal the reference planner aims
    # the model's tip at (output-disturbance correction)
    if spec.tip_feedback and (spec.tip_sensor is None or not hasattr(reference, "retarget")):
        raise InputError("tip_feedback: needs a tip sensor and a reference source that can retarget (the planner's)")
    tip = TipSensing(model, spec.tip_sensor, spec.tip_feedback, spec.tip_gain, cfg.goal, cfg.goal_tolerance)
    ref_setup = ReferenceSetup(
        model, o, spec.loop_options, reference, spec.initial_reference, limits, spec.clock
    )  # fmt: skip
    servo = tracker.servo
    recorder = RunRecorder(RecorderSetup(model, servo.config, cfg.goal, o.dt, cfg.n_sub, o.safety, limits))
    parts = LoopParts(
        model=model,
        scene=scene,
        obstacles=obstacles,
        checks=checks,
        tracker=tracker,
        servo=servo,
        motion=motion,
        replanner=replanner,
        policy=StepPolicy(replanner, motion, checks, o),
        references=ReferenceManager(ref_setup, checks),
        tip=tip,
        pacer=Pacer(spec.clock, o.dt),
        recorder=recorder,
    )
    return parts, cfg


def set_point_limits(model: Model, o: ReplanOptions, limits: RateLimits) -> RateLimits:
    """`limits` with each speed capped by the NLP's own per-actuator rate (max_cable_speed,
    max_z_speed): the executed motion then never moves faster than the NLP's first step may, so its
    velocity history never makes the next NLP infeasible. J's row i is scale_i times the cable
    matrix row i (actuator value per mm of actuation)."""
    A, _ = model.robot.cable_matrix()
    rates = np.append(np.full(3 * model.robot.n_segments, o.max_cable_speed), o.max_z_speed)  # mm/s
    scale = np.sum(limits.jacobian * A, axis=1) / np.sum(A * A, axis=1)
    return replace(limits, vmax=np.minimum(limits.vmax, rates * np.abs(scale)))


def control_periods(o: ReplanOptions, tr: TrackingOptions) -> int:
    """Tracking periods per replan step; `InputError` when they do not divide it or the NLP's rate limits
    exceed the tracking controller's."""
    n_sub = o.dt / tr.dt
    if abs(n_sub - round(n_sub)) > 1e-9 or round(n_sub) < 1:
        raise InputError(f"tracking.dt: must divide replan.dt = {o.dt:g} s into whole control periods, got {tr.dt:g} s")
    if o.max_cable_speed > tr.max_cable_rate or o.max_z_speed > tr.max_z_rate:
        raise InputError(
            f"replan.max_cable_speed / max_z_speed ({o.max_cable_speed:g} / {o.max_z_speed:g} mm/s) "
            f"must not exceed the tracking rate limits ({tr.max_cable_rate:g} / {tr.max_z_rate:g} mm/s)"
        )
    return round(n_sub)
