"""The safe IK's rescue stage: many batched starts around a projection that the push-out could not clear.

Before the safety-constrained NLP (IPOPT, 5-130 ms a solve, more with many obstacles) is asked for a
configuration, the rescue moves `starts` configurations spread around the failed projection (in the
body-motion metric, mm), all at once, onto the target by the batch damped-Newton projection
(`SafeIK.project`: the compiled tip Jacobian, one call per step for every start) and pushes the ones on
target out of the obstacles (`SafeIK.push_out`: null-space steps up the batched clearance gradient).
Of the safe ones the nearest to the seed (body motion) is taken, as the NLP, which stays nearest to the
seed, would. Only when none is safe does the NLP run. The spread directions are drawn once from a
fixed seed, so a query's result does not depend on anything but its own inputs, and the query's random
generator is not touched.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# Spreads (mm of body motion) of the starts around the failed projection: half near, half far.
SPREADS = (15.0, 50.0)
# Newton steps that bring the starts onto the target (most need a few; the step size is capped, so
# starts far from it need more) and push-out rounds of the starts on it.
NEWTON = 30
ROUNDS = 12


class IKRescue:
    """Multi-start rescue for one `SafeIK` (`ik`, duck-typed: `project`, `push_out`, `tips`); starts:
    configurations per rescue (0: never rescue, the NLP runs as before)."""

    def __init__(self, ik: Any, nx: int, starts: int) -> None:
        self.ik = ik
        self.starts = int(starts)
        directions = np.random.default_rng(0).normal(size=(self.starts, nx))
        scale = np.repeat(SPREADS, (self.starts + 1) // 2)[: self.starts]
        self._offsets = directions * (scale / np.maximum(np.linalg.norm(directions, axis=1), 1e-300))[:, None]

    def solve(self, run: Any, i: int, deadline: float | None) -> tuple[np.ndarray, float, float] | None:
        """A safe configuration with the tip on `run.target` (mm) near seed i of the IK run `run`
        (`crtraj.planning.ik.IKRun`): (x (nx,), tip error mm, clearance mm), or None. No push-out
        round starts after `deadline` (a `time.perf_counter()` value)."""
        if self.starts == 0:
            return None
        ik, v = self.ik, run.v
        y = v.metric(run.X[i]) + self._offsets
        X, err = ik.project(run.target, v.project_limits(v.config_from_metric(y)), NEWTON)
        on = np.flatnonzero(err <= run.tol)
        if not len(on):
            return None
        X, clear = ik.push_out(
            run.target,
            X[on],
            required=run.required,
            rounds=ROUNDS,
            validator=v,
            t_check=run.t_check,
            tol=run.tol,
            enough=1,
            deadline=deadline,
        )
        err = np.linalg.norm(ik.tips(v, X) - run.target, axis=1)
        ok = np.flatnonzero((clear >= run.required) & (err <= run.tol) & v.within_limits(X) & run.in_cone(X))
        if not len(ok):
            return None
        k = ok[int(np.argmin(v.motion_bound(X[ok] - run.seeds[i])))]
        return X[k], float(err[k]), float(clear[k])
