"""The default planner: safe goal IK, then RRT-Connect in configuration space, shortcuts, a spline.

Why configuration space: the paper's planner (crtraj.planning.rrt.RRT/RRTStar)
samples tip positions and runs one safety-constrained IK per sample; its
hard part is reaching a goal at the edge of the workspace, where few
configurations put the tip on the goal while keeping the body clear. This
planner solves that part first and directly:

1. Start: the given configuration (checked), or safe IK for the start tip.
2. Goal: several distinct safe configurations with the tip exactly on the
   goal (`crtraj.planning.safe_ik.SafeIK`: batch projection, then the
   safety-constrained IPOPT NLP), always including the safe goal
   configuration nearest the start (the NLP from the start itself). Among
   moving obstacles half the starts keep clear over the next `goal_window`
   seconds, by projection only (that NLP is often infeasible, and failed
   NLPs cost more than the rest of a query).
3. Search: the straight motions start -> goal configurations are tried
   first (taken when one is at most 1.5 times the shortest), then one
   batched round of two-motion paths start -> via -> goal over `via_points`
   random via configurations (half of them scattered around the straight
   motions), keeping the shortest; then RRT-Connect (Kuffner & LaValle
   2000) between a start tree and a goal
   tree rooted at all goal configurations, in the body-motion metric of
   `MotionValidator` (distances are mm of body travel). In a scene whose
   obstacles move or change size the goal tree cannot know when it will be
   reached, so the search is forward only: a timed tree grows from the
   start and every new node tries to connect to the nearest goal
   configuration (RRT-Connect's greedy connect toward the goal set).
   This tree may also wait: a node that stays at its parent's
   configuration for a while (an extension waits first with probability
   `wait_bias`; a failed connection is retried after a batch of waits), so
   a sphere that blocks the way is waited out rather than only detoured.
   Every motion and wait is checked by `MotionValidator` (continuous body,
   over the time it takes).
4. Shortcuts: batches of random shortcuts between two points of the path,
   verified in one vectorised call, keeping the one that saves most (with
   moving obstacles a shortcut keeps the times of its ends, so only the new
   motion is checked).
5. Smoothing: a clamped cubic B-spline (scipy) whose control polygon is the
   shortcut path with extra control points `corner` mm either side of each
   corner, so only the corners are rounded. Its samples are convex
   combinations of configurations within limits, so they are within
   limits too (all limits are convex). The returned motion (straight
   between the samples) is verified again; if it is unsafe the corners are
   halved once, then the raw path is returned.

The returned motion is timed from the query's t0. In a static scene each
straight motion lasts its body-motion bound divided by `max_speed`; among
moving obstacles the path keeps the times the search verified it at (waits,
and shortcuts that take the time of the detour they replace), never faster
than `max_speed`.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.postprocess import PathPostprocessor, empty_result, tree_edges
from crtraj.planning.query import PlanQuery
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.safe_ik import SafeIK, format_statuses, resolve_start
from crtraj.planning.stop import StopClock, StopCondition
from crtraj.planning.tree import SearchTree
from crtraj.planning.validity import MotionValidator

# Waits (s) tried at once before a straight motion to the goal set (moving obstacles).
WAITS = np.array([0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0])
# Longest random wait (s) of one tree extension.
MAX_WAIT = 4.0
# Probability that a timed-tree extension starts from a random node rather than the nearest one.
RANDOM_NODE = 0.25
# A timed-tree node whose extensions failed this often is no longer extended (obstacles took its place).
DEAD_NODE = 8


class CSpacePlanner:
    """Configuration-space planner for one robot; reuse it for many queries.

    model: the robot's `Model`. scene: the default `crtraj.world.scene.Scene`
    (a query may pass another). options: `PlannerOptions`. max_obstacles:
    obstacle slots of the IK NLP (default: the scene's count; grown on demand).
    """

    name = "cspace"

    def __init__(
        self,
        model: Model,
        scene: Any,
        options: PlannerOptions | None = None,
        *,
        max_obstacles: int | None = None,
    ) -> None:
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.options = PlannerOptions() if options is None else options
        self._functions: dict[Any, Any] = {}  # CasADi functions shared by this planner's validators
        self.validator = self.options.validator(model, scene, self._functions)
        m = scene.n_obstacles if max_obstacles is None else int(max_obstacles)
        self.ik = SafeIK(model, self.validator, max(m, scene.n_obstacles))

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
        """Plan from a start to a goal tip position (mm).

        Give the start as a configuration (`start_config`, (nx,)) or as a tip
        position (`start_tip`, (3,) mm; a safe configuration is found by IK).
        t0: time (s) at the start, in the scene's clock; obstacles are
        checked at the times the motion reaches them. stop: the stop
        condition (default: the options'). seed: seeds the random generator
        (the same seed gives the same plan). scene: plan among these
        obstacles instead of the planner's scene. goal_tolerance (mm).

        Re-planning (a receding-horizon controller re-seeding its reference):
        ``plan(goal, start_config=x_now, t0=t_now, stop=StopCondition(time_limit=0.2),
        scene=predicted_scene)``; the result's times continue from t_now and
        `PlanResult.config_at(t)` gives the verified motion at any time.
        The same seed gives the same plan as long as no time limit fires.

        Bad input (NaN, wrong shapes) raises `InputError`; an unsafe start
        or an unreachable goal is a result status, not an exception.
        """
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
        if sc.n_obstacles > self.ik.max_obstacles:
            self.ik = SafeIK(self.model, self.validator, sc.n_obstacles)
        run = _Run(self, v, goal, t0, clock, deadline, rng, seed, goal_tolerance)

        # ---- start
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
        run.timings["start_ik"] = time.perf_counter() - t1
        run.counts["ik_solves_start"] = n_ik
        if xs is None:
            return run.fail(PlanStatus.INVALID_START, why)
        run.x_start = xs

        # ---- goal configurations
        t1 = time.perf_counter()
        goals = run.goal_configs()
        run.timings["goal_ik"] = time.perf_counter() - t1
        if not len(goals):
            return run.fail(
                PlanStatus.INVALID_GOAL,
                f"no safe configuration puts the tip on the goal {goal.tolist()} mm "
                f"({run.counts.get('ik_solves_goal', 0)} IK solves: {format_statuses(run.ik_statuses)})",
            )
        run.goals = goals

        # ---- search
        t1 = time.perf_counter()
        path = run.search()
        run.timings["search"] = time.perf_counter() - t1
        run.counts["iterations"] = clock.iterations
        if path is None:
            return run.approximate()
        return run.finish(path)


class _Run:
    """State of one planning query (keeps `CSpacePlanner.plan` readable)."""

    def __init__(
        self,
        planner: CSpacePlanner,
        v: MotionValidator,
        goal: np.ndarray,
        t0: float,
        clock: StopClock,
        deadline: float,
        rng: np.random.Generator,
        seed: int | None,
        goal_tolerance: float,
    ) -> None:
        self.p = planner
        self.o = planner.options
        self.v = v
        self.model = planner.model
        self.goal = goal
        self.t0 = t0
        self.clock = clock
        self.deadline = deadline
        self.rng = rng
        self.seed = seed
        self.goal_tolerance = goal_tolerance
        self.timings: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.ik_statuses: dict[str, int] = {}
        self.x_start = np.zeros(planner.robot.nx)
        self.goals = np.zeros((0, planner.robot.nx))
        self.trees: list[SearchTree] = []
        self._samples = np.zeros((0, planner.robot.nx))
        self.samples0 = v.n_samples
        self.via_seeds = np.zeros((0, planner.robot.nx))

    # ---------------------------------------------------------------- goal IK
    def goal_configs(self) -> np.ndarray:
        o, v, sc, ik = self.o, self.v, self.v.scene, self.p.ik
        n = o.ik_seeds
        # the start itself is the first seed: its projection is a goal configuration close to the start
        seeds = np.concatenate([self.x_start[None], v.sample(self.rng, n - 1)]) if n > 1 else self.x_start[None]
        tip_tol = min(1e-3, self.goal_tolerance)
        kw = {
            "want": o.goal_configs,
            "newton_iterations": o.ik_iterations,
            "deadline": self.deadline,
            "validator": v,
            "max_nlp": o.ik_nlp_solves,
            # the safe goal configuration nearest the start: short paths, above all when re-planning
            "always": (0,),
        }
        if v.static or o.goal_window == 0:
            parts = [ik.solve(self.goal, sc.pack(self.t0, ik.max_obstacles), seeds, tip_tolerance=tip_tol, **kw)]
        else:
            # half the starts keep clear of everything the obstacles sweep over the goal window, by
            # projection only: that NLP is often infeasible (the spheres sweep over the goal region)
            # and its failures would cost far more than the rest of the query
            t_end = self.t0 + o.goal_window
            half = (len(seeds) + 1) // 2
            parts = [
                ik.solve(
                    self.goal,
                    sc.pack_over(self.t0, t_end, ik.max_obstacles),
                    seeds[:half],
                    t_check=(self.t0, t_end),
                    tip_tolerance=tip_tol,
                    **{**kw, "max_nlp": 0, "always": ()},
                ),
                ik.solve(
                    self.goal,
                    sc.pack(self.t0, ik.max_obstacles),
                    np.concatenate([seeds[:1], seeds[half:]]),
                    t_check=(self.t0, self.t0),
                    tip_tolerance=tip_tol,
                    **kw,
                ),
            ]
        for b in parts:
            for k, c in b.statuses.items():
                self.ik_statuses[k] = self.ik_statuses.get(k, 0) + c
        self.counts["ik_solves_goal"] = sum(len(b.solutions) for b in parts)
        return np.concatenate([b.safe for b in parts])

    # ----------------------------------------------------------------- search
    def _sample(self) -> np.ndarray:
        if not len(self._samples):
            self._samples = self.v.metric(self.v.sample(self.rng, 64))
        y, self._samples = self._samples[0], self._samples[1:]
        return y

    def search(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A timed path (configurations (K, nx), times (K,) s) from the start to a goal configuration, or None."""
        found = self._search()
        if found is None or isinstance(found, tuple):
            return found
        return found, self.v.times(found, self.t0)

    def _search(self) -> np.ndarray | tuple[np.ndarray, np.ndarray] | None:
        v = self.v
        # the straight motion to any goal configuration first
        G = len(self.goals)
        XA = np.repeat(self.x_start[None], G, axis=0)
        dur = v.motion_bound(self.goals - XA) / v.max_speed
        self.counts["edge_checks"] = G
        ok = np.flatnonzero(v.edges_valid(XA, self.goals, self.t0, self.t0 + dur))
        direct = None
        if len(ok):
            best = ok[np.argmin(dur[ok])]
            direct = np.stack([self.x_start, self.goals[best]])
            # a direct motion to a far goal configuration can be much longer than a small detour
            # to the nearest one: then the via round competes
            if dur[best] <= 1.5 * dur.min():
                self.trees = []
                return direct
        via = self._via()
        if direct is not None:
            if via is None or v.motion_bound(np.diff(via, axis=0)).sum() >= v.motion_bound(direct[1] - direct[0]):
                return direct
            return via
        if via is not None:
            return via
        return self._connect() if v.static else self._forward()

    def _via(self) -> np.ndarray | None:
        """One batched round of two-motion paths start -> via -> goal over random via configurations.

        Many scenes (the paper's simulation 1 among them) need just one
        intermediate configuration; checking `via_points` candidates in two
        vectorised calls finds one far faster than growing trees one node at
        a time. Valid start -> via motions seed the trees otherwise.
        """
        v, o = self.v, self.o
        self.clock.tick()
        K = o.via_points
        if K == 0:
            return None
        # half uniform over the whole space, half around the straight motions to the goal configurations
        # (a small detour is the common case, and it makes the two-motion path short)
        rng = self.rng
        n_local = K // 2
        g = self.goals[rng.integers(len(self.goals), size=n_local)]
        g[: n_local // 2] = self.goals[int(np.argmin(v.motion_bound(self.goals - self.x_start)))]
        lam = rng.uniform(0.2, 0.8, size=(n_local, 1))
        y = v.metric(self.x_start + lam * (g - self.x_start)) + rng.normal(
            scale=o.via_spread, size=(n_local, len(g[0]))
        )
        local = v.project_limits(v.config_from_metric(y))
        vias = np.concatenate([local, v.sample(rng, K - n_local)])
        t_via = self.t0 + v.motion_bound(vias - self.x_start) / v.max_speed
        ok1 = v.edges_valid(np.repeat(self.x_start[None], K, axis=0), vias, self.t0, t_via)
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + K
        good = np.flatnonzero(ok1)
        self.via_seeds = vias[good]
        # the verified motions form a one-level tree (kept for drawing)
        tree = SearchTree(v.robot.nx, v.robot.nx)
        tree.add(v.metric(self.x_start), self.x_start, self.t0, 0.0, -1)
        for x, t in zip(vias[good], t_via[good], strict=True):
            tree.add(v.metric(x), x, float(t), float(v.motion_bound(x - self.x_start)), 0)
        self.trees = [tree]
        if not len(good):
            return None
        # each via tries its nearest goal configuration (body-motion metric)
        d = v.motion_bound(vias[good][:, None, :] - self.goals[None, :, :])  # (V, G)
        VA = vias[good]
        GB = self.goals[np.argmin(d, axis=1)]
        TA = t_via[good]
        TB = TA + v.motion_bound(GB - VA) / v.max_speed
        ok2 = v.edges_valid(VA, GB, TA, TB)
        self.counts["edge_checks"] += len(VA)
        if not ok2.any():
            return None
        # the shortest valid two-motion path
        total = (TB - self.t0)[ok2]
        k = np.flatnonzero(ok2)[int(np.argmin(total))]
        tree.add(v.metric(GB[k]), GB[k], float(TB[k]), float(total.min()) * v.max_speed, int(k) + 1)
        return np.stack([self.x_start, VA[k], GB[k]])

    def _extend(self, tree: SearchTree, y_target: np.ndarray, timed: bool) -> int:
        """One RRT step of at most `range` toward y_target; the new node index or -1."""
        v = self.v
        i, d = tree.nearest(y_target)
        if d < 1e-9:
            return -1
        step = min(self.o.step, d)
        y_i = tree.keys[i]
        y_new = y_i + (y_target - y_i) * (step / d)
        return self._advance(tree, i, v.config_from_metric(y_new), timed)[0]

    def _advance(
        self, tree: SearchTree, i: int, x_target: np.ndarray, timed: bool, full_only: bool = False
    ) -> tuple[int, bool]:
        """Add the safe prefix of the motion node i -> x_target, a node every `range`.

        Returns (last node added or -1, whether x_target itself was reached and
        added). With full_only, nothing is added unless the whole motion is safe.
        """
        v = self.v
        x_i = tree.x[i]
        t_i = float(tree.t[i])
        bound = float(v.motion_bound(x_target - x_i))
        t_end = t_i + bound / v.max_speed if timed else 0.0
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + 1
        if full_only:
            f = 1.0 if v.edges_valid(x_i[None], x_target[None], t_i, t_end)[0] else 0.0
        else:
            f = v.valid_prefix(x_i, x_target, t_i, t_end)
        reached = f >= 1.0
        if (full_only and not reached) or f * bound < v.resolution:
            return -1, False
        n_nodes = max(1, int(np.ceil(f * bound / self.o.step - 1e-9)))
        fk = f * np.arange(n_nodes + 1) / n_nodes
        P = x_i + fk[:, None] * (x_target - x_i)
        if reached:
            P[-1] = x_target
        Tk = t_i + fk * (t_end - t_i) if timed else np.zeros(n_nodes + 1)
        if not (reached and n_nodes == 1):
            # each tree edge is certified as it stands (a piece of a certified motion need not be again:
            # the conservative check of a piece uses other samples and time windows)
            self.counts["edge_checks"] += n_nodes
            ok = v.edges_valid(P[:-1], P[1:], Tk[:-1], Tk[1:])
            n_ok = int(np.argmin(ok)) if not ok.all() else n_nodes
            if n_ok < n_nodes:
                reached = False
                n_nodes = n_ok
            if n_nodes == 0:
                return -1, False
        last = i
        for k in range(1, n_nodes + 1):
            cost = float(tree.cost[last]) + f * bound / max(1, len(fk) - 1)
            last = tree.add(v.metric(P[k]), P[k], float(Tk[k]), cost, last)
        return last, reached

    def _connect(self) -> np.ndarray | None:
        """Bidirectional RRT-Connect (static scenes)."""
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = SearchTree(self.p.robot.nx, self.p.robot.nx)
        ts.add(v.metric(self.x_start), self.x_start, 0.0, 0.0, -1)
        for x in self.via_seeds:  # motions from the start already verified by the via round
            ts.add(v.metric(x), x, 0.0, float(v.motion_bound(x - self.x_start)), 0)
        tg = SearchTree(self.p.robot.nx, self.p.robot.nx)
        for g in self.goals:
            tg.add(v.metric(g), g, 0.0, 0.0, -1)
        self.trees = [ts, tg]
        y_goals = v.metric(self.goals)
        y_start = v.metric(self.x_start)
        a, b = ts, tg
        while not clock.should_stop(False):
            clock.tick()
            if rng.random() < o.goal_bias:
                y_rand = y_goals[rng.integers(len(y_goals))] if a is ts else y_start
            else:
                y_rand = self._sample()
            i_new = self._extend(a, y_rand, timed=False)
            if i_new >= 0:
                x_new = a.x[i_new]
                j, _ = b.nearest(a.keys[i_new])
                j_new, met = self._advance(b, j, x_new, timed=False)
                if met:
                    pa, pb = a.path_to(i_new), b.path_to(j_new)
                    xa, xb = a.x[pa], b.x[pb][::-1][1:]  # drop the duplicate meeting node
                    path = np.concatenate([xa, xb]) if a is ts else np.concatenate([xb[::-1], xa[::-1]])
                    return path if a is ts else self._orient(path)
            a, b = b, a
        return None

    def _orient(self, path: np.ndarray) -> np.ndarray:
        """Make a path run start -> goal."""
        if np.array_equal(path[0], self.x_start):
            return path
        return path[::-1]

    def _wait(self, tree: SearchTree, i: int, w: float) -> int:
        """Add a node that stays at node i's configuration for w seconds, if that is safe; its index or -1."""
        v = self.v
        x_i, t_i = tree.x[i], float(tree.t[i])
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + 1
        if not v.edges_valid(x_i[None], x_i[None], t_i, t_i + w)[0]:
            return -1
        return tree.add(tree.keys[i].copy(), x_i.copy(), t_i + w, float(tree.cost[i]), i)

    def _wait_connect(self, tree: SearchTree, i: int, x_goal: np.ndarray) -> int:
        """Wait at node i for one of `WAITS` seconds, then move straight to x_goal: the shortest wait
        that is safe, checked for all waits in one vectorised call. The goal node's index or -1."""
        v = self.v
        x_i, t_i = tree.x[i], float(tree.t[i])
        W = len(WAITS)
        dur = float(v.motion_bound(x_goal - x_i)) / v.max_speed
        XA = np.concatenate([np.repeat(x_i[None], W, axis=0), np.repeat(x_i[None], W, axis=0)])
        XB = np.concatenate([np.repeat(x_i[None], W, axis=0), np.repeat(x_goal[None], W, axis=0)])
        TA = np.concatenate([np.full(W, t_i), t_i + WAITS])
        TB = np.concatenate([t_i + WAITS, t_i + WAITS + dur])
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + 2 * W
        ok = v.edges_valid(XA, XB, TA, TB)
        good = np.flatnonzero(ok[:W] & ok[W:])
        if not len(good):
            return -1
        w = float(WAITS[good[0]])
        j = tree.add(tree.keys[i].copy(), x_i.copy(), t_i + w, float(tree.cost[i]), i)
        b = float(v.motion_bound(x_goal - x_i))
        return tree.add(v.metric(x_goal), x_goal, t_i + w + dur, float(tree.cost[i]) + b, j)

    def _forward(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Timed forward RRT with greedy connection to the goal set (moving obstacles).

        The robot may also wait: an extension first stays at its tree node for
        a random time with probability `wait_bias`, and a failed connection to
        the goal set is retried after each of `WAITS` (one batched check), so
        a sphere that blocks the way for a while is waited out.
        """
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = SearchTree(self.p.robot.nx, self.p.robot.nx)
        ts.add(v.metric(self.x_start), self.x_start, self.t0, 0.0, -1)
        for x in self.via_seeds:  # motions from the start already verified (at these times) by the via round
            b = float(v.motion_bound(x - self.x_start))
            ts.add(v.metric(x), x, self.t0 + b / v.max_speed, b, 0)
        self.trees = [ts]
        goal_tree = SearchTree(self.p.robot.nx, self.p.robot.nx)
        for g in self.goals:
            goal_tree.add(v.metric(g), g, 0.0, 0.0, -1)
        y_goals = v.metric(self.goals)
        fails = np.zeros(len(ts), dtype=int)  # failed extensions per node
        # waiting at the start for the nearest goal configuration, before any tree grows
        g0 = int(np.argmin(v.motion_bound(self.goals - self.x_start)))
        j = self._wait_connect(ts, 0, self.goals[g0])
        if j >= 0:
            return ts.x[ts.path_to(j)], ts.t[ts.path_to(j)]
        while not clock.should_stop(False):
            clock.tick()
            goal_sample = rng.random() < o.goal_bias
            y_rand = y_goals[rng.integers(len(y_goals))] if goal_sample else self._sample()
            waits = rng.random() < o.wait_bias
            i, d = ts.nearest(y_rand)
            if len(fails) < len(ts):
                fails = np.concatenate([fails, np.zeros(len(ts) - len(fails), dtype=int)])
            if fails[i] >= DEAD_NODE or rng.random() < RANDOM_NODE:
                # a node the obstacles are taking over fails every extension: grow from a random node that
                # has not failed that often instead (earlier times stay reachable)
                live = np.flatnonzero(fails[: len(ts)] < DEAD_NODE)
                if not len(live):
                    live = np.arange(len(ts))
                i = int(live[rng.integers(len(live))])
                d = float(np.linalg.norm(y_rand - ts.keys[i]))
            i_from = i
            if waits:
                i = self._wait(ts, i, float(rng.uniform(0.0, MAX_WAIT)))
            if i < 0 or d < 1e-9:
                fails[i_from] += 1
                continue
            step = min(o.step, d)
            y_i = ts.keys[i]
            x_new = v.config_from_metric(y_i + (y_rand - y_i) * (step / d))
            i_new = self._advance(ts, i, x_new, timed=True)[0]
            if i_new < 0:
                fails[i_from] += 1
                continue
            g, _ = goal_tree.nearest(ts.keys[i_new])
            x_goal = self.goals[g]
            j, met = self._advance(ts, i_new, x_goal, timed=True)
            if not met and rng.random() < o.wait_bias:
                j = self._wait_connect(ts, i_new, x_goal)
                met = j >= 0
            if met:
                path = ts.path_to(j)
                return ts.x[path], ts.t[path]
        return None

    # ------------------------------------------------------------ post-process
    def finish(self, path: tuple[np.ndarray, np.ndarray]) -> PlanResult:
        X, T = path
        post = PathPostprocessor(self.v, self.o, self.rng, self.t0)
        t1 = time.perf_counter()
        if self.v.static:  # no clock to keep: every motion at full speed
            short = post.shortcut(X, self.deadline)
            T_short = post.times(short)
        else:
            short, T_short = post.shortcut_timed(X, T, self.deadline)
            # the shortcuts kept the tree path's clock; the same path at full speed is often safe too
            T_fast = post.times(short)
            if T_fast[-1] < T_short[-1] - 1e-9 and self.v.path_valid(short, T_fast):
                T_short = T_fast
        self.timings["shortcut"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        if self.v.static:
            final, smoothed = post.smooth(short)
            T_final = post.times(final)
        else:
            final, T_final, smoothed = post.smooth_timed(short, T_short)
        self.timings["smooth"] = time.perf_counter() - t1
        # A resampled motion is made of pieces of certified motions, which the conservative check need
        # not certify again (their time windows differ): then the shortcut path as it stands, then the
        # tree path. Each candidate is verified as returned.
        for cand in ((final, T_final), (short, T_short), (X, T)):
            if (cand[0] is final and smoothed) or self.v.path_valid(*cand):
                final, T_final = cand
                break
        else:
            raise RuntimeError("internal error: no candidate path passed its final verification")
        msg = (
            f"found a path after {self.clock.iterations} iterations; "
            f"{len(X)} tree waypoints, {len(short)} after shortcuts, {'smoothed' if smoothed else 'not smoothed'}"
        )
        return self._result(post, PlanStatus.EXACT, msg, (final, T_final), (X, T), smoothed)

    def approximate(self) -> PlanResult:
        """No connection: the path to the start-tree node whose tip is nearest the goal."""
        ts = self.trees[0] if self.trees else None
        if ts is None or len(ts) < 2:
            return self.fail(PlanStatus.TIMEOUT, f"no path: {self.clock.reason}")
        d0 = float(np.linalg.norm(self.model.tip_position(self.x_start) - self.goal))
        d = np.linalg.norm(self.model.tip_position(ts.x) - self.goal, axis=1)
        best = int(np.argmin(d))
        if d[best] >= d0:
            return self.fail(PlanStatus.TIMEOUT, f"no path: {self.clock.reason}")
        post = PathPostprocessor(self.v, self.o, self.rng, self.t0)
        idx = ts.path_to(best)
        raw = ts.x[idx]
        raw_t = post.times(raw) if self.v.static else ts.t[idx]
        final, T_final = post.resample_timed_verified(raw, raw_t)
        if not self.v.path_valid(final, T_final):
            raise RuntimeError("internal error: the approximate path failed its final verification")
        msg = f"no path to the goal ({self.clock.reason}); closest tip {d[best]:.1f} mm from the goal"
        return self._result(post, PlanStatus.APPROXIMATE, msg, (final, T_final), (raw, raw_t), False)

    def _result(
        self,
        post: PathPostprocessor,
        status: PlanStatus,
        msg: str,
        final_timed: tuple[np.ndarray, np.ndarray],
        raw_timed: tuple[np.ndarray, np.ndarray],
        smoothed: bool,
    ) -> PlanResult:
        final, T = final_timed
        raw, raw_t = raw_timed
        self.counts["nodes"] = int(sum(len(t) for t in self.trees))
        self.counts["collision_samples"] = self.v.n_samples - self.samples0
        self.timings["total"] = time.perf_counter() - self.clock.t_start
        res = post.result(
            status=status,
            message=msg,
            planner=CSpacePlanner.name,
            seed=self.seed,
            goal=self.goal,
            X=final,
            raw=raw,
            smoothed=smoothed,
            cost=float(np.sum(self.v.motion_bound(np.diff(final, axis=0)))),
            goal_configs=self.goals,
            tree_edges=tree_edges(self.model, self.trees),
            timings=self.timings,
            counts=self.counts,
            T=T,
            raw_t=raw_t,
        )
        return res

    def fail(self, status: PlanStatus, message: str) -> PlanResult:
        self.counts.setdefault("iterations", self.clock.iterations)
        self.timings["total"] = time.perf_counter() - self.clock.t_start
        return empty_result(
            status,
            message,
            planner=CSpacePlanner.name,
            seed=self.seed,
            robot=self.p.robot,
            goal_configs=self.goals,
            tree_edges=tree_edges(self.model, self.trees),
            timings=self.timings,
            counts=self.counts,
        )
