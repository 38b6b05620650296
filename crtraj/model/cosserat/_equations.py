"""The Cosserat rod's equations as small CasADi pieces: the right-hand side, one RK4 step, the disc jumps.

The model and its notation are described in `crtraj.model.cosserat._statics`; this module holds the symbolic pieces
that both the interpreted shooting function (`crtraj.model.cosserat._statics.build_shooting`, everything inlined in
SX) and the compiled one (`crtraj.model.cosserat._compiled`, an MX graph calling the pieces) are chained from.
Units: mm, N, rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

_E3 = ca.DM([0.0, 0.0, 1.0])


def _hat(w: Any) -> Any:
    """Skew matrix of a 3-vector: hat(w) x = w x x."""
    return ca.vertcat(
        ca.horzcat(0, -w[2], w[1]),
        ca.horzcat(w[2], 0, -w[0]),
        ca.horzcat(-w[1], w[0], 0),
    )


class _Rod:
    """The symbolic pieces of one robot's rod: stiffness, tendon positions, ODE, jumps, residual."""

    def __init__(self, robot: Robot, mech: Mechanics) -> None:
        self.robot, self.mech = robot, mech
        self.kse = ca.DM(mech.shear_extension())
        self.kbt = ca.DM(mech.bending_torsion())
        rc = robot.cable_radius
        self.r = [
            ca.DM([rc * np.cos(a), rc * np.sin(a), 0.0]) for k in range(robot.n_segments) for a in robot.cable_angles(k)
        ]

    def tangent(self, v: Any, u: Any, i: int) -> Any:
        """Unit tangent of tendon i in the body frame (p_i' / |p_i'|, R^T applied)."""
        pb = v + ca.cross(u, self.r[i])
        return pb / ca.norm_2(pb)

    def rhs(self, y: Any, tau: Any, tendons: range, fe: Any) -> Any:
        """dy/ds of the state y = (p, vec R, v, u, tendon path lengths) with the tendons `tendons`
        passing through (the others' path lengths stay put)."""
        R = ca.reshape(y[3:12], 3, 3)
        v, u = y[12:15], y[15:18]
        A = ca.SX.zeros(3, 3)
        B = ca.SX.zeros(3, 3)
        G = ca.SX.zeros(3, 3)
        H = ca.SX.zeros(3, 3)
        a = ca.SX.zeros(3)
        b = ca.SX.zeros(3)
        rates = ca.SX.zeros(len(self.r))
        for i in tendons:
            ri = _hat(self.r[i])
            pb = v + ca.cross(u, self.r[i])
            nrm = ca.norm_2(pb)
            rates[i] = nrm  # |p_i'|: the tendon's path length grows at this rate
            t = pb / nrm
            # -tau hat(pb)^2 / |pb|^3 = (tau / |pb|) (I - t t^T): the tension's projector off the tangent
            Ai = (tau[i] / nrm) * (ca.SX.eye(3) - t @ t.T)
            Bi = ri @ Ai
            A += Ai
            B += Bi
            G -= Ai @ ri
            H -= Bi @ ri
            ai = Ai @ ca.cross(u, pb)
            a += ai
            b += ri @ ai
        strain = self.kse @ (v - _E3)
        c = -ca.cross(u, self.kbt @ u) - ca.cross(v, strain) - b
        d = -ca.cross(u, strain) - R.T @ fe - a
        lhs = ca.vertcat(ca.horzcat(self.kse + A, G), ca.horzcat(B, self.kbt + H))
        dvu = _solve_dominant(lhs, ca.vertcat(d, c))
        return ca.vertcat(R @ v, ca.reshape(R @ _hat(u), 9, 1), dvu, rates)

    def terminations(self, y: Any, tau: Any, tendons: range) -> tuple[Any, Any]:
        """Force (N) and moment (N mm, about the backbone) that ending tendons apply to the disc."""
        R = ca.reshape(y[3:12], 3, 3)
        v, u = y[12:15], y[15:18]
        F = ca.SX.zeros(3)
        M = ca.SX.zeros(3)
        for i in tendons:
            Fi = -tau[i] * (R @ self.tangent(v, u, i))
            F += Fi
            M += ca.cross(R @ self.r[i], Fi)
        return F, M

    def internal(self, y: Any) -> tuple[Any, Any]:
        """Internal force n (N) and moment m (N mm) of the backbone, base frame."""
        R = ca.reshape(y[3:12], 3, 3)
        return R @ self.kse @ (y[12:15] - _E3), R @ self.kbt @ y[15:18]

    def strains(self, R: Any, n: Any, m: Any) -> tuple[Any, Any]:
        """Body strains (v, u) of internal force n and moment m (base frame) at rotation R."""
        return ca.solve(self.kse, R.T @ n) + _E3, ca.solve(self.kbt, R.T @ m)


def _solve_dominant(M: Any, rhs: Any) -> Any:
    """x with M x = rhs by Gaussian elimination without pivoting.

    M = [K_se + A, G; B, K_bt + H] is strongly diagonally dominant for any tension a backbone can bear
    (the tendon terms scale with tension, the diagonal with EA, GA, EI), so no pivoting is needed; this
    needs a few times fewer symbolic operations than a QR solve, which the Jacobian multiplies.
    """
    n = M.shape[0]
    a = [[M[i, j] for j in range(n)] for i in range(n)]
    b = [rhs[i] for i in range(n)]
    for k in range(n):
        for i in range(k + 1, n):
            f = a[i][k] / a[k][k]
            for j in range(k + 1, n):
                a[i][j] = a[i][j] - f * a[k][j]
            b[i] = b[i] - f * b[k]
    x: list[Any] = [None] * n
    for i in reversed(range(n)):
        acc = b[i]
        for j in range(i + 1, n):
            acc = acc - a[i][j] * x[j]
        x[i] = acc / a[i][i]
    return ca.vertcat(*x)


def _rk4(f: Any, y: Any, h: float) -> Any:
    """One classical Runge-Kutta step of dy/ds = f(y)."""
    k1 = f(y)
    k2 = f(y + 0.5 * h * k1)
    k3 = f(y + 0.5 * h * k2)
    k4 = f(y + h * k3)
    return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


@dataclass(frozen=True)
class RodPieces:
    """The rod's shooting as small CasADi Functions of the state y = (p, vec R, v, u, tendon paths) and
    the parameters p (see `build_shooting`): `init` w -> y(0); `steps[k]` one RK4 step of segment k,
    (y, p) -> (y after the step, the angle (rad) the rod turns through in it); `jumps[k]` the disc at
    the end of segment k < last, (y, p) -> y; `tip` (y, p) -> r, the tip residual. Chaining them gives
    the shooting function; calling them with SX inlines them, with MX keeps the graph small."""

    init: ca.Function
    steps: tuple[ca.Function, ...]
    jumps: tuple[ca.Function, ...]
    tip: ca.Function
    n_steps: int


def rod_pieces(robot: Robot, mech: Mechanics) -> RodPieces:
    """The `RodPieces` of one robot and its mechanics (built once; SX inside)."""
    rod = _Rod(robot, mech)
    n_seg, nt = robot.n_segments, 3 * robot.n_segments
    y = ca.SX.sym("y", 18 + nt)
    p = ca.SX.sym("p", nt + 9)
    tau, fe, f_tip, m_tip = p[:nt], p[nt : nt + 3], p[nt + 3 : nt + 6], p[nt + 6 : nt + 9]
    w = ca.SX.sym("w", 6)
    v0, u0 = rod.strains(ca.SX.eye(3), w[:3], w[3:])
    y0 = ca.vertcat(ca.SX.zeros(3), ca.reshape(ca.SX.eye(3), 9, 1), v0, u0, ca.SX.zeros(nt))
    steps, jumps = [], []
    for k, seg in enumerate(robot.segments):
        f = ca.Function("rod_rhs", [y, p], [rod.rhs(y, tau, range(3 * k, nt), fe)])
        h = seg.length / mech.steps
        y_next = _rk4(lambda z, f=f: f(z, p), y, h)
        steps.append(ca.Function(f"rod_step{k}", [y, p], [y_next, h * ca.norm_2(y[15:18])]))
        F, M = rod.terminations(y, tau, range(3 * k, 3 * k + 3))
        n, m = rod.internal(y)
        if k < n_seg - 1:  # the disc passes the internal wrench on, less what its tendons take
            v, u = rod.strains(ca.reshape(y[3:12], 3, 3), n - F, m - M)
            jumps.append(ca.Function(f"rod_jump{k}", [y, p], [ca.vertcat(y[:12], v, u, y[18:])]))
        else:
            res = ca.vertcat(n - F - f_tip, (m - M - m_tip) / robot.total_length)
    tip = ca.Function("rod_tip", [y, p], [res])
    return RodPieces(ca.Function("rod_init", [w], [y0]), tuple(steps), tuple(jumps), tip, mech.steps)


def march(pieces: RodPieces, w: Any, p: Any) -> tuple[Any, Any, Any, Any]:
    """Integrate from the base wrench w to the tip: (residual r, points 3 x (n_segments steps + 1),
    tip state y, largest turn per step); symbolic in whatever type w and p are (SX inlines, MX calls)."""
    y = pieces.init(w)
    cols, turns = [y[:3]], []
    for k, step in enumerate(pieces.steps):
        for _ in range(pieces.n_steps):
            y, turn = step(y, p)
            turns.append(turn)
            cols.append(y[:3])
        if k < len(pieces.jumps):
            y = pieces.jumps[k](y, p)
    return pieces.tip(y, p), ca.horzcat(*cols), y, ca.mmax(ca.vertcat(*turns))
