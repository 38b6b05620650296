"""The horizon's obstacle spheres of a known scene, tabulated for a run's step times before the steps (issue 29).

A scene whose motion is known in advance (`crtraj.world.sources.SceneObstacles`) gives the same swept spheres
for the same horizon start time; the loop's steps start at times it knows before the first one. `ObstacleTable`
computes the spheres (and their packed slots) of every step time in one vectorised pass before the run, so a
step's `Replanner.obstacles_from_scene` looks its rows up instead of evaluating the scene's time functions
(about 60-80 us of Python and numpy per step on simulation 2). The pass applies the same elementwise operations
to each row as the per-step call, so the rows are the per-step call's bit for bit (checked by
`tests/test_horizon_obstacles.py`); a time or a scene the table does not hold is computed per step as before.
Units: mm, s.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from crtraj.world import packing

# the most step times tabulated (a longer run computes its later steps per step, as before)
MAX_ROWS = 20000


class ObstacleTable:
    """Swept spheres (centres, inflated radii) and packed slots of one scene for given horizon start times.

    windows: t0 (s; (T, 1) for T start times) -> (lo, hi) (N,) or (T, N) s, the step windows
    (`Replanner.step_windows`). rho: radii (mm) -> inflated radii (mm). slots: the QP's obstacle slots (a scene
    of more obstacles is not packed here: the broad phase packs it per step from the centres and radii).
    """

    def __init__(
        self,
        windows: Callable[[Any], tuple[np.ndarray, np.ndarray]],
        rho: Callable[[np.ndarray], np.ndarray],
        slots: int,
    ) -> None:
        self._windows, self._rho, self.slots = windows, rho, slots
        self.scene: Any = None
        self._row: dict[float, int] = {}
        self.centers = self.rho = np.zeros(0)
        self.packed: np.ndarray | None = None

    def tabulate(self, scene: Any, times: np.ndarray) -> None:
        """Compute the rows of `scene` for horizon start times `times` (s; the first MAX_ROWS), replacing any."""
        t = np.asarray(times, dtype=float).ravel()[:MAX_ROWS]
        self.scene, self._row, self.packed = None, {}, None
        if scene.n_obstacles == 0 or t.size == 0:
            return
        lo, hi = self._windows(t[:, None])
        centers, radii = scene.swept_spheres(lo, hi)  # (T, N, M, 3), (T, N, M)
        rho = self._rho(radii)
        fits = scene.n_obstacles <= self.slots
        packed = packing.pack(centers, rho, self.slots, "the replanner") if fits else None
        for a in (centers, rho) if packed is None else (centers, rho, packed):
            a.setflags(write=False)  # handed out as they are: nobody may write into the table
        self.centers, self.rho, self.packed = centers, rho, packed
        self.scene, self._row = scene, {float(x): i for i, x in enumerate(t)}

    def row(self, scene: Any, t0: float) -> int | None:
        """The row of start time t0 (s) of `scene` (the same object as tabulated), or None."""
        return self._row.get(t0) if scene is self.scene else None

    def spheres(self, scene: Any, t0: float) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """(packed slots or None, centres (N, M, 3), inflated radii (N, M)) mm of the horizon from t0 (s): the
        table's row (read-only views) when it holds one, else computed now (packed None)."""
        j = self.row(scene, t0)
        if j is None:
            centers, radii = scene.swept_spheres(*self._windows(t0))
            return None, centers, self._rho(radii)
        return None if self.packed is None else self.packed[j], self.centers[j], self.rho[j]


def swept_states(
    centers: Any, radii: Any, velocities: Any, radius_rates: Any, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(centres (N, m, 3), radii (N, m)) mm of spheres that hold what live obstacles, extrapolated at constant
    velocity, cover over each window [lo_k, hi_k] (s after the state): centers (m, 3) mm, radii (m,) mm,
    velocities (m, 3) mm/s and radius_rates (m,) mm/s (None: zero)."""
    c = np.asarray(centers, dtype=float).reshape(-1, 3)
    m = len(c)
    r = np.asarray(radii, dtype=float).reshape(m)
    v = np.zeros((m, 3)) if velocities is None else np.asarray(velocities, dtype=float).reshape(m, 3)
    rd = np.zeros(m) if radius_rates is None else np.asarray(radius_rates, dtype=float).reshape(m)
    ca_ = c[None] + lo[:, None, None] * v[None]
    cb_ = c[None] + hi[:, None, None] * v[None]
    rmax = np.maximum(r[None] + lo[:, None] * rd[None], r[None] + hi[:, None] * rd[None])
    return 0.5 * (ca_ + cb_), rmax + 0.5 * np.linalg.norm(cb_ - ca_, axis=-1)
