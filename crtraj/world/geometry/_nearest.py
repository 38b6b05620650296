"""The nearest surface point of a moving shape to each of many points (mm, s): what the view's closest-approach
line is drawn to.

- The primitives (sphere, box, capsule, cylinder, half space): their distances are exact signed distances
  (`crtraj.world.geometry._shapes`), whose gradient g at y points from the nearest surface point, so the nearest
  surface point is ``y - d(y) g(y)`` (inside as well: d < 0 steps out to the nearest face).
- A point cloud (balls of one radius): the nearest ball's surface point, ``y - d g`` with the distance to the
  nearest point minus the radius and g from that point (exact for the union of balls).
- A mesh: the closest point on its triangles (`closest_point_on_triangle`), over every triangle that could be
  nearest: the nearest surface sample (`Mesh.samples`, on the surface) bounds the distance above, and a triangle
  whose bounding ball (about its centroid) is farther cannot hold the nearest point.

The distances returned are the true ones (unsigned for a mesh, whose inside is not part of it), not the planner's
conservative bounds.
"""

from __future__ import annotations

import numpy as np

from crtraj.core.fields import MAX_LENGTH, check_array
from crtraj.world.geometry._distance import MovingShape
from crtraj.world.geometry._exact import _pairwise, closest_point_on_triangle
from crtraj.world.geometry._points import Mesh

_CHUNK = 512  # points per block of the mesh's pairwise centroid distances
_SLACK = 1e-3  # mm: candidates kept within this of the bound (what `_pairwise` may be off by)


def nearest_surface_points(ms: MovingShape, points: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(distances (N,) mm, nearest surface points (N, 3) mm, world frame) of world points (N, 3) to the shape at
    time t (s); the distance is signed (negative inside) except for a mesh (module docstring)."""
    x = check_array(points, "points", (None, 3), limit=MAX_LENGTH)
    o, r, s = ms.frame(t)
    y = (x - o) @ r
    if isinstance(ms.shape, Mesh):
        d, q = _mesh_nearest(ms.shape, y, s)
    else:
        d, g = ms.shape.local_distance(y, s)
        q = y - d[:, None] * g
    return d, o + q @ r.T


def _mesh_nearest(mesh: Mesh, y: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """(distances (N,), nearest points (N, 3)) of points y (N, 3) of the mesh's frame to its triangles at scale s."""
    tri = s * mesh.triangles
    centres = tri.mean(axis=1)
    rad = np.linalg.norm(tri - centres[:, None, :], axis=2).max(axis=1)
    samples = s * mesh.samples
    d_out, q_out = np.empty(len(y)), np.empty((len(y), 3))
    for i in range(0, len(y), _CHUNK):
        x = y[i : i + _CHUNK]
        upper = np.linalg.norm(x - samples[mesh._tree.query(x / s)[1]], axis=1)
        dc = _pairwise(x, centres)
        pi, ti = np.nonzero(dc - rad[None, :] <= upper[:, None] + _SLACK)
        q = closest_point_on_triangle(x[pi], tri[ti, 0], tri[ti, 1], tri[ti, 2])
        d = np.linalg.norm(x[pi] - q, axis=1)
        order = np.lexsort((d, pi))  # by point, nearest first
        first = order[np.flatnonzero(np.r_[True, np.diff(pi[order]) != 0])]
        d_out[i + pi[first]] = d[first]
        q_out[i + pi[first]] = q[first]
    return d_out, q_out
