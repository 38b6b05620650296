"""The horizon NLP's broad phase: which obstacles can matter over the horizon, so that only they enter the QP.

Every configuration the horizon NLP can plan is within reach of the measured one: its per-step rate rows
keep the actuator changes of one step within ``step_limit`` (|A (x_k - x_k-1)| <= step_limit, with A the
cable matrix), so x_k differs from x_0 by at most k of those steps. No backbone point moves more than the
body-motion bound B(dx) (`crtraj.planning.metric`) for a change dx, so a point p_j(x_k) lies within
``k * reach`` mm of p_j(x_0), with ``reach`` the largest B of one step's change (`step_reach`).

The obstacle row of point j, obstacle i and step k is ``|p_j(x_k) - c_ik| - rho_ik`` (the inflated swept sphere
of `crtraj.control.horizon.Replanner`), so it is at least ``|p_j(x_0) - c_ik| - rho_ik - k reach``. An obstacle
whose smallest such lower bound (its `gap`) is positive keeps every row of every plan the NLP can make
strictly satisfied: it can never be active, and leaving it out of the QP changes neither the feasible plans
within reach nor the solution. The loop still verifies every move against every obstacle. Units: mm, rad, s.
"""

from __future__ import annotations

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.metric import metric_matrix


def step_reach(model: Model, step_limit: np.ndarray) -> float:
    """Largest body-motion bound (mm) of one step whose actuator changes |A dx| stay within step_limit (nq,) mm.

    dx = A^+ (A dx) (A has full column rank), so |dx_i| <= sum_j |A^+_ij| step_limit_j; through y = M dx the
    bound of each bending block is the length of its coordinates' bounds, and z's bound adds on (the block-l1
    norm of `crtraj.planning.metric`)."""
    robot = model.robot
    A, _ = robot.cable_matrix()
    dx = np.abs(np.linalg.pinv(A)) @ np.asarray(step_limit, dtype=float)
    dy = np.abs(metric_matrix(robot)) @ dx
    m = 2 * robot.n_segments
    return float(np.sum(np.hypot(dy[0:m:2], dy[1:m:2])) + dy[-1])


class BroadPhase:
    """Ranks a scene's obstacles by how close the horizon's reachable body can come to them.

    model: the robot's `Model`. points: backbone points per configuration (the NLP's, evenly spread along
    the arc). step_limit: (nq,) mm of actuator change per step (the NLP's rate rows). horizon: N steps.
    """

    def __init__(self, model: Model, points: int, step_limit: np.ndarray, horizon: int) -> None:
        self.model = model
        self.points = int(points)
        self.reach = step_reach(model, step_limit)  # mm per step
        self.reach_steps = self.reach * np.arange(1, int(horizon) + 1)  # (N,) mm after k steps

    def gaps(self, x0: np.ndarray, centers: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """Per obstacle (m,) the smallest lower bound (mm) of its obstacle rows over every plan within reach of
        x0 (nx,): centres (N, m, 3) mm and inflated radii rho (N, m) mm of its slot at each step."""
        P = self.model.points(np.asarray(x0, dtype=float), self.points)  # (points, 3)
        d = np.linalg.norm(centers[:, :, None, :] - P[None, None], axis=-1).min(axis=-1)  # (N, m)
        return np.min(d - rho - self.reach_steps[:, None], axis=0, initial=np.inf)

    def select(self, x0: np.ndarray, centers: np.ndarray, rho: np.ndarray, slots: int) -> tuple[np.ndarray, int]:
        """(indices, relevant): the obstacles that can matter (gap <= 0 mm), ascending, and how many there are.

        When more than `slots` can matter, the `slots` with the smallest gaps (ascending indices): the plan may
        then pass an obstacle the QP does not see, and the loop's dense verification of every move, against
        every obstacle, refuses it."""
        g = self.gaps(x0, centers, rho)
        idx = np.flatnonzero(g <= 0.0)
        if len(idx) > slots:
            idx = np.sort(np.argsort(g, kind="stable")[:slots])
        return idx, int(np.count_nonzero(g <= 0.0))
