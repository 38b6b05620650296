"""One distance interface for every obstacle shape, and a shape that moves and breathes.

`DistanceField` is what consumers call: the signed distance (mm) and its gradient from body points
(N, 3) to an obstacle at time t, and a conservative lower bound of the signed distance over [t0, t1].
`MovingShape` implements it for every primitive of `crtraj.world.geometry._shapes`.

The sweep bound (docs/concepts/shapes.md derives it). A moving shape occupies
``X(t) = p(t) + R(t) (c + Q s(t) Y)`` (motion p, R; the shape's pose c, Q; breathing s; the shape Y at
scale 1, within radius r of its origin). A point of it moves at speed at most

    L = v + w (|c| + s_max r) + s_rate r                   (mm/s)

over [t0, t1], with v, w the motion's linear and angular speed bounds and s_max, s_rate the scale's
largest value and rate there. The signed distance from a fixed point to X(t) changes at most as fast
as the surface moves, so it is L-Lipschitz in t, and over [t0, t1] with midpoint tm and h = (t1-t0)/2

    d(x, t) >= d(x, tm) - h L.

A half space is unbounded (r infinite), so no speed bounds all of its points; its distance is bounded
directly. With ``d(x, t) = n(t) . (x - o(t)) - s(t) offset`` and ``o = p + R c``, the terms in c cancel
(the plane turns rigidly about p): ``d(x, t) = n(t) . (x - p(t)) - n(t) . R(t) c - s(t) offset`` where
``n . R c = (Q n) . c`` is constant. Hence, with tau = |t - tm|,
``d(x, t) - d(x, tm) = (n(t) - n(tm)) . (x - p(tm)) - n(t) . (p(t) - p(tm)) - (s(t) - s(tm)) offset``, and
``|n(t) - n(tm)| <= min(2, w tau)`` (a chord of the unit sphere is at most its arc and at most 2),
``|p(t) - p(tm)| <= v tau``, ``|s(t) - s(tm)| <= s_rate tau``:
``d(x, t) >= d(x, tm) - min(2, w h) |x - p(tm)| - v h - s_rate h |offset|``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, check_array, check_float
from crtraj.world.geometry._motion import Breathing, Fixed, Motion, StraightLine
from crtraj.world.geometry._points import POINT_SETS, Mesh, PointCloud
from crtraj.world.geometry._shapes import SHAPES, HalfSpace, Shape, Sphere
from crtraj.world.obstacle import Obstacle

# every shape a `MovingShape` moves: the primitives and the point sets (clouds, meshes)
ALL_SHAPES = SHAPES + POINT_SETS


@runtime_checkable
class DistanceField(Protocol):
    """Signed distance (mm, > 0 outside) from body points to one obstacle, over time (s)."""

    def distance(self, points: Any, t: float) -> np.ndarray:
        """(N,) signed distances of points (N, 3) mm at time t s."""
        ...

    def distance_and_gradient(self, points: Any, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(N,) signed distances and (N, 3) unit gradients w.r.t. the points, at time t s."""
        ...

    def lower_bound(self, points: Any, t0: float, t1: float) -> np.ndarray:
        """(N,) values at most the signed distance of each point at every time in [t0, t1] s."""
        ...


def _time(v: Any, name: str) -> float:
    if isinstance(v, np.generic):
        v = v.item()
    return check_float(v, name, limit=MAX_TIME)


@dataclass(frozen=True)
class MovingShape:
    """A primitive `shape` moved by `motion` (`Fixed` by default) and scaled by `breathing` (None: s = 1)."""

    shape: Shape | PointCloud | Mesh
    motion: Motion = field(default_factory=Fixed)
    breathing: Breathing | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.shape, ALL_SHAPES):
            raise InputError(f"shape: expected one of {', '.join(c.kind for c in ALL_SHAPES)}, got {self.shape!r}")
        if not isinstance(self.motion, Motion):
            raise InputError(f"motion: expected a motion (Fixed, Keyframes, StraightLine), got {self.motion!r}")
        if self.breathing is not None and not isinstance(self.breathing, Breathing):
            raise InputError(f"breathing: expected a Breathing or None, got {self.breathing!r}")

    @classmethod
    def from_obstacle(cls, ob: Obstacle) -> MovingShape:
        """The sphere obstacle `ob` as a moving shape: radius A + B sin(...) = A (1 + (B/A) sin(...))."""
        if not ob.radius > 0.0:
            where = f"obstacle {ob.name!r}" if ob.name else "obstacle"
            raise InputError(f"{where}.radius: a shape needs a mean radius > 0 mm, got {ob.radius:g}")
        to = ob.center if ob.to is None else ob.to
        motion = StraightLine(ob.center, to, ob.duration, ob.profile)
        breathing = Breathing(ob.amplitude / ob.radius, ob.omega, ob.phase) if ob.amplitude else None
        return cls(Sphere(ob.radius, name=ob.name), motion, breathing)

    @property
    def static(self) -> bool:
        """True when the shape neither moves nor breathes (its distance does not depend on time)."""
        return isinstance(self.motion, Fixed) and (self.breathing is None or self.breathing.amplitude == 0.0)

    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(origin (3,) mm, rotation (3, 3), scale) of the shape's own frame at time t s."""
        p, rm = self.motion.pose(_time(t, "t"))
        pose = self.shape.pose
        s = 1.0 if self.breathing is None else self.breathing.scale(t)
        return p + rm @ np.asarray(pose.position), rm @ pose.matrix, s

    def distance_and_gradient(self, points: Any, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(N,) signed distances (mm) and (N, 3) unit gradients of points (N, 3) mm at time t s."""
        x = check_array(points, "points", (None, 3), limit=MAX_LENGTH)
        o, r, s = self.frame(t)
        d, g = self.shape.local_distance((x - o) @ r, s)
        return d, g @ r.T

    def distance(self, points: Any, t: float) -> np.ndarray:
        """(N,) signed distances (mm) of points (N, 3) mm at time t s."""
        return self.distance_and_gradient(points, t)[0]

    def _speeds(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """(v, w, s_max, s_rate) over [t0, t1] (module docstring)."""
        v, w = self.motion.speed_bound(t0, t1)
        if self.breathing is None:
            return v, w, 1.0, 0.0
        return v, w, self.breathing.scale_max(t0, t1), self.breathing.rate_max

    def surface_speed(self, t0: float, t1: float) -> float:
        """L (mm/s): no point of the shape moves faster over [t0, t1]; infinite for a half space."""
        v, w, s_max, s_rate = self._speeds(t0, t1)
        r = self.shape.local_radius
        if math.isinf(r):
            return math.inf
        c = float(np.linalg.norm(self.shape.pose.position))
        return v + w * (c + s_max * r) + s_rate * r

    def lower_bound(self, points: Any, t0: float, t1: float) -> np.ndarray:
        """(N,) lower bounds (mm) of the signed distance of points (N, 3) over [t0, t1] s (module docstring)."""
        t0, t1 = _time(t0, "t0"), _time(t1, "t1")
        if t1 < t0:
            raise InputError(f"t1: must be >= t0 = {t0:g} s, got {t1:g}")
        tm, h = 0.5 * (t0 + t1), 0.5 * (t1 - t0)
        x = check_array(points, "points", (None, 3), limit=MAX_LENGTH)
        d = self.distance(x, tm)
        if h == 0.0:
            return d
        if not isinstance(self.shape, HalfSpace):
            return d - h * self.surface_speed(t0, t1)
        v, w, _, s_rate = self._speeds(t0, t1)
        p = self.motion.pose(tm)[0]
        turn = min(2.0, w * h) * np.linalg.norm(x - p, axis=1)
        return d - turn - h * (v + s_rate * abs(self.shape.offset))
