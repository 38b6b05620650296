"""Retiming within the actuator limits: closed forms, finite differences of what the streamer sends,
the geometry the planner verified, and a dense clearance check among moving obstacles."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PROBLEMS
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.context import PlanningContext
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.pipeline import retime_result
from crtraj.planning.planners import BUILTIN
from crtraj.planning.retime import retime, retime_curve
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
    context = PlanningContext.build(model, scene, options)
    return problem, model, act, limits, context, BUILTIN.create(options.algorithm, context)


def _body_fraction(X: np.ndarray, metric: BodyMetric, dt: float) -> float:
    """Largest body-motion bound per frame period over max_speed, of frames X every dt."""
    return float(np.max(metric.motion_bound(np.diff(X, axis=0)), initial=0.0) / dt / metric.max_speed)


def _static_clearance(model: Model, scene: Scene, X: np.ndarray, sub: int = 4) -> float:
    """Smallest distance (mm) beyond body radius and D_sf of 40 backbone points to the static spheres, over the
    frames X and `sub` points on each straight motion between them (as the streamer's frames are joined)."""
    u = np.arange(sub) / sub
    Xs = np.vstack(
        [(X[:-1, None, :] + u[None, :, None] * np.diff(X, axis=0)[:, None, :]).reshape(-1, X.shape[1]), X[-1:]]
    )
    pts = model.points(Xs, 40)
    C = np.array([o.center for o in scene.obstacles])
    R = np.array([o.radius for o in scene.obstacles])
    d = np.linalg.norm(pts[:, :, None, :] - C[None, None], axis=3) - R
    return float(np.min(d) - model.robot.body_radius - scene.safety_distance)


@pytest.mark.parametrize("seed", range(1, 11))
def test_sim1_retimed_within_limits_and_no_slower_than_the_planner_timing(sim1, seed):
    """Static sim 1, the 10 seeds: the retimed motion, as the streamer sends it, keeps every actuator within
    limit_fraction of its limits and the body within max_speed, is clear of the spheres (dense independent
    check of the frames and the straight motions between them), and is no longer than the planner's own
    timing whenever that timing, as streamed, keeps the same limits. (The planner's timing streams through
    PCHIP from rest at full body speed, so it reaches 4/3 of max_speed on its first and last motion; it is
    also compared after the uniform slow-down that brings it within the limits, and against the chord law.)"""
    problem, model, act, limits, context, planner = sim1
    options = context.options
    task = problem.require_task()
    scene = problem.options(Scene, "scene")
    r0 = planner.plan(task.goal, start_tip=task.start, seed=seed, goal_tolerance=task.goal_tolerance)
    assert r0.is_success()
    r1, info = retime_result(r0, planner.validator, context, act.limits, RATE)
    assert info["outcome"].startswith("retimed")
    f, dt = options.limit_fraction, 1.0 / RATE
    metric = BodyMetric(problem.robot, options.max_speed)
    # what the streamer sends: its own sampling of the result, actuator values from the model's
    # cable lengths (not the rate-limit Jacobian), differenced here
    _, sent = SetpointPath.from_actuation(r1.t, model.cables(r1.configs), act).sample(RATE)
    assert len(sent) == len(r1.t) and np.allclose(sent, act.command(model.cables(r1.configs)), atol=1e-9)
    vf, af = _fd_fractions(sent, f * act.vmax, f * act.amax, dt)
    assert vf <= 1 + 1e-6 and af <= 1 + 1e-6
    assert info["max_velocity_fraction"] <= f * (1 + 1e-6)
    assert np.all(sent >= act.lower - 1e-9) and np.all(sent <= act.upper + 1e-9)
    X1 = problem.robot.config(act.actuation(sent))
    assert _body_fraction(X1, metric, dt) <= 1 + 1e-6
    assert np.max(np.abs(X1[0] - r0.configs[0])) <= 1e-9 and np.max(np.abs(X1[-1] - r0.configs[-1])) <= 1e-9
    assert _static_clearance(model, scene, X1) >= -1e-6
    # the planner's own timing, sampled and checked the same way
    _, old = SetpointPath.from_actuation(r0.t, r0.cables, act).sample(RATE)
    vf0, af0 = _fd_fractions(old, f * act.vmax, f * act.amax, dt)
    bf0 = _body_fraction(problem.robot.config(act.actuation(old)), metric, dt)
    if max(vf0, af0, bf0) <= 1:
        assert r1.duration <= r0.duration + 1e-9
    # slowed uniformly until it keeps the limits (speed / s, acceleration / s^2), it is never faster
    assert r1.duration <= r0.duration * max(1.0, vf0, np.sqrt(af0), bf0) + 1e-9
    # nor is the rest-to-rest law along the chords (which stops at every corner)
    chords = retime(r0.configs, limits.scaled(f), metric, t0=float(r0.t[0]), period=dt)
    assert r1.duration <= chords.duration + 1e-9


def test_dynamic_retiming_is_clear_at_its_own_times_or_keeps_the_verified_timing():
    problem = Problem.load(PROBLEMS / "paper_dynamic.toml")
    model = Model(problem.robot)
    act = Actuators.from_robot(problem.robot)
    limits = act.rate_limits(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    context = PlanningContext.build(model, scene, options)
    planner = BUILTIN.create(options.algorithm, context)
    task = problem.require_task()
    r0 = planner.plan(task.goal, start_tip=task.start, seed=problem.seed, goal_tolerance=task.goal_tolerance)
    assert r0.has_path
    # the timed search times every motion within the actuators' speed limits
    usable = limits.scaled(options.limit_fraction)
    assert np.max(usable.velocity_fraction(np.diff(r0.configs, axis=0) / np.diff(r0.t)[:, None])) <= 1 + 1e-6
    r1, info = retime_result(r0, planner.validator, context, act.limits, RATE)
    if info["outcome"].startswith("kept"):
        assert np.array_equal(r1.t, r0.t) and np.array_equal(r1.configs, r0.configs)
        return
    if not info["outcome"].startswith("retimed along the smoothed curve"):
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


class _PolylineOnly:
    """A stand-in validator (static scene) that accepts a straight motion only when both ends lie on the polyline
    X: the smoothed curve fails wherever it leaves the chords."""

    static = True

    def __init__(self, X: np.ndarray, tol: float = 1e-9) -> None:
        self.X, self.tol = X, tol
        self.calls = 0

    def within_limits(self, Y: np.ndarray) -> np.ndarray:
        return np.ones(len(np.atleast_2d(Y)), dtype=bool)

    def edges_valid(self, A: np.ndarray, B: np.ndarray, TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
        self.calls += 1
        return (_distance_to_polyline(A, self.X) <= self.tol) & (_distance_to_polyline(B, self.X) <= self.tol)


class _AcceptAll(_PolylineOnly):
    def edges_valid(self, A: np.ndarray, B: np.ndarray, TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
        return np.ones(len(A), dtype=bool)


def _zigzag() -> tuple[np.ndarray, RateLimits]:
    t = np.linspace(0.0, 1.0, 9)
    X = np.stack([0.4 * t, 0.3 * np.sin(6 * t), 0.2 * t, -0.1 * np.cos(5 * t), 60.0 * t - 30.0], axis=1)
    J = np.diag([10.0, 10.0, 10.0, 10.0, 1.0])
    # accelerations low enough that a stop at a corner costs time (about a second each)
    return X, RateLimits(J, np.array([5.0, 5.0, 5.0, 5.0, 20.0]), np.array([5.0, 5.0, 5.0, 5.0, 20.0]), tuple("abcde"))


def test_curve_keeps_speed_through_the_corners_when_it_passes_its_check(robot):
    X, lim = _zigzag()
    metric = BodyMetric(robot, 50.0)
    curve = retime_curve(X, lim, metric, _AcceptAll(X), t0=0.5, period=1.0 / RATE)
    chords = retime(X, lim, metric, t0=0.5, period=1.0 / RATE)
    assert curve is not None and curve.stops == (0, len(X) - 1)
    assert curve.stamps[0] == 0.5 and np.allclose(np.diff(curve.stamps), 1.0 / RATE)
    assert np.array_equal(curve.configs[0], X[0]) and np.array_equal(curve.configs[-1], X[-1])
    vf, af = _fd_fractions(curve.configs @ lim.jacobian.T, lim.vmax, lim.amax, 1.0 / RATE)
    assert vf <= 1 + 1e-9 and af <= 1 + 1e-9
    assert _body_fraction(curve.configs, metric, 1.0 / RATE) <= 1 + 1e-9
    assert curve.duration < 0.9 * chords.duration  # no stop at the 7 inner corners
    # it passes through every corner (the spline interpolates them): within one frame's motion of each
    step = np.max(np.abs(np.diff(curve.configs, axis=0)), axis=0)
    for x in X:
        assert np.all(np.min(np.abs(curve.configs - x), axis=0) <= step + 1e-12)


@pytest.mark.parametrize("static", [True, False])
def test_curve_falls_back_to_the_chords_where_it_fails_its_check(robot, static):
    """A check that accepts only frames on the verified polyline: the curve stops at corner after corner
    until every piece is one straight motion, i.e. the chord law, frame for frame (among moving obstacles
    the chords are checked at their new times too, and pass here)."""
    X, lim = _zigzag()
    metric = BodyMetric(robot, 50.0)
    check = _PolylineOnly(X)
    check.static = static
    curve = retime_curve(X, lim, metric, check, t0=0.5, period=1.0 / RATE)
    assert curve is not None and curve.stops == tuple(range(len(X)))
    stamps, Y = retime(X, lim, metric, t0=0.5, period=1.0 / RATE).sample()
    np.testing.assert_array_equal(curve.stamps, stamps)
    np.testing.assert_allclose(curve.configs, Y, rtol=0, atol=1e-9)
    assert 1 < check.calls <= len(X)


def test_curve_gives_up_when_a_chord_fails_at_its_new_times(robot):
    """Among moving obstacles a chord that fails at its new times cannot be split further: no curve timing
    (the caller then tries the slower verified timings)."""
    X, lim = _zigzag()

    class _Nothing(_PolylineOnly):
        static = False

        def edges_valid(self, A, B, TA, TB):
            return np.zeros(len(A), dtype=bool)

    assert retime_curve(X, lim, BodyMetric(robot, 50.0), _Nothing(X), period=1.0 / RATE) is None
