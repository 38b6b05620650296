"""The compiled edge check's early exit across a batch (`MotionValidator.first_valid`, `[planner.check]
early_exit`) against the numpy refinement loop: on random static and moving scenes the motions it checks
get the numpy loop's verdicts bit for bit, it stops at the first motion certified whole (the rest are marked
unchecked), `first_valid` names the numpy loop's first valid motion, and plans are identical with it on
and off, each verified by an independent dense check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import require_tool
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_broad_phase import motions, random_scene
from test_planner_helpers import PAPER_STATIC, dense_path_check, paper_static

from crtraj.core.build_cache import BuildCache
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import BUILTIN
from crtraj.planning.postprocess import _at
from crtraj.planning.sampler import LIMIT_TOL, ConfigSampler
from crtraj.planning.validity._kernels import Kernels
from crtraj.planning.validity._motion import MotionValidator
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene


@pytest.fixture(scope="module")
def kernels(tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    return Kernels(BuildCache(tmp_path_factory.mktemp("kernels")))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 30), moving=st.booleans())
def test_early_exit_agrees_with_the_numpy_loop(model: Model, kernels: Kernels, seed, n, moving):
    """Up to the first motion certified whole the early-exit check returns the numpy loop's (f, lower) bit for
    bit (with the broad phase: f); every motion after it is marked unchecked (f = -1); first_valid is the
    numpy loop's first valid."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n, moving)
    # exact lower bounds need every obstacle in every sample (the broad phase keeps the verdicts only)
    v = MotionValidator(model, scene, kernels=kernels, broad_phase=False)
    broad = MotionValidator(model, scene, kernels=kernels)
    loop = MotionValidator(model, scene, kernels=kernels)
    loop.compiled_loop = False
    XA, XB, TA, TB = motions(v, rng, 40)
    order = rng.permutation(40)
    XA, XB, TA, TB = XA[order], XB[order], TA[order], TB[order]
    fe, le = v.check_edges(XA, XB, TA, TB, prefix=False, first=True)
    fl, ll = loop.check_edges(XA, XB, TA, TB, prefix=False)
    ok = np.flatnonzero(fl >= 1.0)
    k = int(ok[0]) if len(ok) else len(XA) - 1
    np.testing.assert_array_equal(fe[: k + 1], fl[: k + 1])
    np.testing.assert_array_equal(le[: k + 1], ll[: k + 1])
    assert np.all(fe[k + 1 :] == -1.0)
    fb, _ = broad.check_edges(XA, XB, TA, TB, prefix=False, first=True)
    np.testing.assert_array_equal(fb, fe)
    assert v.first_valid(XA, XB, TA, TB) == broad.first_valid(XA, XB, TA, TB) == (int(ok[0]) if len(ok) else -1)
    off = MotionValidator(model, scene, kernels=kernels, early_exit=False)
    assert off.first_valid(XA, XB, TA, TB) == v.first_valid(XA, XB, TA, TB)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 12), moving=st.booleans())
def test_bounds_of_a_larger_batch_give_the_same_checks(model: Model, kernels: Kernels, seed, n, moving):
    """The search's via round computes the body-motion bounds of all its candidates once and passes a chunk's
    rows to `check_edges` (as `edges_valid` calls it) and `first_valid`: the rows equal the chunk's own bounds
    bit for bit, so the verdicts, the first valid motion, the samples checked and the durations are those of
    the check computing them."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng, n, moving)
    v = MotionValidator(model, scene, kernels=kernels)
    XA, XB, TA, TB = motions(v, rng, 32)
    bound = v.motion_bound(XB - XA)
    np.testing.assert_array_equal(v.duration(XB - XA, bound), v.duration(XB - XA))
    for idx in (np.arange(8), rng.permutation(32)[: rng.integers(2, 12)], np.arange(32)):
        np.testing.assert_array_equal(bound[idx], v.motion_bound(XB[idx] - XA[idx]))
        s0 = v.n_samples
        f, _ = v.check_edges(XA[idx], XB[idx], TA[idx], TB[idx], prefix=False, bound=bound[idx], verdict=True)
        got = f >= 1.0
        s1 = v.n_samples
        np.testing.assert_array_equal(got, v.edges_valid(XA[idx], XB[idx], TA[idx], TB[idx]))
        assert v.n_samples - s1 == s1 - s0
        first = v.first_valid(XA[idx], XB[idx], TA[idx], TB[idx], bound[idx])
        assert first == v.first_valid(XA[idx], XB[idx], TA[idx], TB[idx])
        assert first == (int(np.flatnonzero(got)[0]) if got.any() else -1)


def test_early_exit_checks_fewer_samples(model: Model, kernels: Kernels):
    """A batch whose first motion is valid: with the early exit only that motion is sampled."""
    rng = np.random.default_rng(4)
    scene = random_scene(rng, 6, moving=False)
    v = MotionValidator(model, scene, kernels=kernels)
    XA, XB, _, _ = motions(v, rng, 60)
    f, _ = v.check_edges(XA, XB, prefix=False)
    first = int(np.flatnonzero(f >= 1.0)[0])
    s0 = v.n_samples
    v.check_edges(XA[first:], XB[first:], prefix=False)
    whole = v.n_samples - s0
    s0 = v.n_samples
    assert v.first_valid(XA[first:], XB[first:]) == 0
    single = v.n_samples - s0
    s0 = v.n_samples
    v.check_edges(XA[first : first + 1], XB[first : first + 1], prefix=False)
    assert single == v.n_samples - s0 < whole


@pytest.mark.parametrize("problem_file", ["paper_static", "paper_dynamic"])
def test_plans_identical_with_and_without_early_exit(kernels: Kernels, problem_file):
    """Seeds 0-2 of the paper's simulations: the same plans bit for bit with the early exit on and off (the
    IK on the same compiled projection), each one clear under a dense check of 200 backbone points."""
    problem = Problem.load(PAPER_STATIC.with_name(f"{problem_file}.toml"))
    model = paper_static()[1]
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner").with_(algorithm="cspace", time_limit=600.0)
    task = problem.task
    plans = []
    for early in (True, False):
        context = PlanningContext(model, scene, options.with_(check={"early_exit": early}), kernels=kernels)
        planner = BUILTIN.create("cspace", context)
        kw = {"start_tip": task.start, "goal_tolerance": task.goal_tolerance}
        plans.append([planner.plan(task.goal, seed=s, **kw) for s in range(3)])
    for a, b in zip(*plans, strict=True):
        assert a.is_success() and b.status == a.status
        np.testing.assert_array_equal(a.configs, b.configs)
        np.testing.assert_array_equal(a.t, b.t)
        clear, viol, _ = dense_path_check(model, scene, a.t, a.configs)
        assert clear >= 0.0 and viol <= 1e-9


def test_points_along_a_polyline_match_np_interp():
    """The shortcut's points at arc positions (`postprocess._at`, all coordinates at once) equal np.interp per
    coordinate bit for bit, at random positions, at the waypoints and beyond both ends."""
    rng = np.random.default_rng(0)
    for _ in range(500):
        n = int(rng.integers(2, 9))
        X = rng.normal(size=(n, 5))
        s = np.concatenate([[0.0], np.cumsum(rng.uniform(0.0, 3.0, n - 1))])
        u = np.concatenate([rng.uniform(-1.0, s[-1] + 1.0, 20), s])
        ref = np.stack([np.interp(u, s, X[:, j]) for j in range(5)], axis=-1)
        np.testing.assert_array_equal(_at(X, s, u), ref)


def test_swept_spheres_without_breathing_match_the_scene(model: Model, kernels: Kernels):
    """Obstacles that move (linear, sin, cos profiles) without breathing (amplitude 0) or stand still: the
    spheres the C check sweeps over random windows (it skips the sine ranges a profile does not use) give
    the clearances of `Scene.swept_spheres`' spheres bit for bit, with and without a time origin."""
    rng = np.random.default_rng(7)
    obs = [
        Obstacle(
            name=f"o{i}",
            center=tuple(rng.uniform([-150, -150, 100], [150, 150, 400])),
            radius=float(rng.uniform(15, 40)),
            amplitude=0.0,
            to=tuple(rng.uniform([-150, -150, 100], [150, 150, 400])) if i < 6 else None,
            duration=float(rng.uniform(0.5, 3.0)),
            profile=("linear", "sin", "cos")[i % 3],
        )
        for i in range(8)
    ]
    scene = Scene(obstacles=tuple(obs), safety_distance=5.0)
    v = MotionValidator(model, scene, kernels=kernels)
    k = v.state.kernel
    X = v.sample(rng, 400)
    lo = rng.uniform(0.0, 4.0, len(X))
    hi = lo + rng.uniform(0.0, 1.0, len(X))
    for sc in (scene, replace(scene, time_origin=0.7)):
        slots = packing.pack(*sc.swept_spheres(lo, hi), sc.n_obstacles)
        np.testing.assert_array_equal(
            k.clearance_windows(X, sc.motion_table(), sc.time_origin, lo, hi), k.clearance(X, slots)
        )


def test_sampler_limit_test_is_the_robots(model: Model):
    """`ConfigSampler.within_limits` (matrices kept from construction) gives `Robot.limit_violation <= LIMIT_TOL`
    on random configurations in and beyond the limits, for the two-segment robot and a coupled three-segment one."""
    from crtraj.model.robot import Segment

    rng = np.random.default_rng(11)
    three = replace(
        model.robot,
        name="three",
        segments=tuple(Segment(130.0, 1.2, k * np.pi / 3) for k in range(3)),
        coupling=-0.5,
        actuators=None,
    )
    for robot in (model.robot, three):
        s = ConfigSampler(robot)
        X = s.sample(rng, 3000) * rng.uniform(0.8, 1.2, (3000, 1))
        X[:, -1] = rng.uniform(robot.z_range[0] - 5.0, robot.z_range[1] + 5.0, 3000)
        ok = s.within_limits(X)
        np.testing.assert_array_equal(ok, robot.limit_violation(X) <= LIMIT_TOL)
        assert 0 < ok.sum() < len(ok)
