"""From a PCC configuration to tendon tensions, and the backbone points of both models to compare.

A PCC configuration gives each segment its effective bending vector ``u_bar_k = theta_k (cos phi_k,
sin phi_k)`` (rad), i.e. a constant curvature ``|u_bar_k| / L_k`` toward phi_k. A rod without gravity
or tip load holds that curvature when its bending moment there is ``EI u_bar_k / L_k`` (turned into
the body frame's curvature axis). Every tendon passing through a segment contributes to its moment,
so the tendons of segment k carry the difference between segment k's moment and segment k+1's; three
tendons 120 degrees apart share it in the least-squares way, shifted so that the smallest tension is
the pretension (tendons cannot push). The shift adds equal tensions, which add no moment.
"""

from __future__ import annotations

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot


def segment_moments(robot: Robot, mech: Mechanics, u_bar: np.ndarray) -> np.ndarray:
    """Body-frame bending moments (N mm), (..., n_segments, 2), that hold the effective bending vectors
    u_bar (..., n_segments, 2) rad as constant curvatures: bending toward +x is a moment about +y."""
    ub = np.asarray(u_bar, dtype=float)
    ub = ub.reshape(*ub.shape[:-2], robot.n_segments, 2) if ub.ndim >= 2 else ub.reshape(robot.n_segments, 2)
    lengths = np.array([s.length for s in robot.segments])
    kappa = np.stack([-ub[..., 1], ub[..., 0]], axis=-1) / lengths[:, None]
    return mech.bending_stiffness * kappa


def tensions_for_bending(robot: Robot, mech: Mechanics, u_bar: np.ndarray, pretension: float = 0.0) -> np.ndarray:
    """Tendon tensions (N), (3 n_segments,) in cable order, that bend a weightless rod to u_bar (rad,
    (n_segments, 2)); the smallest tension of each segment equals `pretension` (N). Many at once: u_bar
    (N, n_segments, 2) gives (N, 3 n_segments)."""
    moments = segment_moments(robot, mech, u_bar)
    r = robot.cable_radius
    out = np.empty((*moments.shape[:-2], 3 * robot.n_segments))
    for k in range(robot.n_segments):
        own = moments[..., k, :] - (moments[..., k + 1, :] if k + 1 < robot.n_segments else 0.0)
        a = robot.cable_angles(k)
        # tendon i at angle a_i adds the body moment tau_i r (-sin a_i, cos a_i); the three unit
        # directions d_i satisfy sum d_i d_i^T = 3/2 I, so tau_i = 2/(3 r) d_i . own is the least-norm share
        d = np.stack([-np.sin(a), np.cos(a)], axis=1)
        share = (2.0 / (3.0 * r)) * own @ d.T
        out[..., 3 * k : 3 * k + 3] = share - share.min(axis=-1, keepdims=True) + pretension
    return out


def pcc_nodes(model: Model, x: np.ndarray, steps: int) -> np.ndarray:
    """PCC backbone points (mm, base frame with the base at the origin) at the rod's integration
    nodes: ``steps`` equal arcs per segment, (n_segments * steps + 1, 3), for configuration x."""
    f = model.segment_point_function()
    fracs = np.linspace(0.0, 1.0, steps + 1)
    per_frac = np.stack([np.asarray(f(x, fr)).T for fr in fracs])  # (steps + 1, n_segments, 3)
    rows = [per_frac[0, 0]]
    for k in range(model.robot.n_segments):
        rows.extend(per_frac[1:, k])
    pts = np.array(rows)
    pts[:, 2] -= float(x[-1])  # the rod's base sits at the origin
    return pts
