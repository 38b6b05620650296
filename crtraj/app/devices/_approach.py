"""Use case: a planned approach from where the device is to the start of an admitted motion (``--approach``).

`plan_approach` is the `ApproachPlanner` (`crtraj.hardware.stream._path`) the stream use
cases inject into `Streamer.run_path` (the planner lives below hardware, the
streamer never imports it). It returns the motion's path with an approach
that ends at the motion's first time (its t = 0 in the scene's clock), found
in the motion's scene:

1. the straight move in actuator space (a straight line in configuration
   space too), then
2. the default planner (`crtraj.planning.planners.make_planner`) from the
   device's configuration to the start's tip, started at -T (T: a bound on
   the approach's duration), in configuration space to the start
   configuration itself (`goal_config`: the pose, not only the tip). The
   planner keeps `ApproachOptions.margin` mm more than D_sf: its own check is
   coarser than the frames' check below, and a path planned to touch D_sf
   would fail that by hundredths of a millimetre.

Each candidate is timed along its straight motions with the plans' rest-to-rest
law (`crtraj.planning.retime.retime`, within `PlannerOptions.limit_fraction`
of the actuator limits and the body-speed limit, never faster than the
planner's own timing, slowed by each of `ApproachOptions.slowdowns`), sampled
at the stream period on the stream's grid so that it ends at the motion's first
time: every frame lies on a straight motion of the candidate, so the cables stay
consistent (an interpolation through sparse waypoints would leave the cables'
affine subspace and the straight motions). A candidate is accepted only when
its frames, as `SetpointPath.sample` gives them, pass the motion's
`crtraj.hardware.verify.FrameVerifier` (dense body check with D_sf, cables,
limits) at their times. Among static obstacles time does not matter; among
moving ones the approach is checked at the times it will run. No candidate:
`AdmissionError` (one line), nothing is sent. Units: mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from crtraj.core.errors import AdmissionError
from crtraj.hardware.admission import AdmittedMotion
from crtraj.hardware.setpoints import SetpointPath
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import make_planner
from crtraj.planning.retime import min_durations, motion_limits, retime


@dataclass(frozen=True)
class ApproachOptions:
    """time_limit: planner budget per attempt (s). attempts: planner queries (seeds seed, seed + 1, ...).
    slowdowns: how many times slower than the limit timing a candidate is tried (each is verified).
    margin: mm the approach planner keeps on top of D_sf (the frames are checked with D_sf itself)."""

    time_limit: float = 5.0
    attempts: int = 3
    seed: int = 0
    slowdowns: tuple[float, ...] = (1.0, 1.25, 1.6, 2.0, 3.0)
    margin: float = 1.0


def _law_durations(X: np.ndarray, motion: AdmittedMotion, options: PlannerOptions) -> np.ndarray:
    """Shortest rest-to-rest duration (s) of each straight motion of X (K, nx) within `options.limit_fraction`
    of the actuator limits and `options.max_speed` (0 for a motion that does not move)."""
    limits = motion.actuators.rate_limits(motion.robot).scaled(options.limit_fraction)
    D = np.diff(X, axis=0)
    moving = np.any(D != 0.0, axis=1)
    T = np.zeros(len(D))
    if np.any(moving):
        T[moving] = min_durations(*motion_limits(D[moving], limits, BodyMetric(motion.robot, options.max_speed)))
    return T


def _candidate_paths(
    motion: AdmittedMotion,
    X: np.ndarray,
    floor: np.ndarray | None,
    slowdowns: tuple[float, ...],
    t_start: float | None = None,
) -> list[SetpointPath]:
    """The motion's path with the configuration path X (ending at its start) as approach, at each slowdown.

    floor (K-1,) s: the straight motions' shortest durations (the planner's timing), or None. t_start: when
    the approach starts (s; the time the planner planned it from): it then starts there, or up to a period
    later (the stream's grid), and waits at the start until the motion's first time; None (or a timing that
    does not fit): it ends at the motion's first time.
    """
    acts, robot = motion.actuators, motion.robot
    X = np.vstack([X[:-1], robot.config(acts.actuation(motion.path.values[:1]))])
    keep = np.concatenate([[True], np.any(np.diff(X, axis=0) != 0.0, axis=1)])
    X, floor = X[keep], None if floor is None else floor[keep[1:]]
    if len(X) < 2:
        return [motion.path]
    options = PlannerOptions()
    limits = acts.rate_limits(robot).scaled(options.limit_fraction)
    metric = BodyMetric(robot, options.max_speed)
    base = _law_durations(X, motion, options)
    if floor is not None:
        base = np.maximum(base, floor)
    period = 1.0 / motion.rate
    t_end = float(motion.path.t[0])
    out = []
    for s in slowdowns:
        _, Y = retime(X, limits, metric, period=period, at_least=s * base).sample()
        V = acts.command(robot.cables(Y))
        V[-1] = motion.path.values[0]  # bit for bit the motion's first set-point
        n = len(V) - 1
        wait = 0
        if t_start is not None:
            wait = max(0, int(np.floor((t_end - t_start) / period + 1e-9)) - n)  # whole periods at the start
        V = np.vstack([V, np.repeat(V[-1:], wait, axis=0)])
        k = np.arange(-(n + wait), 1)
        t = t_end + period * k.astype(float)
        t[-1] = t_end
        out.append(motion.path.with_approach_path(t, V))
    return out


def _first_safe(motion: AdmittedMotion, here: np.ndarray, paths: list[SetpointPath]) -> tuple[SetpointPath | None, str]:
    """The first path whose approach frames pass the motion's verifier (and the reason the last one failed)."""
    why = "no candidate"
    rate = motion.rate
    for p in paths:
        if p.approach is None:
            return p, ""
        stamps, values = p.sample(rate)
        na = p.approach_frames(rate)
        why = motion.verifier.failure(stamps[: na + 1], values[: na + 1], start=here)
        if why is None:
            return p, ""
    return None, why


def plan_approach(motion: AdmittedMotion, here: np.ndarray, options: ApproachOptions | None = None) -> SetpointPath:
    """The motion's path with a verified approach from actuator values `here` (see the module docstring);
    `AdmissionError` when no safe, limit-respecting approach was found."""
    o = ApproachOptions() if options is None else options
    if motion.verifier is None or motion.scene is None:
        raise AdmissionError("--approach: the motion carries no scene to plan the approach in")
    robot, acts, v = motion.robot, motion.actuators, motion.verifier
    x_from = robot.config(acts.actuation(np.asarray(here, dtype=float)))
    x_to = robot.config(acts.actuation(motion.path.values[0]))
    # among static obstacles a slower candidate has the same geometry: one timing is enough
    slowdowns = o.slowdowns[:1] if v.validator.static else o.slowdowns
    path, why = _first_safe(motion, here, _candidate_paths(motion, np.stack([x_from, x_to]), None, slowdowns))
    if path is not None:
        return path
    reasons = [f"straight move: {why}"]
    model = v.model
    goal = model.tip_position(x_to)
    # a bound on the approach's duration: the straight move's limit time, three times over, plus the
    # planner's own full-speed time; the plan starts at -T so that it ends before the motion's t = 0
    t_end = float(motion.path.t[0])
    T = 3.0 * float(np.sum(_law_durations(np.stack([x_from, x_to]), motion, PlannerOptions())))
    # planned in configuration space to the start pose itself, first with a margin on top of D_sf (the
    # frames' check is finer than the planner's), then, if the start is within that margin, without it
    scenes = [replace(motion.scene, safety_distance=motion.scene.safety_distance + o.margin), motion.scene]
    planners: dict[int, Any] = {}
    for k in range(o.attempts):
        for i in (0, 1) if o.margin > 0 else (1,):
            if i not in planners:  # built once (its IK compiles), and only when needed
                planners[i] = make_planner(model, scenes[i], PlannerOptions(time_limit=o.time_limit))
            res = planners[i].plan(
                goal, start_config=x_from, t0=t_end - T, seed=o.seed + k, goal_tolerance=0.05, goal_config=x_to
            )
            if res.is_success():
                break
        if not res.is_success():
            reasons.append(f"planner {res.status}: {res.message}")
            T *= 2.0
            continue
        X = np.vstack([res.configs, x_to[None]])
        floor = np.concatenate([np.diff(res.t), [0.0]])  # never faster than the planner's body-speed limit
        # first as late as the timing allows (ending at the motion's first time); among moving obstacles then
        # also from the time it was planned at, waiting at the start (the planner verified those times)
        paths = _candidate_paths(motion, X, floor, slowdowns)
        if not v.validator.static:
            paths += _candidate_paths(motion, X, floor, slowdowns, t_end - T)
        path, why = _first_safe(motion, here, paths)
        if path is not None:
            return path
        reasons.append(f"planned move: {why}")
    raise AdmissionError(
        "--approach: no safe approach from the device's position to the motion's start ("
        + "; ".join(reasons[:1] + reasons[-1:])
        + ")"
    )
