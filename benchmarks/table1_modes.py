"""Table I in both checking modes (issue 15): the paper's check and the strict dense check, on the paper's scenes.

Planners: rrt-paper and rrtstar-paper (the paper's Algorithm 1 planning with the
paper's check: ten collision points at 1-s step ends, `crtraj.planning.paper_check`),
and rrt, rrtstar, cspace, ompl-rrtconnect, ompl-rrtstar with the strict check.
Every run is judged by both checks (`crtraj.bench.runner.judge`). Runs go
index-major (scenario 0 of every count and planner, then 1, ...), each row is
appended to OUT/runs.csv the moment it finishes, and a rerun skips the rows
already there, so an interrupted run loses nothing and can be continued.
Afterwards `crtraj bench modes OUT` writes the tables, plots and OMPL logs.

`--min-tip-distance MM` draws start and goal tips at least that far apart (default 150 mm, the generator's)
and `--tip-box x0,y0,z0,x1,y1,z1` (mm) bounds where they are drawn: the check of the path-length
explanation (our queries are shorter than the paper's), e.g. `--min-tip-distance 280 --tip-box
-150,-150,100,150,150,500` gives queries as long as simulation 1's (317 mm).

Run: python benchmarks/table1_modes.py [--scenarios 100] [--workers 2] [--out out/table1-modes]
     [--min-tip-distance 150]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import math
import multiprocessing
import os
import platform
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.bench.paper_mode import PAPER_SCENES
from crtraj.bench.records import BenchOptions
from crtraj.bench.runlog import RunLog, read_runs
from crtraj.bench.runner import Table1Bench
from crtraj.io.problem import load_robot

ROOT = Path(__file__).resolve().parent.parent
PLANNERS = ("rrt-paper", "rrtstar-paper", "rrt", "rrtstar", "cspace", "ompl-rrtconnect", "ompl-rrtstar")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", type=int, default=100)
    ap.add_argument("--counts", default="1,3,5,7")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--time-limit", type=float, default=5.0)
    ap.add_argument("--planners", default=",".join(PLANNERS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/table1-modes")
    ap.add_argument("--wall-budget", action="store_true", help="time limit on wall time (default: CPU time)")
    ap.add_argument("--min-tip-distance", type=float, default=PAPER_SCENES.min_tip_distance, help="mm")
    box = ",".join(f"{v:g}" for v in (*PAPER_SCENES.tip_box_lo, *PAPER_SCENES.tip_box_hi))
    ap.add_argument("--tip-box", default=box, help="x0,y0,z0,x1,y1,z1 (mm): where start and goal tips are drawn")
    args = ap.parse_args()

    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
    counts = tuple(int(c) for c in args.counts.split(","))
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    opts = BenchOptions(
        counts=counts,
        scenarios=args.scenarios,
        planners=planners,
        time_limit=args.time_limit,
        seed=args.seed,
        cpu_budget=not args.wall_budget,
    )
    try:
        lo_hi = tuple(float(v) for v in args.tip_box.split(","))
    except ValueError:
        lo_hi = ()
    if len(lo_hi) != 6 or not all(math.isfinite(v) for v in lo_hi):
        ap.error(f"--tip-box: expected 6 numbers x0,y0,z0,x1,y1,z1 (mm), got {args.tip_box!r}")
    scenes = replace(PAPER_SCENES, min_tip_distance=args.min_tip_distance, tip_box_lo=lo_hi[:3], tip_box_hi=lo_hi[3:])
    bench = Table1Bench(robot, opts, scenario_options=scenes)
    out = Path(args.out)
    log_path = out / "runs.csv"
    done = (
        frozenset((r.planner, r.n_obstacles, r.index) for r in read_runs(log_path))
        if log_path.exists()
        else frozenset()
    )
    log = RunLog(log_path)
    executor = cf.ProcessPoolExecutor(
        args.workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=bench.initializer,
        initargs=bench.initargs,
    )
    clock = "wall" if args.wall_budget else "CPU"
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    print(
        f"{started} machine: {platform.node()} {platform.machine()}, {os.cpu_count()} logical CPUs, load average "
        f"{os.getloadavg()[0]:.1f} at start; {args.workers} workers; time limit {args.time_limit:g} s of {clock} time; "
        f"{args.scenarios} scenarios x counts {list(counts)} x {len(planners)} planners; start and goal tips >= "
        f"{args.min_tip_distance:g} mm apart in the box {args.tip_box} mm; {len(done)} rows already done",
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        report = bench.run(executor, workers=args.workers, progress=False, on_record=log.append, done=done)
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
        log.close()
    if report.records:  # a rerun that finds every row done keeps the last leg's report
        report.write(out / "single")
    print(
        f"{datetime.now(timezone.utc).isoformat(timespec='seconds')} wall time {time.perf_counter() - t0:.0f} s; "
        f"load average {os.getloadavg()[0]:.1f} at the end; {len(report.records)} new rows in {log_path}",
        flush=True,
    )
    length_summary(bench, read_runs(log_path))


def length_summary(bench: Table1Bench, rows: list) -> None:
    """Per planner and obstacle count, over the paper check's successes in `rows` (runs of `bench`): mean tip
    path length, mean straight start-to-goal tip distance of those scenarios (from the bench's own scene bounds),
    and the mean detour (length / straight distance). A rerun of the same command prints it again."""
    model = bench.model
    straight = {
        (sc.n_obstacles, sc.index): float(np.linalg.norm(model.tip_position(sc.start) - sc.goal))
        for sc in bench.scenarios()
    }
    print("planner          obs   n  length mm  straight mm  detour   (paper-check successes)")
    for planner in bench.options.planners:
        for count in bench.options.counts:
            ok = [r for r in rows if r.planner == planner and r.n_obstacles == count and r.paper_success]
            if not ok:
                continue
            length = np.array([r.length_mm for r in ok])
            dist = np.array([straight[(count, r.index)] for r in ok])
            print(
                f"{planner:<16s} {count:>3d} {len(ok):>3d} {length.mean():>10.0f} {dist.mean():>12.0f} "
                f"{np.mean(length / dist):>7.2f}"
            )


if __name__ == "__main__":
    main()
