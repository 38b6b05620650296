"""The horizon NLP in stage form for a structured QP solver (option ``qpsol = "hpipm"``, issue 29).

HPIPM solves QPs of optimal-control structure: variables ordered stage by stage [s_0 u_0 s_1 u_1 ... s_N],
each stage's rows in its own (s_k, u_k) and gap rows s_k+1 = A s_k + B u_k. The horizon NLP's rows and
residuals of step j involve x_j, x_j-1 and x_j-2 (rates, accelerations, smoothness), so the stage state is
s_k = (x_k, x_k-1) and the input u_k = x_k+1: every row of step k+1 falls into stage k. s_0 = (x_0, x_-1) is
fixed by its box; the gap rows are s_k+1 - (u_k, x_k) = 0. `StageSolver` has the dense solver's interface
(x, g, multipliers in the dense NLP's order), so the backends, the screening and the warm start are unchanged.
Units: mm, rad, s.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from crtraj.control.horizon._build import HorizonNLP, HorizonSpec, gauss_newton, nlp_solver


def _steps(expr: ca.SX, xv: ca.SX, nx: int) -> np.ndarray:
    """The step j (1..N) of each entry of expr: the last configuration it depends on (its columns of X)."""
    sp = ca.jacobian(expr, xv).sparsity()
    rows, cols = sp.get_triplet()
    step = np.zeros(expr.numel(), dtype=int)
    lo = np.full(expr.numel(), 10**9)
    for r, c in zip(rows, cols, strict=True):
        step[r] = max(step[r], c // nx + 1)
        lo[r] = min(lo[r], c // nx + 1)
    # an entry of step j may use x_j-2 .. x_j only (x_0 and x_-1 are parameters)
    if np.any((step > 0) & (lo < step - 2)):
        raise RuntimeError("horizon stage form: a row couples configurations more than two steps apart")
    return np.maximum(step, 1)


class StageSolver:
    """sqpmethod with HPIPM on the stage form of a horizon NLP, called like the dense solver (`call`, `stats`):
    dense x, g, lam_x, lam_g in and out, mapped to the stage variables and rows by index."""

    def __init__(self, spec: HorizonSpec, built: HorizonNLP) -> None:
        o = spec.options
        nx, N = spec.model.robot.nx, o.horizon
        nlp = built.nlp
        xv, p, g = nlp["x"], nlp["p"], nlp["g"]
        X = ca.reshape(xv, nx, N)
        x0, xm1 = p[:nx], p[nx : 2 * nx]  # the parameters' first entries (`build_nlp`)
        S = [ca.SX.sym(f"s{k}", 2 * nx) for k in range(N + 1)]
        U = [ca.SX.sym(f"u{k}", nx) for k in range(N)]
        cols = [xm1, x0] + [X[:, j] for j in range(N)]  # x_-1 .. x_N

        def at_stage(e: ca.SX, j: int) -> ca.SX:
            # step j's entries in stage j-1's variables: x_j = u, x_j-1 and x_j-2 from the state
            old = ca.vertcat(cols[j + 1], cols[j], cols[j - 1])
            new = ca.vertcat(U[j - 1], S[j - 1][:nx], S[j - 1][nx:])
            return ca.substitute(e, old, new)

        g_step = _steps(g, xv, nx)
        r_step = _steps(built.r_vec, xv, nx)
        rows, order, res = [], [], []
        for j in range(1, N + 1):
            idx = np.flatnonzero(g_step == j)
            order.append(idx)
            rows.append(S[j] - ca.vertcat(U[j - 1], S[j - 1][:nx]))  # HPIPM's order: the gap rows first
            rows.append(at_stage(g[idx.tolist()], j))
            res.append(at_stage(built.r_vec[np.flatnonzero(r_step == j).tolist()], j))
        w = ca.vertcat(*[ca.vertcat(S[k], U[k]) for k in range(N)], S[N])
        gs, r = ca.vertcat(*rows), ca.vertcat(*res)
        stage_nlp = self.nlp = {"x": w, "p": p, "f": ca.sumsqr(r), "g": gs}
        # where each dense row and configuration sits among the stage rows and variables
        pos, at = [], 0
        for idx in order:
            pos.append(np.arange(at + 2 * nx, at + 2 * nx + len(idx)))
            at += len(idx) + 2 * nx
        self.g_of = np.empty(g.numel(), dtype=np.intp)
        self.g_of[np.concatenate(order)] = np.concatenate(pos)
        self.u_of = np.concatenate([k * 3 * nx + 2 * nx + np.arange(nx) for k in range(N)])
        self.nx, self.N, self.nw, self.ng = nx, N, int(w.numel()), int(gs.numel())
        hess = gauss_newton(o, r, stage_nlp, "sqp")
        structure = {
            "N": N,
            "nx": [2 * nx] * (N + 1),
            "nu": [nx] * N + [0],
            "ng": [len(idx) for idx in order] + [0],
        }
        self.solver = nlp_solver("sqp", o, stage_nlp, hess, structure)
        # x_-1 .. x_N stacked (parameters then x) -> the stage variables: s_k = (x_k, x_k-1), u_k = x_k+1
        col = np.arange((N + 2) * nx).reshape(N + 2, nx)
        self.w_of = np.concatenate([np.concatenate([col[k + 1], col[k], col[k + 2]]) for k in range(N)])
        self.w_of = np.concatenate([self.w_of, col[N + 1], col[N]])
        # lam_x of x_j: the sum over its copies (u_j-1 and the two state copies, all boxed: HPIPM bounds every
        # variable, and an infinite bound becomes 1e8, which slows its interior point; the gap rows' terms cancel)
        self.gather = ca.DM(ca.Sparsity.triplet((N + 2) * nx, self.nw, self.w_of.tolist(), list(range(self.nw))), 1.0)
        self.function = self._dense_function()

    def _dense_function(self) -> ca.Function:
        """The stage solver as one CasADi function with sqpmethod's dense inputs and outputs (what
        `build_compiled` generates C for): the index maps of `call`, symbolic."""
        nx, n, ng = self.nx, self.N * self.nx, int(self.g_of.size)
        names = ("x0", "p", "lbx", "ubx", "lbg", "ubg", "lam_x0", "lam_g0")
        x0, p = ca.MX.sym("x0", n), ca.MX.sym("p", self.solver.size1_in("p"))
        lbx, ubx, lx = (ca.MX.sym(k, n) for k in ("lbx", "ubx", "lam_x0"))
        lbg, ubg, lg = (ca.MX.sym(k, ng) for k in ("lbg", "ubg", "lam_g0"))
        v = ca.vertcat(p[nx : 2 * nx], p[:nx], x0)
        w0 = v[self.w_of.tolist()]
        lbw = ca.vertcat(p[nx : 2 * nx], p[:nx], lbx)[self.w_of.tolist()]
        ubw = ca.vertcat(p[nx : 2 * nx], p[:nx], ubx)[self.w_of.tolist()]
        u = self.u_of.tolist()
        lbgs, ubgs, lam_gs = (ca.MX(ca.DM.zeros(self.ng)) for _ in range(3))
        gi = self.g_of.tolist()
        lbgs[gi], ubgs[gi], lam_gs[gi] = lbg, ubg, lg
        lam_ws = ca.MX(ca.DM.zeros(self.nw))
        lam_ws[u] = lx
        sol = self.solver(x0=w0, p=p, lbx=lbw, ubx=ubw, lbg=lbgs, ubg=ubgs, lam_x0=lam_ws, lam_g0=lam_gs)
        lam_x = ca.mtimes(self.gather, sol["lam_x"])[2 * nx :]
        outs = [sol["x"][u], sol["f"], sol["g"][gi], lam_x, sol["lam_g"][gi], sol["lam_p"]]
        return ca.Function(
            "replan_sqp_stage",
            [x0, p, lbx, ubx, lbg, ubg, lx, lg],
            outs,
            list(names),
            ["x", "f", "g", "lam_x", "lam_g", "lam_p"],
        )

    def call(self, args: dict[str, Any]) -> dict[str, Any]:
        """The dense solver's call: args and outputs in the dense NLP's variables and rows."""
        nx, N = self.nx, self.N
        p = np.asarray(args["p"], dtype=float).ravel()
        xs = np.concatenate([p[nx : 2 * nx], p[:nx], np.asarray(args["x0"], dtype=float).ravel()])
        cols = xs.reshape(N + 2, nx)  # x_-1 .. x_N
        w0 = np.concatenate([np.concatenate([cols[k + 1], cols[k], cols[k + 2]]) for k in range(N)])
        w0 = np.concatenate([w0, cols[N + 1], cols[N]])
        # s_0 = (x_0, x_-1) given; every copy of x_j in its box
        lbw = np.concatenate([xs[: 2 * nx], np.asarray(args["lbx"], dtype=float).ravel()])[self.w_of]
        ubw = np.concatenate([xs[: 2 * nx], np.asarray(args["ubx"], dtype=float).ravel()])[self.w_of]
        lbg, ubg = np.zeros(self.ng), np.zeros(self.ng)  # the gap rows: equalities
        lbg[self.g_of], ubg[self.g_of] = args["lbg"], args["ubg"]
        a: dict[str, Any] = {"x0": w0, "p": p, "lbx": lbw, "ubx": ubw, "lbg": lbg, "ubg": ubg}
        if args.get("lam_g0") is not None:
            lam_w, lam_g = np.zeros(self.nw), np.zeros(self.ng)
            lam_w[self.u_of] = np.asarray(args["lam_x0"]).ravel()
            lam_g[self.g_of] = np.asarray(args["lam_g0"]).ravel()
            a.update(lam_x0=lam_w, lam_g0=lam_g)
        sol = self.solver.call(a)
        # the dense multipliers: the copies of x_j in the state are unbounded, and the gap rows' terms of the
        # copies cancel in the sum over copies, so the dense KKT conditions hold with these
        w, gs = np.asarray(sol["x"]).ravel(), np.asarray(sol["g"]).ravel()
        return {
            "x": ca.DM(w[self.u_of]),
            "f": sol["f"],
            "g": ca.DM(gs[self.g_of]),
            "lam_x": ca.mtimes(self.gather, sol["lam_x"])[2 * nx :],
            "lam_g": ca.DM(np.asarray(sol["lam_g"]).ravel()[self.g_of]),
            "lam_p": sol["lam_p"],
        }

    def stats(self) -> dict[str, Any]:
        """sqpmethod's stats of the last call."""
        return self.solver.stats()
