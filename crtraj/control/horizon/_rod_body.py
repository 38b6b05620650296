"""The rod's body in the horizon NLP as PCC plus a first-order correction (issue 40: the rod horizon at PCC's size).

`crtraj.model.cosserat.RodModel` is PCC's body plus a correction Delta(x) (3 x P mm at the P collision points,
polynomials of degree ~10 in the bending coordinates, interpolated linearly along the arc between them). Built
into every stage of the horizon NLP, those polynomials, their Jacobian and the Hessian made its generated C about
90 MB for cdsr2 (PCC's: 2.5 MB), too large to compile. The horizon takes the correction to first order instead,
step k about a configuration x_bar_k, as NLP parameters:

    Delta(x_k) ~= Delta(x_bar_k) + J(x_bar_k) (b_k - b_bar_k) = a_k + J_k b_k,       b = x[:2 S] (bending),

with ``c_k = [a_k (3 P), vec(J_k) (3 P x 2 S, column-major)]`` filled by numpy (`LinearCorrection.values`, the
polynomials' exact values and derivatives). The NLP's body (tips, backbone points, the QP slots' points, whose
interpolation weights along the arc are parameters too) is PCC's plus this linear term: its generated C is about
PCC's size (cdsr2: 5.2 MB, PCC's 2.5 MB, the full correction's 90 MB) and compiles.

Where: `LinearisedBackend` linearises every solver call about that call's own start point (the shifted previous
solution, or the measured configuration held still on a cold start). An SQP iteration linearises the rows at the
start point anyway, and there the correction's value and Jacobian are the full model's: a call's first SQP
iteration is the full model's iteration (the Gauss-Newton Hessian included); only its line search and later
iterations see the linear model.

The guarantee. The step's move is verified densely on the full `RodModel` body (the loop's `SceneChecks`), never
on this approximation: the approximation only decides whether the NLP's plan passes that check. Its error grows
with the distance from the linearisation point; `reach_error` measures it over one step's reach (every x with
|A (x - x_bar)| <= the horizon's per-step cable and z limits), the largest move a solution's first step makes from
the measured configuration. Units: mm, rad.
"""

from __future__ import annotations

import time
from typing import Any

import casadi as ca
import numpy as np

from crtraj.control.horizon._backends import replace
from crtraj.model.cosserat import BOUND_FACTOR, RodModel, power_products, sample_within_limits
from crtraj.model.kinematics import Model

__all__ = ["LinearCorrection", "LinearisedBackend", "reach_bound", "reach_error"]

# Seeded samples of (configuration, move within one step's reach) the linearisation error is measured on.
REACH_SAMPLES = 2000


class LinearCorrection:
    """The first-order rod correction of `model` (a `RodModel`) as NLP parameters (the module docstring).

    pcc: the robot's PCC `Model` (the body the horizon builds its expressions on); n_params: len(c)."""

    def __init__(self, model: RodModel) -> None:
        self.rod = model
        self.correction = c = model.correction
        r = model.robot
        self.pcc = Model(r, model.n_points)
        self.nb = 2 * r.n_segments
        self.P = len(c.arcs)
        self.n_params = 3 * self.P * (1 + self.nb)
        self._coupling = r.coupling_matrix()
        # the monomials in order of degree: the derivative's coefficients are zero on the highest degree's (no
        # monomial one degree above), which come last, so its product stops after the first `_ng`
        deg = c.exps.sum(axis=1) if c.exps.size else np.zeros(len(c.exps), dtype=int)
        self._order = np.argsort(deg, kind="stable")
        self._exps = c.exps[self._order]
        self._ng = int(np.count_nonzero(deg < deg.max())) if len(deg) else 0
        self._value, self._slopes = self._derivative_table()
        self._tip_coef = (c.coef @ c.basis[:, -3:])[self._order]  # (M, 3): the tip's own polynomials
        # the rows of the last configurations `rows` evaluated (the solutions' tips), by their bytes: the next
        # call's start is the previous solution shifted by a step, the same rows
        self._rows: dict[bytes, np.ndarray] = {}

    def _derivative_table(self) -> tuple[np.ndarray, np.ndarray]:
        """((M, R), (M', 2 S R)): the monomials (M,, in order of degree) times the first give the R modes'
        amplitudes of Delta - mean; the first M' = `_ng` of them times the second, block b, those of dDelta/db_b
        (the modes' `basis` then makes them 3 P numbers each).

        d w^e / d w_i = e_i w^(e - 1_i), a lower monomial of the same list, so row m of block i (in w) is the sum
        of e_ki coef_k over the monomials k whose e_k - 1_i is monomial m; then b -> w = scale (C b)."""
        c = self.correction
        cb = c.coef[self._order]  # (M, R)
        index = {tuple(row): m for m, row in enumerate(self._exps.tolist())}
        dw = np.zeros((self.nb, *cb.shape))
        for i in range(self.nb):
            for k, row in enumerate(self._exps):
                if row[i]:
                    lower = row.copy()
                    lower[i] -= 1
                    dw[i, index[tuple(lower)]] += row[i] * cb[k]
        chain = c.scale[:, None] * self._coupling  # d w_i / d b_j
        db = np.einsum("imk,ij->jmk", dw, chain)  # (nb, M, R)
        if np.any(db[:, self._ng :]):
            raise ValueError("rod correction: a monomial of the highest degree has a nonzero derivative")
        return cb, np.concatenate(list(db[:, : self._ng]), axis=1)

    # ------------------------------------------------------------------ numbers
    def values(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Delta (n, 3 P), dDelta/db (n, 3 P, 2 S)) mm and mm/rad at configurations xs (n, nx): the polynomials'
        values and exact derivatives (column 3 j + i: coordinate i of point j)."""
        delta, blocks = self._evaluate(xs)
        return delta, np.swapaxes(blocks, 1, 2)

    def _evaluate(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Delta (n, 3 P), dDelta/db as (n, 2 S, 3 P): column b of the Jacobian per block) by two matrix
        products of the monomials with the tables (`_derivative_table`), then the modes."""
        c = self.correction
        phi = self._monomials(xs)
        n, R = len(phi), c.basis.shape[0]
        amp = np.empty((n, 1 + self.nb, R))
        amp[:, 0] = phi @ self._value
        # in slices of at most 2^18 multiply-adds: a larger product runs on a BLAS thread pool, whose threads
        # spin beside the loop's on a loaded machine
        cols = max(R, (1 << 18) // max(1, n * self._ng) // R * R)
        slopes = amp[:, 1:].reshape(n, -1)
        for j in range(0, slopes.shape[1], cols):
            slopes[:, j : j + cols] = phi[:, : self._ng] @ self._slopes[:, j : j + cols]
        out = amp @ c.basis  # (n, 1 + nb, 3 P)
        return c.mean + out[:, 0], out[:, 1:]

    def _monomials(self, xs: np.ndarray) -> np.ndarray:
        """The correction's monomials (n, M), in order of degree, at configurations xs (n, nx)."""
        b = np.atleast_2d(np.asarray(xs, dtype=float))[:, : self.nb]
        return power_products((b @ self._coupling.T) * self.correction.scale, self._exps)

    def tips(self, xs: np.ndarray) -> np.ndarray:
        """The full model's tips (n, 3) mm at configurations xs (n, nx): PCC's plus the correction's tip
        polynomials (`Correction.tip_expr`), by numpy (the interpreted `RodModel.tip` costs a step ~1 ms)."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        return self.pcc.tip_position(xs) + self.correction.mean[-3:] + self._monomials(xs) @ self._tip_coef

    def rows(self, xs: np.ndarray) -> np.ndarray:
        """The full model's tips (n, 3) mm at configurations xs (n, nx), from one evaluation of the correction
        and its Jacobian there (the tip is the correction's last point), whose linearisations are kept for
        `parameters_at`: a solution's tips, whose shifted rows are the next call's start point."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        c, delta = self._linearise(xs)
        self._rows = {x.tobytes(): row for x, row in zip(xs, c, strict=True)}
        return self.pcc.tip_position(xs) + delta[:, -3:]

    def parameters(self, x_bar: np.ndarray) -> np.ndarray:
        """c (n_params,) of the linearisation about configuration x_bar (nx,)."""
        return self.parameters_at(np.atleast_2d(x_bar))[0]

    def parameters_at(self, xs: np.ndarray) -> np.ndarray:
        """c (n, n_params) of the linearisations about configurations xs (n, nx), one row each: the rows `rows`
        kept where xs repeats its configurations, the others evaluated (each distinct one once)."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        keys = [x.tobytes() for x in xs]
        known = [self._rows.get(k) for k in keys]
        missing = [i for i, row in enumerate(known) if row is None]
        if missing:
            first = {keys[i]: i for i in reversed(missing)}  # each distinct configuration once
            fresh, _ = self._linearise(xs[list(first.values())])
            found = dict(zip(first, fresh, strict=True))
            for i in missing:
                known[i] = found[keys[i]]
        return np.stack(known)

    def _linearise(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(c (n, n_params) of the linearisations about configurations xs (n, nx), Delta (n, 3 P) there)."""
        delta, blocks = self._evaluate(xs)
        a = delta - np.einsum("nbk,nb->nk", blocks, xs[:, : self.nb])
        return np.concatenate([a, blocks.reshape(len(a), -1)], axis=1), delta  # vec(J) column-major

    # ---------------------------------------------------------------- symbols
    def delta(self, x: Any, c: Any) -> Any:
        """The linear correction (3 x P) at configuration x for parameters c (SX)."""
        n = 3 * self.P
        J = ca.reshape(c[n:], n, self.nb)
        return ca.reshape(c[:n] + ca.mtimes(J, x[: self.nb]), 3, self.P)

    def tip(self, x: Any, c: Any) -> Any:
        """The tip (3,) mm: PCC's plus the correction at the last collision point (the tip)."""
        return self.pcc.tip(x) + self.delta(x, c)[:, -1]

    def points(self, x: Any, c: Any, n: int) -> Any:
        """n backbone points (3 x n) evenly along the arc: PCC's plus the correction interpolated along the arc."""
        w = self.correction.weights(self.pcc.arc_positions(n))  # (n, P)
        return self.pcc.backbone_function(n)(x) + ca.mtimes(self.delta(x, c), ca.DM(w.T))


def reach_error(lin: LinearCorrection, step_limit: np.ndarray, samples: int = REACH_SAMPLES, seed: int = 0) -> float:
    """Largest distance (mm) between the correction and its linearisation about x_bar, at the collision points
    (the body between them is interpolated from them, so no point of it is off by more), over `samples` seeded
    pairs: x_bar random within the robot's limits, x one step's reach away (|A (x - x_bar)| <= step_limit, the
    cable and z rate rows of the horizon, on the boundary of that reach in a random direction) and within the
    limits."""
    r = lin.pcc.robot
    rng = np.random.default_rng([seed, 40])
    A, _ = r.cable_matrix()
    xb = sample_within_limits(r, samples, rng)
    d = rng.normal(size=xb.shape)
    d *= (1.0 / np.max(np.abs(d @ A.T) / step_limit, axis=1))[:, None]  # onto the reach's boundary
    x = xb + d
    lo, hi = r.config_box()
    inside = (r.limit_violation(x) <= 0.0) & np.all((x >= lo) & (x <= hi), axis=1)
    xb, x = xb[inside], x[inside]
    exact, _ = lin.values(x)
    at, J = lin.values(xb)
    approx = at + np.einsum("nkb,nb->nk", J, (x - xb)[:, : lin.nb])
    err = np.linalg.norm((exact - approx).reshape(len(x), -1, 3), axis=2)
    return float(err.max()) if len(err) else 0.0


def reach_bound(lin: LinearCorrection, step_limit: np.ndarray) -> float:
    """The stated bound (mm) of the linearisation's error over one step's reach: `BOUND_FACTOR` (the rod model's
    own) times the seeded `reach_error`."""
    return BOUND_FACTOR * reach_error(lin, step_limit)


class LinearisedBackend:
    """A backend (`crtraj.planning.nlp.NLPBackend`) whose every call first linearises the correction about its
    own start point, step by step: the parameters' last N n_params entries (`build_nlp`'s layout) become, for
    each step k, `LinearCorrection.parameters` at the start's x_k. The correction's value and Jacobian then equal
    the full model's at the point each SQP call linearises at, so the first iteration of a call is the full
    model's. The time taken is part of the call's wall time."""

    def __init__(self, inner: Any, lin: LinearCorrection, N: int) -> None:
        self.inner, self.lin, self.N = inner, lin, N
        self.name = inner.name
        self.n = lin.n_params * N

    def fill(self, p: np.ndarray, x_start: np.ndarray) -> np.ndarray:
        """p with its correction parameters (the last `n` entries) written for start point x_start (N nx,)."""
        c = self.lin.parameters_at(np.asarray(x_start, dtype=float).reshape(self.N, -1))
        out = np.array(p, dtype=float, copy=True)
        out[len(out) - self.n :] = c.ravel()
        return out

    def solve(self, query: Any) -> Any:
        t0 = time.perf_counter()
        p = self.fill(query.p, query.x0)
        spent = time.perf_counter() - t0
        r = self.inner.solve(replace(query, p=p))
        return replace(r, wall=r.wall + spent)
