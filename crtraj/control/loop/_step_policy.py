"""The closed loop's step policy: solve the horizon NLP, choose the move (the NLP's, else the previous
solution's next one, else holding still), verify it, and judge a late result against the step deadline.
Units: mm, rad, s."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from crtraj.control.horizon import HorizonResult, HorizonStatus, Replanner, ReplanOptions
from crtraj.control.loop._run_record import Motion, StepStatus
from crtraj.control.loop._scene_checks import SceneChecks
from crtraj.control.loop._step_motion import StepMotion


@dataclass(frozen=True)
class Choice:
    """The move a step applies: its status, the configuration planned for the step's end (nx,), the
    simulated `Motion` and the conservative clearance bound (mm; NaN without safety)."""

    status: StepStatus
    planned: np.ndarray
    motion: Motion
    bound: float


@dataclass(frozen=True)
class RobotNow:
    """Where the robot is at the step's start t (s): actuation q and set-point qc (nq,) mm, configuration
    x (nx,), the set-point's configuration change in the last control period (inc, nx), and the actuation
    one control period before (q_last, mm; None: unknown, a hold then stops at once)."""

    t: float
    q: np.ndarray
    qc: np.ndarray
    x: np.ndarray
    inc: np.ndarray
    q_last: np.ndarray | None = None


class StepPolicy:
    """Chooses and verifies each step's move; keeps what remains of the applied NLP solution (`last_plan`,
    the next step's fallback). `start` begins a run."""

    def __init__(self, replanner: Replanner, motion: StepMotion, checks: SceneChecks, options: ReplanOptions) -> None:
        self.replanner, self.motion, self.checks, self.options = replanner, motion, checks, options
        self.start()

    def start(self) -> None:
        """Forget the previous run's plan and the replanner's warm start."""
        self.last_plan: np.ndarray | None = None  # remaining steps of the last applied NLP solution
        self.replanner.reset()

    def solve(
        self, x: np.ndarray, X_ref: np.ndarray, obstacles: np.ndarray, x_prev: np.ndarray, time_left: float | None
    ) -> HorizonResult:
        """The horizon NLP from x; time_left: s left of the step deadline (None: no deadline)."""
        return self.replanner.solve(x, X_ref, obstacles, x_prev=x_prev, time_left=time_left)

    def judge_deadline(self, res: HorizonResult, elapsed: float) -> HorizonResult:
        """`res`, or, when it came after the step deadline (elapsed s since the step began), the record of
        an unused solve: status SKIPPED and the solver's own status with the miss appended (never lost)."""
        deadline = self.options.step_deadline
        if not deadline or elapsed <= deadline:
            return res
        why = f"{res.solver_status}; deadline missed ({elapsed * 1e3:.2f} ms > {deadline * 1e3:g} ms): not used"
        return replace(res, status=HorizonStatus.SKIPPED, solver_status=why)

    def stale(self, now: RobotNow, why: str) -> tuple[Choice, HorizonResult]:
        """No trustworthy obstacle state: stop (within the acceleration limits when moving) and stay; the
        step's record says why."""
        self.last_plan = None
        self.replanner.reset()
        hold = self.motion.hold(now.q, now.x, now.t, now.q_last)
        return Choice(StepStatus.STALE, now.x.copy(), hold, math.nan), skipped(self.replanner, f"skipped: {why}")

    def choose(self, now: RobotNow, res: HorizonResult, keep_warm: bool = False) -> Choice:
        """The move to apply: the NLP's, else the previous solution's next one, else holding still.
        keep_warm: the replanner's warm start stays even when the NLP's move is not applied."""
        t, dt = now.t, self.options.dt
        cands: list[tuple[StepStatus, np.ndarray]] = []
        if res.feasible:
            cands.append((StepStatus.MOVE if res.is_success() else StepStatus.SUBOPTIMAL, res.configs[0]))
        if self.last_plan is not None and len(self.last_plan) > 1:
            cands.append((StepStatus.FALLBACK, self.last_plan[1]))
        tried: list[Choice] = []
        chosen: Choice | None = None
        for status, x1 in cands:
            sim = self.motion.track(now.q, now.qc, now.x, x1, t, now.inc)
            if not self.options.safety:
                chosen = Choice(status, x1, sim, math.nan)
                break
            bound = self.checks.verify(sim.times, sim.configs, (t + dt, t + 2 * dt))
            tried.append(Choice(status, x1, sim, bound))
            if bound >= 0.0:
                chosen = tried[-1]
                break
        if chosen is None:
            chosen = self._least_unsafe(now, tried)
        self._keep_plan(chosen.status, res, keep_warm)
        return chosen

    def choose_after(self, now: RobotNow, late: HorizonResult, res: HorizonResult) -> Choice:
        """`choose` with the NLP's result as judged (`res`) and as it came (`late`): a late but feasible
        solve still warm-starts the next one (resetting it would make the next solve cold, hence slower,
        hence late again: a run of misses feeding itself), and its plan (for t + dt, t + 2 dt, ...) is the
        next step's fallback, so a run of misses follows it one step behind (each move re-verified)
        instead of running out of plan."""
        missed = res is not late and late.feasible
        choice = self.choose(now, res, keep_warm=missed)
        if missed:
            self.last_plan = late.configs
        return choice

    def _least_unsafe(self, now: RobotNow, tried: list[Choice]) -> Choice:
        """No candidate move verified: hold when that is safe or no worse than the best move tried, else that
        move. At rest a hold commands every actuator to its measured position (the first-order servos stay
        put); moving, it is the stop within the acceleration limits (`StepMotion.stop`), whose whole duration
        and the rest after it are verified like any move."""
        hold, bound_h = self.hold(now)
        best = max(tried, key=lambda c: c.bound) if tried else None
        if bound_h >= 0.0 or best is None or best.bound <= bound_h:
            return Choice(StepStatus.HOLD if bound_h >= 0.0 else StepStatus.UNSAFE, now.x.copy(), hold, bound_h)
        return Choice(StepStatus.UNSAFE, best.planned, best.motion, best.bound)

    def hold(self, now: RobotNow) -> tuple[Motion, float]:
        """The hold's motion for this step and its conservative clearance bound (mm, minus D_sf): of the whole
        stop and of resting after it for one step when moving, else of staying at now.x for one step."""
        dt = self.options.dt
        if now.q_last is None or self.motion.brake_limits is None or not np.any(now.q != now.q_last):
            return self.motion.hold(now.q, now.x, now.t), self.checks.hold_clearance(now.x, now.t, dt)
        motion, (T, X) = self.motion.stop(now.q, now.q_last, now.t)
        return motion, self.checks.verify(T, X, (T[-1], max(T[-1], now.t + dt) + dt))

    def dropped(self) -> None:
        """The device did not execute the chosen move: the rest of its plan and the replanner's warm start no
        longer match where the robot is going."""
        self.last_plan = None
        self.replanner.reset()

    def _keep_plan(self, status: StepStatus, res: HorizonResult, keep_warm: bool = False) -> None:
        """Keep what remains of the applied NLP solution (the next step's fallback); forget the replanner's
        warm start when the NLP's move was not applied, unless `keep_warm` (the replanner still checks that
        it starts within reach of the next configuration)."""
        if status in (StepStatus.MOVE, StepStatus.SUBOPTIMAL):
            self.last_plan = res.configs
        elif status is StepStatus.FALLBACK and self.last_plan is not None:
            self.last_plan = self.last_plan[1:]
        else:
            self.last_plan = None
        if status is not StepStatus.MOVE and status is not StepStatus.SUBOPTIMAL and not keep_warm:
            # the warm start no longer matches where the robot is going
            self.replanner.reset()


def skipped(rp: Replanner, why: str) -> HorizonResult:
    """The record of a step whose NLP was not solved (why: the solver status text)."""
    nan = np.full((rp.N, rp.nx), np.nan)
    return HorizonResult(
        nan, np.full((rp.N, 3), np.nan), HorizonStatus.SKIPPED, why, 0, 0.0, math.inf, math.nan, math.inf
    )
