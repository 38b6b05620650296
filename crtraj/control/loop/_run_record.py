"""The record of a closed-loop run: one frozen `StepRecord` per control step, and the run (`ReplanRun`).

`crtraj.control.loop._recorder.RunRecorder` collects the records while the loop runs and builds the run's
arrays from them once; every quantity has one name, the same in `StepRecord`, in `ReplanRun` and in the
result schema's source attribute (`crtraj.io.run_schema`). Units: mm, rad, s.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# backbone points used to measure (not decide) clearance and to record the body
REPORT_POINTS = 41


@dataclass(frozen=True)
class Motion:
    """One control step's simulated motion (units mm, rad, s).

    q: actual actuation at the step's end (nq,) mm. qc: the set-point at the step's end (nq,) mm.
    times: sample times (S,) s, the first the step's start. configs: configurations at the samples (S, nx).
    commands: the set-points of the step's control periods (n_sub, nq) mm.
    """

    q: np.ndarray
    qc: np.ndarray
    times: np.ndarray
    configs: np.ndarray
    commands: np.ndarray


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
class StateRecord:
    """The robot and the obstacles at one recorded time t (s), and the motion that led there.

    x (nx,) actual configuration; q (nq,) actual actuation (mm); q_command (nq,) the set-point in force
    (mm); clearance (mm): sampled body clearance minus D_sf over the step ending at t; distance (mm): the
    same without D_sf; clearance_bound (mm): the conservative bound the decision used (NaN without
    safety); planned (nx,) the configuration the NLP planned for t; centers (m, 3), radii (m,) obstacle
    states (mm); dense_t (S,) s, dense_x (S, nx): the verification samples of the motion into t (the
    first record keeps all of its samples, later ones drop the first, which is the previous record's
    last).
    """

    t: float
    x: np.ndarray
    q: np.ndarray
    q_command: np.ndarray
    clearance: float
    distance: float
    clearance_bound: float
    planned: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    dense_t: np.ndarray
    dense_x: np.ndarray


@dataclass(frozen=True)
class StepRecord:
    """What the loop did in one control step (the step that ends at the next `StateRecord`'s t).

    step_status: a `StepStatus` value; solver_status: the horizon solver's own status text; nlp_time,
    plan_time, iter_time (s): the NLP solve, the reference planner charged to this step, the whole
    iteration; iterations: NLP iterations; replanned: a reference path was adopted; reason: why the
    reference was replanned or asked for ("" none); commands (n_sub, nq) mm: the set-point of every
    tracking period; executed (n_sub, nq) mm: the actual actuation at the end of every tracking period.
    """

    step_status: str
    solver_status: str
    nlp_time: float
    plan_time: float
    iter_time: float
    iterations: int
    replanned: bool
    reason: str
    commands: np.ndarray
    executed: np.ndarray


@dataclass(frozen=True)
class ReplanRun:
    """A closed-loop run. Arrays have one row per recorded time t[k] (k = 0..K), built once from the
    run's `StateRecord`s and (per step, K rows) `StepRecord`s under the same names.

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
    feed: dict[str, Any] = field(default_factory=dict)  # a live feed's counters and rejections (`RunRecorder`)
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
