"""Plan the paper's simulation 1 from Python: default planner, the paper's RRT*, and re-planning mid-way.

Run: python examples/plan_static.py   (writes out/plan_static.json; view it with `crtraj view out/plan_static.json`)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import crtraj

ROOT = Path(__file__).resolve().parent.parent

problem = crtraj.Problem.load(ROOT / "problems" / "paper_static.toml")
task = problem.require_task()
model = crtraj.Model(problem.robot)  # CasADi functions, built once
scene = problem.options(crtraj.Scene, "scene")
options = problem.options(crtraj.PlannerOptions, "planner")
context = crtraj.PlanningContext.build(model, scene, options)  # validity, the actuators' rate limits, kernels

# 1. an executable motion: the default planner (safe goal IK + RRT-Connect in configuration space +
#    shortcuts + spline), retimed within the actuator limits and verified
run = crtraj.plan_executable(
    context, task.goal, start_tip=task.start, seed=problem.seed, goal_tolerance=task.goal_tolerance
)
res = run.result
print(
    f"cspace: {run.status} in {res.timings['total'] * 1e3:.1f} ms, tip path {res.length:.0f} mm, "
    f"{len(res.t)} set-points over {run.duration:.1f} s, min clearance {run.min_clearance:.2f} mm beyond D_sf"
)
print(f"  start cables q = {np.round(res.cables[0], 2).tolist()} mm")
print(f"  goal  cables q = {np.round(res.cables[-1], 2).tolist()} mm")

# 2. the paper's method: RRT* over tip positions with the safety-constrained steer (eq. 17-18)
rrtstar = crtraj.BUILTIN.create("rrtstar", context, problem.options(crtraj.SteerOptions, "steer"))
res_star = rrtstar.plan(
    task.goal,
    start_tip=task.start,
    seed=problem.seed,
    goal_tolerance=task.goal_tolerance,
    stop=crtraj.StopCondition(time_limit=10.0, first_solution=True),
)
print(
    f"rrtstar: {res_star.status} in {res_star.timings['total']:.2f} s, tip path {res_star.length:.0f} mm "
    f"(the paper reports 2.41 s)"
)

# 3. re-plan from wherever the robot is at some time t0 (what a receding-horizon controller does)
planner = crtraj.BUILTIN.create("cspace", context)  # build once, query many times
t_mid = 0.5 * res.duration
x_now = res.config_at(t_mid)  # the configuration the motion commands at t_mid
again = planner.plan(task.goal, start_config=x_now, t0=t_mid, seed=1, goal_tolerance=task.goal_tolerance)
print(f"re-plan from t = {t_mid:.1f} s: {again.status}, arrives at t = {again.t[-1]:.1f} s")

# 4. the self-describing result file (robot, scene, options, per-waypoint t / tip / x / q / backbone / obstacles):
#    `crtraj plan` as a call (the same seed gives the same motion as step 1; the model is reused)
out = crtraj.plan_problem(problem, model=model).write(ROOT / "out" / "plan_static.json")
print(f"wrote {out}")
