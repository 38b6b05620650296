"""Table I in both checking modes (issue 15): the paper's check and the strict dense check, on the paper's scenes.

Planners: rrt-paper and rrtstar-paper (the paper's Algorithm 1 planning with the
paper's check: ten collision points at 1-s step ends, `crtraj.planning.validity._paper_check`),
and rrt, rrtstar, cspace, ompl-rrtconnect, ompl-rrtstar with the strict check.
Every run is judged by both checks (`crtraj.bench.runner.judge`). Runs go
index-major (scenario 0 of every count and planner, then 1, ...), each row is
appended to OUT/runs.csv.partial the moment it finishes and OUT/runs.csv is
replaced by all rows at the end, and a rerun skips the rows already there, so
an interrupted run loses nothing and can be continued.
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
import multiprocessing
import os
import platform
import sys
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.app.bench import TABLE1_FILES
from crtraj.bench.paper_mode import PAPER_SCENES
from crtraj.bench.records import BenchOptions
from crtraj.bench.runlog import RunLog, csv_text, read_runs
from crtraj.bench.runner import Table1Bench
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, read_int, read_number
from crtraj.core.fileio import atomic_write_text, check_output_file
from crtraj.io.problem import load_robot

ROOT = Path(__file__).resolve().parent.parent
PLANNERS = ("rrt-paper", "rrtstar-paper", "rrt", "rrtstar", "cspace", "ompl-rrtconnect", "ompl-rrtstar")


def _args() -> argparse.Namespace:
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
    try:
        lo_hi = tuple(read_number(v, "--tip-box", limit=MAX_LENGTH) for v in args.tip_box.split(","))
    except InputError:
        lo_hi = ()
    if len(lo_hi) != 6:
        ap.error(f"--tip-box: expected 6 numbers x0,y0,z0,x1,y1,z1 (mm), got {args.tip_box!r}")
    args.tip_box_lo_hi = lo_hi
    return args


def _resume(final: Path, live: Path) -> RunLog:
    """The live log of this leg, continuing the rows already done.

    Rows are appended the moment each run finishes (an interrupted run loses nothing and is resumed), but
    to `live` (runs.csv.partial), never to runs.csv itself: runs.csv is replaced in one rename at the end
    (`_publish`), so no reader ever sees a torn row there, and a runs.csv that does not read back as
    crtraj's runs log (`read_runs`) is refused here, never appended to or replaced.
    """
    done = read_runs(final) if final.exists() else []
    if not live.exists() and done:
        atomic_write_text(live, csv_text(done))  # the live log starts from the finished legs
    return RunLog(live)  # cuts a row torn by a killed leg


def _publish(final: Path, live: Path) -> None:
    """runs.csv := every row of the live log (one rename); the live log is then removed."""
    atomic_write_text(final, csv_text(read_runs(live)))
    live.unlink()


def main() -> None:
    args = _args()
    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
    counts = tuple(read_int(c, "--counts", ge=0, le=10**6) for c in args.counts.split(","))
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    opts = BenchOptions(
        counts=counts,
        scenarios=args.scenarios,
        planners=planners,
        time_limit=args.time_limit,
        seed=args.seed,
        cpu_budget=not args.wall_budget,
    )
    lo_hi = args.tip_box_lo_hi
    scenes = replace(PAPER_SCENES, min_tip_distance=args.min_tip_distance, tip_box_lo=lo_hi[:3], tip_box_hi=lo_hi[3:])
    bench = Table1Bench(robot, opts, scenario_options=scenes)
    out = Path(args.out)
    log_path, live = out / "runs.csv", out / "runs.csv.partial"
    for p in (log_path, live, *(out / "single" / n for n in TABLE1_FILES)):
        check_output_file(p, "--out")
    log = _resume(log_path, live)
    done = frozenset((r.planner, r.n_obstacles, r.index) for r in read_runs(live))
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
        _publish(log_path, live)
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
    try:
        main()
    except InputError as exc:  # bad flags, a runs.csv that is not crtraj's: one line, no traceback
        sys.exit(f"table1_modes: error: {exc}")
