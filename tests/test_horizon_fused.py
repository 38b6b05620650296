"""The fused horizon call (option `fused`, issue 29): the compiled solver, its KKT check and the row check as one
generated C function agree with the two-call path on recorded queries, and a closed loop makes the same decisions
with either. No timing here (that is benchmarks/replan.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool

from crtraj.control.horizon._backends import CompiledBackend, HorizonQuery
from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.loop import ClosedLoop, LoopOptions, ReplanRun
from crtraj.io.problem import Problem

ROOT = Path(__file__).resolve().parent.parent
# stated tolerance: the two paths run the same generated solver code, so they should agree to rounding
TOL = 1e-9


@pytest.fixture(scope="module")
def problem() -> Problem:
    require_tool("cc", "gcc", "clang", hint="the compiled horizon needs a C compiler")
    return Problem.load(ROOT / "problems" / "paper_dynamic.toml")


def _loop(problem: Problem, fused: bool) -> ClosedLoop:
    """Simulation 2 with the compiled horizon, deterministic: no step deadline, references planned inline."""
    opts = dataclasses.replace(problem.options(ReplanOptions, "replan"), fused=fused, step_deadline=0.0)
    lopts = dataclasses.replace(problem.options(LoopOptions, "loop"), reference_delay=0.0, duration=12.0)
    return ClosedLoop.from_problem(problem, seed=0, options=opts, loop_options=lopts)


@pytest.fixture(scope="module")
def fused(problem) -> tuple[CompiledBackend, list[HorizonQuery], ReplanRun]:
    """The fused loop's run over 12 s, once for both tests: its compiled backend, the queries it answered (warm and
    cold starts) and the run."""
    loop = _loop(problem, fused=True)
    backend = loop.replanner.backend.inner
    seen: list[HorizonQuery] = []
    solve = CompiledBackend.solve

    def record(self: CompiledBackend, query: HorizonQuery):
        seen.append(query)
        return solve(self, query)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(CompiledBackend, "solve", record)
        run = loop.run()
    return backend, seen, run


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(np.abs(np.asarray(a) - np.asarray(b)) <= TOL * (1.0 + np.abs(np.asarray(b)))))


def test_the_fused_call_agrees_with_the_two_call_path_on_recorded_queries(fused):
    """Every recorded query (warm and cold starts, with multipliers and without): the one fused C call returns
    the same point, multipliers, rows, obstacle rows, tips, violation and success test as the solver call followed
    by the KKT call and the numpy row check, to 1e-9 relative."""
    backend, queries, _ = fused
    assert isinstance(backend, CompiledBackend) and backend.parts.fused is not None
    assert len(queries) > 50 and any(q.lam_g0 is not None for q in queries) and any(q.lam_g0 is None for q in queries)
    for q in queries:
        new, st_new = backend._fused(q)
        old, st_old = backend._call(backend.check.args(q))
        assert set(new) == set(old) - {"lam_p"}  # lam_p: zeros (calc_lam_p off), never read
        for k in ("x", "g", "lam_x", "lam_g", "distances", "tips"):
            assert _close(new[k], old[k]), k
        assert _close(new["f"], old["f"])
        assert st_new["success"] == st_old["success"]
        assert abs(st_new["violation"] - st_old["violation"]) <= TOL * (1.0 + abs(st_old["violation"]))
        # the fused violation is the independent numpy check of its own point
        assert abs(st_new["violation"] - backend.check.violation(new["x"], new["g"])) <= 1e-12


def test_a_loop_with_the_fused_call_makes_the_same_decisions(problem, fused):
    """Simulation 2 over the same 12 s, fused and not: the same status at every step, the same configurations
    and set-points (1e-9 mm / rad), and the dense verification holds (no collision, no D_sf breach)."""
    runs = [fused[2], _loop(problem, fused=False).run()]
    a, b = (r.summary() for r in runs)
    assert runs[0].steps == runs[1].steps > 50
    assert runs[0].step_status == runs[1].step_status
    assert a["collisions"] == b["collisions"] == 0 and a["safety_violations"] == b["safety_violations"] == 0
    assert _close(runs[0].x, runs[1].x) and _close(runs[0].commands, runs[1].commands)
