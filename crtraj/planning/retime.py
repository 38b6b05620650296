"""Time-optimal retiming of a verified piecewise-straight path under actuator and body-speed limits.

What the planners verify is a polyline in configuration space: waypoints joined by straight
motions, each certified by `MotionValidator` (the c-space planner's smoothing samples its
B-spline into such waypoints and verifies the polyline, not the spline). Retiming keeps exactly
that geometry, so:

- Consecutive straight motions that are collinear (every inner waypoint within `COLLINEAR` of the
  chord, progressing forward) form one straight motion.
- At every other waypoint the direction of motion jumps: with finite acceleration the velocity must
  vanish there. Each straight motion is therefore timed rest to rest, and on a straight motion
  ``x = x_a + u d`` (u in [0, 1]) every limit is a limit on the scalar u:
  ``|u'| <= V = min(min_i vmax_i / |J_i d|, max_speed / B(d))`` and
  ``|u''| <= A = min_i amax_i / |J_i d|`` (J: `RateLimits`, B: the body-motion bound of
  `crtraj.planning.metric`). The time-optimal law is bang-coast-bang in closed form:
  ``T = 1/V + V/A`` when ``V^2 / A <= 1``, else ``T = 2 / sqrt(A)``.
- Each duration is rounded up to a whole number of stream periods (the law is slowed uniformly,
  which only lowers speed and acceleration), so every waypoint falls on a set-point instant: the
  set-points sampled every period from t0 all lie on the path, and the straight lines between
  consecutive set-points lie on one straight motion each, i.e. on the verified geometry.

The actuator values of the law are C1 in time with |second derivative| <= amax, so their finite
differences at any sampling period stay within the limits (a second difference is an average of
the second derivative). Units: s; configurations as in `Robot` (rad, mm).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.metric import BodyMetric
from crtraj.planning.rate_limits import RateLimits

# Largest distance (configuration units) of a merged inner waypoint from its straight motion.
COLLINEAR = 1e-10
# Default stream period (s): the streamer sends set-points at 100 Hz.
STREAM_PERIOD = 0.01
# Most set-points a retimed path may hold (as `crtraj.hardware.setpoints.MAX_SETPOINTS`).
MAX_SAMPLES = 2_000_000


@dataclass(frozen=True)
class RetimedPath:
    """A rest-to-rest bang-coast-bang law along each straight motion of a polyline.

    vertices: (K, nx) the corners kept (a subset of the verified waypoints). steps: (K-1,) integer
    duration of each motion in stream periods. peak (1/s) and accel (1/s^2): the law's largest
    du/dt and |d2u/dt2| per motion. t0 (s), period (s).
    """

    vertices: np.ndarray
    steps: np.ndarray
    peak: np.ndarray
    accel: np.ndarray
    t0: float
    period: float

    @property
    def times(self) -> np.ndarray:
        """Times (s) at the vertices: t0 + whole numbers of periods."""
        return self.t0 + self.period * np.concatenate([[0], np.cumsum(self.steps)]).astype(float)

    @property
    def duration(self) -> float:
        """Duration (s) of the whole motion."""
        return float(self.period * int(np.sum(self.steps)))

    def at(self, t: np.ndarray) -> np.ndarray:
        """Configurations (N, nx) at times t (s); held at the ends."""
        X = self.vertices
        t = np.asarray(t, dtype=float)
        if len(X) == 1:
            return np.repeat(X, len(t), axis=0)
        T = self.times
        k = np.clip(np.searchsorted(T, t, side="right") - 1, 0, len(self.steps) - 1)
        dur = self.period * self.steps[k]
        tau = np.clip(t - T[k], 0.0, dur)
        a, v = self.accel[k], self.peak[k]
        ta = v / a  # end of the acceleration phase (s); the braking phase is its mirror image
        u = np.where(
            tau <= ta,
            0.5 * a * tau**2,
            np.where(tau <= dur - ta, 0.5 * a * ta**2 + v * (tau - ta), 1.0 - 0.5 * a * (dur - tau) ** 2),
        )
        u = np.clip(u, 0.0, 1.0)
        return X[k] + u[:, None] * (X[k + 1] - X[k])

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """Set-points every period from t0 to the end: (stamps (M,) s, configurations (M, nx)).

        The stamps are ``t0 + period * k`` exactly as the streamer computes them, so a streamer that
        interpolates these samples at the same period sends exactly them.
        """
        n = int(np.sum(self.steps))
        stamps = self.t0 + self.period * np.arange(n + 1)
        return stamps, self.at(stamps)


def keep_corners(X: np.ndarray, tol: float = COLLINEAR) -> np.ndarray:
    """Indices of the waypoints that are corners (plus both ends): runs of collinear,
    forward-progressing straight motions are merged; zero-length motions are dropped."""
    X = np.asarray(X, dtype=float)
    keep = [0]
    i, K = 0, len(X)
    while i < K - 1:
        j = i + 1
        while j + 1 < K and _on_chord(X[i], X[j + 1], X[i + 1 : j + 1], tol):
            j += 1
        if np.max(np.abs(X[j] - X[keep[-1]])) > 0.0:
            keep.append(j)
        i = j
    if keep[-1] != K - 1:
        keep[-1] = K - 1  # the end itself (equal to the last kept corner up to 0)
    return np.asarray(keep)


def _on_chord(a: np.ndarray, b: np.ndarray, inner: np.ndarray, tol: float) -> bool:
    """All `inner` points within tol of the chord a -> b, in order along it."""
    d = b - a
    dd = float(d @ d)
    if dd == 0.0:
        return False
    u = (inner - a) @ d / dd
    if np.any(np.diff(np.concatenate([[0.0], u, [1.0]])) < 0.0):
        return False
    return bool(np.max(np.linalg.norm(a + u[:, None] * d - inner, axis=1)) <= tol)


def motion_limits(D: np.ndarray, limits: RateLimits, metric: BodyMetric) -> tuple[np.ndarray, np.ndarray]:
    """(V, A): largest du/dt (1/s) and |d2u/dt2| (1/s^2) along straight motions x_a + u D[k]."""
    JD = np.abs(np.asarray(D, dtype=float) @ limits.jacobian.T)
    with np.errstate(divide="ignore"):
        V = np.min(limits.vmax / JD, axis=1)
        V = np.minimum(V, metric.max_speed / metric.motion_bound(D))
        A = np.min(limits.amax / JD, axis=1)
    return V, A


def min_durations(V: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Shortest rest-to-rest time (s) over u in [0, 1] with |u'| <= V, |u''| <= A (bang-coast-bang)."""
    return np.where(V * V / A <= 1.0, 1.0 / V + V / A, 2.0 / np.sqrt(A))


def retime(
    X: np.ndarray,
    limits: RateLimits,
    metric: BodyMetric,
    *,
    t0: float = 0.0,
    period: float = STREAM_PERIOD,
    at_least: np.ndarray | None = None,
) -> RetimedPath:
    """The time-optimal limit-respecting law along the polyline X (K, nx) (see the module docstring).

    limits: the usable actuator limits (already `scaled` by the reserve). metric: body-speed
    limit. t0 (s): start time. period (s): the stream period the waypoint times are rounded to.
    at_least (K-1,) s: lower bounds on each straight motion's duration (e.g. a verified slower
    timing; a zero-length motion with a positive bound is a wait), None for none.
    """
    X = np.atleast_2d(np.asarray(X, dtype=float))
    if not (math.isfinite(period) and period > 0):
        raise InputError(f"retime: period must be > 0 s, got {period}")
    if not np.all(np.isfinite(X)) or len(X) < 1:
        raise InputError("retime: the path must hold at least one finite configuration")
    if at_least is None:
        idx = keep_corners(X)
        lo = np.zeros(len(idx) - 1)
    else:
        # with per-motion bounds nothing is merged: each verified motion keeps its own duration floor
        lo = np.asarray(at_least, dtype=float)
        if lo.shape != (len(X) - 1,) or not np.all(np.isfinite(lo)):
            raise InputError(f"retime: at_least must be {len(X) - 1} finite durations (s)")
        idx = np.arange(len(X))
    P = X[idx]
    D = np.diff(P, axis=0)
    moving = np.any(D != 0.0, axis=1)
    V, A = motion_limits(D[moving], limits, metric)
    T = np.zeros(len(D))
    T[moving] = min_durations(V, A)
    T = np.maximum(T, lo)
    steps = np.ceil(T / period - 1e-9).astype(np.int64)
    if int(steps.sum()) > MAX_SAMPLES:
        raise InputError(f"retime: {steps.sum() * period:g} s is more than {MAX_SAMPLES} set-points")
    keep = steps > 0
    steps = np.where(moving & ~keep, 1, steps)  # a motion always takes at least one period
    keep = steps > 0
    P = np.concatenate([P[:1], P[1:][keep]])
    dur = period * steps[keep]
    # the minimal law, slowed uniformly by s = dur / T (speed / s, acceleration / s^2)
    peak, accel = (
        np.full(len(dur), 2.0 / np.maximum(dur, 1e-300)),
        np.full(len(dur), 4.0 / np.maximum(dur, 1e-300) ** 2),
    )
    mv = moving[keep]
    Vk, Ak = np.full(len(D), np.nan), np.full(len(D), np.nan)
    Vk[moving], Ak[moving] = V, A
    Vk, Ak = Vk[keep][mv], Ak[keep][mv]
    Tmin = min_durations(Vk, Ak)
    s = dur[mv] / Tmin
    vp = np.where(Vk * Vk / Ak <= 1.0, Vk, np.sqrt(Ak))
    peak[mv], accel[mv] = vp / s, Ak / s**2
    return RetimedPath(P, steps[keep], peak, accel, float(t0), float(period))


def toppra_durations(X: np.ndarray, limits: RateLimits, metric: BodyMetric, gridpoints: int = 50) -> np.ndarray:
    """The same rest-to-rest problem solved by toppra (the reference TOPP-RA library), per straight
    motion between the corners of X: durations (s). For comparison with `min_durations` (benchmarks)."""
    import toppra as ta  # the reference library: needed only by this cross-check (benchmarks, tests)

    P = np.asarray(X, dtype=float)[keep_corners(X)]
    out = []
    for xa, xb in itertools.pairwise(P):
        d = xb - xa
        # the path in actuator space plus one coordinate for the body motion B(d) u, linear in u
        ends = np.stack([np.concatenate([limits.jacobian @ x, [0.0]]) for x in (xa, xb)])
        ends[1, -1] = float(metric.motion_bound(d))
        path = ta.SplineInterpolator([0.0, 1.0], ends, bc_type="natural")
        vlim = np.concatenate([limits.vmax, [metric.max_speed]])
        alim = np.concatenate([limits.amax, [1e12]])  # no limit on body acceleration
        cons = [
            ta.constraint.JointVelocityConstraint(np.stack([-vlim, vlim], axis=1)),
            ta.constraint.JointAccelerationConstraint(np.stack([-alim, alim], axis=1)),
        ]
        algo = ta.algorithm.TOPPRA(cons, path, gridpoints=np.linspace(0.0, 1.0, gridpoints + 1))
        traj = algo.compute_trajectory(0.0, 0.0)
        if traj is None:
            raise RuntimeError(f"toppra failed on a straight motion of length {ends[1, -1]:g} mm")
        out.append(float(traj.duration))
    return np.asarray(out)
