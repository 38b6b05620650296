"""Where the goal IK's tips and tip Jacobians come from: the validator's compiled kernel when it has one (a rod
kernel's own body, or PCC's for the push-out's direction), else mapped CasADi calls of the model, built on first
use. Units: mm, rad."""

from __future__ import annotations

import casadi as ca
import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.validity import MotionValidator, RodKernel


class TipJacobians:
    """Tips (S, 3) mm and tip Jacobians (S, 3, nx) of configurations (S, nx) for `crtraj.planning.ik.SafeIK`'s
    Newton steps. model: the planning model; validator: its motion validator (its kernel, if compiled);
    compiled: use the validator's tips where the kernel has them."""

    def __init__(self, model: Model, validator: MotionValidator, compiled: bool) -> None:
        self.model = model
        self.validator = validator
        self.compiled = compiled
        # without a compiled kernel: tip and Jacobian in one call, mapped per batch size (built on first use: a
        # rod model's graph takes milliseconds, and a kernel never needs it)
        self._single: ca.Function | None = None
        self._mapped: dict[int, ca.Function] = {}

    def tips(self, v: MotionValidator, X: np.ndarray) -> np.ndarray:
        """Tip positions (N, 3) mm of X (N, nx): with `compiled`, the validator's (its kernel's), else the model's."""
        return v.tip_position(X) if self.compiled else self.model.tip_position(X)

    def push_jacobian(self, X: np.ndarray) -> np.ndarray:
        """Tip Jacobians (S, 3, nx) the push-out moves along: a rod kernel's PCC ones (a direction only: the
        projection after the step puts the rod's tip back on target; a fortieth of the rod's cost), else the
        model's (`tip_jacobian`)."""
        kernel = self.validator.state.kernel
        if isinstance(kernel, RodKernel):
            return kernel.pcc_tip_jacobian(X)
        return self.tip_jacobian(X)[1]

    def tip_jacobian(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tips (S, 3) mm and tip Jacobians (S, 3, nx) of configurations X (S, nx): the validator's compiled
        kernel when it has one, else one mapped CasADi call."""
        kernel = self.validator.state.kernel
        if kernel is not None:
            return kernel.tip_jacobian(X)
        S, nx = X.shape[0], self.model.robot.nx
        f = self._mapped.get(S)
        if f is None:
            if self._single is None:
                x = ca.SX.sym("x", nx)
                self._single = ca.Function("tip_jac", [x], [self.model.tip(x), self.model.jac_tip(x)])
            f = self._single.map(S, "serial")
            self._mapped[S] = f
        P, J = f(X.T)
        # contiguous like the kernel's arrays: numpy's batched products round differently on strided views
        J = np.ascontiguousarray(np.asarray(J).reshape(3, S, nx).transpose(1, 0, 2))
        return np.ascontiguousarray(np.asarray(P).T), J
