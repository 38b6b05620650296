"""Table I in both checking modes (issue 15): the paper's check and the strict dense check, on the paper's scenes.

Planners: rrt-paper and rrtstar-paper (the paper's Algorithm 1 planning with the
paper's check: ten collision points at 1-s step ends, `crtraj.planning.paper_check`),
and rrt, rrtstar, cspace, ompl-rrtconnect, ompl-rrtstar with the strict check.
Every run is judged by both checks (`crtraj.bench.runner.judge`). Runs go
index-major (scenario 0 of every count and planner, then 1, ...), each row is
appended to OUT/runs.csv the moment it finishes, and a rerun skips the rows
already there, so an interrupted run loses nothing and can be continued.
Afterwards `crtraj bench modes OUT` writes the tables, plots and OMPL logs.

Run: python benchmarks/table1_modes.py [--scenarios 100] [--workers 2] [--out out/table1-modes]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing
import os
import platform
import time
from datetime import datetime, timezone
from pathlib import Path

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
    bench = Table1Bench(robot, opts, scenario_options=PAPER_SCENES)
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
        f"{args.scenarios} scenarios x counts {list(counts)} x {len(planners)} planners; {len(done)} rows already done",
        flush=True,
    )
    t0 = time.perf_counter()
    try:
        report = bench.run(executor, workers=args.workers, progress=False, on_record=log.append, done=done)
    finally:
        executor.shutdown(wait=False, cancel_futures=True)
        log.close()
    report.write(out / "single")
    print(
        f"{datetime.now(timezone.utc).isoformat(timespec='seconds')} wall time {time.perf_counter() - t0:.0f} s; "
        f"load average {os.getloadavg()[0]:.1f} at the end; {len(report.records)} new rows in {log_path}",
        flush=True,
    )


if __name__ == "__main__":
    main()
