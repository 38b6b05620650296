"""Identifiability: which parameters the data determines, from the scaled Jacobian."""

from __future__ import annotations

import math

import numpy as np

from crtraj.model.calibration.layout import Layout
from crtraj.model.calibration.sites import PRIORITY
from crtraj.model.calibration.stats import Held


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


def _weighted(J: np.ndarray, e: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(weighted Jacobian rows x n, weighted residual rows, per-observation weights) of observed markers."""
    ok = np.isfinite(e).all(axis=2)
    s = np.sum(np.nan_to_num(e) ** 2, axis=2)
    w = np.where(ok, 1.0 / np.sqrt(1.0 + s / delta**2), 0.0)
    sw = np.sqrt(w)[..., None]
    Jw = (J * sw[..., None])[ok].reshape(-1, J.shape[-1])
    ew = (np.nan_to_num(e) * sw)[ok].reshape(-1)
    return Jw, ew, w[ok]
