"""Growing a configuration-space search tree by checked motions: extend, advance, wait.

Every motion a node is added by is certified by the `MotionValidator` over the
time it takes (continuous body, moving obstacles); a timed tree stores each
node's arrival time (s), an untimed one (static scenes) zeros. Distances are
mm of body motion in the validator's metric.
"""

from __future__ import annotations

import numpy as np

from crtraj.planning.planners._tree import SearchTree
from crtraj.planning.validity import MotionValidator

# Waits (s) tried at once before a straight motion to the goal set (moving obstacles).
WAITS = np.array([0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0])


class TreeGrowth:
    """Adds certified motions to search trees.

    v: the query's validator. step: longest motion per tree edge (mm of body
    motion). counts: the run's counters (``edge_checks`` counts the motions checked).
    """

    def __init__(self, v: MotionValidator, step: float, counts: dict[str, int]) -> None:
        self.v = v
        self.step = step
        self.counts = counts

    def _count(self, n: int) -> None:
        self.counts["edge_checks"] = self.counts.get("edge_checks", 0) + n

    def extend(self, tree: SearchTree, y_target: np.ndarray, timed: bool) -> int:
        """One RRT step of at most `step` toward y_target (metric); the new node index or -1."""
        v = self.v
        i, d = tree.nearest(y_target)
        if d < 1e-9:
            return -1
        step = min(self.step, d)
        y_i = tree.keys[i]
        y_new = y_i + (y_target - y_i) * (step / d)
        return self.advance(tree, i, v.config_from_metric(y_new), timed)[0]

    def advance(
        self, tree: SearchTree, i: int, x_target: np.ndarray, timed: bool, full_only: bool = False
    ) -> tuple[int, bool]:
        """Add the safe prefix of the motion node i -> x_target, a node every `step`.

        Returns (last node added or -1, whether x_target itself was reached and
        added). With full_only, nothing is added unless the whole motion is safe.
        """
        v = self.v
        x_i = tree.x[i]
        t_i = float(tree.t[i])
        bound = float(v.motion_bound(x_target - x_i))
        t_end = t_i + float(v.duration(x_target - x_i)) if timed else 0.0
        self._count(1)
        if full_only:
            f = 1.0 if v.edges_valid(x_i[None], x_target[None], t_i, t_end)[0] else 0.0
        else:
            f = v.valid_prefix(x_i, x_target, t_i, t_end)
        reached = f >= 1.0
        if (full_only and not reached) or f * bound < v.resolution:
            return -1, False
        n_nodes = max(1, int(np.ceil(f * bound / self.step - 1e-9)))
        fk = f * np.arange(n_nodes + 1) / n_nodes
        P = x_i + fk[:, None] * (x_target - x_i)
        if reached:
            P[-1] = x_target
        Tk = t_i + fk * (t_end - t_i) if timed else np.zeros(n_nodes + 1)
        if not (reached and n_nodes == 1):
            # each tree edge is certified as it stands (a piece of a certified motion need not be again:
            # the conservative check of a piece uses other samples and time windows)
            self._count(n_nodes)
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

    def wait(self, tree: SearchTree, i: int, w: float) -> int:
        """Add a node that stays at node i's configuration for w seconds, if that is safe; its index or -1."""
        v = self.v
        x_i, t_i = tree.x[i], float(tree.t[i])
        self._count(1)
        if not v.edges_valid(x_i[None], x_i[None], t_i, t_i + w)[0]:
            return -1
        return tree.add(tree.keys[i].copy(), x_i.copy(), t_i + w, float(tree.cost[i]), i)

    def wait_connect(self, tree: SearchTree, i: int, x_goal: np.ndarray) -> int:
        """Wait at node i for one of `WAITS` seconds, then move straight to x_goal: the shortest wait
        that is safe, checked for all waits in one vectorised call. The goal node's index or -1."""
        v = self.v
        x_i, t_i = tree.x[i], float(tree.t[i])
        W = len(WAITS)
        dur = float(v.duration(x_goal - x_i))
        XA = np.concatenate([np.repeat(x_i[None], W, axis=0), np.repeat(x_i[None], W, axis=0)])
        XB = np.concatenate([np.repeat(x_i[None], W, axis=0), np.repeat(x_goal[None], W, axis=0)])
        TA = np.concatenate([np.full(W, t_i), t_i + WAITS])
        TB = np.concatenate([t_i + WAITS, t_i + WAITS + dur])
        self._count(2 * W)
        ok = v.edges_valid(XA, XB, TA, TB)
        good = np.flatnonzero(ok[:W] & ok[W:])
        if not len(good):
            return -1
        w = float(WAITS[good[0]])
        j = tree.add(tree.keys[i].copy(), x_i.copy(), t_i + w, float(tree.cost[i]), i)
        b = float(v.motion_bound(x_goal - x_i))
        return tree.add(v.metric(x_goal), x_goal, t_i + w + dur, float(tree.cost[i]) + b, j)
