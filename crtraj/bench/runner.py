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
configuration space with the same validity checker, `crtraj.planning.ompl`).

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
import csv
import functools
import io
import json
import math
import os
import platform
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

from crtraj import __version__
from crtraj.bench.scenarios import Scenario, ScenarioGenerator, ScenarioOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import atomic_write_json, atomic_write_text
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.options import PlannerOptions
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.stop import StopCondition
from crtraj.world import packing
from crtraj.world.scene import Scene

PLANNERS = ("rrt", "rrtstar", "cspace", "ompl-rrtstar", "ompl-rrtconnect")
COUNTS = (1, 3, 5, 7)

LABELS = MappingProxyType(
    {
        "rrt": "RRT (Alg. 1)",
        "rrtstar": "RRT* (Alg. 1)",
        "cspace": "C-space (default)",
        "ompl-rrtstar": "OMPL RRTstar",
        "ompl-rrtconnect": "OMPL RRTConnect",
    }
)

# The paper's Table I (Luo et al., arXiv 2309.13813), i7-12700H laptop, Python.
PAPER_TABLE1: Mapping[str, dict[str, tuple[float, ...]]] = MappingProxyType(
    {
        "rrt": {
            "time_s": (3.05, 4.77, 5.55, 6.36),
            "success": (0.99, 0.97, 0.95, 0.90),
            "path_mm": (715.36, 736.11, 785.46, 743.36),
        },
        "rrtstar": {
            "time_s": (3.66, 4.82, 6.07, 7.30),
            "success": (0.99, 0.89, 0.78, 0.65),
            "path_mm": (609.07, 626.70, 625.46, 597.45),
        },
    }
)
PAPER_COUNTS = (1, 3, 5, 7)

# Dense samples are checked in chunks of this many (memory ~ chunk * points * obstacles * 24 bytes).
_CHUNK = 256
# The untimed warm-up query of every worker's planners: its scenario seed and time limit (s).
_WARMUP_SEED = 2**31 - 1
_WARMUP_TIME = 2.0
# A path may start this far (rad / mm, per entry) from the scenario's start configuration.
_START_TOL = 1e-6
# Limit violations below this count as round-off (same units as Robot.limit_violation).
_LIMIT_TOL = 1e-6


# --------------------------------------------------------------------- options
@dataclass(frozen=True)
class BenchOptions:
    """What to run and how to judge it (units mm, s).

    counts: obstacle counts (the table's columns). scenarios: scenarios per
    count. planners: names from `PLANNERS` (or registered extras).
    time_limit: wall-time budget per run (s), the same for every planner.
    seed: seed of the scenarios and of every planner run. goal_tolerance:
    tip-to-goal distance that counts as arrival (mm). verify_points:
    backbone points of the dense check. verify_dt: largest time between dense
    samples (s). verify_step: largest backbone-point motion between dense
    samples (mm). verify_margin: clearance to the sphere surfaces the dense
    check demands (mm; 0 = no contact; the planners themselves keep the
    scene's safety distance).
    """

    counts: tuple[int, ...] = COUNTS
    scenarios: int = 100
    planners: tuple[str, ...] = PLANNERS
    time_limit: float = 5.0
    seed: int = 0
    goal_tolerance: float = 1.0
    verify_points: int = 128
    verify_dt: float = 0.01
    verify_step: float = 1.0
    verify_margin: float = 0.0

    def __post_init__(self) -> None:
        counts = tuple(self.counts)
        if not counts or any(isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 0 for c in counts):
            raise InputError(f"counts: expected obstacle counts >= 0, got {list(counts)!r}")
        if len(set(counts)) != len(counts):
            raise InputError(f"counts: duplicate obstacle count in {list(counts)}")
        object.__setattr__(self, "counts", tuple(int(c) for c in counts))
        if isinstance(self.scenarios, bool) or not isinstance(self.scenarios, int) or self.scenarios < 1:
            raise InputError(f"scenarios: must be an integer >= 1, got {self.scenarios!r}")
        planners = tuple(self.planners)
        if not planners:
            raise InputError("planners: at least one planner is required")
        if len(set(planners)) != len(planners):
            raise InputError(f"planners: duplicate planner in {list(planners)}")
        object.__setattr__(self, "planners", planners)
        if not (math.isfinite(self.time_limit) and self.time_limit > 0):
            raise InputError(f"time_limit: must be a finite number > 0 (s), got {self.time_limit!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"seed: must be an integer >= 0, got {self.seed!r}")
        if not (math.isfinite(self.goal_tolerance) and self.goal_tolerance > 0):
            raise InputError(f"goal_tolerance: must be > 0 mm, got {self.goal_tolerance!r}")
        if isinstance(self.verify_points, bool) or not isinstance(self.verify_points, int) or self.verify_points < 2:
            raise InputError(f"verify_points: must be an integer >= 2, got {self.verify_points!r}")
        for key in ("verify_dt", "verify_step"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{key}: must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.verify_margin) and self.verify_margin >= 0):
            raise InputError(f"verify_margin: must be >= 0 mm, got {self.verify_margin!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["counts"] = list(self.counts)
        d["planners"] = list(self.planners)
        return d


# ------------------------------------------------------------- dense check
@dataclass(frozen=True)
class DenseCheck:
    """Verdict of the independent dense check on one returned path.

    ok: the path passes every test. reason: why not ("" when ok).
    min_clearance: smallest body-surface to sphere-surface distance (mm).
    t_worst: when it occurs (s). length: tip travel (mm). goal_error: final
    tip to goal (mm). samples: dense samples checked.
    """

    ok: bool
    reason: str
    min_clearance: float
    t_worst: float
    length: float
    goal_error: float
    samples: int


def _dense_samples(T: np.ndarray, X: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (S,), configurations (S, nx) and straight-motion index (S,) with n[i] steps on motion i."""
    K = len(T)
    if K == 1:
        return T.copy(), X.copy(), np.zeros(1, dtype=int)
    seg = np.repeat(np.arange(K - 1), n)
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    tau = (np.arange(n.sum()) - np.repeat(starts, n)) / n[seg]
    times = np.concatenate([T[seg] + tau * (T[seg + 1] - T[seg]), T[-1:]])
    configs = np.concatenate([X[seg] + tau[:, None] * (X[seg + 1] - X[seg]), X[-1:]])
    return times, configs, np.concatenate([seg, [K - 2]])


def _dense_path(
    model: Model, T: np.ndarray, X: np.ndarray, n_points: int, dt: float, ds: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense (times, configurations, backbone points): consecutive samples at most dt apart in time
    and ds apart in every backbone point (refined until true, at most 4 passes, then kept as is)."""
    if len(T) == 1:
        return T.copy(), X.copy(), model.points(X, n_points)
    n = np.maximum(1, np.ceil(np.diff(T) / dt)).astype(int)
    for _ in range(4):
        times, configs, seg = _dense_samples(T, X, n)
        pts = model.points(configs, n_points)  # (S, n_points, 3)
        move = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max(axis=-1)  # (S-1,), step k in motion seg[k]
        worst = np.zeros(len(n))
        np.maximum.at(worst, seg[:-1], move)
        factor = np.ceil(worst / ds).astype(int)
        if np.all(factor <= 1):
            break
        n = n * np.maximum(factor, 1)
    return times, configs, pts


def dense_check(
    model: Model,
    scene: Scene,
    result: PlanResult,
    start: np.ndarray,
    goal: np.ndarray,
    *,
    goal_tolerance: float = 1.0,
    n_points: int = 128,
    dt: float = 0.01,
    step: float = 1.0,
    margin: float = 0.0,
    t0: float = 0.0,
) -> DenseCheck:
    """Check a returned path independently of any planner (module docstring)."""
    nan = float("nan")

    def fail(reason: str, clr: float = nan, tw: float = nan, length: float = nan, ge: float = nan, s: int = 0):
        return DenseCheck(False, reason, clr, tw, length, ge, s)

    T = np.asarray(result.t, dtype=float).reshape(-1)
    X = np.asarray(result.configs, dtype=float)
    if len(T) == 0 or X.ndim != 2 or X.shape[0] != len(T) or X.shape[1] != model.nx:
        return fail(f"no usable path ({len(T)} times, configs of shape {X.shape})")
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(X))):
        return fail("path contains NaN or infinity")
    if np.any(np.diff(T) < 0.0):
        return fail("waypoint times decrease")
    if abs(T[0] - t0) > 1e-9:
        return fail(f"path starts at t = {T[0]:.6g} s, not at {t0:g} s")
    if np.max(np.abs(X[0] - np.asarray(start, dtype=float))) > _START_TOL:
        return fail("path does not start at the start configuration")
    times, configs, points = _dense_path(model, T, X, n_points, dt, step)
    limit = model.robot.limit_violation(configs)
    if np.max(limit) > _LIMIT_TOL:
        i = int(np.argmax(limit))
        return fail(f"out of the robot's limits at t = {times[i]:.3f} s (violation {limit[i]:.3g})", s=len(times))
    min_clr, t_worst = math.inf, nan
    length = 0.0
    prev_tip: np.ndarray | None = None
    body = model.robot.body_radius
    for a in range(0, len(times), _CHUNK):
        tc, pts = times[a : a + _CHUNK], points[a : a + _CHUNK]  # (C,), (C, n, 3)
        tips = pts[:, -1, :]
        steps = np.linalg.norm(np.diff(tips, axis=0), axis=-1).sum()
        if prev_tip is not None:
            steps += np.linalg.norm(tips[0] - prev_tip)
        length += float(steps)
        prev_tip = tips[-1]
        if scene.n_obstacles == 0:
            continue
        centers, radii = scene.states(tc)  # (C, M, 3), (C, M)
        A = pts[:, :-1, None, :]  # (C, n-1, 1, 3)
        AB = pts[:, 1:, None, :] - A
        AC = centers[:, None, :, :] - A  # (C, n-1, M, 3)
        den = np.maximum(np.einsum("...k,...k->...", AB, AB), 1e-300)
        u = np.clip(np.einsum("...k,...k->...", AC, AB) / den, 0.0, 1.0)
        dist = np.linalg.norm(AC - u[..., None] * AB, axis=-1)  # (C, n-1, M)
        clr = (dist.min(axis=1) - radii).min(axis=-1) - body  # (C,)
        i = int(np.argmin(clr))
        if clr[i] < min_clr:
            min_clr, t_worst = float(clr[i]), float(tc[i])
    goal_error = float(np.linalg.norm(model.tip_position(X[-1]) - np.asarray(goal, dtype=float)))
    if min_clr <= margin:
        what = "collides with an obstacle" if min_clr <= 0.0 else f"comes within {margin:g} mm of an obstacle"
        return fail(
            f"{what} at t = {t_worst:.3f} s (clearance {min_clr:.3f} mm)",
            min_clr,
            t_worst,
            length,
            goal_error,
            len(times),
        )
    if goal_error > goal_tolerance + 1e-9:
        return fail(
            f"ends {goal_error:.3f} mm from the goal (tolerance {goal_tolerance:g} mm)",
            min_clr,
            t_worst,
            length,
            goal_error,
            len(times),
        )
    return DenseCheck(True, "", min_clr, t_worst, length, goal_error, len(times))


# ---------------------------------------------------------------- planners
class BenchPlanner(Protocol):
    """What the bench needs from a planner: one query, one `PlanResult`."""

    def plan(self, scenario: Scenario, *, time_limit: float, seed: int, goal_tolerance: float) -> PlanResult: ...


PlannerFactory = Callable[[Model, PlannerOptions], BenchPlanner]


_CRTRAJ = ("rrt", "rrtstar", "cspace")


class _CrtrajPlanner:
    """One of crtraj's planners (`crtraj.planning.rrt.make_planner`), stopped by the bench's time limit
    and the options' other limits (iterations, first solution)."""

    def __init__(self, model: Model, options: PlannerOptions, algorithm: str) -> None:
        from crtraj.planning.rrt import make_planner

        self.options = options.with_(algorithm=algorithm)
        self.planner = make_planner(model, Scene(), self.options, max_obstacles=packing.SLOTS)

    def plan(self, scenario: Scenario, *, time_limit: float, seed: int, goal_tolerance: float) -> PlanResult:
        o = self.options
        stop = StopCondition(time_limit=time_limit, max_iterations=o.max_iterations, first_solution=o.first_solution)
        return self.planner.plan(
            scenario.goal,
            start_config=scenario.start,
            scene=scenario.scene,
            stop=stop,
            seed=seed,
            goal_tolerance=goal_tolerance,
        )


class _OMPLBenchPlanner:
    """OMPL's planners through `crtraj.planning.ompl.OMPLPlanner`; anytime planners use the whole budget."""

    def __init__(self, model: Model, options: PlannerOptions, algorithm: str) -> None:
        from crtraj.planning.ompl import OMPLPlanner

        self.planner = OMPLPlanner(model, Scene(), options, algorithm=algorithm)

    def plan(self, scenario: Scenario, *, time_limit: float, seed: int, goal_tolerance: float) -> PlanResult:
        return self.planner.plan(
            scenario.goal,
            start_config=scenario.start,
            scene=scenario.scene,
            stop=StopCondition(time_limit=time_limit),
            seed=seed,
            goal_tolerance=goal_tolerance,
        )


def check_available(name: str) -> None:
    """Raise `InputError` when a built-in planner cannot be imported here."""
    if name in _CRTRAJ:
        try:
            from crtraj.planning.rrt import make_planner  # noqa: F401
        except ImportError as exc:
            raise InputError(f"planners: {name} is not available ({exc})") from None
    elif name in ("ompl-rrtstar", "ompl-rrtconnect"):
        from crtraj.planning.ompl import import_ompl

        import_ompl()


def _builtin(name: str) -> PlannerFactory:
    if name in _CRTRAJ:
        return functools.partial(_CrtrajPlanner, algorithm=name)
    if name == "ompl-rrtstar":
        return functools.partial(_OMPLBenchPlanner, algorithm="RRTstar")
    if name == "ompl-rrtconnect":
        return functools.partial(_OMPLBenchPlanner, algorithm="RRTConnect")
    raise InputError(f"planners: unknown planner {name!r}; choose from {', '.join(PLANNERS)}")


# ------------------------------------------------------------------ records
@dataclass(frozen=True)
class RunRecord:
    """One planner on one scenario: a row of runs.csv (units s, mm).

    claimed: the planner reported an exact solution. verified: the dense
    check accepted the path. success: both. time_s: the planner's wall time.
    """

    planner: str
    n_obstacles: int
    index: int
    seed: int
    status: str
    claimed: bool
    verified: bool
    success: bool
    time_s: float
    length_mm: float
    min_clearance_mm: float
    goal_error_mm: float
    duration_s: float
    waypoints: int
    worker: str
    message: str
    check: str

    @classmethod
    def fields(cls) -> list[str]:
        return list(cls.__dataclass_fields__)


@dataclass(frozen=True)
class WorkerSpec:
    """Plain, hashable data that lets any worker rebuild the model and planners."""

    robot_json: str
    planner_options_json: str
    extra: tuple[tuple[str, PlannerFactory], ...] = ()

    def factory(self, name: str) -> PlannerFactory:
        for n, f in self.extra:
            if n == name:
                return f
        return _builtin(name)


class _WorkerContext:
    """The model and the planners of one worker, built once."""

    def __init__(self, spec: WorkerSpec) -> None:
        robot = Robot.from_table(Table(json.loads(spec.robot_json), "robot"))
        self.spec = spec
        self.model = Model(robot)
        t = Table(json.loads(spec.planner_options_json), "planner")
        self.options = PlannerOptions.from_table(t)
        self._planners: dict[str, BenchPlanner] = {}

    def planner(self, name: str) -> BenchPlanner:
        """The named planner, built and warmed up on first use (never inside a timed run)."""
        p = self._planners.get(name)
        if p is None:
            p = self.spec.factory(name)(self.model, self.options)
            # One untimed query builds what planners build lazily (NLP solvers, CasADi maps),
            # so the first timed run does not pay for it.
            warm = ScenarioGenerator(self.model, ScenarioOptions(seed=_WARMUP_SEED)).generate(1, 0)
            p.plan(warm, time_limit=_WARMUP_TIME, seed=0, goal_tolerance=1.0)
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
    verify: tuple[int, float, float, float]  # points, dt, step, margin


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
    }
    try:
        planner = ctx.planner(task.planner)
    except InputError as exc:
        return _error_record(base, f"planner unavailable: {exc}")
    t1 = time.perf_counter()
    try:
        result = planner.plan(scenario, time_limit=task.time_limit, seed=task.seed, goal_tolerance=task.goal_tolerance)
    except InputError as exc:  # a planner refusing its input is a failed run, not a crashed bench
        return _error_record(base, f"planner refused the query: {exc}", time.perf_counter() - t1)
    except Exception as exc:  # a crash is recorded (status "error", with its text) and the sweep goes on
        return _error_record(base, f"planner raised {type(exc).__name__}: {exc}", time.perf_counter() - t1)
    elapsed = time.perf_counter() - t1
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
    """A `RunRecord` for one planner result: success only when claimed AND densely verified."""
    nan = float("nan")
    claimed = bool(result.status is PlanStatus.EXACT)
    n_pts, dt, step, margin = task.verify
    check: DenseCheck | None = None
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
            margin=margin,
        )
    verified = bool(check is not None and check.ok)
    return RunRecord(
        **base,
        status=str(result.status),
        claimed=claimed,
        verified=verified,
        success=claimed and verified,
        time_s=float(elapsed),
        length_mm=check.length if verified and check else nan,
        min_clearance_mm=check.min_clearance if check else nan,
        goal_error_mm=check.goal_error if check else float(result.goal_error),
        duration_s=float(result.duration) if result.has_path else nan,
        waypoints=len(result.t),
        message=str(result.message),
        check="ok" if verified else (check.reason if check else "not checked (no exact solution claimed)"),
    )


def _run_seed(seed: int, n_obstacles: int, index: int, planner_slot: int) -> int:
    return int(np.random.SeedSequence([seed, n_obstacles, index, planner_slot]).generate_state(1)[0])


# ------------------------------------------------------------------ report
def _fmt(v: float, digits: int = 2) -> str:
    return "—" if not math.isfinite(v) else f"{v:.{digits}f}"


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{100.0 * v:.0f}%"


@dataclass
class BenchReport:
    """All records of a run, the statistics the table shows, and the files."""

    options: BenchOptions
    scenario_options: ScenarioOptions
    planner_options: PlannerOptions
    records: list[RunRecord]
    scenarios: list[Scenario]
    wall_time: float
    executor: str
    workers: int
    interrupted: bool = False
    note: str = ""
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))

    # ------------------------------------------------------------- figures
    def stats(self, planner: str, n_obstacles: int) -> dict[str, float]:
        """mean/median/p90 time (s) over all runs, success rate, mean/median length (mm) of successes."""
        rows = [r for r in self.records if r.planner == planner and r.n_obstacles == n_obstacles]
        nan = float("nan")
        if not rows:
            return {
                "runs": 0,
                "success": nan,
                "time_mean": nan,
                "time_median": nan,
                "time_p90": nan,
                "length_mean": nan,
                "length_median": nan,
                "rejected": 0,
            }
        times = np.array([r.time_s for r in rows], dtype=float)
        times = times[np.isfinite(times)]
        lengths = np.array([r.length_mm for r in rows if r.success], dtype=float)
        return {
            "runs": len(rows),
            "success": float(np.mean([r.success for r in rows])),
            "time_mean": float(times.mean()) if len(times) else nan,
            "time_median": float(np.median(times)) if len(times) else nan,
            "time_p90": float(np.percentile(times, 90)) if len(times) else nan,
            "length_mean": float(lengths.mean()) if len(lengths) else nan,
            "length_median": float(np.median(lengths)) if len(lengths) else nan,
            "rejected": sum(1 for r in rows if r.claimed and not r.verified),
        }

    def paired_lengths(self, a: str, b: str, n_obstacles: int) -> tuple[int, float]:
        """Scenarios both planners solved: (count, mean of length_a / length_b)."""
        la = {
            r.index: r.length_mm for r in self.records if r.planner == a and r.n_obstacles == n_obstacles and r.success
        }
        lb = {
            r.index: r.length_mm for r in self.records if r.planner == b and r.n_obstacles == n_obstacles and r.success
        }
        both = sorted(set(la) & set(lb))
        if not both:
            return 0, float("nan")
        return len(both), float(np.mean([la[i] / lb[i] for i in both]))

    # --------------------------------------------------------------- files
    def markdown(self) -> str:
        o = self.options
        counts = o.counts
        planners = [p for p in o.planners]
        out = io.StringIO()
        w = out.write
        w("# Table I — planners on the paper's random dynamic scenes\n\n")
        w(
            f"crtraj {__version__}, {self.created}, {platform.node()} ({platform.machine()}, "
            f"{os.cpu_count()} logical CPUs, {platform.python_implementation()} {platform.python_version()}); "
            f"{self.executor} with {self.workers} worker(s); whole run {self.wall_time:.0f} s.\n\n"
        )
        w(
            f"{o.scenarios} scenarios per obstacle count (seed {o.seed}), time limit {o.time_limit:g} s per run, "
            f"goal tolerance {o.goal_tolerance:g} mm. Every claimed success was re-checked densely "
            f"({o.verify_points} backbone points, <= {o.verify_dt:g} s and <= {o.verify_step:g} mm between "
            f"samples, clearance > {o.verify_margin:g} mm); a success it rejects counts as a failure.\n\n"
        )
        if self.interrupted:
            w(f"**Incomplete — {self.note}: the table covers only the {len(self.records)} runs that finished.**\n\n")
        paper_cols = {c: PAPER_COUNTS.index(c) for c in counts if c in PAPER_COUNTS}

        def paper(planner: str, key: str, c: int) -> float:
            if planner not in PAPER_TABLE1 or c not in paper_cols:
                return float("nan")
            return PAPER_TABLE1[planner][key][paper_cols[c]]

        # --- the paper's layout: time (s) / success per count
        w("## Time (s) / success\n\n")
        w('Mean wall time per run over all runs (the paper\'s "average running time"), and the success rate.\n\n')
        w("| Method | " + " | ".join(f"{c} obs: time (s) | {c} obs: succ" for c in counts) + " |\n")
        w("|---|" + "---:|---:|" * len(counts) + "\n")
        for p in planners:
            if p in PAPER_TABLE1 and paper_cols:
                cells = [f"{_fmt(paper(p, 'time_s', c))} | {_pct(paper(p, 'success', c))}" for c in counts]
                w(f"| {LABELS.get(p, p)} — paper | " + " | ".join(cells) + " |\n")
            cells = []
            for c in counts:
                s = self.stats(p, c)
                cells.append(f"{_fmt(s['time_mean'], 3)} | {_pct(s['success'])}")
            w(f"| {LABELS.get(p, p)} — crtraj | " + " | ".join(cells) + " |\n")
        # --- average path length
        w("\n## Average path length (mm) of successful runs\n\n")
        w("| Method | " + " | ".join(f"{c} obs" for c in counts) + " |\n")
        w("|---|" + "---:|" * len(counts) + "\n")
        for p in planners:
            if p in PAPER_TABLE1 and paper_cols:
                w(
                    f"| {LABELS.get(p, p)} — paper | "
                    + " | ".join(_fmt(paper(p, "path_mm", c)) for c in counts)
                    + " |\n"
                )
            w(
                f"| {LABELS.get(p, p)} — crtraj | "
                + " | ".join(_fmt(self.stats(p, c)["length_mean"]) for c in counts)
                + " |\n"
            )
        # --- spread
        w("\n## Time spread (s): median / p90, and claimed successes the dense check rejected\n\n")
        w("| Method | " + " | ".join(f"{c} obs" for c in counts) + " |\n")
        w("|---|" + "---:|" * len(counts) + "\n")
        for p in planners:
            cells = []
            for c in counts:
                s = self.stats(p, c)
                cells.append(f"{_fmt(s['time_median'], 3)} / {_fmt(s['time_p90'], 3)} ({s['rejected']} rej.)")
            w(f"| {LABELS.get(p, p)} | " + " | ".join(cells) + " |\n")
        # --- paired length ratios against OMPL RRTstar
        others = [p for p in planners if p != "cspace"]
        if "cspace" in planners and others:
            w("\n## Path length of the default planner relative to each other planner (scenarios both solved)\n\n")
            w("Mean over the scenarios both solved of length(C-space) / length(other); below 1: C-space is shorter.\n")
            w("\n")
            w("| Other planner | " + " | ".join(f"{c} obs" for c in counts) + " |\n")
            w("|---|" + "---:|" * len(counts) + "\n")
            for p in others:
                cells = []
                for c in counts:
                    n, ratio = self.paired_lengths("cspace", p, c)
                    cells.append(f"{_fmt(ratio, 3)} (n={n})")
                w(f"| {LABELS.get(p, p)} | " + " | ".join(cells) + " |\n")
        w(
            "\nTimes were measured with the workers sharing the machine; the paper's figures come from an "
            "Intel i7-12700H laptop.\n"
        )
        return out.getvalue()

    def csv_text(self) -> str:
        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=RunRecord.fields(), lineterminator="\n")
        wr.writeheader()
        for r in sorted(self.records, key=lambda r: (r.n_obstacles, r.index, r.planner)):
            row = asdict(r)
            for k, v in row.items():
                if isinstance(v, float):
                    row[k] = "" if not math.isfinite(v) else f"{v:.6g}"
            wr.writerow(row)
        return buf.getvalue()

    def write(self, out_dir: str | os.PathLike[str]) -> list[Path]:
        """Write table1.md, runs.csv and scenarios.json into out_dir (atomically)."""
        d = Path(out_dir)
        files = [
            atomic_write_text(d / "table1.md", self.markdown()),
            atomic_write_text(d / "runs.csv", self.csv_text()),
            atomic_write_json(
                d / "scenarios.json",
                {
                    "crtraj_version": __version__,
                    "created": self.created,
                    "bench": self.options.to_dict(),
                    "generator": self.scenario_options.to_dict(),
                    "planner": self.planner_options.to_dict(),
                    "scenarios": [s.to_dict() for s in self.scenarios],
                },
            ),
        ]
        return files


# ------------------------------------------------------------------- bench
class Table1Bench:
    """The paper's Table I on crtraj's scenario generator, for any set of planners.

    robot: the robot (default file: problems/robots/cdsr2.toml). options:
    what to run. scenario_options: the generator's bounds (seed taken from
    options.seed). planner_options: shared settings of every planner (max
    speed, collision resolution, check points: the same validity checker for
    crtraj's and OMPL's planners). extra_planners: name -> factory
    ``(model, planner_options) -> object with plan(scenario, *, time_limit,
    seed, goal_tolerance) -> PlanResult``; a factory must be picklable (a
    module-level function or class) to run in worker processes.
    """

    def __init__(
        self,
        robot: Robot,
        options: BenchOptions | None = None,
        *,
        scenario_options: ScenarioOptions | None = None,
        planner_options: PlannerOptions | None = None,
        extra_planners: dict[str, PlannerFactory] | None = None,
    ) -> None:
        self.robot = robot
        self.options = options or BenchOptions()
        so = scenario_options or ScenarioOptions()
        self.scenario_options = replace(so, seed=self.options.seed)
        self.planner_options = planner_options or PlannerOptions()
        extra = dict(extra_planners or {})
        for name in self.options.planners:
            if name not in extra:
                _builtin(name)  # unknown names fail here, before any work starts
        self.spec = WorkerSpec(
            robot_json=json.dumps(robot.to_dict(), sort_keys=True),
            planner_options_json=json.dumps(self.planner_options.to_dict(), sort_keys=True),
            extra=tuple(sorted(extra.items())),
        )
        self._model: Model | None = None

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
        for sc in scenarios:
            d = sc.to_dict()
            for k, p in enumerate(o.planners):
                seed = _run_seed(o.seed, sc.n_obstacles, sc.index, k)
                out.append(_Task(p, d, seed, o.time_limit, o.goal_tolerance, verify))
        return out

    def run(
        self,
        executor: cf.Executor | None = None,
        *,
        workers: int = 1,
        progress: bool = True,
        on_record: Callable[[RunRecord], None] | None = None,
    ) -> BenchReport:
        """Run every planner on every scenario; returns the report (not yet written).

        executor: any `concurrent.futures.Executor` (process pool, Dask
        ``client.get_executor()``, ...); None runs everything here, one by
        one. workers: only for the report's header. progress: draw a rich
        progress bar. On Ctrl-C the pending runs are cancelled and the report
        holds the finished ones (``interrupted=True``).
        """
        t_start = time.perf_counter()
        scenarios = self.scenarios()
        tasks = self.tasks(scenarios)
        records: list[RunRecord] = []
        interrupted, note = False, ""
        bar = _Progress(self.options, len(tasks)) if progress else None
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


class _Progress:
    """A rich progress bar: one line per planner with its running success count."""

    def __init__(self, options: BenchOptions, total: int) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

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
        self.ok = dict.fromkeys(options.planners, 0)
        self.done = dict.fromkeys(options.planners, 0)
        self.rejected = dict.fromkeys(options.planners, 0)

    def start(self) -> None:
        self.progress.start()

    def stop(self) -> None:
        self.progress.stop()

    def advance(self, r: RunRecord) -> None:
        p = r.planner
        self.done[p] += 1
        self.ok[p] += int(r.success)
        self.rejected[p] += int(r.claimed and not r.verified)
        info = f"success {self.ok[p]}/{self.done[p]}"
        if self.rejected[p]:
            info += f", {self.rejected[p]} rejected"
        self.progress.update(self.tasks[p], advance=1, info=info)


# --------------------------------------------------------------------- CLI
def _parse_list(text: str, name: str, conv: Callable[[str], Any]) -> tuple[Any, ...]:
    try:
        items = tuple(conv(s.strip()) for s in text.split(",") if s.strip())
    except ValueError:
        raise InputError(f"{name}: expected a comma-separated list, got {text!r}") from None
    if not items:
        raise InputError(f"{name}: empty list")
    return items


def run_cli(args: Any) -> int:
    """`crtraj bench table1 ...` (arguments from `crtraj.cli`); returns the exit code."""
    from crtraj.io.problem import load_robot, read_toml

    workers = os.cpu_count() or 1 if args.workers is None else args.workers
    if workers < 0:
        raise InputError(f"--workers: must be >= 0 (0 = run in this process), got {workers}")
    planners = _parse_list(args.planners, "--planners", str) if args.planners else PLANNERS
    options = BenchOptions(
        counts=_parse_list(args.counts, "--counts", int),
        scenarios=args.scenarios,
        planners=planners,
        time_limit=args.time_limit,
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
        check_available(name)  # fail now, in one line, not in every worker
    bench = Table1Bench(robot, options, planner_options=planner_options)
    out = Path(args.out)
    total = len(options.counts) * options.scenarios * len(planners)
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
        import multiprocessing

        executor = cf.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=bench.initializer,
            initargs=bench.initargs,
        )
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
