"""Tip direction goals (issue 39): ``[task] goal_direction`` with ``goal_cone`` at the goal IK, in the result and the
verifier; the tip tangent is measured independently, by a backward difference of dense backbone points."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import PROBLEMS

from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.core.tomledit import set_values
from crtraj.io.problem import TASK_KEYS, Problem, Task, load_robot
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.planning import BUILTIN
from crtraj.planning.body import planning_model, planning_scene
from crtraj.planning.context import PlanningContext
from crtraj.planning.goal import TipGoal
from crtraj.planning.options import PlannerOptions
from crtraj.planning.result import PlanStatus
from crtraj.world.geometry import exact_min_clearance
from crtraj.world.scene import Scene

TABLE_WALL = PROBLEMS / "scene_table_wall.toml"


_SEGMENT_POINTS: dict[int, object] = {}


def measured_tangent(model: Model, x: np.ndarray) -> np.ndarray:
    """The tip tangent of configuration x from backbone points of its last segment 0.05 mm apart: the second-order
    backward difference of the last three, normalised (not the model's tip frame)."""
    f = _SEGMENT_POINTS.setdefault(id(model), model.segment_point_function())
    h = 0.05 / model.robot.segments[-1].length
    p = [np.asarray(f(x, 1.0 - k * h))[:, -1] for k in range(3)]
    d = 3.0 * p[0] - 4.0 * p[1] + p[2]
    return d / np.linalg.norm(d)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


@pytest.fixture(scope="module")
def table_wall():
    """(problem, model, problem scene, c-space planner) of problems/scene_table_wall.toml."""
    problem = Problem.load(TABLE_WALL)
    model = planning_model(problem.robot, "pcc")
    scene = problem.options(Scene, "scene")
    context = PlanningContext.build(model, planning_scene(scene, model), problem.options(PlannerOptions, "planner"))
    return problem, model, scene, BUILTIN.create("cspace", context)


# directions (any length), cones (deg) and seeds at the table-wall goal; the goal IK refuses the last one
CASES = [
    ((1, 0, 0), 15.0, (0, 1)),
    ((0.5, 0.35, -0.8), 10.0, (0, 1)),
    ((1, 1, 0), 10.0, (0, 1)),
    ((0, 0, 1), 30.0, (0,)),
]


def test_every_success_ends_with_the_tip_tangent_inside_the_cone(table_wall):
    """For every direction and seed that plans: the measured tip tangent at the last waypoint lies within the cone,
    the result's goal_angle is that angle, every goal configuration keeps the cone and the tip is on the goal; the
    first plan's body keeps D_sf every 10 ms (exact distances, 40 fresh backbone points). Most of the cases plan."""
    problem, model, scene, planner = table_wall
    task = problem.task
    successes = 0
    for d, cone, seeds in CASES:
        for seed in seeds:
            res = planner.plan(TipGoal.of(task.goal, d, cone), start_tip=task.start, seed=seed, goal_tolerance=0.5)
            if not res.is_success():
                assert res.status is PlanStatus.INVALID_GOAL and res.message.startswith("unreachable_goal: ")
                continue
            successes += 1
            measured = angle_deg(measured_tangent(model, res.configs[-1]), np.asarray(d, dtype=float))
            assert measured <= cone, (d, cone, seed, measured)
            assert abs(measured - math.degrees(res.goal_angle)) < 1e-3
            assert res.summary()["goal_angle_deg"] == pytest.approx(math.degrees(res.goal_angle))
            for x in res.goal_configs:
                assert angle_deg(measured_tangent(model, x), np.asarray(d, dtype=float)) <= cone
            assert np.linalg.norm(model.tip_position(res.configs[-1]) - task.goal) <= 0.5
            if successes > 1:
                continue  # the exact check below costs half a second a plan: the first success has it
            times = np.append(np.arange(res.t[0], res.t[-1], 0.01), res.t[-1])
            configs = np.stack([np.interp(times, res.t, res.configs[:, j]) for j in range(model.nx)], axis=1)
            pts = model.points(configs, 40)
            d_exact = np.min([exact_min_clearance(ms, pts, times) for ms in scene.shapes], axis=0)
            assert d_exact.min() - model.robot.body_radius - scene.safety_distance >= 0.0
    assert successes >= 5


def one_segment_planner():
    """A c-space planner for the one-segment robot cdsr1 in an empty scene."""
    robot = load_robot(PROBLEMS / "robots" / "cdsr1.toml")
    model = Model(robot)
    scene = Scene(workspace_lo=(-400.0, -400.0, -300.0), workspace_hi=(400.0, 400.0, 400.0))
    return model, BUILTIN.create(
        "cspace",
        PlanningContext.build(
            model, scene, PlannerOptions(time_limit=60.0).with_(check={"compiled": False}, ik={"compiled": False})
        ),
    )


def test_a_direction_the_robot_cannot_take_is_unreachable_goal():
    """One segment of length L = 200 mm puts its tip r = L (1 - cos th) / th off its axis with the tip tangent th from
    it: for r = 100 mm, th = 63.6 deg (the only root in [0, pi]). A tangent within 30 deg of the axis is impossible:
    one line `unreachable_goal`; the tangent the closed form gives (cone 3 deg) plans, and ends within 3 deg of it."""
    model, planner = one_segment_planner()
    th = 1.0
    for _ in range(50):  # Newton on L (1 - cos th) / th = 100
        f = 200.0 * (1.0 - math.cos(th)) / th - 100.0
        df = 200.0 * (math.sin(th) * th - (1.0 - math.cos(th))) / th**2
        th -= f / df
    goal = np.array([100.0 / math.sqrt(2.0), 100.0 / math.sqrt(2.0), 120.0])
    start = model.tip_position(np.array([0.2, -0.1, 0.0]))
    bad = planner.plan(TipGoal.of(goal, [0, 0, 1], 30.0), start_tip=start, seed=0)
    assert bad.status is PlanStatus.INVALID_GOAL
    assert bad.message.startswith("unreachable_goal: ") and "\n" not in bad.message
    assert "within 30 deg of [0.0, 0.0, 1.0]" in bad.message
    azimuth = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    exact = math.sin(th) * azimuth + math.cos(th) * np.array([0.0, 0.0, 1.0])
    good = planner.plan(TipGoal.of(goal, exact, 3.0), start_tip=start, seed=0)
    assert good.is_success(), good.message
    assert angle_deg(measured_tangent(model, good.configs[-1]), exact) <= 3.0


def test_bad_direction_input_is_one_line_naming_the_key():
    """A zero direction, a cone outside (0, 180], a direction without a cone and a cone without a direction: each
    one `InputError` naming the key, from the problem file and from Python alike."""
    base = {"start": [0.0, 0.0, 390.0], "goal": [80.0, 0.0, 290.0]}
    cases = [
        ({"goal_direction": [0.0, 0.0, 0.0], "goal_cone": 10.0}, "task.goal_direction: must be a non-zero vector"),
        ({"goal_direction": [1.0, 0.0, 0.0], "goal_cone": 0.0}, "task.goal_cone: must be > 0"),
        ({"goal_direction": [1.0, 0.0, 0.0], "goal_cone": 190.0}, "task.goal_cone: must be <= 180"),
        ({"goal_direction": [1.0, 0.0, 0.0]}, "task.goal_direction: needs goal_cone"),
        ({"goal_cone": 10.0}, "task.goal_cone: given without goal_direction"),
        ({"goal_direction": [1.0, 0.0], "goal_cone": 10.0}, "task.goal_direction: expected 3"),
    ]
    robot = load_robot(PROBLEMS / "robots" / "cdsr2.toml")
    for extra, text in cases:
        with pytest.raises(InputError) as err:
            Problem.from_dict({"robot": robot.to_dict(), "task": {**base, **extra}})
        assert str(err.value).startswith(text), (extra, str(err.value))
        assert "\n" not in str(err.value)
    with pytest.raises(InputError, match=r"^goal_direction: must be a non-zero vector"):
        TipGoal.of([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], 10.0)
    ok = Problem.from_dict({"robot": robot.to_dict(), "task": {**base, "goal_direction": [0, 0, -2], "goal_cone": 5}})
    np.testing.assert_allclose(ok.task.goal_direction, [0.0, 0.0, -1.0])
    assert ok.task.tip_goal().cone == pytest.approx(math.radians(5.0))


def test_task_keys_are_the_keys_read_and_the_reference_lists_them():
    """Every key of TASK_KEYS is read by Task.from_table (a table with all of them parses; one more key is refused),
    and the generated problem-file reference has a row for each, the direction keys with their units."""
    from test_docs import _hook

    from crtraj.core.fields import Table

    values = {
        "start": [0.0, 0.0, 390.0],
        "goal": [80.0, 0.0, 290.0],
        "goal_tolerance": 0.5,
        "start_config": [0.0] * 5,
        "goal_direction": [1.0, 0.0, 0.0],
        "goal_cone": 10.0,
    }
    assert sorted(values) == sorted(k[0] for k in TASK_KEYS)
    Task.from_table(Table(values, "task"), 5)
    with pytest.raises(InputError, match="goal_angle"):
        Task.from_table(Table({**values, "goal_angle": 1.0}, "task"), 5)
    page = _hook().problem_markdown()
    assert "## The `[task]` table" in page
    for key, *_ in TASK_KEYS:
        assert f"| `{key}` |" in page
    assert "| `goal_cone` | float (optional) |  | deg |" in page


def test_plan_file_reports_the_angle_and_verify_fails_outside_the_cone(tmp_path, capsys):
    """`crtraj plan` of the table-wall task with a direction writes the direction, cone and final angle (read back
    as written, the angle equal to the measured one); `crtraj verify` prints that angle and passes; the same result
    with its direction turned by 90 deg fails verify with one line naming goal_cone."""
    robot = PROBLEMS / "robots" / "cdsr2.toml"
    text = set_values(
        TABLE_WALL.read_text(), {("task", "goal_direction"): [1.0, 0.0, 0.0], ("task", "goal_cone"): 15.0}
    )
    path = tmp_path / "p.toml"
    path.write_text(text.replace('robot = "robots/cdsr2.toml"', f"robot = {json.dumps(str(robot))}"))
    out = tmp_path / "plan.json"
    assert main(["plan", str(path), "--out", str(out), "-q"]) == 0
    doc = json.loads(out.read_text())
    res = read_result(out)
    np.testing.assert_allclose(res.goal_direction, [1.0, 0.0, 0.0])
    assert res.goal_cone == 15.0
    model = Model(res.robot)
    measured = angle_deg(measured_tangent(model, res.x[-1]), np.array([1.0, 0.0, 0.0]))
    assert measured <= 15.0
    assert doc["summary"]["goal_angle_deg"] == pytest.approx(measured, abs=1e-3)
    # the rod re-shapes only the last three waypoints (the check at the goal; the whole path costs seconds)
    doc["waypoints"] = doc["waypoints"][-3:]
    out.write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["verify", str(out), "--model", "cosserat", "--robot", str(robot)]) == 0
    printed = capsys.readouterr().out
    assert f"tip tangent at the goal {measured:.2f} deg (PCC)" in printed
    doc["task"]["goal_direction"] = [0.0, 1.0, 0.0]
    turned = tmp_path / "turned.json"
    turned.write_text(json.dumps(doc))
    assert main(["verify", str(turned), "--model", "cosserat", "--robot", str(robot)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "goal_cone: the final tip tangent is" in err[0] and "outside the 15 deg cone" in err[0]


def _direction_problem(tmp_path, values=None, name="p.toml"):
    """The table-wall problem with goal_direction [1, 0, 0] and goal_cone 15 deg (and `values`), its robot by an
    absolute path, written to tmp_path/name."""
    robot = PROBLEMS / "robots" / "cdsr2.toml"
    extra = {("task", "goal_direction"): [1.0, 0.0, 0.0], ("task", "goal_cone"): 15.0, **(values or {})}
    text = set_values(TABLE_WALL.read_text(), extra)
    path = tmp_path / name
    path.write_text(text.replace('robot = "robots/cdsr2.toml"', f"robot = {json.dumps(str(robot))}"))
    return path


def test_planners_that_do_not_honour_a_direction_refuse_it(tmp_path, capsys):
    """`crtraj plan --planner rrt`, and `crtraj replan` with an rrt reference planner, of a task with a direction:
    exit 2, one stderr line naming goal_direction, nothing written."""
    path = _direction_problem(tmp_path)
    rrt = _direction_problem(tmp_path, {("planner", "algorithm"): "rrt"}, "rrt.toml")
    for argv in (
        ["plan", str(path), "--planner", "rrt", "--out", str(tmp_path / "rrt.json"), "-q"],
        ["replan", str(rrt), "--out", str(tmp_path / "run"), "--no-html", "-q"],
    ):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "goal_direction" in err[0] and "rrt" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "rrt.toml"]


def test_replan_holds_the_goal_with_the_tip_tangent_inside_the_cone(tmp_path, capsys):
    """`crtraj replan` of the table-wall task with a direction (from a start nearer the goal: a short run) reaches and
    holds the goal; the measured tip tangent of the run's final configuration lies within the 15 deg cone, the run
    file records the direction, and the printed angle is the measured one. (The same run without the direction
    ends 66 deg from it, measured once: the cone binds.)"""
    path = _direction_problem(tmp_path, {("task", "start"): [60.0, 0.0, 320.0]})
    run = tmp_path / "run"
    capsys.readouterr()
    assert main(["replan", str(path), "--out", str(run), "--no-html"]) == 0
    printed = capsys.readouterr().out
    res = read_result(run / "run.json")
    np.testing.assert_allclose(res.goal_direction, [1.0, 0.0, 0.0])
    model = Model(res.robot)
    measured = angle_deg(measured_tangent(model, res.x[-1]), np.array([1.0, 0.0, 0.0]))
    assert measured <= 15.0
    assert f"goal direction: final tip tangent {measured:.2f} deg from goal_direction (cone 15 deg): within" in printed
    assert np.linalg.norm(model.tip_position(res.x[-1]) - res.goal) <= 0.5
