"""The `Planner` contract, run over EVERY planner of the registry (`crtraj.planning.planners.BUILTIN`).

Each registered name, built by the registry from one `PlanningContext` of the paper's simulation 1, must:

- plan the simulation's query (start tip -> goal tip) to an exact result whose path an independent dense
  check accepts: a fresh `Model` of the robot, 200 backbone points sampled every 10 ms along the timed path,
  plain numpy distances to the obstacles (`dense_path_check`, sharing nothing with the planners' validity code);
- report a spent budget as such: a budget of one iteration (crtraj's planners) or a termination condition that
  has already fired (OMPL, whose Python API has no iteration budget: the virtual clock of its solve) gives a
  ``TIMEOUT`` result, without a path, whose message names the stop;
- refuse a start configuration whose body passes through an obstacle (found so by the independent check
  first) with an ``INVALID_START`` status that says why, and no path.

A planner added to the registry runs through the same contract without a new test. A planner of an optional
extra (OMPL) runs in the ``*_of_an_extra`` tests, which need the extra installed (`require_module`: skipped
locally without it, a failure in CI).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PLANNER_HANG_S, require_module
from test_planner_helpers import dense_path_check, paper_static

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.planning.base import Planner
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import CSpaceOptions, PlannerOptions
from crtraj.planning.planners import BUILTIN, PlannerSpec, import_ompl
from crtraj.planning.result import PlanStatus
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition

CORE = [n for n in BUILTIN.names if BUILTIN.spec(n).optional is None]  # always there
EXTRA = [n for n in BUILTIN.names if BUILTIN.spec(n).optional is not None]  # an optional extra's (OMPL)
OMPL_STOPPED = "OMPL stopped at once"  # what the already-fired termination condition makes OMPL report


@pytest.fixture(scope="module")
def sim1():
    return paper_static()


@pytest.fixture(scope="module")
def checker(sim1):
    """The independent check's own model, built afresh from the robot description (never the planner's)."""
    problem, _, _ = sim1
    return Model(problem.robot)


@pytest.fixture(scope="module")
def planners(sim1):
    """name -> the registry's planner, built on first use from one shared context (its NLPs compile once).

    No via round in the c-space planner, so that its one-iteration budget cannot already hold a path."""
    problem, model, scene = sim1
    options = PlannerOptions(time_limit=PLANNER_HANG_S, cspace=CSpaceOptions(via_points=0))
    context = PlanningContext(model, scene, options)
    steer = problem.options(SteerOptions, "steer")
    built: dict[str, Planner] = {}

    def get(name: str) -> Planner:
        if name not in built:
            built[name] = BUILTIN.create(name, context, steer)
        return built[name]

    return get


def _assert_verified(res, checker: Model, scene, start_tip=None) -> tuple[float, float]:
    """The path of `res`, checked independently: tips and cables from the fresh model, limits and the dense
    body clearance (mm beyond the body radius and D_sf) along the timed path. Returns that clearance and the
    tip travel (mm) along the dense samples."""
    assert res.has_path and len(res.t) == len(res.configs) >= 1
    assert np.all(np.diff(res.t) >= 0), "time runs backwards along the path"
    np.testing.assert_allclose(checker.tip_position(res.configs), res.tips, atol=1e-9)
    np.testing.assert_allclose(checker.robot.cables(res.configs), res.cables, atol=1e-9)
    if start_tip is not None:
        assert np.linalg.norm(res.tips[0] - start_tip) <= 1e-3
    clear, limit, S = dense_path_check(checker, scene, res.t, res.configs)
    assert limit <= 1e-9, f"{res.planner}: limits violated by {limit}"
    assert clear >= 0.0, f"{res.planner}: body within D_sf, dense clearance {clear:.3f} mm"
    return clear, float(np.sum(np.linalg.norm(np.diff(checker.tip_position(S), axis=0), axis=1)))


def _plans_a_path_the_dense_check_accepts(name, planners, sim1, checker, monkeypatch) -> None:
    """An exact plan of simulation 1's query, verified by the independent dense check."""
    problem, _, scene = sim1
    task = problem.task
    planner = planners(name)
    assert isinstance(planner, Planner) and planner.name == name
    stop = StopCondition(time_limit=PLANNER_HANG_S, max_iterations=20_000, first_solution=True)
    res = planner.plan(task.goal, start_tip=task.start, seed=0, stop=stop, goal_tolerance=task.goal_tolerance)
    assert res.status is PlanStatus.EXACT and res.is_success(), res.message
    assert res.planner == name and res.seed == 0 and res.t[0] == pytest.approx(0.0)
    clear, travel = _assert_verified(res, checker, scene, start_tip=task.start)
    # the goal reached, and the reported figures are the path's own
    assert np.linalg.norm(checker.tip_position(res.configs[-1]) - task.goal) <= task.goal_tolerance
    assert res.goal_error == pytest.approx(np.linalg.norm(res.tips[-1] - task.goal), abs=1e-9)
    # tip travel along the motion (curved between waypoints): at least the chords, and the dense samples' own
    assert res.length >= np.sum(np.linalg.norm(np.diff(res.tips, axis=0), axis=1)) - 1e-9
    assert res.length == pytest.approx(travel, rel=2e-3)
    assert res.min_clearance <= clear + 1e-6  # the planner's clearance is a conservative figure of the same


def _spent_budget(name: str, planner: Planner, monkeypatch, ob) -> StopCondition:
    """The stop of a query whose budget is spent before the search finds anything: one iteration, or (OMPL, no
    iteration budget) a termination condition that has already fired: OMPL's solve returns at its first check."""
    if BUILTIN.spec(name).optional != "ompl":
        return StopCondition(max_iterations=1)
    monkeypatch.setattr(planner, "_termination", lambda *_: ob.PlannerTerminationCondition(lambda: True))
    return StopCondition(time_limit=PLANNER_HANG_S)


def _a_spent_budget_is_reported_as_such(name, planners, sim1, checker, monkeypatch) -> None:
    """A TIMEOUT without a path, whose message names the spent budget."""
    problem, _, _ = sim1
    task = problem.task
    planner = planners(name)
    ob = import_ompl()[0] if BUILTIN.spec(name).optional == "ompl" else None
    stop = _spent_budget(name, planner, monkeypatch, ob)
    res = planner.plan(task.goal, start_tip=task.start, seed=0, stop=stop, goal_tolerance=task.goal_tolerance)
    assert res.status is PlanStatus.TIMEOUT and not res.is_success(), res.message
    reason = "Timeout" if ob is not None else "iteration limit (1)"
    assert reason in res.message, res.message
    assert not res.has_path and len(res.t) == 0 and res.configs.shape == (0, checker.robot.nx)


def _a_blocked_start_is_refused_with_its_reason(name, planners, sim1, checker, monkeypatch) -> None:
    """INVALID_START, saying why, for a start whose body the dense check finds inside an obstacle."""
    problem, _, scene = sim1
    task = problem.task
    planner = planners(name)
    blocked = checker.robot.straight(0.0)
    blocked[:2] = [0.0, 0.4]  # the first segment bent into the upper sphere
    clear, limit, _ = dense_path_check(checker, scene, np.zeros(1), blocked[None])
    assert clear < -5.0 and limit <= 0.0  # independently: within limits, the body deep in an obstacle
    res = planner.plan(task.goal, start_config=blocked, seed=0, goal_tolerance=task.goal_tolerance)
    assert res.status is PlanStatus.INVALID_START and not res.is_success() and not res.has_path
    assert "start configuration is in collision" in res.message and "clearance" in res.message
    assert len(res.t) == 0 and res.configs.shape == (0, checker.robot.nx)


CLAUSES = [
    _plans_a_path_the_dense_check_accepts,
    _a_spent_budget_is_reported_as_such,
    _a_blocked_start_is_refused_with_its_reason,
]


@pytest.mark.parametrize("clause", CLAUSES, ids=lambda c: c.__name__.strip("_"))
@pytest.mark.parametrize("name", CORE)
def test_the_contract(name, clause, planners, sim1, checker, monkeypatch):
    clause(name, planners, sim1, checker, monkeypatch)


@pytest.mark.parametrize("clause", CLAUSES, ids=lambda c: c.__name__.strip("_"))
@pytest.mark.parametrize("name", EXTRA)
def test_the_contract_of_an_extra(name, clause, planners, sim1, checker, monkeypatch):
    require_module(BUILTIN.spec(name).optional, hint="pip install -e '.[bench]'")
    clause(name, planners, sim1, checker, monkeypatch)


def test_a_factory_is_given_only_the_build_inputs_it_names():
    """The registry passes a factory the context and, by keyword, only the build inputs its signature names (the
    c-space planner no steer options, OMPL neither those nor obstacle slots); a factory naming any other is refused
    when it is registered."""
    got = {}

    def slots_only(context, *, max_obstacles=None):
        got.update(context=context, max_obstacles=max_obstacles)
        return "built"

    registry = BUILTIN.with_planner(PlannerSpec("slots", slots_only))
    assert registry.create("slots", "the context", SteerOptions(), max_obstacles=4) == "built"
    assert got == {"context": "the context", "max_obstacles": 4}
    assert BUILTIN.spec("cspace").inputs() == ("max_obstacles",)
    assert BUILTIN.spec("rrt").inputs() == ("steer_options", "max_obstacles")
    assert BUILTIN.spec("ompl-rrtconnect").inputs() == ()
    with pytest.raises(InputError, match="'steer'"):
        PlannerSpec("old", lambda context, steer, max_obstacles: None)
