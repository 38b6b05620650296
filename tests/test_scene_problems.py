"""The shape scenes of problems/ (issue 39) plan from their files, and every 10 ms of the timed path keeps D_sf
by an independent brute-force distance (triangles, 2-D sections, every point of a cloud); the safe IK's NLP
keeps its check points outside a box."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.plan import plan_problem
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.ik import SafeIK
from crtraj.planning.steer import SteerOptions, SteerSolver
from crtraj.planning.validity import MotionValidator
from crtraj.viz.view import Visualizer
from crtraj.world.geometry import Box, MovingShape, Pose, exact_distance, exact_min_clearance
from crtraj.world.scene import Scene

PROBLEMS = Path(__file__).resolve().parents[1] / "problems"


def _every_10ms(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    times = np.append(np.arange(t[0], t[-1], 0.01), t[-1])
    return times, np.stack([np.interp(times, t, x[:, j]) for j in range(x.shape[1])], axis=1)


def _exact_clearance(model: Model, scene: Scene, times: np.ndarray, configs: np.ndarray) -> np.ndarray:
    """(S,) body clearance beyond D_sf (mm): 100 fresh backbone points per configuration, brute force."""
    pts = model.points(configs, 100)
    d = np.min([exact_min_clearance(ms, pts, times + scene.time_origin) for ms in scene.shapes], axis=0)
    return d - model.robot.body_radius - scene.safety_distance


@pytest.fixture(scope="module")
def plans():
    out = {}
    for name in ("shapes_table_pipe", "shapes_mesh", "shapes_cloud"):
        out[name] = plan_problem(Problem.load(PROBLEMS / f"{name}.toml"))
    return out


@pytest.mark.parametrize("name", ["shapes_table_pipe", "shapes_mesh", "shapes_cloud"])
def test_example_plans_keep_dsf_by_exact_distance(plans, name):
    """The plan succeeds, and at every 10 ms of its timed path the body keeps D_sf from every shape by the
    brute-force distance, with at most 40 mm to spare somewhere (the shapes are in the way)."""
    run = plans[name]
    assert run.result.is_success()
    assert run.scene.n_shapes >= 1
    times, configs = _every_10ms(np.asarray(run.result.t), np.asarray(run.result.configs))
    clearance = _exact_clearance(run.model, run.scene, times, configs)
    assert clearance.min() >= 0.0, f"{name}: {clearance.min():.3f} mm at t = {times[np.argmin(clearance)]:.2f} s"
    assert clearance.min() < 40.0
    assert len(times) >= 100 * float(run.result.t[-1])


def test_the_exact_check_fails_a_plan_whose_scene_changed(plans):
    """The same path against the scene with its table moved onto the robot's body mid-way: the exact check
    finds the collision (the check is not vacuous)."""
    run = plans["shapes_table_pipe"]
    times, configs = _every_10ms(np.asarray(run.result.t), np.asarray(run.result.configs))
    mid = run.model.points(configs[len(configs) // 2][None], 100)[0, 60]
    table = run.scene.shapes[0]
    moved = MovingShape(replace(table.shape, pose=Pose(tuple(mid), table.shape.pose.rotation)))
    scene = replace(run.scene, shapes=(moved, *run.scene.shapes[1:]))
    assert _exact_clearance(run.model, scene, times, configs).min() < -10.0


def test_safe_ik_nlp_keeps_check_points_outside_a_box():
    """Every solution the safe IK's NLP converges to (no push-out stage) keeps its check points at least the
    inflation plus the IK's margin from the box by the brute-force distance: the box is in the NLP."""
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    box = MovingShape(Box((30.0, 30.0, 30.0), Pose((40.0, 0.0, 300.0))))
    v = MotionValidator(model, Scene(shapes=(box,)))
    ik = SafeIK(model, v, 0, push_rounds=0)
    seeds = v.sample(np.random.default_rng(0), 30)
    batch = ik.solve(np.array([0.0, 0.0, 380.0]), np.zeros(0), seeds, want=8, always=tuple(range(8)))
    solved = [s for s in batch.solutions if s.solver_status == "Solve_Succeeded"]
    assert len(solved) >= 3 and ik.nlp_solves >= 3
    for s in solved:
        d = exact_distance(box, v.points(s.x[None])[0], 0.0)
        assert d.min() >= v.inflate + ik.margin - 1e-5


def test_the_shapes_page_shell_block_runs(tmp_path):
    """docs/concepts/shapes.md's shell block runs as written from the repository root (`crtraj` as this tree's
    `python -m crtraj.cli`) and writes a successful plan."""
    page = (PROBLEMS.parent / "docs" / "concepts" / "shapes.md").read_text(encoding="utf-8")
    blocks = re.findall(r"^```bash\n(.*?)^```", page, flags=re.S | re.M)
    assert len(blocks) == 1
    env = {**os.environ, "PYTHONPATH": str(PROBLEMS.parent)}
    for line in blocks[0].strip().splitlines():
        assert line.startswith("crtraj ")
        cmd = [sys.executable, "-m", "crtraj.cli", *shlex.split(line)[1:]]
        done = subprocess.run(cmd, cwd=PROBLEMS.parent, env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert "exact with cspace" in done.stdout
        out = shlex.split(line)[shlex.split(line).index("--out") + 1]
        assert json.loads(Path(out).read_text())["summary"]["success"] is True


def test_steer_nlp_keeps_its_points_from_a_box():
    """A steer step toward a tip just above a box: with the box in the scene the NLP's collision points keep
    D_sf + disc radius + margin from it by the brute-force distance; the same step without it touches the box."""
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    x0 = np.zeros(model.nx)
    tip0 = model.tip_position(x0)
    box = MovingShape(Box((40.0, 40.0, 10.0), Pose(tuple(tip0 + np.array([70.0, 0.0, -40.0])))))
    target = tip0 + np.array([70.0, 0.0, -30.0])
    steer = SteerSolver(model, 0, SteerOptions(solver="ipopt"))
    res = steer.solve(x0, target, Scene(shapes=(box,)))
    keep = 5.0 + model.robot.body_radius + steer.options.margin
    assert exact_distance(box, steer.nlp.evaluate(res.x)[2], 0.0).min() >= keep - 1e-4
    free = SteerSolver(model, 0, SteerOptions(solver="ipopt")).solve(x0, target, Scene())
    assert exact_distance(box, steer.nlp.evaluate(free.x)[2], 0.0).min() < 1.0


def test_view_draws_each_shape_where_the_scene_puts_it(plans):
    """The view of the table + pipe plan: one node per shape placed at the shape's frame (the sliding bar keyed
    along its motion), a box of the table's size with a shell D_sf larger; the cloud plan's points are drawn
    as all 1,500 points."""
    run = plans["shapes_table_pipe"]
    with Visualizer(run.model, server=False) as vis:
        vis.show_result(run.document())
        cmds = vis.scene_commands()
    tf = {c["path"]: np.array(c["matrix"]).reshape(4, 4).T for c in cmds if c["type"] == "set_transform"}
    objects = {c["path"]: c["object"] for c in cmds if c["type"] == "set_object"}
    table = run.scene.shapes[0]
    o, r, _ = table.frame(0.0)
    np.testing.assert_allclose(tf["/meshcat/shapes/0"][:3, 3], o * 1e-3, atol=1e-9)
    np.testing.assert_allclose(tf["/meshcat/shapes/0"][:3, :3], r, atol=1e-9)
    geometries = {g["type"]: g for g in objects["/meshcat/shapes/0/body/0"]["geometries"]}
    box = geometries["BoxGeometry"]
    np.testing.assert_allclose([box["width"], box["height"], box["depth"]], [0.12, 0.08, 0.08], atol=1e-12)
    shell = {g["type"]: g for g in objects["/meshcat/shapes/0/shell/0"]["geometries"]}["BoxGeometry"]
    assert shell["width"] == pytest.approx(0.12 + 2 * run.scene.safety_distance * 1e-3)
    anims = next(c for c in cmds if c["type"] == "set_animation")["animations"]
    bar = {a["path"]: a for a in anims}["/meshcat/shapes/3"]
    keys = {t["name"]: t for t in bar["clip"]["tracks"]}[".position"]["keys"]
    ms = run.scene.shapes[3]
    for k in keys[:: max(1, len(keys) // 5)]:
        np.testing.assert_allclose(k["value"], ms.frame(k["time"])[0] * 1e-3, atol=1e-6)
    cloud = plans["shapes_cloud"]
    with Visualizer(cloud.model, server=False) as vis:
        vis.show_result(cloud.document())
        pts = [c for c in vis.scene_commands() if c["type"] == "set_object" and c["path"] == "/meshcat/shapes/0/body/0"]
    position = pts[0]["object"]["geometries"][0]["data"]["attributes"]["position"]
    drawn = np.frombuffer(position["array"].data, dtype=np.float32).reshape(-1, 3)
    np.testing.assert_allclose(drawn, cloud.scene.shapes[0].shape.points * 1e-3, atol=1e-6)  # in the shape's frame
