"""Retiming within the actuator limits: closed forms, finite differences of what the streamer sends,
the geometry the planner verified, and a dense clearance check among moving obstacles."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PROBLEMS
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.app.plan import retime_result
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.rate_limits import RateLimits
from crtraj.planning.registry import make_planner
from crtraj.planning.retime import retime
from crtraj.world.scene import Scene

RATE = 100.0
TOL = 1e-9


def _distance_to_polyline(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Distance of each point of P (N, n) to the polyline X (K, n) (brute force over segments)."""
    A, D = X[:-1], np.diff(X, axis=0)
    dd = np.maximum(np.einsum("kn,kn->k", D, D), 1e-300)
    u = np.clip(np.einsum("pkn,kn->pk", P[:, None, :] - A[None], D) / dd, 0.0, 1.0)
    near = A[None] + u[..., None] * D[None]
    return np.min(np.linalg.norm(P[:, None, :] - near, axis=2), axis=1)


def _fd_fractions(values: np.ndarray, vmax: np.ndarray, amax: np.ndarray, dt: float) -> tuple[float, float]:
    """Largest |velocity| / vmax and |acceleration| / amax of set-points every dt, from rest to rest."""
    V = np.diff(values, axis=0) / dt
    Vz = np.vstack([np.zeros((1, V.shape[1])), V, np.zeros((1, V.shape[1]))])
    A = np.diff(Vz, axis=0) / dt
    return float(np.max(np.abs(V) / vmax)), float(np.max(np.abs(A) / amax))


# ------------------------------------------------------------------ properties
@st.composite
def _paths(draw):
    k = draw(st.integers(2, 6))
    m = draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    X = rng.normal(scale=draw(st.sampled_from([0.05, 1.0, 5.0])), size=(k, 5))
    if draw(st.booleans()):  # a collinear run and a repeated waypoint
        X = np.concatenate([X[:1], 0.5 * (X[:1] + X[1:2]), X[1:], X[-1:]])
    J = rng.normal(size=(m, 5))
    vmax = 10 ** rng.uniform(-1, 2, size=m)
    amax = 10 ** rng.uniform(-1, 3, size=m)
    speed = float(10 ** rng.uniform(1, 3))
    return X, RateLimits(J, vmax, amax, tuple(f"a{i}" for i in range(m))), speed


@settings(max_examples=60, deadline=None)
@given(_paths())
def test_retimed_motion_never_exceeds_a_limit_and_stays_on_the_path(robot, case):
    X, lim, speed = case
    metric = BodyMetric(robot, speed)
    law = retime(X, lim, metric, t0=1.25, period=1.0 / RATE)
    stamps, Y = law.sample()
    assert stamps[0] == 1.25 and np.allclose(np.diff(stamps), 1.0 / RATE)
    assert np.array_equal(Y[0], X[0]) and np.max(np.abs(Y[-1] - X[-1])) <= TOL
    assert np.max(_distance_to_polyline(Y, X)) <= TOL * max(1.0, np.abs(X).max())
    # the actuator values by the linear map, differenced by the test itself
    vf, af = _fd_fractions(Y @ lim.jacobian.T, lim.vmax, lim.amax, 1.0 / RATE)
    assert vf <= 1 + 1e-9 and af <= 1 + 1e-9
    body = metric.motion_bound(np.diff(Y, axis=0)) * RATE
    assert np.max(body, initial=0.0) <= speed * (1 + 1e-9)


@settings(max_examples=80, deadline=None)
@given(
    st.floats(1e-3, 1e2),  # distance in actuator units
    st.floats(1e-1, 1e2),  # vmax
    st.floats(1e-2, 1e3),  # amax
    st.integers(0, 4),  # direction component
)
def test_single_straight_motion_is_time_optimal(robot, d, v, a, axis):
    """One actuator, no body-speed bound in play: bang-coast-bang closed form, up to one period."""
    J = np.zeros((1, 5))
    J[0, axis] = 2.0
    x1 = np.zeros(5)
    x1[axis] = d / 2.0
    lim = RateLimits(J, [v], [a], ("a",))
    law = retime(np.stack([np.zeros(5), x1]), lim, BodyMetric(robot, 1e12), period=1.0 / RATE)
    t_exact = d / v + v / a if d >= v * v / a else 2.0 * np.sqrt(d / a)
    assert t_exact - 1e-9 <= law.duration <= t_exact + 1.0 / RATE + 1e-9


# ------------------------------------------------------------------ sim 1
@pytest.fixture(scope="module")
def sim1():
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    model = Model(problem.robot)
    act = Actuators.from_robot(problem.robot)
    limits = act.rate_limits(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    planner = make_planner(model, scene, options, rate_limits=limits)
    return problem, model, act, limits, options, planner


@pytest.mark.parametrize("seed", [1, 2, 3, 12])
def test_sim1_retimed_within_limits_on_the_verified_path(sim1, seed):
    problem, model, act, limits, options, planner = sim1
    task = problem.require_task()
    r0 = planner.plan(task.goal, start_tip=task.start, seed=seed, goal_tolerance=task.goal_tolerance)
    assert r0.is_success()
    r1, info = retime_result(r0, planner.validator, options, act, limits, RATE)
    assert info["outcome"] == "retimed"
    # geometry: every new waypoint on the verified polyline
    assert np.max(_distance_to_polyline(r1.configs, r0.configs)) <= TOL
    # what the streamer sends: its own sampling of the result, actuator values from the model's
    # cable lengths (not the rate-limit Jacobian), differenced here
    f = options.limit_fraction
    _, sent = SetpointPath.from_actuation(r1.t, model.cables(r1.configs), act).sample(RATE)
    vf, af = _fd_fractions(sent, f * act.vmax, f * act.amax, 1.0 / RATE)
    assert vf <= 1 + 1e-6 and af <= 1 + 1e-6
    assert info["max_velocity_fraction"] <= f * (1 + 1e-6)
    # the sampled set-points are the result's waypoints themselves
    assert len(sent) == len(r1.t)
    assert np.allclose(sent, act.command(model.cables(r1.configs)), atol=1e-9)
    # the planner's own timing, sampled the same way: when it was within limits, retiming is no slower
    _, old = SetpointPath.from_actuation(r0.t, r0.cables, act).sample(RATE)
    vf0, af0 = _fd_fractions(old, f * act.vmax, f * act.amax, 1.0 / RATE)
    if vf0 <= 1 and af0 <= 1:
        assert r1.duration <= r0.duration + 1e-9


def test_dynamic_retiming_is_clear_at_its_own_times_or_keeps_the_verified_timing():
    problem = Problem.load(PROBLEMS / "paper_dynamic.toml")
    model = Model(problem.robot)
    act = Actuators.from_robot(problem.robot)
    limits = act.rate_limits(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    planner = make_planner(model, scene, options, rate_limits=limits)
    task = problem.require_task()
    r0 = planner.plan(task.goal, start_tip=task.start, seed=problem.seed, goal_tolerance=task.goal_tolerance)
    assert r0.has_path
    # the timed search times every motion within the actuators' speed limits
    usable = limits.scaled(options.limit_fraction)
    assert np.max(usable.velocity_fraction(np.diff(r0.configs, axis=0) / np.diff(r0.t)[:, None])) <= 1 + 1e-6
    r1, info = retime_result(r0, planner.validator, options, act, limits, RATE)
    if info["outcome"].startswith("kept"):
        assert np.array_equal(r1.t, r0.t) and np.array_equal(r1.configs, r0.configs)
        return
    assert np.max(_distance_to_polyline(r1.configs, r0.configs)) <= TOL
    # dense independent clearance: 4 sub-steps per set-point, backbone points against the true spheres
    ts = np.linspace(r1.t[0], r1.t[-1], 4 * len(r1.t))
    Xs = np.stack([np.interp(ts, r1.t, r1.configs[:, j]) for j in range(r1.configs.shape[1])], axis=1)
    pts = model.points(Xs, 40)
    centers, radii = scene.states(ts)
    centers = centers.reshape(len(ts), -1, 3)
    radii = radii.reshape(len(ts), -1)
    d = np.linalg.norm(pts[:, :, None, :] - centers[:, None, :, :], axis=3) - radii[:, None, :]
    assert np.min(d) - problem.robot.body_radius - scene.safety_distance >= -1e-6
