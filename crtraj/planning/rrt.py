"""The paper's planners: RRT and RRT* over tip positions with a safety-constrained steer (Algorithm 1).

Each iteration samples a tip position P in the search space (the scene's
workspace box, by default the paper's 300 x 300 x 500 mm box centred on the
base axis), rejects it when it lies inside an obstacle grown by D_sf, finds
the tree node whose tip is nearest (KD-tree), and steers from that node's
configuration toward a point at most `range` mm along the way to P with the
safety-constrained NLP of `crtraj.planning.steer.SteerSolver` (paper eq. 17-18). If
the steer succeeds and reaches its target, the straight motion between the
two configurations is checked over the time it takes (`MotionValidator`:
continuous body, moving obstacles), and the new node stores its
configuration. RRT* (`RRTStar`) then chooses the cheapest parent among the
nodes within `rewire_radius` of the new tip and rewires those neighbours
through the new node when that shortens their tip path; every changed edge
is verified first (in a scene with moving obstacles, the whole re-timed
subtree). The goal is reached when a node's tip is within the goal tolerance.
Path cost is tip path length (mm), as in the paper's Table I.

The steer keeps the collision points of `check_points` (default 15) clear by
the scene's D_sf plus the disc radius plus a margin, so that the
configurations it returns also pass the planner's continuous-body check
(the paper constrains ten points; with ten points the body between them can
dip a few mm toward a sphere).

The returned path is the tree path, smoothed by the same verified B-spline
as the configuration-space planner (the paper interpolates its path with a
spline before execution); it is not shortcut, so RRT and RRT* keep their own
path shapes. `crtraj.planning.cspace.CSpacePlanner` is the faster default.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.postprocess import PathPostprocessor, empty_result, tree_edges
from crtraj.planning.query import PlanQuery
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.safe_ik import SafeIK, resolve_start
from crtraj.planning.steer import SteerOptions, SteerSolver
from crtraj.planning.stop import StopCondition
from crtraj.planning.tree import SearchTree
from crtraj.planning.validity import MotionValidator
from crtraj.world import margin


class RRT:
    """Task-space RRT with a safety-constrained steer (paper Algorithm 1, no rewiring).

    model: the robot's `Model`. scene: the default `crtraj.world.scene.Scene`.
    options: `PlannerOptions` (range = tip step in mm). steer_options:
    `SteerOptions` of the ``[steer]`` section; the planner raises its
    `n_points` to the check points and its `margin` to what the planner's
    continuous-body check needs (module docstring). max_obstacles: obstacle
    slots of the steer and IK NLPs (default: the scene's count).
    """

    name = "rrt"
    rewire = False

    def __init__(
        self,
        model: Model,
        scene: Any,
        options: PlannerOptions | None = None,
        steer_options: SteerOptions | None = None,
        *,
        max_obstacles: int | None = None,
    ) -> None:
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.options = PlannerOptions(algorithm=self.name) if options is None else options
        self._functions: dict[Any, Any] = {}
        self.validator = self.options.validator(model, scene, self._functions)
        M = max(scene.n_obstacles if max_obstacles is None else int(max_obstacles), scene.n_obstacles)
        so = SteerOptions() if steer_options is None else steer_options
        self.steer_options = replace(
            so,
            n_points=max(so.n_points or 0, self.validator.check_points),
            margin=max(so.margin, self.steer_margin(scene)),
        )
        self.steer = SteerSolver(model, M, self.steer_options)
        self.ik = SafeIK(model, self.validator, M)

    def steer_margin(self, scene: Any) -> float:
        """Extra keep-out (mm) for the steer's points so its configurations pass the validator.

        Between two points h apart that clear rho, a chord clears
        sqrt(rho^2 - h^2/4) > rho - h^2/(8 rho) (smallest rho: the smallest
        obstacle radius of the scene plus D_sf and the disc radius); add the
        arc's sagitta and half the finest check spacing.
        """
        v = self.validator
        h = self.robot.total_length / (v.check_points - 1)
        rmin = min((o.radius - abs(o.amplitude) for o in scene.obstacles), default=0.0)
        rho = margin.keep_out_radius(max(rmin, 0.0), scene.safety_distance, self.robot.body_radius)
        chord = math.sqrt(rho * rho + h * h / 4.0) - rho
        return chord + v.sagitta + v.resolution / 2.0 + 0.25

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
        """Plan from a start to a goal tip position (mm); same arguments as `CSpacePlanner.plan`."""
        o = self.options
        query = PlanQuery.begin(
            o.stop(),
            goal,
            t0=t0,
            goal_tolerance=goal_tolerance,
            start_config=start_config,
            start_tip=start_tip,
            stop=stop,
            seed=seed,
        )
        goal, t0, stop, clock, deadline, rng = (
            query.goal,
            query.t0,
            query.stop,
            query.clock,
            query.deadline,
            query.rng,
        )
        v = self.validator if scene is None or scene is self.scene else o.validator(self.model, scene, self._functions)
        sc = v.scene
        if sc.n_obstacles > self.steer.max_obstacles:  # grow the NLPs' obstacle slots (built once more)
            self.steer = SteerSolver(self.model, sc.n_obstacles, self.steer_options)
            self.ik = SafeIK(self.model, self.validator, sc.n_obstacles)
        self.steer.reset_warm_start()  # the same seed must give the same plan
        timings: dict[str, float] = {}
        counts: dict[str, int] = {"steer_calls": 0, "steer_failed": 0, "not_reached": 0, "edge_rejected": 0}
        samples0 = v.n_samples

        def fail(status: PlanStatus, msg: str, trees: list[SearchTree] | None = None) -> PlanResult:
            timings["total"] = time.perf_counter() - clock.t_start
            counts["iterations"] = clock.iterations
            return empty_result(
                status,
                msg,
                planner=self.name,
                seed=seed,
                robot=self.robot,
                tree_edges=self._edges(trees or []),
                timings=timings,
                counts=counts,
            )

        # ---- start and goal
        t1 = time.perf_counter()
        xs, why, n_ik = resolve_start(
            self.ik,
            v,
            start_config=start_config,
            start_tip=start_tip,
            t0=t0,
            rng=rng,
            seeds=o.ik_seeds,
            iterations=o.ik_iterations,
            deadline=deadline,
            tip_tolerance=min(1e-3, goal_tolerance),
            max_nlp=o.ik_nlp_solves,
        )
        timings["start_ik"] = time.perf_counter() - t1
        counts["ik_solves_start"] = n_ik
        if xs is None:
            return fail(PlanStatus.INVALID_START, why)
        why = self._goal_problem(goal, sc, t0)
        if why:
            return fail(PlanStatus.INVALID_GOAL, why)

        # ---- search (Algorithm 1)
        t1 = time.perf_counter()
        tree = SearchTree(3, self.robot.nx)
        tips: list[np.ndarray] = []
        tip0 = self.model.tip_position(xs)
        tree.add(tip0, xs, t0, 0.0, -1)
        tips.append(tip0)
        lo, hi = sc.workspace
        step = o.step
        window = 3.0 * step / v.max_speed  # time window the steer keeps clear over (moving obstacles)
        best = -1
        best_cost = np.inf
        while not clock.should_stop(best >= 0):
            clock.tick()
            P = goal if rng.random() < o.goal_bias else lo + (hi - lo) * rng.random(3)
            # line 5: the sample must be obstacle-free
            if sc.n_obstacles and float(sc.clearance_points(P[None, None, :], t0)[0]) < 0.0:
                continue
            n, d = tree.nearest(P)
            if d < 1e-9:
                continue
            tip_n = tree.keys[n]
            target = tip_n + (P - tip_n) * min(1.0, step / d)
            x_n, t_n = tree.x[n], float(tree.t[n])
            counts["steer_calls"] += 1
            res = self.steer.solve(x_n, target, sc, t=t_n, t_end=None if v.static else t_n + window, check_start=False)
            if not res.usable:
                counts["steer_failed"] += 1
                continue
            if not res.reached:
                counts["not_reached"] += 1
                continue
            # the steer meets the limits to its solver tolerance; put the node exactly inside
            x_new = v.project_limits(res.x)[0]
            dur = float(v.motion_bound(x_new - x_n)) / v.max_speed
            if not v.edges_valid(x_n[None], x_new[None], t_n, t_n + dur)[0]:
                counts["edge_rejected"] += 1
                continue
            tip_new = self.model.tip_position(x_new)
            parent, cost = n, float(tree.cost[n]) + float(np.linalg.norm(tip_new - tip_n))
            if self.rewire:
                parent, cost = self._choose_parent(tree, v, tip_new, x_new, parent, cost)
            t_new = float(tree.t[parent]) + float(v.motion_bound(x_new - tree.x[parent])) / v.max_speed
            i_new = tree.add(tip_new, x_new, t_new, cost, parent)
            tips.append(tip_new)
            if self.rewire:
                counts["rewired"] = counts.get("rewired", 0) + self._rewire(tree, v, i_new)
            # the goal check (line 12), over every goal node: rewiring may lower their costs
            if np.linalg.norm(tip_new - goal) <= goal_tolerance and best < 0:
                best = i_new
            if best >= 0:
                near_goal = tree.within(goal, goal_tolerance)
                if len(near_goal):
                    k = near_goal[np.argmin(tree.cost[near_goal])]
                    best, best_cost = int(k), float(tree.cost[k])
        timings["search"] = time.perf_counter() - t1
        counts["iterations"] = clock.iterations
        counts["nodes"] = len(tree)
        counts["collision_samples"] = v.n_samples - samples0

        post = PathPostprocessor(v, o, rng, t0)
        if best < 0:
            # approximate: the node whose tip came closest to the goal
            d_goal = np.linalg.norm(tree.keys - goal, axis=1)
            k = int(np.argmin(d_goal))
            if k == 0:
                return fail(PlanStatus.TIMEOUT, f"no path: {clock.reason}", [tree])
            status = PlanStatus.APPROXIMATE
            msg = f"no path to the goal ({clock.reason}); closest tip {d_goal[k]:.1f} mm from the goal"
            best, best_cost = k, float(tree.cost[k])
        else:
            status = PlanStatus.EXACT
            msg = f"reached the goal after {clock.iterations} iterations ({len(tree)} nodes)"
        raw = tree.x[tree.path_to(best)]
        t1 = time.perf_counter()
        final, smoothed = post.smooth(raw) if status is PlanStatus.EXACT else (post.resample(raw), False)
        timings["smooth"] = time.perf_counter() - t1
        if not post.valid(final):  # every edge was verified; only a wrong bound could get here
            raise RuntimeError("internal error: the returned path failed its final verification")
        timings["total"] = time.perf_counter() - clock.t_start
        return post.result(
            status=status,
            message=msg,
            planner=self.name,
            seed=seed,
            goal=goal,
            X=final,
            raw=raw,
            smoothed=smoothed,
            cost=best_cost,
            goal_configs=None,
            tree_edges=self._edges([tree]),
            timings=timings,
            counts=counts,
        )

    def _goal_problem(self, goal: np.ndarray, scene: Any, t0: float) -> str:
        """Why the goal tip can never be reached safely ('' when no reason is known)."""
        robot = self.robot
        if scene.n_obstacles and float(scene.clearance_points(goal[None, None, :], t0)[0]) < 0.0:
            return f"the goal {goal.tolist()} mm lies inside an obstacle grown by D_sf"
        # the tip stays within the total length of the base, which slides on the z axis
        z = min(max(goal[2], robot.z_range[0]), robot.z_range[1])
        reach = float(np.linalg.norm(goal - np.array([0.0, 0.0, z])))
        if reach > robot.total_length:
            return f"the goal {goal.tolist()} mm is {reach - robot.total_length:.1f} mm out of the robot's reach"
        lo, hi = scene.workspace
        if not scene.in_workspace(goal):
            return f"the goal {goal.tolist()} mm is outside the search space {lo.tolist()}..{hi.tolist()} mm"
        return ""

    def _edges(self, trees: list[SearchTree]) -> np.ndarray:
        return tree_edges(self.model, trees, [t.keys for t in trees])

    # -------------------------------------------------------------- RRT* parts
    def _choose_parent(
        self, tree: SearchTree, v: MotionValidator, tip: np.ndarray, x: np.ndarray, parent: int, cost: float
    ) -> tuple[int, float]:
        """The cheapest verified parent within rewire_radius (the nearest node is already verified)."""
        near = tree.within(tip, self.options.rewire_radius)
        near = near[near != parent]
        if not len(near):
            return parent, cost
        c = tree.cost[near] + np.linalg.norm(tree.keys[near] - tip, axis=1)
        better = c < cost - 1e-9
        near, c = near[better], c[better]
        if not len(near):
            return parent, cost
        order = np.argsort(c)
        near, c = near[order], c[order]
        TA = tree.t[near]
        TB = TA + v.motion_bound(x - tree.x[near]) / v.max_speed
        ok = v.edges_valid(tree.x[near], np.repeat(x[None], len(near), axis=0), TA, TB)
        if ok.any():
            k = int(np.argmax(ok))  # the first valid in cost order
            return int(near[k]), float(c[k])
        return parent, cost

    def _rewire(self, tree: SearchTree, v: MotionValidator, i_new: int) -> int:
        """Reparent neighbours through the new node when that shortens their tip path; returns how many."""
        tip, x = tree.keys[i_new], tree.x[i_new]
        near = tree.within(tip, self.options.rewire_radius)
        near = near[(near != i_new) & (near != tree.parent[i_new])]
        if not len(near):
            return 0
        c = tree.cost[i_new] + np.linalg.norm(tree.keys[near] - tip, axis=1)
        better = c < tree.cost[near] - 1e-9
        near, c = near[better], c[better]
        if not len(near):
            return 0
        t_new = float(tree.t[i_new])
        TB = t_new + v.motion_bound(tree.x[near] - x) / v.max_speed
        ok = v.edges_valid(np.repeat(x[None], len(near), axis=0), tree.x[near], t_new, TB)
        done = 0
        for j, cj, tj, good in zip(near, c, TB, ok, strict=True):
            # an earlier rewire in this loop may already have lowered j's cost
            if not good or cj >= float(tree.cost[j]) - 1e-9 or self._is_ancestor(tree, int(j), i_new):
                continue
            sub = tree.subtree(int(j))
            if not v.static and not self._subtree_valid(tree, v, sub, int(j), float(tj)):
                continue
            delta_c = cj - float(tree.cost[j])
            delta_t = tj - float(tree.t[j])
            tree.set_parent(int(j), i_new, float(cj), float(tj))
            rest = sub[1:]
            tree.set_cost_time(rest, tree.cost[rest] + delta_c, tree.t[rest] + delta_t)
            done += 1
        return done

    @staticmethod
    def _is_ancestor(tree: SearchTree, a: int, b: int) -> bool:
        """True when node a lies on the path from the root to b (rewiring a under b would make a cycle)."""
        return bool(np.isin(a, tree.path_to(b)))

    @staticmethod
    def _subtree_valid(tree: SearchTree, v: MotionValidator, sub: np.ndarray, j: int, tj: float) -> bool:
        """Moving obstacles: the subtree of j, re-timed by j's new arrival tj, still verifies."""
        rest = sub[1:]
        if not len(rest):
            return True
        shift = tj - float(tree.t[j])
        par = tree.parent[rest]
        return bool(np.all(v.edges_valid(tree.x[par], tree.x[rest], tree.t[par] + shift, tree.t[rest] + shift)))


class RRTStar(RRT):
    """Task-space RRT* (paper Algorithm 1 with choose-parent and rewiring)."""

    name = "rrtstar"
    rewire = True


def make_planner(
    model: Model,
    scene: Any,
    options: PlannerOptions | None = None,
    steer_options: SteerOptions | None = None,
    *,
    max_obstacles: int | None = None,
) -> Any:
    """The planner `options.algorithm` names: `CSpacePlanner`, `RRT` or `RRTStar`.

    Every planner has ``plan(goal, *, start_config=None, start_tip=None,
    t0=0.0, stop=None, seed=None, scene=None, goal_tolerance=1.0) ->
    PlanResult`` (see `crtraj.planning.cspace.CSpacePlanner.plan`).
    """
    o = PlannerOptions() if options is None else options
    if o.algorithm == "cspace":
        from crtraj.planning.cspace import CSpacePlanner

        return CSpacePlanner(model, scene, o, max_obstacles=max_obstacles)
    cls = RRTStar if o.algorithm == "rrtstar" else RRT
    return cls(model, scene, o, steer_options, max_obstacles=max_obstacles)


# ------------------------------------------------------------- problem files
@dataclass(frozen=True)
class ProblemPlan:
    """One planning run of a problem file: the inputs, the result and the setup time (s)."""

    problem: Any
    model: Model
    scene: Any
    options: PlannerOptions
    steer_options: SteerOptions | None
    result: PlanResult
    setup_time: float

    def document(self) -> dict[str, Any]:
        """The self-describing result file (kind "plan"; schema in the README), as plain JSON data."""
        import datetime

        import casadi as ca

        from crtraj import __version__
        from crtraj.core.fileio import to_jsonable

        p, r, model, scene = self.problem, self.result, self.model, self.scene
        waypoints = []
        if len(r.t):
            backbone = model.points(r.configs)
            centers, radii = scene.states(r.t)
            for k in range(len(r.t)):
                waypoints.append(
                    {
                        "t": float(r.t[k]),
                        "tip": r.tips[k],
                        "x": r.configs[k],
                        "q": r.cables[k],
                        "backbone": backbone[k],
                        "obstacles": {"centers": centers[k].reshape(-1, 3), "radii": radii[k].reshape(-1)},
                    }
                )
        options: dict[str, Any] = {"planner": self.options.to_dict()}
        if self.steer_options is not None:
            options["steer"] = self.steer_options.to_dict()
        doc: dict[str, Any] = {
            "kind": "plan",
            "crtraj_version": __version__,
            "casadi_version": ca.__version__,
            "numpy_version": np.__version__,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "problem": {"name": p.name, "path": None if p.path is None else str(p.path), "seed": r.seed},
            "robot": model.robot.to_dict(),
            "scene": scene.to_dict(),
            "task": p.require_task().to_dict(),
            "options": options,
            "status": str(r.status),
            "success": r.success,
            "message": r.message,
            "timing": {**{f"{k}_s": v for k, v in r.timings.items()}, "setup_s": self.setup_time},
            "summary": r.summary(),
            "waypoints": waypoints,
            "tree": {"edges": r.tree_edges},
        }
        if r.raw_configs is not None and len(r.raw_configs):
            doc["raw_path"] = {"t": r.raw_t, "x": r.raw_configs, "tip": model.tip_position(r.raw_configs)}
        if r.goal_configs is not None and len(r.goal_configs):
            doc["goal_configs"] = r.goal_configs
        return to_jsonable(doc)

    def write(self, path: str | Path) -> Path:
        """Write `document()` as JSON, atomically."""
        from crtraj.core.fileio import atomic_write_json

        return atomic_write_json(path, self.document())


def plan_problem(
    problem: Any,
    *,
    algorithm: str | None = None,
    seed: int | None = None,
    time_limit: float | None = None,
    model: Model | None = None,
) -> ProblemPlan:
    """Plan a problem file's task with its ``[scene]``, ``[planner]`` and ``[steer]`` sections.

    algorithm, seed, time_limit (s) override the file. The start is
    ``task.start_config`` when given, else a safe IK solution for ``task.start``.
    """
    from crtraj.world.scene import Scene

    task = problem.require_task()
    t1 = time.perf_counter()
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner")
    changes: dict[str, Any] = {}
    if algorithm is not None:
        changes["algorithm"] = algorithm
    if time_limit is not None:
        changes["time_limit"] = float(time_limit)
    if changes:
        options = options.with_(**changes)
    steer_options = problem.options(SteerOptions, "steer")
    model = Model(problem.robot) if model is None else model
    planner = make_planner(model, scene, options, steer_options)
    setup = time.perf_counter() - t1
    seed = problem.seed if seed is None else int(seed)
    start = {"start_config": task.start_config} if task.start_config is not None else {"start_tip": task.start}
    result = planner.plan(task.goal, seed=seed, goal_tolerance=task.goal_tolerance, **start)
    used_steer = getattr(planner, "steer_options", None)
    return ProblemPlan(problem, model, scene, options, used_steer, result, setup)
