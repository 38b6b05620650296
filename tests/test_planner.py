"""The paper's task-space RRT / RRT* (Algorithm 1), the problem-file entry point and `crtraj plan`."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import PLANNER_HANG_S
from test_planner_helpers import PAPER_STATIC, assert_valid_plan, paper_static

from crtraj.app.plan import plan_problem
from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.io.problem import Problem
from crtraj.model.robot import Robot
from crtraj.planning.base import Planner
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import CheckOptions, PlannerOptions, RRTOptions
from crtraj.planning.planners._cspace import CSpacePlanner
from crtraj.planning.planners._registry import BUILTIN, make_planner
from crtraj.planning.planners._rrt import RRT, RRTStar
from crtraj.planning.result import PlanStatus
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition
from crtraj.world.scene import Scene


@pytest.fixture(scope="module")
def sim1():
    return paper_static()


@pytest.fixture(scope="module")
def steer_options(sim1):
    problem, _, _ = sim1
    return problem.options(SteerOptions, "steer")


@pytest.fixture(scope="module")
def rrt(sim1, steer_options):
    _, model, scene = sim1
    return RRT(PlanningContext(model, scene, PlannerOptions(algorithm="rrt", time_limit=PLANNER_HANG_S)), steer_options)


@pytest.fixture(scope="module")
def rrtstar(sim1, steer_options):
    _, model, scene = sim1
    return RRTStar(
        PlanningContext(model, scene, PlannerOptions(algorithm="rrtstar", time_limit=PLANNER_HANG_S)), steer_options
    )


def test_rrt_plan_is_valid(sim1, rrt):
    problem, model, scene = sim1
    task = problem.task
    res = rrt.plan(task.goal, start_tip=task.start, seed=0, goal_tolerance=task.goal_tolerance)
    assert res.status is PlanStatus.EXACT and res.planner == "rrt"
    assert np.linalg.norm(res.tips[0] - task.start) <= 1e-3
    assert_valid_plan(res, model, scene, task.goal, task.goal_tolerance)
    # the tree is drawn in tip space; its root is the start tip
    assert res.tree_edges.shape[1:] == (2, 3) and len(res.tree_edges) >= 1
    assert np.min(np.linalg.norm(res.tree_edges[:, 0] - res.tips[0], axis=1)) <= 1e-6
    # cost is the tip length of the tree path (the paper's path length)
    raw_tips = model.tip_position(res.raw_configs)
    assert res.cost == pytest.approx(np.sum(np.linalg.norm(np.diff(raw_tips, axis=0), axis=1)), rel=1e-9, abs=1e-6)
    # the steer keeps the planner's check points, with a margin for the continuous body
    assert rrt.steer.options.n_points == rrt.validator.check_points
    assert rrt.steer.options.margin > rrt.validator.sagitta


def test_rrt_same_seed_same_plan(sim1, rrt):
    problem, _, _ = sim1
    task = problem.task
    a = rrt.plan(task.goal, start_tip=task.start, seed=5, stop=StopCondition(max_iterations=150))
    b = rrt.plan(task.goal, start_tip=task.start, seed=5, stop=StopCondition(max_iterations=150))
    np.testing.assert_array_equal(a.configs, b.configs)
    np.testing.assert_array_equal(a.tree_edges, b.tree_edges)


def test_rrtstar_never_costs_more_than_rrt(sim1, rrt, rrtstar):
    problem, model, scene = sim1
    task = problem.task
    n_better = 0
    for seed in (0, 1):
        stop = StopCondition(max_iterations=120)  # the same tree budget, no early stop
        a = rrt.plan(task.goal, start_tip=task.start, seed=seed, stop=stop)
        b = rrtstar.plan(task.goal, start_tip=task.start, seed=seed, stop=stop)
        # the same samples and steers: the same nodes, only parents differ
        assert a.counts["nodes"] == b.counts["nodes"]
        assert a.counts["steer_calls"] == b.counts["steer_calls"]
        if a.status is PlanStatus.EXACT:
            assert b.status is PlanStatus.EXACT
            assert b.cost <= a.cost + 1e-9
            n_better += b.cost < a.cost - 1e-6
            assert_valid_plan(b, model, scene, task.goal, 1.0)
    assert n_better >= 1  # rewiring does shorten paths


def test_task_space_invalid_start_and_goal(sim1, rrt):
    problem, _, scene = sim1
    task = problem.task
    res = rrt.plan(task.goal, start_tip=np.array(scene.obstacles[1].center), seed=0)
    assert res.status is PlanStatus.INVALID_START
    res = rrt.plan(np.array(scene.obstacles[0].center), start_tip=task.start, seed=0)
    assert res.status is PlanStatus.INVALID_GOAL and "inside an obstacle" in res.message
    res = rrt.plan([0.0, 0.0, 650.0], start_tip=task.start, seed=0)
    assert res.status is PlanStatus.INVALID_GOAL and "reach" in res.message
    res = rrt.plan([140.0, 140.0, -50.0], start_tip=task.start, seed=0)
    assert res.status is PlanStatus.INVALID_GOAL and "search space" in res.message


def test_make_planner_builds_the_named_algorithm(sim1, steer_options, rrt):
    """The registry's planner plans exactly as the class built by hand (same seed, same waypoints)."""
    problem, model, scene = sim1
    task = problem.task
    by_name = make_planner(model, scene)
    by_hand = CSpacePlanner(PlanningContext(model, scene, PlannerOptions()))
    a = by_name.plan(task.goal, start_tip=task.start, seed=7, goal_tolerance=task.goal_tolerance)
    b = by_hand.plan(task.goal, start_tip=task.start, seed=7, goal_tolerance=task.goal_tolerance)
    assert a.is_success() and a.planner == "cspace"
    np.testing.assert_array_equal(a.configs, b.configs)
    np.testing.assert_array_equal(a.t, b.t)
    # the task-space planners: the same query as the fixture gives the same tree and path
    stop = StopCondition(max_iterations=60)
    rrt_named = make_planner(model, scene, PlannerOptions(algorithm="rrt", time_limit=60.0), steer_options)
    c = rrt_named.plan(task.goal, start_tip=task.start, seed=2, stop=stop)
    d = rrt.plan(task.goal, start_tip=task.start, seed=2, stop=stop)
    assert c.planner == d.planner == "rrt"
    np.testing.assert_array_equal(c.tree_edges, d.tree_edges)
    np.testing.assert_array_equal(c.configs, d.configs)
    star = BUILTIN.build("rrtstar", model, scene, PlannerOptions(), steer_options)
    assert star.name == "rrtstar" and star.rewire and isinstance(star, Planner)
    with pytest.raises(InputError, match=r"^planners: unknown planner 'prm'; choose from rrt, rrtstar, cspace"):
        BUILTIN.build("prm", model, scene)


# ------------------------------------------------------------------ problem files and CLI
def test_plan_problem_document(sim1):
    problem, model, _ = sim1
    run = plan_problem(problem, model=model)
    doc = json.loads(json.dumps(run.document()))  # plain JSON
    assert doc["kind"] == "plan" and doc["status"] == "exact" and doc["success"] is True
    assert doc["problem"]["seed"] == problem.seed and doc["problem"]["name"] == "paper_static"
    assert doc["options"]["planner"]["algorithm"] == "cspace"
    from crtraj.core.fields import Table

    assert Robot.from_table(Table(doc["robot"], "robot")) == problem.robot
    scene = Scene.from_table(Table(doc["scene"], "scene"))
    assert scene.n_obstacles == 2
    wps = doc["waypoints"]
    assert len(wps) == len(run.result.t) >= 2
    for w in (wps[0], wps[-1]):
        x = np.array(w["x"])
        np.testing.assert_allclose(w["tip"], model.tip_position(x), atol=1e-9)
        np.testing.assert_allclose(w["q"], problem.robot.cables(x), atol=1e-9)
        assert len(w["q"]) == 7
        np.testing.assert_allclose(w["backbone"], model.points(x), atol=1e-9)
        c, r = scene.states(w["t"])
        np.testing.assert_allclose(w["obstacles"]["centers"], c)
        np.testing.assert_allclose(w["obstacles"]["radii"], r)
    assert np.linalg.norm(np.array(wps[-1]["tip"]) - problem.task.goal) <= problem.task.goal_tolerance
    for key in ("crtraj_version", "casadi_version", "numpy_version", "created", "timing", "summary", "tree"):
        assert key in doc


def test_cli_plan_writes_the_result(tmp_path, capsys):
    out = tmp_path / "res.json"
    rc = main(["plan", str(PAPER_STATIC), "--seed", "3", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0
    assert "exact" in text and "min clearance" in text and str(out) in text
    doc = json.loads(out.read_text())
    assert doc["problem"]["seed"] == 3 and doc["summary"]["planner"] == "cspace"


def test_cli_plan_rrt_and_errors(tmp_path, capsys):
    out = tmp_path / "rrt.json"
    rc = main(["plan", str(PAPER_STATIC), "--planner", "rrt", "--time-limit", str(PLANNER_HANG_S), "--out", str(out)])
    assert rc == 0 and json.loads(out.read_text())["summary"]["planner"] == "rrt"
    capsys.readouterr()
    assert main(["plan", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crtraj: error:") and "no such file" in err and "\n" not in err
    assert main(["plan", str(PAPER_STATIC), "--seed", "-1"]) == 2
    assert main(["plan", str(PAPER_STATIC), "--time-limit", "0"]) == 2
    bad = tmp_path / "bad.toml"
    bad.write_text(
        PAPER_STATIC.read_text().replace("robots/cdsr2.toml", str(PAPER_STATIC.parent / "robots/cdsr2.toml"))
        + "\nfoo = 1\n"
    )
    assert main(["plan", str(bad)]) == 2
    bad.write_text(
        PAPER_STATIC.read_text()
        .replace("robots/cdsr2.toml", str(PAPER_STATIC.parent / "robots/cdsr2.toml"))
        .replace('algorithm = "cspace"', 'algorithm = "prm"')
    )
    assert main(["plan", str(bad)]) == 2
    assert "planner.algorithm" in capsys.readouterr().err


def test_cli_plan_reports_failure_with_exit_1(tmp_path, capsys):
    text = PAPER_STATIC.read_text().replace("robots/cdsr2.toml", str(PAPER_STATIC.parent / "robots/cdsr2.toml"))
    text = text.replace("goal = [10.0, -120.0, 170.0]", "goal = [0.0, 90.0, 330.0]")  # inside the upper sphere
    p = tmp_path / "inside.toml"
    p.write_text(text)
    out = tmp_path / "inside.json"
    assert main(["plan", str(p), "--out", str(out)]) == 1
    assert "invalid_goal" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert doc["success"] is False and doc["status"] == "invalid_goal" and doc["waypoints"] == []


def test_plan_problem_overrides(sim1):
    problem, model, _ = sim1
    run = plan_problem(problem, algorithm="rrtstar", seed=4, time_limit=30.0, model=model)
    assert run.options.algorithm == "rrtstar" and run.options.time_limit == 30.0
    assert run.result.seed == 4 and run.result.planner == "rrtstar"
    assert run.steer_options is not None and run.document()["options"]["steer"]["n_points"] == run.options.check.points
    # the file's [planner] section as written, the rest at its defaults
    read = Problem.load(PAPER_STATIC).options(PlannerOptions, "planner")
    assert read == PlannerOptions(
        algorithm="cspace",
        time_limit=5.0,
        max_iterations=20000,
        max_speed=50.0,
        goal_bias=0.1,
        smooth=True,
        waypoint_step=20.0,
        check=CheckOptions(resolution=3.0, points=15),
        rrt=RRTOptions(rewire_radius=80.0),
    )
    # the override reached the planner: a task-space tree (tip-space edges rooted at the start tip)
    assert run.result.counts["steer_calls"] >= 1 and run.result.tree_edges.shape[1:] == (2, 3)
