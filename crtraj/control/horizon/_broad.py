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
within reach nor the solution. The loop still verifies every move against every obstacle.

When more obstacles can matter than the QP has slots (a fast robot over a long horizon reaches most of its
workspace), the slots take the nearest (`Selection`), and every omitted one is checked at the solution
(`BroadPhase.reselect`): a solution that keeps all of them outside their spheres is a KKT point of the NLP
with every obstacle (the omitted rows hold, with zero multipliers), as with the QP's screened points; one
that enters an omitted sphere is solved again with it in a slot. Units: mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.metric import metric_matrix
from crtraj.world import packing

# an omitted obstacle's row below this (mm) is a violation (the QP's own rows hold to 1e-6)
ROW_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Selection:
    """The obstacles that can matter over one horizon and the ones the QP gets: packed (N, packing.WIDTH *
    slots) the QP's obstacle parameter; centres (N, r, 3) mm and inflated radii rho (N, r) mm of all r that
    can matter; chosen (k,) the indices of those in the slots, ascending."""

    packed: np.ndarray
    centers: np.ndarray
    rho: np.ndarray
    chosen: np.ndarray

    @classmethod
    def of(cls, centers: np.ndarray, rho: np.ndarray, chosen: np.ndarray, slots: int) -> Selection:
        """The selection of `chosen` among centres (N, r, 3) and rho (N, r), packed into `slots` slots."""
        packed = packing.pack(centers[:, chosen], rho[:, chosen], slots, "the replanner")
        return cls(packed, centers, rho, chosen)


def _nearest(C: np.ndarray, P: np.ndarray) -> np.ndarray:
    """min over the last axis of the distances (mm) between C (..., 1, 3) and P (..., n, 3), broadcast:
    `np.linalg.norm`'s numbers (the same sum of squares, x, y, z in that order), by coordinate planes instead of
    a strided reduction, and one square root per minimum (the root is monotone and correctly rounded, so the root
    of the minimum is the minimum of the roots)."""
    dx, dy, dz = (C[..., i] - P[..., i] for i in range(3))
    return np.sqrt((dx * dx + dy * dy + dz * dz).min(axis=-1))


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
        d = _nearest(centers[:, :, None, :], P[None, None])  # (N, m)
        return np.min(d - rho - self.reach_steps[:, None], axis=0, initial=np.inf)

    def pack(
        self, x0: np.ndarray, centers: np.ndarray, rho: np.ndarray, slots: int
    ) -> tuple[np.ndarray, Selection | None]:
        """The QP's obstacle parameter (N, packing.WIDTH * slots) for a horizon from x0 among centres (N, m, 3)
        and rho (N, m) mm, and, when more obstacles can matter than there are slots, the `Selection` whose
        omitted obstacles the solution must be checked against (else None)."""
        g = self.gaps(x0, centers, rho)
        can = np.flatnonzero(g <= 0.0)
        if len(can) <= slots:
            return packing.pack(centers[:, can], rho[:, can], slots, "the replanner"), None
        chosen = np.sort(np.argsort(g[can], kind="stable")[:slots])
        sel = Selection.of(centers[:, can], rho[:, can], chosen, slots)
        return sel.packed, sel

    def reselect(self, sel: Selection, P: np.ndarray, slots: int) -> tuple[float, Selection | None]:
        """(worst, next): the smallest obstacle row (mm) of the obstacles `sel` left out, at the solution's
        backbone points P (N, points, 3) mm; and, when one is inside its sphere, the selection that puts those
        inside first and then the nearest at P into the slots (None when nothing is inside)."""
        rows = _nearest(sel.centers[:, :, None, :], P[:, None]) - sel.rho  # (N, r)
        near = rows.min(axis=0)
        omitted = np.ones(len(near), dtype=bool)
        omitted[sel.chosen] = False
        worst = float(np.min(near[omitted], initial=np.inf))
        if worst >= -ROW_TOLERANCE:
            return worst, None
        inside = omitted & (near < -ROW_TOLERANCE)
        order = np.lexsort((near, ~inside))  # the omitted ones inside first, then by their rows at P
        return worst, Selection.of(sel.centers, sel.rho, np.sort(order[:slots]), slots)

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
