"""How the steer step and a replanning iteration grow with the obstacle count and the number of segments.

Robots: cdsr2 (2 segments) and cdsr2 extended to 3 and 4 segments by repeating its second segment.
Scenes: m spheres of radius 15 mm (m = 1, 3, 7, 15, 31, 100 with 2 segments; 7 with 3 and 4 segments),
seeded, placed around the robot clear of its start and goal bodies. The steer and the interpreted and
"all obstacles in the QP" replan columns stop at --old-up-to obstacles (default 31): past that their
one-off builds take minutes.

- steer: 40 seeded steer problems per scene (benchmarks/steer.py's generator), median wall time of
  `SteerSolver.solve` with sqpmethod + daqp interpreted, and with ``--compiled M``, the compiled C step
  for every scene of at most M obstacles (each new size is one C build; minutes on a loaded machine).
- replan: a 3 s closed-loop run (30 iterations) toward a goal configuration along the straight
  reference; median time per iteration and median horizon-NLP time (sqpmethod + daqp interpreted), and
  with ``--compiled-replan M`` the compiled horizon NLP as problems/paper_dynamic.toml runs it (its iteration
  cap per call and calls; no deadline, so every solve converges) for every scene of at most M
  obstacles (each new size is one C build of the horizon NLP, about a minute). That column puts every
  obstacle in the QP (``qp_obstacles = 0``, the previous path); the "broad" column is the same with the
  shipped ``qp_obstacles`` (``--broad-slots``, a list): a QP of at most that many obstacle slots, filled each
  step by the horizon's broad phase (`crtraj.control.horizon._broad`), every move still verified against every obstacle.

Writes docs/scaling_solvers.png (two panels: vs obstacles, vs segments) and prints the table with the
date, machine and load. Run: python benchmarks/scaling_solvers.py [--compiled 7] [--compiled-replan 31]
[--out docs/scaling_solvers.png] [--obstacles 1,7,31,100] [--segments 2] [--replan-only] (only the compiled
replan columns; issue 29's 31-to-1 ratio is printed at the end)
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._options import LoopOptions
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.steer import SteerOptions
from crtraj.planning.steer._solver import SteerSolver
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from steer import make_problems  # noqa: E402 - the steer benchmark's own problem generator

OBSTACLES = (1, 3, 7, 15, 31, 100)
SHIPPED = Problem.load(ROOT / "problems" / "paper_dynamic.toml")
SEGMENTS = (2, 3, 4)
SEG_OBSTACLES = 7


def robot_with(base, n: int):
    """cdsr2 with n segments: its second segment repeated."""
    segs = tuple(base.segments) + (base.segments[-1],) * (n - len(base.segments))
    return dataclasses.replace(base, segments=segs, name=f"{base.name}-{n}seg")


def configs(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """A start and a goal configuration (the replan tests' pair, extended with zero bending)."""
    n = model.robot.n_segments
    xs = np.zeros(model.nx)
    xg = np.zeros(model.nx)
    xs[0] = 0.3
    xg[: 2 * n] = np.resize([-0.6, 0.5, -0.3, 0.2], 2 * n) / max(1, n - 1)
    xg[-1] = -40.0
    return xs, xg


def scene_for(model: Model, m: int, seed: int) -> Scene:
    """m spheres of 15 mm around the robot, clear (by 25 mm) of its start and goal bodies."""
    rng = np.random.default_rng(seed)
    L = model.robot.total_length
    xs, xg = configs(model)
    body = model.points(np.stack([xs, xg]), 40).reshape(-1, 3)
    obs: list[Obstacle] = []
    while len(obs) < m:
        c = rng.uniform([-0.6 * L, -0.6 * L, 0.1 * L], [0.6 * L, 0.6 * L, 1.1 * L])
        if np.min(np.linalg.norm(body - c, axis=1)) > 15.0 + 25.0:
            obs.append(Obstacle(center=tuple(c), radius=15.0, name=f"s{len(obs)}"))
    lo = (-1.0 * L, -1.0 * L, -250.0)
    hi = (1.0 * L, 1.0 * L, 1.3 * L)
    return Scene(obstacles=tuple(obs), safety_distance=5.0, workspace_lo=lo, workspace_hi=hi)


def steer_ms(model: Model, scene: Scene, compiled: bool, n: int = 40) -> tuple[float, float]:
    """(median CPU ms, success share) of n steers in `scene` (CPU time: the machine is shared)."""
    X, T = make_problems(model, scene, n, seed=0)
    opts = SteerOptions(solver="sqp", qpsol="daqp", compiled=compiled)
    s = SteerSolver(model, scene.n_obstacles, opts)
    for k in range(3):
        s.solve(X[k], T[k], scene)
    s.reset_warm_start()
    times, ok = [], 0
    for k in range(n):
        t0 = time.process_time()
        r = s.solve(X[k], T[k], scene)
        times.append(time.process_time() - t0)
        ok += r.is_success()
    return float(np.median(times) * 1e3), ok / n


def replan_ms(
    model: Model, scene: Scene, compiled: bool = False, qp_obstacles: int = 0, qpsol: str = "daqp"
) -> tuple[float, float, float, float]:
    """(median iteration ms of the iterations that neither planned nor took over a reference path, median NLP
    ms, p99 iteration ms (wall), mean CPU ms per iteration) of a 3 s
    closed-loop run; compiled: the horizon NLP in C with the shipped problem's iteration cap; qp_obstacles:
    the QP's obstacle slots (0: every obstacle of the scene); qpsol: "hpipm" is the stage-form QP (issue 29)."""
    xs, xg = configs(model)
    shipped = SHIPPED.options(ReplanOptions, "replan")  # the iteration cap simulation 2 ships
    cap = {"compiled": True, "max_iter": shipped.max_iter, "max_calls": shipped.max_calls} if compiled else {}
    opts = ReplanOptions(solver="sqp", qpsol=qpsol, points=16, qp_obstacles=qp_obstacles, **cap)
    loop = ClosedLoop.build(
        model, scene, model.tip_position(xg), xs, options=opts, loop_options=LoopOptions(duration=3.0), goal_config=xg
    )
    c0 = time.process_time()
    run = loop.run()
    cpu = (time.process_time() - c0) / max(1, run.steps)
    quiet = run.iter_time[run.plan_time == 0.0]  # the iterations that neither planned nor took over a reference
    return (
        float(np.median(quiet if len(quiet) else run.iter_time) * 1e3),
        float(np.median(run.nlp_time) * 1e3),
        float(np.percentile(run.iter_time, 99) * 1e3),
        cpu * 1e3,
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--compiled", type=int, default=0, help="also time the compiled steer up to this many obstacles")
    ap.add_argument(
        "--compiled-replan", type=int, default=0, help="also time the compiled replanning up to this many obstacles"
    )
    ap.add_argument(
        "--old-up-to", type=int, default=31, help="steer, interpreted and all-obstacle replan up to this many obstacles"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "scaling_solvers.png")
    ap.add_argument("--obstacles", default=",".join(map(str, OBSTACLES)), help="comma list of obstacle counts")
    ap.add_argument("--broad-slots", default="3", help="comma list of the broad phase columns' qp_obstacles")
    ap.add_argument("--segments", default=",".join(map(str, SEGMENTS)), help="comma list of segment counts")
    ap.add_argument(
        "--replan-only", action="store_true", help="only the compiled replan columns (no steer, no interpreted replan)"
    )
    args = ap.parse_args()
    counts = [int(v) for v in args.obstacles.split(",")]
    segments = [int(v) for v in args.segments.split(",")]
    slot_counts = [int(v) for v in args.broad_slots.split(",")]
    base = Problem.load(ROOT / "problems" / "paper_static.toml").robot
    load0 = os.getloadavg()[0]
    cases = [(2, m) for m in counts] + [(n, SEG_OBSTACLES) for n in segments if n != 2]
    rows = []
    print(
        f"{'segments':>8} {'obstacles':>9} {'steer cpu ms':>12} {'ok':>5} {'compiled cpu ms':>15} {'iter ms':>8} "
        f"{'iter p99':>8} {'NLP ms':>7} {'iter cpu ms':>11} {'compiled iter cpu ms':>20} {'compiled NLP ms':>15} "
        + "".join(
            f" {f'broad {k} iter med':>17} {f'broad {k} iter cpu ms':>19} {f'broad {k} NLP ms':>14}"
            for k in slot_counts
        )
    )
    if args.compiled_replan:
        # untimed: the first closed loop of a process pays its one-off costs (imports, caches, page faults)
        model = Model(robot_with(base, 2))
        replan_ms(model, scene_for(model, 1, seed=21), compiled=True, qp_obstacles=slot_counts[0])
    for n, m in cases:
        model = Model(robot_with(base, n))
        scene = scene_for(model, m, seed=10 * n + m)
        nan = float("nan")  # not timed: printed as nan, not plotted
        old = m <= args.old_up_to
        interp = old and not args.replan_only
        st, ok = steer_ms(model, scene, compiled=False) if interp else (nan, nan)
        cst = steer_ms(model, scene, compiled=True)[0] if interp and m <= min(args.compiled, args.old_up_to) else nan
        it, nlp, p99, cpu = replan_ms(model, scene) if interp else (nan, nan, nan, nan)
        cnlp = ccpu = nan
        broad = {k: (nan, nan, nan) for k in slot_counts}  # qp_obstacles -> (wall median, NLP median, CPU mean)
        if m <= args.compiled_replan:
            # interleaved: the previous path (every obstacle in the QP), then the broad phase's
            if old:
                _, cnlp, _, ccpu = replan_ms(model, scene, compiled=True)
            for k in slot_counts:
                bmed, bnlp, _, bcpu = replan_ms(model, scene, compiled=True, qp_obstacles=k)
                broad[k] = (bmed, bnlp, bcpu)
        row = {"segments": n, "obstacles": m, "steer": st, "ok": ok, "compiled": cst}
        rows.append(
            row | {"iter": it, "p99": p99, "nlp": nlp, "iter_cpu": cpu, "compiled_iter_cpu": ccpu, "broad": broad}
        )
        print(
            f"{n:>8} {m:>9} {st:>12.3f} {ok:>5.2f} {cst:>15.3f} {it:>8.2f} {p99:>8.2f} {nlp:>7.2f} {cpu:>11.2f} "
            f"{ccpu:>20.2f} {cnlp:>15.2f}"
            + "".join(f" {broad[k][0]:>17.2f} {broad[k][2]:>19.2f} {broad[k][1]:>14.2f}" for k in slot_counts),
            flush=True,
        )
    _print_ratios(rows)
    stamp = f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"
    machine = f"{platform.machine()}, {os.cpu_count()} cores, load {load0:.1f} -> {os.getloadavg()[0]:.1f}"
    print(f"date {stamp}; machine {machine}")
    plot(rows, args.out, f"{stamp}, {machine}")
    print(f"wrote {args.out}")
    return 0


def _print_ratios(rows: list[dict]) -> None:
    """The broad phase's replan iteration at m obstacles over that at 1 (2 segments; issue 29's target: 31/1 <= 2x)."""
    two = {r["obstacles"]: r for r in rows if r["segments"] == 2}
    if 1 not in two:
        return
    for k, (med1, nlp1, cpu1) in two[1]["broad"].items():
        for m, r in sorted(two.items()):
            med, nlp, cpu = r["broad"][k]
            if m > 1 and np.isfinite(cpu) and np.isfinite(cpu1):
                print(
                    f"broad phase, qp_obstacles {k}, {m} obstacles / 1: iteration wall median x{med / med1:.2f}, "
                    f"CPU mean x{cpu / cpu1:.2f}, NLP median x{nlp / nlp1:.2f}"
                )


def plot(rows: list[dict], out: Path, note: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 5.2))
    for ax, key, sel, label in (
        (axes[0], "obstacles", [r for r in rows if r["segments"] == 2], "obstacles (2 segments)"),
        (
            axes[1],
            "segments",
            [r for r in rows if r["obstacles"] == SEG_OBSTACLES],
            f"segments ({SEG_OBSTACLES} obstacles)",
        ),
    ):
        x = [r[key] for r in sel]
        fin = [(xi, r["steer"]) for xi, r in zip(x, sel, strict=True) if np.isfinite(r["steer"])]
        if fin:
            ax.plot(*zip(*fin, strict=True), "o-", color="C0", label="steer, sqp + daqp interpreted (CPU median)")
        comp = [(xi, r["compiled"]) for xi, r in zip(x, sel, strict=True) if np.isfinite(r["compiled"])]
        if comp:
            ax.plot(*zip(*comp, strict=True), "s-", color="C1", label="steer, compiled C (CPU median)")
        fin = [(xi, r["iter_cpu"]) for xi, r in zip(x, sel, strict=True) if np.isfinite(r["iter_cpu"])]
        if fin:
            ax.plot(*zip(*fin, strict=True), "^-", color="C2", label="replan iteration, interpreted (CPU mean)")
        comp = [
            (xi, r["compiled_iter_cpu"]) for xi, r in zip(x, sel, strict=True) if np.isfinite(r["compiled_iter_cpu"])
        ]
        if comp:
            ax.plot(*zip(*comp, strict=True), "v-", color="C3", label="replan iteration, compiled C (CPU mean)")
        for j, k in enumerate(sel[0]["broad"] if sel else ()):
            for col, what, style in ((2, "CPU mean", "D-"), (0, "wall median", "D--")):
                comp = [
                    (xi, r["broad"][k][col]) for xi, r in zip(x, sel, strict=True) if np.isfinite(r["broad"][k][col])
                ]
                if comp:
                    text = f"replan iteration, compiled C, broad phase, <= {k} QP obstacles ({what})"
                    ax.plot(*zip(*comp, strict=True), style, color=f"C{4 + j}", label=text)
        ax.set_xlabel(label)
        ax.set_xticks(x)
        ax.set_xticklabels([str(v) for v in x])
        ax.set_ylabel("ms")
        ax.set_yscale("log")
        if key == "obstacles":
            ax.set_xscale("log", base=2)
            ax.set_xticks(x)
            ax.set_xticklabels([str(v) for v in x])
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=7)  # below the panels: no line hidden
    fig.suptitle(f"solver cost scaling ({note})", fontsize=9)
    fig.tight_layout(rect=(0.0, 0.2, 1.0, 1.0))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
