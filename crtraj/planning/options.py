"""Options of the planners, read from a problem file's ``[planner]`` section and its sub-tables.

``[planner]`` holds what every planner shares (the algorithm, the stop condition, motion timing and
path post-processing); ``[planner.ik]`` the safe IK of the start and goal (`IKOptions`),
``[planner.check]`` the state and motion validity (`CheckOptions`), and each planner its own table:
``[planner.cspace]`` (`CSpaceOptions`) and ``[planner.rrt]`` (`RRTOptions`, rrt and rrtstar).
A file that still has one of the old flat keys gets a one-line error saying where it moved
(``planner.ik_seeds: moved to [planner.ik] seeds``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, Table
from crtraj.core.options import Options, option
from crtraj.planning.stop import StopCondition

ALGORITHMS = ("cspace", "rrt", "rrtstar")
# "strict": the continuous body over continuous time (`MotionValidator`); "paper": the paper's
# collision points at the ends of `step`-second steps only (`crtraj.planning.validity._paper_check`).
CHECKS = ("strict", "paper")

# Bounds: the highs keep one planner call within memory and a bounded number of solver calls (each far above
# what the paper's problems use); step sizes have a positive floor so that the number of collision checks and
# waypoints along a motion stays bounded (a 1e-300 mm resolution would never finish).


@dataclass(frozen=True)
class IKOptions(Options):
    """Safe IK of a query's start tip and goal (``[planner.ik]``; units mm, s).

    seeds: random starts of the goal/start IK. goal_configs: stop the IK once this many distinct safe
    goal configurations exist. iterations: damped-Newton iterations of the batch projection before
    the safety-constrained IPOPT NLP takes over. nlp_solves: at most this many NLP solves per IK
    query (the slow, rarely needed stage). push_rounds: rounds of the IK's push-out stage between
    the two (on-target projections that come too close to an obstacle move along the tip
    constraint's null space until they clear it; 0 skips the stage). rescue_starts: before an NLP solve
    from a projection, this many batched starts around it are projected and pushed out, and the safe
    one nearest the seed is taken instead (0: the NLP runs as before). compiled: the batch projection's
    Newton loop runs in the compiled kernel (when the checks have one), each start stopping once on
    target (false: the numpy loop). goal_window: dynamic scenes
    only: half of the IK starts keep clear of everything the obstacles sweep over
    [t0, t0 + goal_window] (s), by projection only (no NLP: often infeasible); the other half, with
    the NLP stage, keep clear at t0.
    """

    SECTION: ClassVar[str] = "planner.ik"

    seeds: int = option(64, ge=1, le=10_000)
    goal_configs: int = option(4, ge=1, le=1000)
    iterations: int = option(15, ge=0, le=10_000)
    nlp_solves: int = option(8, ge=0, le=1000)
    push_rounds: int = option(12, ge=0, le=1000)
    rescue_starts: int = option(32, ge=0, le=10_000)
    compiled: bool = option(True)
    goal_window: float = option(4.0, ge=0.0, le=MAX_TIME)


@dataclass(frozen=True)
class CheckOptions(Options):
    """State and motion validity (``[planner.check]``; units mm, s).

    mode: "strict" (default: the continuous body over continuous time) or "paper" (the paper's
    Table I check: the robot's collision points at the ends of `step`-second steps only; meant for
    rrt and rrtstar, see `crtraj.planning.validity._paper_check`). step: the paper check's time step (s).
    resolution: largest body motion between collision-checked samples (mm). points: backbone
    points per collision check (>= 2). compiled: run the collision checks through the compiled
    kernel (C generated once per robot and cached, `crtraj build`) when a C compiler is available;
    false: the interpreted CasADi path (same results to rounding, several times slower).
    broad_phase: the compiled edge check first drops, per motion, the obstacles too far away to decide
    any of its samples (the same verdicts; false: every obstacle enters every sample, the old path).
    early_exit: where a planner wants the best valid motion of a batch (shortcuts, the goal and via
    connections), the compiled check runs the motions best first and stops at the first certified one
    (the same plans; false: the whole batch is checked, the old path).
    """

    SECTION: ClassVar[str] = "planner.check"

    mode: str = option("strict", choices=CHECKS)
    step: float = option(1.0, ge=1e-3, le=MAX_TIME)
    resolution: float = option(3.0, ge=0.1, le=MAX_LENGTH)
    points: int = option(15, ge=2, le=1000)
    compiled: bool = option(True)
    broad_phase: bool = option(True)
    early_exit: bool = option(True)


@dataclass(frozen=True)
class CSpaceOptions(Options):
    """The configuration-space planner's own settings (``[planner.cspace]``; units mm, s).

    range: longest extension per iteration (mm of body motion). wait_bias: among moving obstacles
    only: probability that a tree extension first waits at its node (a random 0-2 s), and that a
    failed connection to the goal set is retried after waits of 0.25-4 s. via_points: random
    intermediate configurations tried at once as start -> via -> goal before the trees grow (0:
    skip); half of them uniform, half scattered by `via_spread` (mm of body motion, normal per
    metric axis) around the straight motions to the goal configurations.
    """

    SECTION: ClassVar[str] = "planner.cspace"

    range: float = option(150.0, ge=1e-3, le=MAX_LENGTH)
    wait_bias: float = option(0.3, ge=0.0, le=1.0)
    via_points: int = option(32, ge=0, le=10_000)
    via_spread: float = option(100.0, gt=0.0, le=MAX_LENGTH)


@dataclass(frozen=True)
class RRTOptions(Options):
    """The task-space RRT and RRT*'s own settings (``[planner.rrt]``; units mm).

    range: longest tip travel per iteration (mm). rewire_radius: RRT* neighbour radius around a
    new tip (mm; rrtstar only).
    """

    SECTION: ClassVar[str] = "planner.rrt"

    range: float = option(40.0, ge=1e-3, le=MAX_LENGTH)
    rewire_radius: float = option(80.0, gt=0.0, le=MAX_LENGTH)


# The sub-tables' defaults (one immutable object each), the sub-tables by field name, and where each old
# flat key of [planner] went.
DEFAULT_IK, DEFAULT_CHECK, DEFAULT_CSPACE, DEFAULT_RRT = IKOptions(), CheckOptions(), CSpaceOptions(), RRTOptions()
_SUBTABLES: Mapping[str, type[Options]] = {
    "ik": IKOptions,
    "check": CheckOptions,
    "cspace": CSpaceOptions,
    "rrt": RRTOptions,
}
MOVED: Mapping[str, tuple[str, str]] = {
    "ik_seeds": ("ik", "seeds"),
    "goal_configs": ("ik", "goal_configs"),
    "ik_iterations": ("ik", "iterations"),
    "ik_nlp_solves": ("ik", "nlp_solves"),
    "ik_push_rounds": ("ik", "push_rounds"),
    "goal_window": ("ik", "goal_window"),
    "resolution": ("check", "resolution"),
    "check_points": ("check", "points"),
    "compiled": ("check", "compiled"),
    "check": ("check", "mode"),
    "check_step": ("check", "step"),
    "wait_bias": ("cspace", "wait_bias"),
    "via_points": ("cspace", "via_points"),
    "via_spread": ("cspace", "via_spread"),
    "rewire_radius": ("rrt", "rewire_radius"),
}


@dataclass(frozen=True)
class PlannerOptions(Options):
    """Planner settings shared by every planner, and the sub-tables (units mm, s).

    algorithm: "cspace" (safe goal IK + RRT-Connect in configuration space,
    the default), "rrt" or "rrtstar" (the paper's Algorithm 1 over tip
    positions, each step a safety-constrained steer NLP).
    time_limit (s), max_iterations, first_solution: the stop condition
    (`crtraj.planning.stop.StopCondition`); with first_solution false, rrt and
    rrtstar keep growing (rrtstar: improving) the tree until time or
    iterations run out; cspace returns its first path (then shortcuts it).
    goal_bias: probability of sampling the goal.
    max_speed: largest speed of any body point (mm/s); times every motion.
    limit_fraction: fraction of each actuator speed and acceleration limit a plan may use (the
    rest is kept in reserve); `crtraj.planning.pipeline.plan_executable` retimes within it.
    shortcut_rounds: rounds of batched shortcut attempts (each checks
    `shortcut_batch` candidate shortcuts at once).
    smooth: B-spline smoothing of the final path (verified; dropped if unsafe).
    corner: how far from each corner (mm of body motion) the spline starts cutting it.
    waypoint_step: largest body motion between returned waypoints (mm).
    ik, check, cspace, rrt: the sub-tables ``[planner.ik]`` (`IKOptions`), ``[planner.check]``
    (`CheckOptions`), ``[planner.cspace]`` (`CSpaceOptions`) and ``[planner.rrt]`` (`RRTOptions`).
    """

    SECTION: ClassVar[str] = "planner"

    algorithm: str = option("cspace", choices=ALGORITHMS)
    time_limit: float = option(5.0, gt=0.0, le=MAX_TIME)
    max_iterations: int = option(20000, ge=1, le=10_000_000)
    first_solution: bool = option(True)
    goal_bias: float = option(0.1, ge=0.0, le=1.0)
    max_speed: float = option(50.0, ge=1e-3, le=MAX_LENGTH)
    limit_fraction: float = option(0.9, gt=0.0, le=1.0)
    shortcut_rounds: int = option(4, ge=0, le=1000)
    shortcut_batch: int = option(16, ge=1, le=10_000)
    smooth: bool = option(True)
    corner: float = option(40.0, ge=1e-3, le=MAX_LENGTH)
    waypoint_step: float = option(20.0, ge=0.1, le=MAX_LENGTH)
    # the sub-tables' defaults are frozen, shared objects (RUF009 guards against mutable ones)
    ik: IKOptions = option(DEFAULT_IK, read=False)  # noqa: RUF009
    check: CheckOptions = option(DEFAULT_CHECK, read=False)  # noqa: RUF009
    cspace: CSpaceOptions = option(DEFAULT_CSPACE, read=False)  # noqa: RUF009
    rrt: RRTOptions = option(DEFAULT_RRT, read=False)  # noqa: RUF009

    def _check(self) -> None:
        for name, cls in _SUBTABLES.items():
            if not isinstance(getattr(self, name), cls):
                raise InputError(f"planner.{name}: expected {cls.__name__}, got {type(getattr(self, name)).__name__}")

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        # an old flat key gets a pointer to its new place (checked here, before Table.finish would call it
        # unknown); ``check`` was a string and is now the sub-table
        for old, (table, key) in MOVED.items():
            if t.has(old) and not (old == "check" and isinstance(t.raw(old), Mapping)):
                raise InputError(f"planner.{old}: moved to [planner.{table}] {key}")
        if t.has("range"):
            raise InputError("planner.range: moved to [planner.cspace] range and [planner.rrt] range")
        return {name: sub.from_table(t.table(name)) for name, sub in _SUBTABLES.items()}

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the TOML schema, the sub-tables as nested tables."""
        out = super().to_dict()
        for name in _SUBTABLES:
            out[name] = getattr(self, name).to_dict()
        return out

    def with_(self, **changes: Any) -> PlannerOptions:
        """A copy with some fields changed (checked like any other); a sub-table may be given as a
        mapping of its changed keys (``with_(check={"mode": "paper"})``)."""
        for name, cls in _SUBTABLES.items():
            value = changes.get(name)
            if isinstance(value, Mapping):
                unknown = sorted(set(value) - {f.name for f in dataclasses.fields(cls)})
                if unknown:
                    raise InputError(f"{cls.SECTION}.{unknown[0]}: unknown option")
                changes[name] = dataclasses.replace(getattr(self, name), **value)
        return super().with_(**changes)

    @property
    def step(self) -> float:
        """The extension range of the chosen algorithm (mm; body motion for cspace, tip travel for rrt)."""
        return self.cspace.range if self.algorithm == "cspace" else self.rrt.range

    def stop(self) -> StopCondition:
        """The stop condition these options describe."""
        return StopCondition(self.time_limit, self.max_iterations, self.first_solution)
