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
"""

from __future__ import annotations

import enum
import math
import shutil
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.core.options import Options, option
from crtraj.model.robot import MAX_COLLISION_POINTS
from crtraj.planning.compiled_nlp import CODEGEN_QP, CompiledFunction, compiled_library
from crtraj.world import margin, packing
from crtraj.world.scene import Scene

SOLVERS = ("ipopt", "sqp", "dls")
QP_SOLVERS = ("daqp", "qrqp", "qpoases", "osqp", "proxqp", "highs")

# Default IPOPT options (overridable from [steer.ipopt]; tol and max_iter
# come from [steer]). The NLP is tiny (nx = 2n + 1 variables), so IPOPT's
# per-iteration overhead dominates: the exact Hessian (SX) keeps iterations
# at 5-8; the adaptive barrier took fewer iterations than monotone in our
# measurements; bound_push/frac 1e-8 keep the warm start where it is; mumps
# is the linear solver bundled with CasADi.
IPOPT_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "print_level": 0,
        "sb": "yes",
        "linear_solver": "mumps",
        "hessian_approximation": "exact",
        "acceptable_tol": 1e-6,
        "acceptable_iter": 5,
        "constr_viol_tol": 1e-8,
        "mu_strategy": "adaptive",
        "mu_init": 1e-2,
        "bound_push": 1e-8,
        "bound_frac": 1e-8,
    }
)

# Default sqpmethod options (overridable from [steer.sqp]).
SQP_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "hessian_approximation": "exact",
        # "regularize" shifts the whole spectrum and made steps crawl (linear
        # convergence, > 50 iterations); reflecting the negative eigenvalues of the
        # 5 x 5 Hessian keeps Newton steps (~6 iterations) and, unlike clipping
        # them to ~0, no near-flat direction sends the QP step to the bounds
        "convexify_strategy": "eigen-reflect",
        # CasADi's symmetric eigen solver stops after max_iter_eig sweeps and the
        # SQP then aborts; 50 (the default) failed on 7% of the benchmark steers,
        # 5000 on none, and converged cases stop early anyway
        "max_iter_eig": 5000,
        "tol_pr": 1e-8,
        "tol_du": 1e-6,
        "min_step_size": 1e-12,
    }
)

_EPS_D2 = 1e-6  # mm^2, keeps the eq. 18 term finite if a point sits on a centre
_G_SCALE = 1e-3  # 1/mm^2: collision constraints in units of 1000 mm^2, O(1..10)


# Most raw solver options per [steer.ipopt] / [steer.sqp] table (each solver knows a few hundred).
MAX_SOLVER_OPTIONS = 1000


def _bad_solver_value(v: Any) -> str | None:
    """Why `v` is not a raw solver option value (a string, a finite number or a boolean), or None."""
    if not isinstance(v, (bool, int, float, str)):
        return f"expected a string, number or boolean, got {v!r:.60}"
    if isinstance(v, float) and not math.isfinite(v):
        return f"must be finite, got {v}"
    # solver options are counts, levels and tolerances; IPOPT's own "infinity" is 1e19
    if isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) > 1e20:
        return f"must be within +-1e20, got {float(v):g}"
    if isinstance(v, str) and len(v) > 1000:
        return "longer than 1000 characters"
    return None


def _pairs(t: Table) -> tuple[tuple[str, Any], ...]:
    """Solver option overrides read from a TOML table: every value a string, number or boolean."""
    keys = t.keys()
    if len(keys) > MAX_SOLVER_OPTIONS:
        raise InputError(f"{t.path}: at most {MAX_SOLVER_OPTIONS} solver options, got {len(keys)}")
    out = []
    for key in keys:
        v = t.raw(key)
        problem = _bad_solver_value(v)
        if problem is not None:
            raise t.error(key, problem)
        out.append((key, v))
    t.finish()
    return tuple(out)


def _check_pairs(pairs: Any, name: str) -> tuple[tuple[str, Any], ...]:
    """The same rules for overrides given in Python, as a sequence of (name, value) pairs."""
    if not isinstance(pairs, (tuple, list)) or len(pairs) > MAX_SOLVER_OPTIONS:
        raise InputError(f"{name}: expected at most {MAX_SOLVER_OPTIONS} (name, value) pairs, got {pairs!r:.60}")
    out = []
    for i, pair in enumerate(pairs):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2 and isinstance(pair[0], str)):
            raise InputError(f"{name}[{i}]: expected a (name, value) pair, got {pair!r:.60}")
        key, v = pair
        if not key or len(key) > 200 or not key.isprintable():
            raise InputError(f"{name}[{i}]: an option name is 1 to 200 printable characters, got {key!r:.60}")
        problem = _bad_solver_value(v)
        if problem is not None:
            raise InputError(f"{name}.{key}: {problem}")
        out.append((key, v))
    return tuple(out)


@dataclass(frozen=True)
class SteerOptions(Options):
    """Options of the ``[steer]`` section (units mm, rad, s).

    solver: "ipopt" (default), "sqp" (CasADi sqpmethod + `qpsol`, the fast
    path) or "dls" (iterated damped least squares, eq. 17, no hard
    constraints). damping, obstacle_coefficient: the paper's lambda and mu;
    damping_scale, obstacle_scale: their mapping to NLP weights (module
    docstring). max_step: bound on ``|S (x - x_prev)|_inf`` (mm). tolerance:
    tip error (mm) counted as reached. margin: extra keep-out (mm) added to
    every obstacle in the hard constraints. n_points: constrained backbone
    points (default the robot's collision_points). max_iter, tol: solver
    iteration cap and tolerance (IPOPT `tol`; sqpmethod `tol_pr`; its
    `tol_du` is 1e-6 in SQP_DEFAULTS). qpsol: QP solver of the sqp path.
    jit: compile the NLP functions with gcc through CasADi's shell compiler
    (falls back to no jit, with `SteerSolver.jit_message` saying why).
    compiled: with solver "sqp" and qpsol daqp or qrqp, generate C for the
    whole step (DLS predictor, sqpmethod with its QP solver, the re-check's
    tip, points and limits, the KKT residuals), compile it once (cached) and
    call it through ctypes: one foreign call per steer. Its convergence is
    judged from the KKT residuals it returns (sqpmethod's own test,
    tol_pr/tol_du); the generated code reports no iteration count
    (`SteerResult.iterations` is -1). Without a C compiler, or with another
    qpsol, the interpreted solver runs (`SteerSolver.compiled_message` says so).
    warm_start: start from the previous successful solve's multipliers
    (default None = on for sqp, where it saved iterations, off for IPOPT,
    where warm_start_init_point cost more time than the iteration it
    saved). fallback: when the sqp path does not converge, re-solve with
    IPOPT (result.solver is then "sqp>ipopt"). predictor: start from one
    DLS step instead of x_prev. feasibility_tolerance: constraint slack (mm)
    accepted by the re-check. dls_gain, dls_iterations: K_P and iterations
    of the dls path. ipopt, sqp: raw solver options overriding the defaults
    (``[steer.ipopt]`` / ``[steer.sqp]`` tables; (name, value) pairs in Python).
    """

    SECTION: ClassVar[str] = "steer"

    solver: str = option("ipopt", choices=SOLVERS)
    damping: float = option(0.3, ge=0.0)
    obstacle_coefficient: float = option(20.0, ge=0.0)
    damping_scale: float = option(0.02, gt=0.0)
    obstacle_scale: float = option(0.02, gt=0.0)
    max_step: float = option(100.0, gt=0.0, limit=MAX_LENGTH)
    tolerance: float = option(0.5, gt=0.0, limit=MAX_LENGTH)
    margin: float = option(0.0, ge=0.0, limit=MAX_LENGTH)
    n_points: int | None = option(None, ge=2, le=MAX_COLLISION_POINTS)
    max_iter: int = option(100, ge=1, le=100_000)
    tol: float = option(1e-6, gt=0.0)
    qpsol: str = option("daqp", choices=QP_SOLVERS)
    jit: bool = option(False)
    compiled: bool = option(False)
    warm_start: bool | None = option(None)
    fallback: bool = option(True)
    predictor: bool = option(True)
    feasibility_tolerance: float = option(1e-5, ge=0.0)
    dls_gain: float = option(1.0, gt=0.0, le=1.0)
    dls_iterations: int = option(200, ge=1, le=100_000)
    ipopt: tuple[tuple[str, Any], ...] = option((), read=False)
    sqp: tuple[tuple[str, Any], ...] = option((), read=False)

    def _check(self) -> None:
        object.__setattr__(self, "ipopt", _check_pairs(self.ipopt, "steer.ipopt"))
        object.__setattr__(self, "sqp", _check_pairs(self.sqp, "steer.sqp"))

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        return {"ipopt": _pairs(t.table("ipopt")), "sqp": _pairs(t.table("sqp"))}

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the ``[steer]`` schema (round-trips through `from_table`).

        Own override: the raw solver options are sub-tables in the file (``[steer.ipopt]``), not the
        list of pairs the base would write; empty ones are left out.
        """
        d = super().to_dict()
        for key in ("ipopt", "sqp"):
            pairs = d.pop(key)
            if pairs:
                d[key] = {k: v for k, v in pairs}
        return d

    @property
    def uses_warm_start(self) -> bool:
        """The warm_start setting resolved per solver."""
        return self.warm_start if self.warm_start is not None else self.solver == "sqp"

    @property
    def damping_weight(self) -> float:
        """w_d = (damping * damping_scale)^2, weight of |S dx|^2 (mm^2)."""
        return (self.damping * self.damping_scale) ** 2

    @property
    def obstacle_weight(self) -> float:
        """w_o = (obstacle_coefficient * obstacle_scale)^2, weight of the eq. 18 sum (mm^2)."""
        return (self.obstacle_coefficient * self.obstacle_scale) ** 2


class SteerStatus(str, enum.Enum):
    """Outcome of one steer step."""

    REACHED = "reached"  # converged, re-checked safe, tip on the target: the step did what was asked
    PARTIAL = "partial"  # converged and safe, but the tip stopped short (an unreachable target): x is usable
    UNSAFE = "unsafe"  # the solver converged but the re-check (points, limits, bounds) fails
    FAILED = "failed"  # the solver did not converge

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class SteerResult:
    """Outcome of one steer step.

    x: configuration (rad, mm); q: cable lengths and z (mm); tip: tip
    position (mm). converged: the solver's own success flag. safe: the
    re-check (collision points vs obstacles, limits, bounds) holds.
    reached: tip_error <= tolerance. `status` sums them up (`SteerStatus`):
    PARTIAL means converged and safe, a trustworthy x that stopped short of
    an unreachable target; `is_success()` only for REACHED.
    solver_status: the solver's own return status.
    message: one line for people. iterations; wall_time (s, whole call);
    tip_error (mm); min_clearance (mm, `Scene.clearance` at t, or the swept
    bound over [t, t_end]).
    """

    x: np.ndarray
    q: np.ndarray
    tip: np.ndarray
    reached: bool
    converged: bool
    safe: bool
    solver_status: str
    message: str
    iterations: int
    wall_time: float
    tip_error: float
    min_clearance: float
    solver: str

    @property
    def status(self) -> SteerStatus:
        """REACHED, PARTIAL (usable x, target not reached), UNSAFE or FAILED."""
        if not self.converged:
            return SteerStatus.FAILED
        if not self.safe:
            return SteerStatus.UNSAFE
        return SteerStatus.REACHED if self.reached else SteerStatus.PARTIAL

    def is_success(self) -> bool:
        """Converged, re-checked safe and the tip reached the target within tolerance."""
        return self.status is SteerStatus.REACHED

    def to_dict(self) -> dict[str, Any]:
        return {
            "x": self.x.tolist(),
            "q": self.q.tolist(),
            "tip": self.tip.tolist(),
            "status": str(self.status),
            "success": self.is_success(),
            "reached": self.reached,
            "converged": self.converged,
            "safe": self.safe,
            "solver_status": self.solver_status,
            "message": self.message,
            "iterations": self.iterations,
            "wall_time": self.wall_time,
            "tip_error": self.tip_error,
            "min_clearance": self.min_clearance,
            "solver": self.solver,
        }


def config_scale(robot: Any) -> np.ndarray:
    """S (nx,): segment length L_k (mm/rad) for both bending entries of segment k, 1 for z."""
    s = np.ones(robot.nx)
    for k, seg in enumerate(robot.segments):
        s[2 * k : 2 * k + 2] = seg.length
    return s


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
    """The steer NLP of one robot, built once for up to `max_obstacles` obstacles.

    Parameters enter as one vector ``p = [x_prev (nx), target (3), packed
    obstacles (packing.WIDTH * max_obstacles, see `Scene.pack`), D_sf, w_d, w_o]``;
    nothing is rebuilt between calls. Each solve starts from a DLS predictor
    (one eq. 17 step from x_prev, option `predictor`) unless x0 is given,
    and, with `warm_start`, from the multipliers of the previous successful
    solve.
    """

    def __init__(self, model: Any, max_obstacles: int = 8, options: SteerOptions | None = None) -> None:
        if not isinstance(max_obstacles, (int, np.integer)) or max_obstacles < 0:
            raise InputError(f"max_obstacles: must be an integer >= 0, got {max_obstacles!r}")
        self.model = model
        self.robot = model.robot
        self.max_obstacles = int(max_obstacles)
        self.options = options if options is not None else SteerOptions()
        o = self.options
        self.n_points = int(o.n_points if o.n_points is not None else self.robot.collision_points)
        self.nx = model.nx
        self.scale = config_scale(self.robot)
        self.box = self.robot.config_box()
        self.jit_message = ""
        self.compiled_message = ""
        self._step: CompiledFunction | None = None
        self._memo: tuple[Any, float, float | None, np.ndarray] | None = None  # last (scene, t, t_end, packed)
        self._lbg_memo: tuple[np.ndarray, np.ndarray] | None = None  # last (packed, lbg) of the compiled step
        self._A, self._q0 = self.robot.cable_matrix()
        self._lam_g: np.ndarray | None = None
        self._lam_x: np.ndarray | None = None
        self._build()

    # ------------------------------------------------------------------ build
    # Long by design: one symbolic NLP, its constraints and the solver variants built from it in one place.
    def _build(self) -> None:
        o, nx, M = self.options, self.nx, self.max_obstacles
        # decision variable y = S x (mm): bending and z on one scale, so the
        # Hessian is well conditioned for the QP solvers and IPOPT alike
        y = ca.SX.sym("y", nx)
        S = ca.DM(self.scale)
        x = y / S
        x_prev = ca.SX.sym("x_prev", nx)
        target = ca.SX.sym("target", 3)
        obs = ca.SX.sym("obstacles", packing.WIDTH * M)
        dsf = ca.SX.sym("safety_distance")
        w_d = ca.SX.sym("w_d")
        w_o = ca.SX.sym("w_o")
        p = ca.vertcat(x_prev, target, obs, dsf, w_d, w_o)
        self.n_params = int(p.numel())
        model = self.model
        fpts = model.backbone if self.n_points == model.n_points else model.backbone_function(self.n_points)
        P = fpts(x)
        tip = self.model.tip(x)
        glim = self.model.limits(x)
        f = ca.sumsqr(tip - target) + w_d * ca.sumsqr(y - S * x_prev)
        g_col = []
        pen = 0
        for i in range(M):
            c, r, act = packing.slot(obs, i)
            rho = margin.keep_out_radius(r, dsf, self.robot.body_radius, o.margin)
            for j in range(self.n_points):
                d2 = ca.sumsqr(P[:, j] - c)
                # inactive slots give the constant g = 1 (and lbg = -inf, see
                # _solve_nlp) instead of a 1e12 mm^2 slack that stalls IPOPT
                g_col.append(act * _G_SCALE * (d2 - rho**2) + (1 - act))
                pen = pen + act * rho**2 / (d2 + _EPS_D2)
        f = f + w_o * pen
        lbg_lim, ubg_lim = self.model.limit_bounds()
        self.n_col = len(g_col)
        self._lbg_lim, self._ubg_lim = lbg_lim, ubg_lim
        self._lbg = np.concatenate([lbg_lim, np.zeros(self.n_col)])
        self._ubg = np.concatenate([ubg_lim, np.full(self.n_col, np.inf)])
        nlp = {"x": y, "p": p, "f": f, "g": ca.vertcat(glim, *g_col)}
        # one call gives everything the predictor and the re-check need
        xs = ca.SX.sym("x", nx)
        tip_s = self.model.tip(xs)
        self._check = ca.Function("steer_check", [xs], [tip_s, ca.jacobian(tip_s, xs), fpts(xs), self.model.limits(xs)])
        self._solver = None
        self._solver_ws = None
        self._fallback = None
        if o.solver == "dls":
            return
        common: dict[str, Any] = {"print_time": False, "error_on_fail": False, "calc_lam_p": False}
        if o.jit:
            if shutil.which("gcc") is None:
                self.jit_message = "jit requested but gcc was not found: running without jit"
            else:
                # CasADi's shell compiler writes its C and object files to the working
                # directory unless told otherwise; keep them in a folder owned by this solver,
                # which removes it (so CasADi's own clean-up is off: it would warn at exit).
                self._jit_dir = tempfile.TemporaryDirectory(prefix="crtraj-jit-")
                jit_opts = {
                    "compiler": "gcc",
                    "flags": ["-O2"],
                    "directory": self._jit_dir.name + "/",
                    "cleanup": False,
                }
                common.update({"jit": True, "compiler": "shell", "jit_options": jit_opts, "jit_cleanup": False})
                self.jit_message = "jit: compiled with gcc -O2"
        ip = dict(IPOPT_DEFAULTS)
        ip.update({"tol": o.tol, "max_iter": o.max_iter})
        ip.update(dict(o.ipopt))
        if o.solver == "ipopt":
            self._solver = self._nlpsol("ipopt", nlp, {**common, "ipopt": ip}, "steer.ipopt")
            if o.uses_warm_start:
                ws = {**ip, "warm_start_init_point": "yes"}
                self._solver_ws = self._nlpsol("ipopt", nlp, {**common, "ipopt": ws}, "steer.ipopt")
            self._probe()  # IPOPT reads its options at the first solve: surface bad ones now
        else:
            sq = dict(SQP_DEFAULTS)
            sq.update({"max_iter": o.max_iter, "tol_pr": o.tol, "qpsol": o.qpsol})
            sq.update({"qpsol_options": _qp_options(o.qpsol), "print_header": False})
            sq.update({"print_iteration": False, "print_status": False})
            sq.update(dict(o.sqp))
            self._solver = self._nlpsol("sqpmethod", nlp, {**common, **sq}, "steer.sqp")
            if o.compiled:
                plain = {k: v for k, v in common.items() if k not in ("jit", "compiler", "jit_options")}
                self._build_compiled(nlp, {**plain, **sq})
            if o.fallback:
                # rare sqp failures (a QP solver's inexact multipliers stall the
                # dual test) are re-solved by IPOPT, built without jit
                plain = {k: v for k, v in common.items() if k not in ("jit", "compiler", "jit_options")}
                self._fallback = self._nlpsol("ipopt", nlp, {**plain, "ipopt": ip}, "steer.ipopt")
                self._probe()

    def _build_compiled(self, nlp: dict[str, Any], sqp_opts: dict[str, Any]) -> None:
        """The whole steer step as one generated C function (option `compiled`), loaded through ctypes.

        Inputs: x_prev, target, packed obstacles, [D_sf, w_d, w_o], lbx, ubx (unscaled), lbg, x0 and
        use_x0 (1: start from x0, 0: from the DLS predictor), lam_x0, lam_g0. Outputs: x (clipped to
        the bounds), lam_x, lam_g, the primal and dual KKT residuals, the tip at x, and at x and at x_prev
        (the start check) the smallest distance to an active sphere's surface (mm) and the smallest slack
        of the robot's limits (and, at x_prev, of the configuration box).
        """
        o = self.options
        if o.qpsol not in CODEGEN_QP:
            self.compiled_message = (
                f"compiled: qpsol {o.qpsol!r} generates no C (use {' or '.join(CODEGEN_QP)}): interpreted solver"
            )
            return
        nx, n_obs = self.nx, packing.WIDTH * self.max_obstacles
        solver = ca.nlpsol("steer_nlp", "sqpmethod", nlp, sqp_opts)
        y, p = nlp["x"], nlp["p"]
        lam_gs = ca.SX.sym("lam_g", self._lbg.size)
        lam_xs = ca.SX.sym("lam_x", nx)
        grad = ca.gradient(nlp["f"], y) + ca.jacobian(nlp["g"], y).T @ lam_gs + lam_xs
        kkt = ca.Function("steer_kkt", [y, p, lam_gs, lam_xs], [ca.norm_inf(grad)])
        xs = ca.SX.sym("x", nx)
        tgs = ca.SX.sym("target", 3)
        los, his = ca.SX.sym("lo", nx), ca.SX.sym("hi", nx)
        tip, J, _, _ = self._check(xs)
        Js = J / ca.repmat(ca.DM(self.scale).T, 3, 1)
        dy = Js.T @ ca.solve(Js @ Js.T + o.damping**2 * ca.SX.eye(3), o.dls_gain * (tgs - tip))
        pred = ca.Function("steer_pred", [xs, tgs, los, his], [ca.fmin(ca.fmax(xs + dy / self.scale, los), his)])
        S = ca.DM(self.scale)
        xp, tg, ob = ca.MX.sym("x_prev", nx), ca.MX.sym("target", 3), ca.MX.sym("obstacles", n_obs)
        w, lbx, ubx = ca.MX.sym("weights", 3), ca.MX.sym("lbx", nx), ca.MX.sym("ubx", nx)
        lbg, x0, use_x0 = ca.MX.sym("lbg", self._lbg.size), ca.MX.sym("x0", nx), ca.MX.sym("use_x0")
        lx0, lg0 = ca.MX.sym("lam_x0", nx), ca.MX.sym("lam_g0", self._lbg.size)
        start = ca.if_else(use_x0, x0, pred(xp, tg, lbx, ubx) if o.predictor else xp)
        start = ca.fmin(ca.fmax(start, lbx), ubx)
        pv = ca.vertcat(xp, tg, ob, w)
        sol = solver(x0=start * S, p=pv, lbx=lbx * S, ubx=ubx * S, lbg=lbg, ubg=self._ubg, lam_x0=lx0, lam_g0=lg0)
        ys, g = sol["x"], sol["g"]
        pr = ca.mmax(ca.vertcat(0, lbx * S - ys, ys - ubx * S, lbg - g, g - self._ubg))
        du = kkt(ys, pv, sol["lam_g"], sol["lam_x"])
        x = ca.fmin(ca.fmax(ys / S, lbx), ubx)
        tip_x, _, P, glim = self._check(x)
        _, _, P0, glim0 = self._check(xp)
        lo_lim, hi_lim = ca.DM(self._lbg_lim), ca.DM(self._ubg_lim)
        box_lo, box_hi = ca.DM(self.box[0]), ca.DM(self.box[1])
        name = f"steer_step_{self.robot.n_segments}s_{self.max_obstacles}o_{self.n_points}p"
        step = ca.Function(
            name,
            [xp, tg, ob, w, lbx, ubx, lbg, x0, use_x0, lx0, lg0],
            [
                *(x, sol["lam_x"], sol["lam_g"], pr, du, tip_x),
                *(self._surface_distance(P, ob), ca.mmin(ca.vertcat(glim - lo_lim, hi_lim - glim))),
                self._surface_distance(P0, ob),
                ca.mmin(ca.vertcat(glim0 - lo_lim, hi_lim - glim0, xp - box_lo, box_hi - xp)),
            ],
        )
        try:
            lib, how = compiled_library(name, [step], o.qpsol)
        except (RuntimeError, OSError) as exc:
            self.compiled_message = f"compiled: build failed ({_last_line(str(exc))}): interpreted solver"
            return
        if lib is None:
            self.compiled_message = f"compiled: {how}"
            return
        self._step = CompiledFunction(lib, name)
        self._tol = (float(sqp_opts["tol_pr"]), float(sqp_opts["tol_du"]))
        self.compiled_message = f"compiled: {how}"

    def _surface_distance(self, P: ca.MX, ob: ca.MX) -> ca.MX:
        """Smallest distance (mm) of the points P (3, n) to an active sphere's surface of the packed `ob`
        (+1e12 without one): the compiled step's re-check quantity, as `_clearance` computes it in numpy."""
        d = [ca.MX(1e12)]
        for i in range(self.max_obstacles):
            c, r, act = packing.slot(ob, i)
            diff = P - ca.repmat(c, 1, P.shape[1])
            dist = ca.mmin(ca.sqrt(ca.sum1(diff * diff))) - r
            d.append(ca.if_else(act > 0, dist, 1e12))
        return ca.mmin(ca.vertcat(*d))

    def _nlpsol(self, plugin: str, nlp: dict[str, Any], opts: dict[str, Any], field_name: str) -> ca.Function:
        try:
            solver = ca.nlpsol(f"steer_{plugin}", plugin, nlp, opts)
        except RuntimeError as exc:
            text = str(exc)
            if opts.get("jit"):
                # a broken compiler must not make the steer unusable
                self.jit_message = f"jit failed ({_last_line(text)}): running without jit"
                opts = {k: v for k, v in opts.items() if k not in ("jit", "compiler", "jit_options")}
                return self._nlpsol(plugin, nlp, opts, field_name)
            raise InputError(f"{field_name}: solver rejected the options ({_last_line(text)})") from None
        if opts.get("jit"):
            _remove_stray_sources(Path(self._jit_dir.name))
        return solver

    def _probe(self) -> None:
        x0 = self.robot.straight()
        tip = np.asarray(self.model.tip(x0), dtype=float).reshape(-1)
        p = self.parameters(x0, tip, self._pad(), 0.0)
        lbx, ubx = self.step_bounds(x0)
        for solver in (self._solver, self._solver_ws, self._fallback):
            if solver is None or (solver is self._solver and self.options.solver != "ipopt"):
                continue
            S = self.scale
            solver(x0=x0 * S, p=p, lbx=lbx * S, ubx=ubx * S, lbg=self._lbg, ubg=self._ubg)
            if solver.stats().get("return_status", "") == "Invalid_Option":
                keys = ", ".join(k for k, _ in self.options.ipopt) or "(defaults)"
                raise InputError(f"steer.ipopt: IPOPT rejected an option (given: {keys})")

    def _pad(self) -> np.ndarray:
        return packing.padding(self.max_obstacles)

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
        wd = self.options.damping_weight if damping_weight is None else damping_weight
        wo = self.options.obstacle_weight if obstacle_weight is None else obstacle_weight
        return np.concatenate([x_prev, target, packed, [safety_distance, wd, wo]])

    def step_bounds(self, x_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Variable bounds: the config box intersected with ``|S (x - x_prev)|_inf <= max_step``."""
        d = self.options.max_step / self.scale
        lo, hi = self.box
        return np.maximum(lo, x_prev - d), np.minimum(hi, x_prev + d)

    def _evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(tip (3,), J (3, nx), points (n_points, 3), limits g) at x."""
        tip, J, P, g = self._check(x)
        return (
            np.asarray(tip, dtype=float).reshape(-1),
            np.asarray(J, dtype=float),
            np.asarray(P, dtype=float).T,
            np.asarray(g, dtype=float).reshape(-1),
        )

    def _limits_ok(self, g: np.ndarray, tol: float = 1e-6) -> bool:
        return bool(np.all(g >= self._lbg_lim - tol) and np.all(g <= self._ubg_lim + tol))

    def _packed(
        self, obstacles: Any, t: float, t_end: float | None, safety_distance: float | None
    ) -> tuple[np.ndarray, float, Scene | None]:
        if isinstance(obstacles, Scene):
            memo = self._memo
            if memo is not None and memo[0] is obstacles and memo[1] == t and memo[2] == t_end:
                packed = memo[3]  # a Scene is frozen: the same scene at the same times packs the same
            elif t_end is None:
                packed = obstacles.pack(t, self.max_obstacles)
            else:
                packed = obstacles.pack_over(t, t_end, self.max_obstacles)
            self._memo = (obstacles, t, t_end, packed)
            dsf = obstacles.safety_distance if safety_distance is None else float(safety_distance)
            return packed, dsf, obstacles
        if obstacles is None:
            packed = self._pad()
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

    def _clearance(
        self, pts: np.ndarray, packed: np.ndarray, dsf: float, scene: Scene | None, t: float, t_end: float | None
    ) -> float:
        """Clearance (mm) of the constrained points: `Scene.clearance_points` (the same
        computation as `Scene.clearance`), or the packed spheres when no scene is given."""
        body = self.robot.body_radius
        if scene is not None:
            if t_end is None:
                return float(scene.clearance_points(pts, t, inflate=body))
            return float(scene.clearance_points_over(pts, t, t_end, inflate=body))
        centers, radii, active = packing.unpack(packed)
        on = active > 0
        if not np.any(on):
            return math.inf
        d = np.linalg.norm(pts[:, None, :] - centers[on][None, :, :], axis=-1) - radii[on]
        return float(margin.clearance(d.min(), dsf, body))

    def predict(self, x_prev: np.ndarray, target: np.ndarray) -> np.ndarray:
        """One DLS step (eq. 17, scaled coordinates) from x_prev, inside the step bounds."""
        tip, J, _, _ = self._evaluate(x_prev)
        return self._dls_update(x_prev, tip, J, target, *self.step_bounds(x_prev))

    def _dls_update(
        self, x: np.ndarray, tip: np.ndarray, J: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> np.ndarray:
        o = self.options
        Js = J / self.scale
        dy = Js.T @ np.linalg.solve(Js @ Js.T + o.damping**2 * np.eye(3), o.dls_gain * (target - tip))
        return np.clip(x + dy / self.scale, lo, hi)

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
        packed, dsf, scene = self._packed(obstacles, float(t), t_end, safety_distance)
        guess = None if x0 is None else _vec(x0, "x0", self.nx)
        if self._step is not None:
            weights = (dsf, damping_weight, obstacle_weight)
            return self._solve_compiled(xp, tg, packed, weights, guess, float(t), check_start, t_start)
        tip0, J0, pts0, g0 = self._evaluate(xp)
        if check_start:
            lo, hi = self.box
            if not self._limits_ok(g0, 1e-9) or np.any(xp < lo - 1e-9) or np.any(xp > hi + 1e-9):
                raise InputError("x_prev: outside the robot's limits (theta, cable stroke or z range)")
            c0 = self._clearance(pts0, packed, dsf, scene, float(t), t_end)
            if c0 < -self.options.feasibility_tolerance:
                raise InputError(
                    f"x_prev: start configuration is in collision (clearance {c0:.3f} mm, "
                    f"D_sf {dsf:g} mm, at t = {float(t):g} s)"
                )
        lbx, ubx = self.step_bounds(xp)
        if self.options.solver == "dls":
            x, converged, status, iters = self._solve_dls(xp, tg, tip0, J0, lbx, ubx)
            used, note = "dls", ""
        else:
            if guess is None:
                guess = self._dls_update(xp, tip0, J0, tg, lbx, ubx) if self.options.predictor else xp
            p = self.parameters(xp, tg, packed, dsf, damping_weight, obstacle_weight)
            lbg = self._lbg.copy()
            # padding slots: free rows (lbg = -inf), no slack for the solver to carry
            act = packing.active_flags(packed)
            lbg[lbg.size - self.n_col :] = np.where(np.repeat(act, self.n_points), 0.0, -np.inf)
            guess = np.clip(guess, lbx, ubx)
            x, converged, status, iters = self._solve_nlp(self._solver, p, lbg, guess, lbx, ubx, warm=True)
            used, note = self.options.solver, ""
            if not converged and self._fallback is not None:
                note = f"sqp: {status} after {iters} iterations; re-solved by IPOPT. "
                x, converged, status, more = self._solve_nlp(self._fallback, p, lbg, guess, lbx, ubx, warm=False)
                iters += more
                used = "sqp>ipopt"
        return self._result(
            x, xp, tg, packed, dsf, scene, float(t), t_end, lbx, ubx, converged, status, iters, t_start, used, note
        )

    def _solve_compiled(
        self,
        xp: np.ndarray,
        tg: np.ndarray,
        packed: np.ndarray,
        weights: tuple[float, float | None, float | None],
        guess: np.ndarray | None,
        t: float,
        check_start: bool,
        t_start: float,
    ) -> SteerResult:
        """`solve` through the compiled step (option `compiled`): one foreign call, then the same re-check
        as the interpreted path, computed here from the returned points against the packed spheres."""
        o = self.options
        dsf, wd, wo = weights
        w = (dsf, o.damping_weight if wd is None else wd, o.obstacle_weight if wo is None else wo)
        lbx, ubx = self.step_bounds(xp)
        if self._lbg_memo is None or self._lbg_memo[0] is not packed:
            lbg = self._lbg.copy()
            act = packing.active_flags(packed)
            lbg[lbg.size - self.n_col :] = np.where(np.repeat(act, self.n_points), 0.0, -np.inf)
            self._lbg_memo = (packed, lbg)
        lbg = self._lbg_memo[1]
        warm = o.uses_warm_start and self._lam_g is not None
        out = self._step(
            xp,
            tg,
            packed,
            w,
            lbx,
            ubx,
            lbg,
            xp if guess is None else guess,
            (0.0 if guess is None else 1.0,),
            self._lam_x if warm else None,
            self._lam_g if warm else None,
        )
        x, lam_x, lam_g, pr, du, tip, d, slack, d0, slack0 = out
        body = self.robot.body_radius
        if check_start:
            if slack0[0] < -1e-9:  # the limits and the configuration box at x_prev, in one number
                raise InputError("x_prev: outside the robot's limits (theta, cable stroke or z range)")
            c0 = margin.clearance(float(d0[0]), dsf, body) if d0[0] < 1e11 else math.inf
            if c0 < -o.feasibility_tolerance:
                raise InputError(
                    f"x_prev: start configuration is in collision (clearance {c0:.3f} mm, "
                    f"D_sf {dsf:g} mm, at t = {t:g} s)"
                )
        x = x.copy()
        pr_inf, du_inf = float(pr[0]), float(du[0])
        # sqpmethod's own convergence test, on the residuals of the point it returned
        converged = bool(np.all(np.isfinite(x))) and pr_inf < self._tol[0] and du_inf < self._tol[1]
        if converged:
            self._lam_x, self._lam_g = lam_x.copy(), lam_g.copy()
            status = "Solve_Succeeded"
        else:
            self.reset_warm_start()
            status = f"Not_Converged (compiled sqpmethod: primal {pr_inf:.2g}, dual {du_inf:.2g})"
        if not converged and self._fallback is not None:
            p = self.parameters(xp, tg, packed, dsf, wd, wo)
            start = np.clip(xp if guess is None else guess, lbx, ubx)
            note = f"sqp: {status}; re-solved by IPOPT. "
            x, converged, status, iters = self._solve_nlp(self._fallback, p, lbg, start, lbx, ubx, warm=False)
            return self._result(
                x, xp, tg, packed, dsf, None, t, None, lbx, ubx, converged, status, iters, t_start, "sqp>ipopt", note
            )
        checked = (tip.copy(), margin.clearance(float(d[0]), dsf, body) if d[0] < 1e11 else math.inf, slack[0] >= -1e-6)
        return self._result(
            x, xp, tg, packed, dsf, None, t, None, lbx, ubx, converged, status, -1, t_start, "sqp", "", checked
        )

    def _solve_nlp(
        self,
        solver: ca.Function,
        p: np.ndarray,
        lbg: np.ndarray,
        x0: np.ndarray,
        lbx: np.ndarray,
        ubx: np.ndarray,
        warm: bool,
    ) -> tuple[np.ndarray, bool, str, int]:
        S = self.scale
        args: dict[str, Any] = {"x0": x0 * S, "p": p, "lbx": lbx * S, "ubx": ubx * S, "lbg": lbg, "ubg": self._ubg}
        if warm and self.options.uses_warm_start and self._lam_g is not None:
            args["lam_g0"] = self._lam_g
            args["lam_x0"] = self._lam_x
            if self._solver_ws is not None:
                solver = self._solver_ws
        try:
            sol = solver(**args)
        except RuntimeError as exc:  # evaluation errors (NaN) inside CasADi
            self.reset_warm_start()
            return x0.copy(), False, f"Evaluation_Error: {_last_line(str(exc))}", 0
        stats = solver.stats()
        # IPOPT relaxes bounds by ~1e-8 relative; project back so the re-check
        # judges the configuration that is actually returned
        x = np.clip(np.asarray(sol["x"], dtype=float).reshape(-1) / S, lbx, ubx)
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(x)))
        if ok:
            self._lam_g = np.asarray(sol["lam_g"], dtype=float).reshape(-1)
            self._lam_x = np.asarray(sol["lam_x"], dtype=float).reshape(-1)
        else:
            self.reset_warm_start()
        return x, ok, str(stats.get("return_status", "unknown")), int(stats.get("iter_count", -1))

    def _solve_dls(
        self, xp: np.ndarray, tg: np.ndarray, tip: np.ndarray, J: np.ndarray, lo: np.ndarray, hi: np.ndarray
    ) -> tuple[np.ndarray, bool, str, int]:
        """Iterate eq. 17 from x_prev inside the step bounds; stop at 1/100 of the
        tolerance or when the step stalls (the closest point DLS can reach)."""
        o = self.options
        x = xp
        for it in range(o.dls_iterations):
            if np.linalg.norm(tg - tip) <= 0.01 * o.tolerance:
                return x, True, "Solve_Succeeded", it
            xn = self._dls_update(x, tip, J, tg, lo, hi)
            if np.max(np.abs((xn - x) * self.scale)) < 1e-9:
                return xn, True, "Stalled_At_Closest_Point", it + 1
            x = xn
            tip, J, _, _ = self._evaluate(x)
        return x, False, "Maximum_Iterations_Exceeded", o.dls_iterations

    def _result(
        self,
        x: np.ndarray,
        xp: np.ndarray,
        tg: np.ndarray,
        packed: np.ndarray,
        dsf: float,
        scene: Scene | None,
        t: float,
        t_end: float | None,
        lbx: np.ndarray,
        ubx: np.ndarray,
        converged: bool,
        status: str,
        iters: int,
        t_start: float,
        used: str,
        note: str,
        checked: tuple[np.ndarray, float, bool] | None = None,
    ) -> SteerResult:
        """The result of a solve. checked: (tip, clearance, within the limits) when the compiled step has
        computed them at x (else they are evaluated here)."""
        o = self.options
        finite = bool(np.all(np.isfinite(x)))
        if not finite:
            x = xp.copy()
            checked = None
        if checked is None:
            tip, _, pts, g = self._evaluate(x)
            clear = self._clearance(pts, packed, dsf, scene, t, t_end)
            in_limits = self._limits_ok(g)
        else:
            tip, clear, in_limits = checked
        err = math.dist(tip, tg)
        in_box = bool(np.all(x >= lbx) and np.all(x <= ubx))
        clear_ok = clear >= -o.feasibility_tolerance
        safe = finite and clear_ok and in_box and in_limits
        reached = finite and err <= o.tolerance
        if not finite:
            message = f"solver returned NaN ({status}); x_prev returned unchanged"
        elif not converged:
            message = f"solver failed ({status}); tip error {err:.3g} mm, clearance {clear:.3g} mm"
        elif not safe:
            what = [] if clear_ok else [f"clearance {clear:.3g} mm < 0"]
            what += [] if in_limits else ["outside the robot's limits"]
            what += [] if in_box else ["outside the step bounds"]
            message = "converged but the re-check failed: " + ", ".join(what)
        elif reached:  # converged and safe here
            message = f"reached: tip error {err:.3g} mm, clearance {clear:.3g} mm"
        else:
            moved = float(np.max(np.abs(x - xp) * self.scale))
            why = "the step bound max_step" if moved >= 0.999 * o.max_step else "obstacles or the robot's limits"
            message = f"target not reached: the closest safe configuration is {err:.3g} mm away (blocked by {why})"
        return SteerResult(
            x=x,
            q=self._A @ x + self._q0,
            tip=tip,
            reached=reached,
            converged=converged,
            safe=safe,
            solver_status=status,
            message=note + message,
            iterations=iters,
            wall_time=time.perf_counter() - t_start,
            tip_error=err,
            min_clearance=clear,
            solver=used,
        )

    def solve_many(self, x_prevs: Any, targets: Any, obstacles: Scene | Any = None, **kwargs: Any) -> list[SteerResult]:
        """`solve` for each row of x_prevs (N, nx) and targets (N, 3); same obstacles and keywords."""
        X = np.asarray(x_prevs, dtype=float)
        T = np.asarray(targets, dtype=float)
        if X.ndim != 2 or T.ndim != 2 or X.shape[0] != T.shape[0] or X.shape[1] != self.nx or T.shape[1] != 3:
            raise InputError(f"x_prevs, targets: expected (N, {self.nx}) and (N, 3), got {X.shape} and {T.shape}")
        return [self.solve(X[k], T[k], obstacles, **kwargs) for k in range(X.shape[0])]

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve."""
        self._lam_g = self._lam_x = None


def _qp_options(qpsol: str) -> dict[str, Any]:
    """Silent, non-raising options of each QP solver."""
    quiet: dict[str, dict[str, Any]] = {
        "daqp": {},
        "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
        "qpoases": {"printLevel": "none"},
        "osqp": {"osqp": {"verbose": False}},
        "proxqp": {"proxqp": {"verbose": False}},
        "highs": {"highs": {"output_flag": False}},
    }
    return {"error_on_fail": False, **quiet[qpsol]}


def _remove_stray_sources(private: Path) -> None:
    """Delete the jit's C sources that CasADi's nlpsol writes to the working directory.

    Measured with CasADi 3.8: an nlpsol built with jit reserves a unique name
    ``jit_tmpXXXXXX.c`` in the jit directory (an empty file) but writes the
    source under that name to the working directory (a plain Function honours
    the directory). The names are random and reserved in this solver's private
    folder, so a working-directory file of the same name is this build's source.
    """
    for reserved in private.glob("jit_tmp*.c"):
        try:
            (Path.cwd() / reserved.name).unlink(missing_ok=True)
        except OSError:  # a read-only or vanished working directory: nothing was written there
            continue


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else text
