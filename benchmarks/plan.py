"""Planning time, interpreted (old) against compiled (new) validity, with OMPL over the same checker.

Sections (each prints the old and the new path side by side, measured in this one run):

1. Simulation 1 (problems/paper_static.toml): the default planner (cspace) with the interpreted CasADi
   validity checks (``[planner.check] compiled = false``, the old path) and with the compiled kernel
   (`crtraj.planning.compiled_validity`, the new path): success, median, p90 over the seeds, and
   whether both paths gave identical plans. Targets (issue 14): median <= 15 ms, p90 <= 30 ms.
   Beside it, optionally, the paper's task-space RRT* (`--rrtstar-seeds`).
2. OMPL's RRTConnect and RRTstar on the same query and seeds, over the same compiled validator, timed
   to their FIRST solution (goal IK included, no simplification): crtraj's median as a ratio of theirs.
3. Table I scenes (`crtraj.bench.scenarios`, moving obstacles) at 7 obstacles: cspace median, old and
   new. Target: new median <= 30 ms.
4. Scaling: plan time against the obstacle count (1, 3, 7, 15, 31 spheres, Table I scenes) and the
   segment count (2, 3, 4: cdsr2's 400 mm split into that many segments, 7 obstacles), old and new;
   the plot goes to docs/scaling_plan.png (`--plot`).
5. Loaders: the same compiled batched backbone FK called through ctypes on numpy buffers (the one
   crtraj uses) and through ``casadi.external`` + ``map`` on CasADi's buffer API.

Every plan time is the planner's own wall time for one query (`PlanResult.timings["total"]`), the
planner built once and warmed up by one untimed query, and beside it the process CPU time of the query
(`time.process_time`: on a machine shared with other jobs it moves far less with their load than wall
time does; the scaling section and its plot use it); every success of sections 1-2 is re-checked
independently (200 backbone points, every 10 ms of the timed path, numpy distances to the spheres).
The compiled kernels come from the build cache (built before timing starts).

Run: python benchmarks/plan.py [--seeds 20] [--ompl-seeds 10] [--table1 20] [--scaling 10] [--plot PATH]
     [--rrtstar-seeds 0] [--skip-ompl]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np

from crtraj.bench.scenarios import ScenarioGenerator, ScenarioOptions
from crtraj.core.build_cache import BuildCache
from crtraj.core.fileio import read_toml
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot, Segment
from crtraj.planning.compiled_validity import ValidityKernel, kernel_functions
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import make_planner
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
MODES = (("old (interpreted)", False), ("new (compiled)", True))


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
    """'median / p90 ms' of plan times (s)."""
    return f"{statistics.median(times) * 1e3:7.1f} / {np.percentile(times, 90) * 1e3:6.1f} ms"


def sim1_queries(planner, problem: Problem, model: Model, scene: Scene, seeds: range, stop: StopCondition) -> dict:
    """Plan sim 1 for every seed (after one untimed warm-up): times, results, independent checks."""
    task = problem.task
    planner.plan(task.goal, start_tip=task.start, seed=10_000, stop=stop, goal_tolerance=task.goal_tolerance)
    times, cpu, results, verified = [], [], [], 0
    for seed in seeds:
        c0 = time.process_time()
        res = planner.plan(task.goal, start_tip=task.start, seed=seed, stop=stop, goal_tolerance=task.goal_tolerance)
        cpu.append(time.process_time() - c0)
        times.append(res.timings["total"])
        results.append(res)
        if res.is_success():
            verified += dense_clearance(model, scene, res.t, res.configs) >= 0.0
    ok = sum(r.is_success() for r in results)
    return {"times": times, "cpu": cpu, "results": results, "success": ok, "verified": verified}


def section_sim1(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, n: int) -> dict:
    print("\n== 1. simulation 1 (paper_static), cspace: old vs new validity ==")
    rows = {}
    for label, compiled in MODES:
        planner = make_planner(model, scene, options.with_(algorithm="cspace", check={"compiled": compiled}))
        rows[label] = sim1_queries(planner, problem, model, scene, range(n), options.stop())
    old, new = rows[MODES[0][0]], rows[MODES[1][0]]
    same = all(
        np.array_equal(a.configs, b.configs) and np.array_equal(a.t, b.t)
        for a, b in zip(old["results"], new["results"], strict=True)
    )
    print(f"{'path':<20s} {'success':>9s} {'wall median / p90':>22s} {'CPU median / p90':>22s}  verified")
    for label, r in rows.items():
        print(
            f"{label:<20s} {r['success']:>4d}/{n:<4d} {summary(r['times']):>22s} {summary(r['cpu']):>22s}  "
            f"{r['verified']}/{r['success']}"
        )
    speed = statistics.median(old["times"]) / statistics.median(new["times"])
    speed_cpu = statistics.median(old["cpu"]) / statistics.median(new["cpu"])
    print(f"speed-up (median): wall {speed:.1f}x, CPU {speed_cpu:.1f}x; identical plans for every seed: {same}")
    print("targets: new median <= 15 ms, p90 <= 30 ms")
    return rows


def section_ompl(problem: Problem, model: Model, scene: Scene, options: PlannerOptions, new: dict, n: int) -> None:
    print("\n== 2. OMPL over the same compiled validator, time to FIRST solution (goal IK included) ==")
    try:
        from crtraj.planning.ompl import OMPLPlanner, import_ompl

        import_ompl()
    except Exception as exc:  # the bench extra is optional
        print(f"skipped: {exc}")
        return
    task = problem.task
    ours, ours_cpu = statistics.median(new["times"][:n]), statistics.median(new["cpu"][:n])
    head = f"{'planner':<22s} {'success':>9s} {'wall median / p90':>22s} {'CPU median / p90':>22s}"
    print(f"{head}  crtraj / it (wall, CPU)")
    o = options.with_(check={"compiled": True}, time_limit=10.0)
    for algo in ("RRTConnect", "RRTstar"):
        planner = OMPLPlanner(PlanningContext(model, scene, o), algorithm=algo, simplify=False)
        stop = StopCondition(time_limit=10.0, first_solution=True)
        starts = [r.configs[0] for r in new["results"][:n]]
        planner.plan(task.goal, start_config=starts[0], seed=10_000, stop=stop, goal_tolerance=task.goal_tolerance)
        times, cpu, ok = [], [], 0
        for seed, xs in enumerate(starts):
            c0 = time.process_time()
            res = planner.plan(task.goal, start_config=xs, seed=seed, stop=stop, goal_tolerance=task.goal_tolerance)
            cpu.append(time.process_time() - c0)
            times.append(res.timings["total"])
            ok += res.is_success() and dense_clearance(model, scene, res.t, res.configs) >= 0.0
        r_wall, r_cpu = ours / statistics.median(times), ours_cpu / statistics.median(cpu)
        print(f"OMPL {algo:<17s} {ok:>4d}/{n:<4d} {summary(times):>22s} {summary(cpu):>22s}  {r_wall:.3f}, {r_cpu:.3f}")


def table1_times(model: Model, options: PlannerOptions, count: int, n: int, compiled: bool) -> tuple[list, int, list]:
    """cspace plan wall times (s), successes and CPU times (s) on the first n Table I scenes with `count` obstacles."""
    gen = ScenarioGenerator(model, ScenarioOptions(seed=0))
    scenes = [gen.generate(count, i) for i in range(n)]
    o = options.with_(algorithm="cspace", check={"compiled": compiled})
    planner = make_planner(model, Scene(), o, max_obstacles=8)
    warm = ScenarioGenerator(model, ScenarioOptions(seed=99)).generate(count, 0)
    stop = StopCondition(time_limit=5.0, max_iterations=options.max_iterations, first_solution=True)
    planner.plan(warm.goal, start_config=warm.start, scene=warm.scene, stop=stop, seed=0)
    times, cpu, ok = [], [], 0
    for i, sc in enumerate(scenes):
        c0 = time.process_time()
        res = planner.plan(sc.goal, start_config=sc.start, scene=sc.scene, stop=stop, seed=i)
        cpu.append(time.process_time() - c0)
        times.append(res.timings["total"])
        ok += res.is_success()
    return times, ok, cpu


def section_table1(model: Model, options: PlannerOptions, n: int) -> None:
    print(f"\n== 3. Table I scenes, 7 moving obstacles, cspace, {n} scenes ==")
    meds, cpus = [], []
    print(f"{'path':<20s} {'success':>9s} {'wall median / p90':>22s} {'CPU median / p90':>22s}")
    for label, compiled in MODES:
        times, ok, cpu = table1_times(model, options, 7, n, compiled)
        meds.append(statistics.median(times))
        cpus.append(statistics.median(cpu))
        print(f"{label:<20s} {ok:>4d}/{n:<4d} {summary(times):>22s} {summary(cpu):>22s}")
    print(
        f"speed-up (median): wall {meds[0] / meds[1]:.1f}x, CPU {cpus[0] / cpus[1]:.1f}x; target: new median <= 30 ms"
    )


def split_robot(robot: Robot, n_segments: int) -> Robot:
    """cdsr2 with its total length split into n_segments equal segments (same bending limit, alternating
    cable phase), for the segment-count scaling."""
    seg = robot.segments[0]
    length = robot.total_length / n_segments
    segs = tuple(Segment(length, seg.theta_max, (k % 2) * np.pi / 3) for k in range(n_segments))
    return replace(robot, name=f"cdsr2x{n_segments}", segments=segs, actuators=None)


def section_scaling(model: Model, options: PlannerOptions, n: int, plot: str | None) -> None:
    print(f"\n== 4. scaling: cspace CPU-time median over {n} Table I scenes, old / new (ms) ==")
    counts = (1, 3, 7, 15, 31)
    rows: dict[str, list[tuple[int, float, float]]] = {"obstacles": [], "segments": []}
    for m in counts:
        old = statistics.median(table1_times(model, options, m, n, False)[2])
        new = statistics.median(table1_times(model, options, m, n, True)[2])
        rows["obstacles"].append((m, old, new))
        print(f"{m:>3d} obstacles (2 segments):  {old * 1e3:8.1f} / {new * 1e3:7.1f}   {old / new:5.1f}x")
    for k in (2, 3, 4):
        mk = Model(split_robot(model.robot, k)) if k != 2 else model
        old = statistics.median(table1_times(mk, options, 7, n, False)[2])
        new = statistics.median(table1_times(mk, options, 7, n, True)[2])
        rows["segments"].append((k, old, new))
        print(f"{k:>3d} segments (7 obstacles):   {old * 1e3:8.1f} / {new * 1e3:7.1f}   {old / new:5.1f}x")
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
        ax.plot(x, [r[1] * 1e3 for r in rows[key]], "o-", label="interpreted (old)")
        ax.plot(x, [r[2] * 1e3 for r in rows[key]], "s-", label="compiled (new)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("cspace plan CPU time, median (ms)")
        ax.set_yscale("log")
        ax.set_xticks(x)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"crtraj plan time, Table I scenes ({n} per point), {datetime.date.today()}, {platform.node()}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def section_loaders(model: Model, check_points: int, n: int = 512, repeat: int = 200) -> None:
    print(f"\n== 5. loading the compiled code: batched backbone FK of {n} configurations ==")
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_static.toml"))
    ap.add_argument("--seeds", type=int, default=20, help="seeds of sim 1 (0..N-1)")
    ap.add_argument("--ompl-seeds", type=int, default=10, help="seeds of each OMPL planner (0 = skip)")
    ap.add_argument("--table1", type=int, default=20, help="Table I scenes at 7 obstacles (0 = skip)")
    ap.add_argument("--scaling", type=int, default=0, help="scenes per scaling point (0 = skip)")
    ap.add_argument("--plot", default=None, help="write the scaling plot here (e.g. docs/scaling_plan.png)")
    ap.add_argument("--rrtstar-seeds", type=int, default=0, help="seeds of the paper's task-space RRT* (0 = skip)")
    ap.add_argument("--rrtstar-time-limit", type=float, default=10.0, help="s per RRT* query")
    args = ap.parse_args()

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

    rows = section_sim1(problem, model, scene, options, args.seeds)
    new = rows[MODES[1][0]]
    if args.ompl_seeds > 0:
        section_ompl(problem, model, scene, options, new, min(args.ompl_seeds, args.seeds))
    if args.rrtstar_seeds > 0:
        steer = problem.options(SteerOptions, "steer")
        p = make_planner(model, scene, options.with_(algorithm="rrtstar", time_limit=args.rrtstar_time_limit), steer)
        stop = StopCondition(
            time_limit=args.rrtstar_time_limit, max_iterations=options.max_iterations, first_solution=True
        )
        r = sim1_queries(p, problem, model, scene, range(args.rrtstar_seeds), stop)
        print(f"\ntask-space RRT* (paper's method): {r['success']}/{args.rrtstar_seeds} {summary(r['times'])}")
    print(f"paper (Python, i7-12700H): {paper_plan_time() * 1e3:.0f} ms")
    if args.table1 > 0:
        section_table1(model, options, args.table1)
    if args.scaling > 0:
        section_scaling(model, options, args.scaling, args.plot)
    section_loaders(model, options.check.points)
    print(
        f"\nload average at the end: {os.getloadavg()[0]:.1f} (a shared machine: the old/new ratios of one run "
        "carry the argument, absolute times move with the load)"
    )


if __name__ == "__main__":
    main()
