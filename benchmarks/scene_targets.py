"""Issue 39's targets, one run: a box as a box against the same box as spheres (planning and the replan step), and
mesh scenes of about 10k and 100k triangles (grid build, planning, replan step, checker throughput).

The task is problems/shapes_table_pipe.toml's (cdsr2, its start, goal and seed) in a scene of one obstacle across
the way: the box of benchmarks/scene_shapes.py, its best sphere cover within the solvers' 100 spheres (and how
many spheres a cover of 1 mm error would take), or a torus mesh (`trimesh.creation.torus`, major radius 60 mm,
minor 25 mm) of about 10k or 100k triangles at the box's place.

Figures: "plan" is `plan_problem` (cspace; wall time, median of --repeat); "replan step" is the horizon NLP's time
per step of one closed-loop run (`crtraj replan`'s loop with the examples' [replan] section: sqpmethod + daqp,
interpreted, no deadline; median, and steps over 4 ms); "grid" is the mesh's NLP grid built cold (an empty cache
folder) and again from the cache; "checker" is `StateValidityChecker.clearance` on 2,000 random configurations
(configurations per CPU second, median of --repeat) against one sphere of the torus's size for comparison.
Run: python benchmarks/scene_targets.py [--repeat 3] [--duration 10]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import tomlkit
import trimesh
from scene_shapes import checker_rate, sphere_cover

from crtraj.app.plan import plan_problem
from crtraj.control.loop import ClosedLoop
from crtraj.io.problem import Problem
from crtraj.world.geometry import Box, GridDistance, Mesh, MovingShape, Pose, load_triangles
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import MAX_OBSTACLES, Scene

ROOT = Path(__file__).resolve().parent.parent
PLACE = Pose((30.0, -10.0, 330.0), (0.9848078, 0.0, 0.0, 0.1736482))
REPLAN = {"horizon": 10, "dt": 0.1, "points": 16, "solver": "sqp", "qpsol": "daqp", "max_iter": 20}


def cover_count_at(ms: MovingShape, error: float) -> int:
    """Spheres in the cubic-cell grid cover of the box whose spheres reach at most `error` mm beyond it: a cell
    of side c has spheres of radius c sqrt(3) / 2, c (sqrt(3) - 1) / 2 beyond a face."""
    c = 2.0 * error / (np.sqrt(3.0) - 1.0)
    return int(np.prod(np.ceil(2.0 * np.asarray(ms.shape.half_extents) / c)))


def torus_file(folder: Path, triangles: int) -> Path:
    """A torus STL of about `triangles` triangles (2 major x minor sections)."""
    minor = max(8, round(np.sqrt(triangles / 4.0)))
    major = max(8, round(triangles / (2.0 * minor)))
    path = folder / f"torus_{2 * major * minor}.stl"
    trimesh.creation.torus(60.0, 25.0, major_sections=major, minor_sections=minor).export(path)
    return path


def _problem_with(scene: Scene, folder: Path, name: str, duration: float) -> Problem:
    """shapes_table_pipe.toml's task and options with `scene`, and the examples' [replan], written to folder."""
    doc = tomlkit.parse((ROOT / "problems" / "shapes_table_pipe.toml").read_text())
    doc["robot"] = str(ROOT / "problems" / "robots" / "cdsr2.toml")
    doc["scene"] = scene.to_dict()
    doc["replan"] = dict(REPLAN, step_deadline=0.0)
    doc["loop"] = {"duration": duration, "max_body_speed": 60.0}
    path = folder / f"{name}.toml"
    path.write_text(tomlkit.dumps(doc))
    return Problem.load(path)


def _plan(problem: Problem, repeat: int) -> tuple[float, object]:
    walls, run = [], None
    for _ in range(repeat):
        w = time.perf_counter()
        run = plan_problem(problem)
        walls.append(time.perf_counter() - w)
    return statistics.median(walls), run


def _replan(problem: Problem) -> tuple[float, int, int, str]:
    """(median NLP time per step s, steps over 4 ms, steps, the run's status) of one closed-loop run."""
    run = ClosedLoop.from_problem(problem).run()
    t = np.asarray(run.nlp_time)
    return float(np.median(t)), int(np.sum(t > 0.004)), len(t), f"{run.status}, {run.collisions} collisions"


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def box_part(base: Scene, folder: Path, repeat: int, duration: float) -> None:
    box = MovingShape(Box((60.0, 40.0, 35.0), PLACE))
    spheres, err = sphere_cover(box, MAX_OBSTACLES)
    need = cover_count_at(box, 1.0)
    print(f"# box {box.shape.half_extents} mm; a 1 mm cover takes {need} spheres (limit {MAX_OBSTACLES}); the best")
    print(f"# cover within the limit: {len(spheres)} spheres, {err:.2f} mm beyond the box")
    print("| obstacles | plan wall (s) | replan step median (ms) | steps > 4 ms | run |")
    print("|---|---|---|---|---|")
    for label, scene in (
        ("1 box", replace(base, shapes=(box,))),
        (f"{len(spheres)} spheres", replace(base, obstacles=tuple(spheres))),
    ):
        problem = _problem_with(scene, folder, label.replace(" ", "_"), duration)
        wall, run = _plan(problem, repeat)
        ok = "" if run.result.is_success() else " (plan failed)"
        med, late, n, status = _replan(problem)
        print(f"| {label}{ok} | {wall:.2f} | {med * 1e3:.1f} | {late} of {n} | {status} |")


def mesh_part(base: Scene, folder: Path, repeat: int, duration: float, sizes: tuple[int, ...]) -> None:
    print("| mesh | mesh load (s) | grid cold (s) | grid cached (s) | plan wall (s) | replan step median (ms) | "
          "steps > 4 ms | checker (configs / CPU s) | 1 sphere checker (configs / CPU s) | run |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for size in sizes:
        stl = torus_file(folder, size)
        t0 = time.perf_counter()
        mesh = Mesh(load_triangles(stl, "mesh"), 4.0, PLACE, "torus", str(stl))
        load = time.perf_counter() - t0
        kept = os.environ.get("CRTRAJ_CACHE_DIR")
        with tempfile.TemporaryDirectory() as cache:
            os.environ["CRTRAJ_CACHE_DIR"] = cache  # an empty cache: the cold build, then the cached one
            t0 = time.perf_counter()
            GridDistance(mesh)
            cold = time.perf_counter() - t0
            t0 = time.perf_counter()
            GridDistance(mesh)
            warm = time.perf_counter() - t0
        if kept is None:
            del os.environ["CRTRAJ_CACHE_DIR"]
        else:
            os.environ["CRTRAJ_CACHE_DIR"] = kept
        scene = replace(base, shapes=(MovingShape(mesh),))
        problem = _problem_with(scene, folder, f"torus_{size}", duration)
        wall, run = _plan(problem, repeat)
        ok = "" if run.result.is_success() else " (plan failed)"
        med, late, n, status = _replan(problem)
        rate = checker_rate(run, problem.options(Scene, "scene"), repeat)
        ball = replace(base, obstacles=(Obstacle(PLACE.position, 85.0),))
        rate1 = checker_rate(run, ball, repeat)
        print(f"| {len(mesh.triangles)} triangles{ok} | {load:.2f} | {cold:.2f} | {warm:.2f} | {wall:.2f} | "
              f"{med * 1e3:.1f} | {late} of {n} | {rate:.0f} | {rate1:.0f} | {status} |")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--duration", type=float, default=20.0, help="s of each closed-loop run at most")
    ap.add_argument("--sizes", type=int, nargs="*", default=[10_000, 100_000], help="mesh triangles")
    ap.add_argument("--skip-box", action="store_true")
    args = ap.parse_args()
    base = replace(Problem.load(ROOT / "problems" / "shapes_table_pipe.toml").options(Scene, "scene"), shapes=())
    print(f"# scene_targets  {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC")
    print(f"# machine: {platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs, {platform.system()}")
    print(f"# load before: {_load()}")
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_box:
            box_part(base, Path(tmp), args.repeat, args.duration)
        mesh_part(base, Path(tmp), args.repeat, args.duration, tuple(args.sizes))
    print(f"# load after: {_load()}")


if __name__ == "__main__":
    main()
