"""The tracking controller's gain: an LQR design per control period (python-control, exact zero-order hold).

See the module docstring of `crtraj.control.tracking._controller` for the design model. Units: mm, rad, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crtraj.control.tracking._options import TrackingOptions
from crtraj.core.errors import InputError
from crtraj.core.lazy import lazy_module
from crtraj.model.robot import Robot

# python-control (LQR design) is imported when a controller is first designed: `crtraj plan` never is
control = lazy_module("control")


@dataclass(frozen=True)
class TrackingDesign:
    """The LQR design for one control period dt (s).

    State e = (x_ref - x, x_ref - x_cmd_prev) (2 nx), input v = set-point
    increment (nx), ``e[k+1] = A e[k] - B v[k]``, ``v = K e``. phi: servo decay
    per period per configuration coordinate (exp(-dt/tau)). S: Riccati solution.
    """

    dt: float
    phi: np.ndarray
    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    K: np.ndarray
    S: np.ndarray
    eigenvalues: np.ndarray

    @property
    def lead(self) -> np.ndarray:
        """phi / (1 - phi) per coordinate: periods a servo lags its set-point on a ramp."""
        return self.phi / (1.0 - self.phi)

    @property
    def closed_loop(self) -> np.ndarray:
        """A - B K, the error dynamics without saturation."""
        return self.A - self.B @ self.K

    def steps_to(self, error0: np.ndarray, tol: float) -> int:
        """Periods after which |e| <= tol for good, from e0 (unsaturated, constant reference).

        Uses |(A-BK)^k| <= cond(V) rho^k for A-BK = V D V^-1; if A-BK is not
        diagonalisable, the first k with |(A-BK)^j| |e0| <= tol for the next 2 nx
        periods too (then a numerical count, not a proof).
        """
        n0 = float(np.linalg.norm(error0))
        if n0 <= tol:
            return 0
        Acl = self.closed_loop
        lam, V = np.linalg.eig(Acl)
        rho = float(np.max(np.abs(lam)))
        kappa = float(np.linalg.cond(V))
        if rho > 0.0 and math.isfinite(kappa) and kappa < 1e12:
            return max(0, math.ceil(math.log(tol / (kappa * n0)) / math.log(rho)))
        P = np.eye(len(Acl))
        norms = []
        for _ in range(100_000):
            norms.append(np.linalg.norm(P, 2) * n0)
            P = Acl @ P
            m = 2 * self.K.shape[0]
            if len(norms) > m and max(norms[-m - 1 :]) <= tol:
                return len(norms) - m - 1
        raise InputError(f"tracking: error does not reach {tol:g} within 100000 periods")


def lqr_design(options: TrackingOptions, robot: Robot, tau_x: np.ndarray, dt: float) -> TrackingDesign:
    """The LQR design for period dt (s) of servos with lags tau_x (nx,) s per configuration coordinate
    (module docstring of `crtraj.control.tracking._controller`); `InputError` when it is not stable."""
    o, nx = options, robot.nx
    M = np.diag(1.0 / tau_x)
    servo = control.c2d(control.ss(-M, M, np.eye(nx), np.zeros((nx, nx))), dt, method="zoh")
    Phi, Gam = np.asarray(servo.A), np.asarray(servo.B)
    A = np.block([[Phi, Gam], [np.zeros((nx, nx)), np.eye(nx)]])
    B = np.vstack([Gam, np.eye(nx)])
    n = robot.n_segments
    err_scale = np.append(np.full(2 * n, o.bending_error_scale), o.z_error_scale)
    step_scale = np.append(np.full(2 * n, o.max_cable_rate * dt / robot.cable_radius), o.max_z_rate * dt)
    Q = np.diag(np.concatenate([1.0 / err_scale**2, np.zeros(nx)]))
    R = o.effort_weight * np.diag(1.0 / step_scale**2)
    sys_d = control.ss(A, B, np.eye(2 * nx), np.zeros((2 * nx, nx)), dt)
    K, S, E = control.dlqr(sys_d, Q, R)
    K, S, E = np.asarray(K), np.asarray(S), np.asarray(E)
    if not np.all(np.abs(E) < 1.0):
        raise InputError(f"tracking: LQR design for dt={dt:g} s is not stable (|eig| max {np.max(np.abs(E)):.6g})")
    return TrackingDesign(dt, np.diag(Phi).copy(), A, B, Q, R, K, S, E)
