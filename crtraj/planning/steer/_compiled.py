"""The steer step as one generated C function (option `compiled`): `CompiledBackend` and its build.

With solver "sqp" and a QP solver that generates C (daqp, qrqp), the whole step (DLS predictor, sqpmethod with its
QP solver, the re-check's tip, points and limits, the KKT residuals) is generated as C, compiled once (cached,
`planning.compiled_nlp`) and called through ctypes: one foreign call per steer. Its convergence is judged from the
KKT residuals it returns (sqpmethod's own test, tol_pr/tol_du); it reports no iteration count (-1).
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.nlp import CODEGEN_QP, CompiledFunction, compiled_library
from crtraj.planning.steer._backends import WarmStart, last_line
from crtraj.planning.steer._nlp import NlpCall, Recheck, SteerNLP, SteerQuery, SteerSolution, start_collision
from crtraj.world import margin, packing

# a distance the generated code reports when no sphere is active (mm); anything above 1e11 means "none"
_NO_SPHERE = 1e12


class CompiledBackend:
    """The compiled step of `nlp`, converged when its primal and dual KKT residuals are below `tolerance`
    ((tol_pr, tol_du)); clearance is measured against the packed spheres (recheck_in_scene False)."""

    name = "sqp"
    recheck_in_scene = False

    def __init__(self, nlp: SteerNLP, step: CompiledFunction, tolerance: tuple[float, float], warm: WarmStart) -> None:
        self.nlp = nlp
        self.step = step
        self.tolerance = tolerance
        self.warm = warm
        self._lbg_memo: tuple[np.ndarray, np.ndarray] | None = None  # last (packed, lbg)

    def with_tolerance(self, tol_pr: float, tol_du: float) -> CompiledBackend:
        """The same compiled step (and warm start) judged by another KKT test."""
        return CompiledBackend(self.nlp, self.step, (tol_pr, tol_du), self.warm)

    def _lbg(self, packed: np.ndarray) -> np.ndarray:
        if self._lbg_memo is None or self._lbg_memo[0] is not packed:
            self._lbg_memo = (packed, self.nlp.lbg_for(packed))
        return self._lbg_memo[1]

    def solve(self, query: SteerQuery) -> SteerSolution:
        """One foreign call, then the start check and the re-check quantities from its outputs."""
        nlp, o = self.nlp, self.nlp.options
        xp, tg, packed, dsf, guess = query.x_prev, query.target, query.packed, query.dsf, query.guess
        wd, wo = query.damping_weight, query.obstacle_weight
        w = (dsf, o.damping_weight if wd is None else wd, o.obstacle_weight if wo is None else wo)
        lbx, ubx = query.lbx, query.ubx
        lbg = self._lbg(packed)
        warm = self.warm.ready
        out = self.step(
            xp,
            tg,
            packed,
            w,
            lbx,
            ubx,
            lbg,
            xp if guess is None else guess,
            (0.0 if guess is None else 1.0,),
            self.warm.lam_x if warm else None,
            self.warm.lam_g if warm else None,
        )
        x, lam_x, lam_g, pr, du, tip, d, slack, d0, slack0 = out
        body = nlp.robot.body_radius
        if query.check_start:
            if slack0[0] < -1e-9:  # the limits and the configuration box at x_prev, in one number
                raise InputError("x_prev: outside the robot's limits (theta, cable stroke or z range)")
            c0 = margin.clearance(float(d0[0]), dsf, body) if d0[0] < 1e11 else math.inf
            start_collision(c0, o, dsf, query.t)
        x = x.copy()
        pr_inf, du_inf = float(pr[0]), float(du[0])
        # sqpmethod's own convergence test, on the residuals of the point it returned
        converged = bool(np.all(np.isfinite(x))) and pr_inf < self.tolerance[0] and du_inf < self.tolerance[1]
        call = None
        if converged:
            self.warm.keep(lam_g.copy(), lam_x.copy())
            status = "Solve_Succeeded"
        else:
            self.warm.reset()
            status = f"Not_Converged (compiled sqpmethod: primal {pr_inf:.2g}, dual {du_inf:.2g})"
            p = nlp.parameters(xp, tg, packed, dsf, wd, wo)
            call = NlpCall(p, lbg, np.clip(xp if guess is None else guess, lbx, ubx), lbx, ubx)
        clear = margin.clearance(float(d[0]), dsf, body) if d[0] < 1e11 else math.inf
        recheck = Recheck(tip.copy(), clear, slack[0] >= -1e-6)
        return SteerSolution(x, converged, status, -1, self.name, recheck=recheck, call=call)

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve."""
        self.warm.reset()


def build_compiled(nlp: SteerNLP, sqp_opts: dict[str, Any], warm: WarmStart) -> tuple[CompiledBackend | None, str]:
    """(the compiled backend, one line saying how the build went); (None, why) when the QP solver generates
    no C, no C compiler is found or the build fails: the interpreted solver then runs.

    The step's inputs: x_prev, target, packed obstacles, [D_sf, w_d, w_o], lbx, ubx (unscaled), lbg, x0 and
    use_x0 (1: start from x0, 0: from the DLS predictor), lam_x0, lam_g0. Outputs: x (clipped to the bounds),
    lam_x, lam_g, the primal and dual KKT residuals, the tip at x, and at x and at x_prev (the start check) the
    smallest distance to an active sphere's surface (mm) and the smallest slack of the robot's limits (and, at
    x_prev, of the configuration box).
    """
    o = nlp.options
    if o.qpsol not in CODEGEN_QP:
        return None, f"compiled: qpsol {o.qpsol!r} generates no C (use {' or '.join(CODEGEN_QP)}): interpreted solver"
    name = f"steer_step_{nlp.robot.n_segments}s_{nlp.max_obstacles}o_{nlp.n_points}p"
    step = _step_function(nlp, sqp_opts, name)
    try:
        lib, how = compiled_library(name, [step], o.qpsol)
    except (RuntimeError, OSError) as exc:
        return None, f"compiled: build failed ({last_line(str(exc))}): interpreted solver"
    if lib is None:
        return None, f"compiled: {how}"
    tolerance = (float(sqp_opts["tol_pr"]), float(sqp_opts["tol_du"]))
    return CompiledBackend(nlp, CompiledFunction(lib, name), tolerance, warm), f"compiled: {how}"


def _kkt_function(nlp: SteerNLP) -> ca.Function:
    """The dual KKT residual |grad f + J_g^T lam_g + lam_x|_inf of the scaled NLP."""
    problem = nlp.problem
    y = problem["x"]
    lam_gs = ca.SX.sym("lam_g", nlp.lbg.size)
    lam_xs = ca.SX.sym("lam_x", nlp.nx)
    grad = ca.gradient(problem["f"], y) + ca.jacobian(problem["g"], y).T @ lam_gs + lam_xs
    return ca.Function("steer_kkt", [y, problem["p"], lam_gs, lam_xs], [ca.norm_inf(grad)])


def _predictor_function(nlp: SteerNLP) -> ca.Function:
    """The DLS predictor (`SteerNLP.dls_update` from x with the tip and Jacobian there) as a function."""
    o, nx = nlp.options, nlp.nx
    xs = ca.SX.sym("x", nx)
    tgs = ca.SX.sym("target", 3)
    los, his = ca.SX.sym("lo", nx), ca.SX.sym("hi", nx)
    tip, J, _, _ = nlp.check(xs)
    Js = J / ca.repmat(ca.DM(nlp.scale).T, 3, 1)
    dy = Js.T @ ca.solve(Js @ Js.T + o.damping**2 * ca.SX.eye(3), o.dls_gain * (tgs - tip))
    return ca.Function("steer_pred", [xs, tgs, los, his], [ca.fmin(ca.fmax(xs + dy / nlp.scale, los), his)])


def _step_function(nlp: SteerNLP, sqp_opts: dict[str, Any], name: str) -> ca.Function:
    """The whole step (inputs and outputs in `build_compiled`'s docstring) as one MX function."""
    o, nx, n_obs = nlp.options, nlp.nx, packing.WIDTH * nlp.max_obstacles
    solver = ca.nlpsol("steer_nlp", "sqpmethod", nlp.problem, sqp_opts)
    kkt = _kkt_function(nlp)
    pred = _predictor_function(nlp)
    S = ca.DM(nlp.scale)
    xp, tg, ob = ca.MX.sym("x_prev", nx), ca.MX.sym("target", 3), ca.MX.sym("obstacles", n_obs)
    w, lbx, ubx = ca.MX.sym("weights", 3), ca.MX.sym("lbx", nx), ca.MX.sym("ubx", nx)
    lbg, x0, use_x0 = ca.MX.sym("lbg", nlp.lbg.size), ca.MX.sym("x0", nx), ca.MX.sym("use_x0")
    lx0, lg0 = ca.MX.sym("lam_x0", nx), ca.MX.sym("lam_g0", nlp.lbg.size)
    start = ca.if_else(use_x0, x0, pred(xp, tg, lbx, ubx) if o.predictor else xp)
    start = ca.fmin(ca.fmax(start, lbx), ubx)
    pv = ca.vertcat(xp, tg, ob, w)
    sol = solver(x0=start * S, p=pv, lbx=lbx * S, ubx=ubx * S, lbg=lbg, ubg=nlp.ubg, lam_x0=lx0, lam_g0=lg0)
    ys, g = sol["x"], sol["g"]
    pr = ca.mmax(ca.vertcat(0, lbx * S - ys, ys - ubx * S, lbg - g, g - nlp.ubg))
    du = kkt(ys, pv, sol["lam_g"], sol["lam_x"])
    x = ca.fmin(ca.fmax(ys / S, lbx), ubx)
    tip_x, _, P, glim = nlp.check(x)
    _, _, P0, glim0 = nlp.check(xp)
    lo_lim, hi_lim = ca.DM(nlp.lbg_lim), ca.DM(nlp.ubg_lim)
    box_lo, box_hi = ca.DM(nlp.box[0]), ca.DM(nlp.box[1])
    return ca.Function(
        name,
        [xp, tg, ob, w, lbx, ubx, lbg, x0, use_x0, lx0, lg0],
        [
            *(x, sol["lam_x"], sol["lam_g"], pr, du, tip_x),
            *(_surface_distance(nlp, P, ob), ca.mmin(ca.vertcat(glim - lo_lim, hi_lim - glim))),
            _surface_distance(nlp, P0, ob),
            ca.mmin(ca.vertcat(glim0 - lo_lim, hi_lim - glim0, xp - box_lo, box_hi - xp)),
        ],
    )


def _surface_distance(nlp: SteerNLP, P: ca.MX, ob: ca.MX) -> ca.MX:
    """Smallest distance (mm) of the points P (3, n) to an active sphere's surface of the packed `ob`
    (+1e12 without one): the compiled step's re-check quantity, as `SteerNLP.clearance` computes it in numpy."""
    d = [ca.MX(_NO_SPHERE)]
    for i in range(nlp.max_obstacles):
        c, r, act = packing.slot(ob, i)
        diff = P - ca.repmat(c, 1, P.shape[1])
        dist = ca.mmin(ca.sqrt(ca.sum1(diff * diff))) - r
        d.append(ca.if_else(act > 0, dist, _NO_SPHERE))
    return ca.mmin(ca.vertcat(*d))
