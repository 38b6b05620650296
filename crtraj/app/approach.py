"""Use case: a planned approach from where the device is to the start of an admitted motion (``--approach``).

`plan_approach` is the `crtraj.hardware.stream.ApproachPlanner` the stream use
cases inject into `Streamer.run_path` (the planner lives below hardware, the
streamer never imports it). It returns the motion's path with an approach
that ends at the motion's first time (its t = 0 in the scene's clock), found
in the motion's scene:

1. the straight move in actuator space (a straight line in configuration
   space too), then
2. the default planner (`crtraj.planning.registry.make_planner`) from the
   device's configuration to the start's tip, started at -T (T: a bound on
   the approach's duration), followed by the straight move to the start
   configuration itself (the planner ends on the tip, in any safe pose).

Each candidate is timed within the actuator limits (every move at least its
rest-to-rest limit time, slowed in steps until the sampled set-points pass
the limits) so that it ends at the motion's first time, and is accepted only
when its frames, as `SetpointPath.sample` gives them, pass the motion's
`crtraj.hardware.verify.FrameVerifier` (dense body check with D_sf, cables,
limits) at their times. Among static obstacles time does not matter; among
moving ones the approach is checked at the times it will run. No candidate:
`AdmissionError` (one line), nothing is sent. Units: mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crtraj.core.errors import AdmissionError
from crtraj.hardware.admission import AdmittedMotion
from crtraj.hardware.setpoints import SetpointPath
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import make_planner

# Rest-to-rest move of distance d in time T between two waypoints (cubic, zero end slopes): peak speed
# 1.5 d / T, peak acceleration 6 d / T^2 (as `SetpointPath.with_approach`).
_PEAK_V, _PEAK_A = 1.5, 6.0


@dataclass(frozen=True)
class ApproachOptions:
    """time_limit: planner budget per attempt (s). attempts: planner queries (seeds seed, seed + 1, ...).
    slowdowns: how many times slower than the limit timing a candidate is tried (each is verified)."""

    time_limit: float = 5.0
    attempts: int = 3
    seed: int = 0
    slowdowns: tuple[float, ...] = (1.25, 1.6, 2.0, 3.0)


def _timings(V: np.ndarray, vmax: np.ndarray, amax: np.ndarray, floor: np.ndarray | None) -> np.ndarray:
    """Per-move rest-to-rest limit time (s) of actuator waypoints V (K, n), at least `floor` (K-1,)."""
    d = np.abs(np.diff(V, axis=0))
    T = np.maximum(np.max(_PEAK_V * d / vmax, axis=1), np.max(np.sqrt(_PEAK_A * d / amax), axis=1))
    T = np.maximum(T, 1e-3)
    return T if floor is None else np.maximum(T, floor)


def _candidate_paths(
    motion: AdmittedMotion,
    X: np.ndarray,
    floor: np.ndarray | None,
    slowdowns: tuple[float, ...],
    t_start: float | None = None,
) -> list[SetpointPath]:
    """The motion's path with the configuration path X (ending at its start) as approach, at each slowdown.

    t_start: when the approach starts (s; the time the planner planned it from): it then keeps the planned
    times as far as the limits allow and waits at the start until the motion's first time; None (or a
    timing that does not fit): it ends at the motion's first time.
    """
    acts, robot = motion.actuators, motion.robot
    V = acts.command(robot.cables(X))
    V[-1] = motion.path.values[0]  # bit for bit the motion's first set-point
    keep = np.concatenate([[True], np.any(np.diff(V, axis=0) != 0.0, axis=1)])
    V, floor = V[keep], None if floor is None else floor[keep[1:]]
    if len(V) < 2:
        return [motion.path]
    base = _timings(V, acts.vmax, acts.amax, floor)
    t_end = float(motion.path.t[0])
    out = []
    for s in slowdowns:
        T = np.concatenate([[0.0], np.cumsum(s * base)])
        if t_start is not None and t_start + T[-1] < t_end - 1e-6:
            t = np.append(t_start + T, t_end)  # arrive early, wait at the start (checked like the rest)
            W = np.vstack([V, V[-1:]])
        else:
            t, W = t_end - (T[-1] - T), V
            t[-1] = t_end
        out.append(motion.path.with_approach_path(t, W))
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
    path, why = _first_safe(motion, here, _candidate_paths(motion, np.stack([x_from, x_to]), None, o.slowdowns))
    if path is not None:
        return path
    reasons = [f"straight move: {why}"]
    model = v.model
    planner = make_planner(model, motion.scene, PlannerOptions(time_limit=o.time_limit))
    goal = model.tip_position(x_to)
    # a bound on the approach's duration: the straight move's limit time, three times over, plus the
    # planner's own full-speed time; the plan starts at -T so that it ends before the motion's t = 0
    t_end = float(motion.path.t[0])
    T = 3.0 * float(np.sum(_timings(acts.command(robot.cables(np.stack([x_from, x_to]))), acts.vmax, acts.amax, None)))
    for k in range(o.attempts):
        res = planner.plan(goal, start_config=x_from, t0=t_end - T, seed=o.seed + k, goal_tolerance=0.05)
        if not res.is_success():
            reasons.append(f"planner {res.status}: {res.message}")
            T *= 2.0
            continue
        X = np.vstack([res.configs, x_to[None]])
        floor = np.concatenate([np.diff(res.t), [0.0]])  # never faster than the planner's body-speed limit
        path, why = _first_safe(motion, here, _candidate_paths(motion, X, floor, o.slowdowns, t_end - T))
        if path is not None:
            return path
        reasons.append(f"planned move: {why}")
    raise AdmissionError(
        "--approach: no safe approach from the device's position to the motion's start ("
        + "; ".join(reasons[:1] + reasons[-1:])
        + ")"
    )
