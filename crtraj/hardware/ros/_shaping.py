"""Shape each step's JointTrajectory so that what joint_trajectory_controller executes is what was verified.

The controller replaces its trajectory at once when a message arrives and splines from its state
then (the point before the trajectory) to the message's first point (`crtraj.hardware.ros._jtc`).
The bridge's committed curve (everything it sent, as the controller executes it) is piecewise cubic:
every point carries positions and velocities, none accelerations. A cubic is fixed by positions and
velocities at both ends, so a message made of the committed curve's own knots reproduces the committed
curve exactly. Its first point is the committed knot at or before the send time `now`: it is already
due when the message arrives, so the controller samples the message's own segments and never uses the
point before the trajectory (its state at arrival, which a real controller reads one update late: a
lagged, slightly different point). Whenever the message arrives between `now` and the step's start t,
and whatever the controller's state lag, the robot stays on the committed curve: arrival latency and a
step computed late by up to ``ros.lead - ros.arrival_margin`` change nothing in the executed curve.

Each step's message (`step_message`) is therefore: the committed knots from the last one at or before
`now` to the step's start t, the committed state at t, the step's points (positions of the servo model, velocities
of the cubic spline through them: `smooth_velocities`), and a stop tail: one segment at constant
deceleration (a fraction `TAIL_FRACTION` of each actuator's acceleration limit) ending at rest. So the
last point has zero velocity (the controller's default refuses anything else), and when the next
message never comes the robot stops on a curve that was verified with this one.
Units: loop time in s, actuator values in rad / mm.
"""

from __future__ import annotations

import numpy as np

from crtraj.hardware.ros._jtc import JtcMessage, Spline

# deceleration of the stop tail, as a fraction of each actuator's acceleration limit
TAIL_FRACTION = 0.8


def stop_tail(
    position: np.ndarray, velocity: np.ndarray, amax: np.ndarray, min_time: float
) -> tuple[float, np.ndarray]:
    """(duration s, rest position) of the stop from `position` moving at `velocity` at constant deceleration
    of at most TAIL_FRACTION * amax per actuator, lasting at least `min_time` s. The cubic Hermite segment
    from (position, velocity) to (rest, 0) over that duration is exactly this parabola."""
    need = np.abs(velocity) / (TAIL_FRACTION * np.asarray(amax, dtype=float))
    duration = max(float(min_time), float(np.max(need)) if need.size else 0.0)
    return duration, position + 0.5 * velocity * duration


def step_message(
    committed: Spline,
    now: float,
    t: float,
    points: tuple[np.ndarray, np.ndarray, np.ndarray],
    amax: np.ndarray,
    names: tuple[str, ...],
    epoch: float = 0.0,
) -> JtcMessage:
    """The message (stamp and times in loop time s) for the step starting at t, sent at loop time `now`:
    the committed knots from the last one at or before `now` to t (exclusive), the committed state at t, the
    step's points (offsets (N,) s after t, values and velocities (N, n)), and the stop tail after the last
    point. epoch: the controller's clock reads epoch + loop time (see `_due`)."""
    offsets, values, _ = points
    keep = (committed.times >= _due(committed, now, epoch)) & (committed.times < t - 1e-9)
    p_t, v_t = committed.state(t)
    spacing = float(offsets[0])
    vel = smooth_velocities(p_t, v_t, values, spacing)
    duration, rest = stop_tail(values[-1], vel[-1], amax, spacing)
    idx = np.flatnonzero(keep)
    times = np.concatenate([committed.times[keep], [t], t + offsets, [t + offsets[-1] + duration]])
    P = np.vstack([committed.positions[keep], p_t[None], values, rest[None]])
    V = np.vstack([np.array([_velocity(committed, i) for i in idx]).reshape(-1, P.shape[1]), v_t[None], vel])
    V = np.vstack([V, np.zeros((1, P.shape[1]))])
    return JtcMessage.from_arrays(names, times[0], times - times[0], P, V)


def smooth_velocities(p0: np.ndarray, v0: np.ndarray, values: np.ndarray, h: float) -> np.ndarray:
    """Velocities (N, n) at points `values` (N, n), `h` s apart after (p0, v0), that make the cubic segments
    through them twice continuously differentiable (the cubic spline: the least squared acceleration through
    these positions), clamped to v0 at the start and with zero acceleration at the last point."""
    P = np.vstack([p0[None], values])
    N = len(values)
    M = np.zeros((N, N))
    rhs = np.empty((N, P.shape[1]))
    for k in range(1, N):  # acceleration continuous at point k: v[k-1] + 4 v[k] + v[k+1] = 3 (p[k+1] - p[k-1]) / h
        M[k - 1, k - 1] = 4.0
        if k >= 2:
            M[k - 1, k - 2] = 1.0
        M[k - 1, k] = 1.0
        rhs[k - 1] = 3.0 * (P[k + 1] - P[k - 1]) / h - (v0 if k == 1 else 0.0)
    # no acceleration at the last point: v[N-1] + 2 v[N] = 3 (p[N] - p[N-1]) / h
    if N >= 2:
        M[N - 1, N - 2] = 1.0
    M[N - 1, N - 1] = 2.0
    rhs[N - 1] = 3.0 * (P[N] - P[N - 1]) / h - (v0 if N == 1 else 0.0)
    return np.linalg.solve(M, rhs)


def hold_message(
    committed: Spline, now: float, spacing: float, names: tuple[str, ...], epoch: float = 0.0
) -> JtcMessage:
    """What to send to keep the robot on its committed curve to rest (its knots from the last one at or before
    `now`), or, when it is at rest already, one point at rest there `spacing` s from now."""
    keep = (committed.times >= _due(committed, now, epoch)) & np.any(committed.times > now)
    if np.any(keep):
        idx = np.flatnonzero(keep)
        V = np.array([_velocity(committed, i) for i in idx])
        T = committed.times[keep]
        return JtcMessage.from_arrays(names, T[0], T - T[0], committed.positions[keep], V)
    rest = committed.positions[-1][None]
    return JtcMessage.from_arrays(names, now + spacing, np.zeros(1), rest, np.zeros_like(rest))


def _due(curve: Spline, now: float, epoch: float = 0.0) -> float:
    """Time of the curve's last knot at or before `now` (its first knot when there is none): the first point of
    a message sent at `now`, already due when it arrives. A knot at controller clock time 0 (epoch + time; ROS
    sim time starts there) would make the message's stamp 0, which the controller reads as "now": the next knot
    is taken instead (the point before the trajectory is then used, as `jtc.executed` models)."""
    k = max(int(np.searchsorted(curve.times, now, side="right")) - 1, 0)
    if curve.times[k] + epoch == 0.0 and k + 1 < len(curve.times):
        k += 1
    return float(curve.times[k])


def _velocity(curve: Spline, k: int) -> np.ndarray:
    v = curve.velocities[k]
    return np.zeros(curve.positions.shape[1]) if v is None else np.asarray(v, dtype=float)
