"""The search of the configuration-space planner: goal connection first, then tree growth.

1. Goal connection: the straight motions start -> goal configurations (taken
   when one is at most 1.5 times the shortest), then one batched round of
   two-motion paths start -> via -> goal over `via_points` random via
   configurations, keeping the shortest.
2. Tree growth: in a static scene, RRT-Connect (Kuffner & LaValle 2000)
   between a start tree and a goal tree rooted at all goal configurations;
   among moving obstacles, a timed tree grown forward from the start whose
   every new node tries to connect to the nearest goal configuration, and
   which may wait (see `CSpaceSearch.forward`).

Distances are mm of body motion (the validator's metric), times s.
"""

from __future__ import annotations

import numpy as np

from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners._growth import TreeGrowth
from crtraj.planning.planners._tree import SearchTree
from crtraj.planning.stop import StopClock
from crtraj.planning.validity import MotionValidator

# Longest random wait (s) of one tree extension.
MAX_WAIT = 4.0
# Probability that a timed-tree extension starts from a random node rather than the nearest one.
RANDOM_NODE = 0.25
# A timed-tree node whose extensions failed this often is no longer extended (obstacles took its place).
DEAD_NODE = 8
# start -> via motions checked per round of the via connection (with the validator's early exit)
VIA_CHUNK = 8


class CSpaceSearch:
    """One query's search from x_start to any of `goals` (G, nx) starting at t0 (s).

    clock: the running stop condition; rng: the query's generator; counts:
    the run's counters. After `run`, `trees` holds the trees grown (for drawing).
    """

    def __init__(
        self,
        v: MotionValidator,
        options: PlannerOptions,
        x_start: np.ndarray,
        goals: np.ndarray,
        t0: float,
        clock: StopClock,
        rng: np.random.Generator,
        counts: dict[str, int],
    ) -> None:
        self.v = v
        self.o = options
        self.x_start = x_start
        self.goals = goals
        self.t0 = t0
        self.clock = clock
        self.rng = rng
        self.counts = counts
        self.grow = TreeGrowth(v, options.step, counts)
        self.trees: list[SearchTree] = []
        self.via_seeds = np.zeros((0, v.robot.nx))
        self._samples = np.zeros((0, v.robot.nx))

    def _sample(self) -> np.ndarray:
        if not len(self._samples):
            self._samples = self.v.metric(self.v.sample(self.rng, 64))
        y, self._samples = self._samples[0], self._samples[1:]
        return y

    def _new_tree(self) -> SearchTree:
        return SearchTree(self.v.robot.nx, self.v.robot.nx)

    def run(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A timed path (configurations (K, nx), times (K,) s) from the start to a goal configuration, or None."""
        found = self._connect_goals()
        if found is None:
            found = self.connect() if self.v.static else self.forward()
        if found is None or isinstance(found, tuple):
            return found
        return found, self.v.times(found, self.t0)

    # ------------------------------------------------------- goal connection
    def _connect_goals(self) -> np.ndarray | None:
        """The straight motion to a goal configuration, or the best start -> via -> goal path; None if neither."""
        v = self.v
        G = len(self.goals)
        XA = np.repeat(self.x_start[None], G, axis=0)
        # the bounds once, for the durations and the check (a batch's rows: the numbers the check computes)
        dX = self.goals - XA
        bound = v.motion_bound(dX)
        dur = v.duration(dX, bound)
        self.counts["edge_checks"] = G
        # the shortest valid motion: the first valid in the order of duration (ties: lowest index, as argmin)
        order = np.argsort(dur, kind="stable")
        k = v.first_valid(XA[order], self.goals[order], self.t0, self.t0 + dur[order], bound[order])
        direct = None
        if k >= 0:
            best = order[k]
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
        return via

    def _via(self) -> np.ndarray | None:
        """One batched round of two-motion paths start -> via -> goal over random via configurations.

        Many scenes (the paper's simulation 1 among them) need just one
        intermediate configuration; checking `via_points` candidates in two
        vectorised calls finds one far faster than growing trees one node at
        a time. Valid start -> via motions seed the trees otherwise.
        """
        v, o = self.v, self.o
        self.clock.tick()
        K = o.cspace.via_points
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
            scale=o.cspace.via_spread, size=(n_local, len(g[0]))
        )
        local = v.project_limits(v.config_from_metric(y))
        vias = np.concatenate([local, v.sample(rng, K - n_local)])
        # body-motion bounds of both motions of every candidate once, for their durations and their checks
        d1 = vias - self.x_start
        b1 = v.motion_bound(d1)
        t_via = self.t0 + v.duration(d1, b1)
        # each via tries its nearest goal configuration (body-motion metric); the two-motion paths are
        # checked in the order of arrival (ties: lowest index), a chunk of start -> via motions at a time,
        # until one is valid: the shortest valid one, as checking them all would find
        GB = self.goals[np.argmin(v.motion_bound(vias[:, None, :] - self.goals[None, :, :]), axis=1)]
        d2 = GB - vias
        b2 = v.motion_bound(d2)
        TB = t_via + v.duration(d2, b2)
        order = np.argsort(TB - self.t0, kind="stable")
        chunk = VIA_CHUNK if v.early_exit else K
        ok1 = np.zeros(K, dtype=bool)
        k = -1
        for c in range(0, K, chunk):
            idx = order[c : c + chunk]
            XA = np.repeat(self.x_start[None], len(idx), axis=0)
            # edges_valid with the bounds already computed
            f, _ = v.check_edges(XA, vias[idx], self.t0, t_via[idx], prefix=False, bound=b1[idx], verdict=True)
            ok1[idx] = f >= 1.0
            self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + len(idx)
            idx = idx[ok1[idx]]
            first = v.first_valid(vias[idx], GB[idx], t_via[idx], TB[idx], b2[idx])
            self.counts["edge_checks"] += len(idx)
            if first >= 0:
                k = int(idx[first])
                break
        good = np.flatnonzero(ok1)
        self.via_seeds = vias[good]
        # the verified motions form a one-level tree (kept for drawing)
        tree = SearchTree(v.robot.nx, v.robot.nx)
        tree.add(v.metric(self.x_start), self.x_start, self.t0, 0.0, -1)
        keys, costs = v.metric(vias[good]), v.motion_bound(vias[good] - self.x_start)
        tree.add_many(keys, vias[good], t_via[good], costs, np.zeros(len(good), dtype=int))
        self.trees = [tree]
        if k < 0:
            return None
        cost = float(v.motion_bound(vias[k] - self.x_start) + v.motion_bound(GB[k] - vias[k]))
        tree.add(v.metric(GB[k]), GB[k], float(TB[k]), cost, int(np.searchsorted(good, k)) + 1)
        return np.stack([self.x_start, vias[k], GB[k]])

    # ------------------------------------------------------------ tree growth
    def connect(self) -> np.ndarray | None:
        """Bidirectional RRT-Connect (static scenes): a path start -> goal, or None when the clock stops."""
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = self._new_tree()
        ts.add(v.metric(self.x_start), self.x_start, 0.0, 0.0, -1)
        for x in self.via_seeds:  # motions from the start already verified by the via round
            ts.add(v.metric(x), x, 0.0, float(v.motion_bound(x - self.x_start)), 0)
        tg = self._new_tree()
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
            i_new = self.grow.extend(a, y_rand, timed=False)
            if i_new >= 0:
                x_new = a.x[i_new]
                j, _ = b.nearest(a.keys[i_new])
                j_new, met = self.grow.advance(b, j, x_new, timed=False)
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

    def forward(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Timed forward RRT with greedy connection to the goal set (moving obstacles).

        The robot may also wait: an extension first stays at its tree node for
        a random time with probability `wait_bias`, and a failed connection to
        the goal set is retried after each of `crtraj.planning.planners._growth.WAITS` (one batched check), so
        a sphere that blocks the way for a while is waited out.
        """
        v, o, rng, clock = self.v, self.o, self.rng, self.clock
        ts = self._new_tree()
        ts.add(v.metric(self.x_start), self.x_start, self.t0, 0.0, -1)
        for x in self.via_seeds:  # motions from the start already verified (at these times) by the via round
            b = float(v.motion_bound(x - self.x_start))
            ts.add(v.metric(x), x, self.t0 + float(v.duration(x - self.x_start)), b, 0)
        self.trees = [ts]
        goal_tree = self._new_tree()
        for g in self.goals:
            goal_tree.add(v.metric(g), g, 0.0, 0.0, -1)
        y_goals = v.metric(self.goals)
        fails = np.zeros(len(ts), dtype=int)  # failed extensions per node
        # waiting at the start for the nearest goal configuration, before any tree grows
        g0 = int(np.argmin(v.motion_bound(self.goals - self.x_start)))
        j = self.grow.wait_connect(ts, 0, self.goals[g0])
        if j >= 0:
            return ts.x[ts.path_to(j)], ts.t[ts.path_to(j)]
        while not clock.should_stop(False):
            clock.tick()
            goal_sample = rng.random() < o.goal_bias
            y_rand = y_goals[rng.integers(len(y_goals))] if goal_sample else self._sample()
            waits = rng.random() < o.cspace.wait_bias
            if len(fails) < len(ts):
                fails = np.concatenate([fails, np.zeros(len(ts) - len(fails), dtype=int)])
            i, d = self._pick_node(ts, y_rand, fails)
            i_from = i
            if waits:
                i = self.grow.wait(ts, i, float(rng.uniform(0.0, MAX_WAIT)))
            if i < 0 or d < 1e-9:
                fails[i_from] += 1
                continue
            step = min(o.step, d)
            y_i = ts.keys[i]
            x_new = v.config_from_metric(y_i + (y_rand - y_i) * (step / d))
            i_new = self.grow.advance(ts, i, x_new, timed=True)[0]
            if i_new < 0:
                fails[i_from] += 1
                continue
            g, _ = goal_tree.nearest(ts.keys[i_new])
            x_goal = self.goals[g]
            j, met = self.grow.advance(ts, i_new, x_goal, timed=True)
            if not met and rng.random() < o.cspace.wait_bias:
                j = self.grow.wait_connect(ts, i_new, x_goal)
                met = j >= 0
            if met:
                path = ts.path_to(j)
                return ts.x[path], ts.t[path]
        return None

    # ------------------------------------------------------------ post-process

    def _pick_node(self, ts: SearchTree, y_rand: np.ndarray, fails: np.ndarray) -> tuple[int, float]:
        """The node to extend toward y_rand and its distance: the nearest, or a random live one.

        A node the obstacles are taking over fails every extension: grow from a random node that
        has not failed `DEAD_NODE` times instead (earlier times stay reachable), and now and then
        (`RANDOM_NODE`) anyway.
        """
        rng = self.rng
        i, d = ts.nearest(y_rand)
        if fails[i] >= DEAD_NODE or rng.random() < RANDOM_NODE:
            live = np.flatnonzero(fails[: len(ts)] < DEAD_NODE)
            if not len(live):
                live = np.arange(len(ts))
            i = int(live[rng.integers(len(live))])
            d = float(np.linalg.norm(y_rand - ts.keys[i]))
        return i, d
