"""The safe IK's compiled batched projection (`ValidityKernel.project`, `[planner.ik] compiled`) against the
numpy loop and independent computations: one step equals the damped least-squares step built from a
finite-difference Jacobian, whole projections agree with the numpy loop run per configuration, converged
configurations reach the target (independent FK) within the limits, and the safe IK built on it returns
configurations that pass a dense clearance check, without more IPOPT solves than the numpy path."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import require_tool
from test_planner_helpers import dense_path_check, paper_static

from crtraj.core.build_cache import BuildCache
from crtraj.planning.ik._safe_ik import SafeIK
from crtraj.planning.sampler import ConfigSampler
from crtraj.planning.validity import Kernels, MotionValidator


@pytest.fixture(scope="module")
def sim1(tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    problem, model, scene = paper_static()
    v = MotionValidator(model, scene, kernels=Kernels(BuildCache(tmp_path_factory.mktemp("kernels"))))
    assert v.state.kernel is not None
    return problem, model, scene, v


def iks(model, v, **kw):
    """(compiled, numpy) safe IKs on the same validator."""
    return SafeIK(model, v, 2, compiled=True, **kw), SafeIK(model, v, 2, compiled=False, **kw)


def fd_jacobian(model, x, h=1e-6):
    """Independent: central differences of the tip position (3, nx)."""
    cols = [(model.tip_position(x + h * e) - model.tip_position(x - h * e)) / (2 * h) for e in np.eye(len(x))]
    return np.stack(cols, axis=1)


def test_one_compiled_step_is_the_damped_least_squares_step(sim1):
    """One step from random seeds: x + W^-1 J^T (J W^-1 J^T + 1e-3 I)^-1 e (e capped at 150 mm, J by finite
    differences), then into the bending discs and z stroke (numpy `ConfigSampler.project_limits`), to 1e-6."""
    problem, model, _, v = sim1
    comp, _ = iks(model, v)
    goal = problem.task.goal
    X0 = v.sample(np.random.default_rng(1), 24)
    X1, _ = comp.project(goal, X0, 1)
    M = v.metric_matrix
    W_inv = np.linalg.inv(M.T @ M)
    sampler = ConfigSampler(model.robot)
    for x0, x1 in zip(X0, X1, strict=True):
        e = goal - model.tip_position(x0)
        e = e * min(1.0, 150.0 / np.linalg.norm(e))
        J = fd_jacobian(model, x0)
        dx = W_inv @ J.T @ np.linalg.solve(J @ W_inv @ J.T + 1e-3 * np.eye(3), e)
        ref = sampler.project_limits((x0 + dx)[None])[0]
        np.testing.assert_allclose(x1, ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("target", ["goal", "start"])
def test_compiled_projection_agrees_with_the_numpy_loop(sim1, target):
    """64 seeds: the compiled batch equals the numpy loop run on each seed alone (it stops once that seed is on
    target, as the compiled loop does per configuration) to 1e-6 mm / rad (LU against Cholesky: rounding
    that 40 steps along a limit grow to ~1e-8); converged configurations have
    their tip on the target by independent FK and respect the limits."""
    problem, model, _, v = sim1
    goal = getattr(problem.task, target)
    comp, ref = iks(model, v)
    X0 = v.sample(np.random.default_rng(2), 64)
    X, err = comp.project(goal, X0, 40)
    assert (err <= 1e-3).sum() >= 16  # many seeds converge: the comparison is not vacuous
    for i, x0 in enumerate(X0):
        xr, er = ref.project(goal, x0[None], 40)
        np.testing.assert_allclose(X[i], xr[0], atol=1e-6, rtol=0)
        assert err[i] == pytest.approx(er[0], abs=1e-6)
    on = err <= 1e-3
    tip = np.array([model.tip_position(x) for x in X[on]])
    assert np.linalg.norm(tip - goal, axis=1).max() <= 1e-3
    assert model.robot.limit_violation(X).max() <= 1e-9


def test_compiled_safe_ik_solutions_verify_densely(sim1):
    """The safe IK of sim 1's goal and start (projection, push-out, rescue; NLP allowed) on the compiled
    projection: as many safe configurations as the numpy path, no more IPOPT solves, and each one has its
    tip on the target (independent FK), is within limits and passes a dense check of 200 backbone points."""
    problem, model, scene, v = sim1
    comp, ref = iks(model, v, rescue_starts=32)
    for target in (problem.task.goal, problem.task.start):
        seeds = v.sample(np.random.default_rng(5), 64)
        kw = {"want": 4, "max_nlp": 8}
        a = comp.solve(target, scene.pack(0.0, 2), seeds, **kw)
        b = ref.solve(target, scene.pack(0.0, 2), seeds, **kw)
        assert len(a.safe) == len(b.safe) >= 1
        for x in a.safe:
            assert np.linalg.norm(model.tip_position(x) - target) <= 1e-3
            assert v.within_limits(x[None])[0]
            clear, viol, _ = dense_path_check(model, scene, np.array([0.0]), x[None])
            assert clear >= 0.0 and viol <= 1e-9
    assert comp.nlp_solves <= ref.nlp_solves
