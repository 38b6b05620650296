"""The closed loop's reference manager: keeps the reference path toward the goal, decides when it must be
planned again, plans it inside the step or asks the reference worker for it, and adopts the paths that
reach the goal. Units: mm, rad, s."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._reference import ReferencePlan, ReferenceSource, TimedReference
from crtraj.control.loop._reference_worker import PendingPlan, ReferenceWorker
from crtraj.control.loop._scene_checks import SceneChecks
from crtraj.core.clock import Clock
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReferenceSetup:
    """What the reference manager is built from.

    model: the robot's `Model`. options: ``[replan]`` (dt, horizon, safety, rate limits). loop_options:
    ``[loop]`` (replan period, stall time, reference speed and delay, planner time). source: plans a path
    ((x, t, scene) -> `ReferencePlan`). initial: a reference planned before the loop from the start at
    t = 0, or None. rate_limits: the actuators' limits (or None), which time the reference. clock: the
    loop's clock (a simulated run's wait for a due path is measured on it).
    """

    model: Model
    options: ReplanOptions
    loop_options: LoopOptions
    source: ReferenceSource
    initial: ReferencePlan | None
    rate_limits: RateLimits | None
    clock: Clock


@dataclass(frozen=True)
class ReferenceStep:
    """What keeping the reference did at one step: why it was planned (reason, '' when it was not), the
    planner's time (s), whether a new path was adopted, and the time (s) to charge to the step."""

    reason: str = ""
    plan_time: float = 0.0
    replanned: bool = False
    charged: float = 0.0


class ReferenceManager:
    """The reference path of one run and the progress along it (`start` begins a run).

    checks: the loop's `SceneChecks` (the obstacles of the current step) that the reference ahead is
    checked against.
    """

    def __init__(self, setup: ReferenceSetup, checks: SceneChecks) -> None:
        self.checks = checks
        self.source = setup.source
        self.initial = setup.initial
        self._model, self._options, self._loop_options = setup.model, setup.options, setup.loop_options
        self._rate_limits, self._clock = setup.rate_limits, setup.clock
        robot = self._model.robot
        self._nx = robot.nx
        self._A, _ = robot.cable_matrix()
        o = setup.options
        self._rates = np.append(np.full(3 * robot.n_segments, o.max_cable_speed), o.max_z_speed)
        self.worker: ReferenceWorker | None = None
        self.start()

    def start(self) -> None:
        """Forget any previous run's reference and progress."""
        self.ref: TimedReference | None = None
        self.s_ref = 0.0  # progress along the reference (s of reference time)
        self.progress_s, self.progress_t = 0.0, 0.0  # last time the progress grew
        self.t_last_plan = -math.inf
        self.t_last_attempt = -math.inf
        self.nlp_failed = False  # the last NLP failed (a reason to replan)
        self.refs_used: list[tuple[int, np.ndarray]] = []
        self.tree_edges = np.zeros((0, 2, 3))
        # the tip goal's version (one more at each retarget) and the version the reference aims at: when
        # they differ the target moved, and the reference is planned again
        self.goal_version, self.ref_goal_version = 0, 0
        self.wait_reference = True  # at a due step, wait for the worker's path (simulated runs)
        self.worker_record: dict[str, Any] = {}  # a worker's record once it has been closed after failing
        self.waited = 0.0  # s this step waited for a due reference path (simulated runs; not charged)
        # step 0's record of the reference planned before the loop: (reason, planner time s, followed)
        self.first_plan: tuple[str, float, bool] | None = None

    # ------------------------------------------------------------ timing and checks
    def seconds_per(self, dX: np.ndarray) -> np.ndarray:
        """Time (s) each configuration change takes at `reference_speed` times the rate limits."""
        lo, limits = self._loop_options, self._rate_limits
        dq = np.abs(dX @ self._A.T)
        t_act = np.max(dq / (lo.reference_speed * self._rates), axis=1)
        if limits is not None:
            f = self._options.limit_fraction * lo.reference_speed
            t_act = np.maximum(t_act, limits.velocity_fraction(dX) / f)
        t_body = self.checks.motion_bound(dX) / (lo.reference_speed * lo.max_body_speed)
        return np.maximum(t_act, t_body)

    def reference_valid(self, ref: TimedReference, s_now: float, t: float) -> bool:
        """The next stretch of the reference is clear of the obstacles at the times it would be reached."""
        o = self._options
        look = max(2.0 * o.horizon * o.dt, 2.0)
        s = np.linspace(s_now, min(s_now + look, ref.end), 12)
        return self.checks.path_clear(ref.at(s), t + (s - s_now), o.dt)

    def current_valid(self, t: float) -> bool | None:
        """`reference_valid` of the reference followed now, from the progress along it, at t s (None: no
        reference yet)."""
        return None if self.ref is None else self.reference_valid(self.ref, self.s_ref, t)

    def replan_reason(self, t: float) -> str:
        """Why the reference path must be planned again at t (s) ('' when it need not)."""
        lo, ref = self._loop_options, self.ref
        if ref is None:
            return "no reference"
        if self.ref_goal_version != self.goal_version:
            return "tip correction"
        if self.nlp_failed:
            return "NLP failed"
        if lo.replan_period > 0 and t - self.t_last_plan >= lo.replan_period - 1e-9:
            return "periodic"
        if t - self.progress_t >= lo.stall_time and self.s_ref < ref.end - 1e-9:
            return "stalled"
        if self._options.safety and not self.reference_valid(ref, self.s_ref, t):
            return "reference blocked"
        return ""

    def _waiting(self, t: float, reason: str) -> bool:
        """After a failed attempt, wait a little (1 s, or a step) before asking the planner again."""
        return reason != "periodic" and t - self.t_last_attempt < max(1.0, self._options.dt) - 1e-9

    # ------------------------------------------------------------ progress
    def locate(self, x: np.ndarray, t: float, ahead: float) -> None:
        """Move the progress to the reference point nearest to configuration x at t (s)."""
        ref = self.ref
        if ref is None:
            return
        self.s_ref = ref.locate(x, self.s_ref, back=1.0, ahead=ahead)
        if self.s_ref > self.progress_s + 1e-3 or self.s_ref >= ref.end - 1e-9:
            self.progress_s, self.progress_t = self.s_ref, t

    def horizon_reference(self, x: np.ndarray, N: int, dt: float) -> np.ndarray:
        """Reference configurations (N, nx) for the horizon's steps; hold x without a reference."""
        if self.ref is None:
            return np.broadcast_to(x, (N, len(x))).copy()
        return self.ref.at(self.s_ref + dt * np.arange(1, N + 1))

    def note_nlp(self, failed: bool) -> None:
        """Whether this step's NLP failed (then the reference is planned again)."""
        self.nlp_failed = failed

    def retarget(self, target: np.ndarray) -> None:
        """Aim the planner at a corrected tip goal (mm): the reference is planned again."""
        self.source.retarget(target)  # type: ignore[attr-defined]
        self.goal_version += 1

    # ------------------------------------------------------------ planning
    def plan_initial(self, t: float) -> None:
        """Follow the reference planned before the loop (if any) from the start: step 0 records it (and,
        planning inline, is charged its planner time), but does not spend its own time taking it over."""
        plan = self.initial
        if plan is None:
            return
        reason = self.replan_reason(t)
        self.t_last_attempt = t
        self.first_plan = (f"{reason}: {plan.status}", plan.wall_time, self.adopt(0, t, plan, None))

    def plan_before(self, x: np.ndarray, scene: Any) -> None:
        """Plan the reference the run starts with (`initial`) from configuration x (nx,) at t = 0 among `scene`,
        before the run."""
        self.initial = self.source(x, 0.0, scene)

    def start_worker(self, realtime: bool) -> None:
        """Start the reference worker with ``loop.reference_delay > 0`` (none without a delay, or on a
        platform without fork: logged). A simulated run waits for a due reference (real time would have
        given the worker those seconds); a real-time run takes it at the first step it has arrived by."""
        self.worker, self.wait_reference = None, not realtime
        lo = self._loop_options
        if not lo.handover_steps(self._options.dt):
            return
        if not ReferenceWorker.can_fork():
            log.warning("this platform cannot fork: reference paths are planned inside the steps")
            return
        # the planner stops itself after planner_time; a worker silent for a minute longer is hung
        worker = ReferenceWorker(self.source, self._nx, lo.planner_time + 60.0)
        worker.start()
        self.worker = worker

    def update(self, k: int, x: np.ndarray, t: float, ahead: float) -> ReferenceStep:
        """Replan the reference path at step k (from x at t) when needed; returns what it did (`ReferenceStep`);
        then locate the progress (`ahead`: s of reference searched ahead).

        Inline (no worker) the plan is made now and its time is part of the step; with a worker the step
        takes over a due path here and asks for a new one after its move (`ask`), and the plan's
        time is the worker's."""
        said, plan_time, replanned = self._take(k, t)
        charged = 0.0
        if k == 0 and self.first_plan is not None:
            # the reference planned before the loop: inline, charged to this iteration; with a worker no
            # reference is planned inside a step, and that one was part of the setup
            said, plan_time, replanned = self.first_plan
            charged = plan_time if self.worker is None else 0.0
        if self.worker is None:
            reason = self.replan_reason(t)
            if reason and not self._waiting(t, reason):
                self.t_last_attempt = t
                plan = self.source(x, t, self.checks.scene_now)
                replanned = self.adopt(k, t, plan, self.goal_version)
                said, plan_time = f"{reason}: {plan.status}", plan.wall_time
        self.locate(x, t, ahead)
        return ReferenceStep(said, plan_time, replanned, charged)

    def ask(self, k: int, x: np.ndarray, t: float) -> str:
        """With a worker, after step k's move was chosen (and sent): ask for a new reference path when one is
        needed, from the step's start (x at t), to be taken over `handover_steps` later; what was asked
        ('' nothing). Neither the check (the reference's clearance ahead, about 0.1 ms) nor the request is in
        the step's latency: the move does not depend on them, and the path arrives steps later anyway."""
        w = self.worker
        if w is None or w.pending is not None:
            return ""  # one request at a time
        reason = self.replan_reason(t)
        if not reason or self._waiting(t, reason):
            return ""
        self.t_last_attempt = t
        due = k + self._loop_options.handover_steps(self._options.dt)
        w.submit(x, t, self.checks.scene_now, PendingPlan(k, due, reason, self.goal_version))
        return f"{reason}: asked"

    def _take(self, k: int, t: float) -> tuple[str, float, bool]:
        """Take over the worker's path when it is due: (reason text, planner time s, adopted); a worker that
        failed is closed (logged once) and the loop plans inside its steps from then on."""
        w = self.worker
        if w is None or w.pending is None or k < w.pending.due:
            return "", 0.0, False
        asked = w.pending
        waited = w.wait_time
        plan = w.take(self.wait_reference, self._clock.now)
        # a simulated run's wait for a due path is not part of the step: in real time the worker would have
        # had the delay's seconds (the run records the waits as the worker's wait_s)
        self.waited += w.wait_time - waited
        if plan is None:
            return "", 0.0, False
        ok = self.adopt(k, t, plan, asked.goal_version)
        if not w.alive:
            log.warning("%s: reference paths are planned inside the steps now", w.failure)
            self.worker_record = w.record()
            w.close()
            self.worker = None
        return f"{asked.reason}: {plan.status}", plan.wall_time, ok

    def adopt(self, k: int, t: float, plan: ReferencePlan, goal_version: int | None) -> bool:
        """Follow `plan` from step k (at t, s) on when it reached the goal; whether it did. goal_version: the
        tip goal's version the plan aims at (None: planned before the loop, for the task's goal)."""
        if not plan.is_success():
            return False
        self.ref = TimedReference(plan.configs, self.seconds_per, self.checks.metric)
        self.s_ref, self.progress_s, self.progress_t, self.t_last_plan = 0.0, 0.0, t, t
        self.refs_used.append((k, self._model.tip_position(self.ref.X)))
        if len(plan.tree_edges):
            self.tree_edges = plan.tree_edges
        if goal_version is not None:
            self.ref_goal_version = goal_version
        return True

    def waited_so_far(self) -> float:
        """The s this step has waited for a due path so far (simulated runs; not charged to the step)."""
        return self.waited

    def take_waited(self) -> float:
        """The s this step waited for a due path (not charged to it), and start counting the next step's."""
        waited, self.waited = self.waited, 0.0
        return waited

    def record(self) -> dict[str, Any]:
        """The run's `ReplanRun.reference_worker` record ({} when references were planned inline)."""
        rec = self.worker.record() if self.worker is not None else self.worker_record
        lo = self._loop_options
        return {"handover_steps": lo.handover_steps(self._options.dt), **rec} if rec else {}

    def outcome(self) -> dict[str, Any]:
        """What the run's ending keeps of the references (`RunEnding` fields): every reference's tip polyline
        with the step it started at, the last planner tree's edges (E, 2, 3) mm and the worker's record."""
        return {
            "reference_tips": tuple(self.refs_used),
            "tree_edges": self.tree_edges,
            "reference_worker": self.record(),
        }

    def close(self) -> None:
        """Stop the worker, if one runs."""
        if self.worker is not None:
            self.worker.close()
