"""The paper's Table I benchmark (sec. IV-B): planners on the same random dynamic scenes.

`Table1Bench` draws the scenarios (`crtraj.bench.scenarios`), runs every planner on
every scenario with the same time budget, re-verifies every claimed success
with an independent dense check, and writes the paper's table beside ours:

    bench = Table1Bench(robot, BenchOptions(scenarios=10, counts=(1, 3)))
    report = bench.run(ProcessPoolExecutor(2, initializer=bench.initializer, initargs=bench.initargs))
    report.write("out/table1")            # table1.md, runs.csv, scenarios.json

Planners (names as in the CSV): ``rrt`` and ``rrtstar`` (the paper's
Algorithm 1 over tip positions), ``cspace`` (crtraj's default planner),
``ompl-rrtstar`` and ``ompl-rrtconnect`` (OMPL 2.x in the same
configuration space with the same validity checker, `crtraj.planning.planners._ompl`).

Work goes through any `concurrent.futures.Executor`; each worker process (or
thread) builds its own model and planners once, because CasADi functions do
not pickle: only plain data (the robot as a dict, the scenario as a dict)
travels to the workers. Without an executor the runs happen in this process.

Independent dense check (the only judge of success): a run counts as a
success only if the planner claims an exact solution AND the returned timed
path (straight motions in configuration space between waypoints, linear in
time, as `PlanResult` defines it)

- starts at the scenario's start configuration at t = 0,
- stays within the robot's limits at every dense sample,
- ends with the tip within the goal tolerance of the goal,
- never touches an obstacle: at every dense time sample the backbone
  (`verify_points` points, checked as the polyline between them, inflated by
  the disc radius) keeps more than `verify_margin` mm from every sphere's
  surface, with the obstacle state `Scene.states(t)` at that very time.

Samples are spaced at most `verify_dt` seconds apart, and refined until no
backbone point moves more than `verify_step` mm between two consecutive
samples. This check shares nothing with the planners'
validity checker except the robot model's points and the obstacle
definition. Path length is the tip's travel along the same dense samples,
computed the same way for every planner.

Timing: `RunRecord.time_s` is the wall time of the planner's ``plan`` call in
the worker. Each worker builds every planner once and runs one untimed
warm-up query with it first (planners build NLP solvers lazily).
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import json
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, TextIO

import numpy as np

try:  # rich comes with the [bench] extra; without it the progress is plain lines (`_PlainProgress`)
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
except ImportError:  # pragma: no cover - exercised by tests that hide rich
    Progress = None

from crtraj.bench.check import DenseCheck, PaperCheck, dense_check, paper_check
from crtraj.bench.paper_mode import CHECK_MODES, PAPER_SPECS
from crtraj.bench.records import LABELS, BenchOptions, RunRecord
from crtraj.bench.report import BenchReport
from crtraj.bench.scenarios import Scenario, ScenarioGenerator, ScenarioOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.base import Planner
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import BUILTIN, PlannerRegistry, PlannerSpec
from crtraj.planning.result import PlanResult
from crtraj.planning.stop import StopCondition
from crtraj.world import packing
from crtraj.world.scene import Scene

# The untimed warm-up query of every worker's planners: its scenario seed and time limit (s).
_WARMUP_SEED = 2**31 - 1
WARMUP_TIME = 2.0


# ---------------------------------------------------------------- planners
def bench_stop(spec: PlannerSpec, options: PlannerOptions, time_limit: float, cpu: bool = False) -> StopCondition:
    """The stop condition of one run: the time budget, plus the options' iteration limit and
    first-solution stop unless the planner runs on its budget alone (`PlannerSpec.budget_only`).
    cpu: the budget counts CPU time (`StopCondition.cpu_time`; OMPL's planners time themselves)."""
    if spec.budget_only:
        return StopCondition(time_limit=time_limit)
    return StopCondition(
        time_limit=time_limit,
        max_iterations=options.max_iterations,
        first_solution=options.first_solution,
        cpu_time=cpu,
    )


def warm_up(planner: Planner, model: Model, stop: StopCondition) -> None:
    """One untimed query that builds what a planner builds lazily (NLP solvers, CasADi maps), so that its
    first timed run does not pay for it."""
    warm = ScenarioGenerator(model, ScenarioOptions(seed=_WARMUP_SEED)).generate(1, 0)
    plan_scenario(planner, stop, warm, seed=0, goal_tolerance=1.0)


def plan_scenario(
    planner: Planner, stop: StopCondition, scenario: Scenario, *, seed: int, goal_tolerance: float
) -> PlanResult:
    """One benchmark query through the `Planner` protocol: the scenario's start configuration and goal."""
    return planner.plan(
        scenario.goal,
        start_config=scenario.start,
        scene=scenario.scene,
        stop=stop,
        seed=seed,
        goal_tolerance=goal_tolerance,
    )


# ------------------------------------------------------------------ workers
@dataclass(frozen=True)
class WorkerSpec:
    """Plain, hashable data that lets any worker rebuild the model and planners (by registry name)."""

    robot_json: str
    planner_options_json: str
    registry: PlannerRegistry = BUILTIN


class _WorkerContext:
    """The model and the planners of one worker, built once."""

    def __init__(self, spec: WorkerSpec) -> None:
        robot = Robot.from_table(Table(json.loads(spec.robot_json), "robot"))
        self.spec = spec
        self.model = Model(robot)
        t = Table(json.loads(spec.planner_options_json), "planner")
        self.options = PlannerOptions.from_table(t)
        self._planners: dict[str, Planner] = {}

    def stop(self, name: str, time_limit: float, cpu: bool = False) -> StopCondition:
        """The stop condition of one run of the named planner (`bench_stop`)."""
        return bench_stop(self.spec.registry.spec(name), self.options, time_limit, cpu)

    def planner(self, name: str) -> Planner:
        """The named planner, built and warmed up on first use (never inside a timed run)."""
        p = self._planners.get(name)
        if p is None:
            p = self.spec.registry.build(name, self.model, Scene(), self.options, max_obstacles=packing.SLOTS)
            warm_up(p, self.model, self.stop(name, WARMUP_TIME))
            self._planners[name] = p
        return p


@functools.lru_cache(maxsize=8)
def _context(spec: WorkerSpec, thread: int) -> _WorkerContext:
    """One context per (spec, thread) in each process: executors pass only plain data,
    and a Model's evaluation buffers must not be shared between threads."""
    del thread  # part of the cache key only
    return _WorkerContext(spec)


def init_worker(spec: WorkerSpec, planners: tuple[str, ...] = ()) -> None:
    """Executor initializer: build the model and the named planners before any run is timed.

    A planner that cannot be built is skipped here; its runs then record the error.
    """
    ctx = _context(spec, threading.get_ident())
    for name in planners:
        try:
            ctx.planner(name)
        except InputError:
            continue


@dataclass(frozen=True)
class _Task:
    planner: str
    scenario: dict[str, Any]
    seed: int
    time_limit: float
    goal_tolerance: float
    verify: tuple[int, float, float, float | None]  # points, dt, step, margin (None: the scene's D_sf)
    check_mode: str = "strict"  # the planner's motion check (``[planner.check] mode``)
    cpu_budget: bool = False  # time_limit counts CPU time (BenchOptions.cpu_budget)


def run_task(spec: WorkerSpec, task: _Task) -> RunRecord:
    """Run one planner on one scenario and judge it by the dense check (runs in a worker)."""
    ctx = _context(spec, threading.get_ident())
    scenario = Scenario.from_dict(task.scenario)
    worker = f"{platform.node()}:{os.getpid()}"
    base = {
        "planner": task.planner,
        "n_obstacles": scenario.n_obstacles,
        "index": scenario.index,
        "seed": task.seed,
        "worker": worker,
        "check_mode": task.check_mode,
    }
    try:
        planner = ctx.planner(task.planner)
    except InputError as exc:
        return _error_record(base, f"planner unavailable: {exc}")
    stop = ctx.stop(task.planner, task.time_limit, task.cpu_budget)
    t1, c1 = time.perf_counter(), time.process_time()
    try:
        result = plan_scenario(planner, stop, scenario, seed=task.seed, goal_tolerance=task.goal_tolerance)
    except InputError as exc:  # a planner refusing its input is a failed run, not a crashed bench
        return _error_record(base, f"planner refused the query: {exc}", time.perf_counter() - t1)
    except Exception as exc:  # a crash is recorded (status "error", with its text) and the sweep goes on
        return _error_record(base, f"planner raised {type(exc).__name__}: {exc}", time.perf_counter() - t1)
    elapsed = time.perf_counter() - t1
    base["cpu_s"] = time.process_time() - c1  # CPU time this process got: on a loaded machine < elapsed
    return judge(ctx.model, scenario, result, elapsed, task, base)


def _error_record(base: dict[str, Any], message: str, elapsed: float = float("nan")) -> RunRecord:
    nan = float("nan")
    return RunRecord(
        **base,
        status="error",
        claimed=False,
        verified=False,
        success=False,
        time_s=elapsed,
        length_mm=nan,
        min_clearance_mm=nan,
        goal_error_mm=nan,
        duration_s=nan,
        waypoints=0,
        message=message,
        check="",
    )


def judge(
    model: Model, scenario: Scenario, result: PlanResult, elapsed: float, task: _Task, base: dict[str, Any]
) -> RunRecord:
    """A `RunRecord` for one planner result: success only when claimed AND densely verified to keep
    `verify_margin` (default: the scene's D_sf); the paper's check judges the same path too."""
    nan = float("nan")
    claimed = result.is_success()
    n_pts, dt, step, margin = task.verify
    dsf = scenario.scene.safety_distance
    check: DenseCheck | None = None
    paper: PaperCheck | None = None
    if claimed:
        check = dense_check(
            model,
            scenario.scene,
            result,
            scenario.start,
            scenario.goal,
            goal_tolerance=task.goal_tolerance,
            n_points=n_pts,
            dt=dt,
            step=step,
            margin=dsf if margin is None else margin,
        )
        paper = paper_check(model, scenario.scene, result, scenario.goal, goal_tolerance=task.goal_tolerance)
    verified = bool(check is not None and check.is_success())
    progress = result.cost_progress
    first = progress[0][0] if progress else (float(elapsed) if claimed else nan)
    best = progress[-1][1] if progress else (float(result.cost) if claimed else nan)
    return RunRecord(
        **base,
        status=str(result.status),
        claimed=claimed,
        verified=verified,
        success=claimed and verified,
        time_s=float(elapsed),
        length_mm=check.length if check else nan,
        min_clearance_mm=check.min_clearance if check else nan,
        goal_error_mm=check.goal_error if check else float(result.goal_error),
        duration_s=float(result.duration) if result.has_path else nan,
        waypoints=len(result.t),
        message=str(result.message),
        check="ok" if verified else (check.reason if check else "not checked (no exact solution claimed)"),
        dsf_clearance_mm=check.min_clearance - dsf if check else nan,
        paper_success=bool(paper is not None and paper.passed),
        paper_clearance_mm=paper.clearance if paper else nan,
        first_solution_s=first,
        graph_states=int(result.counts.get("graph_states", result.counts.get("nodes", 0))),
        best_cost=best,
        cost_progress=";".join(f"{t:.4g}:{c:.6g}" for t, c in progress),
    )


def _key(task: _Task) -> tuple[str, int, int]:
    """(planner, obstacle count, index) of a task."""
    return (task.planner, int(task.scenario["n_obstacles"]), int(task.scenario["index"]))


def _run_seed(seed: int, n_obstacles: int, index: int, planner_slot: int) -> int:
    return int(np.random.SeedSequence([seed, n_obstacles, index, planner_slot]).generate_state(1)[0])


# ------------------------------------------------------------------- bench
class Table1Bench:
    """The paper's Table I on crtraj's scenario generator, for any set of planners.

    robot: the robot (default file: problems/robots/cdsr2.toml). options:
    what to run. scenario_options: the generator's bounds (seed taken from
    options.seed). planner_options: shared settings of every planner (max
    speed, collision resolution, check points: the same validity checker for
    crtraj's and OMPL's planners). extra_planners: `PlannerSpec`s added to
    the built-in registry (`crtraj.planning.planners._registry`); every planner is
    built by its registry factory and called through the `Planner`
    protocol. A factory must be picklable (a module-level function or class)
    to run in worker processes.
    """

    def __init__(
        self,
        robot: Robot,
        options: BenchOptions | None = None,
        *,
        scenario_options: ScenarioOptions | None = None,
        planner_options: PlannerOptions | None = None,
        extra_planners: Sequence[PlannerSpec] = (),
    ) -> None:
        self.robot = robot
        self.options = options or BenchOptions()
        so = scenario_options or ScenarioOptions()
        self.scenario_options = replace(so, seed=self.options.seed)
        self.planner_options = planner_options or PlannerOptions()
        registry = BUILTIN
        for spec in (*PAPER_SPECS, *extra_planners):
            registry = registry.with_planner(spec)
        for name in self.options.planners:
            registry.spec(name)  # unknown names fail here, before any work starts
        self.spec = WorkerSpec(
            robot_json=json.dumps(robot.to_dict(), sort_keys=True),
            planner_options_json=json.dumps(self.planner_options.to_dict(), sort_keys=True),
            registry=registry,
        )
        self._model: Model | None = None
        self.check_modes = dict(CHECK_MODES)

    @property
    def model(self) -> Model:
        if self._model is None:
            self._model = Model(self.robot)
        return self._model

    @property
    def initializer(self) -> Callable[..., None]:
        """Pass as ``initializer=`` to a ProcessPoolExecutor (with `initargs`)."""
        return init_worker

    @property
    def initargs(self) -> tuple[Any, ...]:
        return (self.spec, self.options.planners)

    def scenarios(self) -> list[Scenario]:
        """Every scenario of the table, in (count, index) order."""
        gen = ScenarioGenerator(self.model, self.scenario_options)
        return gen.generate_all(self.options.counts, self.options.scenarios)

    def tasks(self, scenarios: Sequence[Scenario]) -> list[_Task]:
        o = self.options
        verify = (o.verify_points, o.verify_dt, o.verify_step, o.verify_margin)
        out = []
        # index-major order: a run cut short holds the same scenarios for every count and planner
        for sc in sorted(scenarios, key=lambda sc: (sc.index, sc.n_obstacles)):
            d = sc.to_dict()
            for k, p in enumerate(o.planners):
                seed = _run_seed(o.seed, sc.n_obstacles, sc.index, k)
                mode = self.check_modes.get(p, "strict")
                out.append(_Task(p, d, seed, o.time_limit, o.goal_tolerance, verify, mode, o.cpu_budget))
        return out

    def run(
        self,
        executor: cf.Executor | None = None,
        *,
        workers: int = 1,
        progress: bool = True,
        on_record: Callable[[RunRecord], None] | None = None,
        done: frozenset[tuple[str, int, int]] = frozenset(),
    ) -> BenchReport:
        """Run every planner on every scenario; returns the report (not yet written).

        executor: any `concurrent.futures.Executor` (process pool, Dask
        ``client.get_executor()``, ...); None runs everything here, one by
        one. workers: only for the report's header. progress: draw a rich
        progress bar. done: (planner, obstacle count, index) of the runs to
        skip (a resumed run). On Ctrl-C the pending runs are cancelled and the
        report holds the finished ones (``interrupted=True``).
        """
        t_start = time.perf_counter()
        scenarios = self.scenarios()
        tasks = [t for t in self.tasks(scenarios) if _key(t) not in done]
        records: list[RunRecord] = []
        interrupted, note = False, ""
        bar = make_progress(self.options, len(tasks)) if progress else None
        try:
            if bar:
                bar.start()
            for rec in self._execute(tasks, executor):
                records.append(rec)
                if bar:
                    bar.advance(rec)
                if on_record:
                    on_record(rec)
        except KeyboardInterrupt:
            interrupted, note = True, "interrupted (Ctrl-C)"
        except cf.BrokenExecutor as exc:  # a worker died (killed, out of memory): keep what finished
            interrupted, note = True, f"a worker died ({type(exc).__name__}: {exc})"
        finally:
            if bar:
                bar.stop()
        name = "in-process" if executor is None else type(executor).__name__
        return BenchReport(
            self.options,
            self.scenario_options,
            self.planner_options,
            records,
            scenarios,
            time.perf_counter() - t_start,
            name,
            workers if executor is not None else 1,
            interrupted,
            note,
        )

    def _execute(self, tasks: list[_Task], executor: cf.Executor | None) -> Iterable[RunRecord]:
        if executor is None:
            init_worker(self.spec, self.options.planners)
            for task in tasks:
                yield run_task(self.spec, task)
            return
        futures = [executor.submit(run_task, self.spec, task) for task in tasks]
        try:
            for fut in cf.as_completed(futures):
                yield fut.result()
        finally:
            for fut in futures:
                fut.cancel()


def make_progress(options: BenchOptions, total: int, stream: TextIO | None = None) -> _Progress | _PlainProgress:
    """The progress display of a bench run of `total` runs: a rich bar when rich is installed (the
    [bench] extra) and no `stream` is given, else plain lines on `stream` (default stderr)."""
    if Progress is None or stream is not None:
        return _PlainProgress(options, total, sys.stderr if stream is None else stream)
    return _Progress(options, total)


class _Counts:
    """Finished, successful and rejected runs per planner; the text shown beside each planner."""

    def __init__(self, planners: Sequence[str]) -> None:
        self.ok = dict.fromkeys(planners, 0)
        self.done = dict.fromkeys(planners, 0)
        self.rejected = dict.fromkeys(planners, 0)

    def add(self, r: RunRecord) -> str:
        """Count run `r`; returns its planner's info text."""
        p = r.planner
        self.done[p] += 1
        self.ok[p] += int(r.is_success())
        self.rejected[p] += int(r.claimed and not r.verified)
        info = f"success {self.ok[p]}/{self.done[p]}"
        if self.rejected[p]:
            info += f", {self.rejected[p]} rejected"
        return info


class _PlainProgress:
    """Progress without rich: one line per planner each time another tenth of its runs has finished."""

    def __init__(self, options: BenchOptions, total: int, stream: TextIO) -> None:
        self.per = max(1, total // len(options.planners))
        self.counts = _Counts(options.planners)
        self.stream = stream

    def start(self) -> None:
        """Nothing to draw before the first run finishes."""

    def stop(self) -> None:
        self.stream.flush()

    def advance(self, r: RunRecord) -> None:
        info = self.counts.add(r)
        n = self.counts.done[r.planner]
        step = max(1, self.per // 10)  # about ten lines per planner, whatever the run count
        if n % step == 0 or n == self.per:
            label = LABELS.get(r.planner, r.planner)
            self.stream.write(f"bench: {label} {n}/{self.per}, {info}\n")
            self.stream.flush()


class _Progress:
    """A rich progress bar: one line per planner with its running success count."""

    def __init__(self, options: BenchOptions, total: int) -> None:
        self.progress = Progress(
            TextColumn("{task.description:<18}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
        )
        per = total // len(options.planners)
        self.tasks = {p: self.progress.add_task(LABELS.get(p, p), total=per, info="") for p in options.planners}
        self.counts = _Counts(options.planners)

    def start(self) -> None:
        self.progress.start()

    def stop(self) -> None:
        self.progress.stop()

    def advance(self, r: RunRecord) -> None:
        info = self.counts.add(r)
        self.progress.update(self.tasks[r.planner], advance=1, info=info)
