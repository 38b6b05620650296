"""Symbolic PCC model of a multi-segment continuum robot, built once with CasADi.

Singularity-free form (DESIGN.md): each segment is described by its effective
bending vector ``u_bar = theta (cos phi, sin phi)``; the tip of a segment is
``p = L (f1 u_x, f1 u_y, f2)`` and its rotation ``I + f2 W + f1 W^2`` with
``W = skew(-u_y, u_x, 0)``, where ``f1 = (1 - cos theta)/theta^2`` and
``f2 = sin theta/theta`` are evaluated through ``theta^2`` with a series
branch near zero. Value, gradient and Hessian are therefore finite at the
straight pose, where the paper's ``L/theta`` form divides by zero.

All lengths in mm, angles in rad.
"""

from __future__ import annotations

import threading
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.model.robot import Robot

# Below theta^2 = _SERIES_T the exact f1, f2 lose digits to cancellation; the
# series truncation error there is < 1e-17.
_SERIES_T = 1e-2

# Most backbone points of one model function (the solvers use 10-21; dense
# checks up to a few hundred). The symbolic FK grows linearly with it.
MAX_POINTS = 1000
# Most configurations of one exported backbone_map call.
MAX_BATCH = 1_000_000


def _f1_f2(t: ca.SX) -> tuple[ca.SX, ca.SX]:
    """f1 = (1-cos th)/th^2 and f2 = sin th/th as smooth functions of t = th^2."""
    small = t < _SERIES_T
    # Feed the exact branch a safe argument so its (unused) value and
    # derivatives never become NaN at t = 0.
    ts = ca.if_else(small, _SERIES_T, t)
    th = ca.sqrt(ts)
    f1_series = 1 / 2 - t / 24 + t**2 / 720 - t**3 / 40320 + t**4 / 3628800
    f2_series = 1 - t / 6 + t**2 / 120 - t**3 / 5040 + t**4 / 362880
    f1 = ca.if_else(small, f1_series, (1 - ca.cos(th)) / ts)
    f2 = ca.if_else(small, f2_series, ca.sin(th) / th)
    return f1, f2


def _skew(w: list[ca.SX]) -> ca.SX:
    return ca.vertcat(
        ca.horzcat(0, -w[2], w[1]),
        ca.horzcat(w[2], 0, -w[0]),
        ca.horzcat(-w[1], w[0], 0),
    )


def _arc(ub: ca.SX, length: float, frac: float | ca.SX) -> tuple[ca.SX, ca.SX]:
    """Position and rotation at fraction `frac` (a number, or symbolic) of a segment with bending ub (local
    frame)."""
    v = frac * ub
    f1, f2 = _f1_f2(ca.sumsqr(v))
    p = frac * length * ca.vertcat(f1 * v[0], f1 * v[1], f2)
    W = _skew([-v[1], v[0], 0])
    R = ca.SX.eye(3) + f2 * W + f1 * (W @ W)
    return p, R


class Model:
    """CasADi functions of one robot, built once, with thin numpy wrappers.

    The numpy wrappers reuse evaluation buffers, so one Model must not be used
    from several threads at once (give each thread or process its own).

    Named CasADi functions (attributes of the same name):
    ``config_to_cables (x -> q)``, ``cables_to_config (q -> x)``,
    ``bending (x -> u_bar)``, ``tip (x -> p)``, ``tip_frame (x -> T)``,
    ``backbone (x -> points, 3 x n_points)``, ``jac_tip (x -> J)``,
    ``jac_cables (x -> J_q)``, ``limits (x -> g)``.
    """

    def __init__(self, robot: Robot, n_points: int | None = None) -> None:
        self.robot = robot
        self.n_points = int(robot.collision_points if n_points is None else n_points)
        if not 2 <= self.n_points <= MAX_POINTS:
            raise InputError(f"n_points: must be in [2, {MAX_POINTS}], got {self.n_points}")
        self.nx, self.nq = robot.nx, robot.nq
        self._x = ca.SX.sym("x", self.nx)
        A, q0 = robot.cable_matrix()
        B = robot.cable_inverse()
        self._A, self._q0, self._B = A, q0, B
        x = self._x
        qs = ca.SX.sym("q", self.nq)
        q_expr = ca.DM(q0) + ca.DM(A) @ x
        self.config_to_cables = ca.Function("config_to_cables", [x], [q_expr], ["x"], ["q"])
        self.cables_to_config = ca.Function("cables_to_config", [qs], [ca.DM(B) @ (qs - ca.DM(q0))], ["q"], ["x"])
        ub = ca.DM(robot.coupling_matrix()) @ x[: 2 * robot.n_segments]
        self._ub = ub
        self.bending = ca.Function("bending", [x], [ub], ["x"], ["u_bar"])
        T = self._frame_expr()
        self.tip = ca.Function("tip", [x], [ca.densify(T[:3, 3])], ["x"], ["p"], {"cse": True})
        self.tip_frame = ca.Function("tip_frame", [x], [ca.densify(T)], ["x"], ["T"], {"cse": True})
        self.backbone = self.backbone_function(self.n_points, "backbone")
        self.jac_tip = ca.Function("jac_tip", [x], [ca.densify(ca.jacobian(T[:3, 3], x))], ["x"], ["J"], {"cse": True})
        self.jac_cables = ca.Function("jac_cables", [x], [ca.jacobian(q_expr, x)], ["x"], ["J_q"])
        g = [ca.sumsqr(ub[2 * k : 2 * k + 2]) for k in range(robot.n_segments)]
        g.append((ca.DM(A) @ x)[: 3 * robot.n_segments])
        self.limits = ca.Function("limits", [x], [ca.vertcat(*g)], ["x"], ["g"])
        # the evaluators (and their buffers) are per thread: a buffer holds its call's argument and result
        # pointers between set_arg and the call, so two threads sharing one could swap each other's results; and
        # another thread's batch sizes (a live view's) never evict, nor make rebuild, this thread's evaluators
        self._local = threading.local()
        self._dense: dict[int, ca.Function] = {}

    def identity(self) -> dict[str, Any] | None:
        """What makes this model's body differ from the robot file's PCC body (None: it is PCC's); part of the
        key of anything compiled from the model (`crtraj.model.cosserat.RodModel`)."""
        return None

    # ------------------------------------------------------------ expressions
    def _frame_expr(self, frac_total: float | None = None) -> ca.SX:
        R = ca.SX.eye(3)
        o = ca.vertcat(0, 0, self._x[-1])
        for k, seg in enumerate(self.robot.segments):
            p, Rk = _arc(self._ub[2 * k : 2 * k + 2], seg.length, 1.0)
            o = o + R @ p
            R = R @ Rk
        return ca.vertcat(ca.horzcat(R, o), ca.DM([[0, 0, 0, 1]]))

    def arc_segments(self, arcs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(segment index (P,), fraction of that segment's arc (P,) in [0, 1]) of arc lengths `arcs`
        (P,) mm from the base: a segment holds the arc lengths in (start, end], the first also 0."""
        segs = self.robot.segments
        starts = np.cumsum([0.0] + [s.length for s in segs])
        seg = np.zeros(len(arcs), dtype=int)
        frac = np.zeros(len(arcs))
        for i, s in enumerate(arcs):
            for k, sg in enumerate(segs):
                if (starts[k] < s <= starts[k + 1]) or (k == 0 and s <= 0.0):
                    seg[i], frac[i] = k, min(max((s - starts[k]) / sg.length, 0.0), 1.0)
                    break
        return seg, frac

    def _points_expr(self, arcs: np.ndarray) -> ca.SX:
        """Backbone points (3 x len(arcs)) at arc lengths `arcs` (mm from the base)."""
        seg_of, frac_of = self.arc_segments(arcs)
        R = ca.SX.eye(3)
        o = ca.vertcat(0, 0, self._x[-1])
        cols: list[ca.SX] = []
        for k, seg in enumerate(self.robot.segments):
            ubk = self._ub[2 * k : 2 * k + 2]
            for frac in frac_of[seg_of == k]:
                p, _ = _arc(ubk, seg.length, float(frac))
                cols.append(o + R @ p)
            p, Rk = _arc(ubk, seg.length, 1.0)
            o = o + R @ p
            R = R @ Rk
        return ca.horzcat(*cols)

    def segment_point_function(self) -> ca.Function:
        """CasADi function (x, f) -> points (3 x n_segments): the backbone point at fraction f (0..1,
        symbolic) of each segment's arc. One column picked by weights is any backbone point, at the
        cost of one point per segment (a solver that chooses its points by parameters)."""
        f = ca.SX.sym("f")
        R = ca.SX.eye(3)
        o = ca.vertcat(0, 0, self._x[-1])
        cols: list[ca.SX] = []
        for k, seg in enumerate(self.robot.segments):
            ubk = self._ub[2 * k : 2 * k + 2]
            p, _ = _arc(ubk, seg.length, f)
            cols.append(o + R @ p)
            p, Rk = _arc(ubk, seg.length, 1.0)
            o = o + R @ p
            R = R @ Rk
        return ca.Function("segment_points", [self._x, f], [ca.horzcat(*cols)], {"cse": True})

    def arc_positions(self, n: int) -> np.ndarray:
        """Arc lengths (mm) of n points spread evenly from base to tip."""
        return np.linspace(0.0, self.robot.total_length, n)

    def backbone_function(self, n: int, name: str | None = None) -> ca.Function:
        """CasADi function x -> points (3 x n) at n evenly spread arc positions."""
        pts = self._points_expr(self.arc_positions(n))
        return ca.Function(name or f"backbone_{n}", [self._x], [ca.densify(pts)], ["x"], ["points"], {"cse": True})

    # -------------------------------------------------------- numpy wrappers
    def _as_batch(self, x: Any, name: str = "x") -> tuple[np.ndarray, bool]:
        a = np.asarray(x, dtype=float)
        single = a.ndim == 1
        a2 = check_array(a.reshape(1, -1) if single else a, name, (None, self.nx))
        return a2, single

    def _evaluator(self, f: ca.Function, n: int) -> tuple[Any, Any]:
        """A cached (buffer, eval) pair of `f` mapped over n configurations, this thread's own.

        Evaluating through CasADi's buffer API writes straight into numpy memory;
        converting a large DM result to numpy costs more than the evaluation itself.
        """
        maps = getattr(self._local, "maps", None)
        if maps is None:
            maps = self._local.maps = {}
        key = (f.name(), n)
        ev = maps.get(key)
        if ev is None:
            if not f.sparsity_out(0).is_dense():
                raise RuntimeError(f"{f.name()}: buffer evaluation needs a dense output (wrap it in ca.densify)")
            if len(maps) > 64:
                maps.clear()
            ev = (f if n == 1 else f.map(n, "serial")).buffer()
            maps[key] = ev
        return ev

    def _eval(self, f: ca.Function, x: Any, rows: int, cols: int) -> np.ndarray:
        """Evaluate f (x -> rows x cols) at configuration(s) x; returns (cols, rows) or (N, cols, rows).

        A column-major (rows, cols * N) result is, in memory, a C-ordered (N, cols, rows) array.
        """
        # outputs are dense by construction (ca.densify), so nonzeros == entries
        X, single = self._as_batch(x)
        X = np.ascontiguousarray(X)
        out = np.empty((X.shape[0], cols, rows))
        buf, run = self._evaluator(f, X.shape[0])
        buf.set_arg(0, memoryview(X))
        buf.set_res(0, memoryview(out))
        run()
        return out[0] if single else out

    def tip_position(self, x: Any) -> np.ndarray:
        """Tip position(s) (mm): (3,) or (N, 3)."""
        return self._eval(self.tip, x, 3, 1)[..., 0, :]

    def frame(self, x: Any) -> np.ndarray:
        """Tip transform(s): (4, 4) or (N, 4, 4)."""
        return np.swapaxes(self._eval(self.tip_frame, x, 4, 4), -1, -2)

    def points(self, x: Any, n: int | None = None) -> np.ndarray:
        """Backbone points (mm): (n, 3) or (N, n, 3); n defaults to the collision points."""
        if n is None or n == self.n_points:
            f = self.backbone
            n = self.n_points
        else:
            f = self._dense.get(n)
            if f is None:
                f = self.backbone_function(n)
                self._dense[n] = f
        return self._eval(f, x, 3, n)

    def jacobian(self, x: Any) -> np.ndarray:
        """Task Jacobian d tip / d x: (3, nx) or (N, 3, nx)."""
        return np.swapaxes(self._eval(self.jac_tip, x, 3, self.nx), -1, -2)

    def cables(self, x: Any) -> np.ndarray:
        """Actuation q (mm) for configuration(s) x."""
        X, single = self._as_batch(x)
        q = X @ self._A.T + self._q0
        return q[0] if single else q

    def config(self, q: Any) -> np.ndarray:
        """Configuration(s) x from actuation q (mm); least squares for inconsistent cables."""
        a = np.asarray(q, dtype=float)
        single = a.ndim == 1
        Q = check_array(a.reshape(1, -1) if single else a, "q", (None, self.nq))
        X = (Q - self._q0) @ self._B.T
        return X[0] if single else X

    # --------------------------------------------------- exported functions
    def functions(self, batch: int = 1024) -> list[ca.Function]:
        """Every exported function; `backbone_map` evaluates `batch` configurations (1..MAX_BATCH)."""
        if isinstance(batch, bool) or not isinstance(batch, int) or not 1 <= batch <= MAX_BATCH:
            raise InputError(f"batch: must be an integer in [1, {MAX_BATCH}], got {batch!r}")
        bmap = self.backbone.map("backbone_map", "serial", batch, [], [])
        return [
            self.config_to_cables,
            self.cables_to_config,
            self.bending,
            self.tip,
            self.tip_frame,
            self.backbone,
            self.jac_tip,
            self.jac_cables,
            self.limits,
            bmap,
        ]

    def limit_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds (lbg, ubg) of the `limits` function's output g."""
        n = self.robot.n_segments
        lo = [-np.inf] * n
        hi = [s.theta_max**2 for s in self.robot.segments]
        strokes = np.repeat([self.robot.cable_stroke(k) for k in range(n)], 3)
        return np.concatenate([lo, -strokes]), np.concatenate([hi, strokes])
