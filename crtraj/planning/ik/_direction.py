"""The safe IK's projection onto a tip position and a tip direction cone (`crtraj.planning.goal.TipGoal`).

Seeds take damped-Newton steps on the stacked residual

    r = [target - tip(x)  (mm);  DIRECTION_WEIGHT * (aim(x) - tangent(x))]

where tangent(x) is the tip frame's z axis and aim(x) the direction of the cone that is nearest the tangent,
the cone shrunk to `AIM` of its half-angle (so a projection ends inside the cone, not on its edge); a tangent
already inside the shrunk cone has no direction residual (its rows get weight 0: the step then only keeps
the tangent where it is, to first order). Each step is the smallest body motion (metric W = M^T M, damped)
that removes the residual, at most `step` mm of it, then back into the limits. One mapped CasADi call per
step evaluates every seed's tip, tangent and both Jacobians. Units mm, rad.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from crtraj.planning.goal import TipGoal

# mm of residual per unit of tangent error (a tangent 0.1 off weighs like 10 mm of tip error)
DIRECTION_WEIGHT = 100.0
# the projection aims inside this fraction of the cone's half-angle
AIM = 0.8


class DirectionProjection:
    """Batched projection onto tip(x) = target with the tip tangent inside a cone (module docstring).

    model: the robot model (`tip_frame`). W_inv (nx, nx): inverse of the body metric M^T M. damping: of the
    least-squares solve. step: largest residual (mm) removed per step. project_limits: maps configurations
    (S, nx) back into the robot's limits (the validator's).
    """

    def __init__(self, model: Any, W_inv: np.ndarray, damping: float, step: float, project_limits: Any) -> None:
        x = ca.SX.sym("x", model.robot.nx)
        T = model.tip_frame(x)
        p, t = T[:3, 3], T[:3, 2]
        self._single = ca.Function("tip_dir_jac", [x], [p, t, ca.jacobian(p, x), ca.jacobian(t, x)], {"cse": True})
        self._mapped: dict[int, ca.Function] = {}
        self.nx = model.robot.nx
        self.W_inv, self.damping, self.step = W_inv, float(damping), float(step)
        self.project_limits = project_limits

    def evaluate(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tips (S, 3) mm, unit tangents (S, 3), tip Jacobians (S, 3, nx) and tangent Jacobians (S, 3, nx)."""
        S = len(X)
        f = self._mapped.get(S)
        if f is None:
            f = self._single.map(S, "serial")
            self._mapped[S] = f
        P, Tn, Jp, Jt = (np.asarray(a) for a in f(X.T))
        nx = self.nx
        return (
            P.T.copy(),
            Tn.T.copy(),
            Jp.reshape(3, S, nx).transpose(1, 0, 2).copy(),
            Jt.reshape(3, S, nx).transpose(1, 0, 2).copy(),
        )

    def tangents(self, X: np.ndarray) -> np.ndarray:
        """Unit tip tangents (S, 3) of configurations X (S, nx)."""
        return self.evaluate(np.atleast_2d(np.asarray(X, dtype=float)))[1]

    def project(
        self, goal: TipGoal, seeds: np.ndarray, iterations: int, tol: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project seeds (S, nx) toward the goal's position and cone: (configurations (S, nx), tip errors (S,)
        mm, tangent angles to the direction (S,) rad). Stops early once every tip is within `tol` mm and every
        tangent within the cone."""
        assert goal.direction is not None and goal.cone is not None, "a goal with a direction"
        X = np.atleast_2d(np.asarray(seeds, dtype=float)).copy()
        err = np.full(len(X), np.inf)
        ang = np.full(len(X), np.inf)
        for it in range(iterations + 1):
            P, Tn, Jp, Jt = self.evaluate(X)
            e_p = goal.position - P
            err = np.linalg.norm(e_p, axis=1)
            ang = goal.angles(Tn)
            if it == iterations or (np.all(err <= tol) and np.all(ang <= goal.cone)):
                break
            e_t, w = _aim_residual(goal, Tn, ang)
            r = np.concatenate([e_p, DIRECTION_WEIGHT * w[:, None] * e_t], axis=1)
            J = np.concatenate([Jp, DIRECTION_WEIGHT * w[:, None, None] * Jt], axis=1)
            size = np.linalg.norm(r, axis=1)
            r *= np.minimum(1.0, self.step / np.maximum(size, 1e-300))[:, None]
            JW = J @ self.W_inv
            A = JW @ np.transpose(J, (0, 2, 1)) + self.damping * np.eye(J.shape[1])
            dx = np.einsum("nij,ni->nj", JW, np.linalg.solve(A, r[..., None])[..., 0])
            X = self.project_limits(X + dx)
        return X, err, ang


def _aim_residual(goal: TipGoal, Tn: np.ndarray, ang: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(aim - tangent (S, 3), row weights (S,)): the aim is the direction at AIM times the cone's half-angle
    from the goal direction toward the tangent (the goal direction itself when the tangent is antiparallel);
    weight 0 for tangents already inside that shrunk cone."""
    d = goal.direction
    assert d is not None and goal.cone is not None
    limit = AIM * goal.cone
    perp = Tn - (Tn @ d)[:, None] * d
    n = np.linalg.norm(perp, axis=1)
    u = np.where(n[:, None] > 1e-9, perp / np.maximum(n, 1e-300)[:, None], 0.0)
    aim = np.cos(limit) * d + np.sin(limit) * u
    aim[n <= 1e-9] = d
    w = (ang > limit).astype(float)
    return aim - Tn, w
