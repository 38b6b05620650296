"""Retiming of sim-1 plans (problems/paper_static.toml) within the actuator limits (issue 13, item 1).

For each seed: the c-space plan (edges timed within max_speed and the actuators' speed limits),
then `crtraj.app.plan.retime_result` (closed-form rest-to-rest law along the verified polyline,
sampled at the stream rate). Reported side by side: the planner's timing (old) and the retimed
one (new): duration, and the largest actuator velocity and acceleration as fractions of the full
limits, measured as the streamer samples the motion (100 Hz, finite differences from rest). The
retiming time is the median wall time of `crtraj.planning.retime.retime` + sampling per path;
beside it, toppra on the same rest-to-rest problems (one TOPP-RA run per straight motion).

Run: python benchmarks/retime.py [--seeds 10] [--repeat 20]
"""

from __future__ import annotations

import argparse
import datetime
import logging
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from crtraj.app.plan import _fractions, retime_result
from crtraj.hardware.actuators import Actuators
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import make_planner
from crtraj.planning.retime import keep_corners, min_durations, motion_limits, retime, toppra_durations
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
RATE = 100.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    logging.disable(logging.WARNING)  # toppra logs every run
    problem = Problem.load(ROOT / "problems" / "paper_static.toml")
    model = Model(problem.robot)
    act = Actuators.from_robot(problem.robot)
    limits = act.rate_limits(problem.robot)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    planner = make_planner(model, scene, options, rate_limits=limits)
    usable = limits.scaled(options.limit_fraction)
    metric = BodyMetric(problem.robot, options.max_speed)
    task = problem.require_task()
    print(f"# retime benchmark, {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# {platform.node()} {platform.machine()} {platform.processor() or ''} python {platform.python_version()}")
    print(f"# limit_fraction {options.limit_fraction}, max_speed {options.max_speed} mm/s, rate {RATE:g} Hz")
    print(
        "seed  corners | old: dur_s  v_frac  a_frac | new: dur_s  v_frac  a_frac | retime_ms  toppra_ms  toppra/closed"
    )
    times, tops, ratios = [], [], []
    for seed in range(1, args.seeds + 1):
        r0 = planner.plan(task.goal, start_tip=task.start, seed=seed, goal_tolerance=task.goal_tolerance)
        if not r0.is_success():
            print(f"{seed:4d}  plan failed: {r0.status}")
            continue
        old = _fractions(r0, act, RATE)
        r1, new = retime_result(r0, planner.validator, options, act, limits, RATE)
        runs = []
        for _ in range(args.repeat):
            t1 = time.perf_counter()
            retime(r0.configs, usable, metric, t0=float(r0.t[0]), period=1.0 / RATE).sample()
            runs.append(time.perf_counter() - t1)
        t1 = time.perf_counter()
        td = toppra_durations(r0.configs, usable, metric)
        t_top = time.perf_counter() - t1
        P = r0.configs[keep_corners(r0.configs)]
        closed = min_durations(*motion_limits(np.diff(P, axis=0), usable, metric))
        ratio = float(td.sum() / closed.sum())
        times.append(statistics.median(runs))
        tops.append(t_top)
        ratios.append(ratio)
        print(
            f"{seed:4d}  {len(P):7d} | {r0.duration:10.2f}  {old['max_velocity_fraction']:6.2f}  "
            f"{old['max_acceleration_fraction']:6.2f} | {r1.duration:10.2f}  {new['max_velocity_fraction']:6.2f}  "
            f"{new['max_acceleration_fraction']:6.2f} | {times[-1] * 1e3:9.2f}  {t_top * 1e3:9.1f}  {ratio:13.4f}"
        )
    if times:
        print(
            f"median retime {statistics.median(times) * 1e3:.2f} ms per path (target <= 5 ms); "
            f"toppra {statistics.median(tops) * 1e3:.1f} ms; toppra duration / closed form "
            f"{min(ratios):.4f}..{max(ratios):.4f}"
        )


if __name__ == "__main__":
    main()
