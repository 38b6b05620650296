"""A box as one box against the same box as spheres: planning time, checker throughput and clearance, one run.

The scene is one box of 120 x 80 x 70 mm turned 20 degrees about z, across the straight way from the start to
the goal of problems/shapes_table_pipe.toml (cdsr2), so that the plan has to go round it. As spheres, the box
is covered by a grid of nx x ny x nz spheres, each the sphere about its cell's centre through the cell's
corners, with the most cells within the solvers' 100-sphere limit (`crtraj.world.scene.MAX_OBSTACLES`); the
cover's error is how far it reaches beyond the box (the largest distance from the box of the cover's surface,
measured on 20,000 samples of it).

Figures: "plan" is `plan_problem` (cspace, the problem's seed; wall and CPU time of this process, median of
--repeat), "checker" is `StateValidityChecker.clearance` on 2,000 random configurations (configurations per
CPU second, median of --repeat), "clearance" is the plan's smallest body clearance beyond D_sf to the true box by
the brute-force distance (`crtraj.world.geometry.exact_min_clearance`, 100 backbone points every 10 ms).
Run: python benchmarks/scene_shapes.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.app.plan import plan_problem
from crtraj.io.problem import Problem
from crtraj.planning.validity import StateValidityChecker
from crtraj.world.geometry import Box, MovingShape, Pose, exact_min_clearance
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import MAX_OBSTACLES, Scene

ROOT = Path(__file__).resolve().parent.parent


def sphere_cover(ms: MovingShape, most: int) -> tuple[list[Obstacle], float]:
    """The box as a grid of spheres (each through its cell's corners), the grid with the most cells within
    `most`, cells as cubic as may be; and the cover's error (mm): how far the spheres reach beyond the box."""
    h = np.asarray(ms.shape.half_extents)
    best = None
    for nx in range(1, most + 1):
        for ny in range(1, most // nx + 1):
            nz = most // (nx * ny)
            if nz < 1:
                continue
            cell = 2.0 * h / np.array([nx, ny, nz])
            radius = 0.5 * float(np.linalg.norm(cell))
            if best is None or radius < best[0]:
                best = (radius, (nx, ny, nz), cell)
    radius, counts, cell = best
    o, r, _ = ms.frame(0.0)
    spheres = []
    for idx in np.ndindex(*counts):
        local = -h + (np.asarray(idx) + 0.5) * cell
        spheres.append(Obstacle(tuple(o + r @ local), radius))
    # error: sample the cover's surface, measure its distance from the box
    rng = np.random.default_rng(0)
    c = np.array([s.center for s in spheres])
    u = rng.normal(size=(20000, 3))
    pts = c[rng.integers(len(c), size=20000)] + radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    inside_others = np.linalg.norm(pts[:, None] - c[None], axis=2).min(axis=1) < radius - 1e-9
    err = float(np.max(ms.distance(pts[~inside_others], 0.0)))
    return spheres, err


def _plan(problem: Problem, scene: Scene, repeat: int) -> tuple[float, float, object]:
    walls, cpus, run = [], [], None
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        run = plan_problem(problem, scene=scene)
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus), run


def checker_rate(run: object, scene: Scene, repeat: int) -> float:
    checker = StateValidityChecker(run.model, scene)
    X = checker.limits.sample(np.random.default_rng(1), 2000)
    checker.clearance(X[:10], 0.0)
    rates = []
    for _ in range(repeat):
        c = time.process_time()
        checker.clearance(X, 0.0)
        rates.append(len(X) / max(time.process_time() - c, 1e-9))
    return statistics.median(rates)


def _clearance(run: object, box: MovingShape) -> float:
    t, x = np.asarray(run.result.t), np.asarray(run.result.configs)
    times = np.append(np.arange(t[0], t[-1], 0.01), t[-1])
    configs = np.stack([np.interp(times, t, x[:, j]) for j in range(x.shape[1])], axis=1)
    d = exact_min_clearance(box, run.model.points(configs, 100), times).min()
    return float(d) - run.model.robot.body_radius - run.scene.safety_distance


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    problem = Problem.load(ROOT / "problems" / "shapes_table_pipe.toml")
    full = problem.options(Scene, "scene")
    box = MovingShape(Box((60.0, 40.0, 35.0), Pose((30.0, -10.0, 330.0), (0.9848078, 0.0, 0.0, 0.1736482))))
    as_box = replace(full, shapes=(box,), obstacles=())
    spheres, err = sphere_cover(box, MAX_OBSTACLES)
    as_spheres = replace(full, shapes=(), obstacles=tuple(spheres))
    print(f"# scene_shapes  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC")
    print(f"# machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs, {platform.system()}")
    print(f"# load before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"# box: half extents {box.shape.half_extents} mm; sphere cover: {len(spheres)} spheres, error {err:.2f} mm")
    print("| obstacles | plan wall (s) | plan CPU (s) | checker (configs / CPU s) | clearance to the box (mm) |")
    print("|---|---|---|---|---|")
    for label, scene in (("1 box", as_box), (f"{len(spheres)} spheres", as_spheres)):
        wall, cpu, run = _plan(problem, scene, args.repeat)
        rate = checker_rate(run, scene, args.repeat)
        ok = "" if run.result.is_success() else " (plan failed)"
        clr = _clearance(run, box) if run.result.is_success() else math.nan
        print(f"| {label}{ok} | {wall:.2f} | {cpu:.2f} | {rate:.0f} | {clr:.2f} |")
    print(f"# load after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
