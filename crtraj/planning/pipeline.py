"""From a query to an executable motion: plan, smooth, retime within the actuator limits, verify.

`plan_executable` is the one call a user makes::

    context = PlanningContext.build(model, scene, options)
    run = plan_executable(context, goal, start_tip=start, seed=0)
    run.is_success(), run.duration, run.min_clearance

The planner (`options.algorithm`, from `crtraj.planning.planners.BUILTIN`) smooths its own path;
with the robot's actuator limits in the context the result is then retimed within
`options.limit_fraction` of them (`retime_result`), sampled at the stream rate, and its frames are
verified with the context's motion validity at their new times. Units mm, rad, s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from crtraj.core.splines import HermiteCubic, pchip_slopes
from crtraj.model.actuator_limits import ActuatorLimits
from crtraj.planning.context import PlanningContext
from crtraj.planning.metric import BodyMetric
from crtraj.planning.planners import BUILTIN, PlannerRegistry
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.retime import retime, retime_curve
from crtraj.planning.steer import SteerOptions
from crtraj.planning.validity import MotionValidator

# Set-points per second of the streamer the timing is measured for (Hz; `[stream] rate`'s default).
STREAM_RATE = 100.0


@dataclass(frozen=True)
class ExecutablePlan:
    """A planned, smoothed, retimed and verified motion.

    result: the executable `PlanResult` (waypoints every 1/rate s when retimed). timing: the retime
    report (`retime_result`; None without actuator limits: the planner's verified timing stands).
    steer_options: the ``[steer]`` settings the planner used (task-space planners; else None).
    setup_time: building the planner (s).
    """

    result: PlanResult
    timing: dict[str, Any] | None
    steer_options: SteerOptions | None = None
    setup_time: float = 0.0

    def is_success(self) -> bool:
        """True when the motion reaches the goal exactly and is safe (`PlanResult.is_success`)."""
        return self.result.is_success()

    @property
    def status(self) -> PlanStatus:
        return self.result.status

    @property
    def duration(self) -> float:
        """Executed duration of the motion (s)."""
        return self.result.duration

    @property
    def min_clearance(self) -> float:
        """Smallest clearance beyond the safety distance D_sf along the motion (mm)."""
        return self.result.min_clearance


def plan_executable(
    context: PlanningContext,
    goal: Any,
    *,
    start_config: Any = None,
    start_tip: Any = None,
    seed: int | None = None,
    goal_tolerance: float = 1.0,
    steer_options: SteerOptions | None = None,
    rate: float = STREAM_RATE,
    registry: PlannerRegistry = BUILTIN,
) -> ExecutablePlan:
    """Plan from a start (a configuration (nx,), or a tip (3,) mm reached by safe IK) to a goal tip
    (3,) mm with the planner `context.options.algorithm` names, then retime the result within the
    context's rate limits at `rate` set-points per second (Hz) and verify it (module docstring).

    seed: the same seed gives the same motion. Bad input raises a one-line `InputError`; an
    unsafe start or an unreachable goal is the result's status.
    """
    t1 = time.perf_counter()
    planner = registry.create(context.options.algorithm, context, steer_options)
    setup = time.perf_counter() - t1
    result = planner.plan(
        goal, start_config=start_config, start_tip=start_tip, seed=seed, goal_tolerance=goal_tolerance
    )
    used_steer = getattr(planner, "steer_options", None)  # a task-space planner's settings, as it raised them
    limits = context.robot.actuator_limits()
    if limits is None or context.rate_limits is None:
        return ExecutablePlan(result, None, used_steer, setup)
    result, timing = retime_result(result, context.validator, context, limits, rate)
    return ExecutablePlan(result, timing, used_steer, setup)


def retime_result(
    result: PlanResult,
    validator: MotionValidator,
    context: PlanningContext,
    actuators: ActuatorLimits,
    rate: float,
    compiled: bool = True,
) -> tuple[PlanResult, dict[str, Any]]:
    """The result timed within `options.limit_fraction` of the context's rate limits and max_speed.

    The motion is sampled every 1/rate s (the stream rate) into the new waypoints, so a streamer
    sampling at that rate sends exactly them. First the time-optimal law along the smoothed curve
    through the path's corners (`crtraj.planning.retime.retime_curve`): its frames are verified
    with `validator` at their times, and it stops at a corner only where the curve fails. Without
    a curve (a path of one or two straight motions, or chords that fail at their new times among
    moving obstacles): the rest-to-rest law along the verified straight motions (`retime`; among
    moving obstacles re-verified at its own times, then the law that never runs a straight motion
    faster than the planner's verified timing); if that fails as well, the planner's verified
    timing is kept (and the fractions below show by how much it exceeds the limits). Returns the
    result and a report: method, outcome, durations (s) and the largest velocity and acceleration
    as fractions of the full `actuators` limits, measured as the streamer samples the motion.
    compiled: the curve's phase pass and the frames' tips in the validator's compiled kernel when it has one
    (the same numbers; False: numpy, Python loops and the model's CasADi tips, for the benchmarks' comparison).
    """
    options, limits = context.options, context.rate_limits
    assert limits is not None, "retime_result needs a context with rate limits"
    before = result.duration
    info: dict[str, Any] = {"method": "closed-form rest-to-rest per straight motion", "rate_hz": rate}
    info["limit_fraction"] = options.limit_fraction
    if not result.has_path or len(result.t) < 2:
        return result, {**info, "outcome": "no motion", **executed_fractions(result, actuators, context, rate)}
    usable = limits.scaled(options.limit_fraction)
    # the validator's own metric when it has the same speed (its motion bound is the same function of the robot; a
    # new one costs its matrices and their inverse, a tenth of a millisecond)
    space = getattr(validator, "space", None)
    same = isinstance(space, BodyMetric) and space.robot is validator.robot and space.max_speed == options.max_speed
    metric = space if same else BodyMetric(validator.robot, options.max_speed)
    X, t0, period = result.configs, float(result.t[0]), 1.0 / rate
    model = validator.model

    def timed(stamps: np.ndarray, Y: np.ndarray, clearance: float) -> PlanResult:
        # the tips from the compiled kernel when there is one: the model's numbers bit for bit, a seventh of the time
        tips = validator.tip_position(Y) if compiled else model.tip_position(Y)
        return replace(result, t=stamps, configs=Y, tips=tips, cables=model.cables(Y), min_clearance=clearance)

    out, outcome = result, "kept the verified timing (the retimed motion failed its collision check)"
    curve = retime_curve(
        X, usable, metric, validator, t0=t0, period=period, kernel=validator.kernel if compiled else None
    )
    if curve is not None:
        # the frames passed their own check at their times; their clearance is measured the same way
        out = timed(curve.stamps, curve.configs, validator.path_clearance(curve.configs, curve.stamps)[0])
        outcome = f"retimed along the smoothed curve ({len(curve.stops) - 2} of {curve.corners - 2} corners stopped at)"
        info.update(method="phase-plane law along the natural cubic spline through the corners; stops where it fails")
    else:
        candidates = [("retimed", None)]
        if not validator.static:
            candidates.append(("retimed, no faster than verified", np.diff(result.t)))
        for name, floor in candidates:
            stamps, Y = retime(X, usable, metric, t0=t0, period=period, at_least=floor).sample()
            if validator.static or validator.path_valid(Y, stamps):
                clearance = result.min_clearance if validator.static else validator.path_clearance(Y, stamps)[0]
                out, outcome = timed(stamps, Y, clearance), name
                break
    info.update(outcome=outcome, verified_duration_s=before, vertices=len(X))
    return out, {**info, **executed_fractions(out, actuators, context, rate)}


def _setpoints(t: np.ndarray, values: np.ndarray, rate: float) -> np.ndarray:
    """Actuator values every 1/rate s from t[0] through t[-1] (included), as the streamer samples
    waypoints (`crtraj.hardware.setpoints.SetpointPath.sample`): the PCHIP cubic through them,
    at rest at both ends."""
    dt = 1.0 / rate
    t0, t1 = float(t[0]), float(t[-1])
    m = int(np.ceil((t1 - t0) / dt - 1e-9))
    stamps = t0 + dt * np.arange(0, m + 1)
    stamps[-1] = t1
    if len(t) == m + 1 and np.array_equal(stamps, t):
        # waypoints already every 1/rate s (a retimed motion): the cubic through them gives them back exactly
        # (its basis at a knot is (1, 0, 0, 0), at the last (0, 0, 1, 0))
        return np.array(values, dtype=float)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # subnormal steps: slope 0
        slopes = pchip_slopes(t, values)
    slopes[0] = 0.0
    slopes[-1] = 0.0
    return HermiteCubic(t, values, slopes)(np.maximum(stamps, t0))


def executed_fractions(
    result: PlanResult, actuators: ActuatorLimits, context: PlanningContext, rate: float
) -> dict[str, Any]:
    """Executed duration (s) and the largest |velocity| and |acceleration| over all actuators as
    fractions of their full limits, from the set-points the streamer samples (finite differences
    at 1/rate s from rest, as `crtraj.hardware.limits.LimitsGate` checks them)."""
    if len(result.t) < 2:
        return {"executed_duration_s": result.duration, "max_velocity_fraction": 0.0, "max_acceleration_fraction": 0.0}
    _, rest = context.robot.cable_matrix()
    command = actuators.command(np.asarray(result.cables, dtype=float), np.asarray(rest, dtype=float))
    values = _setpoints(np.asarray(result.t, dtype=float), command, rate)
    V = np.diff(values, axis=0) * rate
    A = np.diff(np.vstack([np.zeros((1, V.shape[1])), V]), axis=0) * rate
    return {
        "executed_duration_s": result.duration,
        "max_velocity_fraction": float(np.max(np.abs(V) / actuators.vmax)),
        "max_acceleration_fraction": float(np.max(np.abs(A) / actuators.amax)),
    }
