"""Distances for verification, computed apart from the planner's (mm): the verifiers' judge.

The planner asks `MovingShape.distance` (closed forms, KD-trees over surface samples). A verifier must not
trust that code, so here every obstacle surface becomes triangles or points and the distance is found by
brute force:

- box: its 12 triangles (built from its 8 corners), point-to-triangle distances in numpy;
- cylinder: in the half plane of (distance from the axis, height) its section is a rectangle, so the
  distance is the smallest distance to the rectangle's side and caps as 2-D segments;
- capsule, sphere: the distance to the axis segment (a point) minus the radius, their definition;
- half space: ``n . y - offset``, its definition;
- mesh: point-to-triangle distances to every triangle of the file (exact);
- point cloud: the smallest distance to every point, minus the radius (exact).

Inside a box or a cylinder the distance is the negated depth to the same triangles or segments (the
inside test is the solid's inequalities). `exact_distance(shape, points, t)` places the points in the shape's frame at
time t by its motion (the only part shared with the planner: the motion is data).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.world.geometry._distance import MovingShape
from crtraj.world.geometry._points import Mesh, PointCloud
from crtraj.world.geometry._shapes import Box, Capsule, Cylinder, HalfSpace, Sphere

_CHUNK = 4096  # points per brute-force block


def _closest_on_triangle(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Distances (...) from points x to triangles a, b, c (all broadcast to (..., 3))."""
    return np.linalg.norm(x - closest_point_on_triangle(x, a, b, c), axis=-1)


def closest_point_on_triangle(x: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The points (..., 3) of triangles a, b, c nearest to points x (all broadcast to (..., 3)): Ericson's
    closest point, by region (vertex, edge or face)."""
    ab, ac, ap = b - a, c - a, x - a
    d1, d2 = np.einsum("...k,...k->...", ab, ap), np.einsum("...k,...k->...", ac, ap)
    bp, cp = x - b, x - c
    d3, d4 = np.einsum("...k,...k->...", ab, bp), np.einsum("...k,...k->...", ac, bp)
    d5, d6 = np.einsum("...k,...k->...", ab, cp), np.einsum("...k,...k->...", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v_face, w_face = vb / denom, vc / denom
        v_ab = d1 / (d1 - d3)
        w_ac = d2 / (d2 - d6)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # face by default, then the regions in the reverse of Ericson's order so that the first test wins
    q = a + v_face[..., None] * ab + w_face[..., None] * ac
    shape = q.shape
    regions = [
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + w_bc[..., None] * (c - b)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + w_ac[..., None] * ac),
        ((d6 >= 0) & (d5 <= d6), np.broadcast_to(c, shape)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + v_ab[..., None] * ab),
        ((d3 >= 0) & (d4 <= d3), np.broadcast_to(b, shape)),
        ((d1 <= 0) & (d2 <= 0), np.broadcast_to(a, shape)),
    ]
    for mask, point in regions:
        q = np.where(mask[..., None], point, q)
    return q


def point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N, T) distances (mm) from points p (N, 3) to triangles tri (T, 3, 3)."""
    return _closest_on_triangle(p[:, None, :], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])


def _min_to_triangles(y: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) distance from each point to the nearest triangle: every triangle whose bounding sphere (about its
    centroid) could hold a point nearer than the nearest vertex is measured; the others cannot be nearest."""
    centre = tri.mean(axis=1)
    rad = np.linalg.norm(tri - centre[:, None, :], axis=2).max(axis=1)
    verts = tri.reshape(-1, 3)
    out = np.empty(len(y))
    step = max(1, _CHUNK * 16 // max(1, len(tri)))
    for i in range(0, len(y), step):
        x = y[i : i + step]
        upper = np.full(len(x), np.inf)
        for j in range(0, len(verts), _CHUNK):
            near = np.linalg.norm(x[:, None] - verts[None, j : j + _CHUNK], axis=-1).min(axis=1)
            np.minimum(upper, near, out=upper)
        lower = np.linalg.norm(x[:, None] - centre[None], axis=-1) - rad[None]
        pi, ti = np.nonzero(lower <= upper[:, None])
        d = _closest_on_triangle(x[pi], tri[ti, 0], tri[ti, 1], tri[ti, 2])
        best = upper.copy()
        np.minimum.at(best, pi, d)
        out[i : i + step] = best
    return out


def box_triangles(h: np.ndarray) -> np.ndarray:
    """The 12 triangles (12, 3, 3) of the box [-h, h]."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * h
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    tris = [[corners[q[0]], corners[q[1]], corners[q[2]]] for q in quads]
    tris += [[corners[q[0]], corners[q[2]], corners[q[3]]] for q in quads]
    return np.array(tris)


def _segment_2d(q: np.ndarray, a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    """(N,) distances from 2-D points q (N, 2) to the segment a-b."""
    a_, ab = np.asarray(a), np.asarray(b) - np.asarray(a)
    u = np.clip(((q - a_) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(q - a_ - u[:, None] * ab, axis=1)


def _cylinder_exact(y: np.ndarray, r: float, half: float) -> np.ndarray:
    """Signed distance to the solid cylinder of radius r about z, |z| <= half, via its 2-D section."""
    q = np.stack([np.hypot(y[:, 0], y[:, 1]), y[:, 2]], axis=1)
    d = np.minimum(_segment_2d(q, (r, -half), (r, half)), _segment_2d(q, (0.0, half), (r, half)))
    d = np.minimum(d, _segment_2d(q, (0.0, -half), (r, -half)))
    inside = (q[:, 0] <= r) & (np.abs(q[:, 1]) <= half)
    return np.where(inside, -d, d)


def _segment_distance(y: np.ndarray, half: float) -> np.ndarray:
    z = np.clip(y[:, 2], -half, half)
    return np.sqrt(y[:, 0] ** 2 + y[:, 1] ** 2 + (y[:, 2] - z) ** 2)


def _cloud_distance(y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    out = np.full(len(y), np.inf)
    for i in range(0, len(y), 512):
        for j in range(0, len(pts), _CHUNK):
            d = np.linalg.norm(y[i : i + 512, None, :] - pts[None, j : j + _CHUNK], axis=-1).min(axis=1)
            np.minimum(out[i : i + 512], d, out=out[i : i + 512])
    return out


def local_exact(shape: object, y: np.ndarray, s: float) -> np.ndarray:
    """Signed distance (N,) mm of points y (N, 3) in the shape's frame, the shape at scale s (module docstring)."""
    if isinstance(shape, Sphere):
        return np.linalg.norm(y, axis=1) - s * shape.radius
    if isinstance(shape, Capsule):
        return _segment_distance(y, 0.5 * s * shape.length) - s * shape.radius
    if isinstance(shape, HalfSpace):
        return y @ np.asarray(shape.normal) - s * shape.offset
    if isinstance(shape, Box):
        h = s * np.asarray(shape.half_extents)
        d = _min_to_triangles(y, box_triangles(h))
        return np.where(np.all(np.abs(y) <= h, axis=1), -d, d)
    if isinstance(shape, Cylinder):
        return _cylinder_exact(y, s * shape.radius, 0.5 * s * shape.length)
    if isinstance(shape, Mesh):
        return _min_to_triangles(y, s * shape.triangles)
    if isinstance(shape, PointCloud):
        return _cloud_distance(y, s * shape.points) - s * shape.radius
    raise TypeError(f"no exact distance for {type(shape).__name__}")


def exact_distance(ms: MovingShape, points: np.ndarray, t: float) -> np.ndarray:
    """Signed distance (N,) mm of world points (N, 3) to the moving shape at time t (s), by brute force."""
    p, rm = ms.motion.pose(float(t))
    pose = ms.shape.pose
    origin = p + rm @ np.asarray(pose.position)
    rot = rm @ pose.matrix
    s = 1.0 if ms.breathing is None else ms.breathing.scale(float(t))
    y = (np.asarray(points, dtype=float) - origin) @ rot
    return local_exact(ms.shape, y, s)


def exact_clearances(shapes: tuple[MovingShape, ...], points: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(S, P, K) brute-force signed distances (mm) of points (S, P, 3), each row at its time times[s] (s,
    absolute), to each of the K shapes; (S, P, 0) without shapes."""
    S, P, _ = points.shape
    out = np.empty((S, P, len(shapes)))
    for k, ms in enumerate(shapes):
        if ms.static:
            out[:, :, k] = exact_distance(ms, points.reshape(-1, 3), 0.0).reshape(S, P)
            continue
        for i in range(S):
            out[i, :, k] = exact_distance(ms, points[i], float(times[i]))
    return out


def _pairwise(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, M) distances from x (N, 3) to c (M, 3) by one matrix product (to within 1e-3 mm near zero)."""
    d2 = (x * x).sum(axis=1)[:, None] + (c * c).sum(axis=1)[None, :] - 2.0 * (x @ c.T)
    return np.sqrt(np.maximum(d2, 0.0))


_SLACK = 1e-3  # mm: what `_pairwise` may be off by; candidates are kept within it


def _rows_min(y: np.ndarray, centres: np.ndarray, rad: np.ndarray, exact: Any, reps: np.ndarray) -> np.ndarray:
    """(S,) min over the points of each row y (S, P, 3) of exact(points, items): items are balls (centres,
    rad) that contain the pieces (triangles or groups of points), of which only those that could be nearest
    in their row are measured (a row's smallest distance to a point `reps` of each piece bounds it above)."""
    S, P, _ = y.shape
    out = np.empty(S)
    rows = max(1, 2_000_000 // max(1, P * len(centres)))
    for r in range(0, S, rows):
        flat = y[r : r + rows].reshape(-1, 3)
        n = len(flat) // P
        dc = _pairwise(flat, centres)
        row_upper = _pairwise(flat, reps).min(axis=1).reshape(n, P).min(axis=1)
        lim = np.repeat(row_upper, P)[:, None] + _SLACK
        pi, ti = np.nonzero(dc - rad[None, :] <= lim)
        best = np.full(len(flat), np.inf)
        np.minimum.at(best, pi, exact(flat[pi], ti))
        out[r : r + n] = best.reshape(n, P).min(axis=1)
    return out


def exact_min_clearance(ms: MovingShape, points: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(S,) the smallest brute-force signed distance (mm) of each row of points (S, P, 3), row s at time
    times[s] (absolute s), to the moving shape; a mesh or a cloud measures only the pieces that can be nearest."""
    S = points.shape[0]
    if not isinstance(ms.shape, (Mesh, PointCloud)):
        if ms.static:
            return exact_distance(ms, points.reshape(-1, 3), 0.0).reshape(S, -1).min(axis=1)
        return np.array([exact_distance(ms, points[i], float(times[i])).min() for i in range(S)])
    out = np.empty(S)
    groups = [(0.0, np.arange(S))] if ms.static else [(float(times[i]), np.array([i])) for i in range(S)]
    for t, idx in groups:
        p, rm = ms.motion.pose(t)
        origin = p + rm @ np.asarray(ms.shape.pose.position)
        rot = rm @ ms.shape.pose.matrix
        s = 1.0 if ms.breathing is None else ms.breathing.scale(t)
        y = (points[idx] - origin) @ rot
        out[idx] = _piece_rows(ms.shape, y, s)
    return out


def _groups(pts: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 3) as groups on a grid of `cell` mm: (padded groups (G, m, 3), with far-away padding; the
    first member of each group)."""
    key = np.floor(pts / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    counts = np.bincount(inv)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(pts)) - np.repeat(start, counts)
    padded = np.full((len(counts), int(counts.max()), 3), 1e12)
    padded[inv[order], slot, :] = pts[order]
    return padded, padded[:, 0, :]


def _piece_rows(shape: Mesh | PointCloud, y: np.ndarray, s: float) -> np.ndarray:
    """(S,) row minima of the distance of y (S, P, 3) (shape frame) to a mesh's triangles or a cloud's balls."""
    if isinstance(shape, Mesh):
        tri = s * shape.triangles
        centres = tri.mean(axis=1)
        rad = np.linalg.norm(tri - centres[:, None, :], axis=2).max(axis=1)

        def to_triangles(x: np.ndarray, ti: np.ndarray) -> np.ndarray:
            return _closest_on_triangle(x, tri[ti, 0], tri[ti, 1], tri[ti, 2])

        return _rows_min(y, centres, rad, to_triangles, centres)  # a centroid lies on its triangle
    groups, firsts = _groups(s * shape.points, 10.0)
    real = groups[:, :, 0] < 1e11
    centres = np.array([g[r].mean(axis=0) for g, r in zip(groups, real, strict=True)])
    rad = np.array([np.linalg.norm(g[r] - c, axis=1).max() for g, r, c in zip(groups, real, centres, strict=True)])

    def to_points(x: np.ndarray, gi: np.ndarray) -> np.ndarray:
        return np.linalg.norm(x[:, None, :] - groups[gi], axis=2).min(axis=1)

    return _rows_min(y, centres, rad, to_points, firsts) - s * shape.radius
