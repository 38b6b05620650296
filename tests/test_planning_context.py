"""The planning context (issue 26): planners built from one typed context, the per-planner options with their
sub-tables, actuator limits from the robot description, and the library's plan-to-executable pipeline."""

from __future__ import annotations

import io
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import PROBLEMS, require_module, require_tool

from crtraj import cli
from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.core.fileio import read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.planning import PlanningContext, plan_executable
from crtraj.planning.base import PlannerBase
from crtraj.planning.options import MOVED, PlannerOptions
from crtraj.planning.planners import BUILTIN
from crtraj.planning.validity import Kernels
from crtraj.world.scene import Scene

STATIC = PROBLEMS / "paper_static.toml"
RATE = 100.0


def _copy(tmp_path: Path, text: str) -> Path:
    """paper_static.toml's text as a problem file in tmp_path, with its robot path made absolute."""
    robot = PROBLEMS / "robots" / "cdsr2.toml"
    p = tmp_path / "p.toml"
    p.write_text(text.replace('robot = "robots/cdsr2.toml"', f'robot = "{robot.as_posix()}"'))
    return p


@pytest.mark.parametrize("old", [*MOVED, "range"])
def test_an_old_flat_planner_key_names_its_new_place_in_one_line(old, tmp_path, capsys):
    """A file with an old flat [planner] key gets one line naming the key and where it went, exit 2."""
    value = '"paper"' if old == "check" else ("true" if old == "compiled" else "3")
    text = STATIC.read_text()
    if old == "check":  # the old string and the new table cannot both be in one file
        text = re.sub(r"\[planner\.check\]\n(.+\n)+", "", text)
    p = _copy(tmp_path, text.replace("[planner]\n", f"[planner]\n{old} = {value}\n", 1))
    capsys.readouterr()
    assert cli.main(["plan", str(p), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    if old == "range":
        where = "[planner.cspace] range and [planner.rrt] range"
    else:
        where = f"[planner.{MOVED[old][0]}] {MOVED[old][1]}"
    assert err == f"crtraj: error: planner.{old}: moved to {where}\n"
    assert not (tmp_path / "r.json").exists()


def test_sub_tables_are_read_where_the_old_keys_went():
    """Each old key's value, written in its new sub-table, arrives in that sub-table's options."""
    table = {"ik": {"seeds": 7, "goal_window": 2.5}, "check": {"mode": "paper", "points": 9}}
    table |= {"cspace": {"via_points": 0, "range": 90.0}, "rrt": {"rewire_radius": 60.0, "range": 30.0}}
    robot = read_toml(PROBLEMS / "robots" / "cdsr2.toml")["robot"]
    o = Problem.from_dict({"robot": robot, "planner": table}).options(PlannerOptions, "planner")
    assert (o.ik.seeds, o.ik.goal_window, o.ik.iterations) == (7, 2.5, 15)
    assert (o.check.mode, o.check.points, o.check.resolution) == ("paper", 9, 3.0)
    assert (o.cspace.via_points, o.step, o.rrt.rewire_radius, o.with_(algorithm="rrt").step) == (0, 90.0, 60.0, 30.0)
    with pytest.raises(InputError, match=r"^planner\.check\.points: must be >= 2, got 1$"):
        PlannerOptions().with_(check={"points": 1})
    with pytest.raises(InputError, match=r"^planner\.ik\.seed: unknown option$"):
        PlannerOptions().with_(ik={"seed": 1})


def test_robot_rate_limits_are_the_servo_rates_of_its_cables(robot):
    """J dx is each actuator's rate: cable rate / spool radius (10 mm, sign +1) for servos, dz for the stage,
    measured by finite differences of the model's cable lengths; the limits are the file's."""
    limits = robot.rate_limits()
    model = Model(robot)
    rng = np.random.default_rng(0)
    x = robot.straight(-50.0) + 0.1 * rng.normal(size=robot.nx)
    dx = rng.normal(size=robot.nx)
    h = 1e-6
    dq = (model.cables(x + h * dx) - model.cables(x - h * dx)) / (2 * h)
    rates = np.append(dq[:-1] / 10.0, dq[-1])
    np.testing.assert_allclose(limits.jacobian @ dx, rates, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(limits.vmax, [5.0] * 6 + [20.0])
    np.testing.assert_array_equal(limits.amax, [50.0] * 6 + [100.0])
    # the hardware's actuators give the same limits (it reads only the bus keys beside them)
    acts = Actuators.from_robot(robot).rate_limits(robot)
    np.testing.assert_array_equal(acts.jacobian, limits.jacobian)
    assert load_robot(PROBLEMS / "robots" / "cdsr2.toml").rate_limits() is not None


def test_every_registered_planner_is_built_from_the_context(model):
    """Each built-in planner holds a context sharing the given one's kernels; the c-space planner times its
    edges within the rate limits, the task-space ones (and OMPL) at max_speed only."""
    context = PlanningContext.build(model, Scene(), PlannerOptions())
    assert context.rate_limits is not None
    names = [n for n in BUILTIN.names if not n.startswith("ompl")]
    try:
        require_module("ompl")
        names = list(BUILTIN.names)
    except pytest.skip.Exception:
        pass
    dz = np.zeros((1, model.nx))
    dz[0, -1] = 200.0  # mm of z
    for name in names:
        planner = BUILTIN.create(name, context)
        assert isinstance(planner, PlannerBase) and planner.context.kernels is context.kernels
        assert (planner.context.rate_limits is not None) == (name == "cspace")
        # a fast z motion: the stage's speed limit (18 mm/s usable) binds before the body speed (50 mm/s)
        t = float(planner.validator.duration(dz)[0])
        assert t == pytest.approx(200.0 / 18.0 if name == "cspace" else 200.0 / 50.0, rel=1e-9)


def test_a_context_built_with_injected_kernels_compiles_into_their_cache(model, tmp_path):
    """The seam for the build cache: the context's validators load their kernel from the injected cache."""
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    cache = BuildCache(tmp_path)
    context = PlanningContext(model, Scene(), PlannerOptions(), kernels=Kernels(cache))
    assert context.state.kernel is not None and context.state.kernel.library.is_relative_to(tmp_path)
    assert cache.builds == 1
    other = context.motion_validity(Problem.load(STATIC).options(Scene, "scene"))
    assert other.state.kernel is context.state.kernel and cache.builds == 1
    out = io.StringIO()
    no_cc = Kernels(BuildCache(tmp_path / "n", compiler=None, notice=out))
    bare = PlanningContext(model, Scene(), PlannerOptions(), kernels=no_cc)
    assert bare.state.kernel is None and len(out.getvalue().splitlines()) == 1


def test_quick_start_gives_an_executable_verified_motion_within_the_limits():
    """The README's quick start: the waypoints are the set-points a streamer at 100 Hz sends, every actuator
    keeps within limit_fraction of its speed and acceleration limits (finite differences of the hardware's
    own sampling), the motion starts on the start tip and ends on the goal, clear of D_sf."""
    problem = Problem.load(STATIC)
    task = problem.require_task()
    scene = problem.options(Scene, "scene")
    context = PlanningContext.build(Model(problem.robot), scene, problem.options(PlannerOptions, "planner"))
    run = plan_executable(context, task.goal, start_tip=task.start, seed=problem.seed)
    assert run.is_success() and run.min_clearance >= 0.0 and run.duration > 0
    r, acts = run.result, Actuators.from_robot(problem.robot)
    stamps, sent = SetpointPath.from_actuation(r.t, r.cables, acts).sample(RATE)
    np.testing.assert_allclose(stamps, r.t, atol=1e-9)
    V = np.diff(sent, axis=0) * RATE
    A = np.diff(np.vstack([np.zeros((1, V.shape[1])), V]), axis=0) * RATE
    f = context.options.limit_fraction
    assert np.max(np.abs(V) / acts.vmax) <= f * (1 + 1e-6) and np.max(np.abs(A) / acts.amax) <= f * (1 + 1e-6)
    assert run.timing["max_velocity_fraction"] == pytest.approx(np.max(np.abs(V) / acts.vmax), abs=1e-12)
    model = context.model
    assert np.linalg.norm(model.tip_position(r.configs[0]) - task.start) <= 1e-3
    assert np.linalg.norm(model.tip_position(r.configs[-1]) - task.goal) <= 1.0


def test_without_actuators_the_planner_timing_stands(robot):
    """A robot without [robot.actuators]: no rate limits, no retiming; the result is the planner's own."""
    bare = replace(robot, actuators=None)
    problem = Problem.load(STATIC)
    task = problem.require_task()
    scene = problem.options(Scene, "scene")
    context = PlanningContext.build(Model(bare), scene, problem.options(PlannerOptions, "planner"))
    assert context.rate_limits is None
    run = plan_executable(context, task.goal, start_tip=task.start, seed=1)
    direct = BUILTIN.create("cspace", context).plan(task.goal, start_tip=task.start, seed=1)
    assert run.timing is None and run.is_success()
    np.testing.assert_array_equal(run.result.t, direct.t)
    np.testing.assert_array_equal(run.result.configs, direct.configs)
