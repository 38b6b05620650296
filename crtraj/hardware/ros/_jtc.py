"""What a stock ros2_controllers joint_trajectory_controller (JTC) executes from a JointTrajectory.

The model follows the controller's documented behaviour on its topic interface
(``/<controller>/joint_trajectory``):

- A message is checked when it arrives (`rejection`): joint names known to the controller, every
  controller joint named (unless ``allow_partial_joints_goal``), at least one point, positions of
  every joint at every point, velocity and acceleration arrays empty or one per joint, no efforts,
  ``time_from_start`` strictly increasing, a non-zero ``header.stamp`` whose last point lies in the
  past refused, and a last point with non-zero velocity refused unless
  ``allow_nonzero_velocity_at_trajectory_end`` (by more than float epsilon; the parameter is true by default on
  Humble, false on Jazzy and Rolling).
- An accepted message replaces the current trajectory at once. At its first control cycle (the
  arrival) the controller stores its state as "the point before the trajectory" (the measured
  state, or the last command with Humble's ``open_loop_control`` / later ``interpolate_from_desired_state``),
  stamped with the arrival time. That state is read at the start of the update, before the cycle's
  command: it is the state one controller period old (`state_before`, lag ``1 / update_rate``), not the
  state at the arrival time.
- ``header.stamp`` 0 means "start now": the start time becomes the arrival time. Point k is due at
  start + ``time_from_start[k]``.
- Between the point before and the first point, and between consecutive points, the controller
  interpolates per segment: quintic when both ends carry velocities and accelerations, cubic when
  both carry velocities, linear otherwise. Before the first point is due the first segment runs
  from the arrival; once a point's time has passed the segment that contains the time is used.
- After the last point it holds the last point (its positions and velocities).
- Per distro (`JtcParameters.distro`): Humble writes the trajectory sampled at the cycle time; Jazzy and Rolling
  sample it one update period ahead (`JtcParameters.lookahead`; with a speed scaling factor of 1, which the bridge
  requires). Rolling's ``allow_trajectory_replacement`` (true by default) blends a message into the running
  trajectory instead of replacing it, re-anchored at the previous cycle: the old curve then runs one period late
  until the new stamp, and a stamp not in the future starts at the arrival cycle, which the bridge cannot know.
  The model does not cover that blend: the bridge refuses the parameter
  (`crtraj.hardware.ros._controller.check_parameters`).

Everything here is plain numpy (no rclpy): times in s, values in any consistent unit (rad, mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# interpolation of one segment, by what both of its end points carry
LINEAR, CUBIC, QUINTIC = "linear", "cubic", "quintic"


# the ros2_controllers releases whose JTC semantics differ (master is Rolling)
DISTROS = ("humble", "jazzy", "rolling")
# the controller's tolerance on a last point's velocity (std::numeric_limits<float>::epsilon())
FLOAT_EPS = float(np.finfo(np.float32).eps)


@dataclass(frozen=True)
class JtcParameters:
    """The controller parameters the model depends on (names as in the JTC parameter file).

    allow_nonzero_velocity_at_trajectory_end: accept a last point with non-zero velocity.
    allow_partial_joints_goal: accept a message naming only some of the controller's joints.
    interpolation_method: "splines" (the model) or "none" (the controller jumps to each point; not
    supported by the bridge).
    distro: "humble", "jazzy" or "rolling" (`crtraj.hardware.ros._controller.detect_distro`).
    lookahead: s the command is sampled ahead of the cycle time (Jazzy and later: one update period,
    1 / update_rate; Humble: 0). The bridge stamps its messages that much later (`message_epoch`), so the
    command written at cycle time t is the verified curve at t.
    """

    allow_nonzero_velocity_at_trajectory_end: bool = False
    allow_partial_joints_goal: bool = False
    interpolation_method: str = "splines"
    distro: str = "humble"
    lookahead: float = 0.0


def message_epoch(origin: float, params: JtcParameters) -> float:
    """The controller clock time (s) of loop time 0 of the bridge's messages: `origin` (the loop's) plus the
    controller's lookahead, so a controller that commands its trajectory `lookahead` s ahead commands the verified
    curve at each cycle's own time."""
    return float(origin) + float(params.lookahead)


@dataclass(frozen=True)
class JtcPoint:
    """One trajectory point: time_from_start (s) and per-joint arrays (empty when not given)."""

    time_from_start: float
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    efforts: int = 0  # how many effort values the point carries (the controller refuses any)


@dataclass(frozen=True)
class JtcMessage:
    """A JointTrajectory as the controller reads it: joint names, header stamp (s; 0 = now) and points."""

    joint_names: tuple[str, ...]
    stamp: float
    points: tuple[JtcPoint, ...]

    @classmethod
    def from_arrays(
        cls,
        joint_names: tuple[str, ...],
        stamp: float,
        time_from_start: np.ndarray,
        positions: np.ndarray,
        velocities: np.ndarray | None = None,
        accelerations: np.ndarray | None = None,
    ) -> JtcMessage:
        """A message from (N,) times and (N, n) arrays (None: the field is left empty at every point)."""
        empty = np.zeros(0)
        pts = tuple(
            JtcPoint(
                float(time_from_start[k]),
                np.asarray(positions[k], dtype=float),
                empty if velocities is None else np.asarray(velocities[k], dtype=float),
                empty if accelerations is None else np.asarray(accelerations[k], dtype=float),
            )
            for k in range(len(time_from_start))
        )
        return cls(tuple(joint_names), float(stamp), pts)

    @classmethod
    def from_ros(cls, msg: object) -> JtcMessage:
        """A trajectory_msgs/JointTrajectory as the controller reads it (stamp and durations in s)."""

        def seconds(t: object) -> float:
            return float(t.sec) + 1e-9 * float(t.nanosec)  # type: ignore[attr-defined]

        pts = tuple(
            JtcPoint(
                seconds(p.time_from_start),
                np.asarray(p.positions, dtype=float),
                np.asarray(p.velocities, dtype=float),
                np.asarray(p.accelerations, dtype=float),
                len(p.effort),
            )
            for p in msg.points  # type: ignore[attr-defined]
        )
        return cls(tuple(msg.joint_names), seconds(msg.header.stamp), pts)  # type: ignore[attr-defined]


def rejection(
    msg: JtcMessage, joints: tuple[str, ...], now: float, params: JtcParameters, epoch: float = 0.0
) -> str | None:
    """Why the controller with `joints` refuses `msg` arriving at time `now` (s), or None when it takes it.
    epoch: the controller's clock reads epoch + t at time t of `msg` and `now` (its stamp 0 is "now")."""
    names = msg.joint_names
    if not names:
        return "empty joint names"
    if len(names) != len(joints) and not params.allow_partial_joints_goal:
        return f"{len(names)} joint names, the controller has {len(joints)} joints"
    for name in names:
        if name not in joints:
            return f"joint {name!r} is not one of the controller's joints ({', '.join(joints)})"
    if len(set(names)) != len(names):
        return "a joint is named twice"
    if not msg.points:
        return "empty trajectory"
    end = msg.stamp + msg.points[-1].time_from_start
    if msg.stamp + epoch != 0.0 and end < now:
        return f"the trajectory ends in the past ({end:.6f} s < now {now:.6f} s)"
    for k, p in enumerate(msg.points):
        why = _point_rejection(k, p, len(names))
        if why is None and k > 0 and not p.time_from_start > msg.points[k - 1].time_from_start:
            why = f"time_from_start of points {k - 1} and {k} not strictly increasing"
        if why is not None:
            return why
    last = msg.points[-1]
    moving = np.abs(last.velocities) > FLOAT_EPS
    if not params.allow_nonzero_velocity_at_trajectory_end and last.velocities.size and np.any(moving):
        j = int(np.flatnonzero(moving)[0])
        return f"velocity of the last point of joint {names[j]!r} is not zero ({last.velocities[j]:.15g})"
    return None


def _point_rejection(k: int, p: JtcPoint, n: int) -> str | None:
    """Why point k of a message naming n joints is refused, or None."""
    if p.positions.size != n:
        return f"point {k}: {p.positions.size} positions for {n} joints"
    for field, values in (("velocities", p.velocities), ("accelerations", p.accelerations)):
        if values.size not in (0, n):
            return f"point {k}: {values.size} {field} for {n} joints"
    if p.efforts:
        return f"point {k}: efforts are not supported"
    return None


class Spline:
    """A piecewise-polynomial joint curve through knots, as the controller interpolates it.

    times (K,) s strictly increasing; positions (K, n); velocities and accelerations (K, n) or None
    per knot (a knot without them makes its segments cubic or linear, as in the controller). Before
    the first knot it rests at the first; after the last it holds the last knot's positions and
    velocities (the controller keeps commanding the last point).
    """

    def __init__(
        self,
        times: np.ndarray,
        positions: np.ndarray,
        velocities: list[np.ndarray | None],
        accelerations: list[np.ndarray | None],
    ) -> None:
        self.times = np.asarray(times, dtype=float)
        self.positions = np.atleast_2d(np.asarray(positions, dtype=float))
        self.velocities = velocities
        self.accelerations = accelerations
        n = self.positions.shape[1]
        self._zero = np.zeros(n)
        self.kinds = [self._kind(k) for k in range(len(self.times) - 1)]

    @classmethod
    def hermite(cls, times: np.ndarray, positions: np.ndarray, velocities: np.ndarray) -> Spline:
        """Cubic segments through knots with positions and velocities (K, n)."""
        return cls(times, positions, list(np.asarray(velocities, dtype=float)), [None] * len(times))

    def _kind(self, k: int) -> str:
        va, vb = self.velocities[k], self.velocities[k + 1]
        aa, ab = self.accelerations[k], self.accelerations[k + 1]
        if va is None or vb is None:
            return LINEAR
        return QUINTIC if aa is not None and ab is not None else CUBIC

    @property
    def end(self) -> float:
        """Time of the last knot (s)."""
        return float(self.times[-1])

    def at(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(positions, velocities, accelerations) at time(s) t: (M, n) each, or (n,) for a scalar t."""
        ts = np.atleast_1d(np.asarray(t, dtype=float))
        n = self.positions.shape[1]
        P, V, A = np.empty((ts.size, n)), np.empty((ts.size, n)), np.zeros((ts.size, n))
        seg = np.searchsorted(self.times, ts, side="right") - 1
        before, after = seg < 0, seg >= len(self.times) - 1
        P[before], V[before] = self.positions[0], 0.0
        last_v = self.velocities[-1]
        P[after], V[after] = self.positions[-1], (self._zero if last_v is None else last_v)
        for k in np.unique(seg[~before & ~after]):
            m = seg == k
            P[m], V[m], A[m] = self._segment(int(k), ts[m] - self.times[k])
        if np.ndim(t) == 0:
            return P[0], V[0], A[0]
        return P, V, A

    def _segment(self, k: int, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segment k at tau (M,) s after its start: (M, n) positions, velocities, accelerations."""
        h = float(self.times[k + 1] - self.times[k])
        c = segment_coefficients(
            self.kinds[k],
            h,
            (self.positions[k], self.velocities[k], self.accelerations[k]),
            (self.positions[k + 1], self.velocities[k + 1], self.accelerations[k + 1]),
        )
        powers = tau[:, None] ** np.arange(6)[None, :]  # (M, 6)
        P = powers @ c
        V = powers[:, :5] @ (c[1:] * np.arange(1, 6)[:, None])
        A = powers[:, :4] @ (c[2:] * (np.arange(2, 6) * np.arange(1, 5))[:, None])
        return P, V, A

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) at time t (s), exactly a knot's values when t is a knot time."""
        k = np.flatnonzero(np.abs(self.times - t) <= 1e-12)
        if k.size:
            v = self.velocities[int(k[0])]
            return self.positions[int(k[0])].copy(), (self._zero.copy() if v is None else np.array(v))
        p, v, _ = self.at(float(t))
        return p, v

    def shifted(self, dt: float) -> Spline:
        """The same curve `dt` s later."""
        return Spline(self.times + dt, self.positions, self.velocities, self.accelerations)

    def since(self, t0: float) -> Spline:
        """The knots from the last one at or before t0 on (the curve from t0 on is unchanged)."""
        k = max(int(np.searchsorted(self.times, t0, side="right")) - 1, 0)
        return Spline(self.times[k:], self.positions[k:], self.velocities[k:], self.accelerations[k:])

    def then(self, later: Spline) -> Spline:
        """This curve until `later` begins, then `later` (a replacement at later's first knot)."""
        keep = self.times < later.times[0]
        idx = np.flatnonzero(keep)
        return Spline(
            np.concatenate([self.times[keep], later.times]),
            np.vstack([self.positions[keep], later.positions]),
            [self.velocities[i] for i in idx] + list(later.velocities),
            [self.accelerations[i] for i in idx] + list(later.accelerations),
        )


def segment_coefficients(kind: str, h: float, a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> np.ndarray:
    """Polynomial coefficients (6, n), lowest power first, of a segment of duration h (s) from end point a
    to end point b, each (positions, velocities or None, accelerations or None): the linear, cubic
    (Hermite: positions and velocities at both ends) or quintic (also accelerations) interpolant."""
    pa, pb = a[0], b[0]
    c = np.zeros((6, pa.size))
    c[0] = pa
    if h <= 0.0:
        return c
    d = pb - pa
    if kind == LINEAR:
        c[1] = d / h
    elif kind == CUBIC:
        va, vb = a[1], b[1]
        c[1] = va
        c[2] = (3.0 * d - (2.0 * va + vb) * h) / h**2
        c[3] = (-2.0 * d + (va + vb) * h) / h**3
    else:
        va, vb, aa, ab = a[1], b[1], a[2], b[2]
        c[1], c[2] = va, 0.5 * aa
        c[3] = (20.0 * d - (12.0 * va + 8.0 * vb) * h - (3.0 * aa - ab) * h**2) / (2.0 * h**3)
        c[4] = (-30.0 * d + (16.0 * va + 14.0 * vb) * h + (3.0 * aa - 2.0 * ab) * h**2) / (2.0 * h**4)
        c[5] = (12.0 * d - 6.0 * (va + vb) * h + (ab - aa) * h**2) / (2.0 * h**5)
    return c


def state_before(curve: Spline, arrival: float, lag: float) -> tuple[np.ndarray, np.ndarray]:
    """The point before the trajectory of a message arriving at `arrival` (s) while the controller commands
    `curve`: its state read at the start of that update, i.e. the curve `lag` s earlier (one controller period
    for a ros2_control JTC: 1 / update_rate; 0 for an idealised one). (positions, velocities)."""
    return curve.state(float(arrival) - max(float(lag), 0.0))


def executed(
    msg: JtcMessage,
    arrival: float,
    position: np.ndarray,
    velocity: np.ndarray | None,
    joints: tuple[str, ...] | None = None,
    acceleration: np.ndarray | None = None,
    epoch: float = 0.0,
) -> Spline:
    """The curve the controller commands from `arrival` (s) on for an accepted `msg`, in the order of
    `joints` (default: the message's order): the point before the trajectory is its state as read at
    arrival (position, and velocity / acceleration when its state carries them; `state_before` gives it
    with the controller's state lag), then the message's points
    at stamp + time_from_start (stamp 0: the arrival). Points already due at arrival are passed over
    by time: the curve from arrival on is the segment that contains it. epoch: as in `rejection`."""
    order = list(range(len(msg.joint_names))) if joints is None else [msg.joint_names.index(j) for j in joints]
    start = arrival if msg.stamp + epoch == 0.0 else msg.stamp
    T = [arrival] + [start + p.time_from_start for p in msg.points]
    P = [np.asarray(position, dtype=float)] + [p.positions[order] for p in msg.points]
    V = [velocity] + [p.velocities[order] if p.velocities.size else None for p in msg.points]
    A = [acceleration] + [p.accelerations[order] if p.accelerations.size else None for p in msg.points]
    first_due = T[1]
    if first_due <= arrival:
        # the controller samples the message's own segments: the point before is never used
        return Spline(np.array(T[1:]), np.array(P[1:]), V[1:], A[1:]).since(arrival)
    return Spline(np.array(T), np.array(P), V, A)
