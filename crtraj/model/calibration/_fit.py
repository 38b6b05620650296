"""The fit: initial capture frame, identifiability, the IPOPT solve, covariance and statistics (mm, rad)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.interrupt import check as check_interrupt
from crtraj.model.calibration._frames import align, rotation_vector
from crtraj.model.calibration._identify import at_fit, identifiable, scaled_singular_values, weighted_jacobian
from crtraj.model.calibration._layout import CalibrateOptions, Hardware, Layout
from crtraj.model.calibration._model import CalibrationModel
from crtraj.model.calibration._sites import GROUPS, MIN_SAMPLES, PLAUSIBLE_SCALE, check_sites
from crtraj.model.calibration._stats import CalibrationResult, Held, MarkerStats, Observations, marker_stats
from crtraj.model.robot import Robot


def initial_capture(cm: CalibrationModel, theta: np.ndarray, obs: Observations, rows: np.ndarray) -> np.ndarray:
    """The capture frame (6,) that best aligns the markers with the model at theta; `InputError` when the
    plausibility check on lengths fails (the markers' spread about their centroid against the model's, which
    the segment lengths set): the marker file is in another unit than mm."""
    P = cm.predict(theta, obs.values[rows])
    m = obs.positions[rows]
    ok = np.isfinite(m).all(axis=2)
    R, t, ratio = align(m[ok], P[ok])
    lo, hi = PLAUSIBLE_SCALE
    if not lo <= ratio <= hi:
        raise InputError(
            f"markers: their distances are {1 / ratio:.4g} times what the robot's segment lengths give (expected "
            "about 1): the marker file is not in mm (metres? convert it) or the markers sit elsewhere"
        )
    return np.concatenate([rotation_vector(R), t])


def _stats(
    cm: CalibrationModel, theta: np.ndarray, obs: Observations
) -> tuple[dict[str, dict[str, MarkerStats]], np.ndarray]:
    e = cm.residuals(theta, obs.values, obs.positions)
    names = [s.name for s in cm.sites]
    return {"fit": marker_stats(e[~obs.heldout], names), "heldout": marker_stats(e[obs.heldout], names)}, e


def _check_request(robot: Robot, obs: Observations, groups: Sequence[str], layout: Layout) -> np.ndarray:
    """(n,) the parameters asked for; `InputError` for an unknown group, a bad site or too few samples."""
    for g in groups:
        if g not in GROUPS:
            raise InputError(f"--fit: unknown parameter group {g!r} (known: {', '.join(GROUPS)})")
    check_sites(obs.sites, robot)
    seen = np.isfinite(obs.positions).all(axis=2)
    n_fit = int(np.sum(seen[~obs.heldout].any(axis=1)))
    free = np.zeros(layout.n, dtype=bool)
    for g in groups:
        free[layout.index(g)] = True
    need = max(MIN_SAMPLES, int(free.sum()))
    if n_fit < need:
        raise InputError(f"samples: {n_fit} usable fit samples, need at least {need} (record more motion)")
    return free


def _at_bound(layout: Layout, theta: np.ndarray, free: np.ndarray) -> tuple[str, ...]:
    span = layout.upper - layout.lower
    return tuple(
        layout.names[i]
        for i in np.flatnonzero(free)
        if min(theta[i] - layout.lower[i], layout.upper[i] - theta[i]) < 1e-6 * span[i]
    )


def fit(
    robot: Robot,
    hw: Hardware,
    zero_offsets: np.ndarray,
    obs: Observations,
    groups: Sequence[str],
    options: CalibrateOptions | None = None,
    capture: np.ndarray | None = None,
) -> CalibrationResult:
    """Fit the parameter groups `groups` to the observations; see the package docstring.

    zero_offsets: (nq,) the actuators' current zero offsets (prior). capture: (6,) prior capture frame
    (rotation vector rad, translation mm, capture -> robot); None: the best rigid alignment of the
    markers with the prior model (required when the capture frame is not fitted and unknown).
    """
    o = options or CalibrateOptions()
    fit_rows = ~obs.heldout
    layout0 = Layout.build(robot, zero_offsets, np.zeros(6), o)
    requested = _check_request(robot, obs, groups, layout0)
    cm = CalibrationModel(robot, hw, obs.sites, layout0)  # its functions take theta: only the prior changes
    if capture is None:
        capture = initial_capture(cm, layout0.prior, obs, np.flatnonzero(fit_rows))
    layout = Layout.build(robot, zero_offsets, np.asarray(capture, dtype=float), o)
    prior = layout.prior
    if "capture_frame" not in groups:
        initial_capture(cm, prior, obs, np.flatnonzero(fit_rows))  # the unit check still applies
    # identifiability at the prior (the Jacobian depends on the motion, not on the noise)
    Vf, Pf = obs.values[fit_rows], obs.positions[fit_rows]
    e0 = cm.residuals(prior, Vf, Pf)
    Jw0, _, _ = weighted_jacobian(cm.jacobians(prior, Vf, Pf), e0, o.loss_scale)
    free, held = identifiable(Jw0, layout, requested, o.identifiability_tol)
    if not free.any():
        names = ", ".join(h.name for h in held)
        raise InputError(f"--fit: this data determines none of the parameters asked for ({names})")
    theta, status, success, iters, t_solve = _solve(cm, layout, free, Vf, Pf, o)
    return _analyse(cm, obs, _Solved(layout, free, held, theta, status, success, iters, t_solve), Jw0, requested, o)


@dataclass(frozen=True)
class _Solved:
    """What the solve returns to the analysis: the layout, the fitted mask, the parameters held at the
    prior, the solution and IPOPT's verdict (status, success, iterations, solve time s)."""

    layout: Layout
    free: np.ndarray
    held: tuple[Held, ...]
    theta: np.ndarray
    status: str
    success: bool
    iterations: int
    solve_time: float


def _analyse(
    cm: CalibrationModel, obs: Observations, s: _Solved, Jw0: np.ndarray, requested: np.ndarray, o: CalibrateOptions
) -> CalibrationResult:
    """Identifiability at the fit, the covariance (standard errors; withheld for the parameters confounded
    at the fit) and the residual statistics."""
    layout, free, theta = s.layout, s.free, s.theta
    fit_rows = ~obs.heldout
    Vf, Pf = obs.values[fit_rows], obs.positions[fit_rows]
    e = cm.residuals(theta, Vf, Pf)
    Jw, ew, _ = weighted_jacobian(cm.jacobians(theta, Vf, Pf), e, o.loss_scale)
    ident = at_fit(Jw0, Jw, layout, requested, s.held, o.identifiability_tol)
    kept = ident.kept_fit  # a parameter held at the prior but kept at the fit inflates its partners' errors
    Jf = Jw[:, free]
    dof = max(Jw.shape[0] - int(free.sum()), 1)
    sigma2 = float(ew @ ew) / dof
    se = np.full(layout.n, math.nan)
    Jk = Jw[:, kept]
    cov = sigma2 * np.linalg.pinv(Jk.T @ Jk)
    se[kept] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    se[~free] = math.nan
    for name in ident.withheld:
        se[layout.names.index(name)] = math.nan
    after, e_all = _stats(cm, theta, obs)
    return CalibrationResult(
        layout=layout,
        theta=theta,
        prior=layout.prior,
        free=free,
        std_error=se,
        singular_values=scaled_singular_values(Jf),
        held=s.held,
        before=_stats(cm, layout.prior, obs)[0],
        after=after,
        success=s.success,
        status=s.status,
        iterations=s.iterations,
        solve_time=s.solve_time,
        sigma=math.sqrt(sigma2),
        residuals=e_all,
        heldout_mask=obs.heldout.copy(),
        at_bound=_at_bound(layout, theta, free),
        identifiability=ident,
    )


def _sample_functions(
    cm: CalibrationModel, layout: Layout, idx: np.ndarray, o: CalibrateOptions
) -> tuple[ca.Function, ca.Function]:
    """Per-sample loss and Hessian (upper triangle) as SX functions of the scaled free parameters xi.

    Hessian "gauss-newton": 2 sum_j w_j J_j^T J_j with the robust weights w_j (exact Jacobians J_j of the
    residuals; it drops the residuals' curvature and the loss's negative second derivative, so it is
    positive semidefinite and four times cheaper); "exact": CasADi's exact Hessian of the loss.
    """
    xi = ca.SX.sym("xi", idx.size)
    v = ca.SX.sym("v", 3 * layout.n_segments + 1)
    m = ca.SX.sym("m", 3 * cm.M)
    mask = ca.SX.sym("mask", cm.M)
    S = np.zeros((layout.n, idx.size))
    S[idx, np.arange(idx.size)] = layout.scale[idx]
    th = ca.DM(layout.prior) + ca.DM(S) @ xi
    d2 = o.loss_scale**2
    loss = cm.loss(th, v, m, mask, d2)
    if o.hessian == "exact":
        H = ca.hessian(loss, xi)[0]
    else:
        e = cm.residual(th, v, m)
        J = ca.jacobian(e, xi)
        w = ca.vertcat(*[mask[j] / ca.sqrt(1 + ca.sumsqr(e[3 * j : 3 * j + 3]) / d2) for j in range(cm.M)])
        Wr = ca.repmat(ca.reshape(ca.repmat(w.T, 3, 1), 3 * cm.M, 1), 1, idx.size)
        H = 2 * J.T @ (J * Wr)
    args = [xi, v, m, mask]
    return (
        ca.Function("loss_i", args, [loss], {"cse": True}),
        ca.Function("hess_i", args, [ca.triu(H)], {"cse": True}),
    )


def _solve(
    cm: CalibrationModel,
    layout: Layout,
    free: np.ndarray,
    values: np.ndarray,
    positions: np.ndarray,
    o: CalibrateOptions,
) -> tuple[np.ndarray, str, bool, int, float]:
    """IPOPT on the mean pseudo-Huber loss over the free parameters (scaled: theta = prior + scale xi).

    Returns (theta, IPOPT's status text, success, iterations, solve time s).
    """
    N = values.shape[0]
    mask = np.isfinite(positions).all(axis=2).astype(float)
    mm = np.nan_to_num(positions).reshape(N, 3 * cm.M)
    idx = np.flatnonzero(free)
    t0 = time.perf_counter()
    loss_i, hess_i = _sample_functions(cm, layout, idx, o)
    data = [ca.DM(values.T), ca.DM(mm.T), ca.DM(mask.T)]
    # mean over observations: the objective's size does not grow with N, so the tolerance means the same
    scale = 1.0 / max(float(mask.sum()), 1.0)
    xi = ca.MX.sym("xi", idx.size)
    # the parameters are shared by every sample (reduce_in) and the sums are taken inside the map
    f = scale * loss_i.map("loss_sum", "serial", N, [0], [0])(xi, *data)
    lam_f = ca.MX.sym("lam_f")
    H = lam_f * scale * hess_i.map("hess_sum", "serial", N, [0], [0])(xi, *data)
    hess_lag = ca.Function(
        "hess_lag",
        [xi, ca.MX.sym("p", 0), lam_f, ca.MX.sym("lam_g", 0)],
        [H],
        ["x", "p", "lam_f", "lam_g"],
        ["triu_hess_gamma_x_x"],
    )
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.max_iter": o.max_iter,
        "ipopt.tol": o.tol,
        "hess_lag": hess_lag,
    }
    solver = ca.nlpsol("calibrate", "ipopt", {"x": xi, "f": f}, opts)
    lbx = (layout.lower[idx] - layout.prior[idx]) / layout.scale[idx]
    ubx = (layout.upper[idx] - layout.prior[idx]) / layout.scale[idx]
    sol = solver(x0=np.zeros(idx.size), lbx=lbx, ubx=ubx)
    check_interrupt()  # CasADi turns a Ctrl-C into a stopped solve: stop here (crtraj.core.interrupt)
    t_solve = time.perf_counter() - t0
    st = solver.stats()
    out = layout.prior.copy()
    out[idx] += layout.scale[idx] * np.asarray(sol["x"]).ravel()
    status = str(st.get("return_status", "unknown"))
    return out, status, bool(st.get("success", False)), int(st.get("iter_count", 0)), t_solve
