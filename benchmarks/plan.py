"""Planning time of the cspace planner, old path against new, interleaved in one run, and against OMPL.

"old" and "new" both run on the compiled validity kernel; "old" has neither the edge check's broad phase
(``[planner.check] broad_phase = false``) nor its early exit across a batch (``early_exit = false``), nor the
safe IK's rescue stage (``[planner.ik] rescue_starts = 0``) nor its compiled projection (``compiled = false``),
as the code before issue 29 (the other changes of that issue give identical plans and have no switch).
Each query runs on both paths, one after the other, so both see the same load.

1. Simulation 1 (problems/paper_static.toml), `--seeds` seeds: success, wall and CPU median / p90,
   successes re-checked densely, IPOPT solves of the safe IK (the fallback), identical plans, path
   length and clearance. Targets (new): median <= 3 ms, p90 <= 6 ms, 100 % success.
2. OMPL RRTConnect over the same compiled validator, on sim 1 (the starts crtraj's start IK found) and on
   the Table I scenes at 3 and 7 obstacles: time to the first verified solution (goal IK included; crtraj: when
   its search returns, before shortcuts and smoothing), and time to an
   executable motion: OMPL's path simplified by its PathSimplifier, then both retimed with
   `crtraj.planning.pipeline.retime_result` (as `plan_executable`), the retimed frames re-checked densely.
   Target: crtraj >= 3x faster. Beside them crtraj's same plans retimed the way before issue 41
   (`compiled=False`: the phase pass in Python, the model's CasADi tips), right after the new retiming.
3. Table I scenes (`crtraj.bench.scenarios`, moving obstacles) at 7 obstacles, `--table1` scenes.
   Targets (new): median <= 4 ms, p90 <= 10 ms.
4. Scaling (`--scaling` scenes per point): CPU time against the obstacle count (1 to 100 spheres) and the
   segment count (2, 3, 4 at 7 obstacles); the plot goes to `--plot` (docs/scaling_plan.png).
   Target (new): 31 obstacles at most 3x the time at 1.
5. Edge checks per second, with and without the broad phase, and the kernel's loaders (ctypes against
   ``casadi.external``).
7. With `--stages N`: where a query's time goes, per stage, in C and in Python, planning and retiming, and the
   physical limit: samples, work per sample and the C cost per sample against the measured CPU time
   (`benchmarks/plan_stages.py`).

Plan times are the planner's own wall time per query (`PlanResult.timings["total"]`), planners built once
and warmed up by one untimed query, with the process CPU time beside it (`time.process_time`; on a machine
shared with other jobs it moves far less with their load than wall time). Every success of sections 1-2
is re-checked independently (200 backbone points every 10 ms of the timed path, numpy distances).

With `--baseline REV` (a git revision, e.g. the previous stop's commit) the run starts with section 0: this
code against REV's on the same queries (sim 1 and Table I at 7 obstacles, the planner alone; and the executable
motion, plan and `retime_result`, on sim 1 and Table I at 3 and 7 obstacles), each side in its own process
(`--ab-worker`), the sides alternating `--ab-rounds` times so both see the same load: CPU and wall medians,
their ratio, identical plans, success, length, smallest clearance and the dense re-check.

Run: python benchmarks/plan.py [--seeds 40] [--ompl-seeds 10] [--table1 20] [--scaling 10] [--plot PATH]
     [--rrtstar-seeds 0] [--baseline REV [--ab-rounds 3]]
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.bench.scenarios import ScenarioGenerator, ScenarioOptions
from crtraj.core.build_cache import BuildCache
from crtraj.core.fileio import read_toml
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot, Segment
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.pipeline import STREAM_RATE, retime_result
from crtraj.planning.planners._registry import BUILTIN, make_planner
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity._compiled import ValidityKernel, kernel_functions
from crtraj.planning.validity._motion import MotionValidator
from crtraj.world.scene import Scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from baseline_tree import revision_tree  # sibling modules (the script may be run from anywhere)
from plan_stages import section_stages

ROOT = Path(__file__).resolve().parent.parent
# Section 2's row of crtraj's plans retimed the way before issue 41 (`retime_result(..., compiled=False)`).
OLD_RETIME = "crtraj, retiming in Python"
# The two paths compared in every section (both on the compiled kernel): "old" without the edge check's broad
# phase and without the IK's rescue stage (the code before issue 29), "new" the defaults.
MODES = (
    ("old", {"check": {"broad_phase": False, "early_exit": False}, "ik": {"rescue_starts": 0, "compiled": False}}),
    ("new", {}),
)


def paper_plan_time() -> float:
    """The paper's simulation-1 planning time (s), from benchmarks/paper_results.toml."""
    return float(read_toml(ROOT / "benchmarks" / "paper_results.toml")["static"]["plan_s"])


def dense_clearance(model: Model, scene: Scene, t: np.ndarray, X: np.ndarray, dt: float = 0.01) -> float:
    """Independent check: min distance beyond D_sf + disc radius of 200 backbone points, every dt seconds."""
    xs, ts = [X[:1]], [t[:1]]
    for k in range(len(t) - 1):
        n = max(2, int(np.ceil((t[k + 1] - t[k]) / dt)) + 1)
        f = np.linspace(0.0, 1.0, n)[1:]
        xs.append(X[k] + f[:, None] * (X[k + 1] - X[k]))
        ts.append(t[k] + f * (t[k + 1] - t[k]))
    S, T = np.concatenate(xs), np.concatenate(ts)
    if model.robot.limit_violation(S).max() > 1e-9:
        return -np.inf
    P = model.points(S, 200)
    c, r = scene.states(T)
    d = np.linalg.norm(P[:, :, None, :] - c[:, None], axis=-1) - r[:, None, :]
    return float(d.min()) - model.robot.body_radius - scene.safety_distance


def summary(times: list[float]) -> str:
    """'median / p90 ms' of plan times (s); failures count as inf (then the p90 is the nearest rank above)."""
    method = "linear" if np.isfinite(times).all() else "higher"
    return f"{statistics.median(times) * 1e3:7.1f} / {np.percentile(times, 90, method=method) * 1e3:6.1f} ms"


def timed_plan(planner, goal, **kw) -> tuple[Any, float, float, int]:
    """One query: (result, wall time s (the planner's own), CPU time s, IPOPT solves of its safe IK)."""
    n0 = getattr(planner.ik, "nlp_solves", 0)
    c0 = time.process_time()
    res = planner.plan(goal, **kw)
    cpu = time.process_time() - c0
    return res, res.timings["total"], cpu, getattr(planner.ik, "nlp_solves", 0) - n0


def new_row() -> dict:
    return {"times": [], "cpu": [], "results": [], "nlp": 0, "verified": 0}


def add(row: dict, out: tuple[Any, float, float, int], verified: bool = False) -> None:
    res, wall, cpu, nlp = out
    row["times"].append(wall)
    row["cpu"].append(cpu)
    row["results"].append(res)
    row["nlp"] += nlp
    row["verified"] += bool(verified)


def successes(row: dict) -> int:
    return sum(r.is_success() for r in row["results"])


def planners(model: Model, scene: Scene, options: PlannerOptions, **kw) -> dict:
    """The cspace planner of each mode (old, new), built once."""
    return {label: make_planner(model, scene, options.with_(algorithm="cspace", **mode), **kw) for label, mode in MODES}


def section_sim1(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, n: int) -> dict:
    print(f"\n== 1. simulation 1 (paper_static), cspace, {n} seeds: old vs new, interleaved ==")
    task, stop = problem.task, options.stop()
    kw = {"start_tip": task.start, "stop": stop, "goal_tolerance": task.goal_tolerance}
    ps = planners(model, scene, options)
    rows = {label: new_row() for label in ps}
    for p in ps.values():
        p.plan(task.goal, seed=10_000, **kw)  # warm-up (builds, caches)
    for seed in range(n):
        for label, p in ps.items():
            out = timed_plan(p, task.goal, seed=seed, **kw)
            ok = out[0].is_success() and dense_clearance(model, scene, out[0].t, out[0].configs) >= 0.0
            add(rows[label], out, ok)
    print_rows(rows, n)
    old, new = rows["old"]["results"], rows["new"]["results"]
    same = sum(np.array_equal(a.configs, b.configs) and np.array_equal(a.t, b.t) for a, b in zip(old, new, strict=True))
    both = [(a, b) for a, b in zip(old, new, strict=True) if a.is_success() and b.is_success()]
    if both:
        la, lb = np.mean([a.length for a, _ in both]), np.mean([b.length for _, b in both])
        ca_, cb = min(a.min_clearance for a, _ in both), min(b.min_clearance for _, b in both)
        print(f"identical plans: {same}/{n}; tip path length mean old {la:.1f} / new {lb:.1f} mm; ", end="")
        print(f"smallest clearance old {ca_:.2f} / new {cb:.2f} mm")
    print("targets (new): median <= 3 ms, p90 <= 6 ms, 100 % success, every success verified densely")
    return rows


def print_rows(rows: dict, n: int) -> None:
    """The old/new table: success, wall and CPU median / p90, densely verified successes, IPOPT solves, edge-check
    samples per query (median)."""
    head = f"{'path':<6s} {'success':>9s} {'wall median / p90':>22s} {'CPU median / p90':>22s}"
    print(f"{head}  verified  IPOPT  samples")
    for label, r in rows.items():
        ok = successes(r)
        # edge-check samples per query (median): what the early exits save
        samples = statistics.median(res.counts.get("collision_samples", 0) for res in r["results"])
        print(
            f"{label:<6s} {ok:>4d}/{n:<4d} {summary(r['times']):>22s} {summary(r['cpu']):>22s}  "
            f"{r['verified']:>4d}/{ok:<4d} {r['nlp']:>4d}  {samples:7.0f}"
        )
    old, new = rows["old"], rows["new"]
    wall = statistics.median(old["times"]) / statistics.median(new["times"])
    cpu = statistics.median(old["cpu"]) / statistics.median(new["cpu"])
    print(f"speed-up old/new (median): wall {wall:.2f}x, CPU {cpu:.2f}x")


def table1_scenes(model: Model, count: int, n: int) -> list:
    gen = ScenarioGenerator(model, ScenarioOptions(seed=0))
    return [gen.generate(count, i) for i in range(n)]


def table1_rows(model: Model, options: PlannerOptions, count: int, n: int) -> dict:
    """cspace old and new, interleaved, on the first n Table I scenes with `count` moving obstacles."""
    ps = planners(model, Scene(), options, max_obstacles=8)
    stop = StopCondition(time_limit=5.0, max_iterations=options.max_iterations, first_solution=True)
    warm = ScenarioGenerator(model, ScenarioOptions(seed=99)).generate(count, 0)
    for p in ps.values():
        p.plan(warm.goal, start_config=warm.start, scene=warm.scene, stop=stop, seed=0)
    rows = {label: new_row() for label in ps}
    for i, sc in enumerate(table1_scenes(model, count, n)):
        for label, p in ps.items():
            out = timed_plan(p, sc.goal, start_config=sc.start, scene=sc.scene, stop=stop, seed=i)
            res = out[0]
            add(rows[label], out, res.is_success() and dense_clearance(model, sc.scene, res.t, res.configs) >= 0.0)
    return rows


def ompl_queries(problem: Problem, model: Model, scene: Scene, sim1: dict, n: int) -> dict:
    """The OMPL comparison's query sets: (goal, start configuration, scene) each."""
    sets = {"sim 1": [(problem.task.goal, r.configs[0], scene) for r in sim1["new"]["results"][:n] if r.has_path]}
    for count in (3, 7):
        sets[f"Table I, {count} obstacles"] = [(sc.goal, sc.start, sc.scene) for sc in table1_scenes(model, count, n)]
    return sets


def executable(res: Any, context: PlanningContext, scene: Scene, compiled: bool = True) -> tuple[bool, float, Any]:
    """Retime a result as `plan_executable` does (`retime_result`): (success, retime wall time s, the retimed
    result). compiled False: the phase pass in Python and the model's CasADi tips (the retiming before issue 41)."""
    limits = context.robot.actuator_limits()
    if not res.is_success() or limits is None or context.rate_limits is None:
        return res.is_success(), 0.0, res
    kw = {} if compiled else {"compiled": False}  # a baseline tree's retime_result has no switch
    t1 = time.perf_counter()
    out, _ = retime_result(res, context.validity_for(scene), context, limits, STREAM_RATE, **kw)
    return out.is_success(), time.perf_counter() - t1, out


def section_ompl(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, sim1: dict, n: int) -> None:
    print(f"\n== 2. against OMPL RRTConnect on the same compiled validator, {n} queries per scene set ==")
    try:
        from crtraj.planning.planners._ompl import OMPLPlanner, import_ompl

        import_ompl()
    except Exception as exc:  # the bench extra is optional
        print(f"skipped: {exc}")
        return
    # 5 s per query: OMPL fails many Table I queries, and each failure spends the whole limit
    o = options.with_(algorithm="cspace", time_limit=5.0)
    stop = StopCondition(time_limit=5.0, max_iterations=options.max_iterations, first_solution=True)
    print("first: time to the first verified solution (goal IK included; crtraj: when its search returns, before")
    print("shortcuts and smoothing); executable: crtraj's whole plan (shortcut, smoothed, verified), OMPL's path")
    print("simplified by its PathSimplifier, then both retimed (`retime_result`, as plan_executable) and the retimed")
    print(f"frames re-checked densely; '{OLD_RETIME}': crtraj's same plans retimed as before issue 41")
    for name, queries in ompl_queries(problem, model, scene, sim1, n).items():
        # with the robot's rate limits, as plan_executable plans and retimes
        ctx = PlanningContext.build(model, scene if name == "sim 1" else Scene(), o)
        runs = {
            "crtraj": BUILTIN.create("cspace", ctx, None),
            "RRTConnect": OMPLPlanner(ctx, algorithm="RRTConnect", simplify=False),
            "RRTConnect+simplify": OMPLPlanner(ctx, algorithm="RRTConnect", simplify=True),
        }
        first = {k: [] for k in [*runs, OLD_RETIME]}
        exe = {k: [] for k in [*runs, OLD_RETIME]}
        same = 0
        for i, (goal, xs, sc) in enumerate(queries):
            for label, p in runs.items():
                res = p.plan(goal, start_config=xs, scene=sc, stop=stop, seed=i)
                ok, t_re, out = executable(res, ctx, sc)
                # crtraj: until its search returned a verified path (goal IK included), before shortcuts and
                # smoothing, as OMPL's first solution; OMPL's own total otherwise
                t_first = res.timings.get("first_solution", res.timings["total"])
                if label == "crtraj":  # the same plan retimed the old way too, right after (the same load)
                    ok_old, t_old, old = executable(res, ctx, sc, compiled=False)
                    same += bool(np.array_equal(old.configs, out.configs) and np.array_equal(old.t, out.t))
                    dense_old = ok_old and dense_clearance(model, sc, old.t, old.configs) >= 0.0
                    first[OLD_RETIME].append(t_first if res.is_success() else np.inf)
                    exe[OLD_RETIME].append(res.timings["total"] + t_old if dense_old else np.inf)
                # the executable motion (retimed frames) re-checked densely
                ok = ok and dense_clearance(model, sc, out.t, out.configs) >= 0.0
                first[label].append(t_first if res.is_success() else np.inf)
                exe[label].append(res.timings["total"] + t_re if ok else np.inf)
        print(f"-- {name}: median / p90, success; crtraj's speed-up over RRTConnect")
        for label in exe:
            ok = int(np.isfinite(exe[label]).sum())
            line = f"   {label:<28s} first {summary(first[label])}   executable {summary(exe[label])}"
            print(f"{line}   {ok}/{len(queries)}")
        sp_first = np.median(first["RRTConnect"]) / np.median(first["crtraj"])
        sp_exe = np.median(exe["RRTConnect+simplify"]) / np.median(exe["crtraj"])
        print(f"   speed-up (median): first solution {sp_first:.1f}x, executable {sp_exe:.1f}x (target >= 3x)")
        print(f"   identical executable motions, compiled and Python retiming: {same}/{len(queries)}")


def section_table1(model: Model, options: PlannerOptions, n: int) -> None:
    print(f"\n== 3. Table I scenes, 7 moving obstacles, cspace, {n} scenes: old vs new, interleaved ==")
    rows = table1_rows(model, options, 7, n)
    print_rows(rows, n)
    print("targets (new): median <= 4 ms, p90 <= 10 ms")


def split_robot(robot: Robot, n_segments: int) -> Robot:
    """cdsr2 with its total length split into n_segments equal segments (same bending limit, alternating
    cable phase), for the segment-count scaling."""
    seg = robot.segments[0]
    length = robot.total_length / n_segments
    segs = tuple(Segment(length, seg.theta_max, (k % 2) * np.pi / 3) for k in range(n_segments))
    return replace(robot, name=f"cdsr2x{n_segments}", segments=segs, actuators=None)


def section_scaling(model: Model, options: PlannerOptions, n: int, plot: str | None) -> None:
    print(f"\n== 4. scaling: cspace CPU-time median over {n} Table I scenes, old / new (ms), interleaved ==")
    rows: dict[str, list[tuple[int, float, float]]] = {"obstacles": [], "segments": []}
    for m in (1, 3, 7, 15, 31, 100):
        r = table1_rows(model, options, m, n)
        old, new = statistics.median(r["old"]["cpu"]), statistics.median(r["new"]["cpu"])
        rows["obstacles"].append((m, old, new))
        ok = f"{successes(r['old'])}/{successes(r['new'])} of {n}"
        print(
            f"{m:>3d} obstacles (2 segments):  {old * 1e3:8.1f} / {new * 1e3:7.1f}   {old / new:5.2f}x   success {ok}"
        )
    base = rows["obstacles"][0]
    for m, old, new in rows["obstacles"][1:]:
        print(f"time at {m} / at 1 obstacle: old {old / base[1]:.1f}x, new {new / base[2]:.1f}x")
    print("target (new): at 31 obstacles at most 3x the time at 1")
    for k in (2, 3, 4):
        mk = Model(split_robot(model.robot, k)) if k != 2 else model
        r = table1_rows(mk, options, 7, n)
        old, new = statistics.median(r["old"]["cpu"]), statistics.median(r["new"]["cpu"])
        rows["segments"].append((k, old, new))
        print(f"{k:>3d} segments (7 obstacles):   {old * 1e3:8.1f} / {new * 1e3:7.1f}   {old / new:5.2f}x")
    if plot:
        write_plot(rows, Path(plot), n)


def write_plot(rows: dict, path: Path, n: int) -> None:
    """Two panels: plan time against obstacles and against segments, old and new (log time axis)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.6), layout="constrained")
    for ax, key, xlabel in zip(
        fig.subplots(1, 2), ("obstacles", "segments"), ("obstacles (spheres)", "segments"), strict=True
    ):
        x = [r[0] for r in rows[key]]
        ax.plot(x, [r[1] * 1e3 for r in rows[key]], "o-", label="old (issue 29 switched off)")
        ax.plot(x, [r[2] * 1e3 for r in rows[key]], "s-", label="new")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("cspace plan CPU time, median (ms)")
        ax.set_yscale("log")
        ax.set_xscale("log" if key == "obstacles" else "linear")
        ax.set_xticks(x, [str(v) for v in x])
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"crtraj plan time, Table I scenes ({n} per point), {datetime.date.today()}, {platform.node()}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def section_checks(model: Model, options: PlannerOptions, n: int = 400, repeat: int = 5) -> None:
    print(
        f"\n== 5. edge checks per CPU second: {n} random motions in Table I scenes, without / with the broad phase =="
    )
    rng = np.random.default_rng(0)
    for count in (7, 31, 100):
        sc = ScenarioGenerator(model, ScenarioOptions(seed=0)).generate(count, 0).scene
        rates = []
        for broad in (False, True):
            v = MotionValidator(model, sc, check_points=options.check.points, broad_phase=broad)
            XA, XB = v.sample(rng, n), v.sample(rng, n)
            TA = rng.uniform(0.0, 5.0, n)
            TB = TA + v.duration(XB - XA)
            s0, c0 = v.n_samples, time.process_time()
            for _ in range(repeat):
                v.check_edges(XA, XB, TA, TB, prefix=False)
            cpu = time.process_time() - c0
            rates.append(((v.n_samples - s0) / cpu, n * repeat / cpu))
        (s_old, e_old), (s_new, e_new) = rates
        print(
            f"{count:>3d} obstacles: samples/s {s_old:9.0f} -> {s_new:9.0f}, motions/s {e_old:7.0f} -> {e_new:7.0f} "
            f"({e_new / e_old:.2f}x)"
        )


def section_loaders(model: Model, check_points: int, n: int = 512, repeat: int = 200) -> None:
    print(f"\n== 6. loading the compiled code: batched backbone FK of {n} configurations ==")
    kernel = ValidityKernel.load(model, check_points, BuildCache())
    if kernel is None:
        print("skipped: no C compiler")
        return
    X = np.random.default_rng(0).uniform(-1, 1, (n, model.nx))
    ext = ca.external("crtraj_bb", str(kernel.library))
    mapped = ext.map(n, "serial")
    buf, run = mapped.buffer()
    Xc = np.ascontiguousarray(X)
    out = np.empty((n, check_points, 3))
    buf.set_arg(0, memoryview(Xc))
    buf.set_res(0, memoryview(out))
    ref = kernel.points(X)

    def timed(f) -> float:
        f()
        t = time.perf_counter()
        for _ in range(repeat):
            f()
        return (time.perf_counter() - t) / repeat

    t_ctypes = timed(lambda: kernel.points(X))
    t_ext = timed(run)
    t_ext_dm = timed(lambda: np.asarray(mapped(Xc.T)))
    interp = kernel_functions(model, check_points)[0].map(n, "serial")
    t_interp = timed(lambda: np.asarray(interp(Xc.T)))
    assert np.allclose(out, ref, atol=1e-12)
    print(f"ctypes driver on numpy buffers:        {t_ctypes * 1e6:8.1f} us")
    print(f"casadi.external + map, buffer API:     {t_ext * 1e6:8.1f} us   ({t_ext / t_ctypes:.2f}x ctypes)")
    print(f"casadi.external + map, DM in/out:      {t_ext_dm * 1e6:8.1f} us   ({t_ext_dm / t_ctypes:.2f}x ctypes)")
    print(f"interpreted CasADi map (old):          {t_interp * 1e6:8.1f} us   ({t_interp / t_ctypes:.2f}x ctypes)")


def ab_worker(problem_path: str, seeds: int, scenes: int) -> None:
    """One side of section 0, with whatever crtraj is on the path: per query (wall s, CPU s, success, densely
    verified, tip path length mm, smallest clearance mm, a digest of the timed path), as one JSON line."""
    problem = Problem.load(problem_path)
    model = Model(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner").with_(algorithm="cspace")
    out: dict[str, list] = {"sim 1": [], "Table I, 7 obstacles": []}
    task = problem.task
    p = make_planner(model, scene, options)
    kw = {"start_tip": task.start, "stop": options.stop(), "goal_tolerance": task.goal_tolerance}
    p.plan(task.goal, seed=10_000, **kw)  # warm-up
    queries = [("sim 1", p, task.goal, dict(kw, seed=s), scene) for s in range(seeds)]
    p7 = make_planner(model, Scene(), options, max_obstacles=8)
    stop = StopCondition(time_limit=5.0, max_iterations=options.max_iterations, first_solution=True)
    warm = ScenarioGenerator(model, ScenarioOptions(seed=99)).generate(7, 0)
    p7.plan(warm.goal, start_config=warm.start, scene=warm.scene, stop=stop, seed=0)
    for i, sc in enumerate(table1_scenes(model, 7, scenes)):
        queries.append(("Table I, 7 obstacles", p7, sc.goal, {"start_config": sc.start, "scene": sc.scene,
                                                             "stop": stop, "seed": i}, sc.scene))  # fmt: skip
    for name, planner, goal, kw_q, sc in queries:
        res, wall, cpu, _ = timed_plan(planner, goal, **kw_q)
        ok = res.is_success()
        dense = ok and dense_clearance(model, sc, res.t, res.configs) >= 0.0
        digest = hashlib.sha256(res.configs.tobytes() + res.t.tobytes()).hexdigest()
        out[name].append([wall, cpu, ok, dense, float(res.length), float(res.min_clearance), digest])
    out.update(ab_executable(problem, model, scene, options, seeds, scenes))
    print(json.dumps(out))


def ab_executable(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, seeds: int, scenes: int):
    """Section 0's executable motions: per query (plan + retime wall s, plan + retime CPU s, success, the retimed
    frames verified densely, tip path length mm, clearance mm, a digest of the frames, the retiming's wall s)."""
    out: dict[str, list] = {}
    o = options.with_(algorithm="cspace")
    stop = StopCondition(time_limit=5.0, max_iterations=o.max_iterations, first_solution=True)
    goal, start = problem.task.goal, problem.task.start
    sets = {"executable, sim 1": (scene, [(goal, {"start_tip": start, "seed": s}, scene) for s in range(seeds)])}
    for count in (3, 7):
        qs = [(sc.goal, {"start_config": sc.start, "scene": sc.scene, "seed": i}, sc.scene)
              for i, sc in enumerate(table1_scenes(model, count, scenes))]  # fmt: skip
        sets[f"executable, Table I, {count} obstacles"] = (Scene(), qs)
    for name, (base, qs) in sets.items():
        ctx = PlanningContext.build(model, base, o)
        p, (g, kw0, sc0), rows = BUILTIN.create("cspace", ctx, None), qs[-1], out.setdefault(name, [])
        executable(p.plan(g, stop=stop, **dict(kw0, seed=10_000)), ctx, sc0)  # warm-up
        for goal, kw, sc in qs:
            c0, res = time.process_time(), p.plan(goal, stop=stop, **kw)
            ok, t_re, ex = executable(res, ctx, sc)
            cpu, dense = time.process_time() - c0, ok and dense_clearance(model, sc, ex.t, ex.configs) >= 0.0
            digest = hashlib.sha256(ex.configs.tobytes() + ex.t.tobytes()).hexdigest()
            rows.append([res.timings["total"] + t_re, cpu, ok, dense, ex.length, ex.min_clearance, digest, t_re])
    return out


def stage_queries(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, n: int) -> dict:
    """Section 7's query sets (sim 1 from its start tip, Table I at 7 obstacles), planners built and warmed up, with
    the robot's rate limits as `plan_executable` has them (section 7 retimes every result)."""
    o = options.with_(algorithm="cspace")
    task = problem.task
    p = make_planner(model, scene, o, rate_limits=model.robot.rate_limits())
    kw = {"start_tip": task.start, "stop": o.stop(), "goal_tolerance": task.goal_tolerance}
    p.plan(task.goal, seed=10_000, **kw)
    p7 = make_planner(model, Scene(), o, max_obstacles=8, rate_limits=model.robot.rate_limits())
    stop = StopCondition(time_limit=5.0, max_iterations=o.max_iterations, first_solution=True)
    warm = ScenarioGenerator(model, ScenarioOptions(seed=99)).generate(7, 0)
    p7.plan(warm.goal, start_config=warm.start, scene=warm.scene, stop=stop, seed=0)
    t1 = [(p7, sc.goal, {"start_config": sc.start, "scene": sc.scene, "stop": stop, "seed": i})
          for i, sc in enumerate(table1_scenes(model, 7, n))]  # fmt: skip
    return {"sim 1": [(p, task.goal, dict(kw, seed=s)) for s in range(n)], "Table I, 7 obstacles": t1}


def section_baseline(rev: str, problem_path: str, seeds: int, scenes: int, rounds: int) -> None:
    """Section 0: this code against REV's (module docstring)."""
    print(f"\n== 0. this code against {rev}: {seeds} sim-1 seeds, {scenes} Table I scenes, {rounds} rounds ==")
    with revision_tree(rev) as tmp:
        sides = {rev: tmp, "this": str(ROOT)}
        runs: dict[str, list[dict]] = {k: [] for k in sides}
        for _ in range(rounds):
            for label, tree in sides.items():
                env = dict(os.environ, PYTHONPATH=tree)
                cmd = [sys.executable, str(Path(__file__).resolve()), "--ab-worker", "--problem", problem_path]
                cmd += ["--seeds", str(seeds), "--table1", str(scenes)]
                done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
                runs[label].append(json.loads(done.stdout.strip().splitlines()[-1]))
    for name in runs["this"][0]:
        print(f"-- {name}: CPU and wall median / p90 over {rounds} rounds (every query of every round)")
        rows = {label: [q for r in rs for q in r[name]] for label, rs in runs.items()}
        for label, qs in rows.items():
            ok = sum(q[2] for q in qs) // rounds
            dense = sum(q[3] for q in qs) // rounds
            print(f"   {label:<12s} CPU {summary([q[1] for q in qs])}  wall {summary([q[0] for q in qs])}  "
                  f"success {ok}/{len(qs) // rounds}, verified densely {dense}")  # fmt: skip
        old, new = rows[rev], rows["this"]
        cpu = statistics.median(q[1] for q in old) / statistics.median(q[1] for q in new)
        wall = statistics.median(q[0] for q in old) / statistics.median(q[0] for q in new)
        n = len(new) // rounds
        same = sum(a[6] == b[6] for a, b in zip(old[:n], new[:n], strict=True))
        both = [(a, b) for a, b in zip(old[:n], new[:n], strict=True) if a[2] and b[2]]
        la, lb = np.mean([a[4] for a, _ in both]), np.mean([b[4] for _, b in both])
        ca_, cb = min(a[5] for a, _ in both), min(b[5] for _, b in both)
        print(f"   speed-up {rev} / this (median): CPU {cpu:.2f}x, wall {wall:.2f}x; identical plans {same}/{n}; "
              f"tip path length mean {la:.1f} / {lb:.1f} mm; smallest clearance {ca_:.2f} / {cb:.2f} mm")  # fmt: skip
        if len(new[0]) > 7:  # executable motions: the retiming's own wall time
            rt = {label: summary([q[7] for q in qs]) for label, qs in rows.items()}
            print("   retiming alone, wall median / p90: " + ", ".join(f"{k} {v}" for k, v in rt.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_static.toml"))
    ap.add_argument("--seeds", type=int, default=40, help="seeds of sim 1 (0..N-1)")
    ap.add_argument("--ompl-seeds", type=int, default=10, help="queries per OMPL scene set (0 = skip)")
    ap.add_argument("--table1", type=int, default=20, help="Table I scenes at 7 obstacles (0 = skip)")
    ap.add_argument("--scaling", type=int, default=0, help="scenes per scaling point (0 = skip)")
    ap.add_argument("--plot", default=None, help="write the scaling plot here (e.g. docs/scaling_plan.png)")
    ap.add_argument("--rrtstar-seeds", type=int, default=0, help="seeds of the paper's task-space RRT* (0 = skip)")
    ap.add_argument("--rrtstar-time-limit", type=float, default=10.0, help="s per RRT* query")
    ap.add_argument("--baseline", default=None, help="git revision to compare this code against (section 0)")
    ap.add_argument("--ab-rounds", type=int, default=3, help="alternating rounds of section 0")
    ap.add_argument("--ab-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--stages", type=int, default=0, help="queries per set of section 7 (0 = skip)")
    args = ap.parse_args()
    if args.ab_worker:
        ab_worker(args.problem, args.seeds, args.table1)
        return

    problem = Problem.load(args.problem)
    model = Model(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    print(
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; machine: {platform.node()} "
        f"{platform.machine()}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; Python "
        f"{platform.python_version()}, casadi {ca.__version__}, numpy {np.__version__}"
    )
    cache = BuildCache()
    t1 = time.perf_counter()
    for n in sorted({options.check.points, PlannerOptions().check.points}):
        ValidityKernel.load(model, n, cache)
    print(f"build cache {cache.root}: kernels ready in {time.perf_counter() - t1:.2f} s ({cache.builds} built)")
    print(f"problem: {problem.name} (start {problem.task.start.tolist()} -> goal {problem.task.goal.tolist()} mm)")
    if args.baseline:
        section_baseline(args.baseline, args.problem, args.seeds, args.table1, args.ab_rounds)

    rows = section_sim1(problem, model, scene, options, args.seeds)
    if args.ompl_seeds > 0:
        section_ompl(problem, model, scene, options, rows, min(args.ompl_seeds, args.seeds))
    if args.rrtstar_seeds > 0:
        steer = problem.options(SteerOptions, "steer")
        p = make_planner(model, scene, options.with_(algorithm="rrtstar", time_limit=args.rrtstar_time_limit), steer)
        stop = StopCondition(
            time_limit=args.rrtstar_time_limit, max_iterations=options.max_iterations, first_solution=True
        )
        task = problem.task
        r = new_row()
        for seed in range(args.rrtstar_seeds):
            add(r, timed_plan(p, task.goal, start_tip=task.start, seed=seed, stop=stop, goal_tolerance=0.5))
        print(f"\ntask-space RRT* (paper's method): {successes(r)}/{args.rrtstar_seeds} {summary(r['times'])}")
    print(f"paper (Python, i7-12700H): {paper_plan_time() * 1e3:.0f} ms")
    if args.table1 > 0:
        section_table1(model, options, args.table1)
    if args.scaling > 0:
        section_scaling(model, options, args.scaling, args.plot)
    section_checks(model, options)
    section_loaders(model, options.check.points)
    if args.stages > 0:
        section_stages(stage_queries(problem, model, scene, options, args.stages))
    print(
        f"\nload average at the end: {os.getloadavg()[0]:.1f} (a shared machine: the old/new ratios of one run "
        "carry the argument, absolute times move with the load)"
    )


if __name__ == "__main__":
    main()
