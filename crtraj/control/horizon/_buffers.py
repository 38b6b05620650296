"""Preallocated parameter buffers of the horizon NLP (issue 29: the step's Python around the one generated call).

The NLP's parameter vector is ``[x0, x_-1, X_ref (N nx), P_ref (N 3), obstacles (N, WIDTH M + shapes)]`` (then, when
`closest_points` screens, the selection's slot parameters). `ParameterBuffer` keeps it as one array written in
place every step: each part is a view of it, and the reference's tips are computed by CasADi's buffer API
straight from the X_ref view into the P_ref view (the map's column-major nx x N input and 3 x N output are, in
memory, the C-ordered (N, nx) and (N, 3) views). The numbers are those `Replanner` computed by concatenation
(`tests/test_horizon_lean.py`). The buffer is reused by the next step: whoever keeps a parameter vector beyond
the solve copies it. Units: mm, rad.
"""

from __future__ import annotations

import itertools
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.world import packing


class ParameterBuffer:
    """The horizon NLP's parameter vector (p) for N steps, nx coordinates and M obstacle slots, and its parts as
    views of it: x0, xm1 (nx,), X (N, nx), P (N, 3) mm, O (N, packing.WIDTH M + shape_params).

    model: the robot's `Model` (its ``tip`` function gives the reference's tips). shape_params: the shapes'
    parameters per step, after the step's sphere slots (`crtraj.world.geometry.ShapeTerms`). extra: entries after
    the obstacles, left to the backend (the rod correction's, `crtraj.control.horizon._rod_body`)."""

    def __init__(self, model: Model, N: int, max_obstacles: int, shape_params: int = 0, extra: int = 0) -> None:
        nx, W = model.nx, packing.WIDTH * max_obstacles + shape_params
        self.N, self.nx, self.width = N, nx, W
        cut = np.cumsum((0, nx, nx, N * nx, N * 3, N * W, extra))
        self.p = np.zeros(int(cut[-1]))
        v = [self.p[a:b] for a, b in itertools.pairwise(cut)]
        self.x0, self.xm1 = v[0], v[1]
        self.X = v[2].reshape(N, nx)
        self.P = v[3].reshape(N, 3)
        self.O = v[4].reshape(N, W)
        fn = model.tip if N == 1 else model.tip.map(N, "serial")
        if not fn.sparsity_out(0).is_dense():
            fn = ca.Function("tip_dense", [fn.mx_in(0)], [ca.densify(fn(fn.mx_in(0)))])
        self._tips, self._run = fn.buffer()
        self._tips.set_arg(0, memoryview(self.X))
        self._tips.set_res(0, memoryview(self.P))

    def fill(self, x0: np.ndarray, reference: Any, obstacles: Any, x_prev: Any, tip_reference: Any) -> np.ndarray:
        """The parameter vector (a view of the buffer) from `Replanner.solve`'s inputs; `InputError` for
        obstacles of the wrong size or for NaN (naming the part), a ValueError for a reference of the wrong
        shape (as numpy's reshape says it)."""
        N, nx = self.N, self.nx
        self.x0[:] = x0
        self.xm1[:] = x0 if x_prev is None else np.asarray(x_prev, dtype=float).reshape(nx)
        self.X[:] = np.asarray(reference, dtype=float).reshape(N, nx)
        if tip_reference is None:
            self._run()  # the reference's tips, written into the P view
        else:
            self.P[:] = np.asarray(tip_reference, dtype=float).reshape(N, 3)
        Ob = np.asarray(obstacles, dtype=float)
        if Ob.size != self.O.size:
            raise InputError(
                f"obstacles: expected shape ({N}, {self.width}) from obstacles_from_scene or obstacles_from_states, "
                f"got {Ob.shape}"
            )
        self.O[:] = Ob.reshape(N, self.width)
        if not np.isfinite(self.p).all():
            # one check of the whole vector; the search for the culprit only when there is one
            parts = (("x0", self.x0), ("reference", self.X), ("x_prev", self.xm1), ("tip_reference", self.P))
            for name, arr in (*parts, ("obstacles", self.O)):
                if not np.isfinite(arr).all():
                    raise InputError(f"{name}: contains NaN or infinity")
        return self.p
