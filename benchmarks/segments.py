"""Planning and replanning time against the number of segments (robots cdsr1..cdsr4, issue 15).

For each robot, its static problem is planned with the default planner (configuration-space RRT-Connect
after the safe goal IK) for several seeds, and its dynamic problem is run in closed loop with the
receding-horizon replanner for several seeds. Printed per robot: configuration size, planning wall time
(median and spread over the seeds, and the goal-IK share), and per replanning iteration the median and
p90 wall time of the whole iteration and of the horizon NLP alone, plus whether every run arrived without
a D_sf breach. The tasks differ per robot (each problem file is drawn for its robot), so the columns
compare how the methods scale with the configuration size, not the difficulty of one task.

cdsr2 uses the paper's own problems (paper_static.toml, paper_dynamic.toml).

Run: python benchmarks/segments.py [--seeds 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners._registry import make_planner
from crtraj.planning.steer import SteerOptions
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PROBLEMS = {
    1: ("cdsr1_static.toml", "cdsr1_dynamic.toml"),
    2: ("paper_static.toml", "paper_dynamic.toml"),
    3: ("cdsr3_static.toml", "cdsr3_dynamic.toml"),
    4: ("cdsr4_static.toml", "cdsr4_dynamic.toml"),
}


def plan_times(path: Path, seeds: list[int]) -> dict:
    """Wall time (s) of planning the static problem, per seed, and the goal IK's share."""
    problem = Problem.load(path)
    task = problem.require_task()
    model = Model(problem.robot)
    scene = Scene.from_table(problem.section("scene"))
    planner = make_planner(
        model, scene, problem.options(PlannerOptions, "planner"), problem.options(SteerOptions, "steer")
    )
    planner.plan(task.goal, start_tip=task.start, t0=0.0, seed=10_000, goal_tolerance=task.goal_tolerance, scene=scene)
    times, ik, ok = [], [], 0
    for seed in seeds:
        t0 = time.perf_counter()
        res = planner.plan(
            task.goal, start_tip=task.start, t0=0.0, seed=seed, goal_tolerance=task.goal_tolerance, scene=scene
        )
        times.append(time.perf_counter() - t0)
        ik.append(res.timings.get("goal_ik", float("nan")))
        ok += int(res.is_success())
    return {"nx": problem.robot.nx, "plan": np.array(times), "goal_ik": np.array(ik), "plan_ok": ok}


def replan_times(path: Path, seeds: list[int]) -> dict:
    """Per-iteration wall times (s) of the closed loop over all seeds, and arrivals without a breach."""
    problem = Problem.load(path)
    its, nlp, ok, arrive = [], [], 0, []
    for seed in seeds:
        run = ClosedLoop.from_problem(problem, seed=seed).run()
        its.append(run.iter_time)
        nlp.append(run.nlp_time)
        ok += int(run.is_success())
        arrive.append(float(run.t[-1]))
    return {"iter": np.concatenate(its), "nlp": np.concatenate(nlp), "replan_ok": ok, "arrive": np.array(arrive)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="seeds per robot and problem (default 3)")
    args = ap.parse_args()
    seeds = list(range(1, args.seeds + 1))
    load = os.getloadavg()
    print(
        f"# benchmarks/segments.py, {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.node()} "
        f"({platform.machine()}, {os.cpu_count()} CPUs), load {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; "
        f"{len(seeds)} seeds each"
    )
    print()
    print(
        "| segments | nx | plan median (min-max) s | goal IK median s | plans ok | replan iteration median / p90 ms "
        "| NLP median / p90 ms | runs ok | arrival median s |"
    )
    print("|---:|---:|---|---:|---:|---|---|---:|---:|")
    for n, (static, dynamic) in PROBLEMS.items():
        p = plan_times(ROOT / "problems" / static, seeds)
        r = replan_times(ROOT / "problems" / dynamic, seeds)
        pl, ms = p["plan"], 1e3  # ms per s
        it = f"{ms * np.median(r['iter']):.1f} / {ms * np.percentile(r['iter'], 90):.1f}"
        nlp = f"{ms * np.median(r['nlp']):.1f} / {ms * np.percentile(r['nlp'], 90):.1f}"
        print(
            f"| {n} | {p['nx']} | {np.median(pl):.2f} ({pl.min():.2f}-{pl.max():.2f}) | {np.median(p['goal_ik']):.2f} "
            f"| {p['plan_ok']}/{len(seeds)} | {it} | {nlp} | {r['replan_ok']}/{len(seeds)} "
            f"| {np.median(r['arrive']):.1f} |",
            flush=True,
        )
    load = os.getloadavg()
    print(f"\nload at the end {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")


if __name__ == "__main__":
    main()
