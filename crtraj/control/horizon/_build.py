"""Building the horizon NLP (the symbolic problem of `crtraj.control.horizon._replanner`), separate from solving it.

`build_nlp` turns a `HorizonSpec` (model, options, limits) into a `HorizonNLP`: the cost, the rows and their
bounds of two NLPs over the same variables and cost, the full one (every backbone point of every step against
every obstacle, solved by the IPOPT rescue) and the QP's one (the `closest_points` nearest points per obstacle and
step, selected by parameters; the same NLP when nothing is screened). `nlp_solver` makes a CasADi solver of one of
them, `gauss_newton` its Hessian, and `build_compiled` the generated C of the sqpmethod solver. Units: mm, rad, s.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._rows import implied_rows, merge_parallel_rows, shift_index
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.nlp import CODEGEN_QP, CompiledFunction, compiled_library
from crtraj.world import packing
from crtraj.world.geometry import ShapeTerms

if TYPE_CHECKING:
    from crtraj.control.horizon._rod_body import LinearCorrection

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HorizonSpec:
    """What the horizon NLP is built from.

    cable_matrix: A (3 S, nx), cable-length changes (mm) per configuration change. step_limit: (3 S + 1,) mm
    per step of each cable and of z. scale: (nx,) S of the module docstring of `crtraj.control.horizon._replanner`
    (bending rad -> mm). rate_limits: the actuators' limits already scaled by ``limit_fraction`` (or None).
    closest_points: K, the points per obstacle and step the QP keeps (0: all of them). shapes: the scene's
    obstacles of other shapes as NLP terms (`crtraj.world.geometry.ShapeTerms`; None or empty: none), each of
    `shape_points` backbone points of each step kept `shape_keep` mm from each shape's lower bound over the step's
    window. linear: the rod's correction to first order (`crtraj.control.horizon._rod_body`; None: the body is
    `model`'s own); with it `model` is the robot's PCC model and each step's correction parameters (its
    `n_params`) follow the obstacle slots at the parameter vector's end.
    """

    model: Model
    options: ReplanOptions
    max_obstacles: int
    cable_matrix: np.ndarray
    step_limit: np.ndarray
    scale: np.ndarray
    rate_limits: RateLimits | None
    closest_points: int
    shapes: ShapeTerms | None = None
    shape_keep: float = 0.0
    shape_points: int = 0
    linear: LinearCorrection | None = None

    @property
    def n_linear(self) -> int:
        """Correction parameters per step (0 without `linear`)."""
        return 0 if self.linear is None else self.linear.n_params

    @property
    def n_shape_params(self) -> int:
        """Parameters per step of the shapes (after each step's obstacle slots)."""
        return 0 if self.shapes is None else self.shapes.n_params

    @property
    def tag(self) -> str:
        """The sizes in the names of the generated functions (segments, obstacles, steps; shapes when any)."""
        n = 0 if self.shapes is None else len(self.shapes.shapes)
        return (
            f"{self.model.robot.n_segments}s_{self.max_obstacles}o_{self.options.horizon}n"
            + (f"_{n}sh" if n else "")
            + ("_rodlin" if self.linear is not None else "")
        )


@dataclass(frozen=True)
class HorizonNLP:
    """The built horizon NLP: the QP's NLP (`nlp`, bounds `lbg`/`ubg`) and the full one (`nlp_full`).

    r_vec: the cost's residuals (cost = |r_vec|^2). n_lin: linear rows (rates, actuator limits) that come
    first in both. n_shape: the shape rows right after them (mm, >= 0: every point of every step against every
    shape, never screened). n_params: parameters of the full NLP; the obstacle slots (each step's sphere slots,
    then its shapes' parameters) are its last `n_obstacle_p`.
    n_dist: obstacle rows of the full NLP (0 without). all_distance: (X, O) -> every obstacle row (N M
    points) or None. checked: what the compiled KKT check returns besides the residual (obstacle rows, tips).
    widths: (rows per step, steps) of each row block of the QP's NLP; shift_x, shift_g: the warm start's
    one-step shift of x and of the rows (`shift_index`).
    """

    nlp: dict[str, ca.SX]
    nlp_full: dict[str, ca.SX]
    r_vec: ca.SX
    lbg: np.ndarray
    ubg: np.ndarray
    lbg_full: np.ndarray
    ubg_full: np.ndarray
    n_lin: int
    n_shape: int
    n_params: int
    n_obstacle_p: int
    n_dist: int
    all_distance: ca.Function | None
    checked: tuple[ca.SX, ca.SX]
    widths: tuple[tuple[int, int], ...]
    shift_x: np.ndarray
    shift_g: np.ndarray


@dataclass(frozen=True)
class _Obstacles:
    """The obstacle rows of both NLPs, appended to their linear rows (`_obstacle_rows`)."""

    g_full: list[ca.SX]
    g_red: list[ca.SX]
    p_red: ca.SX
    lb_full: list[np.ndarray]
    lb_red: list[np.ndarray]
    all_distance: ca.Function | None
    checked: tuple[ca.SX, ca.SX]


def build_nlp(spec: HorizonSpec) -> HorizonNLP:
    """The horizon NLP of `spec`: variables X (nx, N), parameters (x0, x_-1, reference, tip reference, obstacles)."""
    o, model = spec.options, spec.model
    nx, N, M = model.robot.nx, o.horizon, spec.max_obstacles
    X = ca.SX.sym("X", nx, N)
    x0 = ca.SX.sym("x0", nx)
    xm1 = ca.SX.sym("x_prev", nx)
    Xr = ca.SX.sym("x_ref", nx, N)
    Pr = ca.SX.sym("tip_ref", 3, N)
    O = ca.SX.sym("obstacles", packing.WIDTH * M + spec.n_shape_params, N)
    C = ca.SX.sym("rod_correction", spec.n_linear, N)
    S = ca.DM(spec.scale)
    Xall = ca.horzcat(xm1, x0, X)  # columns k = -1, 0, 1..N
    tips = _tips(spec, X, C)  # 3 x N
    r_vec, dX, ddX = _residuals(o, (X, Xall, Xr, Pr), tips, S)
    f = ca.sumsqr(r_vec)
    g, lbg, ubg, widths = _rate_rows(spec, dX, ddX)
    # actuation limits
    lim = model.limits.map(N)(X)
    lo, hi = model.limit_bounds()
    g.append(ca.vec(lim))
    lbg.append(np.tile(lo, N))
    ubg.append(np.tile(hi, N))
    widths.append((len(lo), N))
    n_lin = int(sum(len(b) for b in lbg))
    n_shape = _shape_rows(spec, (X, O, C), (g, lbg, ubg, widths))
    p = ca.vertcat(x0, xm1, ca.vec(Xr), ca.vec(Pr), ca.vec(O), ca.vec(C))
    xv = ca.vec(X)
    ob = _obstacle_rows(spec, (X, xv, O, C, p), (g, lbg), tips)
    n, K = o.points, spec.closest_points
    n_dist = int(n * M * N) if (o.safety and M > 0) else 0
    if n_dist:
        widths.append(((K or n) * M, N))
    lbg_full = np.concatenate(ob.lb_full)
    lbg_red = np.concatenate(ob.lb_red)
    n_pre = n_lin + n_shape  # rows with their own upper bounds, before the sphere rows
    return HorizonNLP(
        nlp={"x": xv, "p": ob.p_red, "f": f, "g": ca.vertcat(*ob.g_red)},
        nlp_full={"x": xv, "p": p, "f": f, "g": ca.vertcat(*ob.g_full)},
        r_vec=r_vec,
        lbg=lbg_red,
        ubg=np.concatenate([*ubg, np.full(len(lbg_red) - n_pre, np.inf)]),
        lbg_full=lbg_full,
        ubg_full=np.concatenate([*ubg, np.full(len(lbg_full) - n_pre, np.inf)]),
        n_lin=n_lin,
        n_shape=n_shape,
        n_params=int(p.numel()),
        n_obstacle_p=int(O.numel() + C.numel()),  # the obstacle slots (and the correction) end the parameters
        n_dist=n_dist,
        all_distance=ob.all_distance,
        checked=ob.checked,
        widths=tuple(widths),
        shift_x=shift_index(((nx, N),)),
        shift_g=shift_index(tuple(widths)),
    )


def _tips(spec: HorizonSpec, X: ca.SX, C: ca.SX) -> ca.SX:
    """The tips (3 x N) of the steps' configurations X: the model's, or PCC's plus the linear correction."""
    if spec.linear is None:
        return spec.model.tip.map(X.size2())(X)
    x, c = ca.SX.sym("x", X.size1()), ca.SX.sym("c", spec.n_linear)
    return ca.Function("horizon_tip", [x, c], [spec.linear.tip(x, c)]).map(X.size2())(X, C)


def _points(spec: HorizonSpec, x: ca.SX, c: ca.SX, n: int) -> ca.SX:
    """n backbone points (3 x n) of configuration x: the model's, or PCC's plus the linear correction c."""
    return spec.model.backbone_function(n)(x) if spec.linear is None else spec.linear.points(x, c, n)


def _slot_point(spec: HorizonSpec, x: ca.SX, column: ca.SX, c: ca.SX) -> ca.SX:
    """The backbone point (3,) a QP slot selects by its parameter column: one-hot over the segments, the fraction
    of that segment's arc, and (with `linear`) the P interpolation weights of the correction at that arc, so the
    correction's share is one weighted sum of its linear term (the weights are parameters, not hat functions)."""
    S_ = spec.model.robot.n_segments
    pts = spec.model.segment_point_function()(x, column[S_])  # PCC's, or the model's own body
    point = pts @ column[:S_]
    if spec.linear is None:
        return point
    return point + spec.linear.delta(x, c) @ column[S_ + 1 :]


def _residuals(o: ReplanOptions, syms: tuple[ca.SX, ca.SX, ca.SX, ca.SX], tips: ca.SX, S: ca.DM) -> tuple[ca.SX, ...]:
    """The cost's residuals (mm: tip, body shape, velocity, smoothness and terminal terms, weighted) of the
    symbols (X, [x_-1 x_0 X], x_ref, tip_ref), and the steps' changes dX and their differences ddX."""
    X, Xall, Xr, Pr = syms
    N = X.size2()
    res = []
    res.append(math.sqrt(o.tip_weight) * ca.vec(tips - Pr))
    res.append(math.sqrt(o.config_weight) * ca.vec((X - Xr) * ca.repmat(S, 1, N)))
    dX = Xall[:, 2:] - Xall[:, 1:-1]
    res.append(math.sqrt(o.velocity_weight) * ca.vec(dX * ca.repmat(S, 1, N)))
    ddX = Xall[:, 2:] - 2 * Xall[:, 1:-1] + Xall[:, :-2]
    res.append(math.sqrt(o.smooth_weight) * ca.vec(ddX * ca.repmat(S, 1, N)))
    res.append(math.sqrt(o.terminal_weight) * (tips[:, -1] - Pr[:, -1]))
    return ca.vertcat(*res), dX, ddX


def _rate_rows(
    spec: HorizonSpec, dX: ca.SX, ddX: ca.SX
) -> tuple[list[ca.SX], list[np.ndarray], list[np.ndarray], list[tuple[int, int]]]:
    """The per-step limits on each actuator's change (linear in x): rows, lower and upper bounds, (rows per step,
    steps) of each block."""
    o = spec.options
    g, lbg, ubg = [], [], []
    # the mm/s rate limits and, with actuator limits, their speed limits, one row per direction
    # (`merge_parallel_rows`: a speed row parallel to a rate row would be the same constraint twice, and every QP
    # row costs the QP solver time)
    rl = spec.rate_limits
    speed_rows = [spec.cable_matrix] if rl is None else [spec.cable_matrix, rl.jacobian]
    speed_bounds = [spec.step_limit] if rl is None else [spec.step_limit, rl.vmax * o.dt]
    Rv, bv = merge_parallel_rows(np.vstack(speed_rows), np.concatenate(speed_bounds))
    blocks = [(Rv, bv, dX)]
    if rl is not None:
        # actuator acceleration (k = 1 uses x_-1, the previous applied step). From step 2 on, a row parallel to a
        # speed row whose two steps cannot differ by more than the acceleration bound (|s| 2 b_speed <= b_acc) is
        # implied by the speed rows of steps k and k-1, and left out; step 1's is kept, since the measured step
        # before it is not bounded by this NLP.
        Ra, ba = merge_parallel_rows(rl.jacobian, rl.amax * o.dt**2)
        implied = implied_rows(Rv, bv, Ra, ba)
        blocks.append((Ra[~implied], ba[~implied], ddX))
        if implied.any():
            blocks.append((Ra[implied], ba[implied], ddX[:, :1]))
    widths = []
    for R, bound, expr in blocks:
        if not len(bound):
            continue
        steps = expr.size2()
        g.append(ca.vec(ca.DM(R) @ expr))
        lbg.append(np.tile(-bound, steps))
        ubg.append(np.tile(bound, steps))
        widths.append((len(bound), steps))
    return g, lbg, ubg, widths


def _shape_rows(
    spec: HorizonSpec,
    syms: tuple[ca.SX, ca.SX, ca.SX],
    rows: tuple[list[ca.SX], list[np.ndarray], list[np.ndarray], list[tuple[int, int]]],
) -> int:
    """Append the shape rows (mm) to the row lists (g, lbg, ubg, widths): per step and shape, each of the
    `shape_points` backbone points' lower bound of its distance over the step's window (`ShapeTerms.distances`,
    whose parameters follow the step's sphere slots in its column of O) minus `shape_keep`, >= 0. Returns how
    many (0 without shapes or without safety)."""
    o, model, terms = spec.options, spec.model, spec.shapes
    if terms is None or not terms.shapes or not o.safety:
        return 0
    X, O, C = syms
    g, lbg, ubg, widths = rows
    n, N, W = spec.shape_points, o.horizon, packing.WIDTH * spec.max_obstacles
    x = ca.SX.sym("x", model.robot.nx)
    ob = ca.SX.sym("ob", W + terms.n_params)
    c = ca.SX.sym("c", spec.n_linear)
    pts = _points(spec, x, c, n)  # 3 x n
    d = ca.vertcat(*[row.T for row in terms.distances(pts, ob[W:])]) - spec.shape_keep  # (shapes n) x 1
    per_step = int(d.numel())
    lin = [c] if spec.linear is not None else []  # PCC's functions keep their inputs (and their C)
    fn = ca.Function("horizon_shape_distance", [x, ob, *lin], [d], {"cse": True})
    g.append(ca.vec(fn.map(N)(X, O, *([C] if lin else []))))
    lbg.append(np.zeros(per_step * N))
    ubg.append(np.full(per_step * N, np.inf))
    widths.append((per_step, N))
    return per_step * N


def _obstacle_rows(
    spec: HorizonSpec,
    syms: tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX],
    linear: tuple[list[ca.SX], list[np.ndarray]],
    tips: ca.SX,
) -> _Obstacles:
    """The full NLP's obstacle rows (every point of every step against every obstacle) and the QP's (only the K
    closest points per obstacle and step, `closest_points`; the same rows when K = 0), after the linear rows."""
    o, model = spec.options, spec.model
    nx, N, M = model.robot.nx, o.horizon, spec.max_obstacles
    X, xv, O, C, p = syms  # variables (nx, N) and as a vector, obstacle slots (WIDTH M, N), correction, parameters
    g, lbg = linear
    n, K = o.points, spec.closest_points
    g_full, g_red, p_red = list(g), list(g), p
    lb_full, lb_red = list(lbg), list(lbg)
    out = _Obstacles(g_full, g_red, p_red, lb_full, lb_red, None, (ca.SX(0, 1), ca.vec(tips)))
    if not (o.safety and M > 0):
        return out
    x = ca.SX.sym("x", nx)
    ob = ca.SX.sym("ob", packing.WIDTH * M)
    S_ = model.robot.n_segments
    # per slot: one-hot weights over the segments, then the fraction of that segment's arc
    width = S_ + 1 + (0 if spec.linear is None else spec.linear.P)  # a slot's parameters (`_slot_point`)
    sel = ca.SX.sym("sel", width, max(K, 1) * M)
    corr = ca.SX.sym("c", spec.n_linear)
    pts = _points(spec, x, corr, n)  # 3 x n
    d, ds = [], []
    for i in range(M):
        # the slot's radius is the inflated rho (`Replanner._inflated`); padding has rho = 0 at 1e6 mm
        c, rho, _ = packing.slot(ob, i)
        diff = pts - ca.repmat(c, 1, n)
        d.append(ca.sqrt(ca.sum1(diff * diff) + 1e-9).T - rho)
        if K:
            # slot (i, j) is one backbone point, chosen by parameters: its segment (one-hot) and the fraction of
            # that segment's arc (one point per segment is computed, not all n)
            cols = [_slot_point(spec, x, sel[:, i * K + j], corr) for j in range(K)]
            diff = ca.horzcat(*cols) - ca.repmat(c, 1, K)
            ds.append(ca.sqrt(ca.sum1(diff * diff) + 1e-9).T - rho)
    lin, Lin = ([corr], [C]) if spec.linear is not None else ([], [])  # PCC's functions keep their inputs (and C)
    dist = ca.Function("horizon_distance", [x, ob, *lin], [ca.vertcat(*d)], {"cse": True})
    D = dist.map(N)(X, O[: packing.WIDTH * M, :], *Lin)  # (n M) x N; the shapes' parameters follow the slots
    g_full.append(ca.vec(D))
    lb_full.append(np.zeros(n * M * N))
    tail = ca.vec(O) if spec.linear is None else ca.vertcat(ca.vec(O), ca.vec(C))  # the parameters' last entries
    all_distance = ca.Function(f"horizon_all_distance_{spec.tag}", [xv, tail], [D], {"cse": True})
    if K:
        slots = ca.Function("horizon_slot_distance", [x, ob, ca.vec(sel), *lin], [ca.vertcat(*ds)], {"cse": True})
        Sel = ca.SX.sym("selection", width * K * M, N)
        g_red.append(ca.vec(slots.map(N)(X, O[: packing.WIDTH * M, :], Sel, *Lin)))
        lb_red.append(np.zeros(K * M * N))
        p_red = ca.vertcat(p, ca.vec(Sel))
    else:
        g_red, lb_red = g_full, lb_full
    return _Obstacles(g_full, g_red, p_red, lb_full, lb_red, all_distance, (ca.vec(D), ca.vec(tips)))


def gauss_newton(options: ReplanOptions, r_vec: ca.SX, nlp: dict[str, ca.SX], kind: str) -> ca.Function | None:
    """The Gauss-Newton Hessian of the least-squares cost for solver `kind` ("ipopt" or "sqp") of `nlp` (None:
    the exact Hessian, option ``hessian``)."""
    if options.hessian != "gauss-newton":
        return None
    xv, p = nlp["x"], nlp["p"]
    # positive semidefinite, so every QP of the SQP path is convex (daqp and qrqp need that), and much cheaper to
    # evaluate than the exact Hessian of hundreds of distance constraints
    lam_f = ca.SX.sym("lam_f")
    lam_g = ca.SX.sym("lam_g", nlp["g"].numel())
    Jr = ca.jacobian(r_vec, xv)
    H = 2 * lam_f * (Jr.T @ Jr) + 1e-9 * ca.SX.eye(xv.numel())
    # ipopt wants the upper triangle, sqpmethod the full symmetric matrix
    out = ca.triu(H) if kind == "ipopt" else H
    return ca.Function("nlp_hess_l", [xv, p, lam_f, lam_g], [out], {"cse": True})


def nlp_solver(
    kind: str, options: ReplanOptions, nlp: dict[str, ca.SX], hess: ca.Function | None, qp_extra: dict | None = None
) -> ca.Function:
    """A CasADi solver of `nlp`: "ipopt", or "sqp" (sqpmethod with the QP solver ``qpsol``, given `qp_extra`
    among its options: the stage structure for HPIPM)."""
    # calc_lam_p off: the parametric sensitivities are never used, and computing them is a full gradient over
    # every parameter after each solve
    common: dict[str, Any] = {
        "print_time": False,
        "error_on_fail": False,
        "record_time": True,
        "calc_lam_p": False,
    }
    if hess is not None:
        common["hess_lag"] = hess
    if kind == "ipopt":
        return ca.nlpsol("replan_ipopt", "ipopt", nlp, {**common, **_ipopt_options(options)})
    sqp = _sqp_options(options)
    sqp["qpsol_options"].update(qp_extra or {})
    return ca.nlpsol("replan_sqp", "sqpmethod", nlp, {**common, **sqp})


def _ipopt_options(o: ReplanOptions) -> dict[str, Any]:
    """IPOPT's options: quiet, warm-started, capped at max_iter x max_calls iterations and max_solve_time s."""
    return {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "ipopt.max_iter": o.max_iter * o.max_calls,
        "ipopt.tol": o.tol,
        "ipopt.constr_viol_tol": 1e-7,
        "ipopt.acceptable_tol": 1e-4,
        "ipopt.acceptable_constr_viol_tol": 1e-7,
        "ipopt.max_wall_time": o.max_solve_time,
        "ipopt.mu_strategy": "adaptive",
        "ipopt.warm_start_init_point": "yes",
        "ipopt.warm_start_bound_push": 1e-6,
        "ipopt.warm_start_mult_bound_push": 1e-6,
        "ipopt.mu_init": 1e-3,
    }


def _sqp_options(o: ReplanOptions) -> dict[str, Any]:
    """sqpmethod's options and its QP solver's (``qpsol``), quiet, max_iter iterations per call."""
    qp_opts: dict[str, Any] = {"error_on_fail": False}
    if o.qpsol == "qrqp":
        qp_opts["print_iter"] = False
        qp_opts["print_header"] = False
        # qrqp's default of 1000 active-set iterations can stall one step for seconds
        qp_opts["max_iter"] = 200
    if o.qpsol == "osqp":
        qp_opts["osqp"] = {"verbose": False}
    if o.qpsol == "hpipm":
        # HPIPM's "speed" mode (Cholesky Riccati): the generated code defaults to "robust", whose LQ factorisations
        # made the compiled solve 40x slower than the dense daqp one on simulation 2
        qp_opts["hpipm"] = {"mode": "speed", "warm_start": 1}
    if o.qpsol == "qpoases":
        qp_opts["printLevel"] = "none"
    opts = {
        "qpsol": o.qpsol,
        "qpsol_options": qp_opts,
        "max_iter": o.max_iter,
        "tol_pr": 1e-7,
        "tol_du": o.tol,
        "print_header": False,
        "print_iteration": False,
        "print_status": False,
        "min_step_size": 1e-12,
    }
    if o.hessian == "exact":
        opts["convexify_strategy"] = "regularize"
    return opts


@dataclass(frozen=True)
class CompiledParts:
    """The compiled sqpmethod solver, its KKT check (dual residual, obstacle rows, tips) and, with obstacle rows,
    every obstacle row of the full NLP, all from one generated C library."""

    step: CompiledFunction
    kkt: CompiledFunction
    distance: CompiledFunction | None
    fused: CompiledFunction | None = None


def build_compiled(spec: HorizonSpec, built: HorizonNLP, solver: ca.Function) -> tuple[str, CompiledParts | None]:
    """The sqpmethod `solver` of the QP's NLP and its KKT residual as generated C, loaded through ctypes (option
    `compiled`): (the message that says what happened, the parts or None for the interpreted solver)."""
    o = spec.options
    if o.solver != "sqp" or o.qpsol not in CODEGEN_QP:
        return (
            f"compiled: needs solver 'sqp' with qpsol {' or '.join(CODEGEN_QP)} "
            f"(got {o.solver}/{o.qpsol}): interpreted solver"
        ), None
    if spec.model.identity() is not None:
        # every stage's rows, their Jacobian and the exact Hessian carry the rod correction's polynomials: the
        # generated C is about 90 MB for cdsr2 (PCC's 2.5 MB), and gcc does not finish it within the build cache's
        # bound, so trying would only cost the user that wait before the same interpreted solver runs
        return "compiled: not for a rod-model body (its generated C is too large to compile): interpreted solver", None
    nlp = built.nlp
    xv, p = nlp["x"], nlp["p"]
    lam_g = ca.SX.sym("lam_g", nlp["g"].numel())
    lam_x = ca.SX.sym("lam_x", xv.numel())
    # the Lagrangian's gradient by one reverse sweep (never the whole constraint Jacobian)
    grad = ca.gradient(nlp["f"] + ca.dot(lam_g, nlp["g"]), xv) + lam_x
    # one call after the solve: the dual residual, every obstacle row of the full NLP and the tips
    outs = [ca.norm_inf(grad), *built.checked]
    kkt = ca.Function(f"horizon_kkt_{spec.tag}", [xv, p, lam_g, lam_x], outs, {"cse": True})
    extra = [] if built.all_distance is None else [built.all_distance]
    fused = [fused_function(spec, built, solver, kkt)] if o.fused else []
    try:
        lib, how = compiled_library(f"horizon_{spec.tag}", [solver, kkt, *extra, *fused], o.qpsol)
    except (RuntimeError, OSError) as exc:
        log.debug("horizon: compiling the solver failed: %s", exc)
        return f"compiled: build failed ({str(exc).strip().splitlines()[-1]}): interpreted solver", None
    if lib is None:
        return f"compiled: {how}", None
    distance = CompiledFunction(lib, extra[0].name()) if extra else None
    one = CompiledFunction(lib, fused[0].name()) if fused else None
    return f"compiled: {how}", CompiledParts(
        CompiledFunction(lib, solver.name()), CompiledFunction(lib, kkt.name()), distance, one
    )


FUSED_OUT = ("x", "f", "g", "lam_x", "lam_g", "du", "distances", "tips", "violation")


def fused_function(spec: HorizonSpec, built: HorizonNLP, solver: ca.Function, kkt: ca.Function) -> ca.Function:
    """One function of a solver call (option `fused`): (x0, p, lam_x0, lam_g0) -> `FUSED_OUT`, the sqpmethod
    `solver` with the box and row bounds as constants, its KKT check (dual residual, every obstacle row of the
    full NLP, tips) at the returned point, and the largest violation of the box and rows (mixed units; what
    `RowCheck.violation` computes in numpy), so that a solver call is one foreign call."""
    n, ng = built.nlp["x"].numel(), built.nlp["g"].numel()
    N = spec.options.horizon
    lo, hi = (np.tile(b, N) for b in spec.model.robot.config_box())
    x0, p = ca.MX.sym("x0", n), ca.MX.sym("p", built.nlp["p"].numel())
    lx, lg = ca.MX.sym("lam_x0", n), ca.MX.sym("lam_g0", ng)
    sol = solver(x0=x0, p=p, lbx=lo, ubx=hi, lbg=built.lbg, ubg=built.ubg, lam_x0=lx, lam_g0=lg)
    x, g = sol["x"], sol["g"]
    du, dist, tips = kkt(x, p, sol["lam_g"], sol["lam_x"])
    # the same terms as `RowCheck.violation` (an infinite bound gives -inf, never the maximum)
    terms = [ca.DM(built.lbg) - g, g - ca.DM(built.ubg), ca.DM(lo) - x, x - ca.DM(hi), ca.MX(0.0)]
    viol = ca.mmax(ca.vertcat(*terms))
    outs = [x, sol["f"], g, sol["lam_x"], sol["lam_g"], du, dist, tips, viol]
    return ca.Function(
        f"horizon_fused_{spec.tag}", [x0, p, lx, lg], outs, ["x0", "p", "lam_x0", "lam_g0"], list(FUSED_OUT)
    )
