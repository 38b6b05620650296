"""The steer step's NLP (paper eq. 15-18) built once, its numeric helpers, and one solve's query and solution.

`SteerNLP` builds the symbolic problem of `planning.steer` (its module docstring gives the formulation) in the
scaled variable ``y = S x`` (mm) and the one CasADi function the predictor and the re-check evaluate (tip, tip
Jacobian, collision points and limits at x). Every backend (`planning.steer_backends`) solves this one NLP.
`SteerQuery` is what one `SteerSolver.solve` call asks, `SteerSolution` what a backend answers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.steer._options import SteerOptions
from crtraj.world import margin, packing
from crtraj.world.geometry import ShapeTerms
from crtraj.world.scene import Scene

_EPS_D2 = 1e-6  # mm^2, keeps the eq. 18 term finite if a point sits on a centre
_G_SCALE = 1e-3  # 1/mm^2: collision constraints in units of 1000 mm^2, O(1..10)
_G_SHAPE = 0.1  # 1/mm: shape constraints in cm


def config_scale(robot: Any) -> np.ndarray:
    """S (nx,): segment length L_k (mm/rad) for both bending entries of segment k, 1 for z."""
    s = np.ones(robot.nx)
    for k, seg in enumerate(robot.segments):
        s[2 * k : 2 * k + 2] = seg.length
    return s


@dataclass(frozen=True, eq=False)
class SteerQuery:
    """One steer step as asked (checked by `SteerSolver.solve`).

    x_prev (nx,): configuration (rad, mm); target (3,): tip position (mm); packed: the obstacles packed for
    the solver (`Scene.pack`); dsf: D_sf (mm); scene: the scene the re-check measures clearance in (None:
    the packed spheres); t, t_end: time (s) and, when the obstacles are held over an interval, its end;
    guess: initial configuration or None (the DLS predictor); damping_weight, obstacle_weight: w_d, w_o for
    this call (None: the options'); lbx, ubx: the step bounds at x_prev; check_start: refuse an x_prev in
    collision or outside the limits.
    """

    x_prev: np.ndarray
    target: np.ndarray
    packed: np.ndarray
    dsf: float
    scene: Scene | None
    t: float
    t_end: float | None
    guess: np.ndarray | None
    damping_weight: float | None
    obstacle_weight: float | None
    lbx: np.ndarray
    ubx: np.ndarray
    check_start: bool


@dataclass(frozen=True, eq=False)
class NlpCall:
    """The numeric inputs of one interpreted solve of the NLP: parameter vector p, constraint lower bounds
    lbg, start x0 (unscaled, within the bounds) and the step bounds lbx, ubx (unscaled)."""

    p: np.ndarray
    lbg: np.ndarray
    x0: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray


@dataclass(frozen=True, eq=False)
class Recheck:
    """The re-check quantities a backend computed itself at its x: tip (mm), clearance (mm), within limits."""

    tip: np.ndarray
    clearance: float
    in_limits: bool


@dataclass(frozen=True, eq=False)
class SteerSolution:
    """A backend's answer to a `SteerQuery`.

    x: configuration (rad, mm; may hold NaN); converged: the solver's own success; status: its return
    status; iterations: its iteration count (-1: not reported); solver: the label of what solved it
    ("ipopt", "sqp", "sqp>ipopt", "dls"); note: a prefix of the result's message (why a rescue ran);
    recheck: the re-check quantities at x when the backend computed them (None: `assess` evaluates them);
    call: the NLP inputs used, kept when the solve failed so that a rescue solves the same problem.
    """

    x: np.ndarray
    converged: bool
    status: str
    iterations: int
    solver: str
    note: str = ""
    recheck: Recheck | None = None
    call: NlpCall | None = None


class SteerNLP:
    """The steer NLP of one robot and obstacle count: symbolic problem, bounds and numeric helpers.

    `problem` is the ``nlpsol`` dictionary (x = y = S x, p, f, g); `check` maps x to (tip, tip Jacobian,
    collision points (3, n_points), limits). Parameters: ``p = [x_prev, target, packed obstacles, D_sf,
    w_d, w_o]``, the packed obstacles followed by the shapes' parameters of `terms` (`ShapeTerms`);
    constraints: the robot's limits, one row per (shape, collision point), then one row per (obstacle slot,
    collision point).
    """

    def __init__(self, model: Any, max_obstacles: int, options: SteerOptions, terms: ShapeTerms | None = None) -> None:
        self.terms = ShapeTerms(()) if terms is None else terms
        self.model = model
        self.robot = model.robot
        self.options = options
        self.max_obstacles = max_obstacles
        self.nx = model.nx
        self.n_points = int(options.n_points if options.n_points is not None else self.robot.collision_points)
        self.scale = config_scale(self.robot)
        self.box = self.robot.config_box()
        self._A, self._q0 = self.robot.cable_matrix()
        fpts = model.backbone if self.n_points == model.n_points else model.backbone_function(self.n_points)
        self.problem = self._problem(fpts)
        # one call gives everything the predictor and the re-check need
        xs = ca.SX.sym("x", self.nx)
        tip_s = model.tip(xs)
        self.check = ca.Function("steer_check", [xs], [tip_s, ca.jacobian(tip_s, xs), fpts(xs), model.limits(xs)])

    def _problem(self, fpts: ca.Function) -> dict[str, Any]:
        """The symbolic NLP (and its constraint bounds, set on self)."""
        nx, M = self.nx, self.max_obstacles
        # decision variable y = S x (mm): bending and z on one scale, so the
        # Hessian is well conditioned for the QP solvers and IPOPT alike
        y = ca.SX.sym("y", nx)
        S = ca.DM(self.scale)
        x = y / S
        x_prev = ca.SX.sym("x_prev", nx)
        target = ca.SX.sym("target", 3)
        # the packed spheres, then the shapes' parameters (`ShapeTerms.values`)
        obs = ca.SX.sym("obstacles", packing.WIDTH * M + self.terms.n_params)
        dsf = ca.SX.sym("safety_distance")
        w_d = ca.SX.sym("w_d")
        w_o = ca.SX.sym("w_o")
        p = ca.vertcat(x_prev, target, obs, dsf, w_d, w_o)
        self.n_params = int(p.numel())
        P = fpts(x)
        tip = self.model.tip(x)
        glim = self.model.limits(x)
        f = ca.sumsqr(tip - target) + w_d * ca.sumsqr(y - S * x_prev)
        g_col = []
        pen = 0
        for i in range(M):
            c, r, act = packing.slot(obs, i)
            rho = margin.keep_out_radius(r, dsf, self.robot.body_radius, self.options.margin)
            for j in range(self.n_points):
                d2 = ca.sumsqr(P[:, j] - c)
                # inactive slots give the constant g = 1 (and lbg = -inf, see
                # `lbg_for`) instead of a 1e12 mm^2 slack that stalls IPOPT
                g_col.append(act * _G_SCALE * (d2 - rho**2) + (1 - act))
                pen = pen + act * rho**2 / (d2 + _EPS_D2)
        f = f + w_o * pen
        # shapes: each point keeps D_sf + body + margin from each shape's lower bound over the window (in cm)
        keep = margin.keep_out_radius(0.0, dsf, self.robot.body_radius, self.options.margin)
        rows = self.terms.distances(P, obs[packing.WIDTH * M :]) if self.terms.shapes else []
        g_shape = [_G_SHAPE * (row - keep).T for row in rows]
        n_shape = self.n_points * len(rows)
        lbg_lim, ubg_lim = self.model.limit_bounds()
        self.n_col = len(g_col)
        self.lbg_lim, self.ubg_lim = lbg_lim, ubg_lim
        self.lbg = np.concatenate([lbg_lim, np.zeros(n_shape), np.zeros(self.n_col)])
        self.ubg = np.concatenate([ubg_lim, np.full(n_shape + self.n_col, np.inf)])
        return {"x": y, "p": p, "f": f, "g": ca.vertcat(glim, *g_shape, *g_col)}

    # ------------------------------------------------------------ numeric helpers
    def parameters(
        self,
        x_prev: np.ndarray,
        target: np.ndarray,
        packed: np.ndarray,
        safety_distance: float,
        damping_weight: float | None = None,
        obstacle_weight: float | None = None,
    ) -> np.ndarray:
        """The NLP parameter vector p (layout in the class docstring)."""
        wd = self.options.damping_weight if damping_weight is None else damping_weight
        wo = self.options.obstacle_weight if obstacle_weight is None else obstacle_weight
        return np.concatenate([x_prev, target, packed, [safety_distance, wd, wo]])

    def padding(self) -> np.ndarray:
        """Obstacle parameters with every sphere slot padding and the shapes as they are at t = 0."""
        return np.concatenate([packing.padding(self.max_obstacles), self.terms.values(0.0, 0.0)])

    def step_bounds(self, x_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Variable bounds: the config box intersected with ``|S (x - x_prev)|_inf <= max_step``."""
        d = self.options.max_step / self.scale
        lo, hi = self.box
        return np.maximum(lo, x_prev - d), np.minimum(hi, x_prev + d)

    def lbg_for(self, packed: np.ndarray) -> np.ndarray:
        """Constraint lower bounds for these packed obstacles: padding slots get free rows (lbg = -inf), no
        slack for the solver to carry."""
        lbg = self.lbg.copy()
        act = packing.active_flags(packed[: packing.WIDTH * self.max_obstacles])
        lbg[lbg.size - self.n_col :] = np.where(np.repeat(act, self.n_points), 0.0, -np.inf)
        return lbg

    def cable_lengths(self, x: np.ndarray) -> np.ndarray:
        """Cable lengths and z (mm) at x."""
        return self._A @ x + self._q0

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(tip (3,), J (3, nx), points (n_points, 3), limits g) at x."""
        tip, J, P, g = self.check(x)
        return (
            np.asarray(tip, dtype=float).reshape(-1),
            np.asarray(J, dtype=float),
            np.asarray(P, dtype=float).T,
            np.asarray(g, dtype=float).reshape(-1),
        )

    def limits_ok(self, g: np.ndarray, tol: float = 1e-6) -> bool:
        """The limits g within the robot's bounds, up to tol."""
        return bool(np.all(g >= self.lbg_lim - tol) and np.all(g <= self.ubg_lim + tol))

    def clearance(
        self, pts: np.ndarray, packed: np.ndarray, dsf: float, scene: Scene | None, t: float, t_end: float | None
    ) -> float:
        """Clearance (mm) of the constrained points: `Scene.clearance_points` (the same
        computation as `Scene.clearance`), or the packed spheres when no scene is given."""
        body = self.robot.body_radius
        if scene is not None:
            if t_end is None:
                return float(scene.clearance_points(pts, t, inflate=body))
            return float(scene.clearance_points_over(pts, t, t_end, inflate=body))
        centers, radii, active = packing.unpack(packed[: packing.WIDTH * self.max_obstacles])
        on = active > 0
        if not np.any(on):
            return math.inf
        d = np.linalg.norm(pts[:, None, :] - centers[on][None, :, :], axis=-1) - radii[on]
        return float(margin.clearance(d.min(), dsf, body))

    def dls_update(
        self, x: np.ndarray, tip: np.ndarray, J: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> np.ndarray:
        """One damped-least-squares step (eq. 17, scaled coordinates) from x with tip and J at x, clipped."""
        o = self.options
        Js = J / self.scale
        dy = Js.T @ np.linalg.solve(Js @ Js.T + o.damping**2 * np.eye(3), o.dls_gain * (target - tip))
        return np.clip(x + dy / self.scale, lo, hi)

    def check_start(self, query: SteerQuery, pts: np.ndarray, g: np.ndarray) -> None:
        """Raise `InputError` when x_prev (with points pts and limits g there) is outside the robot's limits
        or in collision."""
        xp, t = query.x_prev, query.t
        lo, hi = self.box
        if not self.limits_ok(g, 1e-9) or np.any(xp < lo - 1e-9) or np.any(xp > hi + 1e-9):
            raise InputError("x_prev: outside the robot's limits (theta, cable stroke or z range)")
        c0 = self.clearance(pts, query.packed, query.dsf, query.scene, t, query.t_end)
        start_collision(c0, self.options, query.dsf, t)


def start_collision(c0: float, options: SteerOptions, dsf: float, t: float) -> None:
    """Raise `InputError` when the start clearance c0 (mm) is below -feasibility_tolerance."""
    if c0 < -options.feasibility_tolerance:
        raise InputError(
            f"x_prev: start configuration is in collision (clearance {c0:.3f} mm, D_sf {dsf:g} mm, at t = {t:g} s)"
        )
