"""A harder, held-out dynamic suite beyond Table I: six seeded scene families, four methods, one strict judge.

Families (each a parameterised generator; scenario i belongs to family ``FAMILIES[i % 6]`` and is drawn from
its own ``numpy.random.Generator`` seeded with ``(seed, family number, i)``, so any one can be regenerated alone):

- ``fast``: three paper-style obstacles (Table I's generator, `crtraj.bench.scenarios`) whose centres move at a
  mean speed drawn from [15, 45) mm/s: up to 3x the paper's "under 15 mm/s".
- ``closing``: two spheres on either side of the straight start -> goal line that grow from their smallest
  radius until they overlap (the passage between them closes, at t = pi / omega) and shrink again (it
  reopens), radius A + B sin(omega t - pi/2) with B in [12, 20] mm: the gap between the surfaces is
  g_open in [26, 46] mm (room for the 16 mm the body and D_sf need) at the smallest radii and g_open - 4 B < 0
  at the largest.
- ``narrow_gap``: two static spheres whose surfaces leave a gap of 2 (body radius + D_sf) + w, w in [2, 10] mm,
  centred on the straight start -> goal line.
- ``goal_sweep``: one sphere (radius 25-40 mm) that moves in a straight line, once, right across the goal tip
  (10-30 mm/s) and then rests beyond it; a path that arrives early is hit while it waits, which the hold
  check below catches.
- ``crowded``: 10 to 15 paper-style obstacles, smaller (radius 15-25 mm +- 3-8 mm).
- ``boundary``: start and goal tips within 2-20 mm of one side of the workspace box (x or y = +-150 mm),
  three paper-style obstacles.

Every scenario is feasible at t = 0: the start body keeps D_sf over the first second and the goal witness
configuration's body keeps it at t = 0 (128 backbone points, with the spacing's slack on top; families
whose obstacles cover the goal later are checked where it matters: ``closing`` at the largest radii,
``goal_sweep`` after the sweep).

Judge (the same for every method): a run succeeds only if the dense check (`crtraj.bench.check`) finds the
body's surface more than D_sf from every sphere surface along the path AND while it then holds its final
configuration for ``hold_time`` s (longer for ``goal_sweep``: until the sweeper has come to rest), and the tip
ends within the goal tolerance. The closed-loop replanner (`crtraj.control.loop.ClosedLoop`) is judged on
its executed motion (every dense verification sample, re-checked the same way) and on arrival within
``replan_duration`` s of simulated time; its time is that arrival time, not planning time.
Units mm, rad, s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from crtraj.bench.check import dense_check
from crtraj.bench.runner import WARMUP_TIME, bench_stop, plan_scenario, warm_up
from crtraj.bench.scenarios import MAX_INDEX, Scenario, ScenarioGenerator, ScenarioOptions
from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop, LoopOptions, PlannerReference
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_SEED, MAX_TIME, Table
from crtraj.core.options import Options, option
from crtraj.hardware.actuators import Actuators
from crtraj.model.kinematics import Model
from crtraj.planning.base import Planner
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import BUILTIN
from crtraj.planning.result import PlanResult
from crtraj.planning.stop import StopCondition
from crtraj.world import packing
from crtraj.world.margin import DEFAULT_SAFETY_DISTANCE
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

FAMILIES = ("fast", "closing", "narrow_gap", "goal_sweep", "crowded", "boundary")
REPLANNER = "replanner"
METHODS = ("cspace", "rrtstar", "ompl-rrtconnect")
# Most scenarios of one suite run (the runs are sequential; 20 take minutes).
MAX_SCENARIOS = 10_000
# Most draws of one scenario's free parameters before the family gives up (one-line error).
_MAX_DRAWS = 500
# Screen points along the body, as in crtraj.bench.scenarios.
_SCREEN_POINTS = 128
# The receding-horizon loop's settings: those of problems/paper_dynamic.toml (tuned there).
_REPLAN = {
    "horizon": 10,
    "dt": 0.1,
    "points": 16,
    "margin": 1.5,
    "solver": "sqp",
    "qpsol": "daqp",
    "max_cable_speed": 8.0,
    "max_z_speed": 16.0,
}


@dataclass(frozen=True)
class SuiteOptions(Options):
    """What the suite runs (units mm, s); the ``[suite]`` section.

    scenarios: total scenarios, spread over the families in turn. seed: of the scenes and the runs.
    time_limit: wall-time budget of one planner run (s). planners: registry names. replanner: also run
    the closed loop. replan_duration: simulated time within which the loop must arrive (s).
    planner_time: wall-time budget of each reference plan inside the loop (s). goal_tolerance: mm.
    hold_time: s the final configuration must stay clear after the path ends. verify_points,
    verify_dt, verify_step: the dense check's backbone points, largest time step (s) and largest
    backbone-point motion between samples (mm).
    """

    SECTION: ClassVar[str] = "suite"

    scenarios: int = option(20, ge=1, le=MAX_SCENARIOS)
    seed: int = option(0, ge=0, le=MAX_SEED)
    time_limit: float = option(5.0, gt=0.0, le=MAX_TIME)
    planners: tuple[str, ...] = option(METHODS, read=False)
    replanner: bool = option(True)
    replan_duration: float = option(30.0, gt=0.0, le=600.0)
    planner_time: float = option(1.0, gt=0.0, le=60.0)
    goal_tolerance: float = option(1.0, gt=0.0, le=100.0)
    hold_time: float = option(5.0, ge=0.0, le=MAX_TIME)
    verify_points: int = option(128, ge=2, le=1000)
    verify_dt: float = option(0.01, gt=0.0, le=1.0)
    verify_step: float = option(1.0, gt=0.0, le=100.0)

    def _check(self) -> None:
        p = self.planners
        if not isinstance(p, (tuple, list)) or len(p) > 16 or len(set(p)) != len(p):
            raise InputError(f"suite.planners: expected at most 16 distinct planner names, got {p!r:.80}")
        for name in p:
            BUILTIN.spec(name)
        object.__setattr__(self, "planners", tuple(p))

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        v = t.raw("planners", METHODS)
        if not isinstance(v, (list, tuple)):
            raise t.error("planners", f"expected a list, got {v!r:.60}")
        return {"planners": tuple(v)}


@dataclass(frozen=True, eq=False)
class SuiteScenario:
    """One scene of the suite: its family, the parameters drawn for it, and the query (`Scenario`).

    hold_until: the final configuration must stay clear until at least this time (s; 0: only
    `SuiteOptions.hold_time` after the path ends).
    """

    family: str
    params: dict[str, float]
    scenario: Scenario
    hold_until: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain data that re-creates the scene exactly (`from_dict`)."""
        return {
            "family": self.family,
            "params": dict(self.params),
            "hold_until": self.hold_until,
            **self.scenario.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SuiteScenario:
        t = Table(d, "suite scenario")
        family = t.str("family")
        if family not in FAMILIES:
            raise InputError(f"suite scenario.family: unknown {family!r}; choose from {', '.join(FAMILIES)}")
        params = t.raw("params", {})
        if not isinstance(params, dict) or not all(isinstance(v, (int, float)) for v in params.values()):
            raise InputError("suite scenario.params: expected a table of numbers")
        hold = t.float("hold_until", 0.0, ge=0.0, limit=MAX_TIME)
        rest = {k: d[k] for k in d if k not in ("family", "params", "hold_until")}
        return cls(family, {k: float(v) for k, v in params.items()}, Scenario.from_dict(rest), hold)


# ------------------------------------------------------------------ generation
class SuiteGenerator:
    """Draws the suite's scenarios for one robot (module docstring lists every family)."""

    def __init__(self, model: Model, seed: int = 0, safety_distance: float = DEFAULT_SAFETY_DISTANCE) -> None:
        self.model = model
        self.seed = int(seed)
        self.safety_distance = float(safety_distance)
        self._slack = model.robot.total_length / (2.0 * (_SCREEN_POINTS - 1))

    def generate(self, index: int) -> SuiteScenario:
        """Scenario number `index` (its family is ``FAMILIES[index % len(FAMILIES)]``)."""
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index <= MAX_INDEX:
            raise InputError(f"index: must be an integer in [0, {MAX_INDEX}], got {index!r}")
        k = int(index) % len(FAMILIES)
        family = FAMILIES[k]
        rng = np.random.default_rng([self.seed, k, int(index)])
        make: Callable[[np.random.Generator, int], SuiteScenario] = getattr(self, f"_{family}")
        return make(rng, int(index))

    def generate_all(self, n: int) -> list[SuiteScenario]:
        return [self.generate(i) for i in range(n)]

    # ----------------------------------------------------------- helpers
    def _paper_like(self, rng: np.random.Generator, index: int, n: int, **bounds: Any) -> Scenario:
        """A Table I scenario with `n` obstacles, drawn with `bounds` instead of the paper's."""
        seed = int(rng.integers(0, MAX_SEED))
        opts = ScenarioOptions(seed=seed, safety_distance=self.safety_distance, **bounds)
        return replace(ScenarioGenerator(self.model, opts).generate(n, index), seed=seed)

    def _query(self, rng: np.random.Generator, index: int) -> Scenario:
        """A start and goal without obstacles (start and goal tips at least 150 mm apart)."""
        return self._paper_like(rng, index, 0)

    def _clear(self, scene: Scene, x: np.ndarray, t0: float, t1: float) -> bool:
        """x's body keeps D_sf (plus the screen points' slack) over [t0, t1]."""
        c = scene.clearance_over(self.model, x, t0, t1, n_points=_SCREEN_POINTS)
        return bool(float(c) >= self._slack)

    def _feasible(self, scene: Scene, q: Scenario, goal_times: Sequence[tuple[float, float]] = ((0.0, 0.0),)) -> bool:
        """Start body clear over the first second, goal witness body clear over every window given."""
        if not self._clear(scene, q.start, 0.0, 1.0):
            return False
        return all(self._clear(scene, q.goal_config, a, b) for a, b in goal_times)

    def _with(self, q: Scenario, scene: Scene) -> Scenario:
        return replace(q, scene=scene, n_obstacles=scene.n_obstacles)

    def _gap_pair(
        self, rng: np.random.Generator, q: Scenario, radii: tuple[float, float], gap: float, **radius: Any
    ) -> tuple[Obstacle, Obstacle]:
        """Two spheres on either side of a point of the start -> goal line whose surfaces are `gap` mm apart
        at the given radii (extra `radius` fields: amplitude, omega, phase)."""
        seg = q.goal - q.start_tip
        e = seg / np.linalg.norm(seg)
        while True:
            v = rng.normal(size=3)
            v -= v.dot(e) * e
            if np.linalg.norm(v) > 1e-6:
                v /= np.linalg.norm(v)
                break
        m = q.start_tip + rng.uniform(0.4, 0.6) * seg
        r1, r2 = radii
        c1 = m + (r1 + 0.5 * gap) * v
        c2 = m - (r2 + 0.5 * gap) * v
        return (
            Obstacle(center=tuple(map(float, c1)), radius=float(radii[0]), name="gap_a", **radius),
            Obstacle(center=tuple(map(float, c2)), radius=float(radii[1]), name="gap_b", **radius),
        )

    def _give_up(self, family: str, index: int) -> InputError:
        return InputError(f"suite: no feasible {family} scenario {index} after {_MAX_DRAWS} draws (robot too small?)")

    # ----------------------------------------------------------- families
    def _fast(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        q = self._paper_like(rng, index, 3, mean_speed=(15.0, 45.0))
        return SuiteScenario("fast", {"n_obstacles": 3.0, "mean_speed_low": 15.0, "mean_speed_high": 45.0}, q)

    def _crowded(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        n = int(rng.integers(10, 16))
        q = self._paper_like(rng, index, n, radius_mean=(15.0, 25.0), radius_amplitude=(3.0, 8.0))
        return SuiteScenario("crowded", {"n_obstacles": float(n)}, q)

    def _boundary(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        lo, hi = np.array(Scene().workspace_lo), np.array(Scene().workspace_hi)
        axis, side = int(rng.integers(0, 2)), int(rng.integers(0, 2))
        depth = float(rng.uniform(2.0, 20.0))
        box_lo, box_hi = np.array([-148.0, -148.0, 100.0]), np.array([148.0, 148.0, 480.0])
        if side:
            box_lo[axis] = hi[axis] - depth - 15.0
            box_hi[axis] = hi[axis] - depth
        else:
            box_lo[axis] = lo[axis] + depth
            box_hi[axis] = lo[axis] + depth + 15.0
        q = self._paper_like(rng, index, 3, tip_box_lo=tuple(box_lo), tip_box_hi=tuple(box_hi))
        d = float(np.min(np.minimum(q.goal - lo, hi - q.goal)[:2]))
        return SuiteScenario("boundary", {"axis": float(axis), "side": float(side), "goal_to_boundary": d}, q)

    def _narrow_gap(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        q = self._query(rng, index)
        need = 2.0 * (self.model.robot.body_radius + self.safety_distance)
        for _ in range(_MAX_DRAWS):
            radii = (float(rng.uniform(30.0, 45.0)), float(rng.uniform(30.0, 45.0)))
            w = float(rng.uniform(2.0, 10.0))
            scene = Scene(obstacles=self._gap_pair(rng, q, radii, need + w), safety_distance=self.safety_distance)
            if self._feasible(scene, q):
                return SuiteScenario("narrow_gap", {"gap_mm": need + w, "spare_mm": w}, self._with(q, scene))
        raise self._give_up("narrow_gap", index)

    def _closing(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        q = self._query(rng, index)
        for _ in range(_MAX_DRAWS):
            A, B = float(rng.uniform(32.0, 40.0)), float(rng.uniform(12.0, 20.0))
            g_open = float(rng.uniform(26.0, 46.0))
            omega = float(rng.uniform(0.3, 0.6))
            # gap at the smallest radii (A - B each) is g_open, so at radius A it is g_open - 2 B
            pair = self._gap_pair(rng, q, (A, A), g_open - 2.0 * B, amplitude=B, omega=omega, phase=-0.5 * math.pi)
            scene = Scene(obstacles=pair, safety_distance=self.safety_distance)
            period = 2.0 * math.pi / omega
            if self._feasible(scene, q, ((0.0, period),)):
                params = {
                    "open_gap_mm": g_open,
                    "closed_gap_mm": g_open - 4.0 * B,
                    "omega": omega,
                    "closes_at": math.pi / omega,
                }
                return SuiteScenario("closing", params, self._with(q, scene))
        raise self._give_up("closing", index)

    def _goal_sweep(self, rng: np.random.Generator, index: int) -> SuiteScenario:
        q = self._query(rng, index)
        inflate = self.model.robot.body_radius + self.safety_distance
        for _ in range(_MAX_DRAWS):
            R = float(rng.uniform(25.0, 40.0))
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            side = np.cross(u, rng.normal(size=3))
            through = q.goal + rng.uniform(0.0, R / 3.0) * side / max(float(np.linalg.norm(side)), 1e-9)
            half = R + inflate + float(rng.uniform(40.0, 80.0))
            speed = float(rng.uniform(10.0, 30.0))
            a, b = through - half * u, through + half * u
            ob = Obstacle(
                center=tuple(map(float, a)),
                radius=R,
                to=tuple(map(float, b)),
                duration=2.0 * half / speed,
                profile="linear",
                name="sweeper",
            )
            scene = Scene(obstacles=(ob,), safety_distance=self.safety_distance)
            end = ob.duration
            if self._feasible(scene, q, ((0.0, 0.0), (end, end))):
                params = {"radius": R, "speed": speed, "covers_goal_at": half / speed, "rests_at": end}
                return SuiteScenario("goal_sweep", params, self._with(q, scene), hold_until=end + 1.0)
        raise self._give_up("goal_sweep", index)


# ------------------------------------------------------------------ records
@dataclass(frozen=True)
class SuiteRecord:
    """One method on one scenario (units s, mm).

    claimed: the method reported success (a planner's exact solution, the loop's arrival without a
    D_sf breach). success: claimed and the dense check (path and hold) passed. time_s: planning wall
    time (planners) or simulated arrival time (replanner). wall_s: wall time of the whole run.
    clearance_mm: smallest body-surface to sphere-surface distance minus D_sf over the checked path and
    hold (NaN when nothing was checked). check: the dense check's verdict.
    """

    method: str
    family: str
    index: int
    status: str
    claimed: bool
    success: bool
    time_s: float
    wall_s: float
    clearance_mm: float
    length_mm: float
    message: str
    check: str


# ------------------------------------------------------------------ running
@dataclass(frozen=True)
class _Path:
    """A timed path in the shape `dense_check` reads (t (K,), configs (K, nx))."""

    t: np.ndarray
    configs: np.ndarray


class SuiteRunner:
    """Runs every method on every scenario of the suite, in this process, one after another."""

    def __init__(
        self, model: Model, options: SuiteOptions | None = None, planner_options: PlannerOptions | None = None
    ):
        self.model = model
        self.options = options or SuiteOptions()
        self.planner_options = planner_options or PlannerOptions()
        self._planners: dict[str, Planner] = {}
        robot = model.robot
        self._rate_limits = None if robot.actuators is None else Actuators.from_robot(robot).rate_limits(robot)

    def planner(self, name: str) -> Planner:
        """The named planner, built once for up to `packing.slot_count(15)` obstacles (the largest family) and
        warmed up before its first timed run."""
        p = self._planners.get(name)
        if p is None:
            p = BUILTIN.build(name, self.model, Scene(), self.planner_options, max_obstacles=packing.slot_count(15))
            warm_up(p, self.model, bench_stop(BUILTIN.spec(name), self.planner_options, WARMUP_TIME))
            self._planners[name] = p
        return p

    def judge(self, sc: SuiteScenario, path: _Path | None, start: np.ndarray) -> tuple[bool, float, float, str]:
        """(passed, D_sf clearance mm, tip length mm, verdict) of a path and then of holding its end
        configuration (`SuiteOptions.hold_time` s, or until `SuiteScenario.hold_until`)."""
        o = self.options
        if path is None or len(path.t) == 0:
            return False, math.nan, math.nan, "no path"
        q = sc.scenario
        d_sf = q.scene.safety_distance

        def check(p: _Path, begin: np.ndarray, t0: float) -> Any:
            return dense_check(
                self.model,
                q.scene,
                p,  # type: ignore[arg-type]  # dense_check reads only t and configs
                begin,
                q.goal,
                goal_tolerance=o.goal_tolerance,
                n_points=o.verify_points,
                dt=o.verify_dt,
                step=o.verify_step,
                margin=d_sf,
                t0=t0,
            )

        first = check(path, start, float(path.t[0]))
        clearance, length = first.min_clearance - d_sf, first.length
        if not first.is_success():
            return False, clearance, length, first.reason
        t_end, x_end = float(path.t[-1]), path.configs[-1]
        hold = max(o.hold_time, sc.hold_until - t_end)
        if hold > 0.0:
            held = check(_Path(np.array([t_end, t_end + hold]), np.stack([x_end, x_end])), x_end, t_end)
            clearance = min(clearance, held.min_clearance - d_sf)
            if not held.is_success():
                return False, clearance, length, f"holding the goal: {held.reason}"
        return True, clearance, length, "ok"

    def run_planner(self, name: str, sc: SuiteScenario, seed: int) -> SuiteRecord:
        o = self.options
        q = sc.scenario
        t0 = time.perf_counter()
        try:
            planner = self.planner(name)  # built and warmed up before the timed run
            stop = bench_stop(BUILTIN.spec(name), self.planner_options, o.time_limit)
            t0 = time.perf_counter()
            res: PlanResult = plan_scenario(planner, stop, q, seed=seed, goal_tolerance=o.goal_tolerance)
        except InputError as exc:
            return self._failed(name, sc, f"refused: {exc}", time.perf_counter() - t0)
        except Exception as exc:  # a crash is a failed run, recorded with its text
            return self._failed(name, sc, f"raised {type(exc).__name__}: {exc}", time.perf_counter() - t0)
        elapsed = time.perf_counter() - t0
        claimed = res.is_success()
        path = _Path(np.asarray(res.t, dtype=float), np.asarray(res.configs, dtype=float)) if claimed else None
        ok, clr, length, verdict = self.judge(sc, path, q.start)
        if not claimed:
            verdict = "not checked (no exact solution claimed)"
        return SuiteRecord(
            name,
            sc.family,
            q.index,
            str(res.status),
            claimed,
            claimed and ok,
            elapsed,
            elapsed,
            clr,
            length,
            str(res.message),
            verdict,
        )

    def run_replanner(self, sc: SuiteScenario, seed: int) -> SuiteRecord:
        o = self.options
        q = sc.scenario
        t0 = time.perf_counter()
        try:
            ropts = ReplanOptions(**_REPLAN)
            lopts = LoopOptions(duration=o.replan_duration, planner_time=o.planner_time)
            planner = BUILTIN.build(
                "cspace", self.model, q.scene, self.planner_options, max_obstacles=packing.slot_count(q.n_obstacles)
            )
            reference = PlannerReference(
                planner,
                q.goal,
                goal_tolerance=o.goal_tolerance,
                stop=self.planner_options.stop() | StopCondition(time_limit=o.planner_time),
                seed=seed,
            )
            loop = ClosedLoop.build(
                self.model,
                q.scene,
                q.goal,
                q.start,
                options=ropts,
                loop_options=lopts,
                reference=reference,
                goal_tolerance=o.goal_tolerance,
                rate_limits=self._rate_limits,
            )
            run = loop.run()
        except InputError as exc:
            return self._failed(REPLANNER, sc, f"refused: {exc}", time.perf_counter() - t0)
        except Exception as exc:  # a crash is a failed run, recorded with its text
            return self._failed(REPLANNER, sc, f"raised {type(exc).__name__}: {exc}", time.perf_counter() - t0)
        wall = time.perf_counter() - t0
        claimed = run.is_success()
        path = _Path(np.asarray(run.dense_t, dtype=float), np.asarray(run.dense_x, dtype=float))
        ok, clr, length, verdict = self.judge(sc, path, path.configs[0])
        if not claimed:
            verdict = f"{run.status}: {run.message}"
        arrival = float(run.t[-1]) if run.reached else math.nan
        return SuiteRecord(
            REPLANNER,
            sc.family,
            q.index,
            str(run.status),
            claimed,
            claimed and ok,
            arrival,
            wall,
            clr,
            length,
            run.message,
            verdict,
        )

    def _failed(self, method: str, sc: SuiteScenario, message: str, elapsed: float) -> SuiteRecord:
        nan = math.nan
        return SuiteRecord(
            method, sc.family, sc.scenario.index, "error", False, False, elapsed, elapsed, nan, nan, message, ""
        )

    def methods(self) -> tuple[str, ...]:
        return (*self.options.planners, *((REPLANNER,) if self.options.replanner else ()))

    def run(
        self, scenarios: Sequence[SuiteScenario], on_record: Callable[[SuiteRecord], None] | None = None
    ) -> list[SuiteRecord]:
        """Every method on every scenario; `on_record` sees each record as it is made."""
        out = []
        for sc in scenarios:
            for k, m in enumerate(self.methods()):
                seed = int(np.random.SeedSequence([self.options.seed, sc.scenario.index, k]).generate_state(1)[0])
                rec = self.run_replanner(sc, seed) if m == REPLANNER else self.run_planner(m, sc, seed)
                out.append(rec)
                if on_record:
                    on_record(rec)
        return out
