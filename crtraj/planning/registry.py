"""Planners by name: one factory per name, so callers (the CLI, the loop, the bench) never branch on types.

    planner = BUILTIN.build("cspace", model, scene, options)
    result = planner.plan(goal, start_config=x0, stop=StopCondition(time_limit=1.0))

Names: ``cspace``, ``rrt``, ``rrtstar`` (crtraj's planners; also the values
of ``[planner] algorithm``) and ``ompl-rrtstar``, ``ompl-rrtconnect`` (OMPL
in the same configuration space). OMPL is an optional extra: its module is
importable without it and imports ``ompl`` only when such a planner is built
(`crtraj.planning.ompl.import_ompl`), so the OMPL entries cost nothing until
used. A `PlannerRegistry` is immutable; `with_planner` returns an extended
copy (the bench adds its extra planners that way). Factories must be
module-level callables so that registries pickle to worker processes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.planning.base import Planner
from crtraj.planning.cspace import CSpacePlanner
from crtraj.planning.ompl import OMPLPlanner, import_ompl
from crtraj.planning.options import PlannerOptions
from crtraj.planning.rate_limits import RateLimits
from crtraj.planning.rrt import RRT, RRTStar
from crtraj.planning.steer import SteerOptions

# (model, scene, options, steer_options, max_obstacles) -> Planner
PlannerFactory = Callable[[Model, Any, PlannerOptions, "SteerOptions | None", "int | None"], Planner]


@dataclass(frozen=True)
class PlannerSpec:
    """One registered planner.

    name: its registry name. factory: builds it (see `PlannerFactory`).
    budget_only: a benchmark stops it on its time budget alone, without the
    options' iteration limit and first-solution stop (OMPL: no iteration
    limit through its Python API, and its anytime planners use the whole
    budget, as OMPL's own benchmarks run them). optional: the extra
    package it needs (None: always available). description: one line.
    """

    name: str
    factory: PlannerFactory
    budget_only: bool = False
    optional: str | None = None
    description: str = ""


def _cspace(
    model: Model,
    scene: Any,
    options: PlannerOptions,
    steer: SteerOptions | None,
    max_obstacles: int | None,
    rate_limits: RateLimits | None = None,
) -> Planner:
    del steer  # the configuration-space planner has no steer step
    o = options.with_(algorithm="cspace")
    return CSpacePlanner(model, scene, o, max_obstacles=max_obstacles, rate_limits=rate_limits)


def _task_space(
    algorithm: str,
    model: Model,
    scene: Any,
    options: PlannerOptions,
    steer: SteerOptions | None,
    max_obstacles: int | None,
    rate_limits: RateLimits | None = None,
) -> Planner:
    del rate_limits  # task-space edges keep full-speed timing; static results are retimed afterwards
    cls = RRTStar if algorithm == "rrtstar" else RRT
    return cls(model, scene, options.with_(algorithm=algorithm), steer, max_obstacles=max_obstacles)


def _ompl(
    algorithm: str,
    model: Model,
    scene: Any,
    options: PlannerOptions,
    steer: SteerOptions | None,
    max_obstacles: int | None,
    rate_limits: RateLimits | None = None,
) -> Planner:
    del steer, max_obstacles, rate_limits  # OMPL plans with the validator only; its IK grows its own slots
    return OMPLPlanner(model, scene, options, algorithm=algorithm)


@dataclass(frozen=True)
class PlannerRegistry:
    """An immutable table of planners by name (see the module docstring)."""

    specs: tuple[PlannerSpec, ...]

    def __post_init__(self) -> None:
        names = [s.name for s in self.specs]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"planners: registered twice: {', '.join(dup)}")

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    def spec(self, name: str) -> PlannerSpec:
        """The entry called `name`, or an `InputError` listing the known names."""
        for s in self.specs:
            if s.name == name:
                return s
        raise InputError(f"planners: unknown planner {name!r}; choose from {', '.join(self.names)}")

    def with_planner(self, spec: PlannerSpec) -> PlannerRegistry:
        """A copy with `spec` added (replacing an entry of the same name)."""
        return PlannerRegistry((*(s for s in self.specs if s.name != spec.name), spec))

    def check_available(self, name: str) -> None:
        """Raise a one-line `InputError` when `name` is unknown or its optional extra is missing."""
        spec = self.spec(name)
        if spec.optional == "ompl":
            import_ompl()

    def build(
        self,
        name: str,
        model: Model,
        scene: Any,
        options: PlannerOptions | None = None,
        steer_options: SteerOptions | None = None,
        *,
        max_obstacles: int | None = None,
        rate_limits: RateLimits | None = None,
    ) -> Planner:
        """Build the planner called `name` for `model` among `scene` (options: shared settings;
        rate_limits: the actuators' limits, passed to the factory only when given (the c-space
        planner times its edges within them))."""
        spec = self.spec(name)
        opts = PlannerOptions() if options is None else options
        if rate_limits is None:
            return spec.factory(model, scene, opts, steer_options, max_obstacles)
        return spec.factory(model, scene, opts, steer_options, max_obstacles, rate_limits=rate_limits)  # type: ignore[call-arg]


BUILTIN = PlannerRegistry(
    (
        PlannerSpec("rrt", partial(_task_space, "rrt"), description="RRT (Alg. 1)"),
        PlannerSpec("rrtstar", partial(_task_space, "rrtstar"), description="RRT* (Alg. 1)"),
        PlannerSpec("cspace", _cspace, description="C-space (default)"),
        PlannerSpec(
            "ompl-rrtstar", partial(_ompl, "RRTstar"), budget_only=True, optional="ompl", description="OMPL RRTstar"
        ),
        PlannerSpec(
            "ompl-rrtconnect",
            partial(_ompl, "RRTConnect"),
            budget_only=True,
            optional="ompl",
            description="OMPL RRTConnect",
        ),
    )
)


def make_planner(
    model: Model,
    scene: Any,
    options: PlannerOptions | None = None,
    steer_options: SteerOptions | None = None,
    *,
    max_obstacles: int | None = None,
    rate_limits: RateLimits | None = None,
) -> Planner:
    """The planner `options.algorithm` names (``[planner] algorithm``), from `BUILTIN`."""
    o = PlannerOptions() if options is None else options
    return BUILTIN.build(
        o.algorithm, model, scene, o, steer_options, max_obstacles=max_obstacles, rate_limits=rate_limits
    )
