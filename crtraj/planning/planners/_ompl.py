"""OMPL's geometric planners (RRTstar, RRTConnect, RRT) on crtraj's problem, with crtraj's validity checker.

OMPL (the ``ompl`` package from PyPI, 2.x; install the ``bench`` extra) is
imported only when an `OMPLPlanner` is built. What OMPL sees:

- State space: configuration space x time, as a 6-D (nx + 1) real vector
  ``(y, tau)`` with ``y = M x`` the body-motion metric coordinates of
  `crtraj.planning.validity.MotionValidator` (mm) and ``tau = w * max_speed * (t - t0)``
  (mm; `time_weight` w), so OMPL's distances and path lengths are in mm.
  Obstacles move and breathe, so validity depends on time; a geometric
  planner can only respect that if time is part of the state (the
  space-time formulation of OMPL's own STRRT*). Bounds: the bending discs
  and z stroke in y, and the planning horizon in tau. The time weight sets
  how wide the cone of reachable states is in OMPL's metric: with w = 1 a
  random extension direction is rarely slow enough to be valid; w = 0.1
  and range = 100 mm were the best of the settings tried on eight
  scenarios (w in 0.05-1, range 100, 150, 300 mm and OMPL's default).
- State validity: ``MotionValidator.state_valid(x, t)`` (limits, and the
  continuous body clear of every obstacle at time t).
- Motion validity: time must run forward no faster than the body speed limit
  allows (``tau_2 - tau_1 >= B(x_2 - x_1)``, the validator's body-motion
  bound), the end state within limits, and
  ``MotionValidator.edge_clearance(x_1, x_2, t_1, t_2) >= 0``: exactly the
  check crtraj's own planners apply to their edges. A motion may be slower
  than the speed limit: OMPL may wait, crtraj's planners always move at it.
- Goal: a `GoalSampleableRegion`: satisfied when the tip is within the goal
  tolerance (distance = tip error, mm); samples are safe goal
  configurations found by `crtraj.planning.ik.SafeIK` exactly as the
  configuration-space planner finds them (half the IK starts clear of the
  goal window's swept obstacles, half clear at t0), each at a random arrival
  time between the earliest the speed limit allows and the horizon.
- RRTstar minimises OMPL's path length in (y, tau); its delayed collision
  checking stays on, because with it RRTstar never reuses a neighbour ->
  new motion check for the reverse direction (which time makes invalid).

The returned `PlanResult` holds the OMPL path as timed waypoints (t = t0 +
tau / (w max_speed)), straight in configuration space and linear in time between
them, exactly what the validity checks covered. RRTConnect's path is
simplified with OMPL's PathSimplifier in whatever time budget is left;
RRTstar spends the whole budget improving its tree (it is an anytime planner),
unless the stop condition asks for the first solution.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.base import PlannerBase, QueryStart
from crtraj.planning.context import PlanningContext
from crtraj.planning.ik import SafeIK
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator
from crtraj.world import packing

ALGORITHMS = ("RRTstar", "RRTConnect", "RRT")


def import_ompl() -> tuple[Any, Any, Any]:
    """(ompl.base, ompl.geometric, ompl.util), or an `InputError` saying how to install OMPL."""
    try:
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou
    except ImportError as exc:
        raise InputError(
            f"OMPL planners need the 'ompl' package (2.x): pip install 'crtraj[bench]' or pip install ompl ({exc})"
        ) from None
    return ob, og, ou


@dataclass
class _SpaceTime:
    """One query's (y, tau) space (module docstring): its validator, start time t0 (s), tau per
    second (mm/s), the goal tip (mm) and its safe configurations, and the run's counts."""

    v: MotionValidator
    t0: float
    tscale: float
    goal: np.ndarray
    goals: np.ndarray
    counts: dict[str, int]
    rng: np.random.Generator
    progress: list[tuple[float, float]] = field(default_factory=list)

    @property
    def nx(self) -> int:
        return int(self.v.robot.nx)

    def unpack(self, s: Any) -> tuple[np.ndarray, float]:
        """(configuration, time in s) of an OMPL state."""
        nx = self.nx
        y = np.array([s[i] for i in range(nx)])
        return self.v.config_from_metric(y), self.t0 + s[nx] / self.tscale

    def bounds(self, ob: Any, horizon: float) -> Any:
        """The state space: bending discs and z stroke in y, the horizon (s) in tau."""
        robot, v, nx = self.v.robot, self.v, self.nx
        space = ob.RealVectorStateSpace(nx + 1)
        bounds = ob.RealVectorBounds(nx + 1)
        tmax = np.array([s.theta_max for s in robot.segments])
        for k in range(robot.n_segments):
            r = float(v.weights[k] * tmax[k])
            for j in (2 * k, 2 * k + 1):
                bounds.setLow(j, -r)
                bounds.setHigh(j, r)
        bounds.setLow(nx - 1, float(robot.z_range[0]))
        bounds.setHigh(nx - 1, float(max(robot.z_range[1], robot.z_range[0] + 1e-9)))
        bounds.setLow(nx, 0.0)
        bounds.setHigh(nx, self.tscale * horizon)
        space.setBounds(bounds)
        return space


def _callbacks(ob: Any, st: _SpaceTime, xs: np.ndarray, model: Any, horizon: float) -> tuple[type, type, type]:
    """OMPL's state validity, motion validity and goal region classes for the query `st` (they are
    OMPL subclasses, so they close over the query instead of holding it)."""
    v, counts, nx, goal, rng = st.v, st.counts, st.nx, st.goal, st.rng
    speed = v.max_speed

    class Validity(ob.StateValidityChecker):
        def isValid(self, s: Any) -> bool:  # noqa: N802 (OMPL's name)
            counts["validity_checks"] += 1
            x, t = st.unpack(s)
            return bool(v.state_valid(x[None], t)[0])

    class Motion(ob.MotionValidator):
        def checkMotion(self, s1: Any, s2: Any) -> bool:  # noqa: N802 (OMPL's name)
            counts["motion_checks"] += 1
            x1, t1_ = st.unpack(s1)
            x2, t2_ = st.unpack(s2)
            if (t2_ - t1_) * speed < float(v.motion_bound(x2 - x1)) - 1e-9:
                return False  # backwards in time, or faster than the body speed limit
            if not bool(v.within_limits(x2[None])[0]):
                return False
            per_edge, _, _ = v.edge_clearance(x1[None], x2[None], t1_, t2_)
            return bool(per_edge[0] >= 0.0)

    y_goals = v.metric(st.goals)
    tau_min = v.motion_bound(st.goals - xs[None]) * (st.tscale / speed)  # earliest arrival at each goal
    tau_max = st.tscale * horizon

    class Goal(ob.GoalSampleableRegion):
        def distanceGoal(self, s: Any) -> float:  # noqa: N802 (OMPL's name)
            x, _ = st.unpack(s)
            return float(np.linalg.norm(model.tip_position(x) - goal))

        def sampleGoal(self, s: Any) -> None:  # noqa: N802 (OMPL's name)
            counts["goal_samples"] += 1
            k = int(rng.integers(len(y_goals)))
            lo = min(float(tau_min[k]), tau_max)
            tau = float(rng.uniform(lo, tau_max))
            for i in range(nx):
                s[i] = float(y_goals[k, i])
            s[nx] = tau

        def maxSampleCount(self) -> int:  # noqa: N802 (OMPL's name)
            return 1_000_000

    return Validity, Motion, Goal


class OMPLPlanner(PlannerBase):
    """One OMPL planner for one robot; reuse it for many queries (like `CSpacePlanner`).

    context: the `PlanningContext` (model, default scene, options shared with crtraj's planners:
    max speed, collision resolution, check points, IK seeds, goal window, goal_bias).
    algorithm: "RRTstar", "RRTConnect" or "RRT". horizon: latest arrival time considered, after
    t0 (s). time_weight: w in tau = w * max_speed * t (module docstring). range: OMPL's extension
    range (mm in (y, tau); None keeps OMPL's default, 20 % of the space's extent). simplify: run
    OMPL's PathSimplifier on the solution with the time left.
    """

    def __init__(
        self,
        context: PlanningContext,
        *,
        algorithm: str = "RRTstar",
        horizon: float = 60.0,
        time_weight: float = 0.1,
        range: float | None = 100.0,
        simplify: bool = True,
    ) -> None:
        if algorithm not in ALGORITHMS:
            raise InputError(f"algorithm: OMPL planner must be one of {', '.join(ALGORITHMS)}; got {algorithm!r}")
        if not (math.isfinite(horizon) and horizon > 0):
            raise InputError(f"horizon: must be a finite number > 0 (s), got {horizon!r}")
        if not (math.isfinite(time_weight) and time_weight > 0):
            raise InputError(f"time_weight: must be a finite number > 0, got {time_weight!r}")
        if range is not None and not (math.isfinite(range) and range > 0):
            raise InputError(f"range: must be a finite number > 0 (mm), got {range!r}")
        self.ob, self.og, self.ou = import_ompl()
        self.ou.setLogLevel(self.ou.LOG_NONE)  # OMPL's console chatter would interleave with progress bars
        super().__init__(context)
        self.algorithm = algorithm
        self.name = f"ompl-{algorithm.lower()}"  # per instance: one class, three algorithms
        self.horizon = float(horizon)
        self.time_weight = float(time_weight)
        self.range = range
        self.simplify = bool(simplify)
        self._iks: dict[int, SafeIK] = {}
        self.ik = self._ik(self.scene.n_obstacles, self.validator)

    # ---------------------------------------------------------------- helpers
    def _ik(self, n_obstacles: int, v: MotionValidator) -> SafeIK:
        slots = packing.slot_count(n_obstacles)
        ik = self._iks.get(slots)
        if ik is None:
            ik = SafeIK(
                self.model,
                v,
                slots,
                push_rounds=self.options.ik.push_rounds,
                rescue_starts=self.options.ik.rescue_starts,
                compiled=self.options.ik.compiled,
            )
            self._iks[slots] = ik
        return ik

    def _prepare(self, validator: MotionValidator) -> None:
        self.ik = self._ik(validator.scene.n_obstacles, validator)

    def _goal_configs(self, q: QueryStart, xs: np.ndarray) -> np.ndarray:
        """Safe configurations with the tip on the goal, found as the c-space planner finds them."""
        o, v, query = self.options, q.validator, q.query
        sc, t0, goal = v.scene, query.t0, query.goal
        ik = self._ik(sc.n_obstacles, v)
        n = o.ik.seeds
        seeds = np.concatenate([xs[None], v.sample(query.rng, n - 1)]) if n > 1 else xs[None]
        kw: dict[str, Any] = {
            "want": o.ik.goal_configs,
            "newton_iterations": o.ik.iterations,
            "deadline": query.deadline,
            "validator": v,
            "tip_tolerance": min(1e-3, q.goal_tolerance),
        }
        if v.static or o.ik.goal_window == 0:
            parts = [ik.solve(goal, sc.pack(t0, ik.max_obstacles), seeds, t_check=(t0, t0), **kw)]
        else:
            t_end = t0 + o.ik.goal_window
            half = (len(seeds) + 1) // 2
            parts = [
                ik.solve(goal, sc.pack_over(t0, t_end, ik.max_obstacles), seeds[:half], t_check=(t0, t_end), **kw),
                ik.solve(goal, sc.pack(t0, ik.max_obstacles), seeds[half:], t_check=(t0, t0), **kw),
            ]
        q.counts["ik_solves_goal"] = sum(len(b.solutions) for b in parts)
        return np.concatenate([b.safe for b in parts])

    # ------------------------------------------------------------------ query
    def plan(
        self,
        goal: Any,
        *,
        start_config: Any = None,
        start_tip: Any = None,
        t0: float = 0.0,
        stop: StopCondition | None = None,
        seed: int | None = None,
        scene: Any = None,
        goal_tolerance: float = 1.0,
    ) -> PlanResult:
        """Plan from a start configuration (nx,) or a start tip (3,) mm (safe IK, as the c-space planner
        resolves it) to a goal tip (3,) mm, starting at time t0 (s): the `crtraj.planning.base.Planner` call.

        stop: must limit time (OMPL planners stop on wall time; an iteration
        limit is not available through OMPL's Python API); first_solution
        stops RRTstar at its first solution. seed: seeds the IK starts and
        OMPL's random generator. Bad input raises `InputError`; an unsafe
        start or an unreachable goal is a result status.
        """
        stop = StopCondition(time_limit=self.options.time_limit) if stop is None else stop
        if stop.time_limit is None:
            raise InputError("stop.time_limit: OMPL planners need a time limit (s)")
        counts = {"validity_checks": 0, "motion_checks": 0, "goal_samples": 0}
        q = self._begin(
            goal,
            start_config=start_config,
            start_tip=start_tip,
            t0=t0,
            stop=stop,
            seed=seed,
            scene=scene,
            goal_tolerance=goal_tolerance,
            counts=counts,
        )
        if q.x_start is None:
            return self._finish(q, None, PlanStatus.INVALID_START, q.why)
        t1 = time.perf_counter()
        goals = self._goal_configs(q, q.x_start)
        q.timings["goal_ik"] = time.perf_counter() - t1
        if not len(goals):
            msg = f"no safe configuration puts the tip on the goal {q.query.goal.tolist()} mm"
            return self._finish(q, None, PlanStatus.INVALID_GOAL, msg)
        tscale = self.time_weight * q.validator.max_speed  # mm of tau per second
        st = _SpaceTime(q.validator, q.query.t0, tscale, q.query.goal, goals, q.counts, q.query.rng)
        return self._search(q, st, q.x_start)

    def _problem(self, st: _SpaceTime, xs: np.ndarray, goal_tolerance: float) -> tuple[Any, Any, Any, Any]:
        """(space information, problem definition, goal region, planner) of one query."""
        ob, og = self.ob, self.og
        space = st.bounds(ob, self.horizon)
        si = ob.SpaceInformation(space)
        Validity, Motion, Goal = _callbacks(ob, st, xs, self.model, self.horizon)
        si.setStateValidityChecker(Validity(si))
        si.setMotionValidator(Motion(si))
        si.setup()
        pdef = ob.ProblemDefinition(si)
        start = space.allocState()
        for i, val in enumerate(st.v.metric(xs)):
            start[i] = float(val)
        start[st.nx] = 0.0
        pdef.addStartState(start)
        goal_region = Goal(si)
        goal_region.setThreshold(float(goal_tolerance))
        pdef.setGoal(goal_region)
        if self.algorithm == "RRTstar":
            pdef.setOptimizationObjective(ob.PathLengthOptimizationObjective(si))
        planner = getattr(og, self.algorithm)(si)
        if self.range is not None:
            planner.setRange(float(self.range))
        if self.algorithm in ("RRTstar", "RRT"):
            planner.setGoalBias(float(self.options.goal_bias))
        if self.algorithm == "RRTstar":
            planner.setDelayCC(True)
        planner.setProblemDefinition(pdef)
        planner.setup()
        return si, pdef, goal_region, planner

    def _termination(self, planner: Any, q: QueryStart, left: float, progress: list[tuple[float, float]]) -> Any:
        """OMPL's termination condition: the time left, RRTstar's first solution when the stop asks for
        it, and a watcher of RRTstar's best cost that never fires."""
        ob = self.ob
        ptc = ob.timedPlannerTerminationCondition(left)
        if q.query.stop.first_solution and self.algorithm == "RRTstar":
            # RRTstar adds its path to the problem only when solve() returns, so an exact-solution condition
            # never fires while it runs; its best cost turns finite at its first solution
            first = ob.PlannerTerminationCondition(lambda: math.isfinite(planner.bestCost().value()))
            ptc = ob.plannerOrTerminationCondition(ptc, first)
        # Time to first solution and the best-cost progress (OMPL's benchmark format): the planner asks its
        # termination condition once per iteration, so a condition that never fires can watch the best cost
        # (the wheel's bindings cannot pass a Python intermediate-solution callback).
        if self.algorithm == "RRTstar":
            t_start = q.query.clock.t_start
            watch = ob.PlannerTerminationCondition(lambda: self._watch(planner, t_start, progress))
            ptc = ob.plannerOrTerminationCondition(ptc, watch)
        return ptc

    def _search(self, q: QueryStart, st: _SpaceTime, xs: np.ndarray) -> PlanResult:
        """Set up OMPL's problem in (y, tau), solve it within the deadline and read its path back."""
        ob = self.ob
        si, pdef, goal_region, planner = self._problem(st, xs, q.goal_tolerance)
        if q.seed is not None:
            self.ou.RNG.setSeed(int(q.seed) % 2_147_483_646 + 1)  # OMPL seeds must be positive 32-bit
        left = q.query.deadline - time.perf_counter()
        if left <= 0:
            return self._finish(q, st, PlanStatus.TIMEOUT, "no time left after the goal IK")
        ptc = self._termination(planner, q, left, st.progress)
        t1 = time.perf_counter()
        status = planner.solve(ptc)
        q.timings["search"] = time.perf_counter() - t1
        t_start = q.query.clock.t_start
        if not st.progress and pdef.hasExactSolution():  # found at the solve's end (RRTConnect stops there)
            st.progress.append((time.perf_counter() - t_start, float(pdef.getSolutionPath().length())))
        if st.progress:
            q.timings["first_solution"] = st.progress[0][0]
        data = ob.PlannerData(si)
        planner.getPlannerData(data)
        q.counts["graph_states"] = int(data.numVertices())
        exact = status.getStatus() == ob.PlannerStatus.EXACT_SOLUTION and pdef.hasExactSolution()
        if not pdef.hasSolution():
            return self._finish(q, st, PlanStatus.TIMEOUT, f"OMPL {self.algorithm}: {status.asString()}")
        path = pdef.getSolutionPath()
        left = q.query.deadline - time.perf_counter()
        if exact and self.simplify and left > 0:
            t1 = time.perf_counter()
            self.og.PathSimplifier(si, goal_region).simplify(path, left)
            q.timings["simplify"] = time.perf_counter() - t1
        nx = st.nx
        S = np.array([[path.getState(i)[j] for j in range(nx + 1)] for i in range(path.getStateCount())])
        X = st.v.config_from_metric(S[:, :nx])
        T = st.t0 + S[:, nx] / st.tscale
        X[0] = xs  # the metric round trip moves the start by round-off only
        msg = f"OMPL {self.algorithm}: {status.asString()}; {len(X)} waypoints"
        return self._finish(q, st, PlanStatus.EXACT if exact else PlanStatus.APPROXIMATE, msg, X, T)

    def _finish(
        self,
        q: QueryStart,
        st: _SpaceTime | None,
        status: PlanStatus,
        message: str,
        X: np.ndarray | None = None,
        T: np.ndarray | None = None,
    ) -> PlanResult:
        """The query's result, with its timings, counts and best-cost progress."""
        q.timings["total"] = time.perf_counter() - q.query.clock.t_start
        goals = None if st is None else st.goals
        result = self._result(status, message, q, goals, X, T)
        return replace(result, cost_progress=tuple(() if st is None else st.progress))

    @staticmethod
    def _watch(planner: Any, t_start: float, progress: list[tuple[float, float]]) -> bool:
        """Record (s since t_start, best cost) when RRTstar's best cost improves; never stops the search."""
        cost = float(planner.bestCost().value())
        if math.isfinite(cost) and (not progress or cost < progress[-1][1]):
            progress.append((time.perf_counter() - t_start, cost))
        return False

    def _result(
        self,
        status: PlanStatus,
        message: str,
        q: QueryStart,
        goals: np.ndarray | None,
        X: np.ndarray | None,
        T: np.ndarray | None,
    ) -> PlanResult:
        """The result of a finished query: the timed path with its length, cost and clearance."""
        seed, v, goal, timings, counts = q.seed, q.validator, q.query.goal, q.timings, q.counts
        nx, nq = self.robot.nx, self.robot.nq
        if X is None or T is None:
            return PlanResult(
                status=status,
                message=message,
                planner=self.name,
                seed=seed,
                t=np.zeros(0),
                configs=np.zeros((0, nx)),
                tips=np.zeros((0, 3)),
                cables=np.zeros((0, nq)),
                goal_configs=goals,
                timings=dict(timings),
                counts=dict(counts),
            )
        tips = self.model.tip_position(X)
        goal_error = float(np.linalg.norm(tips[-1] - goal))
        if status is PlanStatus.EXACT and not np.all(v.within_limits(X)):
            status, message = PlanStatus.APPROXIMATE, message + "; a waypoint is out of limits"
        clear = float(v.path_clearance(X, T)[0]) if len(X) > 1 else float(v.clearance(X, T[0])[0])
        # tip travel along the straight motions, sampled every `resolution` of body motion
        n_sub = np.maximum(1, np.ceil(v.motion_bound(np.diff(X, axis=0)) / v.resolution)).astype(int)
        seg = np.repeat(np.arange(len(X) - 1), n_sub)
        frac = (np.arange(n_sub.sum()) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub) + 1) / n_sub[seg]
        dense = [X[:1], X[seg] + frac[:, None] * (X[seg + 1] - X[seg])]
        length = float(np.sum(np.linalg.norm(np.diff(self.model.tip_position(np.concatenate(dense)), axis=0), axis=1)))
        return PlanResult(
            status=status,
            message=message,
            planner=self.name,
            seed=seed,
            t=T,
            configs=X,
            tips=tips,
            cables=self.model.cables(X),
            length=length,
            cost=float(np.sum(v.motion_bound(np.diff(X, axis=0)))),
            min_clearance=clear,
            goal_error=goal_error,
            goal_configs=goals,
            timings=dict(timings),
            counts=dict(counts),
        )
