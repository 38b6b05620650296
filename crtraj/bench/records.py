"""What the Table I benchmark runs and records: options, one run's record, the paper's figures, labels.

Units mm, s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.planning.registry import BUILTIN

PLANNERS = BUILTIN.names
COUNTS = (1, 3, 5, 7)

# Table labels: the registry's one-line descriptions.
LABELS: Mapping[str, str] = MappingProxyType({s.name: s.description for s in BUILTIN.specs})

# The paper's Table I (Luo et al., arXiv 2309.13813), i7-12700H laptop, Python.
PAPER_TABLE1: Mapping[str, dict[str, tuple[float, ...]]] = MappingProxyType(
    {
        "rrt": {
            "time_s": (3.05, 4.77, 5.55, 6.36),
            "success": (0.99, 0.97, 0.95, 0.90),
            "path_mm": (715.36, 736.11, 785.46, 743.36),
        },
        "rrtstar": {
            "time_s": (3.66, 4.82, 6.07, 7.30),
            "success": (0.99, 0.89, 0.78, 0.65),
            "path_mm": (609.07, 626.70, 625.46, 597.45),
        },
    }
)
PAPER_COUNTS = (1, 3, 5, 7)


# --------------------------------------------------------------------- options
@dataclass(frozen=True)
class BenchOptions:
    """What to run and how to judge it (units mm, s).

    counts: obstacle counts (the table's columns). scenarios: scenarios per
    count. planners: names from `PLANNERS` (or registered extras).
    time_limit: wall-time budget per run (s), the same for every planner.
    seed: seed of the scenarios and of every planner run. goal_tolerance:
    tip-to-goal distance that counts as arrival (mm). verify_points:
    backbone points of the dense check. verify_dt: largest time between dense
    samples (s). verify_step: largest backbone-point motion between dense
    samples (mm). verify_margin: clearance to the sphere surfaces the dense
    check demands (mm; 0 = no contact; the planners themselves keep the
    scene's safety distance).
    """

    counts: tuple[int, ...] = COUNTS
    scenarios: int = 100
    planners: tuple[str, ...] = PLANNERS
    time_limit: float = 5.0
    seed: int = 0
    goal_tolerance: float = 1.0
    verify_points: int = 128
    verify_dt: float = 0.01
    verify_step: float = 1.0
    verify_margin: float = 0.0

    def __post_init__(self) -> None:
        counts = tuple(self.counts)
        if not counts or any(isinstance(c, bool) or not isinstance(c, (int, np.integer)) or c < 0 for c in counts):
            raise InputError(f"counts: expected obstacle counts >= 0, got {list(counts)!r}")
        if len(set(counts)) != len(counts):
            raise InputError(f"counts: duplicate obstacle count in {list(counts)}")
        object.__setattr__(self, "counts", tuple(int(c) for c in counts))
        if isinstance(self.scenarios, bool) or not isinstance(self.scenarios, int) or self.scenarios < 1:
            raise InputError(f"scenarios: must be an integer >= 1, got {self.scenarios!r}")
        planners = tuple(self.planners)
        if not planners:
            raise InputError("planners: at least one planner is required")
        if len(set(planners)) != len(planners):
            raise InputError(f"planners: duplicate planner in {list(planners)}")
        object.__setattr__(self, "planners", planners)
        if not (math.isfinite(self.time_limit) and self.time_limit > 0):
            raise InputError(f"time_limit: must be a finite number > 0 (s), got {self.time_limit!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise InputError(f"seed: must be an integer >= 0, got {self.seed!r}")
        if not (math.isfinite(self.goal_tolerance) and self.goal_tolerance > 0):
            raise InputError(f"goal_tolerance: must be > 0 mm, got {self.goal_tolerance!r}")
        if isinstance(self.verify_points, bool) or not isinstance(self.verify_points, int) or self.verify_points < 2:
            raise InputError(f"verify_points: must be an integer >= 2, got {self.verify_points!r}")
        for key in ("verify_dt", "verify_step"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"{key}: must be a finite number > 0, got {v!r}")
        if not (math.isfinite(self.verify_margin) and self.verify_margin >= 0):
            raise InputError(f"verify_margin: must be >= 0 mm, got {self.verify_margin!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["counts"] = list(self.counts)
        d["planners"] = list(self.planners)
        return d


# ------------------------------------------------------------------ records
@dataclass(frozen=True)
class RunRecord:
    """One planner on one scenario: a row of runs.csv (units s, mm).

    claimed: the planner reported an exact solution. verified: the dense
    check accepted the path. success: both. time_s: the planner's wall time.
    """

    planner: str
    n_obstacles: int
    index: int
    seed: int
    status: str
    claimed: bool
    verified: bool
    success: bool
    time_s: float
    length_mm: float
    min_clearance_mm: float
    goal_error_mm: float
    duration_s: float
    waypoints: int
    worker: str
    message: str
    check: str

    @classmethod
    def fields(cls) -> list[str]:
        return list(cls.__dataclass_fields__)

    def is_success(self) -> bool:
        """Claimed by the planner and verified by the dense check."""
        return self.success


# ------------------------------------------------------------------ report
def _fmt(v: float, digits: int = 2) -> str:
    return "—" if not math.isfinite(v) else f"{v:.{digits}f}"


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{100.0 * v:.0f}%"
