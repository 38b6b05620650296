"""The limits a tracking set-point keeps: the actuation limits (cable strokes, theta_max, z stroke) and the
actuators' speed and acceleration limits (`RateLimits`). Units: mm, rad, s."""

from __future__ import annotations

import math

import numpy as np

from crtraj.model.rate_limits import RateLimits
from crtraj.model.robot import Robot


class ActuationLimits:
    """The actuation limits on a set-point x: linear |A_cab x| <= stroke (G x <= h), the z box, and
    |C_k u| <= theta_max per segment.

    robot: the robot; J_q: its cable Jacobian dq/dx (nq, nx), constant.
    """

    def __init__(self, robot: Robot, J_q: np.ndarray) -> None:
        n = robot.n_segments
        A_cab = J_q[: 3 * n]
        strokes = np.repeat([robot.cable_stroke(k) for k in range(n)], 3)
        self.G = np.vstack([A_cab, -A_cab])
        self.h = np.concatenate([strokes, strokes])
        C = robot.coupling_matrix()
        self.C = [np.hstack([C[2 * k : 2 * k + 2], np.zeros((2, 1))]) for k in range(n)]
        self.tmax2 = np.array([s.theta_max**2 for s in robot.segments])
        self.z_range = robot.z_range

    def shrink(self, xc: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, float]:
        """Shrink the increment so the set-point stays within (or gets no further outside) the limits.

        z is clipped on its own (independent stage); the bending part is scaled
        by one factor so its direction is kept. The feasible set is convex, so
        a line search along v is exact.
        """
        v = v.copy()
        lo, hi = self.z_range
        # Python floats: the same IEEE arithmetic as numpy scalars, without their overhead
        z0 = float(xc[-1])
        z1 = z0 + float(v[-1])
        z_new = min(max(z1, min(lo, z0)), max(hi, z0))
        scale_z = 1.0
        if z_new != z1:
            scale_z = (z_new - z0) / v[-1] if v[-1] != 0.0 else 1.0
            v[-1] = z_new - z0
        vb = v.copy()
        vb[-1] = 0.0
        alpha = 1.0
        g0 = self.G @ xc - self.h
        gv = self.G @ vb
        grow = gv > 0.0
        if np.count_nonzero(grow):  # the fastest "any" on a handful of flags
            # rows already violated (g0 > 0) may not grow at all
            g0g = g0[grow]
            room = np.where(g0g <= 0.0, -g0g, 0.0)
            alpha = min(alpha, float((room / gv[grow]).min()))
        for Ck, t2 in zip(self.C, self.tmax2, strict=True):
            a_ = Ck @ vb
            b_ = Ck @ xc
            a = float(a_ @ a_)
            if a == 0.0:
                continue
            b = float(a_ @ b_)
            c = float(b_ @ b_) - t2
            # inside: up to the root of |C_k (x + alpha v)|^2 = theta_max^2;
            # outside: only moves that do not increase |C_k u| (a alpha^2 + 2 b alpha <= 0)
            reach = (-b + math.sqrt(b * b - a * c)) / a if c <= 0.0 else max(0.0, -2.0 * b / a)
            alpha = min(alpha, reach)
        alpha = max(alpha, 0.0)
        if alpha < 1.0:
            v[:-1] *= alpha
        return v, min(alpha, scale_z)


def accelerate(rl: RateLimits, v: np.ndarray, vp: np.ndarray, room: np.ndarray) -> tuple[np.ndarray, float]:
    """Move from the previous increment toward v only as far as the acceleration limits allow.

    vp: the previous increment (nx); room: amax h^2 per actuator (period h, s). Returns (increment, share of
    v - vp used) with |J (v_out - vp)| <= amax h^2 per actuator.
    """
    change = np.abs(rl.jacobian @ (v - vp))
    worst = float((change / room).max())
    if worst <= 1.0:
        return v, 1.0
    s = 1.0 / worst
    return vp + s * (v - vp), s


def braking(
    rl: RateLimits, v: np.ndarray, remaining: np.ndarray, ff: np.ndarray, h: float, room: np.ndarray
) -> np.ndarray:
    """v scaled (direction kept) so no actuator closes on its target faster than it can still stop there.

    remaining: the set-point's configuration distance to its target; ff: the target's own motion over the
    period (feed-forward); room: amax h^2 per actuator (period h, s). An actuator |r| from its target may
    close on it at most sqrt(2 amax |r|) faster than the target moves (the braking curve); without this
    cap the LQR law, designed without acceleration limits, overshoots against them and rings
    (integrator-like windup).
    """
    step = rl.jacobian @ v
    r = rl.jacobian @ remaining
    toward = step * r > 0.0
    if not np.count_nonzero(toward):  # the fastest "any" on a handful of flags
        return v
    # every actuator's ratio elementwise, then one selection (the same numbers as selecting first)
    cap = np.abs(rl.jacobian @ ff) + np.sqrt(2.0 * rl.amax * np.abs(r)) * h + room
    worst = float((np.abs(step) / cap)[toward].max())
    return v / worst if worst > 1.0 else v
