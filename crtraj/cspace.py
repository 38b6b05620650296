"""The default planner: safe goal IK, then RRT-Connect in configuration space, shortcuts, a spline.

Why configuration space: the paper's planner (crtraj.planner.RRT/RRTStar)
samples tip positions and runs one safety-constrained IK per sample; its
hard part is reaching a goal at the edge of the workspace, where few
configurations put the tip on the goal while keeping the body clear. This
planner solves that part first and directly:

1. Start: the given configuration (checked), or safe IK for the start tip.
2. Goal: several distinct safe configurations with the tip exactly on the
   goal (`crtraj.safe_ik.SafeIK`: batch projection, then the
   safety-constrained IPOPT NLP).
3. Search: the straight motion start -> goal configuration is tried first;
   then RRT-Connect (Kuffner & LaValle 2000) between a start tree and a goal
   tree rooted at all goal configurations, in the body-motion metric of
   `MotionValidator` (distances are mm of body travel). In a scene whose
   obstacles move or change size the goal tree cannot know when it will be
   reached, so the search is forward only: a timed tree grows from the
   start and every new node tries to connect to the nearest goal
   configuration (RRT-Connect's greedy connect toward the goal set).
   Every motion is checked by `MotionValidator` (continuous body, over
   the time the motion takes).
4. Shortcuts: batches of random shortcuts between two points of the path,
   verified in one vectorised call, keeping the one that saves most.
5. Smoothing: a clamped cubic B-spline (scipy) whose control polygon is the
   shortcut path with extra control points `corner` mm either side of each
   corner, so only the corners are rounded. Its samples are convex
   combinations of configurations within limits, so they are within
   limits too (all limits are convex). The returned motion (straight
   between the samples) is verified again; if it is unsafe the corners are
   halved once, then the raw path is returned.

The returned motion is timed: each straight motion lasts its body-motion
bound divided by `max_speed`, starting at the query's t0.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.interpolate import BSpline

from crtraj.errors import InputError
from crtraj.fields import check_array
from crtraj.model import Model
from crtraj.plan_options import PlannerOptions
from crtraj.plan_result import PlanResult, PlanStatus
from crtraj.safe_ik import SafeIK
from crtraj.stop import StopClock, StopCondition
from crtraj.tree import SearchTree
from crtraj.validity import MotionValidator


class CSpacePlanner:
    """Configuration-space planner for one robot; reuse it for many queries.

    model: the robot's `Model`. scene: the default `crtraj.scene.Scene`
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
        self.validator = self._validator(scene)
        m = scene.n_obstacles if max_obstacles is None else int(max_obstacles)
        self.ik = SafeIK(model, self.validator, max(m, scene.n_obstacles))

    def _validator(self, scene: Any) -> MotionValidator:
        o = self.options
        return MotionValidator(
            self.model, scene, check_points=o.check_points, resolution=o.resolution, max_speed=o.max_speed
        )

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

        Bad input (NaN, wrong shapes) raises `InputError`; an unsafe start
        or an unreachable goal is a result status, not an exception.
        """
        t_begin = time.perf_counter()
        o = self.options
        goal = check_array(goal, "goal", (3,))
        t0 = float(check_array(t0, "t0", ()))
        if not goal_tolerance > 0:
            raise InputError(f"goal_tolerance: must be > 0 mm, got {goal_tolerance}")
        if (start_config is None) == (start_tip is None):
            raise InputError("start: give exactly one of start_config or start_tip")
        stop = o.stop() if stop is None else stop
        stop.check_bounded()
        clock = stop.start()
        deadline = clock.t_start + (stop.time_limit if stop.time_limit is not None else np.inf)
        rng = np.random.default_rng(seed)
        v = self.validator if scene is None or scene is self.scene else self._validator(scene)
        sc = v.scene
        if sc.n_obstacles > self.ik.max_obstacles:
            self.ik = SafeIK(self.model, self.validator, sc.n_obstacles)
        run = _Run(self, v, goal, t0, clock, deadline, rng, seed, goal_tolerance)

        # ---- start
        t1 = time.perf_counter()
        if start_config is not None:
            xs = check_array(start_config, "start_config", (self.robot.nx,))
            viol = float(self.robot.limit_violation(xs)[0])
            if viol > 1e-7:
                return run.fail(PlanStatus.INVALID_START, f"start configuration violates the robot limits by {viol:.3g}")
            c = float(v.clearance(xs[None], t0)[0])
            if c < 0:
                return run.fail(
                    PlanStatus.INVALID_START,
                    f"start configuration is in collision: body clearance {c:.2f} mm (below D_sf + margins)",
                )
        else:
            st = check_array(start_tip, "start_tip", (3,))
            batch = self.ik.solve(
                st,
                sc.pack(t0, self.ik.max_obstacles),
                v.sample(rng, o.ik_seeds),
                t_check=(t0, t0),
                want=max(1, o.goal_configs),
                newton_iterations=o.ik_iterations,
                deadline=deadline,
                validator=v,
                tip_tolerance=min(1e-3, goal_tolerance),
            )
            run.counts["ik_solves_start"] = len(batch.solutions)
            if not len(batch.safe):
                run.timings["start_ik"] = time.perf_counter() - t1
                return run.fail(
                    PlanStatus.INVALID_START,
                    f"no safe configuration puts the tip on the start {st.tolist()} mm "
                    f"({o.ik_seeds} IK starts: {_fmt(batch.statuses)})",
                )
            # the least bent safe configuration
            xs = batch.safe[int(np.argmin(v.motion_bound(_bend_only(batch.safe))))]
        run.timings["start_ik"] = time.perf_counter() - t1
        run.x_start = xs

        # ---- goal configurations
        t1 = time.perf_counter()
        goals = run.goal_configs()
        run.timings["goal_ik"] = time.perf_counter() - t1
        if not len(goals):
            return run.fail(
                PlanStatus.INVALID_GOAL,
                f"no safe configuration puts the tip on the goal {goal.tolist()} mm "
                f"({run.counts.get('ik_solves_goal', 0)} IK solves: {_fmt(run.ik_statuses)})",
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


def _bend_only(X: np.ndarray) -> np.ndarray:
    """Configurations with z zeroed: distance from straight counts bending only."""
    out = np.array(X, dtype=float)
    out[:, -1] = 0.0
    return out


def _fmt(statuses: dict[str, int]) -> str:
    return ", ".join(f"{k} x{n}" for k, n in statuses.items()) or "none tried"


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

    # ---------------------------------------------------------------- goal IK
    def goal_configs(self) -> np.ndarray:
        o, v, sc, ik = self.o, self.v, self.v.scene, self.p.ik
        n = o.ik_seeds
        # the start itself is the first seed: its projection is a goal configuration close to the start
        seeds = np.concatenate([self.x_start[None], v.sample(self.rng, n - 1)]) if n > 1 else self.x_start[None]
        tip_tol = min(1e-3, self.goal_tolerance)
        kw = {"want": o.goal_configs, "newton_iterations": o.ik_iterations, "deadline": self.deadline, "validator": v}
        if v.static or o.goal_window == 0:
            parts = [ik.solve(self.goal, sc.pack(self.t0, ik.max_obstacles), seeds, tip_tolerance=tip_tol, **kw)]
        else:
            # half the starts keep clear of everything the obstacles sweep over the goal window
            t_end = self.t0 + o.goal_window
            half = (len(seeds) + 1) // 2
            parts = [
                ik.solve(
                    self.goal,
                    sc.pack_over(self.t0, t_end, ik.max_obstacles),
                    seeds[:half],
                    t_check=(self.t0, t_end),
                    tip_tolerance=tip_tol,
                    **kw,
                ),
                ik.solve(
                    self.goal,
                    sc.pack(self.t0, ik.max_obstacles),
                    seeds[half:],
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

    def search(self) -> np.ndarray | None:
        """A path (K, nx) from the start to a goal configuration, or None."""
        v = self.v
        # the straight motion to any goal configuration first
        G = len(self.goals)
        XA = np.repeat(self.x_start[None], G, axis=0)
        dur = v.motion_bound(self.goals - XA) / v.max_speed
        per_edge, _, _ = v.edge_clearance(XA, self.goals, self.t0, self.t0 + dur)
        self.counts["edge_checks"] = G
        ok = np.flatnonzero(per_edge >= 0)
        if len(ok):
            best = ok[np.argmin(dur[ok])]
            self.trees = []
            return np.stack([self.x_start, self.goals[best]])
        return self._connect() if v.static else self._forward()

    def _extend(self, tree: SearchTree, y_target: np.ndarray, timed: bool) -> int:
        """One RRT step of at most `range` toward y_target; the new node index or -1."""
        v = self.v
        i, d = tree.nearest(y_target)
        if d < 1e-9:
            return -1
        step = min(self.o.step, d)
        y_i = tree.keys[i]
        y_new = y_i + (y_target - y_i) * (step / d)
        return self._advance(tree, i, v.config_from_metric(y_new), timed)

    def _advance(self, tree: SearchTree, i: int, x_target: np.ndarray, timed: bool, full_only: bool = False) -> int:
        """Add the safe prefix of the motion node i -> x_target; returns the last node added or -1.

        Nodes are added every `range` along the prefix. With full_only, nothing
        is added unless the whole motion is safe.
        """
        v = self.v
        x_i = tree.x[i]
        t_i = float(tree.t[i])
        bound = float(v.motion_bound(x_target - x_i))
        t_end = t_i + bound / v.max_speed if timed else 0.0
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + 1
        f = v.valid_prefix(x_i, x_target, t_i, t_end)
        if f < 1.0 and full_only:
            return -1
        if f * bound < v.resolution:
            return -1
        n_nodes = max(1, int(np.ceil(f * bound / self.o.step - 1e-9)))
        last = i
        for k in range(1, n_nodes + 1):
            fk = f * k / n_nodes
            x = x_i + fk * (x_target - x_i)
            t = t_i + fk * (t_end - t_i) if timed else 0.0
            cost = float(tree.cost[last]) + f * bound / n_nodes
            last = tree.add(v.metric(x), x, t, cost, last)
        return last

    def _connect(self) -> np.ndarray | None:
        """Bidirectional RRT-Connect (static scenes)."""
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = SearchTree(self.p.robot.nx, self.p.robot.nx)
        ts.add(v.metric(self.x_start), self.x_start, 0.0, 0.0, -1)
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
                j_new = self._advance(b, j, x_new, timed=False)
                if j_new >= 0 and np.array_equal(b.x[j_new], x_new):
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

    def _forward(self) -> np.ndarray | None:
        """Timed forward RRT with greedy connection to the goal set (moving obstacles)."""
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = SearchTree(self.p.robot.nx, self.p.robot.nx)
        ts.add(v.metric(self.x_start), self.x_start, self.t0, 0.0, -1)
        self.trees = [ts]
        goal_tree = SearchTree(self.p.robot.nx, self.p.robot.nx)
        for g in self.goals:
            goal_tree.add(v.metric(g), g, 0.0, 0.0, -1)
        y_goals = v.metric(self.goals)
        while not clock.should_stop(False):
            clock.tick()
            if rng.random() < o.goal_bias:
                y_rand = y_goals[rng.integers(len(y_goals))]
            else:
                y_rand = self._sample()
            i_new = self._extend(ts, y_rand, timed=True)
            if i_new < 0:
                continue
            g, _ = goal_tree.nearest(ts.keys[i_new])
            x_goal = self.goals[g]
            j = self._advance(ts, i_new, x_goal, timed=True)
            if j >= 0 and np.array_equal(ts.x[j], x_goal):
                return ts.x[ts.path_to(j)]
        return None

    # ------------------------------------------------------------ post-process
    def _times(self, X: np.ndarray) -> np.ndarray:
        return self.v.times(X, self.t0)

    def _valid(self, X: np.ndarray) -> tuple[bool, float]:
        T = self._times(X)
        if not np.all(self.v.within_limits(X)):
            return False, -np.inf
        c, _ = self.v.path_clearance(X, T)
        return c >= 0.0, c

    def shortcut(self, X: np.ndarray) -> np.ndarray:
        """Batched random shortcuts; each round keeps the verified one that saves most."""
        v, o, rng = self.v, self.o, self.rng
        n_checked = 0
        for _ in range(o.shortcut_rounds):
            if len(X) <= 2 or time.perf_counter() > self.deadline:
                break
            seg = v.motion_bound(np.diff(X, axis=0))
            s = np.concatenate([[0.0], np.cumsum(seg)])
            total = s[-1]
            B = o.shortcut_batch
            u = np.sort(rng.random((B, 2)) * total, axis=1)
            # a third of the candidates skip whole vertices (u on the waypoints)
            k = B // 3
            if k and len(X) > 2:
                idx = np.sort(rng.choice(len(X), size=(k, 2)), axis=1)
                u[:k] = s[idx]
            keep = (u[:, 1] - u[:, 0]) > v.resolution
            u = u[keep]
            if not len(u):
                continue
            P1, P2 = _at(X, s, u[:, 0]), _at(X, s, u[:, 1])
            saving = (u[:, 1] - u[:, 0]) - v.motion_bound(P2 - P1)
            good = saving > 1e-6
            u, P1, P2, saving = u[good], P1[good], P2[good], saving[good]
            if not len(u):
                continue
            cands = [self._splice(X, s, a, b, p1, p2) for a, b, p1, p2 in zip(u[:, 0], u[:, 1], P1, P2)]
            n_checked += len(cands)
            ok = self._batch_ok(cands)
            if not ok.any():
                continue
            best = np.flatnonzero(ok)[np.argmax(saving[ok])]
            X = _dedup(cands[best][0])
        self.counts["shortcut_checks"] = n_checked
        return _dedup(X)

    @staticmethod
    def _splice(
        X: np.ndarray, s: np.ndarray, a: float, b: float, p1: np.ndarray, p2: np.ndarray
    ) -> tuple[np.ndarray, int]:
        """X with the part between arc positions a < b replaced by p1 -> p2; (path, index of p1)."""
        i = int(np.searchsorted(s, a, side="right"))  # waypoints up to a: X[:i]
        j = int(np.searchsorted(s, b, side="left"))  # waypoints from b on: X[j:]
        # p1 may repeat X[i-1] and p2 X[j]: zero-length motions are harmless and removed later
        return np.concatenate([X[:i], p1[None], p2[None], X[j:]]), i

    def _batch_ok(self, cands: list[tuple[np.ndarray, int]]) -> np.ndarray:
        """Which candidate paths are safe, checked in one vectorised call.

        Static scenes: only the new straight motion needs checking. Moving
        obstacles: the rest of the path is reached earlier, so everything from
        the new motion on is checked at its new times.
        """
        v = self.v
        XA, XB, TA, TB, owner = [], [], [], [], []
        for c_i, (C, k) in enumerate(cands):
            T = self._times(C)
            last = k + 1 if v.static else len(C) - 1
            XA.append(C[k:last])
            XB.append(C[k + 1 : last + 1])
            TA.append(T[k:last])
            TB.append(T[k + 1 : last + 1])
            owner.append(np.full(last - k, c_i))
        per_edge, _, _ = v.edge_clearance(np.concatenate(XA), np.concatenate(XB), np.concatenate(TA), np.concatenate(TB))
        worst = np.full(len(cands), np.inf)
        np.minimum.at(worst, np.concatenate(owner), per_edge)
        return worst >= 0.0

    def smooth(self, X: np.ndarray) -> tuple[np.ndarray, bool]:
        """B-spline corner rounding, verified; (path, smoothed?)."""
        o = self.o
        if not o.smooth or len(X) < 3:
            return self.resample(X), False
        corner = o.corner
        for _ in range(2):
            Y = self._spline(X, corner)
            ok, _ = self._valid(Y)
            self.counts["smooth_checks"] = self.counts.get("smooth_checks", 0) + 1
            if ok:
                return Y, True
            corner /= 2.0
        return self.resample(X), False

    def _spline(self, X: np.ndarray, corner: float) -> np.ndarray:
        v = self.v
        ctrl = [X[0]]
        for a, b in zip(X[:-1], X[1:]):
            L = float(v.motion_bound(b - a))
            c = min(corner, L / 3.0) / L if L > 0 else 0.0
            ctrl.extend([a + c * (b - a), b - c * (b - a), b])
        P = np.array(ctrl)
        k = 3
        n = len(P)
        knots = np.concatenate([np.zeros(k), np.linspace(0.0, 1.0, n - k + 1), np.ones(k)])
        spl = BSpline(knots, P, k)
        # fine evaluation, then resampling at equal body-motion spacing
        uu = np.linspace(0.0, 1.0, 40 * n)
        F = spl(uu)
        F[0], F[-1] = X[0], X[-1]
        s = np.concatenate([[0.0], np.cumsum(v.motion_bound(np.diff(F, axis=0)))])
        m = max(2, int(np.ceil(s[-1] / self.o.waypoint_step)) + 1)
        target = np.linspace(0.0, s[-1], m)
        Y = spl(np.interp(target, s, uu))
        Y[0], Y[-1] = X[0], X[-1]  # exact ends (the clamped spline hits them up to round-off)
        return Y

    def resample(self, X: np.ndarray) -> np.ndarray:
        """Insert waypoints on each straight motion so none is longer than `waypoint_step`."""
        v = self.v
        out = [X[:1]]
        for a, b in zip(X[:-1], X[1:]):
            n = max(1, int(np.ceil(float(v.motion_bound(b - a)) / self.o.waypoint_step)))
            f = np.arange(1, n + 1)[:, None] / n
            out.append(a + f * (b - a))
        return np.concatenate(out)

    def finish(self, path: np.ndarray) -> PlanResult:
        t1 = time.perf_counter()
        raw = path
        path = self.shortcut(path)
        self.timings["shortcut"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        final, smoothed = self.smooth(path)
        self.timings["smooth"] = time.perf_counter() - t1
        ok, clear = self._valid(final)
        if not ok:  # the raw tree path is verified edge by edge; this cannot happen unless a bound is wrong
            raise RuntimeError("internal error: the returned path failed its final verification")
        msg = (
            f"found a path after {self.clock.iterations} iterations; "
            f"{len(raw)} tree waypoints, {len(path)} after shortcuts, {'smoothed' if smoothed else 'not smoothed'}"
        )
        return self.result(PlanStatus.EXACT, msg, final, raw, smoothed, clear)

    def approximate(self) -> PlanResult:
        """No connection: the path to the start-tree node whose tip is nearest the goal."""
        ts = self.trees[0] if self.trees else None
        d0 = float(np.linalg.norm(self.model.tip_position(self.x_start) - self.goal))
        if ts is None or len(ts) < 2:
            return self.fail(PlanStatus.TIMEOUT, f"no path: {self.clock.reason}")
        tips = self.model.tip_position(ts.x)
        d = np.linalg.norm(tips - self.goal, axis=1)
        best = int(np.argmin(d))
        if d[best] >= d0:
            return self.fail(PlanStatus.TIMEOUT, f"no path: {self.clock.reason}")
        raw = ts.x[ts.path_to(best)]
        final = self.resample(raw)
        ok, clear = self._valid(final)
        if not ok:
            raise RuntimeError("internal error: the approximate path failed its final verification")
        msg = f"no path to the goal ({self.clock.reason}); closest tip {d[best]:.1f} mm from the goal"
        return self.result(PlanStatus.APPROXIMATE, msg, final, raw, False, clear)

    def fail(self, status: PlanStatus, message: str) -> PlanResult:
        self.timings["total"] = time.perf_counter() - self.clock.t_start
        self.counts.setdefault("iterations", self.clock.iterations)
        nx, nq = self.p.robot.nx, self.p.robot.nq
        return PlanResult(
            status=status,
            message=message,
            planner=CSpacePlanner.name,
            seed=self.seed,
            t=np.zeros(0),
            configs=np.zeros((0, nx)),
            tips=np.zeros((0, 3)),
            cables=np.zeros((0, nq)),
            goal_configs=self.goals if len(self.goals) else None,
            tree_edges=self._tree_edges(),
            timings=dict(self.timings),
            counts=dict(self.counts),
        )

    def result(
        self, status: PlanStatus, message: str, X: np.ndarray, raw: np.ndarray, smoothed: bool, clear: float
    ) -> PlanResult:
        v, model = self.v, self.model
        T = self._times(X)
        tips = model.tip_position(X)
        dense = self._dense(X)
        length = float(np.sum(np.linalg.norm(np.diff(model.tip_position(dense), axis=0), axis=1)))
        self.timings["total"] = time.perf_counter() - self.clock.t_start
        self.counts["nodes"] = int(sum(len(t) for t in self.trees))
        return PlanResult(
            status=status,
            message=message,
            planner=CSpacePlanner.name,
            seed=self.seed,
            t=T,
            configs=X,
            tips=tips,
            cables=model.cables(X),
            length=length,
            cost=float(np.sum(v.motion_bound(np.diff(X, axis=0)))),
            min_clearance=clear,
            goal_error=float(np.linalg.norm(tips[-1] - self.goal)),
            smoothed=smoothed,
            raw_configs=raw,
            raw_t=self._times(raw),
            goal_configs=self.goals,
            tree_edges=self._tree_edges(),
            timings=dict(self.timings),
            counts=dict(self.counts),
        )

    def _dense(self, X: np.ndarray) -> np.ndarray:
        """The path with extra points every ~resolution of body motion (for tip length)."""
        v = self.v
        out = [X[:1]]
        for a, b in zip(X[:-1], X[1:]):
            n = max(1, int(np.ceil(float(v.motion_bound(b - a)) / v.resolution)))
            out.append(a + (np.arange(1, n + 1)[:, None] / n) * (b - a))
        return np.concatenate(out)

    def _tree_edges(self) -> np.ndarray:
        parts = []
        for tr in self.trees:
            if len(tr) < 2:
                continue
            tips = self.model.tip_position(tr.x)
            par, child = tr.edges()
            parts.append(np.stack([tips[par], tips[child]], axis=1))
        return np.concatenate(parts) if parts else np.zeros((0, 2, 3))


def _at(X: np.ndarray, s: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points at arc positions u along the polyline X with cumulative arc s."""
    return np.stack([np.interp(u, s, X[:, j]) for j in range(X.shape[1])], axis=-1)


def _dedup(X: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate waypoints."""
    if len(X) < 2:
        return X
    keep = np.concatenate([[True], np.any(np.abs(np.diff(X, axis=0)) > 1e-12, axis=1)])
    return X[keep]
