"""What every planner returns: `PlanResult` with an OMPL-like `PlanStatus`.

A plan is a timed sequence of configurations; the motion between two
consecutive waypoints is the straight line in configuration space, so
`PlanResult.config_at` reproduces exactly the motion the planner verified.
Units: mm, rad, s.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np


class PlanStatus(str, enum.Enum):
    """Outcome of a planning query (names follow OMPL's PlannerStatus)."""

    EXACT = "exact"  # a verified path reaches the goal within tolerance
    APPROXIMATE = "approximate"  # a verified path to the tree node closest to the goal; goal not reached
    TIMEOUT = "timeout"  # the stop condition fired before any path was found
    INVALID_START = "invalid_start"  # start out of reach, out of limits or in collision
    INVALID_GOAL = "invalid_goal"  # no safe configuration puts the tip on the goal
    ERROR = "error"  # the planner could not run (its worker process stopped, or it raised)

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class PlanResult:
    """A planned motion and how it was found.

    t: waypoint times (s, absolute: the first is the query's t0). configs:
    (K, nx) configurations; tips: (K, 3) tip positions (mm); cables: (K, nq)
    actuation (mm). length: tip travel along the returned motion (mm),
    cost: the planner's own path cost (tip length of the tree path for the
    task-space planners, body-motion metric for the c-space planner).
    min_clearance: smallest body clearance minus the safety distance along
    the returned motion (mm, checked densely; >= 0 means safe). goal_error: final tip to goal (mm);
    goal_angle: final tip tangent to the goal's direction (rad; NaN without a direction goal). tree_edges:
    (E, 2, 3) tip positions of the search tree's edges, for drawing.
    timings (s) and counts describe the run. cost_progress: the best cost each time a planner
    found a better solution, as (s since the plan call began, cost) pairs (OMPL planners; empty otherwise).
    """

    status: PlanStatus
    message: str
    planner: str
    seed: int | None
    t: np.ndarray
    configs: np.ndarray
    tips: np.ndarray
    cables: np.ndarray
    length: float = float("nan")
    cost: float = float("nan")
    min_clearance: float = float("nan")
    goal_error: float = float("nan")
    goal_angle: float = float("nan")  # rad: final tip tangent to a direction goal's direction (NaN: none)
    smoothed: bool = False
    raw_configs: np.ndarray | None = None
    raw_t: np.ndarray | None = None
    goal_configs: np.ndarray | None = None
    tree_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    cost_progress: tuple[tuple[float, float], ...] = ()

    def is_success(self) -> bool:
        """True only for an exact solution (a verified path that reaches the goal)."""
        return self.status is PlanStatus.EXACT

    @property
    def has_path(self) -> bool:
        """True when the result carries a path (exact or approximate)."""
        return len(self.t) >= 1 and self.status in (PlanStatus.EXACT, PlanStatus.APPROXIMATE)

    @property
    def duration(self) -> float:
        """Time the motion takes (s)."""
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    def config_at(self, t: float | np.ndarray) -> np.ndarray:
        """Configuration(s) at time(s) t (s), linear between waypoints, held at the ends."""
        if not len(self.t):
            raise ValueError("config_at: the result has no path")
        tt = np.asarray(t, dtype=float)
        out = np.stack([np.interp(tt, self.t, self.configs[:, j]) for j in range(self.configs.shape[1])], axis=-1)
        return out

    def summary(self) -> dict[str, Any]:
        """Short figures for printing and for the result file."""
        return {
            "status": str(self.status),
            "success": self.is_success(),
            "planner": self.planner,
            "seed": self.seed,
            "waypoints": len(self.t),
            "duration_s": self.duration,
            "length_mm": self.length,
            "cost": self.cost,
            "min_clearance_mm": self.min_clearance,
            "goal_error_mm": self.goal_error,
            "smoothed": self.smoothed,
            "plan_time_s": self.timings.get("total", float("nan")),
            **{f"n_{k}": v for k, v in self.counts.items()},
            # a direction goal's final tip tangent angle (deg), only for a goal with a direction
            **({"goal_angle_deg": float(np.degrees(self.goal_angle))} if np.isfinite(self.goal_angle) else {}),
        }
