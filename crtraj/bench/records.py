"""What the Table I benchmark runs and records: options, one run's record, the paper's figures, labels.

Units mm, s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from crtraj.bench.scenarios import MAX_INDEX
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_SEED, MAX_TIME, Table
from crtraj.core.options import Options, option
from crtraj.planning.planners import BUILTIN
from crtraj.world.scene import MAX_OBSTACLES

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
# Most planners in one benchmark (names are registry entries; duplicates are refused).
MAX_PLANNERS = 64


@dataclass(frozen=True)
class BenchOptions(Options):
    """What to run and how to judge it (units mm, s); the ``[bench]`` section.

    counts: obstacle counts (the table's columns, distinct, each at most
    `MAX_OBSTACLES`). scenarios: scenarios per count. planners: names from
    `PLANNERS` (or registered extras), distinct.
    time_limit: wall-time budget per run (s), the same for every planner.
    seed: seed of the scenarios and of every planner run. goal_tolerance:
    tip-to-goal distance that counts as arrival (mm). verify_points:
    backbone points of the dense check. verify_dt: largest time between dense
    samples (s). verify_step: largest backbone-point motion between dense
    samples (mm). verify_margin: clearance to the sphere surfaces the dense
    check demands (mm; None, the default: the scene's safety distance D_sf, so
    that success means safe; 0 = merely no contact). cpu_budget: time_limit
    counts each run's CPU time rather than wall time (a shared machine's load
    then does not shrink the budget; OMPL's planners time themselves on the
    wall clock either way).
    """

    SECTION: ClassVar[str] = "bench"

    counts: tuple[int, ...] = option(COUNTS, read=False)
    # scenario indices run 0 .. scenarios - 1, and a scenario's index is at most MAX_INDEX
    scenarios: int = option(100, ge=1, le=MAX_INDEX)
    planners: tuple[str, ...] = option(PLANNERS, read=False)
    time_limit: float = option(5.0, gt=0.0, le=MAX_TIME)
    seed: int = option(0, ge=0, le=MAX_SEED)
    goal_tolerance: float = option(1.0, gt=0.0, le=MAX_LENGTH)
    # the dense check holds (samples x verify_points x 3) floats at once: bounded before any run starts
    verify_points: int = option(128, ge=2, le=1000)
    verify_dt: float = option(0.01, gt=0.0, le=MAX_TIME)
    verify_step: float = option(1.0, gt=0.0, le=MAX_LENGTH)
    verify_margin: float | None = option(None, ge=0.0, le=MAX_LENGTH)
    cpu_budget: bool = option(False)

    def _check(self) -> None:
        counts = self.counts
        if not isinstance(counts, (tuple, list)) or not counts or len(counts) > MAX_OBSTACLES + 1:
            raise InputError(f"bench.counts: expected 1 to {MAX_OBSTACLES + 1} obstacle counts, got {counts!r:.60}")
        for c in counts:
            if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c <= MAX_OBSTACLES:
                raise InputError(f"bench.counts: each must be an integer in [0, {MAX_OBSTACLES}], got {c!r:.40}")
        if len(set(counts)) != len(counts):
            raise InputError(f"bench.counts: duplicate obstacle count in {list(counts)}")
        object.__setattr__(self, "counts", tuple(int(c) for c in counts))
        planners = self.planners
        if not isinstance(planners, (tuple, list)) or not planners or len(planners) > MAX_PLANNERS:
            raise InputError(f"bench.planners: expected 1 to {MAX_PLANNERS} planner names, got {planners!r:.60}")
        for p in planners:
            if not isinstance(p, str) or not p or len(p) > 100:
                raise InputError(f"bench.planners: a planner name is 1 to 100 characters, got {p!r:.60}")
        if len(set(planners)) != len(planners):
            raise InputError(f"bench.planners: duplicate planner in {list(planners)}")
        object.__setattr__(self, "planners", tuple(planners))

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, default in (("counts", COUNTS), ("planners", PLANNERS)):
            v = t.raw(key, default)
            if not isinstance(v, (list, tuple)):
                raise t.error(key, f"expected a list, got {v!r:.60}")
            out[key] = tuple(v)
        return out


# ------------------------------------------------------------------ records
@dataclass(frozen=True)
class RunRecord:
    """One planner on one scenario: a row of runs.csv (units s, mm).

    claimed: the planner reported an exact solution. verified: the dense
    check accepted the path. success: both. time_s: the planner's wall time.
    min_clearance_mm: the dense check's body-surface to sphere-surface clearance;
    dsf_clearance_mm: the same beyond the scene's D_sf (>= 0: safe).
    paper_success, paper_clearance_mm: the paper's check (`crtraj.bench.check.paper_check`:
    collision points at 1-s step ends) on the same path; check_mode: the planner's own
    motion check ("strict" or "paper"). first_solution_s: time to the first solution
    (OMPL planners; else the run's time when it succeeded). graph_states: nodes of
    the planner's graph. best_cost: the planner's cost at the end of its budget;
    cost_progress: "t:cost" pairs, ";"-separated, each time the best cost improved.
    cpu_s: CPU time of the worker process during the plan call (s; below time_s when the
    machine is loaded: the planners' budgets are wall time).
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
    check_mode: str = "strict"
    dsf_clearance_mm: float = float("nan")
    paper_success: bool = False
    paper_clearance_mm: float = float("nan")
    first_solution_s: float = float("nan")
    graph_states: int = 0
    best_cost: float = float("nan")
    cost_progress: str = ""
    cpu_s: float = float("nan")

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
