"""The calibration's forward kinematics and residuals as CasADi functions of the parameters (mm, rad)."""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from crtraj.model.calibration._layout import Hardware, Layout
from crtraj.model.calibration._sites import MarkerSite
from crtraj.model.kinematics import _arc, _f1_f2, _skew
from crtraj.model.robot import CABLE_SPACING, Robot


def _bending_inverse(robot: Robot, k: int) -> np.ndarray:
    """B1_k (2 x 3): u_k = B1_k d_k / r, the pseudo-inverse of eq. 4 at unit cable radius."""
    a = robot.segments[k].cable_phase + CABLE_SPACING * np.arange(3)
    A1 = np.stack([-np.cos(a), np.sin(a)], axis=1)
    return np.linalg.pinv(A1)


def _markers_expr(robot: Robot, hw: Hardware, sites: Sequence[MarkerSite], theta: ca.SX, v: ca.SX) -> ca.SX:
    """Robot-frame positions (3 x M) of the marker sites for parameters theta and actuator values v."""
    n = robot.n_segments
    L = theta[0:n]
    c = theta[n]
    r = theta[n + 1]
    a0 = theta[n + 2 : n + 2 + 3 * n]
    z0 = theta[n + 2 + 3 * n]
    d = ca.DM(hw.sign[:-1] * hw.spool_radius) * (v[: 3 * n] - a0)
    z = float(hw.sign[-1]) * (v[3 * n] - z0)
    u = [ca.DM(_bending_inverse(robot, k)) @ d[3 * k : 3 * k + 3] / r for k in range(n)]
    ub: list[ca.SX] = [None] * n  # type: ignore[list-item]
    acc = ca.SX.zeros(2)
    for k in reversed(range(n)):  # u_bar_k = u_k + c u_bar_{k+1}
        acc = u[k] + c * acc if k < n - 1 else u[k]
        ub[k] = acc
    R = ca.SX.eye(3)
    o = ca.vertcat(0, 0, z)
    cols: dict[str, ca.SX] = {}
    for k in range(n):
        for s in sites:
            if s.segment == k:
                frac = 1.0 if s.arc is None else s.arc / L[k]
                p, _ = _arc(ub[k], L[k], frac)
                cols[s.name] = o + R @ p
        p, Rk = _arc(ub[k], L[k], 1.0)
        o = o + R @ p
        R = R @ Rk
    return ca.horzcat(*[cols[s.name] for s in sites])


def _rotation_expr(w: ca.SX) -> ca.SX:
    f1, f2 = _f1_f2(ca.sumsqr(w))
    W = _skew([w[0], w[1], w[2]])
    return ca.SX.eye(3) + f2 * W + f1 * (W @ W)


class CalibrationModel:
    """The residual of one sample as CasADi functions of theta (built once per robot and marker set).

    ``markers(theta, v) -> P`` (3 x M, robot frame, mm); ``residual(theta, v, m) -> e`` (3M, mm) with m
    the stacked capture-frame positions; ``jacobian(theta, v, m) -> de/dtheta`` (3M x n).
    """

    def __init__(self, robot: Robot, hw: Hardware, sites: Sequence[MarkerSite], layout: Layout) -> None:
        self.robot, self.hw, self.sites, self.layout = robot, hw, tuple(sites), layout
        self.M = len(self.sites)
        th = ca.SX.sym("theta", layout.n)
        v = ca.SX.sym("v", 3 * robot.n_segments + 1)
        m = ca.SX.sym("m", 3 * self.M)
        P = _markers_expr(robot, hw, self.sites, th, v)
        nb = layout.n - 6
        Rw = _rotation_expr(th[nb : nb + 3])
        t = th[nb + 3 : nb + 6]
        e = ca.vertcat(*[Rw @ m[3 * j : 3 * j + 3] + t - P[:, j] for j in range(self.M)])
        self.markers = ca.Function("markers", [th, v], [P], {"cse": True})
        self.residual = ca.Function("residual", [th, v, m], [e], {"cse": True})
        self.jacobian = ca.Function("jacobian", [th, v, m], [ca.jacobian(e, th)], {"cse": True})
        mask = ca.SX.sym("mask", self.M)
        delta2 = ca.SX.sym("delta2")
        loss = 0
        for j in range(self.M):
            s = ca.sumsqr(e[3 * j : 3 * j + 3])
            loss += mask[j] * 2 * delta2 * (ca.sqrt(1 + s / delta2) - 1)
        self.loss = ca.Function("loss", [th, v, m, mask, delta2], [loss], {"cse": True})

    def predict(self, theta: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Robot-frame marker positions (N, M, 3) mm for actuator values (N, nq)."""
        N = values.shape[0]
        out = np.asarray(self.markers.map(N)(theta, values.T))  # 3 x (M N)
        return out.reshape(3, N, self.M).transpose(1, 2, 0)

    def residuals(self, theta: np.ndarray, values: np.ndarray, m: np.ndarray) -> np.ndarray:
        """Residuals (N, M, 3) mm; m (N, M, 3) capture-frame positions (NaN entries give NaN)."""
        N = values.shape[0]
        mm = np.nan_to_num(m).reshape(N, 3 * self.M)
        e = np.asarray(self.residual.map(N)(theta, values.T, mm.T)).T.reshape(N, self.M, 3)
        e[np.isnan(m).any(axis=2)] = np.nan
        return e

    def jacobians(self, theta: np.ndarray, values: np.ndarray, m: np.ndarray) -> np.ndarray:
        """d residual / d theta (N, M, 3, n)."""
        N = values.shape[0]
        mm = np.nan_to_num(m).reshape(N, 3 * self.M)
        J = np.asarray(self.jacobian.map(N)(theta, values.T, mm.T))  # (3M) x (n N)
        return J.reshape(3 * self.M, N, self.layout.n).transpose(1, 0, 2).reshape(N, self.M, 3, self.layout.n)
