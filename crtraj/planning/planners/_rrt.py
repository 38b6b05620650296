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

With ``[planner.check] mode = "paper"`` the validator is the paper's own check
(`crtraj.planning.validity.PaperValidator`: the robot's ten collision points at
the ends of 1-s steps only), the steer keeps those points clear with no extra
margin, and it sees the obstacles as they are at the node's time: Algorithm 1
as the paper evaluates it, for the Table I comparison (`crtraj bench table1`).

The returned path is the tree path, smoothed by the same verified B-spline
as the configuration-space planner (the paper interpolates its path with a
spline before execution); it is not shortcut, so RRT and RRT* keep their own
path shapes. `crtraj.planning.planners._cspace.CSpacePlanner` is the faster default.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from crtraj.planning.base import PlannerBase, QueryStart
from crtraj.planning.context import PlanningContext
from crtraj.planning.ik import SafeIK
from crtraj.planning.planners._tree import SearchTree
from crtraj.planning.postprocess import PathPostprocessor, tree_edges
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.steer import SteerOptions, SteerSolver
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator
from crtraj.world import margin


class RRT(PlannerBase):
    """Task-space RRT with a safety-constrained steer (paper Algorithm 1, no rewiring).

    context: the `PlanningContext` (model, default scene, options; range = tip step in mm; its
    rate limits, if any, also time the edges: the registry builds task-space planners without
    them, see `crtraj.planning.planners._registry`). steer_options:
    `SteerOptions` of the ``[steer]`` section; the planner raises its
    `n_points` to the check points and its `margin` to what the planner's
    continuous-body check needs (module docstring). max_obstacles: obstacle
    slots of the steer and IK NLPs (default: the scene's count).
    """

    name = "rrt"
    rewire = False

    def __init__(
        self,
        context: PlanningContext,
        steer_options: SteerOptions | None = None,
        *,
        max_obstacles: int | None = None,
    ) -> None:
        super().__init__(context)
        model, scene = context.model, context.scene
        M = max(scene.n_obstacles if max_obstacles is None else int(max_obstacles), scene.n_obstacles)
        so = SteerOptions() if steer_options is None else steer_options
        # The paper check (options.check.mode == "paper") looks at the collision points only, so the steer
        # keeps them clear with no continuous-body margin, as the paper's eq. 18 does.
        self.paper = self.options.check.mode == "paper"
        self.steer_options = replace(
            so,
            n_points=max(so.n_points or 0, self.validator.check_points),
            margin=so.margin if self.paper else max(so.margin, self.steer_margin(scene)),
        )
        self.steer = SteerSolver(model, M, self.steer_options)
        self.ik = SafeIK(
            model,
            self.validator,
            M,
            push_rounds=self.options.ik.push_rounds,
            rescue_starts=self.options.ik.rescue_starts,
            compiled=self.options.ik.compiled,
        )

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
        q = self._begin(
            goal,
            start_config=start_config,
            start_tip=start_tip,
            t0=t0,
            stop=stop,
            seed=seed,
            scene=scene,
            goal_tolerance=goal_tolerance,
            counts={"steer_calls": 0, "steer_failed": 0, "not_reached": 0, "edge_rejected": 0},
        )
        if q.x_start is None:
            return self._fail(q, PlanStatus.INVALID_START, q.why)
        why = self._goal_problem(q.query.goal, q.validator.scene, q.query.t0)
        if why:
            return self._fail(q, PlanStatus.INVALID_GOAL, why)
        t1 = time.perf_counter()
        tree, best, best_cost = self._search(q, q.x_start)
        q.timings["search"] = time.perf_counter() - t1
        return self._finish(q, tree, best, best_cost)

    def _prepare(self, v: MotionValidator) -> None:
        sc = v.scene
        if sc.n_obstacles > self.steer.max_obstacles:  # grow the NLPs' obstacle slots (built once more)
            self.steer = SteerSolver(self.model, sc.n_obstacles, self.steer_options)
            self.ik = SafeIK(
                self.model,
                self.validator,
                sc.n_obstacles,
                push_rounds=self.options.ik.push_rounds,
                rescue_starts=self.options.ik.rescue_starts,
                compiled=self.options.ik.compiled,
            )
        self.steer.reset_warm_start()  # the same seed must give the same plan

    def _fail(self, q: QueryStart, status: PlanStatus, msg: str, trees: list[SearchTree] | None = None) -> PlanResult:
        q.counts["iterations"] = q.query.clock.iterations
        return q.fail(status, msg, planner=self.name, robot=self.robot, tree_edges=self._edges(trees or []))

    def _search(self, q: QueryStart, xs: np.ndarray) -> tuple[SearchTree, int, float]:
        """Grow the tree (Algorithm 1) until the stop condition; (tree, goal node or -1, its cost)."""
        o, v, counts = self.options, q.validator, q.counts
        sc = v.scene
        goal, t0, clock, rng = q.query.goal, q.query.t0, q.query.clock, q.query.rng
        goal_tolerance = q.goal_tolerance
        samples0 = v.n_samples
        tree = SearchTree(3, self.robot.nx)
        tree.add(self.model.tip_position(xs), xs, t0, 0.0, -1)
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
            i_new = self._extend(q, tree, P, step, window)
            if i_new < 0:
                continue
            tip_new = tree.keys[i_new]
            # the goal check (line 12), over every goal node: rewiring may lower their costs
            if np.linalg.norm(tip_new - goal) <= goal_tolerance and best < 0:
                best = i_new
            if best >= 0:
                near_goal = tree.within(goal, goal_tolerance)
                if len(near_goal):
                    k = near_goal[np.argmin(tree.cost[near_goal])]
                    best, best_cost = int(k), float(tree.cost[k])
        counts["iterations"] = clock.iterations
        counts["nodes"] = len(tree)
        counts["collision_samples"] = v.n_samples - samples0
        return tree, best, best_cost

    def _extend(self, q: QueryStart, tree: SearchTree, P: np.ndarray, step: float, window: float) -> int:
        """Steer from the node nearest P toward P (at most `step` mm of tip travel) and add the
        verified node (RRT*: with its cheapest parent, then rewire); its index or -1."""
        v, counts = q.validator, q.counts
        n, d = tree.nearest(P)
        if d < 1e-9:
            return -1
        tip_n = tree.keys[n]
        target = tip_n + (P - tip_n) * min(1.0, step / d)
        x_n, t_n = tree.x[n], float(tree.t[n])
        counts["steer_calls"] += 1
        # paper check: the obstacles as they are at the node's time (the start of its step)
        t_end = None if v.static or self.paper else t_n + window
        res = self.steer.solve(x_n, target, v.scene, t=t_n, t_end=t_end, check_start=False)
        if not (res.converged and res.safe):
            counts["steer_failed"] += 1
            return -1
        if not res.reached:
            counts["not_reached"] += 1
            return -1
        # the steer meets the limits to its solver tolerance; put the node exactly inside
        x_new = v.project_limits(res.x)[0]
        dur = float(v.motion_bound(x_new - x_n)) / v.max_speed
        if not v.edges_valid(x_n[None], x_new[None], t_n, t_n + dur)[0]:
            counts["edge_rejected"] += 1
            return -1
        tip_new = self.model.tip_position(x_new)
        parent, cost = n, float(tree.cost[n]) + float(np.linalg.norm(tip_new - tip_n))
        if self.rewire:
            parent, cost = self._choose_parent(tree, v, tip_new, x_new, parent, cost)
        t_new = float(tree.t[parent]) + float(v.motion_bound(x_new - tree.x[parent])) / v.max_speed
        i_new = tree.add(tip_new, x_new, t_new, cost, parent)
        if self.rewire:
            counts["rewired"] = counts.get("rewired", 0) + self._rewire(tree, v, i_new)
        return i_new

    def _finish(self, q: QueryStart, tree: SearchTree, best: int, best_cost: float) -> PlanResult:
        """The verified path to the goal node (or, approximate, to the node nearest the goal)."""
        v, clock, goal, timings = q.validator, q.query.clock, q.query.goal, q.timings
        post = PathPostprocessor(v, self.options, q.query.rng, q.query.t0)
        if best < 0:
            # approximate: the node whose tip came closest to the goal
            d_goal = np.linalg.norm(tree.keys - goal, axis=1)
            k = int(np.argmin(d_goal))
            if k == 0:
                return self._fail(q, PlanStatus.TIMEOUT, f"no path: {clock.reason}", [tree])
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
            seed=q.seed,
            goal=goal,
            X=final,
            raw=raw,
            smoothed=smoothed,
            cost=best_cost,
            goal_configs=None,
            tree_edges=self._edges([tree]),
            timings=timings,
            counts=q.counts,
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
        near = tree.within(tip, self.options.rrt.rewire_radius)
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
        near = tree.within(tip, self.options.rrt.rewire_radius)
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
