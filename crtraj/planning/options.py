"""Options of every planner, read from a problem file's ``[planner]`` section."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator

ALGORITHMS = ("cspace", "rrt", "rrtstar")


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
        checks = {
            "time_limit": self.time_limit > 0,
            "max_iterations": self.max_iterations >= 1,
            "goal_bias": 0.0 <= self.goal_bias <= 1.0,
            "wait_bias": 0.0 <= self.wait_bias <= 1.0,
            "range": self.range is None or self.range > 0,
            "rewire_radius": self.rewire_radius > 0,
            "max_speed": self.max_speed > 0,
            "resolution": self.resolution > 0,
            "check_points": self.check_points >= 2,
            "ik_seeds": self.ik_seeds >= 1,
            "goal_configs": self.goal_configs >= 1,
            "ik_iterations": self.ik_iterations >= 0,
            "ik_nlp_solves": self.ik_nlp_solves >= 0,
            "goal_window": self.goal_window >= 0,
            "via_points": self.via_points >= 0,
            "via_spread": self.via_spread > 0,
            "shortcut_rounds": self.shortcut_rounds >= 0,
            "shortcut_batch": self.shortcut_batch >= 1,
            "corner": self.corner > 0,
            "waypoint_step": self.waypoint_step > 0,
        }
        for key, ok in checks.items():
            if not ok:
                raise InputError(f"planner.{key}: out of range, got {getattr(self, key)!r}")

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
            time_limit=t.float("time_limit", d.time_limit, gt=0.0),
            max_iterations=t.int("max_iterations", d.max_iterations, ge=1),
            first_solution=t.bool("first_solution", d.first_solution),
            goal_bias=t.float("goal_bias", d.goal_bias, ge=0.0, le=1.0),
            wait_bias=t.float("wait_bias", d.wait_bias, ge=0.0, le=1.0),
            range=t.float("range", None, gt=0.0),
            rewire_radius=t.float("rewire_radius", d.rewire_radius, gt=0.0),
            max_speed=t.float("max_speed", d.max_speed, gt=0.0),
            resolution=t.float("resolution", d.resolution, gt=0.0),
            check_points=t.int("check_points", d.check_points, ge=2),
            ik_seeds=t.int("ik_seeds", d.ik_seeds, ge=1),
            goal_configs=t.int("goal_configs", d.goal_configs, ge=1),
            ik_iterations=t.int("ik_iterations", d.ik_iterations, ge=0),
            ik_nlp_solves=t.int("ik_nlp_solves", d.ik_nlp_solves, ge=0),
            goal_window=t.float("goal_window", d.goal_window, ge=0.0),
            via_points=t.int("via_points", d.via_points, ge=0),
            via_spread=t.float("via_spread", d.via_spread, gt=0.0),
            shortcut_rounds=t.int("shortcut_rounds", d.shortcut_rounds, ge=0),
            shortcut_batch=t.int("shortcut_batch", d.shortcut_batch, ge=1),
            smooth=t.bool("smooth", d.smooth),
            corner=t.float("corner", d.corner, gt=0.0),
            waypoint_step=t.float("waypoint_step", d.waypoint_step, gt=0.0),
        )
        t.finish()
        return opts

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if d["range"] is None:
            d.pop("range")
        return d
