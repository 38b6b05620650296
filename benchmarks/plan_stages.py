"""Where a cspace query's time goes: per stage, wall time and the part of it spent in compiled (C) calls.

`benchmarks/plan.py --stages N` prints, for N sim-1 seeds (start tip, so the start IK runs) and N Table I
scenes at 7 moving obstacles (start configuration given), the median per stage over the queries: the
planner's wall time in the stage and, of it, the time inside the compiled kernel's calls (`ValidityKernel`:
edge checks, clearances, tips and Jacobians, the IK projection, B-spline samples, path clearance); the rest
is Python (numpy and the interpreter) around them. The stages are the planner's own methods, timed by
wrappers installed for this section only (removed afterwards): "begin" (the query's checks, the scene's
validator, the start), "goal IK", "search" (the goal connection, the via round, the trees), "shortcut",
"smooth", "result" (the measured clearance and the result), and "plan" (the whole query). Medians of
different stages come from different queries, so they need not add up to the median of "plan".
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from crtraj.planning.base import PlannerBase
from crtraj.planning.planners._cspace import CSpacePlanner
from crtraj.planning.planners._cspace_search import CSpaceSearch
from crtraj.planning.postprocess import PathPostprocessor
from crtraj.planning.validity._compiled import ValidityKernel

# the kernel's entry points that call C (each returns after its one C call)
KERNEL_CALLS = ("_run_auto", "_run_edges", "clearance", "clearance_windows", "tip_jacobian", "project",
                "points", "motion_bound", "path_clearance", "bspline")  # fmt: skip
STAGES = (
    ("begin", PlannerBase, "_begin"),
    ("goal IK", CSpacePlanner, "_goals"),
    ("search", CSpaceSearch, "run"),
    ("shortcut", PathPostprocessor, "shortcut"),
    ("shortcut", PathPostprocessor, "shortcut_timed"),
    ("smooth", PathPostprocessor, "smooth"),
    ("smooth", PathPostprocessor, "smooth_timed"),
    ("result", PathPostprocessor, "result"),
    ("plan", CSpacePlanner, "plan"),
)


class StageClock:
    """Wall time per stage call and the compiled calls' time within it (s), collected by `installed`."""

    def __init__(self) -> None:
        self.in_c = 0.0
        self.calls: dict[str, list[tuple[float, float]]] = {}

    def kernel_wrapper(self, f: Callable) -> Callable:
        def timed(*a: Any, **k: Any) -> Any:
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                self.in_c += time.perf_counter() - t

        return timed

    def stage_wrapper(self, name: str, f: Callable) -> Callable:
        def timed(*a: Any, **k: Any) -> Any:
            c0, t = self.in_c, time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                self.calls.setdefault(name, []).append((time.perf_counter() - t, self.in_c - c0))

        return timed

    @contextmanager
    def installed(self) -> Iterator[StageClock]:
        """The wrappers on the classes while the block runs; the original methods afterwards."""
        saved = []
        for name in KERNEL_CALLS:
            if hasattr(ValidityKernel, name):
                saved.append((ValidityKernel, name, getattr(ValidityKernel, name)))
                setattr(ValidityKernel, name, self.kernel_wrapper(getattr(ValidityKernel, name)))
        for stage, cls, name in STAGES:
            if name in cls.__dict__:
                saved.append((cls, name, cls.__dict__[name]))
                setattr(cls, name, self.stage_wrapper(stage, cls.__dict__[name]))
        try:
            yield self
        finally:
            for cls, name, f in reversed(saved):
                setattr(cls, name, f)

    def rows(self) -> list[str]:
        out = []
        for name in dict.fromkeys(s for s, _, _ in STAGES):
            calls = self.calls.get(name)
            if not calls:
                continue
            wall = np.array([c[0] for c in calls]) * 1e3
            c = np.array([c[1] for c in calls]) * 1e3
            py = wall - c
            out.append(
                f"   {name:<9s} {len(calls):4d} calls  wall {np.median(wall):6.3f} ms  C {np.median(c):6.3f} ms  "
                f"Python {np.median(py):6.3f} ms   (means {wall.mean():6.3f} / {c.mean():6.3f} / {py.mean():6.3f})"
            )
        return out


def section_stages(queries: dict[str, list[tuple[Any, Any, dict]]]) -> None:
    """Section 7: per query set {name: [(planner, goal, plan keyword arguments)]}, the stages' medians."""
    print("\n== 7. where the time goes: per stage, wall median, of it in compiled calls (C), the rest Python ==")
    print("   (the planners' own methods timed by wrappers; medians per stage, so they need not add up)")
    for name, qs in queries.items():
        clock = StageClock()
        with clock.installed():
            for planner, goal, kw in qs:
                planner.plan(goal, **kw)
        print(f"-- {name}, {len(qs)} queries")
        for line in clock.rows():
            print(line)
