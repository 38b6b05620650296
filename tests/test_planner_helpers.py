"""Independent checks of planned motions, shared by the planner tests, and tests of the checks themselves.

`dense_path_check` shares nothing with the planners' validity code: it
samples the timed piecewise-straight path every `dt` seconds, evaluates 200
backbone points per configuration with the model, and measures plain numpy
distances to the obstacle centres of `Scene.states` at each sample's own
time. Points lie on the backbone, so if the continuous body keeps its
distance every sampled point does too: a negative value is a real violation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PAPER_STATIC = ROOT / "problems" / "paper_static.toml"


def dense_path_check(model: Model, scene: Scene, t: np.ndarray, X: np.ndarray, dt: float = 0.01, points: int = 200):
    """Sample the timed path (t (K,), X (K, nx)) every dt seconds.

    Returns (min clearance beyond D_sf and the disc radius (mm), worst limit
    violation, the sampled configurations).
    """
    t = np.asarray(t, dtype=float)
    X = np.asarray(X, dtype=float)
    pieces_x, pieces_t = [X[:1]], [t[:1]]
    for k in range(len(t) - 1):
        n = max(2, int(np.ceil((t[k + 1] - t[k]) / dt)) + 1)
        f = np.linspace(0.0, 1.0, n)[1:]
        pieces_x.append(X[k] + f[:, None] * (X[k + 1] - X[k]))
        pieces_t.append(t[k] + f * (t[k + 1] - t[k]))
    S, T = np.concatenate(pieces_x), np.concatenate(pieces_t)
    limit = float(np.max(model.robot.limit_violation(S)))
    if scene.n_obstacles == 0:
        return np.inf, limit, S
    P = model.points(S, points)  # (N, points, 3)
    centers, radii = scene.states(T)  # (N, M, 3), (N, M)
    d = np.linalg.norm(P[:, :, None, :] - centers[:, None, :, :], axis=-1) - radii[:, None, :]
    clear = float(d.min()) - model.robot.body_radius - scene.safety_distance
    return clear, limit, S


def body_motion_bound(robot, dX: np.ndarray) -> np.ndarray:
    """Closed form of the body-motion bound (mm) for changes dX (N, nx), written from DESIGN.md without
    the validator: u_bar_k = sum_{j>=k} c^(j-k) u_j, w_k = L_k / 2 + sum_{j>k} L_j,
    B = sum_k w_k |d u_bar_k| + |dz|."""
    dX = np.atleast_2d(np.asarray(dX, dtype=float))
    n, c = robot.n_segments, robot.coupling
    lengths = [seg.length for seg in robot.segments]
    out = np.abs(dX[:, -1]).copy()
    for k in range(n):
        dub = sum((c ** (j - k)) * dX[:, 2 * j : 2 * j + 2] for j in range(k, n))
        out += (lengths[k] / 2.0 + sum(lengths[k + 1 :])) * np.linalg.norm(dub, axis=1)
    return out


def full_speed_times(robot, X: np.ndarray, max_speed: float, t0: float = 0.0) -> np.ndarray:
    """Waypoint times (s) of a path moving every body point at most max_speed (mm/s): closed form."""
    return t0 + np.concatenate([[0.0], np.cumsum(body_motion_bound(robot, np.diff(X, axis=0)) / max_speed)])


def test_body_motion_bound_bounds_every_backbone_point(model):
    """The closed form is an upper bound of how far 200 backbone points move, and not a loose one."""
    rng = np.random.default_rng(11)
    lo, hi = model.robot.config_box()
    XA = rng.uniform(0.5 * lo, 0.5 * hi, size=(200, model.nx))
    dX = rng.normal(size=(200, model.nx)) * np.r_[np.full(model.nx - 1, 0.2), 20.0]
    for scale in (1e-3, 1.0):
        XB = XA + scale * dX
        moved = np.linalg.norm(model.points(XB, 200) - model.points(XA, 200), axis=-1).max(axis=1)
        bound = body_motion_bound(model.robot, XB - XA)
        assert np.all(moved <= bound * (1 + 1e-9) + 1e-12)
        assert np.median(moved / bound) > 0.3


def paper_static():
    """(problem, model, scene) of the paper's simulation 1."""
    problem = Problem.load(PAPER_STATIC)
    model = Model(problem.robot)
    return problem, model, problem.options(Scene, "scene")


def assert_valid_plan(res, model: Model, scene: Scene, goal: np.ndarray, tol: float, t0: float = 0.0, start=None):
    """The structural properties every exact plan must have, checked independently."""
    assert res.is_success(), res.message
    assert res.t[0] == pytest.approx(t0)
    assert np.all(np.diff(res.t) >= 0)
    if start is not None:
        np.testing.assert_allclose(res.configs[0], start, atol=1e-12)
    np.testing.assert_allclose(model.tip_position(res.configs), res.tips, atol=1e-9)
    np.testing.assert_allclose(model.robot.cables(res.configs), res.cables, atol=1e-9)
    assert np.linalg.norm(model.tip_position(res.configs[-1]) - goal) <= tol
    clear, limit, _ = dense_path_check(model, scene, res.t, res.configs)
    assert limit <= 1e-9, f"limits violated by {limit}"
    assert clear >= 0.0, f"body within D_sf: dense clearance {clear:.3f} mm"
    return clear


# ------------------------------------------------------------- the checker itself
def test_dense_check_catches_a_collision():
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    model = Model(robot)
    # a sphere the straight robot passes through between t = 1 and t = 2 s
    scene = Scene((Obstacle((0.0, 0.0, 250.0), 20.0, to=(200.0, 0.0, 250.0), duration=1.0, profile="cos"),))
    X = np.array([robot.straight(0.0), robot.straight(0.0)])
    clear, limit, _ = dense_path_check(model, scene, np.array([1.5, 2.5]), X)
    # at t = 2 s the cos profile brings the centre back onto the axis: inside the body
    assert clear < -20.0
    assert limit <= 0.0
    # at t = 1 s it is 200 mm away: clear by 200 - 20 - 3 - 5
    clear_far, _, _ = dense_path_check(model, scene, np.array([1.0, 1.0]), X[:2])
    assert clear_far == pytest.approx(200.0 - 20.0 - robot.body_radius - scene.safety_distance, abs=1e-2)


def test_dense_check_samples_between_waypoints():
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    model = Model(robot)
    scene = Scene((Obstacle((0.0, 0.0, 380.0), 10.0),))
    # swinging the robot from bent -x to bent +x: both ends clear the sphere on the axis, the middle does not
    x_a = robot.straight(0.0)
    x_a[:2] = [-0.8, 0.0]
    x_b = robot.straight(0.0)
    x_b[:2] = [0.8, 0.0]
    ends, _, _ = dense_path_check(model, scene, np.array([0.0, 0.0]), np.stack([x_a, x_a]))
    assert ends > 0
    mid, _, S = dense_path_check(model, scene, np.array([0.0, 2.0]), np.stack([x_a, x_b]))
    assert len(S) > 100
    assert mid < 0
