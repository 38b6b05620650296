"""The horizon NLP keeps its body D_sf from obstacles of every shape (issue 39): each kind, fixed and turning,
judged by an independent brute-force distance (fresh backbone points, `exact_distance`), and a closed-loop
replan among shapes reaches its goal with D_sf held every 10 ms of the executed motion."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import PROBLEMS

from crtraj.control.horizon import Replanner, ReplanOptions
from crtraj.control.loop import ClosedLoop
from crtraj.core.errors import InputError
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.world.geometry import (
    Box,
    Capsule,
    Cylinder,
    HalfSpace,
    Keyframes,
    Mesh,
    MovingShape,
    PointCloud,
    Pose,
    Sphere,
    exact_distance,
    exact_min_clearance,
)
from crtraj.world.scene import Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
N = 5
DSF = 5.0
OPTIONS = ReplanOptions(horizon=N, points=10, solver="sqp", max_iter=100)


def _box_mesh(h: float) -> np.ndarray:
    """The 12 triangles (12, 3, 3) of a cube of half side h about the origin."""
    c = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) * h
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1)]
    faces += [(2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return np.array([[c[i] for i in f] for f in faces])


@pytest.fixture(scope="module")
def setting(model):
    """(x0, reference, the unconstrained plan, a placement along its tip motion): the free plan's tip moves L mm
    along u from p0; a shape whose surface is keep + L/2 mm ahead of p0 is clear of the start and in the way."""
    x0 = XS + 0.25 * (XG - XS)
    Xr = x0 + np.clip(0.2 * np.arange(1, N + 1), 0, 1)[:, None] * (XG - x0)
    free = Replanner(model, OPTIONS, max_obstacles=0, safety_distance=DSF)
    res = free.solve(x0, Xr, free.obstacles_from_scene(Scene(), 0.0))
    assert res.is_success()
    p0 = model.tip_position(x0)
    move = model.tip_position(res.configs[-1]) - p0
    L = float(np.linalg.norm(move))
    u = move / L
    ahead = free.shapes.keep + 0.5 * L
    # a plane whose normal is the direction in which the body's extent grows most over the free plan, 5 mm beyond
    # the start body's keep
    P0, P1 = model.points(np.stack([x0, res.configs[-1]]), 100)
    dirs = np.random.default_rng(0).normal(size=(2000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    v = dirs[np.argmax((P1 @ dirs.T).max(axis=0) - (P0 @ dirs.T).max(axis=0))]
    level = float(np.max(P0 @ v)) + free.shapes.keep + 5.0
    return x0, Xr, res.configs, lambda r: tuple(p0 + u * (ahead + r)), (v, level)


def _shapes(at, plane) -> dict[str, MovingShape]:
    u, level = plane
    cloud = np.random.default_rng(1).normal(size=(400, 3))
    cloud = 12.0 * cloud / np.linalg.norm(cloud, axis=1, keepdims=True)
    turn = (0.9659258, 0.0, 0.0, 0.2588190)
    # a box on an arm turning about z by 90 degrees in 0.4 s: the NLP's sweep pad must cover it
    arm = Keyframes(
        (0.0, 0.4), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((1.0, 0.0, 0.0, 0.0), (0.7071068, 0.0, 0.0, 0.7071068))
    )
    c = np.array(at(15.0))
    pivot = c - np.array([40.0, 0.0, 0.0])
    arm = Keyframes(arm.times, (tuple(pivot), tuple(pivot)), arm.rotations)
    return {
        "sphere": MovingShape(Sphere(15.0, Pose(at(15.0)))),
        "box": MovingShape(Box((15.0, 15.0, 15.0), Pose(at(15.0), turn))),
        "capsule": MovingShape(Capsule(10.0, 30.0, Pose(at(10.0), (0.7071068, 0.7071068, 0.0, 0.0)))),
        "cylinder": MovingShape(Cylinder(12.0, 40.0, Pose(at(12.0)))),
        "halfspace": MovingShape(HalfSpace(tuple(-u), -level)),
        "mesh": MovingShape(Mesh(_box_mesh(15.0), 6.0, Pose(at(15.0)))),
        "points": MovingShape(PointCloud(cloud, 3.0, Pose(at(15.0)))),
        "turning box": MovingShape(Box((15.0, 15.0, 15.0), Pose((40.0, 0.0, 0.0))), arm),
    }


def _exact(model, ms: MovingShape, X: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(len(X),) smallest brute-force clearance beyond D_sf + body (mm) of 100 fresh backbone points of each
    configuration over the times (s) given per configuration (rows of `times`)."""
    P = model.points(X, 100)
    out = np.full(len(X), np.inf)
    for i in range(len(X)):
        for t in times[i]:
            out[i] = min(out[i], exact_distance(ms, P[i], float(t)).min())
    return out - DSF - model.robot.body_radius


@pytest.mark.parametrize("kind", ["sphere", "box", "capsule", "cylinder", "halfspace", "mesh", "points", "turning box"])
def test_each_shape_kind_keeps_dsf_over_each_steps_window(model, setting, kind):
    """Every step's configuration keeps D_sf + body from the shape at every time of its window [t_k-1, t_k+1]
    (21 instants) by the brute-force distance, the free plan breaks that, and the shape shaped the plan (its
    rows are active: the plan comes within 40 mm where the reference went through)."""
    x0, Xr, free, at, plane = setting
    ms = _shapes(at, plane)[kind]
    scene = Scene(shapes=(ms,), safety_distance=DSF)
    rp = Replanner(model, OPTIONS, max_obstacles=0, safety_distance=DSF, shapes=(ms,))
    windows = np.stack([np.linspace(a, b, 21) for a, b in zip(*rp.step_windows(0.0), strict=True)])
    assert _exact(model, ms, x0[None], windows[:1]).min() > 0.0  # the start is clear
    assert _exact(model, ms, free, windows).min() < 0.0  # the plan without the shape is not
    res = rp.solve(x0, Xr, rp.obstacles_from_scene(scene, 0.0))
    assert res.feasible, res.solver_status
    clear = _exact(model, ms, res.configs, windows)
    assert clear.min() >= 0.0, (kind, clear)
    assert clear.min() < 40.0
    assert rp.describe()["shape_constraints"] == N * (2 * OPTIONS.points - 1)


def test_shape_parameters_refuse_a_scene_of_other_shapes(model):
    """A replanner built for one box refuses a scene with another one, naming scene.shape (never silently the
    wrong obstacle), and a live state without the shapes' motion."""
    box = MovingShape(Box((10.0, 10.0, 10.0), Pose((0.0, 80.0, 300.0))))
    rp = Replanner(model, OPTIONS, max_obstacles=1, safety_distance=DSF, shapes=(box,))
    other = MovingShape(Box((10.0, 10.0, 11.0), Pose((0.0, 80.0, 300.0))))
    with pytest.raises(InputError, match=r"scene\.shape"):
        rp.obstacles_from_scene(Scene(shapes=(other,)), 0.0)
    with pytest.raises(InputError, match="obstacles_from_scene"):
        rp.obstacles_from_states(np.zeros((1, 3)), np.ones(1))
    assert rp.obstacles_from_scene(Scene(shapes=(box,)), 0.0).shape == (N, rp.obstacle_width)


SMALL = """
name = "shapes_replan_small"
robot = "{robot}"
seed = 1

[task]
start = [-50.0, 100.0, 390.0]
goal = [40.0, 60.0, 330.0]
goal_tolerance = 1.0

[scene]
safety_distance = 5.0

[[scene.shape]]
name = "block"
kind = "box"
half_extents = [15.0, 15.0, 15.0]
position = [0.0, 80.0, 330.0]

[[scene.shape]]
name = "wall"
kind = "halfspace"
normal = [1.0, 0.0, 0.0]
offset = -100.0

[[scene.shape]]
name = "bar"
kind = "capsule"
radius = 8.0
length = 40.0
position = [100.0, 0.0, 250.0]
[scene.shape.keyframes]
times = [0.0, 3.0]
positions = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
rotations = [[1.0, 0.0, 0.0, 0.0], [0.7071068, 0.0, 0.0, 0.7071068]]

[planner]
algorithm = "cspace"
time_limit = 10.0

[replan]
horizon = 8
points = 16
solver = "sqp"
max_iter = 20
step_deadline = 0.0

[loop]
duration = 12.0
"""


def test_closed_loop_among_shapes_reaches_its_goal_keeping_dsf_every_10ms(tmp_path):
    """A replan among a box, a floor and a turning bar reaches the goal with no breach, and at every 10 ms of
    the executed motion 100 fresh backbone points keep D_sf + body from every shape by brute force."""
    path = tmp_path / "small.toml"
    path.write_text(SMALL.format(robot=PROBLEMS / "robots" / "cdsr2.toml"))
    problem = Problem.load(path)
    run = ClosedLoop.from_problem(problem).run()
    assert run.is_success(), run.message
    assert run.nlp["shape_constraints"] > 0
    t, x = np.asarray(run.dense_t), np.asarray(run.dense_x)
    times = np.append(np.arange(t[0], t[-1], 0.01), t[-1])
    configs = np.stack([np.interp(times, t, x[:, j]) for j in range(x.shape[1])], axis=1)
    model = Model(problem.robot)
    scene = Scene.from_table(problem.section("scene"))
    pts = model.points(configs, 100)
    d = np.min([exact_min_clearance(ms, pts, times) for ms in scene.shapes], axis=0)
    clear = d - model.robot.body_radius - scene.safety_distance
    assert clear.min() >= 0.0, (clear.min(), times[np.argmin(clear)])
    assert clear.min() < 40.0  # the shapes were in the way
