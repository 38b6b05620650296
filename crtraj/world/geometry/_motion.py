"""Rigid motion over time as plain data (mm, rad, s), and breathing as a uniform scale.

A motion maps time t to a rigid pose (position p(t) mm, rotation R(t)); a shape moved by it occupies
``p(t) + R(t) X`` where X is the shape placed by its own `Pose`. Each motion also bounds its speeds
over a time interval: `speed_bound(t0, t1)` returns (v, w) with ``|dp/dt| <= v`` mm/s and angular speed
``<= w`` rad/s at every t in [t0, t1], from which `crtraj.world.geometry.MovingShape` bounds how far any
point of a shape can move (the sweep bound).

- `Fixed`: no motion.
- `Keyframes`: poses at strictly increasing times; position by linear interpolation or by the natural
  cubic spline through the keyframes (C2, zero acceleration at both ends; `crtraj.core.splines`),
  rotation by slerp between consecutive keyframes (constant angular speed on each interval). Before
  the first and after the last keyframe the pose holds.
- `StraightLine`: the existing sphere obstacles' straight-line profiles (`crtraj.world.obstacle`),
  no rotation.
- `Breathing`: scale ``1 + a sin(omega t + phase)`` about the shape's own origin, |a| < 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, check_array, check_float, check_vec
from crtraj.core.splines import HermiteCubic, natural_cubic
from crtraj.world.geometry._rotation import angle, check_unit, matrix, slerp
from crtraj.world.obstacle import MAX_OMEGA, MIN_DURATION, PROFILES, sin_range

INTERPOLATIONS = ("linear", "cubic")


@runtime_checkable
class Motion(Protocol):
    """A rigid pose over time, with speed bounds over intervals."""

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) mm, rotation matrix (3, 3)) at time t (s)."""
        ...

    def speed_bound(self, t0: float, t1: float) -> tuple[float, float]:
        """(max linear speed mm/s, max angular speed rad/s) over [t0, t1] (s)."""
        ...


@dataclass(frozen=True)
class Fixed:
    """No motion: the identity pose at every time."""

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) mm, rotation matrix (3, 3)) at time t (s)."""
        return np.zeros(3), np.eye(3)

    def speed_bound(self, t0: float, t1: float) -> tuple[float, float]:
        """(0, 0): nothing moves."""
        return 0.0, 0.0


def _quad_abs_max(f: Any, a: float, b: float) -> np.ndarray:
    """max over [a, b] of |f(x, 1)| per component, for f a piecewise cubic that is one cubic on [a, b]:
    the velocity is quadratic, so its extremes are at a, b or where the acceleration vanishes."""
    va, vb = np.abs(f(a, 1)), np.abs(f(b, 1))
    best = np.maximum(va, vb)
    acc, jerk = f(a, 2), f(a, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = a - acc / jerk
    for i in range(len(best)):
        if jerk[i] != 0.0 and a < x[i] < b:
            best[i] = max(best[i], abs(float(f(x[i], 1)[i])))
    return best


@dataclass(frozen=True)
class Keyframes:
    """Poses at `times` (K,) s, strictly increasing: `positions` (K, 3) mm, `rotations` (K, 4) unit
    quaternions (w, x, y, z; None: no rotation). `interpolation`: "linear" or "cubic" (the natural cubic
    spline through the positions); rotation always by slerp. The pose holds outside [times[0], times[-1]].
    """

    times: tuple[float, ...]
    positions: tuple[tuple[float, float, float], ...]
    rotations: tuple[tuple[float, float, float, float], ...] | None = None
    interpolation: str = "linear"
    _curve: HermiteCubic | None = field(init=False, repr=False, compare=False, default=None)
    _p: np.ndarray = field(init=False, repr=False, compare=False, default=None)
    _q: np.ndarray = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        t = check_array(self.times, "keyframes.times", (None,), limit=MAX_TIME)
        if len(t) < 1:
            raise InputError("keyframes.times: need at least one keyframe")
        bad = np.flatnonzero(np.diff(t) <= 0.0)
        if bad.size:
            i = int(bad[0]) + 1
            raise InputError(
                f"keyframes.times: must be strictly increasing, got {t[i]:g} s after {t[i - 1]:g} s at index {i}"
            )
        p = check_array(self.positions, "keyframes.positions", (len(t), 3), limit=MAX_LENGTH)
        if self.rotations is None:
            q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
        else:
            rot = self.rotations.tolist() if isinstance(self.rotations, np.ndarray) else self.rotations
            if not isinstance(rot, (list, tuple)) or len(rot) != len(t):
                raise InputError(f"keyframes.rotations: expected {len(t)} quaternions, one per time")
            q = np.array([check_unit(r, f"keyframes.rotations[{i}]", 4) for i, r in enumerate(rot)])
        if self.interpolation not in INTERPOLATIONS:
            raise InputError(
                f"keyframes.interpolation: must be one of {', '.join(INTERPOLATIONS)}; got {self.interpolation!r}"
            )
        object.__setattr__(self, "times", tuple(t.tolist()))
        object.__setattr__(self, "positions", tuple(tuple(r) for r in p.tolist()))
        object.__setattr__(self, "rotations", tuple(tuple(r) for r in q.tolist()))
        p.setflags(write=False)
        q.setflags(write=False)
        object.__setattr__(self, "_p", p)
        object.__setattr__(self, "_q", q)
        if self.interpolation == "cubic" and len(t) >= 2:
            object.__setattr__(self, "_curve", natural_cubic(t, p))

    def _segment(self, t: float) -> tuple[int, float]:
        """(k, u): t lies at fraction u in [0, 1] of [times[k], times[k+1]] (clamped to the keyframes)."""
        ts = self.times
        tc = min(max(t, ts[0]), ts[-1])
        k = int(np.clip(np.searchsorted(ts, tc, side="right") - 1, 0, len(ts) - 2))
        return k, (tc - ts[k]) / (ts[k + 1] - ts[k])

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) mm, rotation matrix (3, 3)) at time t (s)."""
        p, q = self._p, self._q
        if len(self.times) == 1:
            return p[0], matrix(q[0])
        k, u = self._segment(float(t))
        if self._curve is not None:
            tc = min(max(float(t), self.times[0]), self.times[-1])
            pos = self._curve(tc)
        else:
            pos = p[k] + u * (p[k + 1] - p[k])
        return pos, matrix(slerp(q[k], q[k + 1], u))

    def speed_bound(self, t0: float, t1: float) -> tuple[float, float]:
        """(max |dp/dt| mm/s, max angular speed rad/s) over [t0, t1] (s); zero where the pose holds."""
        ts = self.times
        a, b = max(t0, ts[0]), min(t1, ts[-1])
        if len(ts) == 1 or a >= b:  # the pose holds: a single instant of motion moves nothing
            return 0.0, 0.0
        p, q = self._p, self._q
        v = w = 0.0
        for k in range(len(ts) - 1):
            lo, hi = max(a, ts[k]), min(b, ts[k + 1])
            if lo >= hi:
                continue
            dt = ts[k + 1] - ts[k]
            w = max(w, angle(q[k], q[k + 1]) / dt)
            if self._curve is None:
                v = max(v, float(np.linalg.norm(p[k + 1] - p[k])) / dt)
            else:
                # the velocity is continuous at the knots, so each end may be read from either piece
                v = max(v, float(np.linalg.norm(_quad_abs_max(self._curve, lo, hi))))
        return v, w


@dataclass(frozen=True)
class StraightLine:
    """The straight-line profiles of `crtraj.world.obstacle.Obstacle`, no rotation:
    ``p(t) = start + s(t) (to - start)`` with s from `profile` ("linear", "sin", "cos") and `duration` D."""

    start: tuple[float, float, float]
    to: tuple[float, float, float]
    duration: float = 1.0
    profile: str = "linear"

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", check_vec(self.start, "motion.start", 3, limit=MAX_LENGTH))
        object.__setattr__(self, "to", check_vec(self.to, "motion.to", 3, limit=MAX_LENGTH))
        d = check_float(float(self.duration), "motion.duration", ge=MIN_DURATION, limit=MAX_TIME)
        object.__setattr__(self, "duration", d)
        if self.profile not in PROFILES:
            raise InputError(f"motion.profile: must be one of {', '.join(PROFILES)}; got {self.profile!r}")

    def _progress(self, t: float) -> float:
        x = t / self.duration
        if self.profile == "linear":
            return min(max(x, 0.0), 1.0)
        if self.profile == "sin":
            return math.sin(0.5 * math.pi * x)
        return 0.5 * (1.0 - math.cos(math.pi * x))

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,) mm, identity rotation) at time t (s)."""
        a, b = np.asarray(self.start), np.asarray(self.to)
        return a + self._progress(float(t)) * (b - a), np.eye(3)

    def speed_bound(self, t0: float, t1: float) -> tuple[float, float]:
        """(max speed mm/s, 0): |d|/D while a linear profile moves, |d| pi / (2 D) for sin and cos."""
        dist = float(np.linalg.norm(np.asarray(self.to) - np.asarray(self.start)))
        if self.profile == "linear":
            moving = t0 <= self.duration and t1 >= 0.0
            return (dist / self.duration if moving else 0.0), 0.0
        return dist * math.pi / (2.0 * self.duration), 0.0


@dataclass(frozen=True)
class Breathing:
    """Uniform scale ``s(t) = 1 + amplitude sin(omega t + phase)`` of a shape about its own origin;
    |amplitude| < 1 so that the scale stays positive. omega rad/s, phase rad."""

    amplitude: float = 0.0
    omega: float = 0.0
    phase: float = 0.0

    def __post_init__(self) -> None:
        a = check_float(float(self.amplitude), "breathing.amplitude")
        if abs(a) >= 1.0:
            raise InputError(f"breathing.amplitude: must be in (-1, 1) so the scale stays > 0, got {a:g}")
        object.__setattr__(self, "amplitude", a)
        object.__setattr__(self, "omega", check_float(float(self.omega), "breathing.omega", limit=MAX_OMEGA))
        object.__setattr__(self, "phase", check_float(float(self.phase), "breathing.phase", limit=1e3))

    def scale(self, t: float) -> float:
        """s(t), dimensionless."""
        return 1.0 + self.amplitude * math.sin(self.omega * t + self.phase)

    def scale_max(self, t0: float, t1: float) -> float:
        """The exact max of s over [t0, t1]."""
        lo, hi = sin_range(np.array(self.omega * t0 + self.phase), np.array(self.omega * t1 + self.phase))
        a = self.amplitude
        return 1.0 + float(a * hi if a >= 0.0 else a * lo)

    @property
    def rate_max(self) -> float:
        """max_t |ds/dt| = |amplitude omega| (1/s)."""
        return abs(self.amplitude * self.omega)
