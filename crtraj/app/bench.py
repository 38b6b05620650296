"""Use case: the benchmarks from the command line: the paper's Table I (`crtraj bench table1`, here) and the
held-out dynamic suite (`crtraj bench suite`, `crtraj.app.suite`)."""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from crtraj.app.suite import run_suite
from crtraj.bench.records import LABELS, PLANNERS, BenchOptions, _fmt, _pct
from crtraj.bench.runner import Table1Bench
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import read_toml
from crtraj.io.problem import load_robot
from crtraj.planning.options import PlannerOptions
from crtraj.planning.registry import BUILTIN


def _parse_list(text: str, name: str, conv: Callable[[str], Any]) -> tuple[Any, ...]:
    try:
        items = tuple(conv(s.strip()) for s in text.split(",") if s.strip())
    except ValueError:
        raise InputError(f"{name}: expected a comma-separated list, got {text!r}") from None
    if not items:
        raise InputError(f"{name}: empty list")
    return items


def _executor(args: Any, bench: Table1Bench, workers: int) -> tuple[cf.Executor | None, Any, int]:
    """(executor or None, Dask client or None, worker count) for --dask / --workers."""
    client = None
    executor: cf.Executor | None = None
    if args.dask:
        try:
            from distributed import Client
        except ImportError:
            raise InputError("--dask: needs the 'distributed' package: pip install 'crtraj[bench]'") from None
        try:
            client = Client(args.dask, timeout="10s")
        except OSError as exc:
            raise InputError(f"--dask: cannot reach a Dask scheduler at {args.dask!r} ({exc})") from None
        executor = client.get_executor()
        workers = sum(client.nthreads().values())
    elif workers > 0:
        executor = cf.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=bench.initializer,
            initargs=bench.initargs,
        )
    return executor, client, workers


def run_table1(args: Any) -> int:
    """`crtraj bench table1 ...` (arguments from `crtraj.cli`); returns the exit code."""
    workers = os.cpu_count() or 1 if args.workers is None else args.workers
    if workers < 0:
        raise InputError(f"--workers: must be >= 0 (0 = run in this process), got {workers}")
    planners = _parse_list(args.planners, "--planners", str) if args.planners else PLANNERS
    options = BenchOptions(
        counts=_parse_list(args.counts, "--counts", int),
        scenarios=100 if args.scenarios is None else args.scenarios,
        planners=planners,
        time_limit=5.0 if args.time_limit is None else args.time_limit,
        seed=args.seed,
        verify_margin=args.verify_margin,
    )
    planner_options = PlannerOptions()
    if args.planner_config:
        data = read_toml(args.planner_config)
        unknown = sorted(set(data) - {"planner"})
        if unknown:
            raise InputError(f"{args.planner_config}: only a [planner] table is read here, found {unknown}")
        planner_options = PlannerOptions.from_table(Table(data.get("planner", {}), "planner"))
    robot = load_robot(args.robot)
    for name in planners:
        BUILTIN.check_available(name)  # fail now, in one line, not in every worker
    bench = Table1Bench(robot, options, planner_options=planner_options)
    out = Path(args.out or "out/table1")
    total = len(options.counts) * options.scenarios * len(planners)
    executor, client, workers = _executor(args, bench, workers)
    where = f"Dask at {args.dask} ({workers} threads)" if args.dask else f"{workers or 'no'} worker processes"
    print(
        f"crtraj bench table1: {total} runs ({options.scenarios} scenarios x counts {list(options.counts)} x "
        f"{len(planners)} planners), time limit {options.time_limit:g} s, {where}"
    )
    try:
        report = bench.run(executor, workers=workers, progress=not args.no_progress)
    finally:
        if isinstance(executor, cf.ProcessPoolExecutor):
            executor.shutdown(wait=True, cancel_futures=True)
        elif executor is not None:
            executor.shutdown(wait=False)
        if client is not None:
            client.close()
    files = report.write(out)
    for p in planners:
        cells = []
        for c in options.counts:
            s = report.stats(p, c)
            cells.append(f"{c} obs: {_pct(s['success'])} median {_fmt(s['time_median'], 3)} s")
        print(f"  {LABELS.get(p, p):<18} " + "; ".join(cells))
    print(f"wrote {', '.join(str(f) for f in files)} ({report.wall_time:.0f} s)")
    if report.interrupted:
        print(f"crtraj: {report.note}; the files hold the {len(report.records)} runs that finished", file=sys.stderr)
        return 130 if "Ctrl-C" in report.note else 1
    return 0


def bench_command(args: Any) -> int:
    """`crtraj bench TABLE ...`: dispatch on TABLE (table1 or suite); returns the exit code."""
    if args.table == "suite":
        return run_suite(args)
    return run_table1(args)
