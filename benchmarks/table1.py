"""The paper's Table I, measured: every planner on the same random dynamic scenes, against the targets.

Targets (issue 5), for the default planner ("cspace"): success >= 99 % at every
obstacle count, median time <= 100 ms, and average path length no longer than
OMPL RRTstar's on the same scenes at the same time budget. The paper's RRT*:
3.66-7.30 s at 99/89/78/65 %.

Run: python benchmarks/table1.py [--scenarios 100] [--counts 1,3,5,7] [--workers 2] [--time-limit 5]
     [--planners ...] [--out out/table1-bench] [--dask ADDRESS]
Writes the same files as `crtraj bench table1` and prints medians, p90 and ratios.
The full table (100 scenarios x 4 counts x 5 planners) is long on a 2-core machine:
`--scenarios 10` gives a first look.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.app.bench import TABLE1_FILES
from crtraj.bench.records import LABELS, PAPER_COUNTS, PAPER_TABLE1, PLANNERS, BenchOptions
from crtraj.bench.report import BenchReport
from crtraj.bench.runner import Table1Bench
from crtraj.core.errors import InputError
from crtraj.core.fields import read_int
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.io.problem import load_robot
from crtraj.planning.planners._registry import BUILTIN

ROOT = Path(__file__).resolve().parent.parent


def _args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", type=int, default=100)
    ap.add_argument("--counts", default="1,3,5,7")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--time-limit", type=float, default=5.0)
    ap.add_argument("--planners", default=",".join(PLANNERS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/table1-bench")
    ap.add_argument("--dask", default=None, help="Dask scheduler address instead of local processes")
    return ap.parse_args()


def _executor(args: argparse.Namespace, bench: Table1Bench) -> tuple[cf.Executor, Any, int]:
    """(executor, Dask client or None, worker count) for --dask / --workers."""
    if args.dask:
        from distributed import Client

        client = Client(args.dask)
        return client.get_executor(), client, sum(client.nthreads().values())
    executor = cf.ProcessPoolExecutor(
        args.workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=bench.initializer,
        initargs=bench.initargs,
    )
    return executor, None, args.workers


def main() -> None:
    args = _args()
    planners = tuple(p.strip() for p in args.planners.split(",") if p.strip())
    for p in planners:
        BUILTIN.check_available(p)
    counts = tuple(read_int(c, "--counts", ge=0, le=10**6) for c in args.counts.split(","))
    robot_file = ROOT / "problems" / "robots" / "cdsr2.toml"
    out = Path(args.out)
    # before hours of runs: no output is the robot file, and every output can be written
    check_outputs_not_inputs({f"--out ({n})": out / n for n in TABLE1_FILES}, {"robot": robot_file})
    for n in TABLE1_FILES:
        check_output_file(out / n, f"--out ({n})")
    robot = load_robot(robot_file)
    opts = BenchOptions(
        counts=counts, scenarios=args.scenarios, planners=planners, time_limit=args.time_limit, seed=args.seed
    )
    bench = Table1Bench(robot, opts)
    executor, client, workers = _executor(args, bench)
    print(
        f"machine: {platform.node()} {platform.machine()}, {os.cpu_count()} logical CPUs, load average "
        f"{os.getloadavg()[0]:.1f} at start; {workers} workers; time limit {args.time_limit:g} s; "
        f"{args.scenarios} scenarios x counts {list(counts)} x {len(planners)} planners"
    )
    t0 = time.perf_counter()
    try:
        report = bench.run(executor, workers=workers, progress=True)
    finally:
        executor.shutdown(wait=False)
        if client is not None:
            client.close()
    report.write(out)  # table1.md, runs.csv and scenarios.json together (crtraj.bench.outputs)
    print(
        f"wall time {time.perf_counter() - t0:.0f} s; load average {os.getloadavg()[0]:.1f} at the end; "
        f"files in {args.out}\n"
    )
    _print_stats(report, planners, counts)
    if "cspace" not in planners:
        return
    _print_targets(report, planners, counts)
    _print_losses(report, planners, counts)


def _print_stats(report: BenchReport, planners: tuple[str, ...], counts: tuple[int, ...]) -> None:
    """Success, median / p90 / mean time (s), mean length (mm) and rejections per planner and count."""
    print(
        f"{'planner':<18} {'obs':>3} {'success':>8} {'median s':>9} {'p90 s':>8} {'mean s':>8} {'mean mm':>8} "
        f"{'rejected':>8}"
    )
    for p in planners:
        for c in counts:
            s = report.stats(p, c)
            print(
                f"{LABELS.get(p, p):<18} {c:>3} {100 * s['success']:>7.0f}% {s['time_median']:>9.3f} "
                f"{s['time_p90']:>8.3f} {s['time_mean']:>8.3f} {s['length_mean']:>8.1f} {s['rejected']:>8d}"
            )


def _print_targets(report: BenchReport, planners: tuple[str, ...], counts: tuple[int, ...]) -> None:
    """The default planner against its targets (issue 5) and the paper's RRT*."""
    print("\ntargets for the default planner (cspace):")
    for c in counts:
        s = report.stats("cspace", c)
        line = (
            f"  {c} obs: success {100 * s['success']:.0f}% (target >= 99%) "
            f"{'PASS' if s['success'] >= 0.99 else 'MISS'}; median {1e3 * s['time_median']:.0f} ms "
            f"(target <= 100 ms) {'PASS' if s['time_median'] <= 0.1 else 'MISS'}"
        )
        if c in PAPER_COUNTS:
            k = PAPER_COUNTS.index(c)
            paper_t = PAPER_TABLE1["rrtstar"]["time_s"][k]
            line += (
                f"; paper RRT* {paper_t:.2f} s at {100 * PAPER_TABLE1['rrtstar']['success'][k]:.0f}%: "
                f"{paper_t / s['time_median']:.0f}x faster (median vs the paper's mean)"
            )
        if "ompl-rrtstar" in planners:
            o = report.stats("ompl-rrtstar", c)
            n, ratio = report.paired_lengths("cspace", "ompl-rrtstar", c)
            verdict = "PASS" if np.isfinite(s["length_mean"]) and s["length_mean"] <= o["length_mean"] else "MISS"
            line += (
                f"; mean length {s['length_mean']:.0f} mm vs OMPL RRTstar {o['length_mean']:.0f} mm "
                f"{verdict} (paired ratio {ratio:.2f} on {n} scenes both solved)"
            )
        print(line)


def _print_losses(report: BenchReport, planners: tuple[str, ...], counts: tuple[int, ...]) -> None:
    """Where the default planner loses to an OMPL planner (success, median time, paired path length)."""
    print("\nwhere the default planner loses to an OMPL planner (success, median time, paired path length):")
    lost = False
    for p in ("ompl-rrtstar", "ompl-rrtconnect"):
        if p not in planners:
            continue
        for c in counts:
            s, o = report.stats("cspace", c), report.stats(p, c)
            n, ratio = report.paired_lengths("cspace", p, c)
            if o["success"] > s["success"]:
                lost = True
                print(f"  {c} obs: {LABELS[p]} success {100 * o['success']:.0f}% > {100 * s['success']:.0f}%")
            if o["time_median"] < s["time_median"]:
                lost = True
                print(f"  {c} obs: {LABELS[p]} median {o['time_median']:.3f} s < {s['time_median']:.3f} s")
            if n and ratio > 1.0:
                lost = True
                print(f"  {c} obs: {LABELS[p]} paths shorter: length ratio {ratio:.3f} on {n} scenes both solved")
    if not lost:
        print("  nowhere")


if __name__ == "__main__":
    try:
        main()
    except InputError as exc:  # bad flags or outputs: one line, no traceback, nothing written
        sys.exit(f"table1: error: {exc}")
