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
the second derivative).

Stopping at every corner is slow where the path is a finely sampled smooth curve (the c-space
planner's smoothing). `retime_curve` therefore keeps speed through the corners when it can: the
natural cubic spline through the corners (parameterised by the body-motion bound of the chords) is
timed near time-optimally by a forward-backward pass in the phase plane (`_piece_law`: actuator speed
and acceleration limits on ``J x(s)``, and the body-speed bound ``B(x'(s)) ds/dt <= max_speed``; toppra,
the reference TOPP-RA library, gives the same law some 10 times slower, `method="toppra"`), sampled
every stream period from rest to rest,
slowed uniformly until the samples' finite differences keep every limit, and its frames, joined by
straight motions as the streamer sends them, are verified with the planner's `MotionValidator` at
their times (the curve is not the verified geometry, so it must pass its own dense check). Where a
piece fails, the path stops at the corner nearest to the failure and the pieces on either side are
timed again; a piece down to one straight motion is the verified chord with the law above. Units: s;
configurations as in `Robot` (rad, mm).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.splines import natural_cubic
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.metric import BodyMetric
from crtraj.planning.validity import MotionValidator

# Largest distance (configuration units) of a merged inner waypoint from its straight motion.
COLLINEAR = 1e-10
# Default stream period (s): the streamer sends set-points at 100 Hz.
STREAM_PERIOD = 0.01
# Most set-points a retimed path may hold (as `crtraj.hardware.setpoints.MAX_SETPOINTS`).
MAX_SAMPLES = 2_000_000
# TOPP-RA grid points per spline interval of a curve piece, and at most per piece.
GRID_PER_KNOT = 8
MAX_GRID = 2000
# Uniform slow-downs tried on a sampled curve piece before it is given up (each at least 1 % slower).
MAX_SLOWDOWNS = 30


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
    K = len(X)
    # a run from X[i] can only grow past X[i+1] when X[i+1] lies on the chord X[i] -> X[i+2]: that first
    # test is made for all i at once, so the loop below visits only those i (elsewhere the walk steps by one)
    first = _middles_on_chords(X, tol) if K >= 3 else np.zeros(0, dtype=bool)
    visited = np.ones(K, dtype=bool)  # the waypoints the walk from 0 stands on (not inside a merged run)
    reach = 0  # the walk has stood on no waypoint beyond this one yet
    for i in np.flatnonzero(first).tolist():
        if i < reach:
            continue  # inside a run merged from an earlier waypoint
        j = i + 1
        while j + 1 < K and _on_chord(X[i], X[j + 1], X[i + 1 : j + 1], tol):
            j += 1
        visited[i + 1 : j] = False
        reach = j
    v = np.flatnonzero(visited)
    if np.all(np.isfinite(X)):
        # a visited waypoint is kept where it differs from the previous one visited (a zero-length motion is
        # dropped: the previous one then equals the last kept, which the walk compares with)
        moved = np.max(np.abs(X[v[1:]] - X[v[:-1]]), axis=1, initial=0.0) > 0.0 if len(v) > 1 else []
        keep = np.concatenate([[0], v[1:][moved]]).astype(np.int64)
    else:  # NaN equals nothing: compare with the last kept, as the walk does
        keep_list = [0]
        for j in v[1:].tolist():
            if np.max(np.abs(X[j] - X[keep_list[-1]])) > 0.0:
                keep_list.append(j)
        keep = np.asarray(keep_list, dtype=np.int64)
    if keep[-1] != K - 1:
        keep[-1] = K - 1  # the end itself (equal to the last kept corner up to 0)
    return keep


def _middles_on_chords(X: np.ndarray, tol: float) -> np.ndarray:
    """(K-2,) bool: X[i+1] on the chord X[i] -> X[i+2] as `_on_chord` decides it (vectorised)."""
    a, m, b = X[:-2], X[1:-1], X[2:]
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.einsum("ij,ij->i", m - a, d) / dd
        dist = np.linalg.norm(a + u[:, None] * d - m, axis=1)
    return (dd != 0.0) & (u >= 0.0) & (u <= 1.0) & (dist <= tol)


def _on_chord(a: np.ndarray, b: np.ndarray, inner: np.ndarray, tol: float) -> bool:
    """All `inner` points within tol of the chord a -> b, in order along it."""
    d = b - a
    dd = float(d @ d)
    if dd == 0.0:
        return False
    u = (inner - a) @ d / dd
    # in order along the chord: 0 <= u_0 <= u_1 <= ... <= 1 (a difference of two doubles is negative exactly when
    # the second is the smaller, so these comparisons decide as the differences did)
    if u[0] < 0.0 or u[-1] > 1.0 or np.any(u[1:] < u[:-1]):
        return False
    w = a + u[:, None] * d - inner
    # the largest distance as np.linalg.norm computes each (the square root of the summed squares)
    return bool(np.sqrt(np.max((w * w).sum(axis=1))) <= tol)


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


@dataclass(frozen=True)
class CurveTiming:
    """A path timed along the smoothed curve through its corners (`retime_curve`).

    stamps (M,) s, every period from t0; configs (M, nx): the frames. stops: indices of the corners
    (of `keep_corners`) where the motion comes to rest; corners: how many corners there are. A
    motion with stops only at its two ends follows the curve throughout; stops at every corner is
    the chord law of `retime`.
    """

    stamps: np.ndarray
    configs: np.ndarray
    stops: tuple[int, ...]
    corners: int

    @property
    def duration(self) -> float:
        return float(self.stamps[-1] - self.stamps[0])


def _piece_law(
    P: np.ndarray, limits: RateLimits, metric: BodyMetric, kernel: Any = None
) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """(x(s), grid points, ds/dt at them, the law's time (s) at them) of a near time-optimal rest-to-rest law along
    the natural cubic spline through P (K >= 3, nx), s the cumulative body-motion bound of the chords (mm);
    `InputError` when there is none. kernel: a `ValidityKernel` runs the pass and the knot times in one C call
    (`ValidityKernel.phase_law`, the same numbers); None: numpy and the loops of `_phase_pass`.

    A forward-backward pass on x = (ds/dt)^2 over the grid (the phase-plane method, in closed form per
    interval): with q = J x(s) the actuator values, q' and q'' their s-derivatives, an actuator's
    acceleration is q' s'' + q'' x, so over an interval where x rises from x_k to x_{k+1} = x_k + 2 h s''
    every |q' s'' + q'' x| <= amax holds when s'' <= (amax - |q''| x_{k+1}) / |q'| (the worst of both
    ends of the interval). Solving for x_{k+1} gives ``x_{k+1} <= (x_k + 2 h A) / (1 + 2 h B)`` with
    A = amax / |q'|, B = |q''| / |q'|; the backward pass is the same from the end at rest. Speed caps
    (actuators, body, and amax / |q''| where q' vanishes) bound x at each grid point. Conservative
    where q'' helps; the sampled frames are then checked against every limit (`_curve_piece`).
    """
    ss = np.concatenate([[0.0], np.cumsum(metric.motion_bound(np.diff(P, axis=0)))])
    spline = _natural(ss, P, kernel)  # x(s); spline(s, 1) is dx/ds
    J = limits.jacobian
    n = int(min(MAX_GRID, GRID_PER_KNOT * (len(ss) - 1)))
    grid = np.unique(np.concatenate([ss, np.linspace(0.0, ss[-1], n + 1)]))
    h = np.diff(grid)
    # the speed caps hold between grid points too: each takes the path's largest rate within one grid
    # spacing either side (from a 4 times finer sampling)
    fine = np.linspace(0.0, ss[-1], 4 * n + 1)
    d_fine = spline(fine, 1)
    w = math.ceil(float(np.max(h)) / (fine[1] - fine[0])) + 1
    q_win = _window_max(np.abs(d_fine @ J.T), w)
    b_win = _window_max(metric.motion_bound(d_fine)[:, None], w)[:, 0]
    at = np.clip(np.rint(grid / (fine[1] - fine[0])).astype(int), 0, len(fine) - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = np.min((limits.vmax / q_win[at]) ** 2, axis=1)
        cap = np.minimum(cap, (metric.max_speed / b_win[at]) ** 2)
        a = np.abs(spline(grid, 1) @ J.T)  # |q'| per grid point and actuator
        b = np.abs(spline(grid, 2) @ J.T)  # |q''|
        tiny = a <= 1e-12 * max(float(np.max(a)), 1e-300)
        # where q' vanishes the acceleration is q'' x alone: a speed cap
        cap = np.minimum(cap, np.min(np.where(tiny & (b > 0.0), limits.amax / b, np.inf), axis=1))
        A = np.where(tiny, np.inf, limits.amax / a)
        B = np.where(tiny, 0.0, b / a)
    A = np.minimum(A[:-1], A[1:])  # per interval: the worse end
    B = np.maximum(B[:-1], B[1:])
    if not np.all(np.isfinite(cap[1:-1])) or np.any(cap[1:-1] <= 0.0):
        raise InputError("retime: no speed is allowed somewhere along a curve piece")
    if kernel is not None:
        h2 = 2.0 * h[:, None]
        sd, T = kernel.phase_law(np.minimum(cap, 1e30), h2 * A, 1.0 + h2 * B, h)
    else:
        sd = np.sqrt(_phase_pass(np.minimum(cap, 1e30), h, A, B))
        T = _knot_times(grid, sd)
    if np.any(sd[1:-1] <= 0.0):
        raise InputError("retime: no law along a curve piece")
    return spline, grid, sd, T


class _KernelCubic:
    """The cubic `crtraj.core.splines.HermiteCubic(t, Y, S)` evaluated by a `ValidityKernel` (`hermite`: the same
    numbers, one C call per evaluation); derivative orders 0-2, x (N,)."""

    def __init__(self, t: np.ndarray, Y: np.ndarray, S: np.ndarray, kernel: Any) -> None:
        self.t, self.values, self.slopes, self.kernel = t, Y, S, kernel

    def __call__(self, x: np.ndarray, nu: int = 0) -> np.ndarray:
        return self.kernel.hermite(self.t, self.values, self.slopes, x, nu)


def _natural(ss: np.ndarray, P: np.ndarray, kernel: Any) -> Any:
    """`natural_cubic(ss, P)`, with a kernel solved and evaluated in C (the same numbers) when ss is strictly
    increasing and there are at least 3 knots (else numpy's, which raises on bad knots)."""
    if kernel is None or len(ss) < 3 or P.ndim != 2 or not np.all(np.diff(ss) > 0.0):
        return natural_cubic(ss, P)
    t, Y = np.ascontiguousarray(ss, dtype=float), np.ascontiguousarray(P, dtype=float)
    return _KernelCubic(t, Y, kernel.natural_slopes(t, Y), kernel)


def _knot_times(gp: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """The law's time (s) at the grid points gp (mm) with ds/dt = sd there, constant ds2/dt2 between them."""
    dt = 2.0 * np.diff(gp) / (sd[:-1] + sd[1:])
    return np.concatenate([[0.0], np.cumsum(dt)])


def _window_max(Y: np.ndarray, w: int) -> np.ndarray:
    """Each row's column-wise maximum over the rows within w of it (Y: (N, m))."""
    out = Y.copy()
    for k in range(1, w + 1):
        out[k:] = np.maximum(out[k:], Y[:-k])
        out[:-k] = np.maximum(out[:-k], Y[k:])
    return out


def _phase_pass(cap: np.ndarray, h: np.ndarray, A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """x = (ds/dt)^2 at the grid points: rest at both ends, x <= cap, and per interval k (length h_k)
    x_{k+1} <= min_j (x_k + 2 h_k A_kj) / (1 + 2 h_k B_kj), and the same backward."""
    h2 = 2.0 * h[:, None]
    num, den = h2 * A, 1.0 + h2 * B  # x_next <= min((x + num) / den)
    x = cap.astype(float).copy()
    x[0] = x[-1] = 0.0
    # plain floats and explicit loops: a numpy call (or a generator) per grid point would cost more than the rest
    xs = x.tolist()
    terms = [list(zip(nk, dk, strict=True)) for nk, dk in zip(num.tolist(), den.tolist(), strict=True)]
    for k, pairs in enumerate(terms):  # forward: accelerate as hard as allowed
        xk, best = xs[k], xs[k + 1]
        for u, d in pairs:
            r = (xk + u) / d
            if r < best:
                best = r
        xs[k + 1] = best
    for k in range(len(terms) - 1, -1, -1):  # backward: brake in time to every later cap
        xk1, best = xs[k + 1], xs[k]
        for u, d in terms[k]:
            r = (xk1 + u) / d
            if r < best:
                best = r
        xs[k] = best
    return np.maximum(np.asarray(xs), 0.0)


def _toppra_law(
    P: np.ndarray, limits: RateLimits, metric: BodyMetric, kernel: Any = None
) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """The same law computed by toppra (TOPP-RA, the reference library), for the benchmark's comparison:
    (x(s), grid points, ds/dt at them, times at them); `InputError` when toppra finds none. kernel: unused."""
    import toppra as ta  # the reference library: needed only by this cross-check (benchmarks, tests)

    ss = np.concatenate([[0.0], np.cumsum(metric.motion_bound(np.diff(P, axis=0)))])
    spline = natural_cubic(ss, P)
    J = limits.jacobian
    # toppra's path: the actuator values J x(s) (the same spline, mapped linearly) and s itself
    path = ta.SplineInterpolator(ss, np.hstack([P @ J.T, ss[:, None]]), bc_type="natural")
    n = int(min(MAX_GRID, GRID_PER_KNOT * (len(ss) - 1)))
    grid = np.unique(np.concatenate([ss, np.linspace(0.0, ss[-1], n + 1)]))
    step = float(np.max(np.diff(grid)))
    fine = np.linspace(0.0, ss[-1], 4 * n + 1)
    d_fine = spline(fine, 1)
    q_fine, b_fine = np.abs(d_fine @ J.T), metric.motion_bound(d_fine)

    def vlim(s: float) -> np.ndarray:
        w = np.abs(fine - s) <= step
        qmax, bmax = np.max(q_fine[w], axis=0), float(np.max(b_fine[w]))
        q_here = np.abs(spline(s, 1) @ J.T)
        scale = np.where(qmax > 0.0, q_here / np.where(qmax > 0.0, qmax, 1.0), 1.0)
        v = np.append(limits.vmax * scale, metric.max_speed / max(bmax, 1e-12))
        return np.stack([-v, v], axis=1)

    alim = np.append(limits.amax, 1e12)  # no limit on the body's acceleration
    cons = [
        ta.constraint.JointVelocityConstraintVarying(vlim),
        ta.constraint.JointAccelerationConstraint(np.stack([-alim, alim], axis=1)),
    ]
    algo = ta.algorithm.TOPPRA(cons, path, gridpoints=grid)
    algo.compute_parameterization(0.0, 0.0)
    data = algo.problem_data
    sd = None if data.sd_vec is None else np.maximum(np.asarray(data.sd_vec, dtype=float), 0.0)
    if data.return_code != ta.algorithm.ParameterizationReturnCode.Ok or sd is None or np.any(sd[1:-1] <= 0.0):
        raise InputError(f"retime: toppra found no law along a curve piece ({data.return_code})")
    gp = np.asarray(data.gridpoints, dtype=float)
    return spline, gp, sd, _knot_times(gp, sd)


def _sample_law(spline: Any, gp: np.ndarray, sd: np.ndarray, T: np.ndarray, period: float, slow: float) -> np.ndarray:
    """Configurations every period along x(s) with ds/dt = sd at the grid points gp, reached at the law's times T
    (`_knot_times`: constant ds2/dt2 between them, as TOPP-RA assumes), slowed `slow` >= 1 times and stretched to
    whole periods."""
    ds = np.diff(gp)
    n = max(1, math.ceil(slow * T[-1] / period - 1e-9))
    tau = np.arange(n + 1) * (T[-1] / n)  # the law's own time at each frame
    i = np.clip(np.searchsorted(T, tau, side="right") - 1, 0, len(ds) - 1)
    u = tau - T[i]
    acc = (sd[i + 1] ** 2 - sd[i] ** 2) / (2.0 * ds[i])
    s = np.clip(gp[i] + sd[i] * u + 0.5 * acc * u * u, gp[0], gp[-1])
    s[-1] = gp[-1]
    return spline(s)


def _over_limits(Y: np.ndarray, limits: RateLimits, metric: BodyMetric, period: float) -> float:
    """The largest of: actuator speed / vmax, sqrt(acceleration / amax) (finite differences from rest to
    rest) and body speed / max_speed of frames Y every period: 1 or less keeps every limit."""
    V = np.diff(Y @ limits.jacobian.T, axis=0) / period
    Vz = np.vstack([np.zeros((1, V.shape[1])), V, np.zeros((1, V.shape[1]))])
    A = np.diff(Vz, axis=0) / period
    body = metric.motion_bound(np.diff(Y, axis=0)) / period / metric.max_speed
    return float(
        max(np.max(np.abs(V) / limits.vmax), np.sqrt(np.max(np.abs(A) / limits.amax)), np.max(body, initial=0.0))
    )


def _curve_piece(
    P: np.ndarray, limits: RateLimits, metric: BodyMetric, period: float, law: Any = None, kernel: Any = None
) -> np.ndarray | None:
    """Frames (n+1, nx) every period, rest to rest, along the curve through P (>= 3 corners) within
    every limit, or None when the law (`_piece_law`, or `_toppra_law`) finds none or the slow-downs run out.
    kernel: passed to the law (`_piece_law`: its pass in C)."""
    try:
        spline, gp, sd, T = (_piece_law if law is None else law)(P, limits, metric, kernel)
    except InputError:
        return None
    slow = 1.0
    for _ in range(MAX_SLOWDOWNS):
        Y = _sample_law(spline, gp, sd, T, period, slow)
        Y[0], Y[-1] = P[0], P[-1]
        over = _over_limits(Y, limits, metric, period)
        if over <= 1.0:
            return Y
        slow *= max(1.01, over * 1.001)
    return None


def _piece_frames(
    P: np.ndarray, limits: RateLimits, metric: BodyMetric, period: float, law: Any = None, kernel: Any = None
) -> np.ndarray | None:
    """Frames of one piece between two stops: the chord law for one straight motion, else the curve."""
    if len(P) == 2:
        return retime(P, limits, metric, period=period).sample()[1]
    return _curve_piece(P, limits, metric, period, law, kernel)


def _failures(validator: MotionValidator, stamps: np.ndarray, Y: np.ndarray, check: np.ndarray) -> np.ndarray:
    """Indices k of the frame-to-frame motions Y[k] -> Y[k+1] (those with `check` set) that fail the validator
    at their times (body, D_sf) or leave the configuration limits."""
    e = np.flatnonzero(check)
    if not e.size:
        return e
    ok = validator.edges_valid(Y[e], Y[e + 1], stamps[e], stamps[e + 1])
    inside = validator.within_limits(Y)  # once per frame (a frame ends one motion and starts the next)
    ok &= inside[e] & inside[e + 1]
    return e[~ok]


def retime_curve(
    X: np.ndarray,
    limits: RateLimits,
    metric: BodyMetric,
    validator: MotionValidator,
    *,
    t0: float = 0.0,
    period: float = STREAM_PERIOD,
    method: str = "phase",
    kernel: Any = None,
) -> CurveTiming | None:
    """The path X (K, nx) timed along the smoothed curve through its corners, stopping only where the
    curve fails its check (see the module docstring), or None when even the chords fail at their new
    times (moving obstacles) or the path has fewer than 3 corners (nothing to smooth). limits: the
    usable actuator limits; metric: the body-speed limit; validator: the planner's motion check,
    against the scene at the frames' times. Among static obstacles the chords (the verified geometry)
    need no new check. method: "phase" (`_piece_law`, the closed-form phase-plane pass) or "toppra"
    (the reference library, for comparison). kernel: a `ValidityKernel` (`MotionValidator.kernel`) runs the
    phase pass and the knot times in C (the same numbers); None: numpy and Python loops."""
    if method not in ("phase", "toppra"):
        raise InputError(f"retime: method must be 'phase' or 'toppra', got {method!r}")
    law = _piece_law if method == "phase" else _toppra_law
    X = np.atleast_2d(np.asarray(X, dtype=float))
    P = X[keep_corners(X)]
    if len(P) < 3:
        return None
    stops = [0, len(P) - 1]
    laws: dict[tuple[int, int], np.ndarray | None] = {}
    for _ in range(len(P)):  # every round adds a stop; all corners stopped at is the chord law
        pieces = list(itertools.pairwise(stops))
        for a, b in pieces:
            if (a, b) not in laws:
                laws[(a, b)] = _piece_frames(P[a : b + 1], limits, metric, period, law, kernel)
        # piece index -> the frame near which it failed (None: no law along the whole piece)
        split: dict[int, np.ndarray | None] = {i: None for i, ab in enumerate(pieces) if laws[ab] is None}
        if not split:
            frames = [laws[ab] for ab in pieces]
            owner = np.concatenate([np.full(len(f) - (i > 0), i) for i, f in enumerate(frames)])
            Y = np.concatenate([f if i == 0 else f[1:] for i, f in enumerate(frames)])
            if len(Y) > MAX_SAMPLES:
                raise InputError(f"retime: {len(Y) * period:g} s is more than {MAX_SAMPLES} set-points")
            stamps = t0 + period * np.arange(len(Y))
            curved = np.array([b - a > 1 for a, b in pieces])
            bad = _failures(validator, stamps, Y, (curved | (not validator.static))[owner[1:]])
            if not bad.size:
                return CurveTiming(stamps, Y, tuple(stops), len(P))
            for k in bad[::-1]:  # the first failure of each piece
                split[int(owner[k + 1])] = Y[k]
        added = set()
        for i, near in split.items():
            a, b = pieces[i]
            if b - a == 1:
                return None  # a chord fails at its new times: the caller keeps a slower verified timing
            inner = np.arange(a + 1, b)
            # stop at the corner nearest to the failure; with no law at all, halve the piece
            k = len(inner) // 2 if near is None else int(np.argmin(metric.motion_bound(P[inner] - near)))
            added.add(int(inner[k]))
        stops = sorted(set(stops) | added)
    return None
