"""Closed-loop simulation of the receding-horizon replanner with the tracking controller.

`ClosedLoop` runs the paper's simulation 2 loop ("the robot periodically
updates its path based on its current position") at the replanner's step dt:

1. read the obstacles (an `crtraj.control.ports.ObstacleSource`: the scene's
   known time functions, or a live feed);
2. keep a reference path toward the goal (`crtraj.control.reference`): plan it
   with the planner from the current configuration when there is none, when it
   becomes invalid (the next seconds of it collide with the predicted
   obstacles), when the robot stalls, after an NLP failure, or every
   `replan_period` seconds;
3. solve the horizon NLP (`crtraj.control.horizon.Replanner`) from the measured
   configuration toward the reference;
4. simulate the tracking controller (`crtraj.control.tracking.TrackingController`,
   with its servo model) over the step to get the motion the robot would
   really make, and verify that motion densely before applying it (the
   continuous body, every instant of the step, `validity.MotionValidator`
   bounds), together with a safe way to stop after it (holding the end
   configuration over the next step is safe);
5. if the move fails verification or the NLP failed, try the previous
   solution's next move, then holding still (actuators commanded to their
   measured positions: the servos stop where they are); if even holding is
   unsafe, apply the least unsafe of these and report it.

A live device is driven through the `crtraj.control.ports.Device` port; the loop
never imports hardware or viewing code. Every step records time,
configuration, actuation, set-points, tip, backbone, obstacle states,
clearance (sampled densely in time, and the conservative bound the decision
used), NLP and planner time, status and the solver's own status text. The
options are `ReplanOptions` (``[replan]``, the NLP) and `LoopOptions`
(``[loop]``, this loop). Units: mm, rad, s.
"""

from __future__ import annotations

import contextlib
import enum
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.control.compiled_tracking import CompiledTracking
from crtraj.control.executed import limit_fractions
from crtraj.control.horizon import INTERPOLATION_GAIN, HorizonResult, HorizonStatus, Replanner, ReplanOptions
from crtraj.control.loop_options import LoopOptions
from crtraj.control.ports import Device, DeviceError, ObstacleSource, TipSensor
from crtraj.control.reference import DirectReference, ReferencePlan, ReferenceSource, TimedReference
from crtraj.control.reference_worker import PendingPlan, ReferenceWorker
from crtraj.control.tracking import TrackingController, TrackingOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.model.kinematics import Model
from crtraj.planning.kernels import Kernels
from crtraj.planning.rate_limits import RateLimits
from crtraj.planning.validity import MotionValidator
from crtraj.world.sources import SceneObstacles

# backbone points used to measure (not decide) clearance and to record the body
REPORT_POINTS = 41

# one step's simulated motion: (q at the end, set-point at the end, sample times (S,),
# configurations at the samples (S, nx), set-points per control period (n_sub, nq))
Motion = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class StepStatus(str, enum.Enum):
    """What the loop did in one control step."""

    MOVE = "move"  # the NLP converged; its first move passed verification and was applied
    SUBOPTIMAL = "suboptimal"  # the NLP stopped at an iteration/time limit at a feasible point; move applied
    FALLBACK = "fallback"  # the NLP's move was unusable; the previous solution's next move was applied
    HOLD = "hold"  # no verified move: the robot held its configuration (verified safe)
    UNSAFE = "unsafe"  # nothing verified safe, not even holding: the least unsafe option was applied
    STALE = "stale"  # no trustworthy obstacle state (live feed stale): held still, nothing could be verified

    def __str__(self) -> str:
        return self.value


class RunStatus(str, enum.Enum):
    """How a closed-loop run ended (`ReplanRun.status`)."""

    REACHED = "reached"  # the tip reached the goal and held it for settle_time
    TIMEOUT = "timeout"  # the goal was not reached within the duration
    INVALID_START = "invalid_start"  # the start configuration is not clear of the obstacles at t = 0
    NO_OBSTACLES = "no_obstacles"  # a live source gave no obstacle state to start from
    DEVICE = "device"  # the device can no longer be driven (stopped, lost, refused)
    ESTOP = "estop"  # nothing was verified safe: the device was e-stopped
    INTERRUPTED = "interrupted"  # Ctrl-C during a live run: the device was held

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class ReplanRun:
    """A closed-loop run. Arrays have one row per recorded time t[k] (k = 0..K).

    status: how the run ended (`RunStatus`); `is_success()`: reached the goal
    and no step broke D_sf (`reached` alone ignores the safety distance).
    t (K+1,) s; x (K+1, nx) actual configurations; q (K+1, nq) actual actuator
    positions (mm); q_command (K+1, nq) the actuator set-point in force at
    t[k] (mm); tip (K+1, 3) mm; backbone
    (K+1, P, 3) mm; centers (K+1, m, 3), radii (K+1, m) obstacle states (mm);
    clearance (K+1,) mm: min over the step ending at t[k] of the body
    clearance (distance to the obstacle surface minus body radius and D_sf),
    sampled densely in time and along the body; distance (K+1,) the same
    without D_sf (negative = the body touches an obstacle); clearance_bound
    (K+1,) mm the conservative bound the decision used; planned (K+1, nx) the
    configuration the NLP planned for t[k]; tip_error (K+1,) mm: actual tip
    to planned tip; goal_error (K+1,) mm: actual tip to goal. Per step (K,):
    step_status (`StepStatus` values), solver_status, nlp_time, plan_time,
    iter_time (s), iterations, replanned (bool), reason (why the reference
    was replanned, or "").
    dense_t, dense_x: every verification sample of the actual motion.
    commands: (K n_sub, nq) actuator set-point of every tracking period of
    length control_dt (s), from t = 0: with the servo model and q[0] they
    reproduce the actual motion at any instant (for independent re-checks).
    executed: (K n_sub + 1, nq) the actual actuation (mm) at the end of every
    tracking period, from t = 0: what `crtraj stream` sends, as the clamped
    cubic B-spline of `crtraj.control.executed`.
    reference_tips: tip polylines of every reference path used, with the
    step index each started at. feed: a live feed's counters, options and
    every rejected or clamped message (loop time t, receiver time, kind,
    reason); {} without a feed.
    """

    t: np.ndarray
    x: np.ndarray
    q: np.ndarray
    q_command: np.ndarray
    tip: np.ndarray
    backbone: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    clearance: np.ndarray
    distance: np.ndarray
    clearance_bound: np.ndarray
    planned: np.ndarray
    tip_error: np.ndarray
    goal_error: np.ndarray
    step_status: tuple[str, ...]
    solver_status: tuple[str, ...]
    nlp_time: np.ndarray
    plan_time: np.ndarray
    iter_time: np.ndarray
    iterations: np.ndarray
    replanned: np.ndarray
    reason: tuple[str, ...]
    dense_t: np.ndarray
    dense_x: np.ndarray
    commands: np.ndarray
    control_dt: float
    reference_tips: tuple[tuple[int, np.ndarray], ...]
    tree_edges: np.ndarray
    goal: np.ndarray
    status: RunStatus
    message: str
    safety: bool
    setup_time: float
    wall_time: float
    nlp: dict[str, Any] = field(default_factory=dict)
    executed: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    late_steps: int = 0
    # steps whose NLP result came after `replan.step_deadline` and was not used (0 without a deadline)
    deadline_misses: int = 0
    live: bool = False
    device: dict[str, Any] = field(default_factory=dict)  # the device's `describe()` of a live-streamed run
    feed: dict[str, Any] = field(default_factory=dict)  # a live feed's counters and rejections (`_Log.feed_record`)
    # largest actuator speed / acceleration as fractions of the limits: of the recorded actuation as
    # streamed (`crtraj.control.executed.limit_fractions`), or, live, of what the device was sent
    # (`Device.limit_fractions`); {} without actuator limits
    limit_fractions: dict[str, float] = field(default_factory=dict)
    # the tip sensor's measurement at every t[k] (K+1, 3) mm, NaN when not seen; None without a sensor
    measured_tip: np.ndarray | None = None
    # references planned beside the loop (`ReferenceWorker`): handover steps, plans taken over, the
    # simulation's waits for due paths (s, outside every iteration time) and why the worker stopped, if
    # it did; {} when every reference was planned inside its control step
    reference_worker: dict[str, Any] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return len(self.step_status)

    @property
    def reached(self) -> bool:
        """The tip reached the goal and held it (whatever the clearance on the way)."""
        return self.status is RunStatus.REACHED

    def is_success(self) -> bool:
        """Reached the goal without any step breaking D_sf."""
        return self.reached and self.safety_violations == 0

    @property
    def collisions(self) -> int:
        """Steps during which the body touched an obstacle (sampled distance < 0)."""
        return int(np.sum(self.distance[1:] < 0.0))

    @property
    def safety_violations(self) -> int:
        """Steps during which the body came closer than D_sf (sampled clearance < 0)."""
        return int(np.sum(self.clearance[1:] < 0.0))

    def summary(self) -> dict[str, Any]:
        """Headline figures (mm, s) for printing and the result file."""
        it = self.iter_time
        counts: dict[str, int] = {}
        for s in self.step_status:
            counts[s] = counts.get(s, 0) + 1
        some = self.steps > 0
        return {
            "outcome": str(self.status),  # the result file's key, kept for its readers
            "reached_goal": self.reached,
            "safety": self.safety,
            "steps": self.steps,
            "duration_s": float(self.t[-1] - self.t[0]),
            "collisions": self.collisions,
            "safety_violations": self.safety_violations,
            "min_clearance_mm": float(np.min(self.clearance[1:])) if some else math.nan,
            "min_distance_mm": float(np.min(self.distance[1:])) if some else math.nan,
            "min_clearance_bound_mm": float(np.min(self.clearance_bound[1:])) if some else math.nan,
            "median_iteration_s": float(np.median(it)) if some else math.nan,
            "p90_iteration_s": float(np.percentile(it, 90)) if some else math.nan,
            "p99_iteration_s": float(np.percentile(it, 99)) if some else math.nan,
            "max_iteration_s": float(np.max(it)) if some else math.nan,
            "step_deadline_s": self.nlp.get("step_deadline_s", 0.0),
            "deadline_misses": self.deadline_misses,
            "median_nlp_s": float(np.median(self.nlp_time)) if some else math.nan,
            "p90_nlp_s": float(np.percentile(self.nlp_time, 90)) if some else math.nan,
            "median_nlp_iterations": float(np.median(self.iterations)) if some else math.nan,
            "final_tip_error_mm": float(self.goal_error[-1]),
            "max_tracking_error_mm": float(np.max(self.tip_error)),
            "reference_plans": int(np.sum(self.replanned)),
            "planner_time_s": float(np.sum(self.plan_time)),
            "reference_planning": "worker" if self.reference_worker else "inline",
            "reference_wait_s": float(self.reference_worker.get("wait_s", 0.0)),
            "status_counts": counts,
            "live_obstacles": self.live,
            "feed_rejected": int(self.feed.get("rejected", 0)),
            "feed_events": dict(self.feed.get("counts", {})),
            "late_steps": self.late_steps,
            "max_velocity_fraction": _finite_or_none(self.limit_fractions.get("max_velocity_fraction")),
            "max_acceleration_fraction": _finite_or_none(self.limit_fractions.get("max_acceleration_fraction")),
            "setup_s": self.setup_time,
            "wall_time_s": self.wall_time,
        }

    def summary_line(self) -> str:
        """One line: reached?, collisions, min clearance, median/p90 time per iteration, final tip error."""
        s = self.summary()
        return (
            f"{self.status}: reached goal {'yes' if self.reached else 'no'}, "
            f"collisions {s['collisions']} (D_sf breaches {s['safety_violations']}), "
            f"min clearance {s['min_clearance_mm']:.2f} mm, "
            f"iteration median {s['median_iteration_s'] * 1e3:.2f} ms / p99 {s['p99_iteration_s'] * 1e3:.2f} ms / "
            f"max {s['max_iteration_s'] * 1e3:.2f} ms, {_deadline_text(s)}, "
            f"final tip error {s['final_tip_error_mm']:.3f} mm, {self.steps} steps, "
            f"{s['reference_plans']} reference plans" + (" (planned beside the loop)" if self.reference_worker else "")
        )

    def limits_line(self) -> str:
        """One line: the executed duration and the largest actuator speed and acceleration as fractions of
        their limits, as the run's actuation will be streamed."""
        s = self.summary()
        v, a = s["max_velocity_fraction"], s["max_acceleration_fraction"]
        if self.device and (v is None or a is None):
            return f"executed {s['duration_s']:.2f} s (no motion was sent to the device)"
        if v is None or a is None:
            return f"executed {s['duration_s']:.2f} s (no actuator limits in the robot file)"
        return (
            f"executed {s['duration_s']:.2f} s, actuators at most {v:.2f} of their velocity limit and "
            f"{a:.2f} of their acceleration limit " + ("(as sent to the device)" if self.device else "(as streamed)")
        )


def _finite_or_none(v: float | None) -> float | None:
    """v, or None when it is missing or not finite (a figure nothing was measured for)."""
    return None if v is None or not math.isfinite(v) else float(v)


def _deadline_text(s: dict[str, Any]) -> str:
    """'no step deadline' or 'N deadline misses (deadline D ms)' from a run summary."""
    d = s["step_deadline_s"]
    if not d:
        return "no step deadline"
    return f"{s['deadline_misses']} deadline misses (deadline {d * 1e3:g} ms)"


class ClosedLoop:
    """The replanning loop for one robot, scene and goal.

    model: the robot's `Model`. scene: `crtraj.world.scene.Scene` (obstacle truth
    and prediction). goal: tip position (mm). start_config: (nx,) the
    robot's configuration at t = 0 (servos settled). options:
    `ReplanOptions` (the horizon NLP). loop_options: `LoopOptions` (this
    loop: duration, reference timing, verification, settling). tracking:
    `TrackingOptions` (its dt must divide the replanner's dt). reference: a
    `ReferenceSource` ((x, t, scene) -> `ReferencePlan`); default: the
    straight motion to `goal_config`. replanner: a prebuilt `Replanner`
    (tests inject failures this way). goal_tolerance: mm. goal_config: used
    by the default reference. initial_reference: a reference already planned
    from start_config at t = 0 (saves the first planner call).
    extra_options: more option sections (name -> object with ``to_dict``)
    recorded in result files. obstacles: where the obstacle states come from
    each step, an `ObstacleSource`: default `SceneObstacles` (the scene's
    known time functions), or `crtraj.world.sources.FeedObstacles` (a live
    feed, extrapolated at constant velocity; the scene then only gives D_sf,
    the workspace and the expected obstacles). rate_limits: the actuators' speed
    and acceleration limits (`RateLimits`, built by the caller from the robot's
    actuators): the NLP, the tracking set-points and the reference timing keep
    within ``replan.limit_fraction`` of them; None: only the mm/s rate limits.
    timer: the clock (s) that times every iteration and judges it against
    ``replan.step_deadline`` (default `time.perf_counter`; tests inject a virtual one).
    """

    def __init__(
        self,
        model: Model,
        scene: Any,
        goal: Any,
        start_config: Any,
        *,
        options: ReplanOptions | None = None,
        loop_options: LoopOptions | None = None,
        tracking: TrackingOptions | None = None,
        reference: ReferenceSource | None = None,
        replanner: Replanner | None = None,
        goal_tolerance: float = 0.5,
        goal_config: Any = None,
        initial_reference: ReferencePlan | None = None,
        extra_options: dict[str, Any] | None = None,
        obstacles: ObstacleSource | None = None,
        rate_limits: RateLimits | None = None,
        tip_sensor: TipSensor | None = None,
        tip_feedback: bool = False,
        tip_gain: float = 0.5,
        timer: Callable[[], float] | None = None,
    ) -> None:
        t_setup = time.perf_counter()
        self.timer = time.perf_counter if timer is None else timer
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.options = ReplanOptions() if options is None else options
        self.loop_options = LoopOptions() if loop_options is None else loop_options
        o = self.options
        self.loop_options.steps(o.dt)  # refuse a huge run before building anything
        self.goal = check_array(goal, "goal", (3,))
        self.x_start = check_array(start_config, "start_config", (self.robot.nx,))
        if not goal_tolerance > 0:
            raise InputError(f"goal_tolerance: must be > 0 mm, got {goal_tolerance}")
        self.goal_tolerance = float(goal_tolerance)
        tr = TrackingOptions() if tracking is None else tracking
        self.n_sub = _control_periods(o, tr)
        # the full actuator limits (reports). The executed motion's samples keep the speeds and the
        # accelerations over the interpolation gain (the set-points enforce that); the NLP plans within
        # limit_fraction of them, which leaves the tracking room to catch up with its plan.
        self.rate_limits = rate_limits
        sampled = None if rate_limits is None else replace(rate_limits, amax=rate_limits.amax / INTERPOLATION_GAIN)
        self.tracker = TrackingController(
            model, tr, rate_limits=None if sampled is None else self._set_point_limits(sampled)
        )
        self.servo = self.tracker.servo
        if reference is None:
            if goal_config is None:
                raise InputError("reference: give a reference source or a goal_config")
            reference = DirectReference(check_array(goal_config, "goal_config", (self.robot.nx,)))
        self.reference_source = reference
        self.initial_reference = initial_reference
        self.tracking_options = tr
        # the loop's own section is recorded in result files beside the others
        self.extra_options = {"loop": self.loop_options, **(extra_options or {})}
        self.replanner = (
            replanner
            if replanner is not None
            else Replanner(
                model,
                o,
                max_obstacles=scene.n_obstacles,
                safety_distance=scene.safety_distance,
                rate_limits=sampled,
            )
        )
        if self.replanner.options.dt != o.dt or o.horizon != self.replanner.N:
            raise InputError("replanner: its dt and horizon must match the loop's options")
        self.obstacles: ObstacleSource = SceneObstacles(scene) if obstacles is None else obstacles
        self._kernels = Kernels()  # compiled kernels and CasADi functions shared by every step's validator
        self.validator = self._validator(scene)
        # with compiled checks (a C compiler), each step's tracking simulation runs in C as well
        self._tracking = self._compiled_tracking() if self.validator.state.kernel is not None else None
        self._scene_now = scene
        A, _ = self.robot.cable_matrix()
        self._A = A
        self._rates = np.append(np.full(3 * self.robot.n_segments, o.max_cable_speed), o.max_z_speed)
        # the tip sensor is always read and recorded; with tip_feedback the loop also corrects its model's
        # error: a low-pass estimate (gain tip_gain per step) of measured minus model tip shifts the goal
        # the reference planner aims the model's tip at (output-disturbance correction)
        if tip_feedback and (tip_sensor is None or not hasattr(self.reference_source, "retarget")):
            raise InputError(
                "tip_feedback: needs a tip sensor and a reference source that can retarget (the planner's)"
            )
        if not 0.0 < tip_gain <= 1.0:
            raise InputError(f"tip_gain: must be in (0, 1], got {tip_gain}")
        self.tip_sensor, self.tip_feedback, self.tip_gain = tip_sensor, bool(tip_feedback), float(tip_gain)
        self.setup_time = time.perf_counter() - t_setup

    # ------------------------------------------------------------ utilities
    def _set_point_limits(self, limits: RateLimits) -> RateLimits:
        """`limits` with each speed capped by the NLP's own per-actuator rate (max_cable_speed,
        max_z_speed): the executed motion then never moves faster than the NLP's first step may, so its
        velocity history never makes the next NLP infeasible. J's row i is scale_i times the cable
        matrix row i (actuator value per mm of actuation)."""
        A, _ = self.robot.cable_matrix()
        o = self.options
        rates = np.append(np.full(3 * self.robot.n_segments, o.max_cable_speed), o.max_z_speed)  # mm/s
        scale = np.sum(limits.jacobian * A, axis=1) / np.sum(A * A, axis=1)
        return replace(limits, vmax=np.minimum(limits.vmax, rates * np.abs(scale)))

    def _compiled_tracking(self) -> CompiledTracking | None:
        """The C tracking simulation (`crtraj.control.compiled_tracking`) from the validity kernel's build cache;
        None in tip mode, without a C compiler, or when it fails to build (said in one stderr line)."""
        cache = self._kernels.build_cache
        h = self.options.dt / self.n_sub
        try:
            return CompiledTracking.load(self.tracker, h, self.validator.space.metric_matrix, cache)
        except (RuntimeError, OSError) as exc:
            print(f"crtraj: compiled tracking unavailable ({exc}): simulating in numpy", file=sys.stderr)
            return None

    def _validator(self, scene: Any) -> MotionValidator:
        lo = self.loop_options
        return MotionValidator(
            self.model, scene, check_points=lo.check_points, resolution=lo.check_resolution, kernels=self._kernels
        )

    @property
    def scene_now(self) -> Any:
        """The obstacles (a `crtraj.world.scene.Scene`, loop time) the current step was checked against: a
        device that verifies what it sends checks against the same snapshot."""
        return self._scene_now

    def _use(self, scene: Any) -> None:
        """Make `scene` the obstacles every check of this step uses."""
        if scene is not self._scene_now:
            self._scene_now = scene
            self.validator = self._validator(scene)

    def _seconds_per(self, dX: np.ndarray) -> np.ndarray:
        """Time (s) each configuration change takes at `reference_speed` times the rate limits."""
        lo = self.loop_options
        dq = np.abs(dX @ self._A.T)
        t_act = np.max(dq / (lo.reference_speed * self._rates), axis=1)
        if self.rate_limits is not None:
            f = self.options.limit_fraction * lo.reference_speed
            t_act = np.maximum(t_act, self.rate_limits.velocity_fraction(dX) / f)
        t_body = self.validator.motion_bound(dX) / (lo.reference_speed * lo.max_body_speed)
        return np.maximum(t_act, t_body)

    def _track(
        self, q: np.ndarray, qc: np.ndarray, x0: np.ndarray, x1: np.ndarray, t: float, inc: np.ndarray
    ) -> Motion:
        """Simulate the tracking controller toward the straight move x0 -> x1 over one step.

        inc: the set-point's configuration change in the control period before t
        (the history of the actuator acceleration limits).
        Returns (q at the end, set-point at the end, sample times (S,),
        actual configurations at the samples (S, nx), set-points per control
        period (n_sub, nq)). The first sample is the current state at t.
        """
        n, ctl, servo, v = self.n_sub, self.tracker, self.servo, self.validator
        dt, resolution = self.options.dt, self.loop_options.check_resolution
        if self._tracking is not None:
            done = self._tracking.step(q, qc, x0, x1, t, inc, n, dt, resolution)
            if done is not None:
                return done
        h = dt / n
        rate = (x1 - x0) / dt
        ts, xs = [np.array([t])], [servo.config(q)[None]]
        cmds = np.empty((n, self.robot.nq))
        for j in range(n):
            xm = servo.config(q)
            cmd = ctl.step(xm, qc, x0 + (j + 1) / n * (x1 - x0), h, x_reference_rate=rate, previous_increment=inc)
            inc = cmd.increment
            q_end = servo.advance(q, cmd.q, h)
            span = float(v.motion_bound(servo.config(q_end) - xm))
            ns = max(1, math.ceil(2.0 * span / resolution))
            tau = h * np.arange(1, ns + 1) / ns
            ts.append(t + j * h + tau)
            xs.append(servo.config(servo.trajectory(q, cmd.q, tau)))
            q, qc = q_end, cmd.q
            cmds[j] = qc
        return q, qc, np.concatenate(ts), np.concatenate(xs), cmds

    def _verify(self, T: np.ndarray, X: np.ndarray, after: tuple[float, float] | None) -> float:
        """Conservative body clearance (mm, minus D_sf) of the sampled motion X at times T.

        after: a time window (s) over which the last configuration, held
        still, must also be clear (so the robot can always stop safely).

        Between two samples every actuator moves monotonically (first-order
        servos), and the bending part moves along a straight line, so each
        configuration in between is within half the body-motion bound of the
        two samples from one of them; each sample therefore must clear, over
        the time window from its previous to its next sample, the obstacles
        by that half bound on top of the validator's chord/sagitta bounds.
        """
        v = self.validator
        if len(X) == 1:
            half, t_lo, t_hi = np.zeros(1), T[:1], T[:1]
        else:
            B = v.motion_bound(np.diff(X, axis=0))
            half = 0.5 * np.concatenate([[B[0]], np.maximum(B[:-1], B[1:]), [B[-1]]])
            t_lo = np.concatenate([[T[0]], T[:-1]])
            t_hi = np.concatenate([T[1:], [T[-1]]])
        if after is not None:
            X = np.concatenate([X, X[-1:]])
            half = np.append(half, 0.0)
            t_lo = np.append(t_lo, after[0])
            t_hi = np.append(t_hi, after[1])
        return float(np.min(v.clearance(X, t_lo, t_hi, half)))

    def _measure(self, T: np.ndarray, X: np.ndarray) -> float:
        """Sampled (not conservative) body clearance (mm, minus D_sf) along the motion, many points."""
        P = self.model.points(X, REPORT_POINTS)
        return float(np.min(self._scene_now.clearance_points(P, T, inflate=self.robot.body_radius)))

    def _at_rest(self, st: _State) -> bool:
        """The last control period moved every actuator slowly enough to stop within its acceleration limit
        in one period: the streamed curve (`crtraj.control.executed`) ends at rest with an acceleration of
        at most |last period's step| / h^2, which then keeps the limit."""
        if self.rate_limits is None:
            return True
        h = self.options.dt / self.n_sub
        f = self.options.limit_fraction
        step = np.abs(self.rate_limits.jacobian @ (st.x - self.servo.config(st.q_last)))
        return bool(np.all(step <= f * self.rate_limits.amax * h * h))

    def _reference_valid(self, ref: TimedReference, s_now: float, t: float) -> bool:
        """The next stretch of the reference is clear of the obstacles at the times it would be reached."""
        o = self.options
        look = max(2.0 * o.horizon * o.dt, 2.0)
        s = np.linspace(s_now, min(s_now + look, ref.end), 12)
        X = ref.at(s)
        tt = t + (s - s_now)
        return bool(np.all(self.validator.clearance(X, tt - o.dt, tt + o.dt) >= 0.0))

    # ------------------------------------------------------------------- run
    def run(
        self,
        *,
        progress: Callable[[int, float, str], None] | None = None,
        realtime: bool | None = None,
        device: Device | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> ReplanRun:
        """Simulate from the start configuration until the goal is held, or `duration` runs out.

        progress: called after every step with (step index, time s, status).
        realtime: pace the steps by the wall clock (default: only with a live
        obstacle source, whose states are only meaningful in real time).
        device: drive a device live (a `Device`, e.g. `crtraj.hardware.link.DeviceLink`; real
        time): the run starts where the device is, every verified move is sent as it is chosen,
        the device's telemetry is the measured configuration, a held or stale
        step holds the device, an unsafe step e-stops it and ends the run, and
        Ctrl-C holds it and ends the run (status "interrupted"). The device is
        finished (settled at the final actuation) and closed on return.
        clock, sleep: the time (s) and the sleep that pace a real-time run without a device and
        bound the wait for a live feed's first states (default: the wall clock); a virtual clock
        shared with the feed makes a live run independent of the machine's speed.
        """
        t_wall = time.perf_counter()
        clock = time.perf_counter if clock is None else clock
        sleep = time.sleep if sleep is None else sleep
        live = bool(self.obstacles.live)
        realtime = live if realtime is None or device is not None else bool(realtime)
        q = self.tracker.initial_command(self.x_start) if device is None else device.start_actuation()
        st = _State(q=q, qc=q.copy(), x=self.servo.config(q))
        st.x_prev = st.x.copy()
        st.target = self.goal.copy()
        self._sense(st)
        self.replanner.reset()
        log = _Log()
        refused = self._start(log, st, live, clock, sleep)
        if refused is not None:
            return self._finish(log, st, *refused, t_wall, device)
        self._initial_reference(st)
        # a simulated run waits for a due reference (real time would have given the worker those seconds);
        # a real-time run takes it at the first step it has arrived by
        st.worker, st.wait_reference = self._reference_worker(), not realtime
        self._warm_up(st)
        t_clock = clock()
        if device is not None:
            device.begin(time.perf_counter())
        try:
            return self._steps(log, st, t_wall, (clock, sleep, t_clock), realtime, progress, device)
        except KeyboardInterrupt:
            if device is None:
                raise
            device.hold("interrupted (Ctrl-C)")
            msg = "interrupted (Ctrl-C): device held"
            return self._finish(log, st, RunStatus.INTERRUPTED, msg, t_wall, device)
        finally:
            if st.worker is not None:
                st.worker.close()

    def _initial_reference(self, st: _State) -> None:
        """Follow the reference planned before the loop (if any) from the start: step 0 records it (and,
        planning inline, is charged its planner time), but does not spend its own time taking it over."""
        plan = self.initial_reference
        if plan is None:
            return
        reason = self._replan_reason(st)
        st.t_last_attempt = st.t
        st.first_plan = (f"{reason}: {plan.status}", plan.wall_time, self._adopt(st, 0, plan, None))

    def _warm_up(self, st: _State) -> None:
        """Run a step's computations once, untimed, before the first step, and keep nothing of it. Their
        first calls allocate buffers, fill caches and (after the worker's fork) copy the pages they write:
        milliseconds that would otherwise land in step 0. The solve is the base `Replanner.solve` (an
        injected replanner's own bookkeeping never sees it), and its warm start is forgotten."""
        rp, dt = self.replanner, self.options.dt
        res = Replanner.solve(
            rp,
            st.x,
            st.horizon_reference(rp.N, dt),
            rp.obstacles_from_scene(self._scene_now, st.t),
            x_prev=st.x_prev,
        )
        rp.reset()
        sim = self._track(st.q, st.qc, st.x, res.configs[0] if res.feasible else st.x, st.t, st.inc)
        if self.options.safety:
            self._verify(sim[2], sim[3], (st.t + dt, st.t + 2 * dt))
            if st.ref is not None:
                self._reference_valid(st.ref, st.s_ref, st.t)

    def _reference_worker(self) -> ReferenceWorker | None:
        """The started reference worker with ``loop.reference_delay > 0``; None to plan inside the steps
        (no delay, or a platform without fork: said in one stderr line)."""
        if not self.loop_options.handover_steps(self.options.dt):
            return None
        if not ReferenceWorker.can_fork():
            print("crtraj: this platform cannot fork: reference paths are planned inside the steps", file=sys.stderr)
            return None
        # the planner stops itself after planner_time; a worker silent for a minute longer is hung
        worker = ReferenceWorker(self.reference_source, self.robot.nx, self.loop_options.planner_time + 60.0)
        worker.start()
        return worker

    def _start(
        self,
        log: _Log,
        st: _State,
        live: bool,
        clock: Callable[[], float],
        sleep: Callable[[float], None],
    ) -> tuple[RunStatus, str] | None:
        """Record t = 0 and check that the run can start: (status, why) when it cannot, else None."""
        scene0, why = self.obstacles.at(0.0)
        deadline = clock() + 2.0
        while scene0 is None and live and clock() < deadline:
            sleep(0.01)  # give a live feed a moment to deliver its first states
            scene0, why = self.obstacles.at(0.0)
        log.feed_events(self.obstacles, 0.0)
        still = np.zeros((0, self.robot.nq))
        if scene0 is None:
            nan = math.nan
            log.record(0.0, st, nan, nan, nan, st.x, still, np.zeros(1), st.x[None], self.scene)
            return RunStatus.NO_OBSTACLES, f"no obstacle state to start from: {why}"
        self._use(scene0)
        c0 = self._measure(np.array([0.0]), st.x[None])
        b0 = self._verify(np.array([0.0]), st.x[None], None)
        d0 = c0 + self.scene.safety_distance
        log.record(0.0, st, c0, d0, b0, st.x, still, np.array([0.0]), st.x[None], scene0)
        if self.options.safety and b0 < 0.0:
            msg = f"the start configuration is not clear of the obstacles at t = 0 (bound {b0:.2f} mm)"
            return RunStatus.INVALID_START, msg
        return None

    def _steps(
        self,
        log: _Log,
        st: _State,
        t_wall: float,
        pacing: tuple[Callable[[], float], Callable[[float], None], float],
        realtime: bool,
        progress: Callable[[int, float, str], None] | None,
        device: Device | None,
    ) -> ReplanRun:
        """The control steps of `run` after the start checks. pacing: (clock, sleep, clock at t = 0)."""
        lo = self.loop_options
        settled_since: float | None = None
        for k in range(lo.steps(self.options.dt)):
            t = st.t
            t_iter = self.timer()
            if device is not None:
                why_not = device.problem()
                if why_not:
                    return self._finish(log, st, RunStatus.DEVICE, why_not, t_wall, device)
                st.q, st.qc, _ = device.measure(t, st.q, st.qc)
                st.x = self.servo.config(st.q)
            status = self._step(k, st, log, device, t_iter)
            self._sense(st)
            if progress is not None:
                progress(k, st.t, str(status))
            if device is not None and status is StepStatus.UNSAFE:
                msg = f"unsafe step at t={t:.2f} s: nothing verified safe, device e-stopped"
                return self._finish(log, st, RunStatus.ESTOP, msg, t_wall, device)
            # with tip feedback the goal is where the corrected tip (model tip + estimated error) reaches it
            err = float(np.linalg.norm(self.model.tip_position(st.x) - st.target))
            if err > self.goal_tolerance or not self._at_rest(st):
                settled_since = None
            else:
                settled_since = st.t if settled_since is None else settled_since
                if st.t - settled_since >= lo.settle_time - 1e-9:
                    return self._finish(log, st, RunStatus.REACHED, "goal reached and held", t_wall, device)
            self._pace(log, st.t, realtime, pacing, device)
        msg = f"goal not reached within {lo.duration:g} s"
        return self._finish(log, st, RunStatus.TIMEOUT, msg, t_wall, device)

    def _step(self, k: int, st: _State, log: _Log, device: Device | None, t_iter: float) -> StepStatus:
        """Control step k from st.t: choose, verify, (send,) apply and record one move; its status.
        t_iter: `self.timer` when the step began (its iteration time is charged from then). An NLP
        result that arrives after ``replan.step_deadline`` is not used: the step falls back to the last
        plan's next move (verified now), or a verified hold (`_choose`); the late plan, if feasible,
        becomes the last plan for the next step."""
        t, dt, rp = st.t, self.options.dt, self.replanner
        scene_t, why = self.obstacles.at(t)
        log.feed_events(self.obstacles, t)
        if scene_t is None:
            # no trustworthy obstacle state: keep the actuators where they are and say so
            status, res = StepStatus.STALE, _skipped(rp, f"skipped: {why}")
            x1, bound, sim = st.x.copy(), math.nan, self._hold(st)
            reason, plan_time, replanned, charged = "", 0.0, False, 0.0
            st.last_plan = None
            rp.reset()
        else:
            self._use(scene_t)
            reason, plan_time, replanned, charged = self._update_reference(st, k)
            X_ref = st.horizon_reference(rp.N, dt)
            obstacles = rp.obstacles_from_scene(scene_t, t)
            left = self.options.step_deadline - (self.timer() - t_iter) if self.options.step_deadline else None
            late = self._solve(st.x, X_ref, obstacles, st.x_prev, left)
            res = self._judge_deadline(late, self.timer() - t_iter + charged - st.t_waited, log)
            st.nlp_failed = not res.feasible and res.status is not HorizonStatus.SKIPPED
            # a late but feasible solve still warm-starts the next one: resetting it would make the next
            # solve cold, hence slower, hence late again (a run of misses feeding itself)
            status, x1, sim, bound = self._choose(st, res, keep_warm=res is not late and late.feasible)
            if res is not late and late.feasible:
                # the late plan (for t + dt, t + 2 dt, ...) is the next step's fallback: a run of misses
                # follows it one step behind (each move re-verified) instead of running out of plan
                st.last_plan = late.configs
        iter_time = self.timer() - t_iter + charged - st.t_waited
        st.t_waited = 0.0
        q_new, qc_new, T, X, cmds = sim
        if device is not None:
            self._drive(device, status, t, st.q, cmds, why, bound)
        if scene_t is not None:
            reason = "; ".join(filter(None, (reason, self._ask_reference(st, k))))
        periods = self._periods(st.q, cmds)
        measured = self._measure(T, X)
        # the set-point's last change (configuration): the next step's acceleration history
        before = cmds[-2] if len(cmds) > 1 else st.qc
        st.inc = self.servo.config(qc_new) - self.servo.config(before)
        st.x_prev, st.x, st.q, st.qc = st.x, self.servo.config(q_new), q_new, qc_new
        st.q_last = periods[-2] if len(periods) > 1 else st.q
        st.t = round((k + 1) * dt, 12)
        dist = measured + self.scene.safety_distance
        log.record(st.t, st, measured, dist, bound, x1, cmds, T, X, self._scene_now)
        log.executed.append(periods)
        log.step(status, res, plan_time, iter_time, replanned, reason)
        return status

    def _periods(self, q: np.ndarray, cmds: np.ndarray) -> np.ndarray:
        """Actual actuation (n_sub, nq) mm at the end of each control period of a step that starts at q
        and holds each of `cmds` for one period (the servo model, as `_track` advances it)."""
        h = self.options.dt / self.n_sub
        out = np.empty((len(cmds), self.robot.nq))
        for j, c in enumerate(cmds):
            q = self.servo.advance(q, c, h)
            out[j] = q
        return out

    def _judge_deadline(self, res: HorizonResult, elapsed: float, log: _Log) -> HorizonResult:
        """`res`, or, when it came after the step deadline (elapsed s since the step began), the record of
        an unused solve: status SKIPPED and the solver's own status with the miss appended (never lost)."""
        deadline = self.options.step_deadline
        if not deadline or elapsed <= deadline:
            return res
        log.deadline_misses += 1
        why = f"{res.solver_status}; deadline missed ({elapsed * 1e3:.2f} ms > {deadline * 1e3:g} ms): not used"
        return replace(res, status=HorizonStatus.SKIPPED, solver_status=why)

    def _drive(
        self, device: Device, status: StepStatus, t: float, q0: np.ndarray, cmds: np.ndarray, why: str, bound: float
    ) -> None:
        """Pass the step starting at t (from actuation q0, mm) to the device: hold, e-stop or move."""
        if status in (StepStatus.STALE, StepStatus.HOLD):
            device.hold(f"replanner {status} at t={t:.2f} s" + (f": {why}" if why else ""))
        elif status is StepStatus.UNSAFE:
            device.estop(f"unsafe step at t={t:.2f} s (clearance bound {bound:.2f} mm)")
        else:
            # not sent (held or stopped meanwhile): `device.problem()` at the next step says whether that is final
            with contextlib.suppress(DeviceError):
                device.move(t, q0, cmds, self.options.dt / self.n_sub)

    def _pace(
        self,
        log: _Log,
        t: float,
        realtime: bool,
        pacing: tuple[Callable[[], float], Callable[[float], None], float],
        device: Device | None,
    ) -> None:
        """Wait until loop time t (s) is due in a real-time run; count the steps that came late."""
        if device is not None:
            log.late += device.pace(t)
        elif realtime:
            clock, sleep, t_clock = pacing
            lag = clock() - t_clock - t
            if lag < 0.0:
                sleep(-lag)
            elif lag > self.options.dt:
                log.late += 1

    def _hold(self, st: _State) -> Motion:
        """The motion of holding still for one step: actuators commanded to their measured positions."""
        t, dt = st.t, self.options.dt
        return (
            st.q.copy(),
            st.q.copy(),
            np.array([t, t + dt]),
            np.stack([st.x, st.x]),
            np.repeat(st.q[None], self.n_sub, axis=0),
        )

    def _sense(self, st: _State) -> None:
        """Read the tip sensor (if any) at st.t; with tip feedback, update the model-error estimate and
        retarget the reference when the corrected goal moved by more than half the goal tolerance."""
        if self.tip_sensor is None:
            return
        m = self.tip_sensor.tip(st.t, st.q)
        st.measured.append(np.full(3, np.nan) if m is None else np.asarray(m, dtype=float))
        if m is None or not self.tip_feedback:
            return
        bias = np.asarray(m, dtype=float) - self.model.tip_position(st.x)
        st.tip_bias = st.tip_bias + self.tip_gain * (bias - st.tip_bias)
        target = self.goal - st.tip_bias
        if np.linalg.norm(target - st.target) > 0.5 * self.goal_tolerance:
            st.target = target
            self.reference_source.retarget(target)  # type: ignore[attr-defined]
            st.goal_version += 1

    def _replan_reason(self, st: _State) -> str:
        """Why the reference path must be planned again now ('' when it need not)."""
        lo, t, ref = self.loop_options, st.t, st.ref
        if ref is None:
            return "no reference"
        if st.ref_goal_version != st.goal_version:
            return "tip correction"
        if st.nlp_failed:
            return "NLP failed"
        if lo.replan_period > 0 and t - st.t_last_plan >= lo.replan_period - 1e-9:
            return "periodic"
        if t - st.progress_t >= lo.stall_time and st.s_ref < ref.end - 1e-9:
            return "stalled"
        if self.options.safety and not self._reference_valid(ref, st.s_ref, t):
            return "reference blocked"
        return ""

    def _update_reference(self, st: _State, k: int) -> tuple[str, float, bool, float]:
        """Replan the reference path when needed; returns (reason, planner time s, replanned, time to charge s).

        Inline (no worker) the plan is made now and its time is part of the step; with a worker the step
        takes over a due path here and asks for a new one after its move (`_ask_reference`), and the plan's
        time is the worker's."""
        said, plan_time, replanned = self._take_reference(st, k)
        charged = 0.0
        if k == 0 and st.first_plan is not None:
            # the reference planned before the loop: inline, charged to this iteration; with a worker no
            # reference is planned inside a step, and that one was part of the setup
            said, plan_time, replanned = st.first_plan
            charged = plan_time if st.worker is None else 0.0
        if st.worker is None:
            reason = self._replan_reason(st)
            if reason and not self._waiting(st, reason):
                st.t_last_attempt = st.t
                plan = self.reference_source(st.x, st.t, self._scene_now)
                replanned = self._adopt(st, k, plan, st.goal_version)
                said, plan_time = f"{reason}: {plan.status}", plan.wall_time
        st.locate(self.options.dt * self.replanner.N)
        return said, plan_time, replanned, charged

    def _waiting(self, st: _State, reason: str) -> bool:
        """After a failed attempt, wait a little (1 s, or a step) before asking the planner again."""
        return reason != "periodic" and st.t - st.t_last_attempt < max(1.0, self.options.dt) - 1e-9

    def _ask_reference(self, st: _State, k: int) -> str:
        """With a worker, after step k's move was chosen (and sent): ask for a new reference path when one is
        needed, from the step's start (st.x at st.t), to be taken over `handover_steps` later; what was asked
        ('' nothing). Neither the check (the reference's clearance ahead, about 0.1 ms) nor the request is in
        the step's latency: the move does not depend on them, and the path arrives steps later anyway."""
        w = st.worker
        if w is None or w.pending is not None:
            return ""  # one request at a time
        reason = self._replan_reason(st)
        if not reason or self._waiting(st, reason):
            return ""
        st.t_last_attempt = st.t
        due = k + self.loop_options.handover_steps(self.options.dt)
        w.submit(st.x, st.t, self._scene_now, PendingPlan(k, due, reason, st.goal_version))
        return f"{reason}: asked"

    def _take_reference(self, st: _State, k: int) -> tuple[str, float, bool]:
        """Take over the worker's path when it is due: (reason text, planner time s, adopted); a worker that
        failed is closed (said once on stderr) and the loop plans inside its steps from then on."""
        w = st.worker
        if w is None or w.pending is None or k < w.pending.due:
            return "", 0.0, False
        asked = w.pending
        waited = w.wait_time
        plan = w.take(st.wait_reference, self.timer)
        # a simulated run's wait for a due path is not part of the step: in real time the worker would have
        # had the delay's seconds (the run records the waits as the worker's wait_s)
        st.t_waited += w.wait_time - waited
        if plan is None:
            return "", 0.0, False
        ok = self._adopt(st, k, plan, asked.goal_version)
        if not w.alive:
            print(f"crtraj: {w.failure}: reference paths are planned inside the steps now", file=sys.stderr)
            st.worker_record = w.record()
            w.close()
            st.worker = None
        return f"{asked.reason}: {plan.status}", plan.wall_time, ok

    def _adopt(self, st: _State, k: int, plan: ReferencePlan, goal_version: int | None) -> bool:
        """Follow `plan` from step k on when it reached the goal; whether it did. goal_version: the tip
        goal's version the plan aims at (None: planned before the loop, for the task's goal)."""
        if not plan.is_success():
            return False
        t = st.t
        st.ref = TimedReference(plan.configs, self._seconds_per, self.validator.metric)
        st.s_ref, st.progress_s, st.progress_t, st.t_last_plan = 0.0, 0.0, t, t
        st.refs_used.append((k, self.model.tip_position(st.ref.X)))
        if len(plan.tree_edges):
            st.tree_edges = plan.tree_edges
        if goal_version is not None:
            st.ref_goal_version = goal_version
        return True

    def _choose(
        self, st: _State, res: HorizonResult, keep_warm: bool = False
    ) -> tuple[StepStatus, np.ndarray, Motion, float]:
        """The move to apply: the NLP's, else the previous solution's next one, else holding still.
        keep_warm: the replanner's warm start stays even when the NLP's move is not applied.

        Returns (status, planned configuration for the step's end, simulated
        motion (q end, set-point end, sample times, sample configurations,
        set-points per period), conservative clearance bound (mm; NaN without safety)).
        """
        t, dt = st.t, self.options.dt
        cands: list[tuple[StepStatus, np.ndarray]] = []
        if res.feasible:
            cands.append((StepStatus.MOVE if res.is_success() else StepStatus.SUBOPTIMAL, res.configs[0]))
        if st.last_plan is not None and len(st.last_plan) > 1:
            cands.append((StepStatus.FALLBACK, st.last_plan[1]))
        tried: list[tuple[float, StepStatus, np.ndarray, Motion]] = []
        chosen: tuple[StepStatus, np.ndarray, Motion, float] | None = None
        for status, x1 in cands:
            sim = self._track(st.q, st.qc, st.x, x1, t, st.inc)
            if not self.options.safety:
                chosen = (status, x1, sim, math.nan)
                break
            bound = self._verify(sim[2], sim[3], (t + dt, t + 2 * dt))
            tried.append((bound, status, x1, sim))
            if bound >= 0.0:
                chosen = (status, x1, sim, bound)
                break
        if chosen is None:
            chosen = self._least_unsafe(st, tried)
        self._keep_plan(st, chosen[0], res, keep_warm)
        return chosen

    def _least_unsafe(
        self, st: _State, tried: list[tuple[float, StepStatus, np.ndarray, Motion]]
    ) -> tuple[StepStatus, np.ndarray, Motion, float]:
        """No candidate move verified: hold (command every actuator to its measured position, so the
        first-order servos stay put) when that is safe or no worse than the best move tried, else that move."""
        t = st.t
        hold = self._hold(st)
        bound_h = float(self.validator.clearance(st.x[None], t, t + self.options.dt)[0])
        best = max(tried, key=lambda c: c[0]) if tried else None
        if bound_h >= 0.0 or best is None or best[0] <= bound_h:
            return (StepStatus.HOLD if bound_h >= 0.0 else StepStatus.UNSAFE, st.x.copy(), hold, bound_h)
        return (StepStatus.UNSAFE, best[2], best[3], best[0])

    def _keep_plan(self, st: _State, status: StepStatus, res: HorizonResult, keep_warm: bool = False) -> None:
        """Keep what remains of the applied NLP solution (the next step's fallback); forget the replanner's
        warm start when the NLP's move was not applied, unless `keep_warm` (the replanner still checks that
        it starts within reach of the next configuration)."""
        if status in (StepStatus.MOVE, StepStatus.SUBOPTIMAL):
            st.last_plan = res.configs
        elif status is StepStatus.FALLBACK and st.last_plan is not None:
            st.last_plan = st.last_plan[1:]
        else:
            st.last_plan = None
        if status is not StepStatus.MOVE and status is not StepStatus.SUBOPTIMAL and not keep_warm:
            # the warm start no longer matches where the robot is going
            self.replanner.reset()

    def _solve(
        self, x: np.ndarray, X_ref: np.ndarray, obstacles: np.ndarray, x_prev: np.ndarray, time_left: float | None
    ) -> HorizonResult:
        """The horizon NLP from x; time_left: s left of the step deadline (None: no deadline)."""
        return self.replanner.solve(x, X_ref, obstacles, x_prev=x_prev, time_left=time_left)

    def _finish(
        self,
        log: _Log,
        st: _State,
        status: RunStatus,
        message: str,
        t_wall: float,
        device: Device | None = None,
    ) -> ReplanRun:
        """Finish the device (if any) and turn the log into the run's record."""
        model = self.model
        if device is not None:
            device.finish(st.q)
        t = np.array(log.t)
        X = np.array(log.x)
        planned = np.array(log.planned)
        executed = np.vstack([log.q[0][None], *log.executed])
        h = self.options.dt / self.n_sub
        xe = self.servo.config(executed)
        if device is not None:
            # live: what the device was sent (the loop's executed samples restart from each step's
            # measured state, so their second differences are not a motion anything received)
            fractions = device.limit_fractions()
        elif self.rate_limits is not None:
            fractions = limit_fractions(float(t[0]), h, xe, self.rate_limits)
        else:
            fractions = {}
        tips = model.tip_position(X)
        nq = self.robot.nq
        return ReplanRun(
            t=t,
            x=X,
            q=np.array(log.q),
            q_command=np.array(log.qc),
            tip=tips,
            backbone=model.points(X, REPORT_POINTS),
            centers=np.array(log.centers),
            radii=np.array(log.radii),
            clearance=np.array(log.clear),
            distance=np.array(log.dist),
            clearance_bound=np.array(log.bound),
            planned=planned,
            tip_error=np.linalg.norm(tips - model.tip_position(planned), axis=1),
            goal_error=np.linalg.norm(tips - self.goal, axis=1),
            step_status=tuple(log.status),
            solver_status=tuple(log.solver),
            nlp_time=np.array(log.nlp, dtype=float),
            plan_time=np.array(log.plan, dtype=float),
            iter_time=np.array(log.iter, dtype=float),
            iterations=np.array(log.its, dtype=int),
            replanned=np.array(log.replanned, dtype=bool),
            reason=tuple(log.reason),
            dense_t=np.concatenate(log.dense_t),
            dense_x=np.concatenate(log.dense_x),
            commands=np.concatenate(log.commands) if log.commands else np.zeros((0, nq)),
            control_dt=self.options.dt / self.n_sub,
            executed=executed,
            reference_tips=tuple(st.refs_used),
            tree_edges=st.tree_edges,
            goal=self.goal,
            status=status,
            message=message,
            safety=self.options.safety,
            setup_time=self.setup_time,
            wall_time=time.perf_counter() - t_wall,
            nlp=self.replanner.describe(),
            late_steps=log.late,
            deadline_misses=log.deadline_misses,
            live=bool(self.obstacles.live),
            device={} if device is None else device.describe(),
            feed=log.feed_record(self.obstacles),
            limit_fractions=fractions,
            measured_tip=np.array(st.measured) if self.tip_sensor is not None else None,
            reference_worker=self._worker_record(st),
        )

    def _worker_record(self, st: _State) -> dict[str, Any]:
        """The run's `ReplanRun.reference_worker` record ({} when references were planned inline)."""
        rec = st.worker.record() if st.worker is not None else st.worker_record
        return {"handover_steps": self.loop_options.handover_steps(self.options.dt), **rec} if rec else {}


def _control_periods(o: ReplanOptions, tr: TrackingOptions) -> int:
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


def _skipped(rp: Replanner, why: str) -> HorizonResult:
    """The record of a step whose NLP was not solved (why: the solver status text)."""
    nan = np.full((rp.N, rp.nx), np.nan)
    return HorizonResult(
        nan, np.full((rp.N, 3), np.nan), HorizonStatus.SKIPPED, why, 0, 0.0, math.inf, math.nan, math.inf
    )


class _State:
    """Mutable state of one run: actual and commanded actuators, reference path and progress."""

    def __init__(self, q: np.ndarray, qc: np.ndarray, x: np.ndarray) -> None:
        self.t = 0.0
        self.q, self.qc, self.x = q, qc, x
        self.x_prev = x
        self.q_last = q  # actual actuation one control period before now
        self.inc = np.zeros_like(x)  # the set-point's configuration change in the last control period
        self.ref: TimedReference | None = None
        self.s_ref = 0.0  # progress along the reference (s of reference time)
        self.progress_s, self.progress_t = 0.0, 0.0  # last time the progress grew
        self.t_last_plan = -math.inf
        self.t_last_attempt = -math.inf
        self.last_plan: np.ndarray | None = None  # remaining steps of the last applied NLP solution
        self.nlp_failed = False
        self.refs_used: list[tuple[int, np.ndarray]] = []
        self.tree_edges = np.zeros((0, 2, 3))
        self.target = np.zeros(3)  # the tip goal the reference aims the model's tip at (mm)
        self.tip_bias = np.zeros(3)  # estimated measured minus model tip (mm)
        # the tip goal's version (one more at each retarget) and the version the reference aims at: when
        # they differ the target moved, and the reference is planned again
        self.goal_version, self.ref_goal_version = 0, 0
        self.worker: ReferenceWorker | None = None  # plans references beside the loop (`_reference_worker`)
        self.wait_reference = True  # at a due step, wait for the worker's path (simulated runs)
        self.worker_record: dict[str, Any] = {}  # a worker's record once it has been closed after failing
        self.t_waited = 0.0  # s this step waited for a due reference path (simulated runs; not charged)
        # step 0's record of the reference planned before the loop: (reason, planner time s, followed)
        self.first_plan: tuple[str, float, bool] | None = None
        self.measured: list[np.ndarray] = []  # the tip sensor's readings (mm)

    def locate(self, ahead: float) -> None:
        """Move the progress to the reference point nearest to the robot."""
        ref = self.ref
        if ref is None:
            return
        self.s_ref = ref.locate(self.x, self.s_ref, back=1.0, ahead=ahead)
        if self.s_ref > self.progress_s + 1e-3 or self.s_ref >= ref.end - 1e-9:
            self.progress_s, self.progress_t = self.s_ref, self.t

    def horizon_reference(self, N: int, dt: float) -> np.ndarray:
        """Reference configurations (N, nx) for the horizon's steps; hold still without a reference."""
        if self.ref is None:
            return np.broadcast_to(self.x, (N, len(self.x))).copy()
        return self.ref.at(self.s_ref + dt * np.arange(1, N + 1))


class _Log:
    """Per-time and per-step records of one run."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.x: list[np.ndarray] = []
        self.q: list[np.ndarray] = []
        self.qc: list[np.ndarray] = []
        self.clear: list[float] = []
        self.dist: list[float] = []
        self.bound: list[float] = []
        self.planned: list[np.ndarray] = []
        self.status: list[str] = []
        self.solver: list[str] = []
        self.nlp: list[float] = []
        self.plan: list[float] = []
        self.iter: list[float] = []
        self.its: list[int] = []
        self.replanned: list[bool] = []
        self.reason: list[str] = []
        self.dense_t: list[np.ndarray] = []
        self.dense_x: list[np.ndarray] = []
        self.commands: list[np.ndarray] = []
        self.executed: list[np.ndarray] = []  # per step: actual actuation at the end of each control period
        self.centers: list[np.ndarray] = []
        self.radii: list[np.ndarray] = []
        self.late = 0  # real-time steps that finished more than one step late
        self.deadline_misses = 0  # NLP results that came after replan.step_deadline (not used)
        self.feed: list[dict[str, Any]] = []  # the live feed's rejected/clamped messages, with loop time

    def feed_events(self, source: ObstacleSource, t: float) -> None:
        """Record the source's new events (a live feed's rejected or clamped messages) at loop time t (s)."""
        self.feed.extend({"t": float(t), **e.to_dict()} for e in source.new_events())

    def feed_record(self, source: ObstacleSource) -> dict[str, Any]:
        """The feed section of a live run: counters, options and every recorded event ({} without a feed)."""
        if not source.live:
            return {}
        self.feed_events(source, self.t[-1] if self.t else 0.0)
        return {**source.describe(), "events": list(self.feed)}

    def record(
        self,
        t: float,
        st: _State,
        clear: float,
        dist: float,
        bound: float,
        planned: np.ndarray,
        commands: np.ndarray,
        T: np.ndarray,
        X: np.ndarray,
        scene: Any,
    ) -> None:
        """The state at time t, the motion samples (T, X) that led to it (first sample = previous time)
        and the obstacles (as `scene` knows them) at t."""
        self.t.append(t)
        self.x.append(st.x)
        self.q.append(st.q)
        self.qc.append(st.qc)
        self.clear.append(clear)
        self.dist.append(dist)
        self.bound.append(bound)
        self.planned.append(np.asarray(planned, dtype=float))
        if len(commands):
            self.commands.append(commands)
        c, r = scene.states(t)
        self.centers.append(c.reshape(-1, 3))
        self.radii.append(r.reshape(-1))
        skip = 1 if self.dense_t else 0
        self.dense_t.append(T[skip:])
        self.dense_x.append(X[skip:])

    def step(
        self, status: StepStatus, res: HorizonResult, plan_time: float, iter_time: float, replanned: bool, reason: str
    ) -> None:
        self.status.append(str(status))
        self.solver.append(res.solver_status)
        self.nlp.append(res.wall_time)
        self.plan.append(plan_time)
        self.iter.append(iter_time)
        self.its.append(res.iterations)
        self.replanned.append(replanned)
        self.reason.append(reason)


# ------------------------------------------------------------------ problems
