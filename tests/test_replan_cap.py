"""The horizon NLP's iteration cap under a step deadline (`ReplanOptions.max_iter`, `max_calls`, `solve(time_left=)`).

An iterate the cap stops inside every constraint is a usable plan (FEASIBLE) and warm-starts the next solve; one
it stops outside a constraint goes on from there while calls and time are left; with a deadline nothing slower
(the IPOPT rescue) is started. The closed loop keeps the warm start of a late but feasible solve. Checked against
the uncapped solve of the same problem and on a virtual clock.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import XG, XS, SlowReplanner, VirtualClock, straight_loop

from crtraj.control.horizon import DIVERGED, HorizonStatus, Replanner, ReplanOptions
from crtraj.control.loop._options import LoopOptions
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

X0 = XS + 0.25 * (XG - XS)


def _problem(model):
    """A ball whose inflated sphere reaches 1 mm into the body at X0 (the plan must move out of it at once),
    and the straight reference toward XG: (scene, reference (6, nx))."""
    P = model.points(X0[None], 50)[0]
    c = P[35] + np.array([0.0, 40.0, 0.0])
    r = 40.0 - 5.0 - model.robot.body_radius - 1.5 + 1.0  # margin 1.5 mm
    scene = Scene(obstacles=(Obstacle(center=tuple(c), radius=r, name="b"),), safety_distance=5.0)
    return scene, X0 + np.clip(0.12 * np.arange(1, 7), 0, 1)[:, None] * (XG - X0)


def _replanner(model, **kw) -> Replanner:
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", **kw)
    return Replanner(model, opts, max_obstacles=1, safety_distance=5.0)


def _limping(model, drop: float = 100.0, **kw) -> tuple[Replanner, _Limping]:
    """`_replanner` whose NLP solver is wrapped in `_Limping` (through the replanner's solver_wrapper)."""
    made: list[_Limping] = []

    def wrap(solver):
        made.append(_Limping(solver, drop=drop))
        return made[0]

    opts = ReplanOptions(horizon=6, points=12, solver="sqp", **kw)
    return Replanner(model, opts, max_obstacles=1, safety_distance=5.0, solver_wrapper=wrap), made[0]


def _inside(model, scene: Scene, X: np.ndarray) -> float:
    """Largest depth (mm) of the body, 100 points per configuration, inside the ball's inflated sphere."""
    o = scene.obstacles[0]
    d = np.linalg.norm(model.points(X, 100) - np.asarray(o.center), axis=-1).min(axis=1)
    return float(np.max(o.radius + 5.0 + model.robot.body_radius + 1.5 - d))


def test_the_uncapped_solve_escapes_the_sphere(model):
    scene, ref = _problem(model)
    assert _inside(model, scene, X0[None]) > 0.5  # holding still breaks the constraint
    full = _replanner(model).solve(X0, ref, _replanner(model).obstacles_from_scene(scene, 0.0))
    assert full.is_success() and _inside(model, scene, full.configs) < 0.05  # 12 of 100 points constrained


def test_a_capped_iterate_inside_the_constraints_is_a_feasible_plan_and_a_warm_start(model):
    scene, ref = _problem(model)
    rp = _replanner(model, max_iter=1, rescue=True)
    O = rp.obstacles_from_scene(scene, 0.0)
    res = rp.solve(X0, ref, O)
    assert res.status is HorizonStatus.FEASIBLE and res.feasible and not res.is_success()
    # a usable plan: not handed to the IPOPT rescue, even without a deadline
    assert res.solver_status == "Maximum_Iterations_Exceeded" and res.violation <= 1e-6
    assert _inside(model, scene, res.configs) < 0.05
    # the next solve starts from it, shifted one step
    again = rp.solve(res.configs[0], ref, O, x_prev=X0, time_left=1.0)
    assert again.warm


class _Limping:
    """The real sqpmethod, except that its first call stops where it started (holding still, inside the sphere:
    outside the constraints); records the start point and the returned iterate of every call."""

    def __init__(self, solver, drop: float = 100.0) -> None:
        self.solver, self.starts, self.returned, self._stats = solver, [], [], {}
        self.drop = drop

    def call(self, args):
        self.starts.append(np.asarray(args["x0"], dtype=float).ravel().copy())
        sol = self.solver.call(args)
        self._stats = dict(self.solver.stats())
        if len(self.starts) == 1:
            # x back at the start, and constraint values that say so (every row `drop` below its value there)
            sol = dict(sol, x=self.starts[0].copy(), g=np.asarray(sol["g"]).ravel() - self.drop)
            self._stats.update(success=False, return_status="Injected_Stop")
        self.returned.append(np.asarray(sol["x"], dtype=float).ravel().copy())
        return sol

    def stats(self):
        return self._stats


def test_an_infeasible_capped_iterate_goes_on_from_there_while_calls_are_left(model):
    scene, ref = _problem(model)
    full = _replanner(model).solve(X0, ref, _replanner(model).obstacles_from_scene(scene, 0.0))
    # every point in the QP (closest_points = 0): each solver call is one call of `_Limping`
    rp, limp = _limping(model, max_calls=3, rescue=False, closest_points=0)
    res = rp.solve(X0, ref, rp.obstacles_from_scene(scene, 0.0))
    assert len(limp.starts) == 2  # the stopped call, then one more that converged
    np.testing.assert_array_equal(limp.starts[1], limp.returned[0])  # from the stopped iterate, not from scratch
    assert res.is_success() and res.solver_status == "Solve_Succeeded"
    np.testing.assert_allclose(res.configs, full.configs, atol=1e-5)


def test_a_diverged_iterate_is_not_gone_on_from(model):
    scene, ref = _problem(model)
    rp, limp = _limping(model, max_calls=5, rescue=True, closest_points=0, drop=10.0 * DIVERGED)
    res = rp.solve(X0, ref, rp.obstacles_from_scene(scene, 0.0))
    # no second call from an iterate 10 m outside its constraints: the IPOPT rescue (no deadline) solves it
    assert len(limp.starts) == 1 and res.solver_status.startswith("Injected_Stop; rescue ipopt:")
    assert res.is_success() and _inside(model, scene, res.configs) < 0.05
    # one just inside the bound is gone on from
    rp, limp = _limping(model, max_calls=5, rescue=True, closest_points=0, drop=0.5 * DIVERGED)
    res = rp.solve(X0, ref, rp.obstacles_from_scene(scene, 0.0))
    assert len(limp.starts) == 2 and res.solver_status == "Solve_Succeeded"


@pytest.mark.parametrize("max_calls", [1, 5])
def test_with_no_time_left_nothing_more_is_started(model, max_calls):
    scene, ref = _problem(model)
    rp, limp = _limping(model, max_calls=max_calls, rescue=True, closest_points=0)
    res = rp.solve(X0, ref, rp.obstacles_from_scene(scene, 0.0), time_left=0.0)
    # one call: no second call, no cold retry, no IPOPT rescue; the failure is reported as such
    assert len(limp.starts) == 1 and res.status is HorizonStatus.FAILED
    assert res.solver_status == "Injected_Stop" and "rescue" not in res.solver_status


def test_without_a_deadline_a_failed_solve_is_still_rescued(model):
    scene, ref = _problem(model)
    rp, _ = _limping(model, max_iter=3, max_calls=1, rescue=True, closest_points=0)
    res = rp.solve(X0, ref, rp.obstacles_from_scene(scene, 0.0))
    # the rescue's IPOPT gets max_iter x max_calls iterations (3 here) and says what it did
    assert "Injected_Stop; rescue ipopt:" in res.solver_status


def test_without_a_deadline_a_feasible_capped_iterate_goes_on_to_convergence(model):
    scene, ref = _problem(model)
    O = _replanner(model).obstacles_from_scene(scene, 0.0)
    full = _replanner(model).solve(X0, ref, O)
    # one iteration per call: the first call stops inside the constraints (the test above) ...
    rp, limp = _limping(model, max_iter=1, max_calls=80, rescue=False)
    limp.starts.append(None)  # `_Limping` leaves every call after its first alone
    res = rp.solve(X0, ref, O)
    # ... and without a deadline the calls go on to the uncapped solution
    assert res.is_success() and res.solver_status == "Solve_Succeeded"
    assert res.extra["attempts"] == len(limp.returned) > 2  # calls of one solve (no cold retry, no rescue)
    np.testing.assert_allclose(res.configs, full.configs, atol=1e-5)
    # under a deadline, with time left, the first feasible iterate is the plan: one call
    rp, limp = _limping(model, max_iter=1, max_calls=80, rescue=False)
    limp.starts.append(None)
    res = rp.solve(X0, ref, O, time_left=10.0)
    assert res.status is HorizonStatus.FEASIBLE and len(limp.returned) == 1


# ------------------------------------------------------------------------------------ in the closed loop
def test_a_late_feasible_solve_still_warm_starts_the_next_one(model):
    clock = VirtualClock()
    scene = Scene(obstacles=(Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, name="ball"),), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", step_deadline=0.004)
    # every third solve takes 10 ms of the virtual clock: the 4 ms deadline misses it
    cost = lambda k: 0.010 if k % 3 == 2 else 0.0  # noqa: E731
    rp = SlowReplanner(model, opts, max_obstacles=1, safety_distance=5.0, clock=clock, cost=cost)
    lopts = LoopOptions(duration=2.0)
    run = straight_loop(model, scene, options=opts, loop_options=lopts, replanner=rp, clock=clock).run()
    late = [k for k, s in enumerate(run.solver_status) if "deadline missed" in s]
    assert late and len(late) == run.deadline_misses
    assert all(rp.results[k].feasible for k in late)
    # the solve after each miss starts from the late solution, shifted (before: from scratch)
    assert all(rp.results[k + 1].warm for k in late if k + 1 < len(rp.results))
