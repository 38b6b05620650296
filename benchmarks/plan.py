"""Planning time on the paper's simulation 1 (problems/paper_static.toml): crtraj vs the paper's 2.41 s.

Targets (issue 4): the default planner (cspace) solves 20 of 20 seeds with a
median plan time <= 50 ms. Beside it: the paper's own method, task-space
RRT* with the safety-constrained steer (crtraj.planning.rrt.RRTStar), to its
first solution as the paper measures it, and optionally task-space RRT.

Every reported plan time is the planner's own wall time for one query
(`PlanResult.timings["total"]`: start IK, goal IK, search, shortcuts,
smoothing, verification), with the planner built once and warmed up by one
untimed query. Every success is re-checked independently (200 backbone
points, every 10 ms of the timed path, numpy distances to the spheres).

Run: python benchmarks/plan.py [--seeds 20] [--rrtstar-seeds 10] [--rrtstar-time-limit 10] [--rrt-seeds 0]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import casadi as ca
import numpy as np

from crtraj.core.fileio import read_toml
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import make_planner
from crtraj.planning.steer import SteerOptions
from crtraj.planning.stop import StopCondition
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


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


def run(label: str, planner, problem: Problem, model: Model, scene: Scene, seeds: range, stop: StopCondition) -> dict:
    task = problem.task
    planner.plan(task.goal, start_tip=task.start, seed=10_000, stop=stop, goal_tolerance=task.goal_tolerance)
    times, lengths, clears, ok, verified = [], [], [], 0, 0
    for seed in seeds:
        res = planner.plan(task.goal, start_tip=task.start, seed=seed, stop=stop, goal_tolerance=task.goal_tolerance)
        times.append(res.timings["total"])
        if res.is_success():
            ok += 1
            c = dense_clearance(model, scene, res.t, res.configs)
            verified += c >= 0.0
            lengths.append(res.length)
            clears.append(c)
    n = len(seeds)
    return {
        "label": label,
        "runs": n,
        "success": ok,
        "verified": verified,
        "median_s": statistics.median(times),
        "p90_s": float(np.percentile(times, 90)),
        "min_s": min(times),
        "max_s": max(times),
        "median_length_mm": statistics.median(lengths) if lengths else float("nan"),
        "min_clearance_mm": min(clears) if clears else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_static.toml"))
    ap.add_argument("--seeds", type=int, default=20, help="seeds of the default planner (0..N-1)")
    ap.add_argument("--rrtstar-seeds", type=int, default=10, help="seeds of the paper's task-space RRT* (0 = skip)")
    ap.add_argument("--rrtstar-time-limit", type=float, default=10.0, help="s per RRT* query")
    ap.add_argument("--rrt-seeds", type=int, default=0, help="seeds of task-space RRT (0 = skip)")
    args = ap.parse_args()

    problem = Problem.load(args.problem)
    model = Model(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    steer = problem.options(SteerOptions, "steer")
    paper_s = paper_plan_time()
    print(
        f"machine: {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"casadi {ca.__version__}, numpy {np.__version__}"
    )
    print(f"problem: {problem.name} (start {problem.task.start.tolist()} -> goal {problem.task.goal.tolist()} mm)\n")

    rows = []
    t1 = time.perf_counter()
    cs = make_planner(model, scene, options.with_(algorithm="cspace"))
    print(f"cspace planner built in {time.perf_counter() - t1:.2f} s (once)")
    rows.append(run("cspace (default)", cs, problem, model, scene, range(args.seeds), options.stop()))
    for name, n_seeds in (("rrtstar", args.rrtstar_seeds), ("rrt", args.rrt_seeds)):
        if n_seeds <= 0:
            continue
        t1 = time.perf_counter()
        p = make_planner(model, scene, options.with_(algorithm=name, time_limit=args.rrtstar_time_limit), steer)
        print(f"{name} planner built in {time.perf_counter() - t1:.2f} s (once)")
        stop = StopCondition(
            time_limit=args.rrtstar_time_limit, max_iterations=options.max_iterations, first_solution=True
        )
        rows.append(
            run(
                f"task-space {name.upper().replace('STAR', '*')} (paper's method)",
                p,
                problem,
                model,
                scene,
                range(n_seeds),
                stop,
            )
        )

    print()
    head = (
        f"{'planner':<36s} {'success':>9s} {'median':>10s} {'p90':>10s} {'range':>19s} {'length':>9s} {'vs paper':>9s}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        print(
            f"{r['label']:<36s} {r['success']:>3d}/{r['runs']:<3d}   {r['median_s'] * 1e3:>7.1f} ms "
            f"{r['p90_s'] * 1e3:>7.1f} ms {r['min_s'] * 1e3:>7.1f}..{r['max_s'] * 1e3:<7.1f} ms "
            f"{r['median_length_mm']:>6.0f} mm {paper_s / r['median_s']:>7.0f}x"
        )
    print(f"{'paper (Python, i7-12700H)':<36s} {'':>9s} {paper_s * 1e3:>7.0f} ms")
    for r in rows:
        if r["verified"] != r["success"]:
            print(f"WARNING: {r['label']}: {r['success'] - r['verified']} successes failed the independent check")
    print(
        "\nTimes are one query each (planner built once, one untimed warm-up), measured on a machine shared with "
        "other jobs; 'vs paper' = paper's mean time / our median."
    )


if __name__ == "__main__":
    main()
