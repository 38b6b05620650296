"""The run recorder of the closed loop: collects one `StateRecord` per recorded time and one `StepRecord`
per control step, counts deadline misses, and builds the `ReplanRun` from them once.
Units: mm, rad, s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from crtraj.control.executed import limit_fractions
from crtraj.control.loop._run_record import REPORT_POINTS, ReplanRun, RunStatus, StateRecord, StepRecord
from crtraj.control.ports import Device, ObstacleSource, StepObserver
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits


@dataclass(frozen=True)
class RunEnding:
    """How and where a run ended, and what the loop knows about it beside the records.

    status, message: the verdict. reference_tips:
    every reference path's tip polyline with the step it started at; tree_edges (E, 2, 3) mm: the last
    planner tree. measured_tip (K+1, 3) mm or None: the tip sensor's readings. reference_worker: the
    worker's record ({} inline). setup_time, wall_time (s). nlp: the replanner's description.
    """

    status: RunStatus
    message: str
    reference_tips: tuple[tuple[int, np.ndarray], ...]
    tree_edges: np.ndarray
    measured_tip: np.ndarray | None
    reference_worker: dict[str, Any]
    setup_time: float
    wall_time: float
    nlp: dict[str, Any]
    late_steps: int


@dataclass(frozen=True)
class RecorderSetup:
    """What the recorder needs to turn records into a run: the model, the servo model's actuation ->
    configuration map, the goal (3,) mm, the replanner's step dt (s) and tracking periods per step, whether
    safety was on, the actuator rate limits (or None)."""

    model: Model
    config: Callable[[np.ndarray], np.ndarray]
    goal: np.ndarray
    dt: float
    n_sub: int
    safety: bool
    rate_limits: RateLimits | None


class RunRecorder:
    """Collects the records of one run (`start` clears them) and builds its `ReplanRun` (`build`)."""

    def __init__(self, setup: RecorderSetup) -> None:
        self.setup = setup
        self.start()

    def start(self, observer: StepObserver | None = None) -> None:
        """Forget the records of any previous run; observer: told of each record of this run as it is kept (a
        live view), or None."""
        self.observer = observer
        self.states: list[StateRecord] = []
        self.steps: list[StepRecord] = []
        self.deadline_misses = 0  # NLP results that came after replan.step_deadline (not used)
        self.feed: list[dict[str, Any]] = []  # the live feed's rejected/clamped messages, with loop time

    def count_deadline_miss(self) -> None:
        """One more NLP result came after ``replan.step_deadline`` and was not used."""
        self.deadline_misses += 1

    def feed_events(self, source: ObstacleSource, t: float) -> None:
        """Record the source's new events (a live feed's rejected or clamped messages) at loop time t (s)."""
        self.feed.extend({"t": float(t), **e.to_dict()} for e in source.new_events())

    def feed_record(self, source: ObstacleSource) -> dict[str, Any]:
        """The feed section of a live run: counters, options and every recorded event ({} without a feed)."""
        if not source.live:
            return {}
        self.feed_events(source, self.states[-1].t if self.states else 0.0)
        return {**source.describe(), "events": list(self.feed)}

    def record_state(self, state: StateRecord) -> None:
        """Keep the record of one time; its motion samples skip the first one after the first record."""
        if self.states:
            state = _drop_first_sample(state)
        self.states.append(state)
        if self.observer is not None and len(self.states) == 1:
            self.observer.observe(state, None)

    def record_step(self, step: StepRecord) -> None:
        """Keep the record of one control step (after the state it led to) and tell the observer, if any."""
        self.steps.append(step)
        if self.observer is not None:
            self.observer.observe(self.states[-1], step)

    def build(self, ending: RunEnding, source: ObstacleSource, device: Device | None) -> ReplanRun:
        """The run's record: arrays built once from the records."""
        st, sp, model = self.states, self.steps, self.setup.model
        t = np.array([s.t for s in st])
        X = np.array([s.x for s in st])
        planned = np.array([np.asarray(s.planned, dtype=float) for s in st])
        executed = np.vstack([st[0].q[None], *[s.executed for s in sp]])
        tips = model.tip_position(X)
        nq = model.robot.nq
        commands = [s.commands for s in sp if len(s.commands)]
        return ReplanRun(
            t=t,
            x=X,
            q=np.array([s.q for s in st]),
            q_command=np.array([s.q_command for s in st]),
            tip=tips,
            backbone=model.points(X, REPORT_POINTS),
            centers=np.array([s.centers for s in st]),
            radii=np.array([s.radii for s in st]),
            clearance=np.array([s.clearance for s in st]),
            distance=np.array([s.distance for s in st]),
            clearance_bound=np.array([s.clearance_bound for s in st]),
            planned=planned,
            tip_error=np.linalg.norm(tips - model.tip_position(planned), axis=1),
            goal_error=np.linalg.norm(tips - self.setup.goal, axis=1),
            **self._step_arrays(),
            dense_t=np.concatenate([s.dense_t for s in st]),
            dense_x=np.concatenate([s.dense_x for s in st]),
            commands=np.concatenate(commands) if commands else np.zeros((0, nq)),
            control_dt=self.setup.dt / self.setup.n_sub,
            executed=executed,
            reference_tips=ending.reference_tips,
            tree_edges=ending.tree_edges,
            goal=self.setup.goal,
            status=ending.status,
            message=ending.message,
            safety=self.setup.safety,
            setup_time=ending.setup_time,
            wall_time=ending.wall_time,
            nlp=ending.nlp,
            late_steps=ending.late_steps,
            deadline_misses=self.deadline_misses,
            live=bool(source.live),
            device={} if device is None else device.describe(),
            feed=self.feed_record(source),
            limit_fractions=self._fractions(float(t[0]), executed, device),
            measured_tip=ending.measured_tip,
            reference_worker=ending.reference_worker,
        )

    def _step_arrays(self) -> dict[str, Any]:
        """The per-step fields of `ReplanRun`, one entry per `StepRecord` field of the same name."""
        sp = self.steps
        return {
            "step_status": tuple(s.step_status for s in sp),
            "solver_status": tuple(s.solver_status for s in sp),
            "nlp_time": np.array([s.nlp_time for s in sp], dtype=float),
            "plan_time": np.array([s.plan_time for s in sp], dtype=float),
            "iter_time": np.array([s.iter_time for s in sp], dtype=float),
            "iterations": np.array([s.iterations for s in sp], dtype=int),
            "replanned": np.array([s.replanned for s in sp], dtype=bool),
            "reason": tuple(s.reason for s in sp),
        }

    def _fractions(self, t0: float, executed: np.ndarray, device: Device | None) -> dict[str, float]:
        """Largest actuator speed and acceleration as fractions of the limits ({} without limits)."""
        if device is not None:
            # live: what the device was sent (the loop's executed samples restart from each step's
            # measured state, so their second differences are not a motion anything received)
            return device.limit_fractions()
        limits = self.setup.rate_limits
        if limits is None:
            return {}
        h = self.setup.dt / self.setup.n_sub
        xe = self.setup.config(executed)
        return limit_fractions(t0, h, xe, limits)


def _drop_first_sample(state: StateRecord) -> StateRecord:
    """`state` without its first motion sample (the previous record's last)."""
    return replace(state, dense_t=state.dense_t[1:], dense_x=state.dense_x[1:])
