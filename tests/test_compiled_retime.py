"""The retiming's phase-plane pass and knot times in C (`ValidityKernel.phase_law`) against the numpy/Python pass,
on random curves (hypothesis) and recorded sim-1 plans; toppra (the reference TOPP-RA library) as an independent
check of the law's duration; the limit check that catches a law computed for weaker limits; and the curve in C
(`ValidityKernel.natural_slopes`, `hermite`) against numpy's `crtraj.core.splines`, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PROBLEMS, require_module, require_tool
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.core.splines import HermiteCubic, natural_cubic
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.context import PlanningContext
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.pipeline import retime_result
from crtraj.planning.planners import BUILTIN
from crtraj.planning.retime import (
    COLLINEAR,
    _middles_on_chords,
    _on_chord,
    _over_limits,
    _piece_law,
    _sample_law,
    _toppra_law,
    keep_corners,
    retime_curve,
)
from crtraj.planning.validity import ValidityKernel
from crtraj.world.scene import Scene

PERIOD = 0.01


@pytest.fixture(scope="module")
def kernel(model, tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    k = ValidityKernel.load(model, 10, BuildCache(tmp_path_factory.mktemp("kernels")))
    assert k is not None
    return k


class _AcceptAll:
    """A stand-in validator of a static scene that certifies every motion (the law alone is compared)."""

    static = True

    def within_limits(self, Y: np.ndarray) -> np.ndarray:
        return np.ones(len(np.atleast_2d(Y)), dtype=bool)

    def edges_valid(self, A: np.ndarray, B: np.ndarray, TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
        return np.ones(len(A), dtype=bool)


@st.composite
def _curves(draw):
    """A random path of 3-12 corners in the robot's 5 coordinates (2 bending vectors, z), and random rate limits."""
    k = draw(st.integers(3, 12))
    m = draw(st.integers(1, 7))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    scale = np.array([0.3, 0.3, 0.3, 0.3, 20.0]) * draw(st.sampled_from([0.05, 0.5, 1.0]))
    X = np.cumsum(rng.normal(size=(k, 5)) * scale, axis=0)
    J = rng.normal(size=(m, 5))
    vmax = 10 ** rng.uniform(-1, 2, size=m)
    amax = 10 ** rng.uniform(-1, 3, size=m)
    return X, RateLimits(J, vmax, amax, tuple(f"a{i}" for i in range(m))), float(10 ** rng.uniform(1, 3))


@settings(max_examples=80, deadline=None)
@given(_curves())
def test_compiled_law_equals_the_python_law(robot, kernel, case):
    """ds/dt and the knot times from C equal numpy's and the Python loops' within 1e-9 (they are the same
    operations, so in fact bit for bit), and so do the frames of the whole curve timing."""
    X, lim, speed = case
    metric = BodyMetric(robot, speed)
    try:
        _, grid, sd_py, T_py = _piece_law(X, lim, metric, None)
    except InputError:  # no law along this curve: C must say so as well
        with pytest.raises(InputError):
            _piece_law(X, lim, metric, kernel)
        return
    _, grid_c, sd_c, T_c = _piece_law(X, lim, metric, kernel)
    np.testing.assert_array_equal(grid_c, grid)
    np.testing.assert_allclose(T_c, T_py, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sd_c, sd_py, rtol=1e-12, atol=0)
    # the knot times are the law's own: T_{k+1} - T_k = 2 ds / (sd_k + sd_{k+1}), summed independently here
    dt = 2.0 * np.diff(grid) / (sd_py[:-1] + sd_py[1:])
    assert abs(T_c[-1] - float(np.sum(dt))) <= 1e-9 * max(1.0, T_c[-1])
    a = retime_curve(X, lim, metric, _AcceptAll(), period=PERIOD, kernel=kernel)
    b = retime_curve(X, lim, metric, _AcceptAll(), period=PERIOD)
    assert (a is None) == (b is None)
    if a is not None:
        assert a.stops == b.stops
        np.testing.assert_array_equal(a.stamps, b.stamps)
        np.testing.assert_allclose(a.configs, b.configs, rtol=0, atol=1e-9)


def test_law_computed_for_weaker_limits_is_caught(robot, kernel):
    """The C law for doubled accelerations and speeds, sampled, breaks the true limits and the frames' check
    (`_over_limits`, finite differences of what the streamer sends) says so; the true law keeps them."""
    t = np.linspace(0.0, 1.0, 9)
    X = np.stack([0.4 * t, 0.3 * np.sin(6 * t), 0.2 * t, -0.1 * np.cos(5 * t), 60.0 * t], axis=1)
    J = np.diag([10.0, 10.0, 10.0, 10.0, 1.0])
    lim = RateLimits(J, np.full(5, 5.0), np.full(5, 5.0), tuple("abcde"))
    weak = RateLimits(J, 2.0 * lim.vmax, 4.0 * lim.amax, lim.names)
    metric = BodyMetric(robot, 1e3)
    spline, gp, sd, T = _piece_law(X, weak, metric, kernel)
    over = _over_limits(_sample_law(spline, gp, sd, T, PERIOD, 1.0), lim, metric, PERIOD)
    assert over > 1.5  # about 2 (speed 2x, acceleration 4x: its square root 2x)
    spline, gp, sd, T = _piece_law(X, lim, metric, kernel)
    assert _over_limits(_sample_law(spline, gp, sd, T, PERIOD, 1.0), lim, metric, PERIOD) <= 1.0 + 1e-6


def test_compiled_law_duration_agrees_with_toppra(robot, kernel):
    """toppra (TOPP-RA, independent code) times the same spline within the same caps: the closed-form pass is
    conservative where q'' helps (module docstring of `crtraj.planning.retime`), so its duration is at least
    toppra's and within 15 % of it."""
    require_module("toppra", "pip install -e .[bench]")
    t = np.linspace(0.0, 1.0, 9)
    X = np.stack([0.4 * t, 0.3 * np.sin(6 * t), 0.2 * t, -0.1 * np.cos(5 * t), 60.0 * t], axis=1)
    lim = RateLimits(np.diag([10.0, 10.0, 10.0, 10.0, 1.0]), np.full(5, 5.0), np.full(5, 5.0), tuple("abcde"))
    metric = BodyMetric(robot, 50.0)
    T_c = _piece_law(X, lim, metric, kernel)[3][-1]
    T_ref = _toppra_law(X, lim, metric)[3][-1]
    assert T_ref * (1.0 - 1e-3) <= T_c <= 1.15 * T_ref


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_sim1_executable_motion_is_the_same_with_the_compiled_law(seed):
    """A recorded sim-1 plan retimed through the compiled law and through the Python law: the same frames, stamps,
    tips, clearance and report (the validator's kernel computes the tips, bit for bit the model's)."""
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    model = Model(problem.robot)
    options = problem.options(PlannerOptions, "planner").with_(algorithm="cspace")
    context = PlanningContext.build(model, problem.options(Scene, "scene"), options)
    v = context.validator
    if v.kernel is None:
        pytest.skip("no C compiler")
    task = problem.task
    res = BUILTIN.create("cspace", context).plan(task.goal, start_tip=task.start, seed=seed)
    assert res.is_success()
    out, info = retime_result(res, v, context, problem.robot.actuator_limits(), 1.0 / PERIOD)
    usable = context.rate_limits.scaled(options.limit_fraction)
    metric = BodyMetric(v.robot, options.max_speed)
    py = retime_curve(res.configs, usable, metric, v, t0=float(res.t[0]), period=PERIOD)
    assert py is not None and "smoothed curve" in info["outcome"]
    np.testing.assert_array_equal(out.t, py.stamps)
    np.testing.assert_array_equal(out.configs, py.configs)
    np.testing.assert_array_equal(out.tips, model.tip_position(py.configs))
    assert out.min_clearance == v.path_clearance(py.configs, py.stamps)[0]
    assert info["max_velocity_fraction"] <= options.limit_fraction + 1e-9


def _on_chord_plain(a: np.ndarray, b: np.ndarray, inner: np.ndarray, tol: float) -> bool:
    """The chord test as written before (differences of the parameters, np.linalg.norm)."""
    d = b - a
    dd = float(d @ d)
    if dd == 0.0:
        return False
    u = (inner - a) @ d / dd
    if np.any(np.diff(np.concatenate([[0.0], u, [1.0]])) < 0.0):
        return False
    return bool(np.max(np.linalg.norm(a + u[:, None] * d - inner, axis=1)) <= tol)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 8), st.floats(1e-12, 1e-8))
def test_chord_test_decides_as_before(seed, k, tol):
    """`_on_chord` decides as the plain formulas on points near, on, before and beyond random chords."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=5), rng.normal(size=5)
    u = np.sort(rng.uniform(-0.1, 1.1, size=k)) if rng.random() < 0.7 else rng.uniform(-0.1, 1.1, size=k)
    inner = a + u[:, None] * (b - a) + rng.choice([0.0, 1e-11, 1e-9]) * rng.normal(size=(k, 5))
    assert _on_chord(a, b, inner, tol) == _on_chord_plain(a, b, inner, tol)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 40), st.integers(1, 6))
def test_compiled_natural_cubic_equals_numpy(kernel, seed, n, d):
    rng = np.random.default_rng(seed)
    t = np.cumsum(10 ** rng.uniform(-3, 2, size=n))
    Y = rng.normal(size=(n, d)) * 10 ** rng.uniform(-2, 2, size=d)
    ref = natural_cubic(t, Y)
    S = kernel.natural_slopes(t, Y)
    np.testing.assert_array_equal(S, ref.slopes)
    # the spline's defining conditions, checked independently: C2 at the inner knots, zero curvature at the ends
    curve = HermiteCubic(t, Y, S)
    left, right = curve(t[1:-1] - 1e-9 * (t[1:-1] - t[:-2]), 2), curve(t[1:-1], 2)
    scale = np.max(np.abs(curve(t, 2)), axis=0) + np.max(np.abs(Y), axis=0)
    assert np.all(np.abs(left - right) <= 1e-5 * scale)
    x = np.concatenate([rng.uniform(t[0] - 1.0, t[-1] + 1.0, size=200), t, [np.nan, -np.inf, np.inf]])
    for nu in (0, 1, 2):
        with np.errstate(invalid="ignore"):  # inf - inf at the infinite parameters: NaN on both sides
            np.testing.assert_array_equal(kernel.hermite(t, Y, S, x, nu), ref(x, nu))


def test_compiled_cubic_rejects_a_bad_order(kernel):
    t, Y = np.arange(4.0), np.ones((4, 2))
    with pytest.raises(RuntimeError):
        kernel.hermite(t, Y, Y, t, 3)
    with pytest.raises(ValueError):
        kernel.natural_slopes(t[:2], Y[:2])


def _keep_corners_walk(X: np.ndarray, tol: float = COLLINEAR) -> np.ndarray:
    """`keep_corners` as it was written before: a walk over every waypoint."""
    X = np.asarray(X, dtype=float)
    first = _middles_on_chords(X, tol) if len(X) >= 3 else np.zeros(0, dtype=bool)
    keep = [0]
    i, K = 0, len(X)
    while i < K - 1:
        j = i + 1
        while j + 1 < K and first[i] and _on_chord(X[i], X[j + 1], X[i + 1 : j + 1], tol):
            j += 1
        if np.max(np.abs(X[j] - X[keep[-1]])) > 0.0:
            keep.append(j)
        i = j
    if keep[-1] != K - 1:
        keep[-1] = K - 1
    return np.asarray(keep)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 40))
def test_corners_found_as_by_the_walk(seed, k):
    """`keep_corners` (only the possible merges visited) keeps the corners the walk over every waypoint keeps, on
    paths of straight runs (finely and coarsely resampled), repeated waypoints, backtracks and random corners."""
    rng = np.random.default_rng(seed)
    pts = [rng.normal(size=5)]
    for _ in range(k):
        r = rng.random()
        if r < 0.4:  # a straight run through 1-4 inner points
            b = pts[-1] + rng.normal(size=5)
            pts += list(pts[-1] + np.linspace(0.0, 1.0, rng.integers(2, 6))[1:, None] * (b - pts[-1]))
        elif r < 0.55:
            pts.append(pts[-1].copy())  # a zero-length motion
        elif r < 0.65 and len(pts) > 1:
            pts.append(pts[-2].copy())  # straight back
        else:
            pts.append(pts[-1] + rng.normal(size=5) * rng.choice([1e-12, 1e-3, 1.0]))
    X = np.array(pts)
    np.testing.assert_array_equal(keep_corners(X), _keep_corners_walk(X))
    if k:
        X[rng.integers(0, len(X))] = np.nan  # NaN equals nothing
        np.testing.assert_array_equal(keep_corners(X), _keep_corners_walk(X))
