"""Options of every planner, read from a problem file's ``[planner]`` section."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, Table
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator

ALGORITHMS = ("cspace", "rrt", "rrtstar")

# Bounds of every integer option: [low, high]. The highs keep one planner call
# within memory and a bounded number of solver calls; each is far above what
# the paper's problems use (the defaults).
_INT_BOUNDS: Mapping[str, tuple[int, int]] = MappingProxyType(
    {
        "max_iterations": (1, 10_000_000),
        "check_points": (2, 1000),
        "ik_seeds": (1, 10_000),
        "goal_configs": (1, 1000),
        "ik_iterations": (0, 10_000),
        "ik_nlp_solves": (0, 1000),
        "via_points": (0, 10_000),
        "shortcut_rounds": (0, 1000),
        "shortcut_batch": (1, 10_000),
    }
)
# Bounds of every float option: (low, high, low excluded). Step sizes have a
# positive floor so that the number of collision checks and waypoints along
# a motion stays bounded (a 1e-300 mm resolution would never finish).
_FLOAT_BOUNDS: Mapping[str, tuple[float, float, bool]] = MappingProxyType(
    {
        "time_limit": (0.0, MAX_TIME, True),
        "goal_bias": (0.0, 1.0, False),
        "wait_bias": (0.0, 1.0, False),
        "range": (1e-3, MAX_LENGTH, False),
        "rewire_radius": (0.0, MAX_LENGTH, True),
        "max_speed": (1e-3, MAX_LENGTH, False),
        "resolution": (0.1, MAX_LENGTH, False),
        "goal_window": (0.0, MAX_TIME, False),
        "via_spread": (0.0, MAX_LENGTH, True),
        "corner": (1e-3, MAX_LENGTH, False),
        "waypoint_step": (0.1, MAX_LENGTH, False),
    }
)


@dataclass(frozen=True)
class PlannerOptions:
    """Planner settings (units mm, s). Defaults suit the paper's two-segment robot.

    algorithm: "cspace" (safe goal IK + RRT-Connect in configuration space,
    the default), "rrt" or "rrtstar" (the paper's Algorithm 1 over tip
    positions, each step a safety-constrained steer NLP).
    time_limit (s), max_iterations, first_solution: the stop condition
    (`crtraj.planning.stop.StopCondition`); with first_solution false, rrt and
    rrtstar keep growing (rrtstar: improving) the tree until time or
    iterations run out; cspace returns its first path (then shortcuts it).
    goal_bias: probability of sampling the goal. wait_bias: cspace among
    moving obstacles only: probability that a tree extension first waits at
    its node (a random 0-2 s), and that a failed connection to the goal set
    is retried after waits of 0.25-4 s. range: longest extension
    per iteration (mm; body motion for cspace, tip travel for rrt/rrtstar;
    None: 150 for cspace, 40 for rrt/rrtstar). rewire_radius: RRT* neighbour
    radius around a new tip (mm).
    max_speed: largest speed of any body point (mm/s); times every motion.
    resolution: largest body motion between collision-checked samples (mm).
    check_points: backbone points per collision check (>= 2).
    ik_seeds: random starts of the goal/start IK. goal_configs: stop the IK
    once this many distinct safe goal configurations exist.
    ik_iterations: damped-Newton iterations of the batch projection before
    the safety-constrained IPOPT NLP takes over. ik_nlp_solves: at most
    this many NLP solves per IK query (the slow, rarely needed stage).
    goal_window: dynamic scenes only: half of the IK starts keep clear of
    everything the obstacles sweep over [t0, t0 + goal_window] (s), by
    projection only (no NLP: often infeasible); the other half, with the NLP
    stage, keep clear at t0.
    via_points: cspace only: random intermediate configurations tried at
    once as start -> via -> goal before the trees grow (0: skip); half of
    them uniform, half scattered by `via_spread` (mm of body motion, normal
    per metric axis) around the straight motions to the goal configurations.
    shortcut_rounds: rounds of batched shortcut attempts (each checks
    `shortcut_batch` candidate shortcuts at once).
    smooth: B-spline smoothing of the final path (verified; dropped if unsafe).
    corner: how far from each corner (mm of body motion) the spline starts cutting it.
    waypoint_step: largest body motion between returned waypoints (mm).
    """

    algorithm: str = "cspace"
    time_limit: float = 5.0
    max_iterations: int = 20000
    first_solution: bool = True
    goal_bias: float = 0.1
    wait_bias: float = 0.3
    range: float | None = None
    rewire_radius: float = 80.0
    max_speed: float = 50.0
    resolution: float = 3.0
    check_points: int = 15
    ik_seeds: int = 64
    goal_configs: int = 4
    ik_iterations: int = 15
    ik_nlp_solves: int = 8
    goal_window: float = 4.0
    via_points: int = 32
    via_spread: float = 100.0
    shortcut_rounds: int = 4
    shortcut_batch: int = 16
    smooth: bool = True
    corner: float = 40.0
    waypoint_step: float = 20.0

    def __post_init__(self) -> None:
        if self.algorithm not in ALGORITHMS:
            raise InputError(f"planner.algorithm: must be one of {', '.join(ALGORITHMS)}; got {self.algorithm!r}")
        for key, (lo, hi) in _INT_BOUNDS.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise InputError(f"planner.{key}: must be an integer in [{lo}, {hi}], got {v!r}")
        for key, (lo, hi, lo_open) in _FLOAT_BOUNDS.items():
            v = getattr(self, key)
            if v is None and key == "range":
                continue
            ok = (
                isinstance(v, (int, float, np.integer))
                and not isinstance(v, bool)
                and (v > lo if lo_open else v >= lo)
                and v <= hi
            )
            if not ok:
                bracket = "(" if lo_open else "["
                raise InputError(f"planner.{key}: must be a number in {bracket}{lo:g}, {hi:g}], got {v!r}")

    @property
    def step(self) -> float:
        """The extension range in effect (mm)."""
        if self.range is not None:
            return self.range
        return 150.0 if self.algorithm == "cspace" else 40.0

    def stop(self) -> StopCondition:
        """The stop condition these options describe."""
        return StopCondition(self.time_limit, self.max_iterations, self.first_solution)

    def validator(self, model: Any, scene: Any, functions: dict[Any, Any] | None = None) -> MotionValidator:
        """The `MotionValidator` these options describe for `scene` (functions: a shared CasADi cache)."""
        return MotionValidator(
            model,
            scene,
            check_points=self.check_points,
            resolution=self.resolution,
            max_speed=self.max_speed,
            functions=functions,
        )

    def with_(self, **changes: Any) -> PlannerOptions:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)

    @classmethod
    def from_table(cls, t: Table) -> PlannerOptions:
        """Read ``[planner]``; every key is optional (see the class docstring)."""
        d = cls()
        opts = cls(
            algorithm=t.str("algorithm", d.algorithm, choices=ALGORITHMS),
            time_limit=_float(t, "time_limit", d.time_limit),
            max_iterations=_int(t, "max_iterations", d.max_iterations),
            first_solution=t.bool("first_solution", d.first_solution),
            goal_bias=_float(t, "goal_bias", d.goal_bias),
            wait_bias=_float(t, "wait_bias", d.wait_bias),
            range=_float(t, "range", None),
            rewire_radius=_float(t, "rewire_radius", d.rewire_radius),
            max_speed=_float(t, "max_speed", d.max_speed),
            resolution=_float(t, "resolution", d.resolution),
            check_points=_int(t, "check_points", d.check_points),
            ik_seeds=_int(t, "ik_seeds", d.ik_seeds),
            goal_configs=_int(t, "goal_configs", d.goal_configs),
            ik_iterations=_int(t, "ik_iterations", d.ik_iterations),
            ik_nlp_solves=_int(t, "ik_nlp_solves", d.ik_nlp_solves),
            goal_window=_float(t, "goal_window", d.goal_window),
            via_points=_int(t, "via_points", d.via_points),
            via_spread=_float(t, "via_spread", d.via_spread),
            shortcut_rounds=_int(t, "shortcut_rounds", d.shortcut_rounds),
            shortcut_batch=_int(t, "shortcut_batch", d.shortcut_batch),
            smooth=t.bool("smooth", d.smooth),
            corner=_float(t, "corner", d.corner),
            waypoint_step=_float(t, "waypoint_step", d.waypoint_step),
        )
        t.finish()
        return opts

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["range"] is None:
            d.pop("range")
        return d


def _float(t: Table, key: str, default: float | None) -> float:
    """Read float option `key` with its `_FLOAT_BOUNDS`."""
    lo, hi, lo_open = _FLOAT_BOUNDS[key]
    if lo_open:
        return t.float(key, default, gt=lo, le=hi)
    return t.float(key, default, ge=lo, le=hi)


def _int(t: Table, key: str, default: int) -> int:
    """Read integer option `key` with its `_INT_BOUNDS`."""
    lo, hi = _INT_BOUNDS[key]
    return t.int(key, default, ge=lo, le=hi)
