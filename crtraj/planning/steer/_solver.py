"""The safety-constrained steer step (paper eq. 15-18) as one NLP built once, and the DLS step.

Given the current configuration ``x_prev`` and a target tip position, the
steer step solves (mm, rad)

    min_x  |tip(x) - target|^2
           + w_d |S (x - x_prev)|^2                              (damping, eq. 17)
           + w_o sum_ij a_i rho_i^2 / (|p_j(x) - c_i|^2 + eps)     (obstacle term, eq. 18)
    s.t.   |p_j(x) - c_i|^2 >= a_i rho_i^2    for every collision point j, obstacle slot i
           model.limits(x) within model.limit_bounds()           (theta <= theta_max, cable strokes)
           x in robot.config_box(),  |S (x - x_prev)|_inf <= max_step

with ``rho_i = R_i + D_sf + body_radius + margin`` and ``a_i`` the slot's
active flag (padding slots: a = 0, constraint ``d^2 >= 0``, no penalty).

Scaling ``S = diag(L_1, L_1, ..., L_n, L_n, 1)``: a bending change du of
segment k moves points by up to about ``L_k du`` mm, so ``S dx`` is in mm
like the tip error and z; one number (`max_step`, mm) bounds the step, and
the solvers work in ``y = S x`` so their Hessians are well conditioned.

Mapping of the paper's coefficients (given for an unstated unit system):
``w_d = (damping * damping_scale)^2`` and ``w_o = (obstacle_coefficient *
obstacle_scale)^2``, defaults damping_scale = obstacle_scale = 0.02, so the
paper's 0.3 and 20 (40) give w_d = 3.6e-5 and w_o = 0.16 (0.64) per mm^2 of
tip error. Only ratios matter: the tip term dominates both (measured on
sim 1: the damping biases a 300 mm IK move by < 0.1 mm, the obstacle term
the tip by < 0.01 mm), while inside the 2-D null space the obstacle term
dominates the damping, so the body bends away from obstacles while the tip
tracks (the paper's "null-space solutions") and the damping picks the
smallest such motion. The paper iterates eq. 17, where the damping only
slows the approach to the target; one NLP with a small damping weight
reaches that fixed point in one solve.

Safety between collision points: the hard constraints hold at `n_points`
backbone points (the paper's ten, 44 mm apart on cdsr2). Between two
neighbours the arc can dip toward a sphere by the chord depth
``sqrt(rho^2 + h^2/4) - rho`` (3.3 mm for the sim-1 spheres) plus the arc's
sagitta (1.9 mm at theta = pi/2 per segment, 3.8 mm at theta = pi). D_sf =
5 mm absorbs this, so the dense body stays outside every sphere surface
plus the disc radius (the tests check 200 points); to keep the full D_sf
densely as well, raise `margin` (mm, added to every keep-out radius) or
`n_points`.

How a step is solved is one backend (`planning.steer_backends`: IPOPT, sqp with daqp, sqp with an IPOPT rescue,
the compiled C step, DLS), chosen once when the `SteerSolver` is built; the NLP itself is `planning.steer_nlp`,
the options `planning.steer_options`, the re-check of a solution `planning.steer_result`.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.steer._backends import (
    DlsBackend,
    IpoptBackend,
    RescuedBackend,
    SolverFactory,
    SqpBackend,
    SteerBackend,
    WarmStart,
)
from crtraj.planning.steer._compiled import build_compiled
from crtraj.planning.steer._nlp import SteerNLP, SteerQuery, config_scale
from crtraj.planning.steer._options import (
    SteerOptions,
)
from crtraj.planning.steer._result import SteerResult, assess
from crtraj.world import packing
from crtraj.world.geometry import ShapeTerms
from crtraj.world.scene import Scene

__all__ = ["SteerSolver", "dls_step"]


def dls_step(
    model: Any,
    x: Any,
    target: Any,
    damping: float = 0.3,
    *,
    gain: float = 1.0,
    max_step: float | None = None,
    clip: bool = True,
) -> np.ndarray:
    """One damped-least-squares step (paper eq. 15-17); returns the new configuration.

    Solves ``min |J S^-1 dy - K_P e|^2 + lambda^2 |dy|^2`` in the scaled
    coordinates ``dy = S dx`` (mm; see `config_scale`), so lambda = damping
    is dimensionless as in the paper's cable-space form; e = target - tip (mm),
    K_P = gain. ``max_step`` (mm) shrinks dy to ``|dy|_inf <= max_step``;
    ``clip`` keeps the result inside ``robot.config_box()``. No obstacle
    constraints: check the result with `Scene.clearance`.
    """
    xv = _vec(x, "x", model.nx)
    tv = _vec(target, "target", 3)
    S = config_scale(model.robot)
    e = tv - model.tip_position(xv)
    Js = model.jacobian(xv) / S
    dy = Js.T @ np.linalg.solve(Js @ Js.T + damping**2 * np.eye(3), gain * e)
    if max_step is not None:
        big = np.max(np.abs(dy))
        if big > max_step:
            dy *= max_step / big
    xn = xv + dy / S
    if clip:
        lo, hi = model.robot.config_box()
        xn = np.clip(xn, lo, hi)
    return xn


def _vec(v: Any, name: str, n: int) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected {n} numbers") from None
    if a.shape != (n,):
        raise InputError(f"{name}: expected shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or infinity")
    return a


class SteerSolver:
    """The steer NLP of one robot, built once for up to `max_obstacles` obstacles, and its backend.

    Parameters enter as one vector ``p = [x_prev (nx), target (3), packed
    obstacles (packing.WIDTH * max_obstacles, see `Scene.pack`), D_sf, w_d, w_o]``;
    nothing is rebuilt between calls. Each solve starts from a DLS predictor
    (one eq. 17 step from x_prev, option `predictor`) unless x0 is given,
    and, with `warm_start`, from the multipliers of the previous successful
    solve. The backend (`backend`) is chosen here from `options.solver`,
    `compiled` and `fallback`; a given `backend` (one built for the same NLP:
    model, obstacle count and options) is used instead.
    """

    def __init__(
        self,
        model: Any,
        max_obstacles: int = 8,
        options: SteerOptions | None = None,
        *,
        backend: SteerBackend | None = None,
    ) -> None:
        if not isinstance(max_obstacles, (int, np.integer)) or max_obstacles < 0:
            raise InputError(f"max_obstacles: must be an integer >= 0, got {max_obstacles!r}")
        self.model = model
        self.robot = model.robot
        self.max_obstacles = int(max_obstacles)
        self.options = options if options is not None else SteerOptions()
        self.nlp = SteerNLP(model, self.max_obstacles, self.options)
        self.n_points = self.nlp.n_points
        self.nx = model.nx
        self.scale = self.nlp.scale
        self.box = self.nlp.box
        self.n_params = self.nlp.n_params
        self.n_col = self.nlp.n_col
        self.jit_message = ""
        self.compiled_message = ""
        self._factory: SolverFactory | None = None
        self._memo: tuple[Any, float, float | None, np.ndarray] | None = None  # last (scene, t, t_end, packed)
        self.backend: SteerBackend = backend if backend is not None else self._choose_backend()
        self._shapes_key: tuple[int, ...] = ()  # the scene shapes the NLP was built for (`_use_shapes`)

    def _use_shapes(self, shapes: tuple[Any, ...]) -> None:
        """Rebuild the NLP and its backend when a query brings other shapes than the NLP's (their poses are
        parameters: a moving shape does not rebuild). With shapes the compiled step is not used: its re-check
        measures the packed spheres only."""
        key = tuple(id(ms) for ms in shapes)
        if key == self._shapes_key:
            return
        self._shapes_key = key
        self.nlp = SteerNLP(self.model, self.max_obstacles, self.options, ShapeTerms(tuple(shapes)))
        self.n_params, self.n_col = self.nlp.n_params, self.nlp.n_col
        self._memo = None
        self.backend = self._choose_backend()

    def _choose_backend(self) -> SteerBackend:
        """The backend of the options, built once (`jit_message` and `compiled_message` say how it went)."""
        o, nlp = self.options, self.nlp
        if o.solver == "dls":
            return DlsBackend(nlp)
        self._factory = factory = SolverFactory(nlp)  # kept: it owns the jit's folder
        warm = WarmStart(o.uses_warm_start)
        backend: SteerBackend
        if o.solver == "ipopt":
            backend = IpoptBackend.build(factory, warm)
        else:
            backend = SqpBackend.build(factory, warm)
            if o.compiled and not nlp.terms.shapes:
                compiled, self.compiled_message = build_compiled(nlp, {**factory.plain, **factory.sqp_options()}, warm)
                backend = backend if compiled is None else compiled
            if o.fallback:
                backend = RescuedBackend(backend, IpoptBackend.build(factory, warm, rescue=True))
        self.jit_message = factory.jit_message
        return backend

    @property
    def jit_directory(self) -> Path | None:
        """The folder holding the jit's compiled objects (removed with the solver); None without jit."""
        if self._factory is None or self._factory.jit_dir is None:
            return None
        return Path(self._factory.jit_dir.name)

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        x_prev: Any,
        target: Any,
        obstacles: Scene | Any = None,
        *,
        t: float = 0.0,
        t_end: float | None = None,
        safety_distance: float | None = None,
        x0: Any = None,
        obstacle_weight: float | None = None,
        damping_weight: float | None = None,
        check_start: bool = True,
    ) -> SteerResult:
        """One steer step from configuration x_prev toward tip position `target` (mm).

        obstacles: a `Scene` (evaluated at time t (s), or held conservatively
        over [t, t_end] with `Scene.pack_over` when t_end is given), a packed
        vector from `Scene.pack` (then give `safety_distance`), or None.
        x0: initial guess (default: the DLS predictor). obstacle_weight,
        damping_weight: override w_o, w_d for this call. check_start: raise
        `InputError` when x_prev is in collision or outside the robot's limits.
        """
        t_start = time.perf_counter()
        xp = _vec(x_prev, "x_prev", self.nx)
        tg = _vec(target, "target", 3)
        if not math.isfinite(float(t)):
            raise InputError(f"t: must be finite, got {t}")
        if t_end is not None and not (math.isfinite(float(t_end)) and t_end >= t):
            raise InputError(f"t_end: must be finite and >= t = {t}, got {t_end}")
        self._use_shapes(obstacles.shapes if isinstance(obstacles, Scene) else ())
        packed, dsf, scene = self._packed(obstacles, float(t), t_end, safety_distance)
        guess = None if x0 is None else _vec(x0, "x0", self.nx)
        lbx, ubx = self.step_bounds(xp)
        in_scene = self.backend.recheck_in_scene
        query = SteerQuery(
            x_prev=xp,
            target=tg,
            packed=packed,
            dsf=dsf,
            scene=scene if in_scene else None,
            t=float(t),
            t_end=t_end if in_scene else None,
            guess=guess,
            damping_weight=damping_weight,
            obstacle_weight=obstacle_weight,
            lbx=lbx,
            ubx=ubx,
            check_start=check_start,
        )
        return assess(self.nlp, query, self.backend.solve(query), t_start)

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve."""
        self.backend.reset_warm_start()

    # -------------------------------------------------------------- helpers
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
        return self.nlp.parameters(x_prev, target, packed, safety_distance, damping_weight, obstacle_weight)

    def step_bounds(self, x_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Variable bounds: the config box intersected with ``|S (x - x_prev)|_inf <= max_step``."""
        return self.nlp.step_bounds(x_prev)

    def predict(self, x_prev: np.ndarray, target: np.ndarray) -> np.ndarray:
        """One DLS step (eq. 17, scaled coordinates) from x_prev, inside the step bounds."""
        tip, J, _, _ = self.nlp.evaluate(x_prev)
        return self.nlp.dls_update(x_prev, tip, J, target, *self.step_bounds(x_prev))

    def _packed(
        self, obstacles: Any, t: float, t_end: float | None, safety_distance: float | None
    ) -> tuple[np.ndarray, float, Scene | None]:
        """(packed obstacles, D_sf (mm), the scene or None) of `solve`'s obstacles at t (over [t, t_end])."""
        if isinstance(obstacles, Scene):
            memo = self._memo
            if memo is not None and memo[0] is obstacles and memo[1] == t and memo[2] == t_end:
                packed = memo[3]  # a Scene is frozen: the same scene at the same times packs the same
            else:
                pack = obstacles.pack(t, self.max_obstacles) if t_end is None else None
                pack = obstacles.pack_over(t, t_end, self.max_obstacles) if pack is None else pack
                origin = obstacles.time_origin
                shapes = self.nlp.terms.values(t + origin, (t if t_end is None else t_end) + origin)
                packed = np.concatenate([pack, shapes]) if shapes.size else pack
            self._memo = (obstacles, t, t_end, packed)
            dsf = obstacles.safety_distance if safety_distance is None else float(safety_distance)
            return packed, dsf, obstacles
        if obstacles is None:
            packed = packing.padding(self.max_obstacles)
            if safety_distance is None:
                safety_distance = 0.0
        else:
            packed = _vec(obstacles, "obstacles", packing.WIDTH * self.max_obstacles)
        if safety_distance is None:
            raise InputError("safety_distance: required (mm) when obstacles are given as a packed vector")
        dsf = float(safety_distance)
        if not (math.isfinite(dsf) and dsf >= 0):
            raise InputError(f"safety_distance: must be >= 0 mm, got {safety_distance}")
        return packed, dsf, None
