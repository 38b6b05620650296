"""Drive the receding-horizon replanner from Python: the paper's simulation 2, then one horizon solve by hand.

Run from the repository root:  python examples/replan_dynamic.py [out_dir]
Units: mm, rad, s.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import crtraj

ROOT = Path(__file__).resolve().parent.parent
out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out") / "replan-example"

# 1. The whole closed loop: planner reference, horizon NLP, tracking controller, verified moves.
problem = crtraj.Problem.load(ROOT / "problems" / "paper_dynamic.toml")
loop = crtraj.ClosedLoop.from_problem(problem)  # safety=False would switch the collision-free terms off
run = loop.run()
print(run.summary_line())
paths = crtraj.write_run(run, loop, out, problem=problem, html=False)  # html=True also writes run.html
print("wrote", paths["json"], paths["png"])

# Per-step records are plain arrays: time (s), actual configuration, actuation (mm), clearance (mm) ...
k = int(np.argmin(run.clearance[1:])) + 1
print(f"closest approach at t = {run.t[k]:.1f} s: clearance {run.clearance[k]:.2f} mm, cables {run.q[k].round(2)}")

# 2. One horizon solve by hand, with the loop's replanner (built once; obstacles and reference are parameters).
rp, scene = loop.replanner, loop.scene
x0 = run.x[10]
reference = run.x[11 : 11 + rp.N]  # e.g. where the robot went next
res = rp.solve(x0, reference, rp.obstacles_from_scene(scene, t0=run.t[10]), x_prev=run.x[9])
print(
    f"horizon NLP: {res.status} ({res.solver_status}), {res.iterations} iterations, {res.wall_time * 1e3:.2f} ms, "
    f"next configuration {res.configs[0].round(3)}"
)
