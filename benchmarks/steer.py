"""Steer-step benchmark: 200 seeded problems in the paper's simulation-1 scene, old paths and compiled C side by side.

Each problem is a planner-like steer: a random configuration of cdsr2 whose
body keeps the safety distance, and a target 5-50 mm from its tip, inside
the workspace and outside every obstacle's keep-out sphere. Every solver
runs the same problems (after a short warm-up); per-steer wall times are
printed as median and p90 next to the paper's 0.47 s per IK solve. Every result
the solver calls safe is re-checked here independently: 200 backbone points
against the scene's spheres ("dense unsafe": the body enters a sphere; "D_sf
dips": closer than D_sf between the constrained points, allowed by design).

The compiled rows ([steer] compiled = true) generate C for the whole step
(predictor, sqpmethod with qrqp or daqp, re-check quantities), compile it once
into the solver cache and call it through ctypes; their build time is the
first build (a cached run loads in well under a second).

    /work/venv/bin/python benchmarks/steer.py                 # all solvers
    /work/venv/bin/python benchmarks/steer.py --no-jit        # skip the jit builds (~10-30 s each)
    /work/venv/bin/python benchmarks/steer.py --only compiled # just the compiled rows
    /work/venv/bin/python benchmarks/steer.py --json out/bench_steer.json
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time
from pathlib import Path

import casadi as ca
import numpy as np

from crtraj.core.fileio import atomic_write_json
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.steer import SteerOptions
from crtraj.planning.steer._solver import SteerSolver
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PAPER_IK_S = 0.47  # reference/paper_results.toml [static] ik_solve_s


def make_problems(model: Model, scene: Scene, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n (x_prev, target) pairs: safe starts, targets 5-50 mm away in free workspace."""
    rng = np.random.default_rng(seed)
    lo, hi = model.robot.config_box()
    starts, targets = [], []
    while len(starts) < n:
        X = rng.uniform(0.5 * lo, 0.5 * hi, size=(400, model.nx))
        X[:, -1] = rng.uniform(lo[-1], hi[-1], size=400)
        ok = (model.robot.limit_violation(X) <= 0) & (scene.clearance(model, X, 0.0) > 0)
        X = X[ok]
        tips = model.tip_position(X)
        d = rng.normal(size=tips.shape)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        T = tips + d * rng.uniform(5.0, 50.0, size=(len(X), 1))
        free = (scene.clearance_points(T[:, None, :], 0.0, inflate=model.robot.body_radius) > 0) & scene.in_workspace(T)
        good = free & scene.in_workspace(tips)
        starts.extend(X[good])
        targets.extend(T[good])
    return np.array(starts[:n]), np.array(targets[:n])


def dense_check(model: Model, scene: Scene, results: list) -> tuple[int, int]:
    """(unsafe, D_sf dips) among the results called safe, from 200 backbone points against the spheres at
    t = 0, computed here independently of the solver's re-check. unsafe: the body (with its radius) enters
    a sphere. D_sf dips: it keeps out of the sphere but comes closer than D_sf between the constrained
    points (allowed by design: D_sf absorbs the chord and sagitta, see crtraj/planning/steer/_solver.py)."""
    safe = [r for r in results if r.safe]
    if not safe:
        return 0, 0
    P = model.points(np.array([r.x for r in safe]), 200)  # (n, 200, 3)
    c, rad = scene.states(0.0)
    d = np.linalg.norm(P[:, :, None, :] - np.asarray(c)[None, None], axis=-1) - np.asarray(rad)[None, None]
    gap = d.min(axis=(1, 2)) - model.robot.body_radius
    return int(np.sum(gap < -1e-6)), int(np.sum(gap < scene.safety_distance - 1e-6))


def run(label: str, solver: SteerSolver, scene: Scene, X: np.ndarray, T: np.ndarray, build_s: float) -> dict:
    for k in range(min(5, len(X))):  # warm-up: first-call allocations
        solver.solve(X[k], T[k], scene)
    solver.reset_warm_start()
    times, cpu, results = [], [], []
    for k in range(len(X)):
        t0, c0 = time.perf_counter(), time.process_time()
        r = solver.solve(X[k], T[k], scene)
        cpu.append(time.process_time() - c0)
        times.append(time.perf_counter() - t0)
        results.append(r)
    ms = np.array(times) * 1e3
    cpu_ms = np.array(cpu) * 1e3
    row = {
        "solver": label,
        "build_s": build_s,
        "median_ms": float(np.median(ms)),
        "p90_ms": float(np.percentile(ms, 90)),
        "cpu_median_ms": float(np.median(cpu_ms)),
        "cpu_p90_ms": float(np.percentile(cpu_ms, 90)),
        "success": float(np.mean([r.is_success() for r in results])),
        "reached": float(np.mean([r.reached for r in results])),
        "unsafe": int(sum(not r.safe for r in results)),
        "mean_iterations": float(np.mean([r.iterations for r in results])),
        "fallbacks": int(sum(r.solver == "sqp>ipopt" for r in results)),
    }
    row["dense_unsafe"], row["dense_dsf_dips"] = dense_check(solver.model, scene, results)
    row["speedup_vs_paper"] = PAPER_IK_S * 1e3 / row["median_ms"]
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", type=int, default=200, help="number of steer problems (default 200)")
    ap.add_argument("--seed", type=int, default=0, help="problem seed (default 0)")
    ap.add_argument("--no-jit", action="store_true", help="skip the jit-compiled fast path")
    ap.add_argument("--json", type=Path, default=None, help="also write the table as JSON")
    ap.add_argument("--only", default="", help="run only the rows whose label contains this text")
    args = ap.parse_args()

    prob = Problem.load(ROOT / "problems" / "paper_static.toml")
    scene = prob.options(Scene, "scene")
    base = prob.options(SteerOptions, "steer")
    model = Model(prob.robot)
    X, T = make_problems(model, scene, args.problems, args.seed)

    configs: list[tuple[str, int, dict]] = [
        ("ipopt (max 2 obstacles)", 2, {"solver": "ipopt"}),
        ("ipopt (max 8 obstacles)", 8, {"solver": "ipopt"}),
        ("sqp + daqp", 2, {"solver": "sqp"}),
        ("sqp + daqp (max 8 obstacles)", 8, {"solver": "sqp"}),
    ]
    if not args.no_jit:
        configs += [
            ("sqp + daqp + jit", 2, {"solver": "sqp", "jit": True}),
            ("sqp + daqp + jit (max 8 obstacles)", 8, {"solver": "sqp", "jit": True}),
        ]
    configs.append(("dls (eq. 17, no hard constraints)", 2, {"solver": "dls"}))
    configs += [
        ("sqp + qrqp, compiled C", 2, {"solver": "sqp", "qpsol": "qrqp", "compiled": True}),
        ("sqp + daqp, compiled C", 2, {"solver": "sqp", "compiled": True}),
    ]
    configs = [c for c in configs if args.only in c[0]]

    load0 = os.getloadavg()
    rows = []
    for label, max_obs, over in configs:
        opts = SteerOptions.from_table(_table({**base.to_dict(), **over}))
        t0 = time.perf_counter()
        solver = SteerSolver(model, max_obs, opts)
        build_s = time.perf_counter() - t0
        row = run(label, solver, scene, X, T, build_s)
        if solver.jit_message:
            row["jit"] = solver.jit_message
        if solver.compiled_message:
            row["compiled"] = solver.compiled_message
        rows.append(row)
        print(_fmt(row), flush=True)
    load1 = os.getloadavg()

    print()
    base_row = next((r for r in rows if r["solver"] == "sqp + daqp + jit"), None)
    for r in rows:
        if base_row is not None and "compiled" in r["solver"]:
            print(f"{r['solver']}: x{base_row['median_ms'] / r['median_ms']:.1f} faster than sqp + daqp + jit (median)")
    print(f"{args.problems} steer problems, sim-1 scene (2 spheres), seed {args.seed}")
    print(f"date {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC")
    print(f"paper: {PAPER_IK_S * 1e3:.0f} ms per IK solve; speed-up = paper / wall median")
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
        f"{load0[0]:.1f} -> {load1[0]:.1f} (shared machine: times include contention)"
    )
    print(f"casadi {ca.__version__}, numpy {np.__version__}")
    if args.json:
        atomic_write_json(
            args.json,
            {
                "problems": args.problems,
                "seed": args.seed,
                "paper_ik_s": PAPER_IK_S,
                "load": [load0, load1],
                "rows": rows,
            },
        )
        print(f"wrote {args.json}")
    return 0


def _table(d: dict):
    from crtraj.core.fields import Table

    return Table(d, "steer")


def _fmt(row: dict) -> str:
    return (
        f"{row['solver']:<36s} median {row['median_ms']:6.3f} ms  p90 {row['p90_ms']:6.3f} ms  "
        f"(cpu {row['cpu_median_ms']:6.3f} / {row['cpu_p90_ms']:6.3f})  "
        f"x{row['speedup_vs_paper']:4.0f} vs paper  success {100 * row['success']:5.1f}%  "
        f"reached {100 * row['reached']:5.1f}%  unsafe {row['unsafe']:2d}  it {row['mean_iterations']:4.1f}  "
        f"fallbacks {row['fallbacks']}  dense unsafe {row['dense_unsafe']} (D_sf dips {row['dense_dsf_dips']})  "
        f"build {row['build_s']:.1f} s"
    )


if __name__ == "__main__":
    raise SystemExit(main())
