"""The stage-form horizon QP for HPIPM (``qpsol = "hpipm"``, issue 29) against the dense daqp QP: the same rows
and cost through its index maps, the same solutions on recorded simulation-2 queries, and a safe closed loop. No
timing here (that is benchmarks/replan.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import require_tool

from crtraj.control.horizon._backends import CompiledBackend, HorizonQuery, InterpretedBackend
from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._stage import StageSolver
from crtraj.control.loop import ClosedLoop, LoopOptions
from crtraj.io.problem import Problem

ROOT = Path(__file__).resolve().parent.parent
# stated tolerances: two QP solvers (active set vs interior point) converge to the same KKT point of the same NLP
# (sqpmethod's tolerances: primal 1e-7, dual 1e-4 on a cost of order 1); seen: 1e-7 in x, 1e-9 in cost
X_TOL = 1e-5  # mm, rad
COST_TOL = 1e-6  # relative


@pytest.fixture(scope="module")
def problem() -> Problem:
    return Problem.load(ROOT / "problems" / "paper_dynamic.toml")


def _loop(problem: Problem, qpsol: str, compiled: bool = False, duration: float = 6.0) -> ClosedLoop:
    """Simulation 2, deterministic: no step deadline, references planned inline; three SQP iterations a call (the
    problem ships one since issue 29: most calls would then stop short of convergence)."""
    opts = dataclasses.replace(
        problem.options(ReplanOptions, "replan"),
        qpsol=qpsol,
        compiled=compiled,
        step_deadline=0.0,
        max_iter=3,
        max_calls=20,
    )
    lopts = dataclasses.replace(problem.options(LoopOptions, "loop"), reference_delay=0.0, duration=duration)
    return ClosedLoop.from_problem(problem, seed=0, options=opts, loop_options=lopts)


def _inner(loop: ClosedLoop):
    b = loop.replanner.backend
    return getattr(b, "inner", b)


@pytest.fixture(scope="module")
def cc() -> str:
    """The C compiler, asked for before the module's recorded run: without one the compiled test fails (skips
    locally) at once, not after 6 s of simulation."""
    return require_tool("cc", "gcc", "clang", hint="the compiled horizon needs a C compiler")


@pytest.fixture(scope="module")
def recorded(problem) -> list[HorizonQuery]:
    """The queries the dense daqp solver answers over 6 s of simulation 2 (the screened QP's parameters)."""
    loop = _loop(problem, "daqp")
    seen: list[HorizonQuery] = []
    solve = InterpretedBackend.solve

    def record(self: InterpretedBackend, query: HorizonQuery):
        seen.append(query)
        return solve(self, query)

    InterpretedBackend.solve = record  # type: ignore[method-assign]
    try:
        loop.run()
    finally:
        InterpretedBackend.solve = solve  # type: ignore[method-assign]
    return seen


def test_the_stage_rows_and_cost_are_the_dense_ones(problem, recorded):
    """At random points, the stage NLP's rows (through `g_of`) and cost equal the dense NLP's, evaluated
    independently, and its gap rows vanish: the index maps lose and repeat nothing."""
    dense = _loop(problem, "daqp").replanner
    stage = _loop(problem, "hpipm").replanner.solver
    assert isinstance(stage, StageSolver)
    nlp = dense._nlp.nlp
    f_dense = ca.Function("d", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]])
    snlp = stage.nlp
    f_stage = ca.Function("s", [snlp["x"], snlp["p"]], [snlp["f"], snlp["g"]])
    rng = np.random.default_rng(0)
    for q in recorded[:: max(1, len(recorded) // 5)]:
        p = np.concatenate([q.p, rng.uniform(0.0, 1.0, dense._nlp.nlp["p"].numel() - len(q.p))])
        x = q.x0 + rng.normal(0.0, 0.01, q.x0.shape)
        fd, gd = (np.asarray(a).ravel() for a in f_dense(x, p))
        v = np.concatenate([p[stage.nx : 2 * stage.nx], p[: stage.nx], x])
        fs, gs = (np.asarray(a).ravel() for a in f_stage(v[stage.w_of], p))
        assert abs(fs[0] - fd[0]) <= 1e-9 * (1.0 + abs(fd[0]))
        assert np.allclose(gs[stage.g_of], gd, rtol=1e-10, atol=1e-10)
        gap = np.setdiff1d(np.arange(stage.ng), stage.g_of)
        assert len(gap) == 2 * stage.nx * stage.N and np.all(gs[gap] == 0.0)


def _agree(a, b) -> None:
    assert a.ok == b.ok, (a.status, b.status)
    if a.ok:
        assert np.max(np.abs(a.x - b.x)) <= X_TOL
        assert abs(a.cost - b.cost) <= COST_TOL * (1.0 + abs(a.cost))
        assert abs(a.min_distance - b.min_distance) <= X_TOL


def test_the_stage_form_agrees_with_the_dense_qp_on_recorded_queries(problem, recorded):
    """Every recorded sim-2 query (warm and cold starts): HPIPM on the stage form returns the dense daqp solve's
    success, point (1e-5) and cost (1e-6 relative), and its smallest obstacle row."""
    dense, stage = _inner(_loop(problem, "daqp")), _inner(_loop(problem, "hpipm"))
    assert len(recorded) > 20 and any(q.lam_g0 is not None for q in recorded)
    n_ok = 0
    for q in recorded:
        a, b = dense.solve(q), stage.solve(q)
        _agree(a, b)
        n_ok += a.ok
    assert n_ok > len(recorded) // 2


def test_the_compiled_stage_form_agrees_with_the_interpreted_one(cc, problem, recorded):
    """The stage form as generated C (HPIPM linked into the library) gives the interpreted stage solve's answer."""
    loop = _loop(problem, "hpipm", compiled=True)
    compiled, interp = _inner(loop), _inner(_loop(problem, "hpipm"))
    assert isinstance(compiled, CompiledBackend), loop.replanner.compiled_message
    for q in recorded[:10]:
        _agree(interp.solve(q), compiled.solve(q))


def test_a_sim2_loop_with_the_stage_form_is_safe(problem):
    """Simulation 2 over 12 s with HPIPM: no collision and no D_sf breach at the dense verification, and the
    horizon solves succeed as often as with daqp (within 2 steps)."""
    runs = {qp: _loop(problem, qp, duration=12.0).run() for qp in ("hpipm", "daqp")}
    s = runs["hpipm"].summary()
    assert runs["hpipm"].steps > 50
    assert s["collisions"] == 0 and s["safety_violations"] == 0 and s["min_clearance_mm"] > 0.0
    solved = {qp: sum(st == "solved" for st in r.step_status) for qp, r in runs.items()}
    assert abs(solved["hpipm"] - solved["daqp"]) <= 2, solved
