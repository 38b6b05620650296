"""Identifiability: which parameters the data determines, from the scaled Jacobian."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crtraj.model.calibration._layout import Layout
from crtraj.model.calibration._sites import PRIORITY
from crtraj.model.calibration._stats import Held


def identifiable(Jw: np.ndarray, layout: Layout, free: np.ndarray, tol: float) -> tuple[np.ndarray, tuple[Held, ...]]:
    """(free parameters the data determines, the held ones) from the weighted Jacobian Jw (rows x n).

    Columns are scaled to unit norm and taken in `PRIORITY` order; one whose part outside the span of
    those already kept is below `tol` (relative) is held. Works on the n x n Gram matrix: a tall QR or SVD
    runs multi-threaded LAPACK, which is 25 times slower on a loaded machine; the Gram matrix keeps the
    relative residuals to ~1e-7 for the near-dependent columns that matter here (tol 1e-6).
    """
    G = Jw.T @ Jw
    norms = np.sqrt(np.maximum(np.diag(G), 0.0))
    order = [i for g in PRIORITY for i in layout.index(g) if free[i]]
    kept: list[int] = []
    held: list[Held] = []
    for i in order:
        if norms[i] == 0.0:
            held.append(Held(layout.names[i], (), 0.0))
            continue
        if kept:
            Gn = G[np.ix_(kept, kept)] / np.outer(norms[kept], norms[kept])
            g = G[kept, i] / (norms[kept] * norms[i])
            coef = np.linalg.lstsq(Gn, g, rcond=None)[0]
            rel = math.sqrt(max(1.0 - float(g @ coef), 0.0))
        else:
            coef, rel = np.zeros(0), 1.0
        if rel < tol:
            big = [layout.names[kept[j]] for j in np.argsort(-np.abs(coef))[:3] if abs(coef[j]) > 1e-3]
            held.append(Held(layout.names[i], tuple(big), rel))
            continue
        kept.append(i)
    out = np.zeros(layout.n, dtype=bool)
    out[kept] = True
    return out, tuple(held)


def scaled_singular_values(Jf: np.ndarray) -> np.ndarray:
    """Singular values (descending) of Jf with its columns scaled to unit norm, from the Gram matrix."""
    if Jf.size == 0:
        return np.zeros(0)
    G = Jf.T @ Jf
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    ev = np.linalg.eigvalsh(G / np.outer(d, d))
    return np.sqrt(np.maximum(ev, 0.0))[::-1]


def weighted_jacobian(J: np.ndarray, e: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(weighted Jacobian rows x n, weighted residual rows, per-observation weights) of the observed markers.

    J: (N, M, 3, n) residual Jacobians; e: (N, M, 3) residuals (mm, NaN: not seen); delta: the pseudo-Huber
    scale (mm). Rows are scaled by the square root of the robust weight 1 / sqrt(1 + |e|^2 / delta^2).
    """
    ok = np.isfinite(e).all(axis=2)
    s = np.sum(np.nan_to_num(e) ** 2, axis=2)
    w = np.where(ok, 1.0 / np.sqrt(1.0 + s / delta**2), 0.0)
    sw = np.sqrt(w)[..., None]
    Jw = (J * sw[..., None])[ok].reshape(-1, J.shape[-1])
    ew = (np.nan_to_num(e) * sw)[ok].reshape(-1)
    return Jw, ew, w[ok]


@dataclass(frozen=True)
class Identifiability:
    """What the data determines, judged at the prior and again at the fitted parameters.

    held_prior: the parameters asked for that were held at their prior (judged at the prior). held_fit: the
    same test at the fitted parameters. A Jacobian column can be zero at the prior only (a segment commanded
    straight makes the coupling look inert while, at the truth, its zero offsets bend it), so a parameter is
    confounded at the fit when `held_fit` holds it and `held_prior` did not, or named it as having no effect.
    kept_fit: (n,) the parameters the fit's covariance is taken over. withheld: fitted parameters whose
    standard error is withheld (confounded at the fit). sv_prior, sv_fit: singular values (descending) of
    the column-scaled weighted Jacobian of the parameters asked for, at the prior and at the fit.
    """

    held_prior: tuple[Held, ...]
    held_fit: tuple[Held, ...]
    kept_fit: np.ndarray
    withheld: tuple[str, ...]
    sv_prior: np.ndarray
    sv_fit: np.ndarray

    def confounded_at_fit(self) -> tuple[Held, ...]:
        """The parameters confounded at the fit that the prior did not show as confounded."""
        before = {h.name: h for h in self.held_prior}
        return tuple(
            h
            for h in self.held_fit
            if h.name not in before or (h.confounded_with and not before[h.name].confounded_with)
        )

    def effect_at_fit(self, name: str) -> tuple[str, ...]:
        """For a parameter without effect at the prior: what it is confounded with at the fit (() if nothing)."""
        out: list[str] = []
        for h in self.confounded_at_fit():
            if h.name == name:
                out += h.confounded_with
            elif name in h.confounded_with:
                out += [h.name, *(c for c in h.confounded_with if c != name)]
        return tuple(dict.fromkeys(out))


def at_fit(
    Jw_prior: np.ndarray,
    Jw_fit: np.ndarray,
    layout: Layout,
    requested: np.ndarray,
    held_prior: tuple[Held, ...],
    tol: float,
) -> Identifiability:
    """Identifiability at the fit (see `Identifiability`): Jw_prior, Jw_fit are the weighted Jacobians
    (rows x n) at the prior and at the fitted parameters; requested: (n,) the parameters asked for."""
    kept, held_fit = identifiable(Jw_fit, layout, requested, tol)
    ident = Identifiability(held_prior, held_fit, kept, (), np.zeros(0), np.zeros(0))
    withheld: list[str] = []
    for h in ident.confounded_at_fit():
        withheld += [h.name, *h.confounded_with]
    return Identifiability(
        held_prior,
        held_fit,
        kept,
        tuple(dict.fromkeys(withheld)),
        scaled_singular_values(Jw_prior[:, requested]),
        scaled_singular_values(Jw_fit[:, requested]),
    )
