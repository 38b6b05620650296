"""Reference planning beside the control loop (`crtraj.control.loop._reference_worker`, ``[loop] reference_delay``).

The worker is a forked process; what crosses its pipe is checked bit for bit against calling the same
source in this process. In the closed loop, the reference source charges its planning time to the loop's
virtual clock: planned inline, that time lands in the step (and misses the step deadline); planned by
the worker, it is spent in the other process and no step pays for it. No wall-clock timing: the only
waits are on events.
"""

from __future__ import annotations

import multiprocessing
import os
import signal

import numpy as np
import pytest
from conftest import BALL, XG, XS, VirtualClock, straight_loop

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._reference import ReferencePlan
from crtraj.control.loop._reference_worker import PendingPlan, ReferenceWorker
from crtraj.control.loop._run_record import StepStatus
from crtraj.planning.result import PlanStatus
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

NX = 5
DEADLINE = 0.004  # s


class EchoSource:
    """A reference source whose path spells out what it was asked: x, t, its goal and the first obstacle."""

    def __init__(self) -> None:
        self.goal = np.array([1.0, 2.0, 3.0])
        self.calls = 0

    def retarget(self, goal) -> None:
        self.goal = np.asarray(goal, dtype=float)

    def __call__(self, x, t, scene) -> ReferencePlan:
        self.calls += 1
        o = scene.obstacles[0]
        X = np.stack([x, x + t / 3.0, np.r_[self.goal, o.radius, o.omega], np.r_[o.center, self.calls, np.pi]])
        edges = np.arange(12.0).reshape(2, 2, 3) * np.sqrt(t + 1.0)
        return ReferencePlan(X, PlanStatus.EXACT, f"echo at t={t!r}", 0.125 + t, edges)


@pytest.fixture
def worker():
    made: list[ReferenceWorker] = []

    def make(source) -> ReferenceWorker:
        w = ReferenceWorker(source, NX)
        w.start()
        made.append(w)
        return w

    yield make
    for w in made:
        w.close()
    assert multiprocessing.active_children() == []  # every worker ended with close()


def _ask(w: ReferenceWorker, x, t, scene) -> ReferencePlan:
    w.submit(np.asarray(x, dtype=float), t, scene, PendingPlan(0, 0, "test"))
    plan = w.take(True, lambda: 0.0)
    assert plan is not None and w.pending is None
    return plan


def _same(a: ReferencePlan, b: ReferencePlan) -> None:
    assert a.status is b.status and a.message == b.message and a.wall_time == b.wall_time
    np.testing.assert_array_equal(a.configs, b.configs)
    np.testing.assert_array_equal(a.tree_edges, b.tree_edges)


def test_the_worker_plans_exactly_what_the_source_plans_here(worker):
    rng = np.random.default_rng(4)
    here, w = EchoSource(), worker(EchoSource())
    scenes = [Scene(obstacles=(BALL,)), Scene(obstacles=(Obstacle(center=(1e-7, -2.5, 1 / 3), radius=0.1 + 1e-12),))]
    for i in range(6):
        x, t = rng.normal(size=NX) * np.array([1.0, 1e-9, 1e9, 1.0, 1.0]), float(rng.uniform(0, 60))
        scene = scenes[i // 3]  # the same scene object three times (sent once), then another
        if i == 4:
            goal = rng.normal(size=3)
            here.retarget(goal)
            w.source.retarget(goal)  # the loop retargets its own copy; the worker follows with the next request
        _same(_ask(w, x, t, scene), here(x, t, scene))
    assert w.plans == 6 and w.alive and w.failure == ""
    # the worker only takes CPU time the control loop leaves idle (it would otherwise preempt a step)
    assert os.sched_getscheduler(w.pid) == os.SCHED_IDLE


def test_a_raising_planner_is_a_failed_plan_and_the_worker_goes_on(worker):
    class Picky(EchoSource):
        def __call__(self, x, t, scene):
            if t < 0.5:
                raise ValueError("t too small")
            return super().__call__(x, t, scene)

    w = worker(Picky())
    scene = Scene(obstacles=(BALL,))
    bad = _ask(w, XS, 0.1, scene)
    assert bad.status is PlanStatus.ERROR and bad.message == "planner raised ValueError: t too small"
    assert not bad.is_success() and w.alive
    good = _ask(w, XS, 2.0, scene)
    assert good.is_success() and good.message == "echo at t=2.0"


def test_a_worker_that_dies_is_reported_with_its_exit_code(worker):
    class Dies(EchoSource):
        def __call__(self, x, t, scene):
            os._exit(7)

    w = worker(Dies())
    plan = _ask(w, XS, 1.0, Scene(obstacles=(BALL,)))
    assert plan.status is PlanStatus.ERROR and "exit code 7" in plan.message
    assert not w.alive and w.failure == plan.message
    # further requests are not sent anywhere: the failure is repeated, never a hang
    again = _ask(w, XS, 2.0, Scene(obstacles=(BALL,)))
    assert again.status is PlanStatus.ERROR and again.message == plan.message


def test_take_without_waiting_returns_nothing_until_the_plan_is_there(worker):
    go, started = multiprocessing.Event(), multiprocessing.Event()

    class Gated(EchoSource):
        def __call__(self, x, t, scene):
            started.set()
            go.wait(60.0)
            return super().__call__(x, t, scene)

    w = worker(Gated())
    w.submit(XS, 1.0, Scene(obstacles=(BALL,)), PendingPlan(3, 6, "test"))
    assert started.wait(60.0)
    assert not w.ready() and w.take(False, lambda: 0.0) is None and w.pending is not None
    with pytest.raises(RuntimeError, match="already pending"):
        w.submit(XS, 1.0, None, PendingPlan(4, 7, "test"))
    go.set()
    plan = w.take(True, lambda: 0.0)
    assert plan is not None and plan.is_success() and w.pending is None


def test_close_ends_a_worker_that_is_still_planning(worker):
    started = multiprocessing.Event()

    class Stuck(EchoSource):
        def __call__(self, x, t, scene):
            started.set()
            multiprocessing.Event().wait(3600.0)

    w = worker(Stuck())
    w.submit(XS, 1.0, Scene(obstacles=(BALL,)), PendingPlan(0, 1, "test"))
    assert started.wait(60.0)
    w.close()
    assert multiprocessing.active_children() == [] and w.pending is None


def test_close_ends_a_worker_that_ignores_sigterm(worker):
    """A child that terminate() cannot end (as a child left unscheduled on a loaded machine) is killed:
    no process outlives close()."""
    started = multiprocessing.Event()

    class Deaf(EchoSource):
        def __call__(self, x, t, scene):
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
            started.set()
            multiprocessing.Event().wait(3600.0)

    w = worker(Deaf())
    w.submit(XS, 1.0, Scene(obstacles=(BALL,)), PendingPlan(0, 1, "test"))
    assert started.wait(60.0)
    proc = w._proc
    w.close()
    assert not proc.is_alive() and proc.exitcode == -signal.SIGKILL
    assert multiprocessing.active_children() == []


def test_a_worker_that_never_replies_is_reported_not_waited_for_forever(worker):
    class Stuck(EchoSource):
        def __call__(self, x, t, scene):
            multiprocessing.Event().wait(3600.0)

    w = worker(Stuck())
    w.reply_timeout = 0.2  # the hang bound (the planner itself never replies here)
    w.submit(XS, 1.0, Scene(obstacles=(BALL,)), PendingPlan(0, 1, "test"))
    plan = w.take(True, lambda: 0.0)
    assert plan is not None and plan.status is PlanStatus.ERROR and "no reply in 0.2 s" in plan.message
    assert not w.alive


@pytest.mark.parametrize(("delay", "dt", "steps"), [(0.0, 0.1, 0), (0.3, 0.1, 3), (0.25, 0.1, 3), (0.05, 0.1, 1)])
def test_handover_steps(delay, dt, steps):
    assert LoopOptions(reference_delay=delay).handover_steps(dt) == steps


# ----------------------------------------------------------------------------- in the closed loop
class ChargedSource:
    """The straight motion to XG, planned in `cost` seconds of the parent's virtual clock (inline only:
    a forked worker advances its own copy of the clock)."""

    def __init__(self, clock: VirtualClock, cost: float) -> None:
        self.clock, self.cost = clock, cost

    def __call__(self, x, t, scene) -> ReferencePlan:
        self.clock.advance(self.cost)
        return ReferencePlan(np.stack([x, XG]), PlanStatus.EXACT, "straight", self.cost)


def _run(model, delay: float, period: float = 1.0):
    clock = VirtualClock()
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", step_deadline=DEADLINE)
    loop = straight_loop(
        model,
        scene,
        options=opts,
        loop_options=LoopOptions(duration=3.0, reference_delay=delay, replan_period=period),
        reference=ChargedSource(clock, 0.05),
        clock=clock,
    )
    return loop.run(), scene


def _dense_distance(run, model, scene: Scene) -> np.ndarray:
    """Distance (mm) of the body surface to the obstacle at every recorded sample of the actual motion."""
    P = model.points(run.dense_x, 150)
    o = scene.obstacles[0]
    r = o.radius + o.amplitude * np.sin(o.omega * run.dense_t + o.phase)
    return np.linalg.norm(P - np.asarray(o.center), axis=-1).min(axis=1) - r - model.robot.body_radius


def test_inline_plans_are_paid_by_their_steps(model):
    run, _ = _run(model, 0.0)
    asked = [k for k, r in enumerate(run.reason) if r]
    assert asked == [0, 10, 20] and all(run.reason[k].endswith(": exact") for k in asked)
    # each planning step carries the 50 ms plan, misses the 4 ms deadline and falls back or holds
    np.testing.assert_allclose(run.iter_time[asked], 0.05)
    assert run.deadline_misses == 3 and run.reference_worker == {}
    assert run.summary()["reference_planning"] == "inline"


def test_worker_plans_are_taken_over_after_the_delay_and_no_step_pays_for_them(model):
    run, scene = _run(model, 0.2)
    asked = [k for k, r in enumerate(run.reason) if r.endswith(": asked")]
    taken = [k for k, r in enumerate(run.reason) if r.endswith(": exact")]
    # each request (the first, then periodic or for a blocked reference) is taken over two steps later
    assert asked[0] == 0 and len(asked) >= 3 and taken == [k + 2 for k in asked]
    assert run.reason[0] == "no reference: asked" and run.replanned[taken].all() and not run.replanned[asked].any()
    assert [k for k, _ in run.reference_tips] == taken
    # the plan's 50 ms went by in the worker's copy of the clock: no step was charged, none missed
    np.testing.assert_array_equal(run.iter_time, 0.0)
    assert run.deadline_misses == 0
    # without a reference the first two steps' horizons hold still; then the robot moves toward XG
    np.testing.assert_allclose(run.x[2], run.x[0], atol=1e-6)
    assert str(StepStatus.MOVE) in run.step_status[2:]
    assert np.linalg.norm(run.x[-1] - XG) < 0.8 * np.linalg.norm(XS - XG)
    assert _dense_distance(run, model, scene).min() >= scene.safety_distance - 1e-9
    rec = run.reference_worker
    assert rec["handover_steps"] == 2 and rec["plans"] == 3 and rec["failure"] == ""
    assert run.summary()["reference_planning"] == "worker" and "planned beside the loop" in run.summary_line()
    # a simulated run waits for each due plan, so it reproduces exactly
    again, _ = _run(model, 0.2)
    np.testing.assert_array_equal(again.x, run.x)
    assert again.reason == run.reason


@pytest.mark.parametrize("delay", [0.0, 0.2])
def test_a_reference_planned_before_the_loop_is_charged_only_when_planning_inline(model, delay):
    clock = VirtualClock()
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    first = ReferencePlan(np.stack([XS, XG]), PlanStatus.EXACT, "planned before the loop", 0.07)
    run = straight_loop(
        model, scene, options=ReplanOptions(horizon=6, points=12, solver="sqp"),
        loop_options=LoopOptions(duration=0.5, reference_delay=delay), reference=ChargedSource(clock, 0.05),
        initial_reference=first, clock=clock,
    ).run()  # fmt: skip
    assert run.reason[0] == "no reference: exact" and run.replanned[0] and run.plan_time[0] == 0.07
    assert [k for k, _ in run.reference_tips] == [0]
    # inline, the loop's first iteration carries the plan it starts with; with a worker that was setup
    assert run.iter_time[0] == (0.07 if delay == 0.0 else 0.0)
    np.testing.assert_array_equal(run.iter_time[1:], 0.0)


@pytest.mark.parametrize("delay", [0.0, 0.2])
def test_with_a_worker_the_check_for_a_new_reference_is_in_no_step(model, delay, monkeypatch):
    clock = VirtualClock()
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    loop = straight_loop(
        model, scene, options=ReplanOptions(horizon=6, points=12, solver="sqp"),
        loop_options=LoopOptions(duration=0.5, reference_delay=delay), reference=ChargedSource(clock, 0.0),
        clock=clock,
    )  # fmt: skip
    reason = loop.parts.references.replan_reason
    checks = []

    def costly_reason(t):
        # the check (the reference's clearance ahead) takes 1 ms of the virtual clock
        clock.advance(0.001)
        checks.append(t)
        return reason(t)

    monkeypatch.setattr(loop.parts.references, "replan_reason", costly_reason)
    run = loop.run()
    assert len(checks) >= run.steps - 1  # the check ran at (nearly) every step either way
    # inline, the plan (hence the check) belongs to the step; with a worker it comes after the move is sent
    expected = 0.001 if delay == 0.0 else 0.0
    np.testing.assert_allclose(run.iter_time, expected, atol=1e-12)
