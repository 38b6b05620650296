"""Shapes in an NLP: symbolic lower bounds of the distance from body points to each shape, with the shape's
pose, scale and sweep pad as parameters, so that an NLP is built once per set of shapes and re-solved as
they move (mm, s).

Each shape takes `WIDTH` parameters: its frame's origin (3), rotation matrix (9, column-major), scale (1)
and pad (1). `ShapeTerms.values(t0, t1)` fills them for a window: the frame at the middle time and the pad
``f(x, tm) - lower_bound(x, t0, t1)`` that the sweep bound (`MovingShape.lower_bound`) takes off, for a
bounded shape ``h L`` and for a half space its largest value over points within `reach` mm of the motion's
origin. `distances(P, p)` gives, per shape, the row (1, n) of lower bounds of the signed distance of the
points P (3, n) over the window:

- sphere, half space, capsule: the exact distance (`casadi_distance`); box and cylinder: its smooth lower
  bound, at most `BOX_SMOOTH_ERROR * smooth` mm below the exact one;
- mesh, point cloud: the trilinear grid lower bound of the set's distance (`crtraj.world.geometry._grid`), at
  most `GridDistance.error` mm below the obstacle's distance inside the grid, so never above it: an NLP that
  keeps it above a margin keeps the set's.
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from crtraj.world.geometry._distance import MovingShape
from crtraj.world.geometry._grid import grid_of
from crtraj.world.geometry._points import POINT_SETS
from crtraj.world.geometry._shapes import HalfSpace
from crtraj.world.geometry._symbolic import casadi_distance

WIDTH = 14
# Largest distance (mm) from a half space's motion origin to a body point, for its turning pad.
REACH = 2000.0


class ShapeTerms:
    """The NLP distances of `shapes` (module docstring); `smooth` mm: the box and cylinder smoothing length."""

    def __init__(self, shapes: tuple[MovingShape, ...], *, smooth: float = 0.5) -> None:
        self.shapes = tuple(shapes)
        self.smooth = float(smooth)
        self.grids = [grid_of(ms.shape) if isinstance(ms.shape, POINT_SETS) else None for ms in shapes]
        self.n_params = WIDTH * len(self.shapes)

    def symbols(self) -> Any:
        """The parameter symbol (n_params, 1)."""
        return ca.SX.sym("shapes", self.n_params)

    def distances(self, P: Any, p: Any) -> list[Any]:
        """Per shape, a (1, n) row of lower bounds (mm) of the signed distance of points P (3, n) over the
        window `p` describes (`values`)."""
        rows = []
        n = P.shape[1]
        for k, ms in enumerate(self.shapes):
            base = WIDTH * k
            origin = p[base : base + 3]
            rot = ca.reshape(p[base + 3 : base + 12], 3, 3)
            scale, pad = p[base + 12], p[base + 13]
            grid = self.grids[k]
            row = []
            for j in range(n):
                x = P[:, j]
                if grid is None:
                    d = casadi_distance(ms.shape, x, origin, rot, scale, self.smooth)
                else:  # the set grown by `scale` about its origin: s f(y / s)
                    d = scale * grid(ca.mtimes(ca.transpose(rot), x - origin) / scale)
                row.append(d - pad)
            rows.append(ca.horzcat(*row))
        return rows

    def values(self, t0: float, t1: float) -> np.ndarray:
        """The parameters (n_params,) for the window [t0, t1] (absolute s)."""
        out = np.empty(self.n_params)
        tm, h = 0.5 * (t0 + t1), 0.5 * (t1 - t0)
        for k, ms in enumerate(self.shapes):
            base = WIDTH * k
            o, r, s = ms.frame(tm)
            if ms.static or h == 0.0:
                pad = 0.0
            elif isinstance(ms.shape, HalfSpace):
                v, w = ms.motion.speed_bound(t0, t1)
                rate = 0.0 if ms.breathing is None else ms.breathing.rate_max
                pad = min(2.0, w * h) * REACH + h * (v + rate * abs(ms.shape.offset))
            else:
                pad = h * ms.surface_speed(t0, t1)
            out[base : base + 3] = o
            out[base + 3 : base + 12] = r.ravel(order="F")
            out[base + 12] = s
            out[base + 13] = pad if math.isfinite(pad) else 1e9
        return out
