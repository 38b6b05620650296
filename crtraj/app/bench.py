"""Use case: the benchmarks from the command line: the paper's Table I (`crtraj bench table1`, here) and the
held-out dynamic suite (`crtraj bench suite`, `crtraj.app.suite`)."""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import multiprocessing
import os
import platform
import re
import sys
from collections.abc import Callable
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from crtraj import __version__
from crtraj.app.suite import run_suite
from crtraj.bench import modes
from crtraj.bench.figures import figure_files
from crtraj.bench.ompl_log import LogSetup, log_files
from crtraj.bench.outputs import OutputSet
from crtraj.bench.paper_mode import CHECK_MODES, PAPER_ROWS, PAPER_SCENES, STRICT_ROWS
from crtraj.bench.records import LABELS, PLANNERS, BenchOptions, _fmt, _pct
from crtraj.bench.runlog import read_runs
from crtraj.bench.runner import Table1Bench
from crtraj.bench.scenarios import ScenarioGenerator, ScenarioOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table, read_int
from crtraj.core.fileio import check_output_dir, check_output_file, check_outputs_not_inputs, read_toml
from crtraj.core.interrupt import die_with_parent
from crtraj.core.logs import configure_logging
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import BUILTIN

log = logging.getLogger(__name__)

# What table1 writes into --out (`crtraj.bench.report.Table1Report.write`) and modes (`run_modes`).
TABLE1_FILES = ("table1.md", "runs.csv", "scenarios.json")
MODES_FILES = ("table1-modes.md", "success.png", "time_cdf.png", "length.png")
# modes' OMPL logs: a folder of their own, replaced as a whole; its crtraj marker kind and its files' names
OMPL_DIR = "ompl"
OMPL_MARKER = "bench-ompl-logs"
_LOG_NAME = re.compile(r"table1-[a-z]+-[0-9]+obs\.log")


def _int(text: str, name: str) -> int:
    """One integer of a comma-separated flag (ASCII digits only: int() also takes other scripts' digits)."""
    return read_int(text, name, ge=0, le=10**6)


def _check_outputs(out: Path, names: tuple[str, ...], inputs: dict[str, Any]) -> None:
    """Before any work: no file the command writes into `out` may be one of its inputs, and each must be
    writable (one line naming the flag)."""
    check_outputs_not_inputs({f"--out ({n})": out / n for n in names}, inputs)
    for n in names:
        check_output_file(out / n, f"--out ({n})")


def _parse_list(text: str, name: str, conv: Callable[[str], Any]) -> tuple[Any, ...]:
    try:
        items = tuple(conv(s.strip()) for s in text.split(",") if s.strip())
    except ValueError:
        raise InputError(f"{name}: expected a comma-separated list, got {text!r}") from None
    if not items:
        raise InputError(f"{name}: empty list")
    return items


def _worker_start(parent: int, level: int, initializer: Callable[..., None], initargs: tuple[Any, ...]) -> None:
    """A table1 worker process's start: it dies with this process (even a SIGKILLed one), logs at the command's
    level (-q, -v), then sets up."""
    die_with_parent(parent)
    configure_logging()
    logging.getLogger("crtraj").setLevel(level)
    initializer(*initargs)


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
            initializer=_worker_start,
            initargs=(os.getpid(), logging.getLogger("crtraj").level, bench.initializer, bench.initargs),
        )
    return executor, client, workers


def _planner_options(path: str | None) -> PlannerOptions:
    """The [planner] table of --planner-config (the defaults without one); any other table is refused."""
    if not path:
        return PlannerOptions()
    data = read_toml(path)
    unknown = sorted(set(data) - {"planner"})
    if unknown:
        raise InputError(f"{path}: only a [planner] table is read here, found {unknown}")
    return PlannerOptions.from_table(Table(data.get("planner", {}), "planner"))


def run_table1(args: Any) -> int:
    """`crtraj bench table1 ...` (arguments from `crtraj.cli`); returns the exit code."""
    if args.table == "modes":
        return run_modes(args)
    workers = os.cpu_count() or 1 if args.workers is None else args.workers
    if workers < 0:
        raise InputError(f"--workers: must be >= 0 (0 = run in this process), got {workers}")
    planners = _parse_list(args.planners, "--planners", str) if args.planners else PLANNERS
    options = BenchOptions(
        counts=_parse_list(args.counts, "--counts", lambda c: _int(c, "--counts")),
        scenarios=100 if args.scenarios is None else args.scenarios,
        planners=planners,
        time_limit=5.0 if args.time_limit is None else args.time_limit,
        seed=args.seed,
        verify_margin=args.verify_margin,
        cpu_budget=args.cpu_budget,
    )
    out = Path(args.out or "out/table1")
    _check_outputs(out, TABLE1_FILES, {"--robot": args.robot, "--planner-config": args.planner_config})
    planner_options = _planner_options(args.planner_config)
    robot = load_robot(args.robot)
    for name in planners:
        if name not in CHECK_MODES:  # rrt-paper, rrtstar-paper: the bench's own entries
            BUILTIN.check_available(name)  # fail now, in one line, not in every worker
    scenes = PAPER_SCENES if args.scenes == "paper" else None
    bench = Table1Bench(robot, options, planner_options=planner_options, scenario_options=scenes)
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
        if "Ctrl-C" in report.note:
            log.warning("%s; the files hold the %d runs that finished", report.note, len(report.records))
            return 130
        # a failure, not a diagnostic: said even with -q
        print(
            f"crtraj: bench failed: {report.note}; the files hold the {len(report.records)} runs that finished",
            file=sys.stderr,
        )
        return 1
    return 0


def bench_command(args: Any) -> int:
    """`crtraj bench TABLE ...`: dispatch on TABLE (table1 or suite); returns the exit code."""
    if args.table == "suite":
        return run_suite(args)
    return run_table1(args)


def run_modes(args: Any) -> int:
    """`crtraj bench modes --runs A.csv,B.csv --out DIR`: Table I in both checking modes from finished runs
    (table1-modes.md, success.png, time_cdf.png, length.png and OMPL benchmark logs in DIR/ompl)."""
    if not args.runs:
        raise InputError("--runs: give the runs.csv file(s) of `crtraj bench table1` runs, comma-separated")
    runs = _parse_list(args.runs, "--runs", str)
    out = Path(args.out or "docs/table1")
    ompl = out / OMPL_DIR
    inputs = {"--robot": args.robot, **{f"--runs ({r})": r for r in runs}}
    _check_outputs(out, MODES_FILES, inputs)
    check_outputs_not_inputs({f"--out ({OMPL_DIR})": ompl}, inputs)
    check_output_dir(ompl, f"--out ({OMPL_DIR})", _ompl_replaceable(ompl), OMPL_MARKER)
    records = [r for path in runs for r in read_runs(path)]
    if not records:
        raise InputError(f"--runs: no runs in {args.runs}")
    counts = tuple(sorted({r.n_obstacles for r in records}))
    limits = ", ".join(f"{p}: {t}" for p, t in sorted(_limits(records).items()))
    header = (
        f"Rendered {datetime.now(timezone.utc).isoformat(timespec='seconds')} by crtraj {__version__} from "
        f"{args.runs}; {len(records)} runs. Machine: {platform.node()} ({platform.machine()}, {os.cpu_count()} "
        f"logical CPUs). Largest time per run (wall s) by planner: {limits}.\n\n{args.note or ''}"
    )
    rows = {"paper": PAPER_ROWS, "strict": STRICT_ROWS}
    outputs = OutputSet()
    outputs.file(out / "table1-modes.md", modes.markdown(records, counts, header, _straight(records, args)))
    for name, data in figure_files(records, rows, counts).items():
        outputs.file(out / name, data)
    setup = LogSetup(time_limit=5.0 if args.time_limit is None else args.time_limit, setup=header)
    logs = log_files(records, rows, counts, setup)
    outputs.folder(ompl, logs, marker=OMPL_MARKER, replaceable=_ompl_replaceable(ompl))
    files = outputs.commit()
    print(f"wrote {len(files)} files in {out}: " + ", ".join(f.name for f in files))
    return 0


def _ompl_replaceable(folder: Path) -> frozenset[str]:
    """The names an existing DIR/ompl without crtraj's marker may hold and still be replaced: OMPL logs as
    crtraj names them (`crtraj.bench.ompl_log.log_files`; versions before the marker wrote none)."""
    try:
        names = os.listdir(folder) if folder.is_dir() else []
    except OSError:
        return frozenset()
    return frozenset(n for n in names if _LOG_NAME.fullmatch(n))


def _straight(records: list[Any], args: Any) -> dict[tuple[int, int], float]:
    """The scenarios' straight start-to-goal tip distances (mm), regenerated from their seeds (the detour
    column)."""
    bounds = replace(PAPER_SCENES if args.scenes == "paper" else ScenarioOptions(), seed=args.seed)
    gen = ScenarioGenerator(Model(load_robot(args.robot)), bounds)
    straight = {}
    for c, i in sorted({(r.n_obstacles, r.index) for r in records}):
        sc = gen.generate(c, i)
        straight[(c, i)] = float(np.linalg.norm(sc.goal - sc.start_tip))
    return straight


def _limits(records: list[Any]) -> dict[str, str]:
    """The longest wall time of each planner's runs (s), formatted (shows the budget a run was held to)."""
    out: dict[str, float] = {}
    for r in records:
        out[r.planner] = max(out.get(r.planner, 0.0), r.time_s if math.isfinite(r.time_s) else 0.0)
    return {p: f"{t:.1f}" for p, t in out.items()}
