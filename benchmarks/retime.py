"""Retiming of sim-1 plans (problems/paper_static.toml) within the actuator limits (issue 13, item 1).

For each seed: the c-space plan (edges timed within max_speed and the actuators' speed limits),
then `crtraj.planning.pipeline.retime_result` (the phase-plane law along the smoothed curve through the
corners, verified, stopping at corners only where the curve fails; `crtraj.planning.retime.retime_curve`). Reported
side by side: the planner's timing (old; body: its largest body speed as streamed over max_speed),
the rest-to-rest law along the chords (chords: stops at every corner, the previous retiming) and the
retimed motion (new): duration, and the largest actuator velocity and acceleration as fractions of
the full limits, measured as the streamer samples the motion (100 Hz, finite differences from
rest). Times: the median wall time of the chord law (`retime` + sampling, closed form) per path, of
the whole curve retiming (`retime_curve`: the phase-plane law, sampling, verification) beside the same
with toppra as the law (tcurve: its time and duration), and of toppra on the chord law's
rest-to-rest problems (one TOPP-RA run per straight motion).

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

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.context import PlanningContext
from crtraj.planning.metric import BodyMetric
from crtraj.planning.options import PlannerOptions
from crtraj.planning.pipeline import executed_fractions, retime_result
from crtraj.planning.planners._registry import BUILTIN
from crtraj.planning.retime import (
    keep_corners,
    min_durations,
    motion_limits,
    retime,
    retime_curve,
    toppra_durations,
)
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
    context = PlanningContext.build(model, scene, options)
    planner = BUILTIN.create(options.algorithm, context)
    usable = limits.scaled(options.limit_fraction)
    metric = BodyMetric(problem.robot, options.max_speed)
    task = problem.require_task()
    print(f"# retime benchmark, {datetime.datetime.now().isoformat(timespec='seconds')}")
    print(f"# {platform.node()} {platform.machine()} {platform.processor() or ''} python {platform.python_version()}")
    print(f"# limit_fraction {options.limit_fraction}, max_speed {options.max_speed} mm/s, rate {RATE:g} Hz")
    print(
        "seed  corners | old: dur_s  v_frac  a_frac  body | chords: dur_s | new: dur_s  v_frac  a_frac  stops "
        "| chord_ms  curve_ms  tcurve_ms tcurve_dur_s  toppra_ms  toppra/closed"
    )
    times, curve_times, tcurve_times, tops, ratios, rows = [], [], [], [], [], []
    for seed in range(1, args.seeds + 1):
        r0 = planner.plan(task.goal, start_tip=task.start, seed=seed, goal_tolerance=task.goal_tolerance)
        if not r0.is_success():
            print(f"{seed:4d}  plan failed: {r0.status}")
            continue
        old = executed_fractions(r0, act.limits, context, RATE)
        _, sent = SetpointPath.from_actuation(r0.t, r0.cables, act).sample(RATE)
        body = np.max(metric.motion_bound(np.diff(problem.robot.config(act.actuation(sent)), axis=0))) * RATE
        r1, new = retime_result(r0, planner.validator, context, act.limits, RATE)
        # the curve retiming itself, by the phase-plane pass (crtraj's) and by toppra (the reference)
        per = {}
        for method in ("phase", "toppra"):
            runs = []
            for _ in range(max(1, args.repeat // 4)):
                t1 = time.perf_counter()
                ct = retime_curve(r0.configs, usable, metric, planner.validator, t0=float(r0.t[0]),
                                  period=1.0 / RATE, method=method)  # fmt: skip
                runs.append(time.perf_counter() - t1)
            per[method] = (statistics.median(runs), ct)
        curve_times.append(per["phase"][0])
        tcurve_times.append(per["toppra"][0])
        tcurve = per["toppra"][1]
        runs = []
        for _ in range(args.repeat):
            t1 = time.perf_counter()
            chords = retime(r0.configs, usable, metric, t0=float(r0.t[0]), period=1.0 / RATE)
            chords.sample()
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
        stops = new["outcome"].split("(")[-1].split(" of")[0] if "curve" in new["outcome"] else "all"
        rows.append((r0.duration, chords.duration, r1.duration))
        print(
            f"{seed:4d}  {len(P):7d} | {r0.duration:10.2f}  {old['max_velocity_fraction']:6.2f}  "
            f"{old['max_acceleration_fraction']:6.2f}  {body / options.max_speed:4.2f} | {chords.duration:13.2f} | "
            f"{r1.duration:10.2f}  {new['max_velocity_fraction']:6.2f}  {new['max_acceleration_fraction']:6.2f}  "
            f"{stops:>5s} | {times[-1] * 1e3:8.2f}  {curve_times[-1] * 1e3:8.1f}  {tcurve_times[-1] * 1e3:9.1f} "
            f"{tcurve.duration if tcurve is not None else float('nan'):12.2f}  {t_top * 1e3:9.1f}  {ratio:13.4f}"
        )
    if times:
        old_d, chord_d, new_d = (np.array(c) for c in zip(*rows, strict=True))
        print(
            f"median per path: chord law {statistics.median(times) * 1e3:.2f} ms; curve retiming (phase-plane pass, "
            f"the default) {statistics.median(curve_times) * 1e3:.1f} ms (target <= 5 ms); the same with toppra "
            f"{statistics.median(tcurve_times) * 1e3:.1f} ms; toppra per chord law {statistics.median(tops) * 1e3:.1f} "
            f"ms; toppra duration / closed form {min(ratios):.4f}..{max(ratios):.4f}"
        )
        print(
            f"duration new / old: median {np.median(new_d / old_d):.3f} ({np.min(new_d / old_d):.3f}.."
            f"{np.max(new_d / old_d):.3f}); new / chords: median {np.median(new_d / chord_d):.3f} "
            f"({np.min(new_d / chord_d):.3f}..{np.max(new_d / chord_d):.3f})"
        )


if __name__ == "__main__":
    main()
