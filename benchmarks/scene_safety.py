"""Issue 39's safety target: 0 unsafe successes over at least 200 plans across the four scene examples and seeds,
judged by an independent exact-distance check.

Each of problems/scene_{table_wall,plate_hole,bent_pipe,swinging_arm}.toml is planned (`crtraj plan`'s
`plan_problem`: cspace, retimed within the actuator limits) with seeds 0..N-1. Every success is then checked
apart from the planner: a fresh PCC model of the result's robot gives `--points` backbone points (evenly along
the arc) every 10 ms of the timed path (linear between waypoints, as the result's motion is), and each point's
distance to each shape at that time is measured exactly, without the planner's distance code or grid:

- mesh: trimesh's closest point on the triangles (`trimesh.triangles.closest_point`, Ericson's method), the
  triangles first split to edges of at most `SPLIT` mm (`trimesh.remesh.subdivide_to_size`: the same surface), for
  every triangle that could be nearest (centre within the nearest vertex's distance plus the largest triangle
  radius); points whose lower bound (nearest centre minus that radius) is beyond `CUTOFF` keep that bound;
- box: the same trimesh closest point on the 12 triangles of `trimesh.creation.box`, negative depth inside;
- sphere, half space: their definitions (|y| - r, n . y - offset); capsule and cylinder: the distance to the axis
  segment minus the radius, and the 2-D distance to the (radial, axial) rectangle.

A point whose lower bound is beyond `CUTOFF` (12 mm, above D_sf + body radius) cannot be unsafe, so the table's
smallest clearance is exact below CUTOFF - D_sf - body radius and reads ">= 4.00" above it.
Only the shapes' poses over time come from crtraj (`MovingShape.frame`: the motion is data). A success is unsafe
when some point comes closer than D_sf + body radius. Between neighbouring points (spacing h mm) the body may be up
to h/2 closer than at them; the table gives h/2 too.
Run: python benchmarks/scene_safety.py [--seeds 50] [--points 201]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from crtraj.app.plan import plan_problem
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
SCENES = ("scene_table_wall", "scene_plate_hole", "scene_bent_pipe", "scene_swinging_arm")
# mm: points surely farther than this from a mesh (or box) keep the lower bound; above D_sf + body radius (8 mm in
# the examples), so such a point is never unsafe, and the table's smallest clearance is exact below CUTOFF - 8 mm
CUTOFF = 12.0
SPLIT = 5.0  # mm: longest triangle edge of the meshes measured


class MeshDistance:
    """Distances (mm) from points to the triangles tri (T, 3, 3) (module docstring); the trees are built once."""

    def __init__(self, tri: np.ndarray) -> None:
        # split into triangles of edges at most SPLIT mm (midpoint subdivision: the same surface), so that few
        # triangles lie near any point
        tri = np.asarray(tri, dtype=float)
        v, f = trimesh.remesh.subdivide_to_size(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3), SPLIT)
        self.tri = v[f]
        centre = self.tri.mean(axis=1)
        self.rmax = float(np.linalg.norm(self.tri - centre[:, None, :], axis=2).max())
        self.centres = cKDTree(centre)
        self.vertices = cKDTree(self.tri.reshape(-1, 3))

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """(N,) distances of points y (N, 3)."""
        lower = self.centres.query(y)[0] - self.rmax
        out = lower.copy()
        near = np.flatnonzero(lower < CUTOFF)
        if not len(near):
            return out
        yn = y[near]
        upper = self.vertices.query(yn)[0]
        cand = self.centres.query_ball_point(yn, upper + self.rmax)
        rows = np.repeat(np.arange(len(near)), [len(c) for c in cand])
        faces = np.concatenate([np.asarray(c, dtype=int) for c in cand])
        d = np.linalg.norm(trimesh.triangles.closest_point(self.tri[faces], yn[rows]) - yn[rows], axis=1)
        best = np.full(len(near), np.inf)
        np.minimum.at(best, rows, d)
        out[near] = best
        return out


_MESHES: dict[int, MeshDistance] = {}


def mesh_distance(tri: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N,) distances (mm) from points y (N, 3) to the triangles tri (T, 3, 3), one `MeshDistance` per array."""
    key = id(tri)
    if key not in _MESHES:
        _MESHES[key] = MeshDistance(tri)
    return _MESHES[key](y)


_BOXES: dict[tuple[float, ...], np.ndarray] = {}


def _box_distance(half: np.ndarray, y: np.ndarray) -> np.ndarray:
    key = tuple(half.tolist())
    if key not in _BOXES:
        _BOXES[key] = np.asarray(trimesh.creation.box(extents=2.0 * half).triangles)
    d = mesh_distance(_BOXES[key], y)
    inside = np.all(np.abs(y) <= half, axis=1)
    return np.where(inside, -np.min(half - np.abs(y), axis=1), d)


def local_distance(shape, y: np.ndarray) -> np.ndarray:
    """(N,) signed distances (mm) of points y (N, 3) in the shape's frame at scale 1 (module docstring)."""
    kind = shape.kind
    if kind == "mesh":
        return mesh_distance(shape.triangles, y)
    if kind == "points":
        return cKDTree(shape.points).query(y)[0] - shape.radius
    if kind == "box":
        return _box_distance(np.asarray(shape.half_extents), y)
    if kind == "sphere":
        return np.linalg.norm(y, axis=1) - shape.radius
    if kind == "halfspace":
        return y @ np.asarray(shape.normal) - shape.offset
    half = 0.5 * shape.length
    if kind == "capsule":
        axis = np.stack([np.zeros(len(y)), np.zeros(len(y)), np.clip(y[:, 2], -half, half)], axis=1)
        return np.linalg.norm(y - axis, axis=1) - shape.radius
    if kind == "cylinder":
        q = np.stack([np.hypot(y[:, 0], y[:, 1]) - shape.radius, np.abs(y[:, 2]) - half], axis=1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    raise ValueError(f"no exact distance for shape kind {kind!r}")


def exact_clearance(scene: Scene, model: Model, t: np.ndarray, X: np.ndarray, points: int) -> float:
    """Smallest body clearance beyond D_sf (mm) over the configurations X (K, nx) at times t (K,) s."""
    P = model.points(X, points)  # (K, points, 3)
    best = np.inf
    for ms in scene.shapes:
        # a shape that neither moves nor breathes: every time sample's points at once
        steps = [np.arange(len(t))] if ms.static else [np.array([k]) for k in range(len(t))]
        for ks in steps:
            o, R, s = ms.frame(float(t[ks[0]]) + scene.time_origin)
            d = s * local_distance(ms.shape, (P[ks].reshape(-1, 3) - o) @ R / s)
            best = min(best, float(d.min()))
    return best - model.robot.body_radius - scene.safety_distance


def check_plan(result, scene: Scene, model: Model, points: int) -> float:
    """The plan's exact clearance beyond D_sf (mm), every 10 ms of its timed path."""
    t = np.append(np.arange(result.t[0], result.t[-1], 0.01), result.t[-1])
    X = np.stack([np.interp(t, result.t, result.configs[:, j]) for j in range(result.configs.shape[1])], axis=1)
    return exact_clearance(scene, model, t, X, points)


def run_scene(name: str, seeds: int, points: int) -> dict:
    """Plan scene `name` with seeds 0..seeds-1 and check every success; the row of the table."""
    problem = Problem.load(ROOT / "problems" / f"{name}.toml")
    scene = problem.options(Scene, "scene")
    model = Model(problem.robot)
    plan_s, check_s, clear, statuses = [], [], [], {}
    for seed in range(seeds):
        t1 = time.perf_counter()
        res = plan_problem(problem, seed=seed).result
        plan_s.append(time.perf_counter() - t1)
        statuses[str(res.status)] = statuses.get(str(res.status), 0) + 1
        if res.is_success():
            t1 = time.perf_counter()
            clear.append(check_plan(res, scene, model, points))
            check_s.append(time.perf_counter() - t1)
    h = model.robot.total_length / (points - 1)
    cap = CUTOFF - model.robot.body_radius - scene.safety_distance  # clearances above it are lower bounds
    return {
        "cap": cap,
        "scene": name,
        "plans": seeds,
        "successes": len(clear),
        "unsafe": int(sum(c < 0.0 for c in clear)),
        "min_clearance": min(clear) if clear else float("nan"),
        "half_spacing": h / 2.0,
        "plan_median_s": statistics.median(plan_s),
        "check_median_s": statistics.median(check_s) if check_s else float("nan"),
        "statuses": statuses,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50, help="seeds per scene (default 50: 200 plans)")
    ap.add_argument("--points", type=int, default=201, help="backbone points checked per time sample")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    a = ap.parse_args()
    print(f"# scene safety: {datetime.now(timezone.utc).isoformat(timespec='seconds')}, {platform.node()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()}")  # fmt: skip
    print(f"# python benchmarks/scene_safety.py --seeds {a.seeds} --points {a.points}")
    print("| scene | plans | successes | unsafe successes | min clearance beyond D_sf (mm) | h/2 (mm) | "
          "plan median (s) | check median (s) | statuses |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    total = unsafe = plans = 0
    for name in a.scenes:
        r = run_scene(name, a.seeds, a.points)
        total, unsafe, plans = total + r["successes"], unsafe + r["unsafe"], plans + r["plans"]
        st = ", ".join(f"{k} {v}" for k, v in sorted(r["statuses"].items()))
        low = r["min_clearance"]
        low_text = f"{low:.2f}" if low < r["cap"] else f">= {r['cap']:.2f}"
        row = [r["plans"], r["successes"], r["unsafe"], low_text, f"{r['half_spacing']:.2f}"]
        row += [f"{r['plan_median_s']:.2f}", f"{r['check_median_s']:.2f}", st]
        print(f"| {name} | " + " | ".join(str(v) for v in row) + " |", flush=True)
    print(f"# {unsafe} unsafe successes of {total} successes over {plans} plans; load {os.getloadavg()}")


if __name__ == "__main__":
    main()
