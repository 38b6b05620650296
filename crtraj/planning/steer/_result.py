"""The outcome of one steer step: `SteerStatus`, `SteerResult`, and `assess`, which re-checks a backend's solution.

Whatever backend solved the step, its x is judged the same way here: the tip error against the tolerance, the
clearance of the collision points (`SteerNLP.clearance`), the robot's limits and the step bounds.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.planning.steer._nlp import Recheck, SteerNLP, SteerQuery, SteerSolution


class SteerStatus(str, enum.Enum):
    """Outcome of one steer step."""

    REACHED = "reached"  # converged, re-checked safe, tip on the target: the step did what was asked
    PARTIAL = "partial"  # converged and safe, but the tip stopped short (an unreachable target): x is usable
    UNSAFE = "unsafe"  # the solver converged but the re-check (points, limits, bounds) fails
    FAILED = "failed"  # the solver did not converge

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class SteerResult:
    """Outcome of one steer step.

    x: configuration (rad, mm); q: cable lengths and z (mm); tip: tip
    position (mm). converged: the solver's own success flag. safe: the
    re-check (collision points vs obstacles, limits, bounds) holds.
    reached: tip_error <= tolerance. `status` sums them up (`SteerStatus`):
    PARTIAL means converged and safe, a trustworthy x that stopped short of
    an unreachable target; `is_success()` only for REACHED.
    solver_status: the solver's own return status.
    message: one line for people. iterations; wall_time (s, whole call);
    tip_error (mm); min_clearance (mm, `Scene.clearance` at t, or the swept
    bound over [t, t_end]).
    """

    x: np.ndarray
    q: np.ndarray
    tip: np.ndarray
    reached: bool
    converged: bool
    safe: bool
    solver_status: str
    message: str
    iterations: int
    wall_time: float
    tip_error: float
    min_clearance: float
    solver: str

    @property
    def status(self) -> SteerStatus:
        """REACHED, PARTIAL (usable x, target not reached), UNSAFE or FAILED."""
        if not self.converged:
            return SteerStatus.FAILED
        if not self.safe:
            return SteerStatus.UNSAFE
        return SteerStatus.REACHED if self.reached else SteerStatus.PARTIAL

    def is_success(self) -> bool:
        """Converged, re-checked safe and the tip reached the target within tolerance."""
        return self.status is SteerStatus.REACHED

    def to_dict(self) -> dict[str, Any]:
        return {
            "x": self.x.tolist(),
            "q": self.q.tolist(),
            "tip": self.tip.tolist(),
            "status": str(self.status),
            "success": self.is_success(),
            "reached": self.reached,
            "converged": self.converged,
            "safe": self.safe,
            "solver_status": self.solver_status,
            "message": self.message,
            "iterations": self.iterations,
            "wall_time": self.wall_time,
            "tip_error": self.tip_error,
            "min_clearance": self.min_clearance,
            "solver": self.solver,
        }


def assess(nlp: SteerNLP, query: SteerQuery, solution: SteerSolution, t_start: float) -> SteerResult:
    """The result of a solve: the solution's x re-checked (NaN: x_prev returned unchanged); wall_time counts
    from t_start (`time.perf_counter`, s)."""
    o = nlp.options
    x, xp = solution.x, query.x_prev
    finite = bool(np.all(np.isfinite(x)))
    if not finite:
        x = xp.copy()
    check = _recheck(nlp, query, x, solution.recheck if finite else None)
    err = math.dist(check.tip, query.target)
    in_box = bool(np.all(x >= query.lbx) and np.all(x <= query.ubx))
    clear_ok = check.clearance >= -o.feasibility_tolerance
    safe = finite and clear_ok and in_box and check.in_limits
    reached = finite and err <= o.tolerance
    message = _message(nlp, query, solution, x, check, err, in_box)
    return SteerResult(
        x=x,
        q=nlp.cable_lengths(x),
        tip=check.tip,
        reached=reached,
        converged=solution.converged,
        safe=safe,
        solver_status=solution.status,
        message=solution.note + message,
        iterations=solution.iterations,
        wall_time=time.perf_counter() - t_start,
        tip_error=err,
        min_clearance=check.clearance,
        solver=solution.solver,
    )


def _recheck(nlp: SteerNLP, query: SteerQuery, x: np.ndarray, given: Recheck | None) -> Recheck:
    """The backend's own re-check quantities, or (tip, clearance, within limits) evaluated at x."""
    if given is not None:
        return given
    tip, _, pts, g = nlp.evaluate(x)
    clear = nlp.clearance(pts, query.packed, query.dsf, query.scene, query.t, query.t_end)
    return Recheck(tip, clear, nlp.limits_ok(g))


def _message(
    nlp: SteerNLP, query: SteerQuery, solution: SteerSolution, x: np.ndarray, check: Recheck, err: float, in_box: bool
) -> str:
    """One line for people: why the step failed, or how close it came."""
    o = nlp.options
    status, clear = solution.status, check.clearance
    if not bool(np.all(np.isfinite(solution.x))):
        return f"solver returned NaN ({status}); x_prev returned unchanged"
    if not solution.converged:
        return f"solver failed ({status}); tip error {err:.3g} mm, clearance {clear:.3g} mm"
    clear_ok = clear >= -o.feasibility_tolerance
    if not (clear_ok and in_box and check.in_limits):
        what = [] if clear_ok else [f"clearance {clear:.3g} mm < 0"]
        what += [] if check.in_limits else ["outside the robot's limits"]
        what += [] if in_box else ["outside the step bounds"]
        return "converged but the re-check failed: " + ", ".join(what)
    if err <= o.tolerance:  # converged and safe here
        return f"reached: tip error {err:.3g} mm, clearance {clear:.3g} mm"
    moved = float(np.max(np.abs(x - query.x_prev) * nlp.scale))
    why = "the step bound max_step" if moved >= 0.999 * o.max_step else "obstacles or the robot's limits"
    return f"target not reached: the closest safe configuration is {err:.3g} mm away (blocked by {why})"
