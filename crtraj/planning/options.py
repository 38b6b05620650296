"""Options of every planner, read from a problem file's ``[planner]`` section."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from crtraj.core.fields import MAX_LENGTH, MAX_TIME
from crtraj.core.options import Options, option
from crtraj.planning.stop import StopCondition

ALGORITHMS = ("cspace", "rrt", "rrtstar")
# "strict": the continuous body over continuous time (`MotionValidator`); "paper": the paper's
# collision points at the ends of `check_step`-second steps only (`crtraj.planning.paper_check`).
CHECKS = ("strict", "paper")

# Bounds: the highs keep one planner call within memory and a bounded number of solver calls (each far above
# what the paper's problems use); step sizes have a positive floor so that the number of collision checks and
# waypoints along a motion stays bounded (a 1e-300 mm resolution would never finish).


@dataclass(frozen=True)
class PlannerOptions(Options):
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
    ik_push_rounds: rounds of the IK's push-out stage between the two
    (on-target projections that come too close to an obstacle move along the
    tip constraint's null space until they clear it; 0 skips the stage).
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
    limit_fraction: fraction of each actuator speed and acceleration limit a plan may use (the
    rest is kept in reserve); `crtraj plan` retimes its result within it.
    compiled: run the collision checks through the compiled kernel (C generated once per robot and
    cached, `crtraj build`) when a C compiler is available; false: the interpreted CasADi path (same
    results to rounding, several times slower).
    check: the motion check, "strict" (default) or "paper" (the paper's Table I check: the robot's
    collision points at the ends of `check_step`-second steps only; meant for rrt and rrtstar, see
    `crtraj.planning.paper_check`). check_step: the paper check's time step (s).
    """

    SECTION: ClassVar[str] = "planner"

    algorithm: str = option("cspace", choices=ALGORITHMS)
    time_limit: float = option(5.0, gt=0.0, le=MAX_TIME)
    max_iterations: int = option(20000, ge=1, le=10_000_000)
    first_solution: bool = option(True)
    goal_bias: float = option(0.1, ge=0.0, le=1.0)
    wait_bias: float = option(0.3, ge=0.0, le=1.0)
    range: float | None = option(None, ge=1e-3, le=MAX_LENGTH)
    rewire_radius: float = option(80.0, gt=0.0, le=MAX_LENGTH)
    max_speed: float = option(50.0, ge=1e-3, le=MAX_LENGTH)
    resolution: float = option(3.0, ge=0.1, le=MAX_LENGTH)
    check_points: int = option(15, ge=2, le=1000)
    ik_seeds: int = option(64, ge=1, le=10_000)
    goal_configs: int = option(4, ge=1, le=1000)
    ik_iterations: int = option(15, ge=0, le=10_000)
    ik_nlp_solves: int = option(8, ge=0, le=1000)
    ik_push_rounds: int = option(12, ge=0, le=1000)
    goal_window: float = option(4.0, ge=0.0, le=MAX_TIME)
    via_points: int = option(32, ge=0, le=10_000)
    via_spread: float = option(100.0, gt=0.0, le=MAX_LENGTH)
    shortcut_rounds: int = option(4, ge=0, le=1000)
    shortcut_batch: int = option(16, ge=1, le=10_000)
    smooth: bool = option(True)
    corner: float = option(40.0, ge=1e-3, le=MAX_LENGTH)
    waypoint_step: float = option(20.0, ge=0.1, le=MAX_LENGTH)
    limit_fraction: float = option(0.9, gt=0.0, le=1.0)
    compiled: bool = option(True)
    check: str = option("strict", choices=CHECKS)
    check_step: float = option(1.0, ge=1e-3, le=MAX_TIME)

    @property
    def step(self) -> float:
        """The extension range in effect (mm)."""
        if self.range is not None:
            return self.range
        return 150.0 if self.algorithm == "cspace" else 40.0

    def stop(self) -> StopCondition:
        """The stop condition these options describe."""
        return StopCondition(self.time_limit, self.max_iterations, self.first_solution)
