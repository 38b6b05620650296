"""Obstacles given as data: a point cloud (balls of one radius) and a triangle mesh (its surface), in mm.

Both are a set of points in the shape's own frame with a radius, and their distance is the distance to the
union of the balls, from a KD-tree (`scipy.spatial.cKDTree`):

- `PointCloud(points, radius)`: every point is a ball of `radius` (a depth camera's voxels, say). The
  distance ``min_k |y - p_k| - radius`` is exact for that union of balls.
- `Mesh(triangles, spacing)`: the mesh's surface (its triangles; a closed mesh's inside is not part of it).
  Each triangle is split into n^2 similar triangles with edges at most `spacing` mm, and their corners are
  the samples. Every point of a triangle lies within ``l / sqrt(3)`` of a corner of a triangle with longest
  edge l (the circumradius of an acute triangle, ``l / (2 sin A)`` with A >= 60 deg opposite the longest
  edge, or half the longest edge when the circumcentre is outside), so the surface lies within
  ``cover = max sub-edge / sqrt(3)`` of the samples, and ``min_k |y - p_k| - cover`` is at most the distance
  to the surface and at least that distance minus `cover`: a conservative distance with a stated error.

The NLPs and the checker's chord bound take either as a conservative distance grid (`crtraj.world.geometry._grid`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_array, check_float
from crtraj.core.lazy import lazy_module
from crtraj.world.geometry._shapes import Distance, Pose, _pose_of, _unit_or, _where

# SciPy's spatial package costs about 0.5 s to import; only a mesh or a point cloud needs its KD-tree
spatial = lazy_module("scipy.spatial")

# Most points a cloud (or samples a mesh) may have: a KD-tree of 10^6 points is about 50 MB.
MAX_POINTS = 1_000_000
# Most triangles a mesh file may hold.
MAX_TRIANGLES = 500_000


def _nearest(tree: spatial.cKDTree, pts: np.ndarray, y: np.ndarray, s: float) -> Distance:
    """(distance to the nearest point of s * pts, unit direction from it) for points y (N, 3)."""
    dist, idx = tree.query(y / s)
    v = y - s * pts[idx]
    return s * dist, _unit_or(v, np.array([0.0, 0.0, 1.0]))


@dataclass(frozen=True, eq=False)  # equal when the same object: arrays have no single truth value
class PointCloud:
    """Balls of `radius` (mm) about `points` (K, 3) mm of the shape's frame (module docstring)."""

    points: np.ndarray
    radius: float
    pose: Pose = Pose()  # noqa: RUF009 - a frozen value, as the primitives' default pose
    name: str = ""
    source: str = ""  # the file it was read from (for messages and the result), "" when built in code
    kind: ClassVar[str] = "points"
    _tree: spatial.cKDTree = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        w = _where(self.kind, self.name)
        p = check_array(self.points, f"{w}.points", (None, 3), limit=MAX_LENGTH)
        if len(p) == 0:
            raise InputError(f"{w}.points: the cloud is empty{_from(self.source)}; give at least one point")
        if len(p) > MAX_POINTS:
            raise InputError(f"{w}.points: {len(p)} points{_from(self.source)}, more than {MAX_POINTS}; thin it")
        r = self.radius.item() if isinstance(self.radius, np.generic) else self.radius
        object.__setattr__(self, "radius", check_float(r, f"{w}.radius", gt=0.0, limit=MAX_LENGTH))
        object.__setattr__(self, "pose", _pose_of(self.pose, w))
        p = np.ascontiguousarray(p)
        p.setflags(write=False)
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "_tree", spatial.cKDTree(p))

    @property
    def ball(self) -> float:
        """The radius (mm) of each point's ball at scale 1."""
        return self.radius

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the shape from its frame origin, at scale 1."""
        return float(np.max(np.linalg.norm(self.points, axis=1))) + self.radius

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """Signed distance (N,) mm to the union of balls and unit gradient (N, 3), points y in the frame."""
        d, g = _nearest(self._tree, self.points, y, s)
        return d - s * self.radius, g


def _from(source: str) -> str:
    return f" (from {source})" if source else ""


def surface_samples(tri: np.ndarray, spacing: float) -> tuple[np.ndarray, float]:
    """(samples (K, 3) mm, cover mm): corners of each triangle's n^2 similar sub-triangles, n chosen so
    that every sub-edge is at most `spacing`; every surface point is within cover of a sample."""
    edges = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2)  # (T, 3)
    longest = edges.max(axis=1)
    n = np.maximum(1, np.ceil(longest / spacing)).astype(int)
    cover = float(np.max(longest / n)) / math.sqrt(3.0)
    out = []
    for m in np.unique(n):
        ij = np.array([(i, j) for i in range(m + 1) for j in range(m + 1 - i)], dtype=float) / m  # (B, 2)
        sel = tri[n == m]
        a, b, c = sel[:, 0], sel[:, 1], sel[:, 2]
        pts = a[:, None] + ij[None, :, :1] * (b - a)[:, None] + ij[None, :, 1:] * (c - a)[:, None]
        out.append(pts.reshape(-1, 3))
    samples = np.unique(np.round(np.concatenate(out), 9), axis=0)
    return samples, cover


@dataclass(frozen=True, eq=False)  # equal when the same object: arrays have no single truth value
class Mesh:
    """The surface of a triangle mesh, `triangles` (T, 3, 3) mm in the shape's frame, sampled every
    `spacing` mm (module docstring: its distance is conservative by at most `cover` mm)."""

    triangles: np.ndarray
    spacing: float = 4.0
    pose: Pose = Pose()  # noqa: RUF009 - a frozen value, as the primitives' default pose
    name: str = ""
    source: str = ""
    kind: ClassVar[str] = "mesh"
    samples: np.ndarray = field(init=False, repr=False, compare=False, default=None)
    cover_radius: float = field(init=False, repr=False, compare=False, default=0.0)
    _tree: spatial.cKDTree = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self) -> None:
        w = _where(self.kind, self.name)
        tri = np.asarray(self.triangles, dtype=float)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
            raise InputError(f"{w}.file: no triangles{_from(self.source)}; give a mesh (STL, OBJ or PLY)")
        if len(tri) > MAX_TRIANGLES:
            raise InputError(f"{w}.file: {len(tri)} triangles{_from(self.source)}, more than {MAX_TRIANGLES}")
        tri = check_array(tri.reshape(-1, 3), f"{w}.triangles", (None, 3), limit=MAX_LENGTH).reshape(-1, 3, 3)
        sp = self.spacing.item() if isinstance(self.spacing, np.generic) else self.spacing
        sp = check_float(sp, f"{w}.spacing", gt=0.0, limit=MAX_LENGTH)
        samples, cover = surface_samples(tri, sp)
        if len(samples) > MAX_POINTS:
            raise InputError(f"{w}.spacing: {sp:g} mm gives {len(samples)} samples, more than {MAX_POINTS}; raise it")
        tri.setflags(write=False)
        samples.setflags(write=False)
        object.__setattr__(self, "triangles", tri)
        object.__setattr__(self, "spacing", sp)
        object.__setattr__(self, "pose", _pose_of(self.pose, w))
        object.__setattr__(self, "samples", samples)
        object.__setattr__(self, "cover_radius", cover)
        object.__setattr__(self, "_tree", spatial.cKDTree(samples))

    @property
    def ball(self) -> float:
        """The covering radius (mm) of the samples at scale 1: the distance's largest error."""
        return self.cover_radius

    @property
    def points(self) -> np.ndarray:
        """The surface samples (K, 3) mm in the shape's frame."""
        return self.samples

    @property
    def local_radius(self) -> float:
        """Largest distance (mm) of a point of the surface from its frame origin, at scale 1."""
        return float(np.max(np.linalg.norm(self.triangles.reshape(-1, 3), axis=1)))

    def local_distance(self, y: np.ndarray, s: float = 1.0) -> Distance:
        """A lower bound (N,) mm of the distance to the surface (within `cover_radius` of it) and the unit
        direction (N, 3) from the nearest sample, for points y (N, 3) in the shape's frame."""
        d, g = _nearest(self._tree, self.samples, y, s)
        return d - s * self.cover_radius, g


POINT_SETS = (PointCloud, Mesh)
