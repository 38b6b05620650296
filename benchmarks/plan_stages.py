"""Where a cspace query's time goes: per stage, CPU time and the part of it spent in compiled (C) calls.

`benchmarks/plan.py --stages N` prints, for N sim-1 seeds (start tip, so the start IK runs) and N Table I
scenes at 7 moving obstacles (start configuration given), the median per stage over the queries: the
planner's CPU time in the stage (the thread's, `time.thread_time`: on a shared machine wall time mostly measures
the other jobs) and, of it, the time inside the compiled kernel's calls (`ValidityKernel`:
edge checks, clearances, tips and Jacobians, the IK projection, B-spline samples, path clearance); the rest
is Python (numpy and the interpreter) around them. The stages are the planner's own methods, timed by
wrappers installed for this section only (removed afterwards): "begin" (the query's checks, the scene's
validator, the start), "goal IK", "search" (the goal connection, the via round, the trees), "shortcut",
"smooth", "result" (the measured clearance and the result), and "plan" (the whole query). Medians of
different stages come from different queries, so they need not add up to the median of "plan".

Each result is then retimed as `plan_executable` does (`crtraj.planning.pipeline.retime_result`), with the
retiming's stages timed the same way: "corners" (`keep_corners`), "curve law" (the spline and the phase-plane
pass), "curve samples", "limit check" (the frames' finite differences), "frame check" (the frames' edge check and
limits at their times), "clearance" (the retimed frames' measured clearance, and the planner's), "fractions"
(the executed fractions) and "retime" (all of it).

The physical limit (sim 1): the samples a query checks (the planner's, the retiming's edge check and clearance:
the validator's sample counter), the floating-point operations per sample (the generated backbone function's
CasADi instructions plus the chords against every obstacle), and the C cost per sample measured on this machine
(`ValidityKernel.clearance` on 4,000 configurations, and the edge check on the frames of a retimed motion): the
samples' C time is the floor; the measured CPU time of the executable motion over it is the ratio.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

import crtraj.planning.pipeline as pipeline
import crtraj.planning.retime as retime
from crtraj.planning.base import PlannerBase
from crtraj.planning.planners._cspace import CSpacePlanner
from crtraj.planning.planners._cspace_search import CSpaceSearch
from crtraj.planning.postprocess import PathPostprocessor
from crtraj.planning.validity._compiled import ValidityKernel, kernel_functions
from crtraj.planning.validity._motion import MotionValidator

# the kernel's entry points that call C (each returns after its one C call)
KERNEL_CALLS = ("_run_auto", "_run_edges", "clearance", "clearance_windows", "tip_jacobian", "project",
                "points", "motion_bound", "path_clearance", "bspline", "phase_law", "natural_slopes",
                "hermite", "verify_motion")  # fmt: skip
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
    ("corners", retime, "keep_corners"),
    ("curve law", retime, "_piece_law"),
    ("curve samples", retime, "_sample_law"),
    ("limit check", retime, "_over_limits"),
    ("frame check", retime, "_failures"),
    ("clearance", MotionValidator, "path_clearance"),
    ("fractions", pipeline, "executed_fractions"),
    ("retime", pipeline, "retime_result"),
)


class StageClock:
    """CPU time (the thread's) per stage call and the compiled calls' CPU time within it (s), collected by
    `installed`."""

    def __init__(self) -> None:
        self.in_c = 0.0
        self.calls: dict[str, list[tuple[float, float]]] = {}

    def kernel_wrapper(self, f: Callable) -> Callable:
        def timed(*a: Any, **k: Any) -> Any:
            t = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                self.in_c += time.thread_time() - t

        return timed

    def stage_wrapper(self, name: str, f: Callable) -> Callable:
        def timed(*a: Any, **k: Any) -> Any:
            c0, t = self.in_c, time.thread_time()
            try:
                return f(*a, **k)
            finally:
                self.calls.setdefault(name, []).append((time.thread_time() - t, self.in_c - c0))

        return timed

    @contextmanager
    def installed(self) -> Iterator[StageClock]:
        """The wrappers on the classes while the block runs; the original methods afterwards."""
        saved = []
        for name in KERNEL_CALLS:  # each wrapped once (a name the kernel lacks is skipped)
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
            cpu = np.array([c[0] for c in calls]) * 1e3
            c = np.array([c[1] for c in calls]) * 1e3
            py = cpu - c
            out.append(
                f"   {name:<13s} {len(calls):4d} calls  CPU {np.median(cpu):6.3f} ms  C {np.median(c):6.3f} ms  "
                f"Python {np.median(py):6.3f} ms   (means {cpu.mean():6.3f} / {c.mean():6.3f} / {py.mean():6.3f})"
            )
        return out


def retimed(planner: Any, res: Any, kw: dict) -> tuple[Any, int]:
    """`res` retimed as `plan_executable` does (through the module, so the stage wrappers see it): (the executable
    result, the samples its checks took)."""
    ctx = planner.context
    v = ctx.validity_for(kw.get("scene"))
    n0 = v.n_samples
    out, _ = pipeline.retime_result(res, v, ctx, ctx.robot.actuator_limits(), pipeline.STREAM_RATE)
    return out, v.n_samples - n0


def section_stages(queries: dict[str, list[tuple[Any, Any, dict]]]) -> None:
    """Section 7: per query set {name: [(planner, goal, plan keyword arguments)]}, the stages' medians, then the
    physical limit on the first set (sim 1)."""
    print("\n== 7. where the time goes: per stage, CPU median, of it in compiled calls (C), the rest Python ==")
    print("   (the planners' own methods timed by wrappers; medians per stage, so they need not add up)")
    counts: list[tuple[int, int, int, float]] = []
    for i, (name, qs) in enumerate(queries.items()):
        clock = StageClock()
        with clock.installed():
            for planner, goal, kw in qs:
                c0 = time.process_time()
                res = planner.plan(goal, **kw)
                out, n_re = retimed(planner, res, kw)
                if i == 0 and out.is_success():
                    counts.append((res.counts.get("collision_samples", 0), n_re, len(out.t), time.process_time() - c0))
        print(f"-- {name}, {len(qs)} queries (plan, then retime_result)")
        for line in clock.rows():
            print(line)
    if counts:
        planner, goal, kw = next(iter(queries.values()))[0]
        physical_limit(planner, goal, kw, counts)


def physical_limit(planner: Any, goal: Any, kw: dict, counts: list[tuple[int, int, int, float]]) -> None:
    """The samples and floating-point work of a sim-1 executable query against the C cost per sample (module
    docstring); counts: per query (planner samples, retiming samples, frames, CPU s of plan + retime)."""
    ctx = planner.context
    v = ctx.validity_for(kw.get("scene"))
    k = v.kernel
    if k is None:
        return
    rng = np.random.default_rng(0)
    X = v.sample(rng, 4000)
    slots = v.state.static_slots
    obstacles = int(np.count_nonzero(slots[4::5] > 0.0))
    best = min(_timed(lambda: k.clearance(X, slots)) for _ in range(7)) / len(X)
    res = planner.plan(goal, **dict(kw, seed=0))
    out, _ = retimed(planner, res, kw)
    Y, T = out.configs, out.t
    n0 = v.n_samples
    edge = min(_timed(lambda: v.edges_valid(Y[:-1], Y[1:], T[:-1], T[1:])) for _ in range(7))
    n_edge = (v.n_samples - n0) // 7
    per_edge = edge / max(n_edge, 1)
    npts = k.check_points
    bb = kernel_functions(ctx.model, npts)[0]
    flops = bb.n_instructions() + 8 * (npts - 1) + obstacles * 23 * (npts - 1)
    plan_s = float(np.median([c[0] for c in counts]))
    re_s = float(np.median([c[1] for c in counts]))
    frames = float(np.median([c[2] for c in counts]))
    cpu = float(np.median([c[3] for c in counts]))
    # the floor: the planner's samples and the retimed frames' edge check at their C cost, and one backbone per frame
    # for the measured clearance (a frame's sample is shared by the motions on either side of it: computed once)
    parts = (plan_s * best, n_edge * per_edge, frames * best)
    floor = sum(parts)
    print(f"-- physical limit, sim 1 ({len(counts)} executable queries, medians; {obstacles} obstacles, {npts} points)")
    print(f"   samples per query: planner {plan_s:.0f}, retiming {re_s:.0f} as counted (the frames' edge check, "
          f"{n_edge}, and the clearance of {frames:.0f} frames at 100 Hz, each counted twice)")  # fmt: skip
    print(f"   work per sample: ~{flops} floating-point operations (backbone {bb.n_instructions()} CasADi "
          f"instructions, chords {8 * (npts - 1)}, {obstacles} obstacles x {npts - 1} chords x 23)")  # fmt: skip
    print(f"   C per sample: clearance {best * 1e6:.3f} us ({flops / best * 1e-9:.2f} GFLOP/s), edge check of the "
          f"frames {per_edge * 1e6:.3f} us per sample")  # fmt: skip
    print(f"   floor (samples x C cost): planner {parts[0] * 1e3:.2f} + frames' edge check {parts[1] * 1e3:.2f} + "
          f"frames' clearance {parts[2] * 1e3:.2f} = {floor * 1e3:.2f} ms; measured CPU plan + retime "
          f"{cpu * 1e3:.2f} ms: ratio {cpu / floor:.1f}x")  # fmt: skip


def _timed(f: Callable[[], Any]) -> float:
    """The thread's CPU time (s) of one call of f."""
    t = time.thread_time()
    f()
    return time.thread_time() - t
