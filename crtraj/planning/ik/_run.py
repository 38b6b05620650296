"""The running state of one safe-IK solve (`crtraj.planning.ik.SafeIK.solve`): seeds, projections,
clearances, the solutions tried and the distinct safe configurations kept."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from crtraj.planning.goal import TipGoal
from crtraj.planning.validity import MotionValidator

if TYPE_CHECKING:
    from crtraj.planning.ik._safe_ik import IKSolution


NLP_CONE_SLACK = 1e-3  # rad: the NLP aims this far inside a direction goal's cone


class IKRun:
    """The running state of one `SafeIK.solve` call: the seeds, their projections X (S, nx), tip
    errors (mm) and clearances (mm), which were checked and found safe, every solution tried, and the
    distinct safe configurations kept (closer than `dedup` mm of body motion to a kept one: dropped)."""

    def __init__(
        self,
        target: np.ndarray,
        seeds: np.ndarray,
        v: MotionValidator,
        t_check: tuple[float, float],
        tol: float,
        required: float,
        want: int,
        dedup: float,
    ) -> None:
        S = len(seeds)
        self.target, self.seeds, self.v, self.t_check = target, seeds, v, t_check
        self.tol, self.required, self.want, self.dedup = tol, required, want, dedup
        self.X = seeds.copy()
        self.err = np.full(S, np.inf)
        self.clear = np.full(S, -np.inf)
        self.checked = np.zeros(S, dtype=bool)
        self.good = np.zeros(S, dtype=bool)
        self.sols: list[IKSolution] = []
        self.kept: list[np.ndarray] = []
        self.statuses: dict[str, int] = {}
        self.goal: TipGoal | None = None  # a tip direction goal (`aim`)
        self._tangents: Callable[[np.ndarray], np.ndarray] | None = None

    def aim(self, goal: TipGoal, tangents: Callable[[np.ndarray], np.ndarray]) -> None:
        """Keep only configurations whose tip tangent (`tangents`: (S, nx) -> unit (S, 3)) lies within the cone
        of `goal` (a goal with a direction, at `target`)."""
        self.goal, self._tangents = goal, tangents

    def in_cone(self, X: np.ndarray) -> np.ndarray:
        """Which configurations X (S, nx) keep the goal's direction cone (all, without a direction goal)."""
        if self.goal is None or self._tangents is None or not len(X):
            return np.ones(len(X), dtype=bool)
        return self.goal.within(self._tangents(X))

    def cone_parameters(self) -> np.ndarray:
        """The safe-IK NLP's direction parameters (direction (3,), cos of the cone less NLP_CONE_SLACK rad, so its
        solutions land inside the cone despite its constraint tolerance): inert zeros and -1 without a
        direction goal."""
        if self.goal is None or self.goal.direction is None or self.goal.cone is None:
            return np.array([0.0, 0.0, 0.0, -1.0])
        return np.append(self.goal.direction, np.cos(max(self.goal.cone - NLP_CONE_SLACK, 0.5 * self.goal.cone)))

    def keep(self, x: np.ndarray) -> None:
        if self.kept and np.min(self.v.motion_bound(np.array(self.kept) - x)) < self.dedup:
            return
        self.kept.append(x)

    def add(self, sol: IKSolution) -> None:
        """A safe solution of stage 1 or 2: recorded and kept."""
        self.sols.append(sol)
        self.keep(sol.x)

    def add_all(self, sols: list[IKSolution]) -> None:
        """`add` of each of `sols` in turn, with the body-motion bounds between them and the kept ones in one
        call: the same decisions, up to the rounding of a batch's product against one row's (a bound within
        ~1e-13 mm of `dedup`)."""
        if len(sols) < 2:
            for sol in sols:
                self.add(sol)
            return
        self.sols.extend(sols)
        X = np.array([sol.x for sol in sols])
        ref = np.concatenate([np.array(self.kept).reshape(-1, X.shape[1]), X])
        K = len(self.kept)
        B = self.v.motion_bound(X[:, None, :] - ref[None, :, :])  # (new, kept + new)
        keep = list(range(K))
        for j in range(len(X)):
            if keep and np.min(B[j, keep]) < self.dedup:
                continue
            keep.append(K + j)
            self.kept.append(sols[j].x)


def format_statuses(statuses: dict[str, int]) -> str:
    """'Solve_Succeeded x3, Infeasible_Problem_Detected x2' (for messages)."""
    return ", ".join(f"{k} x{n}" for k, n in statuses.items()) or "none tried"
