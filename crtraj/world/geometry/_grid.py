"""A point set's distance on a grid, for NLPs: a trilinear CasADi interpolant that is a conservative lower bound
(mm).

A point set (`PointCloud`, `Mesh`) has the distance ``f(y) = min_k |y - p_k| - b`` (b its ball: the cloud's
radius, the mesh's covering radius), which is at most the distance to the obstacle and 1-Lipschitz. The grid
holds ``g_i = f(y_i) - (sqrt(3) / 2) h`` at the nodes y_i of a regular grid of spacing h (mm) over the set's
bounding box grown by `pad` mm. Trilinear interpolation ``I(y) = sum_i w_i g_i`` (weights w_i >= 0, summing to
1, of the 8 corners of y's cell) is then below f:

    sum_i w_i f(y_i) <= f(y) + sum_i w_i |y_i - y| <= f(y) + sqrt(sum_i w_i |y_i - y|^2)
                      = f(y) + h sqrt(sum_axes u_a (1 - u_a)) <= f(y) + (sqrt(3) / 2) h,

(u_a the cell coordinates of y; Jensen, then the trilinear weights' variance per axis), so
``f(y) - sqrt(3) h <= I(y) <= f(y)``: conservative, at most sqrt(3) h below f (a cloud's distance), and
b + sqrt(3) h below the obstacle's distance for a mesh (the error bound `error`). Outside the grid, the lower
bound is the larger of ``I(clip(y)) - |y - clip(y)|`` (f is 1-Lipschitz; the norm is taken as
``sqrt(|.|^2 + e^2)`` with e = 1e-3 mm, which is above it, so the bound stays one) and the smooth lower bound of
the distance to the set's bounding box grown by b (a box that contains every ball). Inside the grid the first
term is I(y) - e.

The interpolant is piecewise trilinear: continuous, its gradient jumps across cell faces (the NLPs' SQP and
IPOPT steps cope; the verifiers never use it). Grids are kept per set object, and their node values in the build
cache's folder under the SHA-256 of the set's points and the grid (built once).
"""

from __future__ import annotations

import hashlib
import io
import logging
import math
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import default_root
from crtraj.core.fileio import atomic_write_bytes
from crtraj.core.lazy import lazy_module
from crtraj.world.geometry._points import Mesh, PointCloud
from crtraj.world.geometry._shapes import Box
from crtraj.world.geometry._symbolic import casadi_distance

ndimage = lazy_module("scipy.ndimage")  # as the KD-tree's SciPy: loaded when a point set is first used

# Most grid nodes per set: the spacing grows until the grid fits (about 16 MB of doubles).
MAX_NODES = 2_000_000
_EPS = 1e-3  # mm, the smoothing of the norm outside the grid
_VERSION = b"grid-1"  # changes when the node values are computed otherwise
log = logging.getLogger(__name__)
_GRIDS: dict[int, tuple[Any, GridDistance]] = {}


class GridDistance:
    """The grid lower bound of a point set's distance (module docstring), in the set's frame at scale 1.

    shape: the `PointCloud` or `Mesh`. spacing: the grid's h (mm; None: half the mesh's sample spacing, or the
    cloud's ball radius, at least 1 mm, grown until at most `MAX_NODES` nodes). pad: mm the grid reaches
    beyond the set's bounding box. near: mm from the set within which the nodes hold f exactly (`_node_distances`).
    """

    def __init__(
        self, shape: PointCloud | Mesh, spacing: float | None = None, pad: float = 40.0, near: float = 30.0
    ) -> None:
        pts, ball = shape.points, shape.ball
        lo, hi = pts.min(axis=0) - pad - ball, pts.max(axis=0) + pad + ball
        h = (
            spacing
            if spacing is not None
            else max(1.0, 0.5 * shape.spacing if isinstance(shape, Mesh) else shape.radius)
        )
        ext = hi - lo
        while np.prod(np.ceil(ext / h) + 1) > MAX_NODES:
            h *= 1.25
        n = (np.ceil(ext / h) + 1).astype(int)
        self.spacing, self.lo, self.n = float(h), lo, n
        self.hi = lo + (n - 1) * h
        axes = [lo[a] + h * np.arange(n[a]) for a in range(3)]
        d = _cached_nodes(shape, lo, h, n, near) - 0.5 * math.sqrt(3.0) * h
        # CasADi's interpolant takes the values with the first axis fastest (Fortran order)
        values = d.reshape(n).ravel(order="F")
        self.values = d.reshape(n)
        self._f = ca.interpolant(f"grid_{shape.kind}", "linear", [a.tolist() for a in axes], values.tolist())
        cmin, cmax = pts.min(axis=0) - ball, pts.max(axis=0) + ball
        half = np.maximum(0.5 * (cmax - cmin), 1e-6)
        self._box = Box(tuple(half.tolist()))
        self._box_centre = ca.DM(0.5 * (cmax + cmin))
        # below the obstacle's distance at most (inside the grid, within `near` of the set): the grid's, and a
        # mesh's sampling (a cloud's balls are its obstacle: its f is exact)
        self.error = math.sqrt(3.0) * h + (ball if isinstance(shape, Mesh) else 0.0)

    def __call__(self, y: Any) -> Any:
        """A lower bound (mm) of the distance at y (3, 1) in the set's frame at scale 1 (symbolic or numeric)."""
        c = ca.fmin(ca.fmax(y, ca.DM(self.lo)), ca.DM(self.hi))
        v = y - c
        grid = self._f(c) - ca.sqrt(ca.dot(v, v) + _EPS * _EPS)
        box = casadi_distance(self._box, y - self._box_centre, ca.DM.zeros(3), ca.DM.eye(3))
        return ca.fmax(grid, box)

    def lookup(self, y: np.ndarray) -> np.ndarray:
        """The same bound at points y (N, 3) in numpy (the checker's trilinear lookup; the box term is the exact
        distance to the box, at most `BOX_SMOOTH_ERROR` k above the interpolant's smooth one): (N,) mm."""
        c = np.clip(y, self.lo, self.hi)
        u = (c - self.lo) / self.spacing
        i = np.minimum(np.floor(u).astype(np.int64), self.n - 2)
        f = u - i
        v = self.values
        out = np.zeros(len(y))
        for corner in range(8):
            b = np.array([(corner >> a) & 1 for a in range(3)])
            w = np.prod(np.where(b == 1, f, 1.0 - f), axis=1)
            j = i + b
            out += w * v[j[:, 0], j[:, 1], j[:, 2]]
        grid = out - np.sqrt(np.sum((y - c) ** 2, axis=1) + _EPS * _EPS)
        box = self._box.local_distance(y - np.asarray(self._box_centre).ravel())[0]
        return np.maximum(grid, box)

    def numeric(self, y: np.ndarray) -> np.ndarray:
        """The bound at points y (N, 3) (numbers; for tests and benchmarks)."""
        x = ca.SX.sym("y", 3)
        f = ca.Function("grid_bound", [x], [self(x)]).map(len(y))
        return np.asarray(f(np.asarray(y, dtype=float).T)).ravel()


def _node_distances(shape: PointCloud | Mesh, lo: np.ndarray, h: float, n: np.ndarray, near: float) -> np.ndarray:
    """f at the grid's nodes (n) where it is below `near` mm (the set's KD-tree), and a lower bound of it elsewhere:
    the Euclidean distance transform of the nodes nearest to a point of the set, less h sqrt(3) / 2 (each point is
    that near its node) and the ball. Only the nodes the transform puts within `near` + h sqrt(3) are queried."""
    pts, ball = shape.points, shape.ball
    idx = np.clip(np.rint((pts - lo) / h).astype(np.int64), 0, n - 1)
    occupied = np.zeros(n, dtype=bool)
    occupied[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    half = 0.5 * math.sqrt(3.0) * h
    d = ndimage.distance_transform_edt(~occupied) * h - half - ball
    close = np.flatnonzero(d.ravel() < near)
    if len(close):
        ijk = np.stack(np.unravel_index(close, n), axis=1)
        nodes = lo + h * ijk
        dist, _ = shape._tree.query(nodes, distance_upper_bound=near + 2.0 * half + ball)
        exact = np.where(np.isfinite(dist), dist - ball, near)  # beyond the bound: f is at least near
        d.ravel()[close] = np.maximum(d.ravel()[close], exact)
    return d


def _cached_nodes(shape: PointCloud | Mesh, lo: np.ndarray, h: float, n: np.ndarray, near: float) -> np.ndarray:
    """`_node_distances`, kept in the build cache's folder (``grids/<sha256>.npy``) under the SHA-256 of the set's
    points, ball and the grid (a set built again, in this process or another, reads it back). A cache that
    cannot be read or written is passed by (the grid is computed)."""
    key = hashlib.sha256(np.ascontiguousarray(shape.points, dtype=np.float64).tobytes())
    key.update(np.array([shape.ball, h, near, *lo, *n], dtype=np.float64).tobytes() + _VERSION)
    path = default_root() / "grids" / f"{key.hexdigest()}.npy"
    try:
        cached = np.load(path, allow_pickle=False)
        if cached.shape == tuple(n) and np.isfinite(cached).all():
            return cached
    except (OSError, ValueError):
        pass
    d = _node_distances(shape, lo, h, n, near)
    buf = io.BytesIO()
    np.save(buf, d, allow_pickle=False)
    try:
        atomic_write_bytes(path, buf.getvalue())
    except OSError as exc:
        log.debug("grid cache: not written (%s)", exc)
    return d


def grid_of(shape: PointCloud | Mesh) -> GridDistance:
    """The shape's `GridDistance`, built on first use and kept while the shape lives."""
    hit = _GRIDS.get(id(shape))
    if hit is not None and hit[0] is shape:
        return hit[1]
    g = GridDistance(shape)
    if len(_GRIDS) >= 32:  # a few sets per process; the oldest goes
        _GRIDS.pop(next(iter(_GRIDS)))
    _GRIDS[id(shape)] = (shape, g)
    return g
