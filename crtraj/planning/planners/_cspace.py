"""The default planner: safe goal IK, then RRT-Connect in configuration space, shortcuts, a spline.

Why configuration space: the paper's planner (crtraj.planning.planners.RRT/RRTStar)
samples tip positions and runs one safety-constrained IK per sample; its
hard part is reaching a goal at the edge of the workspace, where few
configurations put the tip on the goal while keeping the body clear. This
planner solves that part first and directly:

1. Start: the given configuration (checked), or safe IK for the start tip.
2. Goal: several distinct safe configurations with the tip exactly on the
   goal (`crtraj.planning.ik.SafeIK`: batch projection, then the
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
5. Smoothing: a clamped cubic B-spline (`crtraj.core.splines`, numpy) whose control polygon is the
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
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.fields import check_array
from crtraj.planning.base import PlannerBase, QueryStart
from crtraj.planning.context import PlanningContext
from crtraj.planning.ik import SafeIK, format_statuses
from crtraj.planning.planners._cspace_search import CSpaceSearch
from crtraj.planning.postprocess import PathPostprocessor, tree_edges
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator


class CSpacePlanner(PlannerBase):
    """Configuration-space planner for one robot; reuse it for many queries.

    context: the `PlanningContext` (model, default scene, options; with rate limits every edge is
    timed within their speed limits). max_obstacles: obstacle slots of the IK NLP (default: the
    scene's count; grown on demand).
    """

    name = "cspace"
    honours_direction = True

    def __init__(self, context: PlanningContext, *, max_obstacles: int | None = None) -> None:
        super().__init__(context)
        scene = context.scene
        m = scene.n_obstacles if max_obstacles is None else int(max_obstacles)
        self.ik = self._safe_ik(max(m, scene.n_obstacles))

    def _safe_ik(self, slots: int) -> SafeIK:
        """The goal IK with `slots` obstacle slots in its NLP, as the options configure it."""
        ik = self.options.ik
        return SafeIK(
            self.model,
            self.validator,
            slots,
            push_rounds=ik.push_rounds,
            rescue_starts=ik.rescue_starts,
            compiled=ik.compiled,
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
        goal_config: Any = None,
    ) -> PlanResult:
        """Plan from a start to a goal tip position (mm).

        Give the start as a configuration (`start_config`, (nx,)) or as a tip
        position (`start_tip`, (3,) mm; a safe configuration is found by IK).
        t0: time (s) at the start, in the scene's clock; obstacles are
        checked at the times the motion reaches them. stop: the stop
        condition (default: the options'). seed: seeds the random generator
        (the same seed gives the same plan). scene: plan among these
        obstacles instead of the planner's scene. goal_tolerance (mm).
        goal: a (3,) tip position (mm), or a `crtraj.planning.goal.TipGoal` whose direction cone the goal
        configurations keep (the tip tangent within the cone).
        goal_config: (nx,) reach this configuration (its tip must be the goal)
        instead of any safe one with the tip on the goal (an approach to a
        motion's start pose).

        Re-planning (a receding-horizon controller re-seeding its reference):
        ``plan(goal, start_config=x_now, t0=t_now, stop=StopCondition(time_limit=0.2),
        scene=predicted_scene)``; the result's times continue from t_now and
        `PlanResult.config_at(t)` gives the verified motion at any time.
        The same seed gives the same plan as long as no time limit fires.

        Bad input (NaN, wrong shapes) raises `InputError`; an unsafe start
        or an unreachable goal is a result status, not an exception.
        """
        q = self._begin(
            goal,
            start_config=start_config,
            start_tip=start_tip,
            t0=t0,
            stop=stop,
            seed=seed,
            scene=scene,
            goal_tolerance=goal_tolerance,
        )
        run = _Query(q, np.zeros((0, self.robot.nx)), [])
        if q.x_start is None:
            return self._fail(run, PlanStatus.INVALID_START, q.why)
        statuses: dict[str, int] = {}
        goals = self._goals(q, q.x_start, goal_config, statuses)
        if not len(goals):
            return self._fail(run, PlanStatus.INVALID_GOAL, unreachable_message(q, statuses))
        run.goals = goals
        return self._search(run)

    def _goals(self, q: QueryStart, xs: np.ndarray, goal_config: Any, statuses: dict[str, int]) -> np.ndarray:
        """The goal configurations: `goal_config` when given (checked), else safe IK solutions (timed)."""
        t1 = time.perf_counter()
        if goal_config is not None:
            goals = check_array(goal_config, "goal_config", (self.robot.nx,))[None]
            if q.validator.static:  # among moving obstacles the search checks it at the time it is reached
                goals = goals[q.validator.state_valid(goals)]
        else:
            goals = self._goal_configs(q, xs, statuses)
        q.timings["goal_ik"] = time.perf_counter() - t1
        return goals

    def _search(self, run: _Query) -> PlanResult:
        """Grow the trees to the goal configurations, then shortcut and smooth the path found."""
        q, goals = run.q, run.goals
        t1 = time.perf_counter()
        query = q.query
        search = CSpaceSearch(q.validator, self.options, q.x_start, goals, query.t0, query.clock, query.rng, q.counts)
        path = search.run()
        run.trees = search.trees
        q.timings["search"] = time.perf_counter() - t1
        if path is not None:  # a verified path exists from here on (before shortcuts and smoothing)
            q.timings["first_solution"] = time.perf_counter() - query.clock.t_start
        q.counts["iterations"] = query.clock.iterations
        if path is None:
            return self._approximate(run)
        return self._finish(run, path)

    def _prepare(self, v: MotionValidator) -> None:
        if v.scene.n_obstacles > self.ik.max_obstacles:
            self.ik = self._safe_ik(v.scene.n_obstacles)

    # ---------------------------------------------------------------- goal IK
    def _goal_configs(self, q: QueryStart, x_start: np.ndarray, statuses: dict[str, int]) -> np.ndarray:
        """Distinct safe configurations (G, nx) with the tip on the goal; IK statuses are added to `statuses`."""
        o, v, ik = self.options, q.validator, self.ik
        sc, goal, t0, rng = v.scene, q.query.goal, q.query.t0, q.query.rng
        n = o.ik.seeds
        # the start itself is the first seed: its projection is a goal configuration close to the start
        seeds = np.concatenate([x_start[None], v.sample(rng, n - 1)]) if n > 1 else x_start[None]
        tip_tol = min(1e-3, q.goal_tolerance)
        kw = {
            "want": o.ik.goal_configs,
            "newton_iterations": o.ik.iterations,
            "deadline": q.query.deadline,
            "validator": v,
            "max_nlp": o.ik.nlp_solves,
            # the safe goal configuration nearest the start: short paths, above all when re-planning
            "always": (0,),
            "direction": q.query.tip_goal,
        }
        if v.static or o.ik.goal_window == 0:
            parts = [ik.solve(goal, lambda: sc.pack(t0, ik.max_obstacles), seeds, tip_tolerance=tip_tol, **kw)]
        else:
            # half the starts keep clear of everything the obstacles sweep over the goal window, by
            # projection only: that NLP is often infeasible (the spheres sweep over the goal region)
            # and its failures would cost far more than the rest of the query
            t_end = t0 + o.ik.goal_window
            half = (len(seeds) + 1) // 2
            parts = [
                ik.solve(
                    goal,
                    lambda: sc.pack_over(t0, t_end, ik.max_obstacles),
                    seeds[:half],
                    t_check=(t0, t_end),
                    tip_tolerance=tip_tol,
                    **{**kw, "max_nlp": 0, "always": (), "push_rounds": 0},
                ),
                ik.solve(
                    goal,
                    lambda: sc.pack(t0, ik.max_obstacles),
                    np.concatenate([seeds[:1], seeds[half:]]),
                    t_check=(t0, t0),
                    tip_tolerance=tip_tol,
                    **kw,
                ),
            ]
        for b in parts:
            for k, c in b.statuses.items():
                statuses[k] = statuses.get(k, 0) + c
        q.counts["ik_solves_goal"] = sum(len(b.solutions) for b in parts)
        return np.concatenate([b.safe for b in parts])

    # ------------------------------------------------------------ post-process
    def _finish(self, run: _Query, path: tuple[np.ndarray, np.ndarray]) -> PlanResult:
        """Shortcut and smooth the search path; return the first candidate that verifies."""
        q = run.q
        v, query = q.validator, q.query
        X, T = path
        post = PathPostprocessor(v, self.options, query.rng, query.t0)
        t1 = time.perf_counter()
        if v.static:  # no clock to keep: every motion at full speed
            short = post.shortcut(X, query.deadline)
            T_short = post.times(short)
        else:
            short, T_short = post.shortcut_timed(X, T, query.deadline)
            # the shortcuts kept the tree path's clock; the same path at full speed is often safe too
            T_fast = post.times(short)
            if T_fast[-1] < T_short[-1] - 1e-9 and v.path_valid(short, T_fast):
                T_short = T_fast
        q.timings["shortcut"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        if v.static:
            final, smoothed = post.smooth(short)
            T_final = post.times(final)
        else:
            final, T_final, smoothed = post.smooth_timed(short, T_short)
        q.timings["smooth"] = time.perf_counter() - t1
        # A resampled motion is made of pieces of certified motions, which the conservative check need
        # not certify again (their time windows differ): then the shortcut path as it stands, then the
        # tree path. Each candidate is verified as returned.
        for cand in ((final, T_final), (short, T_short), (X, T)):
            if (cand[0] is final and smoothed) or v.path_valid(*cand):
                final, T_final = cand
                break
        else:
            raise RuntimeError("internal error: no candidate path passed its final verification")
        msg = (
            f"found a path after {query.clock.iterations} iterations; "
            f"{len(X)} tree waypoints, {len(short)} after shortcuts, {'smoothed' if smoothed else 'not smoothed'}"
        )
        return self._result(run, post, PlanStatus.EXACT, msg, (final, T_final), (X, T), smoothed)

    def _approximate(self, run: _Query) -> PlanResult:
        """No connection: the path to the start-tree node whose tip is nearest the goal."""
        q = run.q
        v, query = q.validator, q.query
        ts = run.trees[0] if run.trees else None
        if ts is None or len(ts) < 2:
            return self._fail(run, PlanStatus.TIMEOUT, f"no path: {query.clock.reason}")
        d0 = float(np.linalg.norm(self.model.tip_position(q.x_start) - query.goal))
        d = np.linalg.norm(self.model.tip_position(ts.x) - query.goal, axis=1)
        best = int(np.argmin(d))
        if d[best] >= d0:
            return self._fail(run, PlanStatus.TIMEOUT, f"no path: {query.clock.reason}")
        post = PathPostprocessor(v, self.options, query.rng, query.t0)
        idx = ts.path_to(best)
        raw = ts.x[idx]
        raw_t = post.times(raw) if v.static else ts.t[idx]
        final, T_final = post.resample_timed_verified(raw, raw_t)
        if not v.path_valid(final, T_final):
            raise RuntimeError("internal error: the approximate path failed its final verification")
        msg = f"no path to the goal ({query.clock.reason}); closest tip {d[best]:.1f} mm from the goal"
        return self._result(run, post, PlanStatus.APPROXIMATE, msg, (final, T_final), (raw, raw_t), False)

    def _result(
        self,
        run: _Query,
        post: PathPostprocessor,
        status: PlanStatus,
        msg: str,
        final_timed: tuple[np.ndarray, np.ndarray],
        raw_timed: tuple[np.ndarray, np.ndarray],
        smoothed: bool,
    ) -> PlanResult:
        q = run.q
        v = q.validator
        final, T = final_timed
        raw, raw_t = raw_timed
        q.counts["nodes"] = int(sum(len(t) for t in run.trees))
        q.counts["collision_samples"] = v.n_samples - q.samples0
        q.timings["total"] = time.perf_counter() - q.query.clock.t_start
        return post.result(
            status=status,
            message=msg,
            planner=self.name,
            seed=q.seed,
            goal=q.query.tip_goal,
            X=final,
            raw=raw,
            smoothed=smoothed,
            cost=float(np.sum(v.motion_bound(np.diff(final, axis=0)))),
            goal_configs=run.goals,
            tree_edges=tree_edges(run.q.validator, run.trees),
            timings=q.timings,
            counts=q.counts,
            T=T,
            raw_t=raw_t,
        )

    def _fail(self, run: _Query, status: PlanStatus, message: str) -> PlanResult:
        return run.q.fail(
            status,
            message,
            planner=self.name,
            robot=self.robot,
            goal_configs=run.goals,
            tree_edges=tree_edges(run.q.validator, run.trees),
        )


@dataclass
class _Query:
    """One query's start, goal configurations and search trees (for the result)."""

    q: QueryStart
    goals: np.ndarray
    trees: list[Any]


def unreachable_message(q: QueryStart, statuses: dict[str, int]) -> str:
    """The one line of a goal no safe configuration reaches; a direction goal's begins with
    ``unreachable_goal:`` and names the cone."""
    tip = q.query.tip_goal
    solves = f"({q.counts.get('ik_solves_goal', 0)} IK solves: {format_statuses(statuses)})"
    if not tip.has_direction:
        return f"no safe configuration puts the tip on the goal {q.query.goal.tolist()} mm {solves}"
    return f"unreachable_goal: no safe configuration puts the tip on the goal {tip.describe()} {solves}"
