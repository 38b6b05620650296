"""Closed-loop simulation of the receding-horizon replanner with the tracking controller.

`ClosedLoop` runs the paper's simulation 2 loop ("the robot periodically
updates its path based on its current position") at the replanner's step dt:

1. read the obstacles (an `crtraj.control.ports.ObstacleSource`: the scene's
   known time functions, or a live feed);
2. keep a reference path toward the goal (`crtraj.control.loop._reference`): plan it
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
   solution's next move, then holding: at rest, actuators commanded to their
   measured positions; moving, a stop within the acceleration limits
   (`crtraj.control.braking`), verified over its whole duration; if even
   holding is unsafe, apply the least unsafe of these and report it.

A live device is driven through the `crtraj.control.ports.Device` port; the loop
never imports hardware or viewing code. Every step records time,
configuration, actuation, set-points, tip, backbone, obstacle states,
clearance (sampled densely in time, and the conservative bound the decision
used), NLP and planner time, status and the solver's own status text. The
options are `ReplanOptions` (``[replan]``, the NLP) and `LoopOptions`
(``[loop]``, this loop). Units: mm, rad, s.

`ClosedLoop` is a small coordinator over parts with one job each (`crtraj.control.loop._setup.LoopParts`):
the step policy (`crtraj.control.loop._step_policy`: choose, verify, fall back), the reference manager
(`crtraj.control.loop._reference_manager`), the pacer (`crtraj.control.loop._pacer`, on one injected
`crtraj.core.clock.Clock`), the tip sensing and the run recorder (`crtraj.control.loop._recorder`). Build one
with `ClosedLoop.build` (a robot, a scene and keyword options) or `ClosedLoop.from_problem`.
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.control.horizon import HorizonStatus
from crtraj.control.loop._problem import ProblemLike, ProblemRun, spec_from_problem
from crtraj.control.loop._recorder import RunEnding
from crtraj.control.loop._reference_manager import ReferenceStep
from crtraj.control.loop._run_record import ReplanRun, RunStatus, StateRecord, StepRecord, StepStatus
from crtraj.control.loop._setup import LoopConfig, LoopParts, LoopSpec, assemble
from crtraj.control.loop._step_policy import Choice, RobotNow
from crtraj.control.ports import Device, DeviceError, Landing, StepObserver
from crtraj.model.robot import Robot
from crtraj.planning.goal import tip_tangents

__all__ = ["ClosedLoop"]

# LoopSpec fields whose None means "the default"
_DEFAULTED = ("options", "loop_options", "tracking", "extra_options", "clock")


@dataclass
class _Robot:
    """The robot as the loop knows it at loop time t (s): actual actuation q and set-point qc (nq,) mm,
    configuration x and the one a step before (nx,), actuation one control period before now (q_last),
    and the set-point's configuration change in the last control period (inc)."""

    t: float
    q: np.ndarray
    qc: np.ndarray
    x: np.ndarray
    x_prev: np.ndarray
    q_last: np.ndarray
    inc: np.ndarray
    on_device: bool = False  # q is a device's measurement: the device brakes a hold itself

    def now(self) -> RobotNow:
        # a measured q and the model's q_last give no velocity to plan a stop from
        return RobotNow(self.t, self.q, self.qc, self.x, self.inc, None if self.on_device else self.q_last)


def _freeze_heap() -> bool:
    """Move every object alive now (the setup's CasADi functions, arrays, planner data) out of the cyclic garbage
    collector's reach for the run (issue 29): its full collections traverse them all, 1-4 ms pauses that landed
    inside every other step of a 31-obstacle run. Garbage made during the run is still collected; the caller
    unfreezes at the end (then they are collectable again). No collection first: one costs 60-80 ms of CPU on
    simulation 2's heap, and the few hundred unreachable objects it would free wait until the unfreeze. False
    when something else froze the heap already."""
    if gc.get_freeze_count():
        return False
    gc.freeze()
    return True


class ClosedLoop:
    """The replanning loop for one robot, scene and goal: a coordinator over its parts.

    parts: the `LoopParts` (built by `crtraj.control.loop.assemble`). config: the frozen
    `LoopConfig`. setup_time: s it took to build them (recorded in the run).
    """

    def __init__(self, parts: LoopParts, config: LoopConfig, setup_time: float = 0.0) -> None:
        self.parts, self.config, self.setup_time = parts, config, setup_time
        self.model, self.scene = parts.model, parts.scene
        self.options, self.loop_options = config.options, config.loop_options
        self.tracking_options, self.extra_options = config.tracking_options, config.extra_options
        self.goal, self.x_start, self.goal_tolerance = config.goal, config.x_start, config.goal_tolerance
        self.n_sub, self.rate_limits = config.n_sub, config.rate_limits
        self.tracker, self.servo, self.replanner = parts.tracker, parts.servo, parts.replanner
        # the parts the coordinator asks, each through its own methods
        self._obstacles, self._checks, self._motion = parts.obstacles, parts.checks, parts.motion
        self._policy, self._references, self._tip = parts.policy, parts.references, parts.tip
        self._pacer, self._recorder = parts.pacer, parts.recorder

    @property
    def robot(self) -> Robot:
        """The robot description of the loop's model."""
        return self.model.robot

    @classmethod
    def build(cls, model: Any, scene: Any, goal: Any, start_config: Any, **options: Any) -> ClosedLoop:
        """The loop for `model` among `scene` from start_config (nx,) to the tip goal (3,) mm; options: the
        other fields of `crtraj.control.loop._setup.LoopSpec` by name (None for options, loop_options,
        tracking, extra_options or clock means its default)."""
        t_setup = time.perf_counter()
        kw = {k: v for k, v in options.items() if v is not None or k not in _DEFAULTED}
        parts, config = assemble(LoopSpec(model, scene, goal, start_config, **kw))
        return cls(parts, config, time.perf_counter() - t_setup)

    @classmethod
    def from_problem(cls, problem: ProblemLike, **run: Any) -> ClosedLoop:
        """The loop for a problem file (its robot, scene, task and option sections); run: the fields of
        `crtraj.control.loop.ProblemRun` by name (safety, seed, options, loop_options, feed, lead,
        start_config, tip_sensor, tip_feedback, clock). Raises `UnsolvableTaskError` when there is no safe
        start or the goal can never be reached safely."""
        spec = spec_from_problem(problem, ProblemRun(**run))
        t_setup = time.perf_counter()
        parts, config = assemble(spec)
        return cls(parts, config, time.perf_counter() - t_setup)

    def start_command(self) -> np.ndarray:
        """The actuation (nq,) mm a run without a device starts from: the tracker's command at the start
        configuration."""
        return self.tracker.initial_command(self.x_start)

    def plan_first_reference(self, q: np.ndarray) -> None:
        """Plan the first reference path (followed from t = 0) from actuation q (nq,) mm among the obstacles as
        the loop's source has them at t = 0, before the run; nothing while the source has no state yet."""
        scene, _ = self._obstacles.at(0.0)
        if scene is not None:
            self._references.plan_before(self.servo.config(q), scene)

    def describe_nlp(self) -> dict[str, Any]:
        """The horizon NLP as the run records it (solver, variables, constraints, build; `Replanner.describe`)."""
        return self.replanner.describe()

    @property
    def scene_now(self) -> Any:
        """The obstacles (a `crtraj.world.scene.Scene`, loop time) the current step was checked against: a
        device that verifies what it sends checks against the same snapshot."""
        return self._checks.scene_now

    # ------------------------------------------------------------------- run
    def run(
        self,
        *,
        progress: Callable[[int, float, str], None] | None = None,
        realtime: bool | None = None,
        device: Device | None = None,
        observer: StepObserver | None = None,
    ) -> ReplanRun:
        """Simulate from the start configuration until the goal is held, or `duration` runs out.

        progress: called after every step with (step index, time s, status).
        realtime: pace the steps by the loop's clock (default: only with a live
        obstacle source, whose states are only meaningful in real time).
        device: drive a device live (a `Device`, e.g. `crtraj.hardware.link.DeviceLink`; real
        time): the run starts where the device is, every verified move is sent as it is chosen,
        the device's telemetry is the measured configuration, a held or stale step holds the device, a step
        the device does not take (refused, late, held) is recorded as what it executes instead and the next
        step starts there (`Device.landing`), an unsafe step e-stops it and ends the run, and Ctrl-C holds it
        and ends the run (status "interrupted"). The device is finished (settled at the final actuation) and
        closed on return.
        observer: told of every recorded state and step as it is kept, on this thread (a live view,
        `crtraj.control.ports.StepObserver`; it keeps references only, so the loop's timing does not change).
        """
        t_wall = time.perf_counter()
        live = bool(self._obstacles.live)
        realtime = live if realtime is None or device is not None else bool(realtime)
        q = self.start_command() if device is None else device.start_actuation()
        x = self.servo.config(q)
        robot = _Robot(0.0, q, q.copy(), x, x.copy(), q, np.zeros_like(x))
        self._tip.start()
        self._references.start()
        self._recorder.start(observer)
        self._policy.start()
        self._pacer.start(realtime, device)
        self._tip.sense(robot.t, robot.q, robot.x, self._references)
        refused = self._start(robot, live)
        if refused is not None:
            return self._finish(robot, *refused, t_wall, device)
        self._references.plan_initial(robot.t)
        self._references.start_worker(realtime)
        if not live:
            # a known scene: the horizon's obstacle spheres of every step's start time in one pass (the numbers
            # of the per-step call, looked up in the steps; issue 29)
            dt = self.options.dt
            times = [0.0] + [round((k + 1) * dt, 12) for k in range(self.loop_options.steps(dt))]
            self.replanner.tabulate_obstacles(self._checks.scene_now, np.array(times))
        self._warm_up(robot)
        frozen = _freeze_heap()
        self._pacer.begin()
        try:
            return self._steps(robot, t_wall, progress, device)
        except KeyboardInterrupt:
            if device is None:
                raise
            device.hold("interrupted (Ctrl-C)")
            msg = "interrupted (Ctrl-C): device held"
            return self._finish(robot, RunStatus.INTERRUPTED, msg, t_wall, device)
        finally:
            self._references.close()
            if frozen:
                gc.unfreeze()

    def _warm_up(self, robot: _Robot) -> None:
        """Run a step's computations once, untimed, before the first step, and keep nothing of it. Their
        first calls allocate buffers, fill caches and (after the worker's fork) copy the pages they write:
        milliseconds that would otherwise land in step 0. The replanner's warm start is forgotten."""
        rp, dt = self.replanner, self.options.dt
        X_ref = self._references.horizon_reference(robot.x, rp.N, dt)
        res = rp.solve(
            robot.x, X_ref, rp.obstacles_from_scene(self._checks.scene_now, robot.t, robot.x), x_prev=robot.x_prev
        )
        rp.reset()
        x1 = res.configs[0] if res.feasible else robot.x
        sim = self._motion.track(robot.q, robot.qc, robot.x, x1, robot.t, robot.inc)
        if self.options.safety:
            self._checks.verify(sim.times, sim.configs, (robot.t + dt, robot.t + 2 * dt))
            self._references.current_valid(robot.t)

    def _state_record(
        self,
        robot: _Robot,
        clear: tuple[float, float, float],
        planned: np.ndarray,
        T: np.ndarray,
        X: np.ndarray,
        scene: Any,
    ) -> StateRecord:
        """The record of `robot` now; clear: (clearance, distance, bound) mm; (T, X) the motion samples that
        led here; the obstacles as `scene` knows them at robot.t."""
        c, r = scene.states(robot.t)
        return StateRecord(
            robot.t, robot.x, robot.q, robot.qc, *clear, np.asarray(planned, dtype=float), c.reshape(-1, 3),
            r.reshape(-1), T, X,
        )  # fmt: skip

    def _start(self, robot: _Robot, live: bool) -> tuple[RunStatus, str] | None:
        """Record t = 0 and check that the run can start: (status, why) when it cannot, else None."""
        scene0, why = self._pacer.first_states(self._obstacles, live)
        self._recorder.feed_events(self._obstacles, 0.0)
        if scene0 is None:
            nan = math.nan
            self._recorder.record_state(
                self._state_record(robot, (nan, nan, nan), robot.x, np.zeros(1), robot.x[None], self.scene)
            )
            return RunStatus.NO_OBSTACLES, f"no obstacle state to start from: {why}"
        self._checks.use(scene0)
        c0 = self._checks.measure(np.array([0.0]), robot.x[None])
        b0 = self._checks.verify(np.array([0.0]), robot.x[None], None)
        d0 = c0 + self.scene.safety_distance
        self._recorder.record_state(
            self._state_record(robot, (c0, d0, b0), robot.x, np.array([0.0]), robot.x[None], scene0)
        )
        if self.options.safety and b0 < 0.0:
            msg = f"the start configuration is not clear of the obstacles at t = 0 (bound {b0:.2f} mm)"
            return RunStatus.INVALID_START, msg
        return None

    def _steps(
        self, robot: _Robot, t_wall: float, progress: Callable[[int, float, str], None] | None, device: Device | None
    ) -> ReplanRun:
        """The control steps of `run` after the start checks."""
        lo = self.loop_options
        settled_since: float | None = None
        for k in range(lo.steps(self.options.dt)):
            t = robot.t
            t_iter = self._pacer.now()
            if device is not None:
                why_not = device.problem()
                if why_not:
                    return self._finish(robot, RunStatus.DEVICE, why_not, t_wall, device)
                robot.q, robot.qc, _ = device.measure(t, robot.q, robot.qc)
                robot.on_device = True
                robot.x = self.servo.config(robot.q)
            status = self._step(k, robot, device, t_iter)
            self._tip.sense(robot.t, robot.q, robot.x, self._references)
            if progress is not None:
                progress(k, robot.t, str(status))
            if device is not None and status is StepStatus.UNSAFE:
                msg = f"unsafe step at t={t:.2f} s: nothing verified safe, device e-stopped"
                return self._finish(robot, RunStatus.ESTOP, msg, t_wall, device)
            # with tip feedback the goal is where the corrected tip (model tip + estimated error) reaches it
            err = float(np.linalg.norm(self.model.tip_position(robot.x) - self._tip.target))
            if err > self.goal_tolerance or not self._at_rest(robot) or not self._aimed(robot.x):
                settled_since = None
            else:
                settled_since = robot.t if settled_since is None else settled_since
                if robot.t - settled_since >= lo.settle_time - 1e-9:
                    return self._finish(robot, RunStatus.REACHED, "goal reached and held", t_wall, device)
            self._pacer.pace(robot.t)
        msg = f"goal not reached within {lo.duration:g} s"
        return self._finish(robot, RunStatus.TIMEOUT, msg, t_wall, device)

    def _decide(self, k: int, robot: _Robot, scene_t: Any, t_iter: float) -> tuple[Choice, Any, ReferenceStep]:
        """Step k's move among the obstacles `scene_t`: (choice, NLP result as recorded, what keeping the
        reference did). An NLP result that arrives after ``replan.step_deadline`` is not used:
        the step falls back to the last plan's next move (verified now), or a verified hold; the late plan, if
        feasible, becomes the last plan for the next step."""
        t, dt, rp = robot.t, self.options.dt, self.replanner
        self._checks.use(scene_t)
        refs = self._references.update(k, robot.x, t, dt * rp.N)
        X_ref = self._references.horizon_reference(robot.x, rp.N, dt)
        obstacles = rp.obstacles_from_scene(scene_t, t, robot.x)
        deadline = self.options.step_deadline
        left = deadline - (self._pacer.now() - t_iter) if deadline else None
        late = self._policy.solve(robot.x, X_ref, obstacles, robot.x_prev, left)
        res = self._policy.judge_deadline(
            late, self._pacer.now() - t_iter + refs.charged - self._references.waited_so_far()
        )
        if res is not late:
            self._recorder.count_deadline_miss()
        self._references.note_nlp(failed=not res.feasible and res.status is not HorizonStatus.SKIPPED)
        return self._policy.choose_after(robot.now(), late, res), res, refs

    def _step(self, k: int, robot: _Robot, device: Device | None, t_iter: float) -> StepStatus:
        """Control step k from robot.t: choose, verify, (send,) apply and record one move; its status.
        t_iter: the clock when the step began (its iteration time is charged from then)."""
        t = robot.t
        scene_t, why = self._obstacles.at(t)
        self._recorder.feed_events(self._obstacles, t)
        if scene_t is None:
            # no trustworthy obstacle state: keep the actuators where they are and say so
            choice, res = self._policy.stale(robot.now(), why)
            refs = ReferenceStep()
        else:
            choice, res, refs = self._decide(k, robot, scene_t, t_iter)
        iter_time = self._pacer.now() - t_iter + refs.charged - self._references.take_waited()
        reason = refs.reason
        m = choice.motion
        q_new, qc_new, T, X, cmds = m.q, m.qc, m.times, m.configs, m.commands
        periods = self._motion.periods(robot.q, cmds)
        if device is not None:
            landing, not_sent = self._drive(device, choice.status, t, robot.q, cmds, why, choice.bound)
            if landing is not None:
                # the device did not take the planned motion: the record and the next step follow what it executes
                q_new, qc_new, cmds, periods = landing.q, landing.qc, landing.commands, landing.executed
                T = t + self.options.dt / len(periods) * np.arange(len(periods) + 1)
                X = self.servo.config(np.vstack([robot.q[None], periods]))
                reason = "; ".join(filter(None, (reason, not_sent)))
                if not_sent:
                    self._policy.dropped()
        if scene_t is not None:
            reason = "; ".join(filter(None, (reason, self._references.ask(k, robot.x, t))))
        measured = self._checks.measure(T, X)
        # the set-point's last change (configuration): the next step's acceleration history
        before = cmds[-2] if len(cmds) > 1 else robot.qc
        robot.inc = self.servo.config(qc_new) - self.servo.config(before)
        robot.x_prev, robot.x, robot.q, robot.qc = robot.x, self.servo.config(q_new), q_new, qc_new
        robot.q_last = periods[-2] if len(periods) > 1 else robot.q
        robot.t = round((k + 1) * self.options.dt, 12)
        clear = (measured, measured + self.scene.safety_distance, choice.bound)
        self._recorder.record_state(self._state_record(robot, clear, choice.planned, T, X, self._checks.scene_now))
        step = StepRecord(
            str(choice.status), res.solver_status, res.wall_time, refs.plan_time, iter_time, res.iterations,
            refs.replanned, reason, cmds, periods,
        )  # fmt: skip
        self._recorder.record_step(step)
        return choice.status

    def _aimed(self, x: np.ndarray) -> bool:
        """The tip tangent at configuration x lies within the goal's direction cone (always, without one)."""
        goal = self.config.tip_goal
        return goal.cone is None or bool(goal.within(tip_tangents(self.model, x[None]))[0])

    def _at_rest(self, robot: _Robot) -> bool:
        """The last control period moved every actuator slowly enough to stop within its acceleration limit
        in one period: the streamed curve (`crtraj.control.executed`) ends at rest with an acceleration of
        at most |last period's step| / h^2, which then keeps the limit."""
        if self.rate_limits is None:
            return True
        h = self.options.dt / self.n_sub
        f = self.options.limit_fraction
        step = np.abs(self.rate_limits.jacobian @ (robot.x - self.servo.config(robot.q_last)))
        return bool(np.all(step <= f * self.rate_limits.amax * h * h))

    def _drive(
        self, device: Device, status: StepStatus, t: float, q0: np.ndarray, cmds: np.ndarray, why: str, bound: float
    ) -> tuple[Landing | None, str]:
        """Pass the step starting at t (from actuation q0, mm) to the device: hold, e-stop or move. (None, '')
        when the device took the planned move; else (what it executes instead, `Device.landing`, and why the
        move was not sent, '' for a hold): the next step starts from there, never from the unsent plan (a
        loop that planned on from its own plan asked a held robot for the same impossible catch-up forever)."""
        if status is StepStatus.UNSAFE:
            device.estop(f"unsafe step at t={t:.2f} s (clearance bound {bound:.2f} mm)")
            return None, ""  # the run ends at this step
        h = self.options.dt / self.n_sub
        not_sent = ""
        if status in (StepStatus.STALE, StepStatus.HOLD):
            device.hold(f"replanner {status} at t={t:.2f} s" + (f": {why}" if why else ""))
        else:
            try:
                device.move(t, q0, cmds, h)
                return None, ""
            except DeviceError as exc:  # `device.problem()` at the next step says whether that is final
                not_sent = f"not sent: {exc}"
        return device.landing(t, len(cmds), h), not_sent

    def _finish(
        self, robot: _Robot, status: RunStatus, message: str, t_wall: float, device: Device | None = None
    ) -> ReplanRun:
        """Finish the device (if any) and turn the records into the run."""
        if device is not None:
            device.finish(robot.q)
        ending = RunEnding(
            status=status,
            message=message,
            measured_tip=self._tip.readings(),
            **self._references.outcome(),
            setup_time=self.setup_time,
            wall_time=time.perf_counter() - t_wall,
            nlp=self.describe_nlp(),
            late_steps=self._pacer.late,
        )
        return self._recorder.build(ending, self._obstacles, device)
