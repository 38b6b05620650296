"""Hard step deadlines of the replanning loop, on a virtual clock (no wall-clock timing).

The replanner below charges every solve a chosen amount of virtual time on an injected timer; the loop
must then refuse each late NLP result, fall back to the last verified plan's next move or a verified
hold, count the misses, and stay safe. Safety is checked by this file's own dense computation: every
recorded sample of the actual motion, 150 backbone points, obstacles from their closed-form time
functions.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import BALL, XG, XS, SlowReplanner, VirtualClock

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._run_record import StepStatus
from crtraj.world.scene import Scene

DEADLINE = 0.004  # s


def _run(model, scene, cost, duration=6.0):
    clock = VirtualClock()
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", step_deadline=DEADLINE)
    rp = SlowReplanner(model, opts, max_obstacles=1, safety_distance=scene.safety_distance, clock=clock, cost=cost)
    loop = ClosedLoop.build(
        model,
        scene,
        model.tip_position(XG),
        XS,
        options=opts,
        loop_options=LoopOptions(duration=duration),
        goal_config=XG,
        replanner=rp,
        clock=clock,
    )
    return loop.run()


def _dense_distance(run, model, scene: Scene) -> np.ndarray:
    """Distance (mm) of the body surface to the obstacle at every recorded sample of the actual motion."""
    T, X = run.dense_t, run.dense_x
    P = model.points(X, 150)
    o = scene.obstacles[0]
    r = o.radius + o.amplitude * np.sin(o.omega * T + o.phase)
    d = np.linalg.norm(P - np.asarray(o.center)[None, None, :], axis=-1).min(axis=1)
    return d - r - model.robot.body_radius


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(obstacles=(BALL,), safety_distance=5.0)


def test_every_solve_late_holds_safely_and_counts_every_miss(model, scene):
    run = _run(model, scene, lambda k: 10 * DEADLINE, duration=2.0)
    assert run.deadline_misses == run.steps > 0
    # no step applied its own NLP result: the first holds (no plan yet), later ones follow the previous
    # step's late plan one step behind, or hold
    assert run.step_status[0] == str(StepStatus.HOLD)
    assert set(run.step_status) <= {str(StepStatus.HOLD), str(StepStatus.FALLBACK)}
    assert all("deadline missed" in s for s in run.solver_status)
    np.testing.assert_allclose(run.x[1], run.x[0], atol=1e-9)  # the first step held still
    d = _dense_distance(run, model, scene)
    assert d.min() >= scene.safety_distance - 1e-9
    s = run.summary()
    assert s["deadline_misses"] == run.steps and s["step_deadline_s"] == DEADLINE
    assert f"{run.steps} deadline misses" in run.summary_line()
    # the recorded iteration times are the virtual clock's: each step took the charged cost
    np.testing.assert_allclose(run.iter_time, 10 * DEADLINE)
    assert s["p99_iteration_s"] == pytest.approx(10 * DEADLINE)


def test_late_solves_fall_back_to_the_last_verified_plan_and_stay_safe(model, scene):
    late = lambda k: 10 * DEADLINE if k % 3 == 2 else 0.0  # noqa: E731 - every third solve is late
    run = _run(model, scene, late)
    statuses = np.array(run.step_status)
    missed = np.array(["deadline missed" in s for s in run.solver_status])
    assert run.deadline_misses == int(missed.sum()) > 0
    # a late step never applies its own NLP result: it follows the previous plan (or holds)
    assert set(statuses[missed]) <= {str(StepStatus.FALLBACK), str(StepStatus.HOLD)}
    assert str(StepStatus.FALLBACK) in set(statuses[missed])
    assert str(StepStatus.MOVE) in set(statuses[~missed])
    d = _dense_distance(run, model, scene)
    assert d.min() >= scene.safety_distance - 1e-9, d.min()
    assert run.collisions == 0
    # the robot still moves toward the goal between the misses
    assert np.linalg.norm(run.tip[-1] - model.tip_position(XG)) < np.linalg.norm(run.tip[0] - model.tip_position(XG))


def test_no_deadline_means_no_misses(model, scene):
    clock = VirtualClock()
    opts = ReplanOptions(horizon=6, points=12, solver="sqp")
    rp = SlowReplanner(model, opts, max_obstacles=1, safety_distance=5.0, clock=clock, cost=lambda k: 1.0)
    run = ClosedLoop.build(
        model,
        scene,
        model.tip_position(XG),
        XS,
        options=opts,
        loop_options=LoopOptions(duration=1.0),
        goal_config=XG,
        replanner=rp,
        clock=clock,
    ).run()
    assert run.deadline_misses == 0 and "no step deadline" in run.summary_line()
    assert not any("deadline missed" in s for s in run.solver_status)
    assert str(StepStatus.MOVE) in run.step_status
    np.testing.assert_allclose(run.iter_time, 1.0)
