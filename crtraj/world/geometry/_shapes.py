"""Obstacle primitives as plain data, each with a pose, and their closed-form signed distances (mm).

Every shape is a frozen dataclass. Its geometry is given in its own frame; `pose` places that frame in
the world (or in the frame of a motion, `crtraj.world.geometry.MovingShape`). The signed distance is
positive outside, zero on the surface and minus the depth inside. Each shape's `local_distance(y, s)`
takes points ``y`` (N, 3) in its own frame and a uniform scale ``s`` (the shape grown about its frame
origin) and returns the distance (N,) and its gradient (N, 3), a unit vector, in that frame.

Where a distance is not differentiable the gradient returned is one of its one-sided gradients (a
subgradient direction), chosen by the rule stated in the shape's docstring, so that it is always a unit
vector that points out of the shape (never NaN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_float, check_vec
from crtraj.world.geometry._rotation import IDENTITY, check_unit, matrix

Distance = tuple[np.ndarray, np.ndarray]


def _where(kind: str, name: str) -> str:
    return f"{kind} {name!r}" if name else kind


def _length(v: Any, name: str) -> float:
    """One extent (mm): finite and > 0."""
    if isinstance(v, np.generic):
        v = v.item()
    return check_float(v, name, gt=0.0, limit=MAX_LENGTH)


def _unit_or(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Rows of v (N, 3) normalised; rows of zero length become `fallback` (3,)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    safe = np.where(n > 0.0, n, 1.0)
    return np.where(n > 0.0, v / safe, fallback)


def _sign(v: np.ndarray) -> np.ndarray:
    """sign with sign(0) = +1 (a side must be chosen on a symmetry plane)."""
    return np.where(v < 0.0, -1.0, 1.0)


@dataclass(frozen=True)
class Pose:
    """A rigid placement: ``x = position + R(rotation) y`` for a point y of the shape's frame.

    position: (3,) mm. rotation: unit quaternion (w, x, y, z), checked to be unit within
    `crtraj.world.geometry._rotation.QUAT_TOL` and then normalised.
    """

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = IDENTITY
    matrix: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", check_vec(self.position, "pose.position", 3, limit=MAX_LENGTH))
        object.__setattr__(self, "rotation", check_unit(self.rotation, "pose.rotation", 4))
        m = matrix(self.rotation)
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)


def _pose_of(pose: Any, where: str) -> Pose:
    if not isinstance(pose, Pose):
        raise InputError(f"{where}.pose: expected a Pose, got {type(pose).__name__}")
    return pose


@dataclass(frozen=True)
class Sphere:
    """A ball of `radius` (mm) about its frame origin.

    Smooth everywhere except at the centre, where the gradient returned is +z of the shape's frame.
    """

    radius: float
    pose: Pose = Pose()
    name: str = ""
    kind: ClassVar[str] = "sphere"

    def __post_init__(self) -> None:
        w = _where(self.kind, self.name)
        object.__setattr__(self, "radius", _length(self.radius, f"{w}.radius"))
        object.__setattr__(self, "pose", _pose_of(self.pose, w))

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the shape from its frame origin, at scale 1."""
        return self.radius

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm and unit gradient (N, 3) of points y (N, 3) in the shape's frame."""
        g = _unit_or(y, np.array([0.0, 0.0, 1.0]))
        return np.linalg.norm(y, axis=1) - s * self.radius, g


def _box_like(q: np.ndarray, dirs: np.ndarray) -> Distance:
    """Distance of a box in the coordinates q_i = |y_i| - h_i (N, k), with dirs (N, k, 3) the unit outward
    direction of each q_i: |max(q, 0)| + min(max_i q_i, 0); gradient as documented on `Box`."""
    qo = np.maximum(q, 0.0)
    out = np.linalg.norm(qo, axis=1)
    m = np.max(q, axis=1)
    d = out + np.minimum(m, 0.0)
    outside = out > 0.0
    w = np.where(outside[:, None], qo / np.where(outside, out, 1.0)[:, None], 0.0)
    # inside (or on the surface): the face of the largest q_i, the lowest index among ties
    k = np.argmax(q, axis=1)
    w[~outside, k[~outside]] = 1.0
    return d, np.einsum("nk,nkc->nc", w, dirs)


@dataclass(frozen=True)
class Box:
    """A box of `half_extents` (3,) mm along the axes of its frame, centred on its origin.

    Outside the box the distance is continuously differentiable (its gradient points from the nearest
    surface point). It is not differentiable on the surface's edges and corners (the gradient jumps from
    the outside value to a face normal) and inside on the medial planes, where two faces are equally near;
    there the gradient returned is the outward normal of the nearest face, the lowest axis among ties, and
    on a symmetry plane y_i = 0 the + side.
    """

    half_extents: tuple[float, float, float]
    pose: Pose = Pose()
    name: str = ""
    kind: ClassVar[str] = "box"

    def __post_init__(self) -> None:
        w = _where(self.kind, self.name)
        h = check_vec(self.half_extents, f"{w}.half_extents", 3, limit=MAX_LENGTH)
        for i, v in enumerate(h):
            if not v > 0.0:
                raise InputError(f"{w}.half_extents[{i}]: must be > 0 mm, got {v:g}")
        object.__setattr__(self, "half_extents", h)
        object.__setattr__(self, "pose", _pose_of(self.pose, w))

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the shape from its frame origin, at scale 1."""
        return math.sqrt(sum(v * v for v in self.half_extents))

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm and unit gradient (N, 3) of points y (N, 3) in the shape's frame."""
        q = np.abs(y) - s * np.asarray(self.half_extents)
        dirs = np.eye(3)[None, :, :] * _sign(y)[:, :, None]
        return _box_like(q, dirs)


def _axial(kind: str, obj: Any) -> None:
    w = _where(kind, obj.name)
    object.__setattr__(obj, "radius", _length(obj.radius, f"{w}.radius"))
    object.__setattr__(obj, "length", _length(obj.length, f"{w}.length"))
    object.__setattr__(obj, "pose", _pose_of(obj.pose, w))


@dataclass(frozen=True)
class Capsule:
    """All points within `radius` (mm) of the segment z in [-length/2, length/2] of its frame's z axis;
    `length` (mm) is the segment's, so the capsule is length + 2 radius long overall.

    Outside it is continuously differentiable. Inside it is not differentiable on the segment itself (the
    axis), where the gradient returned is +x of the shape's frame.
    """

    radius: float
    length: float
    pose: Pose = Pose()
    name: str = ""
    kind: ClassVar[str] = "capsule"

    def __post_init__(self) -> None:
        _axial(self.kind, self)

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the shape from its frame origin, at scale 1."""
        return 0.5 * self.length + self.radius

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm and unit gradient (N, 3) of points y (N, 3) in the shape's frame."""
        half = 0.5 * s * self.length
        v = y.copy()
        v[:, 2] -= np.clip(y[:, 2], -half, half)
        return np.linalg.norm(v, axis=1) - s * self.radius, _unit_or(v, np.array([1.0, 0.0, 0.0]))


@dataclass(frozen=True)
class Cylinder:
    """A solid circular cylinder of `radius` (mm) about its frame's z axis, z in [-length/2, length/2] mm,
    with flat caps.

    Outside it is continuously differentiable. It is not differentiable on the rims (where a cap meets
    the side), inside where the side and a cap are equally near (a cone-shaped medial surface) and on the
    axis where the side is the nearest. The gradient returned there is the nearest feature's outward
    normal, the side among ties, +x of the shape's frame as the radial direction on the axis, and +z
    on the mid-plane z = 0.
    """

    radius: float
    length: float
    pose: Pose = Pose()
    name: str = ""
    kind: ClassVar[str] = "cylinder"

    def __post_init__(self) -> None:
        _axial(self.kind, self)

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the shape from its frame origin, at scale 1."""
        return math.hypot(self.radius, 0.5 * self.length)

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm and unit gradient (N, 3) of points y (N, 3) in the shape's frame."""
        radial = y.copy()
        radial[:, 2] = 0.0
        rho = np.linalg.norm(radial, axis=1)
        q = np.stack([rho - s * self.radius, np.abs(y[:, 2]) - 0.5 * s * self.length], axis=1)
        axial = np.zeros_like(y)
        axial[:, 2] = _sign(y[:, 2])
        dirs = np.stack([_unit_or(radial, np.array([1.0, 0.0, 0.0])), axial], axis=1)
        return _box_like(q, dirs)


@dataclass(frozen=True)
class HalfSpace:
    """The half space ``normal . y <= offset`` of its frame (a floor, a wall); `normal` is the unit
    vector out of the obstacle into free space, `offset` in mm. The distance ``normal . y - s offset``
    is linear, so smooth everywhere, with the constant gradient `normal`.
    """

    normal: tuple[float, float, float]
    offset: float = 0.0
    pose: Pose = Pose()
    name: str = ""
    kind: ClassVar[str] = "halfspace"

    def __post_init__(self) -> None:
        w = _where(self.kind, self.name)
        object.__setattr__(self, "normal", check_unit(self.normal, f"{w}.normal", 3))
        off = self.offset.item() if isinstance(self.offset, np.generic) else self.offset
        object.__setattr__(self, "offset", check_float(off, f"{w}.offset", limit=MAX_LENGTH))
        object.__setattr__(self, "pose", _pose_of(self.pose, w))

    @property
    def local_radius(self) -> float:
        """Unbounded: a half space has no bounding sphere (its sweep bound is point-wise instead)."""
        return math.inf

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm and unit gradient (N, 3) of points y (N, 3) in the shape's frame."""
        n = np.asarray(self.normal)
        return y @ n - s * self.offset, np.broadcast_to(n, y.shape).copy()


Shape = Sphere | Box | Capsule | Cylinder | HalfSpace
SHAPES = (Sphere, Box, Capsule, Cylinder, HalfSpace)
