"""The rod's body in the horizon NLP to first order (crtraj.control.horizon._rod_body, issue 40).

The robot is problems/robots/cdsr1_side.toml (one 300 mm NiTi segment mounted sideways, sagging up to 17 mm below
PCC) with a small rod model (the options of tests/test_rod_model.py, built in about a second). The independent
references are the `RodModel`'s own CasADi body (its full polynomials), numpy distances, and fresh rod solves for
the closed loop."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._replanner import Replanner
from crtraj.control.horizon._rod_body import LinearCorrection, LinearisedBackend, reach_bound
from crtraj.io.problem import load_robot
from crtraj.model.cosserat import (
    BOUND_FACTOR,
    RodModel,
    RodModelOptions,
    SurrogateOptions,
    load_rod_model,
    sample_within_limits,
)
from crtraj.model.kinematics import Model
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
ROBOT = load_robot(ROOT / "problems" / "robots" / "cdsr1_side.toml")
SMALL = RodModelOptions(degree=6, samples=2000, holdout=40, seed=2, surrogate=SurrogateOptions(grid=7, holdout=10))
SHELF = Obstacle(center=(0.0, -137.0, 300.0), radius=120.0, name="shelf")
SCENE = Scene(obstacles=(SHELF,), safety_distance=5.0)
OPTS = ReplanOptions(horizon=3, points=6, solver="sqp", qpsol="qrqp", rescue=False, compiled=False)


@pytest.fixture(scope="module")
def rod() -> RodModel:
    return load_rod_model(ROBOT, SMALL)  # the build cache (tests/test_rod_model.py measures a fresh build)


def _configs(n: int, seed: int) -> np.ndarray:
    return sample_within_limits(ROBOT, n, np.random.default_rng(seed))


def _linear_points(lin: LinearCorrection, n: int) -> ca.Function:
    x, c = ca.SX.sym("x", ROBOT.nx), ca.SX.sym("c", lin.n_params)
    return ca.Function("linear_points", [x, c], [lin.points(x, c, n)])


def test_the_horizon_body_is_the_rod_models_at_its_linearisation_point(rod: RodModel) -> None:
    """The NLP's obstacle rows (its own distance function, the correction linearised about the configurations)
    equal numpy distances of the full rod model's points to 1e-9 mm, its tip the model's tip; away from the point
    the body moves: it is not PCC's, and not the rod's at another configuration."""
    rp = Replanner(rod, OPTS, max_obstacles=1, safety_distance=5.0)
    assert rp.linear is not None and isinstance(rp.backend, LinearisedBackend)
    X = _configs(OPTS.horizon, 11)
    O = rp.obstacles_from_scene(SCENE, 0.0)
    c, rho, _ = packing.unpack(O)
    P = rod.points(X, OPTS.points)
    by_numpy = np.sqrt(np.sum((P[:, None] - c[:, :, None]) ** 2, axis=-1) + 1e-9) - rho[:, :, None]
    assert np.abs(rp.distances(X.ravel(), O) - by_numpy).max() <= 1e-9
    pcc = Model(ROBOT).points(X, OPTS.points)
    assert np.abs(P - pcc).max() > 5.0  # the sag the correction carries
    lin = rp.linear
    x, cs = ca.SX.sym("x", ROBOT.nx), ca.SX.sym("c", lin.n_params)
    tip = ca.Function("tip", [x, cs], [lin.tip(x, cs)])
    for xb in X:
        cb = lin.parameters(xb)
        assert np.abs(np.asarray(tip(xb, cb)).ravel() - rod.tip_position(xb)).max() <= 1e-9
        assert np.abs(np.asarray(_linear_points(lin, 21)(xb, cb)).T - rod.points(xb, 21)).max() <= 1e-9


def test_the_screened_qps_slot_rows_are_the_rod_models_at_the_linearisation_point(rod: RodModel) -> None:
    """The QP's rows of the K selected points per obstacle and step (points picked by parameters: segment, arc
    fraction and the correction's interpolation weights) equal numpy distances of those points of the full rod
    model, at the configurations the correction is linearised about, to 1e-9 mm."""
    rp = Replanner(rod, OPTS, max_obstacles=1, safety_distance=5.0)
    nlp = rp._nlp
    X = _configs(OPTS.horizon, 15)
    O = rp.obstacles_from_scene(SCENE, 0.0)
    p = rp.backend.fill(rp._parameters(X[0], X, O, None, None), X.ravel())
    sel = rp.nearest_points(X.ravel(), O)  # (N, M, K) point indices
    g = ca.Function("g", [nlp.nlp["x"], nlp.nlp["p"]], [nlp.nlp["g"]])
    rows = np.asarray(g(X.ravel(), np.concatenate([p, rp._screen.parameter(sel)]))).ravel()
    K = sel.shape[-1]
    P = rod.points(X, OPTS.points)  # (N, points, 3)
    c, rho, _ = packing.unpack(O)
    picked = np.take_along_axis(P, sel[:, 0, :, None], axis=1)  # (N, K, 3)
    by_numpy = np.sqrt(np.sum((picked - c[:, :1]) ** 2, axis=-1) + 1e-9) - rho[:, :1]
    assert np.abs(rows[-K * OPTS.horizon :] - by_numpy.ravel()).max() <= 1e-9


def test_the_linear_correction_is_the_rod_models_tangent(rod: RodModel) -> None:
    """The Jacobian the parameters carry (numpy, from the polynomials' exponents) equals central differences of
    the full model's collision points minus PCC's."""
    lin = LinearCorrection(rod)
    pcc = Model(ROBOT)
    h = 1e-6
    for xb in _configs(4, 12):
        _, J = lin.values(xb)
        fd = []
        for e in np.eye(ROBOT.nx)[: lin.nb]:
            up = (rod.points(xb + h * e) - pcc.points(xb + h * e)).ravel()
            down = (rod.points(xb - h * e) - pcc.points(xb - h * e)).ravel()
            fd.append((up - down) / (2 * h))
        assert np.abs(J[0] - np.stack(fd, axis=1)).max() <= 1e-5


def test_a_solutions_kept_linearisations_are_the_ones_about_the_next_start(rod: RodModel) -> None:
    """`rows` (a solution's tips) keeps the linearisations about its configurations for the next call, whose start
    is that solution shifted by a step: those rows are the ones a fresh evaluation gives (and the tips the
    model's), a configuration not among them (the new last step, a cold start's repeated one) is evaluated
    itself, and a second `rows` replaces the kept ones."""
    lin = LinearCorrection(rod)
    X = _configs(4, 21)
    assert np.abs(lin.rows(X) - rod.tip_position(X)).max() <= 1e-9
    fresh = LinearCorrection(rod)
    start = np.vstack([X[1:], X[-1:]])  # the warm start: shifted, the last step repeated
    assert np.abs(lin.parameters_at(start) - fresh.parameters_at(start)).max() <= 1e-12
    other = _configs(2, 22)
    mixed = np.vstack([X[2:3], other, np.tile(other[0], (2, 1))])
    assert np.abs(lin.parameters_at(mixed) - fresh.parameters_at(mixed)).max() <= 1e-12
    lin.rows(other)  # X is no longer kept: the kept rows are never another configuration's
    assert lin._rows.keys() == {x.tobytes() for x in other}
    assert np.abs(lin.parameters_at(X) - fresh.parameters_at(X)).max() <= 1e-12


def test_the_first_order_error_over_one_step_is_within_its_stated_bound(rod: RodModel) -> None:
    """Fresh pairs (not the bound's seeded ones): x_bar within the limits, x anywhere within one step's reach of it
    (the horizon's per-step cable and z limits). The linear body against the full model's body at x (CasADi, not
    the numpy the bound was measured with) stays within the stated bound at every collision point, and the bound
    is not a blanket: the largest fresh error is more than a third of it. Tightening the bound below the measured
    error (a smaller `BOUND_FACTOR`, fewer samples) fails here."""
    rp = Replanner(rod, OPTS, max_obstacles=1, safety_distance=5.0)
    lin = rp.linear
    bound = reach_bound(lin, rp.step_limit)
    assert rp.describe()["linearisation_bound_mm"] == pytest.approx(bound)
    rng = np.random.default_rng(99)
    A, _ = ROBOT.cable_matrix()
    f = _linear_points(lin, ROBOT.collision_points)
    worst = 0.0
    for xb in _configs(300, 13):
        d = rng.normal(size=ROBOT.nx)
        x = xb + d * rng.uniform(0.5, 1.0) / np.max(np.abs(A @ d) / rp.step_limit)
        if ROBOT.limit_violation(x)[0] > 0.0:
            continue
        full = rod.points(x)
        approx = np.asarray(f(x, lin.parameters(xb))).T
        worst = max(worst, float(np.linalg.norm(full - approx, axis=1).max()))
    assert worst <= bound, (worst, bound)
    assert worst > bound / (2.0 * BOUND_FACTOR), (worst, bound)


def test_the_rod_horizon_compiles_and_equals_the_interpreted_one(rod: RodModel) -> None:
    """The linearised rod horizon is PCC-sized and compiles; its compiled obstacle rows equal the interpreted ones
    to 1e-9 mm, and a solve of each from the same query gives the same configurations to 1e-9."""
    fast = Replanner(rod, replace(OPTS, compiled=True), max_obstacles=1, safety_distance=5.0)
    if not fast.compiled:
        pytest.skip(fast.compiled_message)
    assert "rodlin" in fast.compiled_message
    slow = Replanner(rod, OPTS, max_obstacles=1, safety_distance=5.0)
    O = slow.obstacles_from_scene(SCENE, 0.0)
    X = _configs(OPTS.horizon, 14).ravel()
    assert np.abs(fast.distances(X, O) - slow.distances(X, O)).max() <= 1e-9
    x0 = np.array([0.2, -0.3, -20.0])
    ref = x0 + np.linspace(0.2, 0.6, OPTS.horizon)[:, None] * (np.array([0.6, 0.1, 10.0]) - x0)
    a, b = fast.solve(x0, ref, O), slow.solve(x0, ref, O)
    assert a.status is b.status
    assert np.abs(a.configs - b.configs).max() <= 1e-9
    assert np.abs(a.tips - rod.tip_position(a.configs)).max() <= 1e-9  # the full model's tips, not the NLP's


def test_the_full_rod_horizon_runs_interpreted_without_trying_to_compile(rod: RodModel, monkeypatch) -> None:
    """The earlier path (the full correction in the NLP, ``rod_linear=False``) says it is not compiled and never
    calls the compiler (its C is 90 MB for cdsr2); the linearised path of the same model is the one that compiles."""
    from crtraj.control.horizon import _build

    def no_build(*args, **kw):
        raise AssertionError("the full rod horizon was sent to the compiler")

    monkeypatch.setattr(_build, "compiled_library", no_build)
    rp = Replanner(rod, replace(OPTS, compiled=True), max_obstacles=1, safety_distance=5.0, rod_linear=False)
    assert rp.compiled is False and rp.linear is None
    assert rp.compiled_message.startswith("compiled: not for a rod-model body")


def test_the_rod_loop_reaches_the_goal_and_the_rod_never_touches_the_shelf() -> None:
    """side_shelf.toml with ``--model rod`` (the linearised horizon, sqpmethod + daqp interpreted, one iteration a
    call as in paper_dynamic.toml, no deadline, virtual clock):
    the loop reaches the goal, and fresh rod solves at every step's configuration (the robot file's actuation
    mode, gravity; no surrogate) keep D_sf from the shelf by numpy distances."""
    from crtraj.control.loop import ClosedLoop
    from crtraj.core.clock import VirtualClock
    from crtraj.io.problem import Problem
    from crtraj.model.cosserat import RodDrive
    from crtraj.model.mechanics import Mechanics

    problem = Problem.load(ROOT / "problems" / "side_shelf.toml")
    options = replace(
        problem.options(ReplanOptions, "replan"), solver="sqp", qpsol="daqp", max_iter=1, max_calls=60, compiled=False
    )
    options = replace(options, step_deadline=0.0)
    loop = ClosedLoop.from_problem(problem, body="rod", options=options, clock=VirtualClock())
    assert loop.replanner.linear is not None
    run = loop.run()
    assert run.reached, run.message
    drive = RodDrive(ROBOT, Mechanics.from_robot(ROBOT))
    c, radius = np.array(SHELF.center), SHELF.radius
    worst = np.inf
    for x in run.x:
        shape = drive.shape_config(x)
        assert shape.is_success()
        worst = min(worst, float(np.min(np.linalg.norm(shape.points - c, axis=1))) - radius - ROBOT.body_radius)
    assert worst >= SCENE.safety_distance, worst
    assert len(run.x) > 10
