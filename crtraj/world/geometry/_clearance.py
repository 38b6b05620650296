"""Many shapes against many body points at many times: the distances the scene's and the checker's
clearances are made of (mm, s; times absolute, the scene adds its clock).

- `shape_clearance`: the smallest lower bound of the signed distance (`MovingShape.lower_bound`) over
  points (..., P, 3) and shapes, per leading index, each index with its own window [t0, t1].
- `chord_clearance`: a lower bound of the distance from each *chord* between neighbouring backbone points
  (N, n, 3) to the shapes over each configuration's window, which the checker needs (the body is within the
  sagitta of its chords). For a convex shape the signed distance f is convex (the signed distance of a
  convex set is), so along a chord a -> b, ``f(a + u (b - a)) >= max(f(a) + u g_a.(b - a),
  f(b) - (1 - u) g_b.(b - a))`` (each tangent of a convex function is below it; the one-sided gradients
  returned on the non-smooth set are subgradients), and the smallest value of that maximum of two lines over
  u in [0, 1] (at an end or where they cross) bounds the chord. For a point set (cloud, mesh), whose distance
  is not convex, f is the grid's trilinear lower bound (`crtraj.world.geometry._grid`, at most
  `GridDistance.error` below the set's distance), the chord is sampled every `spacing` mm and
  ``f >= f(sample) - spacing / 2`` (the set's distance is 1-Lipschitz); chords whose end values already
  bound them above `refine_above` mm (``f >= (f(a) + f(b) - |b - a|) / 2``) keep that coarser bound. Over a
  window the distance is taken at the middle time and lowered by the sweep pad ``f(x, tm) - lower_bound(x, t0,
  t1)``, the larger of the two ends' (constant for a bounded shape, h L; convex in x for a half space).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.world.geometry._distance import MovingShape
from crtraj.world.geometry._grid import grid_of
from crtraj.world.geometry._points import POINT_SETS


def _windows(t0: np.ndarray, t1: np.ndarray) -> list[tuple[float, float, np.ndarray]]:
    """(t0, t1, indices) of each distinct window among the rows."""
    pairs = np.stack([t0, t1], axis=1)
    uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    cuts = np.flatnonzero(np.diff(inv[order])) + 1
    return [(float(uniq[inv[g[0]], 0]), float(uniq[inv[g[0]], 1]), g) for g in np.split(order, cuts)]


def shape_clearance(shapes: tuple[MovingShape, ...], p: np.ndarray, t0: Any, t1: Any) -> np.ndarray:
    """min over points and shapes of the signed distance's lower bound over [t0, t1] (mm): p (..., P, 3),
    t0, t1 (s) scalars or broadcastable to the leading dims. Returns the broadcast leading shape; +inf
    without shapes."""
    t0b, t1b = np.broadcast_arrays(np.asarray(t0, dtype=float), np.asarray(t1, dtype=float))
    lead = np.broadcast_shapes(p.shape[:-2], t0b.shape)
    n_pts = p.shape[-2]
    pb = np.broadcast_to(p, (*lead, n_pts, 3)).reshape(-1, n_pts, 3)
    T0 = np.broadcast_to(t0b, lead).ravel()
    T1 = np.broadcast_to(t1b, lead).ravel()
    out = np.full(pb.shape[0], np.inf)
    for ms in shapes:
        if ms.static:
            d = ms.distance(pb.reshape(-1, 3), 0.0).reshape(-1, n_pts).min(axis=1)
            np.minimum(out, d, out=out)
            continue
        for a, b, idx in _windows(T0, T1):
            d = ms.lower_bound(pb[idx].reshape(-1, 3), a, b).reshape(-1, n_pts).min(axis=1)
            out[idx] = np.minimum(out[idx], d)
    return out.reshape(lead)


def _convex_chords(f: np.ndarray, g: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(N,) min over chords of the tangent-line bound (module docstring); f (N, n), g (N, n, 3), P (N, n, 3)."""
    ab = P[:, 1:] - P[:, :-1]
    fa, fb = f[:, :-1], f[:, 1:]
    sa = np.einsum("ijk,ijk->ij", g[:, :-1], ab)
    sb = np.einsum("ijk,ijk->ij", g[:, 1:], ab)
    den = sa - sb
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(den != 0.0, (fb - sb - fa) / den, 0.0)
    u = np.clip(np.nan_to_num(u), 0.0, 1.0)

    def line_max(v: np.ndarray) -> np.ndarray:
        return np.maximum(fa + v * sa, fb + (v - 1.0) * sb)

    best = np.minimum(np.minimum(line_max(np.zeros_like(u)), line_max(np.ones_like(u))), line_max(u))
    return best.min(axis=1)


def _grid_distance(ms: MovingShape, points: np.ndarray, t: float) -> np.ndarray:
    """(N,) the grid's trilinear lower bound (`GridDistance.lookup`) of a point set's distance at points (N, 3) at
    time t: at most `GridDistance.error` below it (a KD-tree query near a ring of samples, a hole's rim or a pipe's
    axis, visits every sample of the ring)."""
    o, r, s = ms.frame(t)
    return s * grid_of(ms.shape).lookup(((points - o) @ r) / s)


def _sampled_chords(ms: MovingShape, tm: float, P: np.ndarray, f: np.ndarray, spacing: float, above: float) -> Any:
    """(N,) chord bound of a point set: coarse from the ends, sampled where the coarse bound is low."""
    ab = P[:, 1:] - P[:, :-1]
    length = np.linalg.norm(ab, axis=2)
    bound = 0.5 * (f[:, :-1] + f[:, 1:] - length)
    fine = np.argwhere(bound < above)
    if len(fine):
        m = int(np.ceil(float(length[fine[:, 0], fine[:, 1]].max()) / spacing))
        if m > 1:
            u = (np.arange(m + 1) / m)[None, :, None]
            a = P[fine[:, 0], fine[:, 1]][:, None, :]
            pts = a + u * ab[fine[:, 0], fine[:, 1]][:, None, :]
            d = _grid_distance(ms, pts.reshape(-1, 3), tm).reshape(len(fine), m + 1).min(axis=1)
            step = length[fine[:, 0], fine[:, 1]] / m
            bound[fine[:, 0], fine[:, 1]] = np.maximum(bound[fine[:, 0], fine[:, 1]], d - 0.5 * step)
    return bound.min(axis=1)


def chord_clearance(
    shapes: tuple[MovingShape, ...],
    P: np.ndarray,
    t0: np.ndarray,
    t1: np.ndarray,
    spacing: float = 1.0,
    refine_above: float = 40.0,
) -> np.ndarray:
    """(N,) lower bound (mm) of the signed distance from the chords of backbone points P (N, n, 3) to the
    shapes, each configuration over its window [t0[i], t1[i]] (absolute s); module docstring."""
    N, n, _ = P.shape
    out = np.full(N, np.inf)
    flat = P.reshape(-1, 3)
    for ms in shapes:
        groups = [(0.0, 0.0, np.arange(N))] if ms.static else _windows(t0, t1)
        for a, b, idx in groups:
            tm = 0.5 * (a + b)
            pts = P[idx]
            if isinstance(ms.shape, POINT_SETS):  # bounded: the sweep pad is h L (`MovingShape.lower_bound`)
                f = _grid_distance(ms, pts.reshape(-1, 3), tm).reshape(len(idx), n)
                pad = 0.5 * (b - a) * ms.surface_speed(a, b) if b > a else 0.0
                out[idx] = np.minimum(out[idx], _sampled_chords(ms, tm, pts, f, spacing, refine_above) - pad)
                continue
            f, g = ms.distance_and_gradient(pts.reshape(-1, 3) if not ms.static else flat, tm)
            f, g = f.reshape(len(idx), n), g.reshape(len(idx), n, 3)
            if b > a:
                pad = f - ms.lower_bound(pts.reshape(-1, 3), a, b).reshape(len(idx), n)
                pad = np.maximum(pad[:, :-1], pad[:, 1:]).max(axis=1)
            else:
                pad = 0.0
            out[idx] = np.minimum(out[idx], _convex_chords(f, g, pts) - pad)
    return out
