"""Row bookkeeping of the horizon NLP: merged parallel rate rows, implied acceleration rows, the warm start's
shift of step-by-step blocks, and the sagitta that inflates its obstacle spheres (units mm, rad)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def sagitta(robot: Any, spacing: float) -> float:
    """Largest distance (mm) of a backbone arc of length `spacing` (mm) from its chord."""
    kappa = max(s.theta_max / s.length for s in robot.segments)
    half = min(kappa * spacing / 2.0, math.pi / 2.0)
    return float((1.0 - math.cos(half)) / kappa)


def _multiple(row: np.ndarray, base: np.ndarray) -> float:
    """s with row = s base (to 1e-12 relative), else 0."""
    s = float(row @ base) / float(base @ base) if base.any() else 0.0
    return s if s != 0.0 and np.max(np.abs(row - s * base)) <= 1e-12 * np.max(np.abs(row)) else 0.0


def merge_parallel_rows(rows: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Constraints |rows @ v| <= bound (rows (m, n), bound (m,)) without repeats.

    A row that is a nonzero multiple s of an earlier kept row states the same constraint as
    |earlier @ v| <= bound_i / |s|: it is dropped and the earlier row keeps the tighter bound.
    Returns (rows (k, n), bounds (k,)) in first-seen order.
    """
    R = np.asarray(rows, dtype=float)
    b = np.array(bound, dtype=float).reshape(len(R))
    keep: list[int] = []
    for i, r in enumerate(R):
        for j in keep:
            s = _multiple(r, R[j])
            if s:
                b[j] = min(b[j], b[i] / abs(s))
                break
        else:
            keep.append(i)
    return R[keep].copy(), b[keep]


def implied_rows(speed: np.ndarray, speed_bound: np.ndarray, acc: np.ndarray, acc_bound: np.ndarray) -> np.ndarray:
    """Which acceleration rows (|acc @ (dx_k - dx_k-1)| <= acc_bound) the speed rows (|speed @ dx| <=
    speed_bound, at both steps) imply: a multiple s of a speed row with |s| 2 speed_bound <= acc_bound.
    Boolean (len(acc),)."""
    out = np.zeros(len(acc), dtype=bool)
    for i, r in enumerate(acc):
        scales = [abs(_multiple(r, base)) for base in speed]
        out[i] = any(s > 0.0 and s * 2.0 * b <= acc_bound[i] for s, b in zip(scales, speed_bound, strict=True))
    return out


def shift_index(blocks: tuple[tuple[int, int], ...]) -> np.ndarray:
    """Indices that move a vector of step-by-step blocks ((rows per step, steps) each) one step earlier, the
    last step repeated: ``np.append(v, 0.0)[index]``. A block of one step (rows of step 1 only) takes the
    zero appended past the end (step 2 had no such rows)."""
    total = sum(w * steps for w, steps in blocks)
    idx, start = [], 0
    for w, steps in blocks:
        if steps == 1:
            idx.append(np.full(w, total))
        else:
            k = np.minimum(np.arange(steps) + 1, steps - 1)
            idx.append((start + k[:, None] * w + np.arange(w)).ravel())
        start += w * steps
    return np.concatenate(idx).astype(np.intp)
