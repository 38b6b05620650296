"""The horizon NLP (crtraj.control.horizon.Replanner): constraints re-checked independently, options, parameters."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from conftest import PLANNER_HANG_S

from crtraj.control.horizon import (
    HorizonResult,
    HorizonStatus,
    Replanner,
    ReplanOptions,
    horizon_status,
    implied_rows,
    merge_parallel_rows,
)
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
# a breathing sphere beside the straight motion XS -> XG: the motion clips it unless it bends away
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=0.5, phase=-0.43, name="ball")


def _radius(o: Obstacle, t: np.ndarray) -> np.ndarray:
    """Independent closed form of a static-centre obstacle's radius (mm)."""
    return o.radius + o.amplitude * np.sin(o.omega * t + o.phase)


def _straight_reference(x0: np.ndarray, xg: np.ndarray, N: int, frac: float) -> np.ndarray:
    return x0 + np.clip(frac * np.arange(1, N + 1), 0, 1)[:, None] * (xg - x0)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(obstacles=(BALL,), safety_distance=5.0)


@pytest.fixture(scope="module")
def planner(model, scene) -> Replanner:
    return Replanner(model, ReplanOptions(horizon=8, points=14, solver="sqp"), max_obstacles=2, safety_distance=5.0)


def test_solution_keeps_every_constraint_on_an_independent_dense_check(model, scene, planner):
    N, dt = planner.N, planner.options.dt
    t0 = 3.0  # the ball is near its largest radius: the straight reference goes through it
    # start part-way along the straight motion, where the reference runs into the ball
    x0 = XS + 0.25 * (XG - XS)
    assert float(scene.clearance(model, x0, t0, 100)) > 10.0
    Xr = _straight_reference(x0, XG, N, 0.12)
    assert np.min(scene.clearance(model, Xr, t0, 100)) < -5.0  # the reference itself collides
    res = planner.solve(x0, Xr, planner.obstacles_from_scene(scene, t0))
    assert res.is_success() and res.status is HorizonStatus.SOLVED, res.solver_status
    assert res.feasible
    X = res.configs
    # dense in arc length: 200 points per configuration, D_sf + disc radius from the ball's surface
    P = model.points(X, 200)  # (N, 200, 3)
    d = np.linalg.norm(P - np.array(BALL.center), axis=-1).min(axis=1)  # (N,)
    # ... at every instant of both steps around each configuration, fine time grid
    for k in range(N):
        tt = np.linspace(t0 + k * dt, t0 + (k + 2) * dt, 41)
        need = _radius(BALL, tt).max() + 5.0 + model.robot.body_radius
        assert d[k] >= need - 1e-6, (k, d[k], need)
    # the obstacle really shaped the plan: some constraint is active
    assert res.min_distance < 1e-3
    # rate limits per actuator and step, and the robot's limits
    A, _ = model.robot.cable_matrix()
    steps = np.diff(np.vstack([x0, X]), axis=0) @ A.T
    assert np.all(np.abs(steps) <= planner.step_limit + 1e-7)
    assert np.all(model.robot.limit_violation(X) <= 1e-7)
    # and it still makes progress toward the goal tip
    goal_tip = model.tip_position(XG)
    assert np.linalg.norm(res.tips[-1] - goal_tip) < np.linalg.norm(model.tip_position(x0) - goal_tip)


def test_without_safety_the_same_problem_runs_into_the_obstacle(model, scene):
    rp = Replanner(
        model, ReplanOptions(horizon=8, points=14, solver="sqp", safety=False), max_obstacles=2, safety_distance=5.0
    )
    x0 = XS + 0.25 * (XG - XS)
    res = rp.solve(x0, _straight_reference(x0, XG, rp.N, 0.12), rp.obstacles_from_scene(scene, 3.0))
    assert res.is_success()
    assert math.isinf(res.min_distance)  # no obstacle constraints in this NLP
    assert np.min(scene.clearance(model, res.configs, 3.0, 100)) < 0.0


@pytest.mark.parametrize("solver", ["ipopt", "sqp"])
def test_both_solvers_agree(model, scene, solver):
    # IPOPT's wall-time cap (max_solve_time) only bounds a hang here: a slow machine must not fail the solve
    opts = ReplanOptions(horizon=6, points=12, solver=solver, max_solve_time=PLANNER_HANG_S)
    rp = Replanner(model, opts, max_obstacles=1, safety_distance=5.0)
    x0 = XS + 0.25 * (XG - XS)
    Xr = _straight_reference(x0, XG, rp.N, 0.12)
    res = rp.solve(x0, Xr, rp.obstacles_from_scene(scene, 3.0))
    assert res.is_success(), res.solver_status
    tight = replace(opts, solver="ipopt", tol=1e-9)
    ref = Replanner(model, tight, max_obstacles=1, safety_distance=5.0).solve(x0, Xr, rp.obstacles_from_scene(scene, 3))
    assert abs(res.cost - ref.cost) <= 1e-3 * max(1.0, ref.cost)


def test_obstacle_slots_enclose_the_obstacle_over_each_window(model, planner):
    mover = Obstacle(
        center=(20.0, -40.0, 250.0),
        radius=25.0,
        amplitude=10.0,
        omega=2.0,
        to=(80.0, 0.0, 260.0),
        duration=1.3,
        profile="cos",
    )
    scene = Scene(obstacles=(BALL, mover), safety_distance=5.0)
    t0 = 0.77
    slots = planner.obstacles_from_scene(scene, t0).reshape(planner.N, 2, packing.WIDTH)
    lo, hi = planner.step_windows(t0)
    h = planner.spacing
    for k in range(planner.N):
        tt = np.linspace(lo[k], hi[k], 101)
        C, R = scene.states(tt)
        for i in range(2):
            r_enc = math.sqrt(slots[k, i, 3] ** 2 - (h / 2) ** 2) - planner.inflate
            reach = np.linalg.norm(C[:, i] - slots[k, i, :3], axis=1) + R[:, i]
            assert np.all(reach <= r_enc + 1e-9)


def test_padding_slots_are_inert(model, planner):
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    slots = planner.obstacles_from_scene(scene, 0.0).reshape(planner.N, 2, packing.WIDTH)
    assert np.all(slots[:, 1, 2] >= 1e5)  # far up the z axis
    too_many = Scene(obstacles=(BALL, BALL, BALL), safety_distance=5.0)
    with pytest.raises(InputError, match="at most 2"):
        planner.obstacles_from_scene(too_many, 0.0)


def test_constant_velocity_prediction_encloses_the_extrapolated_sphere(planner):
    c = np.array([[10.0, 20.0, 300.0]])
    v = np.array([[5.0, -3.0, 1.0]])
    r, rd = np.array([30.0]), np.array([-2.0])
    age = 0.05
    slots = planner.obstacles_from_states(c, r, v, rd, age=age).reshape(planner.N, 2, packing.WIDTH)
    lo, hi = planner.step_windows(age)
    for k in range(planner.N):
        tt = np.linspace(lo[k], hi[k], 51)
        C = c[0] + tt[:, None] * v[0]
        R = r[0] + tt * rd[0]
        r_enc = math.sqrt(slots[k, 0, 3] ** 2 - (planner.spacing / 2) ** 2) - planner.inflate
        assert np.all(np.linalg.norm(C - slots[k, 0, :3], axis=1) + R <= r_enc + 1e-9)


def test_warm_start_reuses_the_shifted_solution(model, scene):
    rp = Replanner(model, ReplanOptions(horizon=6, points=12, solver="sqp"), max_obstacles=1, safety_distance=5.0)
    x0 = XS + 0.1 * (XG - XS)
    Xr = _straight_reference(x0, XG, rp.N, 0.1)
    ob = rp.obstacles_from_scene(scene, 0.0)
    cold = rp.solve(x0, Xr, ob)
    assert cold.is_success() and not cold.warm
    again = rp.solve(x0, Xr, ob)
    assert again.warm
    assert again.is_success()
    np.testing.assert_allclose(again.configs, cold.configs, atol=1e-5)
    rp.reset()
    assert not rp.solve(x0, Xr, ob).warm


def test_failed_solve_is_reported_as_failed(model):
    # the reference asks for an impossible jump, the start is inside an obstacle: no feasible point exists
    scene = Scene(obstacles=(Obstacle(center=(0.0, 0.0, 300.0), radius=40.0),), safety_distance=5.0)
    rp = Replanner(
        model, ReplanOptions(horizon=4, points=10, solver="sqp", max_iter=20), max_obstacles=1, safety_distance=5.0
    )
    x0 = np.zeros(5)  # straight up the z axis, through the sphere
    res = rp.solve(x0, np.repeat(x0[None], 4, axis=0), rp.obstacles_from_scene(scene, 0.0))
    assert isinstance(res, HorizonResult)
    assert not res.is_success()
    assert not res.feasible
    assert res.status is HorizonStatus.FAILED
    assert res.solver_status and res.solver_status != "Solve_Succeeded"


def test_bad_input_is_one_clear_error(planner):
    ob = np.zeros((planner.N, packing.WIDTH * planner.max_obstacles))
    with pytest.raises(InputError, match="x0"):
        planner.solve(np.full(5, np.nan), np.zeros((planner.N, 5)), ob)
    with pytest.raises(InputError, match="max_obstacles"):
        Replanner(planner.model, ReplanOptions(), max_obstacles=-1, safety_distance=5.0)


def test_options_from_table_validate_every_key():
    o = ReplanOptions.from_table(Table({"horizon": 7, "dt": 0.05, "solver": "sqp", "qpsol": "qrqp"}, "replan"))
    assert (o.horizon, o.dt, o.solver, o.qpsol) == (7, 0.05, "sqp", "qrqp")
    assert ReplanOptions.from_table(Table(o.to_dict(), "replan")) == o
    with pytest.raises(InputError, match=r"replan\.horizonn: unknown key"):
        ReplanOptions.from_table(Table({"horizonn": 7}, "replan"))
    with pytest.raises(InputError, match=r"replan\.solver: must be one of"):
        ReplanOptions.from_table(Table({"solver": "snopt"}, "replan"))
    with pytest.raises(InputError, match=r"replan\.dt"):
        ReplanOptions.from_table(Table({"dt": -0.1}, "replan"))
    with pytest.raises(InputError, match=r"replan\.horizon"):
        ReplanOptions(horizon=0)
    with pytest.raises(InputError, match=r"replan\.safety"):
        ReplanOptions.from_table(Table({"safety": "yes"}, "replan"))


class _BrokenSolver:
    """Stands in for a crashed sqpmethod: returns NaN and a failure status."""

    def __init__(self, n: int, m: int) -> None:
        self.n, self.m = n, m

    def call(self, args):
        nan = np.full(self.n, np.nan)
        return {"x": nan, "g": np.full(self.m, np.nan), "f": np.nan, "lam_x": nan, "lam_g": np.full(self.m, np.nan)}

    def stats(self):
        return {"success": False, "return_status": "Injected_Breakdown", "iter_count": 3}


@pytest.mark.parametrize("rescue", [True, False])
def test_a_failed_fast_solve_is_rescued_by_ipopt_or_reported(model, scene, rescue):
    rp = Replanner(
        model,
        ReplanOptions(horizon=6, points=12, solver="sqp", rescue=rescue),
        max_obstacles=1,
        safety_distance=5.0,
        solver_wrapper=lambda solver: _BrokenSolver(solver.nnz_in("x0"), solver.nnz_out("g")),
    )
    assert (rp.rescue is not None) == rescue
    x0 = XS + 0.25 * (XG - XS)
    res = rp.solve(x0, _straight_reference(x0, XG, rp.N, 0.12), rp.obstacles_from_scene(scene, 3.0))
    assert res.solver_status.startswith("Injected_Breakdown")
    if rescue:
        assert res.is_success() and res.feasible and res.extra["rescue"]
        assert "rescue ipopt: Solve_Succeeded" in res.solver_status
    else:
        assert not res.is_success() and not res.feasible


def test_horizon_status_is_one_word_for_the_solve():
    # converged and within the constraints: solved; a feasible point at a limit: feasible; anything else failed
    ok = np.zeros((3, 5))
    assert horizon_status(True, ok, 0.0) is HorizonStatus.SOLVED
    assert horizon_status(False, ok, 1e-7) is HorizonStatus.FEASIBLE
    assert horizon_status(True, ok, 1e-3) is HorizonStatus.FAILED
    assert horizon_status(True, np.full((3, 5), np.nan), 0.0) is HorizonStatus.FAILED
    res = HorizonResult(ok, ok[:, :3], HorizonStatus.FEASIBLE, "Maximum_Iterations_Exceeded", 60, 0.1, 1.0, 2.0, 0.0)
    assert res.feasible and not res.is_success()


class _WrongFirstGuess(Replanner):
    """The screened NLP's first selection is the points FARTHEST from each obstacle (a wrong guess of the
    active points); later selections are the real ones."""

    guesses = 0

    def nearest_points(self, xs, obstacles):
        self.guesses += 1
        if self.guesses > 1:
            return super().nearest_points(xs, obstacles)
        d = self.distances(xs, obstacles)
        return np.sort(np.argsort(-d, axis=-1, kind="stable")[..., : self.options.closest_points], axis=-1)


@pytest.mark.parametrize("t0, frac", [(3.0, 0.25), (2.0, 0.4), (4.0, 0.1)])
def test_the_screened_qp_reaches_the_full_nlp_optimum(model, scene, t0, frac):
    """Keeping only the closest points per obstacle and step in the QP gives the optimum of the NLP with
    every point (same cost, same configurations), and every point keeps its distance."""
    opts = ReplanOptions(horizon=8, points=14, solver="sqp", rescue=False)
    full = Replanner(model, replace(opts, closest_points=0), max_obstacles=2, safety_distance=5.0)
    x0 = XS + frac * (XG - XS)
    Xr = _straight_reference(x0, XG, full.N, 0.12)
    O = full.obstacles_from_scene(scene, t0)
    ref = full.solve(x0, Xr, O)
    assert ref.is_success() and ref.min_distance < 1e-3, ref.solver_status  # an obstacle row is active
    for k in (1, 3):
        rp = Replanner(model, replace(opts, closest_points=k), max_obstacles=2, safety_distance=5.0)
        assert rp.describe()["qp_obstacle_rows"] == k * 2 * rp.N < rp.describe()["obstacle_constraints"]
        res = rp.solve(x0, Xr, O)
        assert res.is_success(), res.solver_status
        assert abs(res.cost - ref.cost) <= 1e-6 * ref.cost
        assert np.max(np.abs(res.configs - ref.configs)) <= 1e-4
        # every point of every step, the NLP's own rows recomputed independently
        P = model.points(res.configs, 14)  # (N, 14, 3)
        c, rho, _ = packing.unpack(O)
        dist = np.linalg.norm(P[:, None] - c[:, :, None], axis=-1) - rho[:, :, None]
        assert np.min(dist) >= -1e-6 and abs(res.min_distance - np.min(dist)) <= 1e-9


def test_a_wrong_guess_of_the_active_points_is_solved_again(model, scene):
    """When the QP's points leave out one that then enters its sphere, the solve is redone with the points
    closest at that solution; the result is the full NLP's optimum and keeps every point clear."""
    opts = ReplanOptions(horizon=8, points=14, solver="sqp", rescue=False, closest_points=2)
    x0 = XS + 0.25 * (XG - XS)
    full = Replanner(model, replace(opts, closest_points=0), max_obstacles=2, safety_distance=5.0)
    Xr = _straight_reference(x0, XG, full.N, 0.12)
    O = full.obstacles_from_scene(scene, 3.0)
    ref = full.solve(x0, Xr, O)
    rp = _WrongFirstGuess(model, opts, max_obstacles=2, safety_distance=5.0)
    res = rp.solve(x0, Xr, O)
    assert res.extra["screen_solves"] >= 2 and rp.guesses >= 2
    assert res.is_success(), res.solver_status
    assert abs(res.cost - ref.cost) <= 1e-6 * ref.cost
    P = model.points(res.configs, 200)
    d = np.linalg.norm(P - np.array(BALL.center), axis=-1).min(axis=1)
    for k in range(rp.N):
        tt = np.linspace(3.0 + k * rp.options.dt, 3.0 + (k + 2) * rp.options.dt, 41)
        assert d[k] >= _radius(BALL, tt).max() + 5.0 + model.robot.body_radius - 1e-6


def test_a_screened_solve_that_never_clears_is_not_ok(model, scene):
    """Only one solve allowed and a wrong first guess: the omitted point stays inside, and the result says
    so (failed, the depth in the status), never solved."""
    opts = ReplanOptions(horizon=8, points=14, solver="sqp", rescue=False, closest_points=2)
    rp = _WrongFirstGuess(model, opts, max_obstacles=2, safety_distance=5.0)
    x0 = XS + 0.25 * (XG - XS)
    Xr = _straight_reference(x0, XG, rp.N, 0.12)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("crtraj.control.horizon._backends.SCREEN_SOLVES", 1)
        res = rp.solve(x0, Xr, rp.obstacles_from_scene(scene, 3.0), warm=False)
    assert res.status is HorizonStatus.FAILED and not res.feasible
    assert "omitted point stays" in res.solver_status and res.min_distance < -1e-6
    # such a solve counts as failed: with the rescue on, IPOPT solves the full NLP instead
    rp = _WrongFirstGuess(model, replace(opts, rescue=True), max_obstacles=2, safety_distance=5.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("crtraj.control.horizon._backends.SCREEN_SOLVES", 1)
        res = rp.solve(x0, Xr, rp.obstacles_from_scene(scene, 3.0), warm=False)
    assert res.extra["rescue"] and res.is_success(), res.solver_status
    assert "omitted point stays" in res.solver_status and res.min_distance >= -1e-6


def test_parallel_rate_rows_merge_to_the_tighter_bound():
    # rows 2 and 4 are multiples of row 1: |2 v0| <= 4 is |v0| <= 2, |-3 v0| <= 9 is |v0| <= 3
    R, b = merge_parallel_rows(np.array([[1.0, 0.0], [2.0, 0.0], [0.0, 1.0], [-3.0, 0.0]]), np.array([5, 4, 1, 9.0]))
    assert np.array_equal(R, [[1.0, 0.0], [0.0, 1.0]]) and np.array_equal(b, [2.0, 1.0])
    # |3 (d_k - d_k-1)| <= 12 follows from |d| <= 2 at both steps (3 * 2 * 2 = 12); 11.9 does not
    speed, vb = np.array([[1.0, 0.0]]), np.array([2.0])
    acc = np.array([[3.0, 0.0], [0.0, 1.0], [-3.0, 0.0]])
    assert implied_rows(speed, vb, acc, np.array([12.0, 1.0, 11.9])).tolist() == [True, False, False]
