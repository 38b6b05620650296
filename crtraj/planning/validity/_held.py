"""The closed loop's dense verification of a step's move: the conservative clearance of a sampled motion whose
configurations between two samples stay near one of them (first-order servos), in one compiled call when the
validator has a kernel. Units: mm, s."""

from __future__ import annotations

import numpy as np

from crtraj.planning.validity._motion import MotionValidator

__all__ = ["held_clearance"]


def held_clearance(
    v: MotionValidator, X: np.ndarray, T: np.ndarray, after: tuple[float, float] | None = None, compiled: bool = True
) -> float:
    """Conservative body clearance (mm, minus D_sf) against `v`'s scene of a sampled motion X (n, nx) at times T
    (n,) s whose configurations between two samples each stay within half the two samples' body-motion bound of
    one of them (the closed loop's servo motions): every sample over the window from its previous to its next
    sample's time, with the larger half bound of its two motions as margin; with `after` (s, s) the last sample
    held over that window too. compiled: in one call of `v`'s compiled kernel when it has one (the bounds from
    the kernel's `motion_bound`, which agrees with numpy's to round-off, so the clearance does to ~1e-12 mm);
    False: numpy and the validator's clearance."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    T = np.atleast_1d(np.asarray(T, dtype=float))
    kernel, state, sc = v.kernel, v.state, v.scene
    if compiled and kernel is not None and sc.n_obstacles and not state.shapes:
        obstacles = (state.static_slots, None, 0.0) if v.static else (None, sc.motion_table(), sc.time_origin)
        out = kernel.verify_motion(X, T, after, obstacles, v.inflate)
        if out is not None:
            state.n_samples += len(X) + (after is not None)
            return out
    n = len(X)
    m = n + (after is not None)
    # one buffer per array, written in place (the numbers of the concatenations they replace)
    Xa, half, t_lo, t_hi = np.empty((m, X.shape[1])), np.zeros(m), np.empty(m), np.empty(m)
    Xa[:n] = X
    t_lo[0], t_hi[n - 1] = T[0], T[n - 1]
    if n > 1:
        B = v.motion_bound(X[1:] - X[:-1])
        half[0], half[n - 1] = B[0], B[-1]
        np.maximum(B[:-1], B[1:], out=half[1 : n - 1])
        half[:n] *= 0.5
        t_lo[1:n] = T[:-1]
        t_hi[: n - 1] = T[1:]
    if after is not None:
        Xa[n] = X[-1]
        t_lo[n], t_hi[n] = after
    return float(np.min(v.clearance(Xa, t_lo, t_hi, half)))
