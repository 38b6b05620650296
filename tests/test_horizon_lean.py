"""The replanning step of issue 29: the parameters written in place into one preallocated buffer around the fused
call (`crtraj.control.horizon._buffers`), the verification's arrays written in place (`SceneChecks.verify`), and one
SQP iteration per call (problems/paper_dynamic.toml). On recorded inputs the new step agrees with the previous one
(the same decisions, the same numbers to a stated tolerance), and a simulation-2 loop with it is safe and reaches
the goal. No timing here (that is benchmarks/replan.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool
from test_horizon_fused import TOL, _close  # the fused call's tolerance and comparison

from crtraj.control.horizon._buffers import ParameterBuffer
from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._replanner import Replanner
from crtraj.control.loop import ClosedLoop, LoopOptions, SceneChecks
from crtraj.core.errors import InputError
from crtraj.io.problem import Problem
from crtraj.world import packing


@pytest.fixture(scope="module")
def problem() -> Problem:
    """Simulation 2 as shipped (its compiled horizon needs a C compiler)."""
    require_tool("cc", "gcc", "clang", hint="the compiled horizon needs a C compiler")
    return Problem.load(Path(__file__).resolve().parent.parent / "problems" / "paper_dynamic.toml")


def _loop(problem: Problem, duration: float = 12.0, **replan) -> ClosedLoop:
    """Simulation 2 with the shipped [replan] options changed by `replan`, references planned inline."""
    opts = dataclasses.replace(problem.options(ReplanOptions, "replan"), **replan)
    lopts = dataclasses.replace(problem.options(LoopOptions, "loop"), reference_delay=0.0, duration=duration)
    return ClosedLoop.from_problem(problem, seed=0, options=opts, loop_options=lopts)


def test_the_parameter_buffer_is_the_concatenation_bit_for_bit(model):
    """For random states, references, obstacles and histories, with and without given tips, the buffer holds the
    vector `Replanner` builds by concatenation (its reference tips from `Model.tip_position`), bit for bit."""
    rng = np.random.default_rng(5)
    opts = ReplanOptions(horizon=6, points=10, solver="sqp")
    rp = Replanner(model, opts, max_obstacles=3, safety_distance=5.0)
    buf = ParameterBuffer(model, rp.N, rp.max_obstacles)
    for k in range(40):
        x0 = rng.normal(0.0, [0.4, 0.4, 0.4, 0.4, 30.0])
        X = x0 + rng.normal(0.0, 0.1, (rp.N, rp.nx))
        O = rng.normal(0.0, 100.0, (rp.N, packing.WIDTH * rp.max_obstacles))
        xm1 = None if k % 3 == 0 else x0 + rng.normal(0.0, 0.01, rp.nx)
        tips = None if k % 2 else rng.normal(0.0, 100.0, (rp.N, 3))
        got = buf.fill(x0, X, O, xm1, tips)
        want = rp._parameters(x0, X, O, xm1, tips)
        assert got.shape == want.shape and np.array_equal(got, want)


@pytest.mark.parametrize("part", ["x0", "reference", "x_prev", "tip_reference", "obstacles"])
def test_a_nan_in_the_buffer_names_its_part(model, part):
    """A NaN in any input is an `InputError` naming that input; obstacles of the wrong size name the expected shape."""
    N, M = 4, 2
    buf = ParameterBuffer(model, N, M)
    args = {
        "x0": np.zeros(model.nx),
        "reference": np.zeros((N, model.nx)),
        "obstacles": np.zeros((N, packing.WIDTH * M)),
        "x_prev": np.zeros(model.nx),
        "tip_reference": np.zeros((N, 3)),
    }
    args[part] = np.full_like(args[part], np.nan)
    with pytest.raises(InputError, match=rf"^{part}: contains NaN"):
        buf.fill(args["x0"], args["reference"], args["obstacles"], args["x_prev"], args["tip_reference"])
    with pytest.raises(InputError, match=r"^obstacles: expected shape \(4, 10\)"):
        buf.fill(np.zeros(model.nx), np.zeros((N, model.nx)), np.zeros(7), None, None)


def test_the_new_step_agrees_with_the_previous_one_on_recorded_inputs(problem, monkeypatch):
    """Every horizon query a simulation-2 run asks (warm starts in sequence, no deadline), replayed on the new
    path (fused call, parameters written in place) and on the previous one (solver and KKT calls, numpy row check,
    parameters concatenated): the same status and solver status, configurations, tips, cost, smallest obstacle row
    and violation to 1e-9 relative. And every verification the run made gives the previous formula's bound (its
    arrays built by concatenation) bit for bit."""
    new, old = _loop(problem, 6.0, step_deadline=0.0), _loop(problem, 6.0, fused=False, step_deadline=0.0)
    assert new.replanner._buffer is not None and old.replanner._buffer is None
    solves, checks = [], []
    solve, verify = Replanner.solve, SceneChecks.verify

    def record_solve(self, x0, reference, obstacles, **kw):
        solves.append((np.array(x0), np.array(reference), np.array(obstacles), kw))
        return solve(self, x0, reference, obstacles, **kw)

    def record_verify(self, T, X, after):
        checks.append((self.validator, np.array(T), np.array(X), after))
        return verify(self, T, X, after)

    monkeypatch.setattr(Replanner, "solve", record_solve)
    monkeypatch.setattr(SceneChecks, "verify", record_verify)
    run = new.run()
    monkeypatch.setattr(Replanner, "solve", solve)
    monkeypatch.setattr(SceneChecks, "verify", verify)
    assert run.steps > 50 and len(solves) > 50 and len(checks) > 50
    new.replanner.reset()
    old.replanner.reset()
    for x0, X, O, kw in solves:
        a = new.replanner.solve(x0, X, O, **kw)
        b = old.replanner.solve(x0, X, O, **kw)
        assert a.status is b.status and a.solver_status == b.solver_status and a.warm == b.warm
        assert _close(a.configs, b.configs) and _close(a.tips, b.tips) and _close(a.cost, b.cost)
        assert _close(a.min_distance, b.min_distance) and abs(a.violation - b.violation) <= TOL
    for v, T, X, after in checks:
        assert verify(new.parts.checks, T, X, after) == _previous_bound(v, T, X, after)


def _previous_bound(v, T: np.ndarray, X: np.ndarray, after) -> float:
    """`SceneChecks.verify` as the previous stop wrote it (arrays by concatenation), with validator v."""
    if len(X) == 1:
        half, t_lo, t_hi = np.zeros(1), T[:1], T[:1]
    else:
        B = v.motion_bound(np.diff(X, axis=0))
        half = 0.5 * np.concatenate([[B[0]], np.maximum(B[:-1], B[1:]), [B[-1]]])
        t_lo, t_hi = np.concatenate([[T[0]], T[:-1]]), np.concatenate([T[1:], [T[-1]]])
    if after is not None:
        X = np.concatenate([X, X[-1:]])
        half, t_lo, t_hi = np.append(half, 0.0), np.append(t_lo, after[0]), np.append(t_hi, after[1])
    return float(np.min(v.clearance(X, t_lo, t_hi, half)))


def test_a_sim2_loop_with_one_iteration_per_call_is_safe_and_reaches_the_goal(problem):
    """The shipped one SQP iteration per call under a deadline that never runs out (so every feasible iterate is
    applied after its one iteration, as a suboptimal move when not converged): simulation 2 reaches the goal within
    the tolerance with no collision and no D_sf breach at any verification sample, and no deadline miss."""
    o = problem.options(ReplanOptions, "replan")
    assert o.max_iter == 1 and o.fused and o.compiled
    loop = _loop(problem, duration=60.0, step_deadline=1000.0)
    run = loop.run()
    s = run.summary()
    assert s["reached_goal"] and s["final_tip_error_mm"] <= problem.require_task().goal_tolerance
    assert s["collisions"] == 0 and s["safety_violations"] == 0 and s["min_clearance_mm"] > 0.0
    assert s["deadline_misses"] == 0
    assert set(s["status_counts"]) <= {"move", "suboptimal"}


def test_the_loop_keeps_its_setup_out_of_the_garbage_collector_during_its_steps(problem):
    """During the steps every object the setup made is frozen (`gc.freeze`: the collector's full collections no
    longer traverse them), and after the run the heap is unfrozen again (nothing stays uncollectable)."""
    import gc

    assert gc.get_freeze_count() == 0
    loop = _loop(problem, duration=1.0, step_deadline=0.0)
    counts: list[int] = []
    run = loop.run(progress=lambda k, t, status: counts.append(gc.get_freeze_count()))
    assert run.steps == len(counts) >= 5
    assert min(counts) > 1000  # the setup's objects: CasADi functions, arrays, the planner's data
    assert gc.get_freeze_count() == 0
