"""The horizon replanner's backends (crtraj.control.horizon._backends): chosen once, each an `NLPBackend`, and each
one's look at its solution checked against independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from crtraj.control.horizon._backends import (
    CompiledBackend,
    HorizonQuery,
    InterpretedBackend,
    PointScreen,
    RowCheck,
    ScreenedBackend,
)
from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._replanner import Replanner
from crtraj.planning.nlp import NLPBackend
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=0.5, phase=-0.43, name="ball")
SCENE = Scene(obstacles=(BALL,), safety_distance=5.0)
X0 = XS + 0.25 * (XG - XS)


def _reference(N: int) -> np.ndarray:
    return X0 + np.clip(0.12 * np.arange(1, N + 1), 0, 1)[:, None] * (XG - X0)


def _independent_rows(model, rp: Replanner, X: np.ndarray, O: np.ndarray) -> np.ndarray:
    """Every obstacle row (N, M, points) mm by numpy: |point - centre| - rho (the NLP's 1e-9 under the root)."""
    P = model.points(X, rp.options.points)  # (N, points, 3)
    c, rho, _ = packing.unpack(O)
    diff = P[:, None] - c[:, :, None]
    return np.sqrt(np.sum(diff * diff, axis=-1) + 1e-9) - rho[:, :, None]


@pytest.mark.parametrize("closest, screened", [(0, False), (3, True)])
def test_the_backend_is_chosen_once_by_the_options(model, closest, screened):
    """sqpmethod with screening is a ScreenedBackend around the interpreted call; without it, the call itself;
    the rescue is IPOPT on the full NLP; every one satisfies the NLPBackend protocol."""
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", closest_points=closest)
    rp = Replanner(model, opts, max_obstacles=1, safety_distance=5.0)
    assert isinstance(rp.backend, ScreenedBackend) is screened
    inner = rp.backend.inner if screened else rp.backend
    assert isinstance(inner, InterpretedBackend) and inner.name == "sqp"
    assert isinstance(rp.rescue, InterpretedBackend) and rp.rescue.name == "ipopt"
    for b in (rp.backend, rp.rescue):
        assert isinstance(b, NLPBackend)
    # IPOPT has no rescue, and never screens when there are no obstacles
    free = Replanner(model, ReplanOptions(horizon=6, points=12), max_obstacles=0, safety_distance=5.0)
    assert free.rescue is None and isinstance(free.backend, InterpretedBackend) and free.backend.name == "ipopt"


def test_the_rescue_backend_answers_one_query_with_independently_checked_numbers(model):
    """One query of the IPOPT rescue (the full NLP): its violation and smallest obstacle row equal numpy's."""
    rp = Replanner(model, ReplanOptions(horizon=6, points=12, solver="sqp"), max_obstacles=1, safety_distance=5.0)
    O = rp.obstacles_from_scene(SCENE, 3.0)
    ref = _reference(rp.N)
    p = np.concatenate([X0, X0, ref.ravel(), model.tip_position(ref).ravel(), O.ravel()])
    r = rp.rescue.solve(HorizonQuery(p, np.tile(X0, rp.N)))
    assert r.ok and r.finite and r.status == "Solve_Succeeded"
    X = r.x.reshape(rp.N, rp.nx)
    rows = _independent_rows(model, rp, X, O)
    assert abs(r.min_distance - rows.min()) <= 1e-6
    assert r.violation <= 1e-6 and rows.min() >= -1e-6
    # the same numbers as a whole solve's rescue would see: solve agrees with it
    res = rp.solve(X0, ref, O)
    assert abs(res.cost - r.cost) <= 1e-5 * max(1.0, r.cost)


def test_a_row_check_measures_the_largest_violation_of_box_and_rows():
    """RowCheck.violation: the largest of lbg - g, g - ubg, lo - x and x - hi, 0 when all hold."""
    check = RowCheck(np.zeros(2), np.ones(2), np.array([-1.0, 0.0]), np.array([1.0, np.inf]), 1, True)
    assert check.violation(np.array([0.5, 0.5]), np.array([0.0, 3.0])) == 0.0
    assert check.violation(np.array([1.25, 0.5]), np.array([0.0, 3.0])) == 0.25
    assert check.violation(np.array([0.5, 0.5]), np.array([-1.5, -0.75])) == 0.75
    # the query's multipliers reach the solver only when it has them
    q = HorizonQuery(np.zeros(3), np.zeros(2))
    assert "lam_g0" not in check.args(q) and "lam_x0" not in check.args(q)
    args = check.args(HorizonQuery(np.zeros(3), np.zeros(2), np.ones(2), np.ones(2)))
    assert np.array_equal(args["lam_g0"], np.ones(2)) and np.array_equal(args["lam_x0"], np.ones(2))


def test_the_obstacle_rows_and_nearest_points_match_numpy(model):
    """Replanner.distances is every obstacle row of the full NLP; nearest_points the K smallest, ascending."""
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", closest_points=3)
    rp = Replanner(model, opts, max_obstacles=2, safety_distance=5.0)
    O = rp.obstacles_from_scene(SCENE, 3.0)
    X = _reference(rp.N)
    rows = _independent_rows(model, rp, X, O)
    np.testing.assert_allclose(rp.distances(X.ravel(), O), rows, atol=1e-9)
    want = np.sort(np.argsort(rows, axis=-1, kind="stable")[..., :3], axis=-1)
    assert np.array_equal(rp.nearest_points(X.ravel(), O), want)


def test_a_screen_keeps_only_the_multipliers_of_unchanged_slots():
    """PointScreen.keep_multipliers zeroes exactly the obstacle slots whose point changed; the linear rows stay."""
    screen = PointScreen(2, np.eye(3), n_lin=2)
    old = np.array([[[0, 1]], [[1, 2]]])  # (N=2, M=1, K=2)
    new = np.array([[[0, 2]], [[1, 2]]])
    lam = screen.keep_multipliers(np.arange(1.0, 7.0), old, new)
    assert lam.tolist() == [1.0, 2.0, 3.0, 0.0, 5.0, 6.0]
    # the selection parameter is the slot table's rows of the selected points, slot by slot
    assert screen.parameter(new).tolist() == np.eye(3)[[0, 2, 1, 2]].ravel().tolist()


def test_the_compiled_backend_is_chosen_when_its_c_is_built(model):
    """With `compiled` (sqp + qrqp) the screened backend wraps the compiled call, and its solve equals the
    interpreted one's (the same NLP, the same start)."""
    opts = ReplanOptions(horizon=3, points=4, solver="sqp", qpsol="qrqp", rescue=False)
    fast = Replanner(model, ReplanOptions(**{**opts.to_dict(), "compiled": True}), max_obstacles=1, safety_distance=5.0)
    if not fast.compiled:
        pytest.skip(fast.compiled_message)
    assert isinstance(fast.backend, ScreenedBackend) and isinstance(fast.backend.inner, CompiledBackend)
    assert "(compiled C)" in fast.describe()["solver"]
    slow = Replanner(model, opts, max_obstacles=1, safety_distance=5.0)
    assert isinstance(slow.backend.inner, InterpretedBackend) and not slow.compiled
    O = slow.obstacles_from_scene(SCENE, 3.0)
    a, b = fast.solve(X0, _reference(3), O), slow.solve(X0, _reference(3), O)
    assert a.status is b.status and np.max(np.abs(a.configs - b.configs)) <= 1e-6


def test_the_loops_rod_horizon_is_linearised_and_sent_to_the_compiler(monkeypatch) -> None:
    """With ``--model rod`` the loop's horizon takes the rod correction to first order (a PCC-sized NLP) and, with
    `compiled = true`, is sent to the compiler under its own name (the compiler is replaced here by one that
    declines, so the test does not wait for gcc: tests/test_rod_horizon.py compiles a small one)."""
    from dataclasses import replace

    from conftest import PROBLEMS

    from crtraj.control.horizon import _build
    from crtraj.control.loop import ClosedLoop
    from crtraj.io.problem import Problem

    names = []

    def declined(name, functions, qpsol):
        names.append(name)
        return None, "no compiler in this test"

    monkeypatch.setattr(_build, "compiled_library", declined)
    problem = Problem.load(PROBLEMS / "side_shelf.toml")
    options = replace(problem.options(ReplanOptions, "replan"), solver="sqp", qpsol="daqp", compiled=True)
    loop = ClosedLoop.from_problem(problem, body="rod", options=options)
    assert loop.replanner.linear is not None and loop.replanner.model is loop.model
    assert len(names) == 1 and names[0].endswith("_rodlin")
    assert loop.replanner.compiled_message == "compiled: no compiler in this test"
