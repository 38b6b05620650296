"""Planners by name: one factory per name, so callers (the CLI, the loop, the bench) never branch on types.

    context = PlanningContext.build(model, scene, options)
    planner = BUILTIN.create("cspace", context)
    result = planner.plan(goal, start_config=x0, stop=StopCondition(time_limit=1.0))

Names: ``cspace``, ``rrt``, ``rrtstar`` (crtraj's planners; also the values
of ``[planner] algorithm``) and ``ompl-rrtstar``, ``ompl-rrtconnect`` (OMPL
in the same configuration space). Every factory builds its planner from a
`PlanningContext` and takes, by keyword, only the other build inputs it uses (`BUILD_INPUTS`: the
``[steer]`` options, the NLPs' obstacle slots): `PlannerRegistry.create` passes a factory the ones its
signature names. OMPL is an optional extra: its module is
importable without it and imports ``ompl`` only when such a planner is built
(`crtraj.planning.planners.import_ompl`), so the OMPL entries cost nothing until
used. A `PlannerRegistry` is immutable; `with_planner` returns an extended
copy (the bench adds its extra planners that way). Factories must be
module-level callables so that registries pickle to worker processes.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.base import Planner
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners._cspace import CSpacePlanner
from crtraj.planning.planners._ompl import OMPLPlanner, import_ompl
from crtraj.planning.planners._rrt import RRT, RRTStar
from crtraj.planning.steer import SteerOptions

# (context, **the build inputs it names) -> Planner
PlannerFactory = Callable[..., Planner]
# What a factory may take besides the context, by keyword: the task-space planners' [steer] options, and the
# obstacle slots of its NLPs (None: the scene's count)
BUILD_INPUTS = ("steer_options", "max_obstacles")


@dataclass(frozen=True)
class PlannerSpec:
    """One registered planner.

    name: its registry name. factory: builds it from the context and, by keyword, the `BUILD_INPUTS`
    its signature names (see `PlannerFactory`).
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

    def __post_init__(self) -> None:
        unknown = sorted(set(self.inputs()) - set(BUILD_INPUTS))
        if unknown:
            raise InputError(f"planners: {self.name}'s factory takes {unknown}; a factory may take {BUILD_INPUTS}")

    def inputs(self) -> tuple[str, ...]:
        """The names of the build inputs the factory takes besides the context (its keyword parameters)."""
        params = list(inspect.signature(self.factory).parameters.values())[1:]
        return tuple(p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD))

    def build(self, context: PlanningContext, **inputs: Any) -> Planner:
        """The planner from `context` and, of `inputs` (`BUILD_INPUTS` by name), those the factory takes."""
        return self.factory(context, **{k: inputs[k] for k in self.inputs()})


def _for_algorithm(context: PlanningContext, algorithm: str) -> PlanningContext:
    """`context` with ``options.algorithm`` set to `algorithm` (the same context when it already is)."""
    if context.options.algorithm == algorithm:
        return context
    return context.with_options(context.options.with_(algorithm=algorithm))


def _cspace(context: PlanningContext, *, max_obstacles: int | None = None) -> Planner:
    # the configuration-space planner has no steer step
    return CSpacePlanner(_for_algorithm(context, "cspace"), max_obstacles=max_obstacles)


def _task_space(
    algorithm: str,
    context: PlanningContext,
    *,
    steer_options: SteerOptions | None = None,
    max_obstacles: int | None = None,
) -> Planner:
    # task-space edges keep full-speed timing; a static result is retimed afterwards (`plan_executable`)
    ctx = _for_algorithm(context, algorithm).without_rate_limits()
    cls = RRTStar if algorithm == "rrtstar" else RRT
    return cls(ctx, steer_options, max_obstacles=max_obstacles)


def _ompl(algorithm: str, context: PlanningContext) -> Planner:
    # OMPL plans with the validator only (no steer step); its IK grows its own obstacle slots
    return OMPLPlanner(context.without_rate_limits(), algorithm=algorithm)


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

    def create(
        self,
        name: str,
        context: PlanningContext,
        steer_options: SteerOptions | None = None,
        *,
        max_obstacles: int | None = None,
    ) -> Planner:
        """Build the planner called `name` from `context` (steer_options: the task-space planners'
        ``[steer]`` settings; max_obstacles: obstacle slots of its NLPs, default the scene's count)."""
        return self.spec(name).build(context, steer_options=steer_options, max_obstacles=max_obstacles)

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
        """`create` with a context of `model` among `scene` (options: shared settings; rate_limits: the
        actuators' limits, within which the c-space planner times its edges; None: max_speed only)."""
        context = PlanningContext(model, scene, options, rate_limits)
        return self.create(name, context, steer_options, max_obstacles=max_obstacles)


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
"""The built-in planners by name: ``rrt`` and ``rrtstar`` (the paper's Alg. 1 over tip positions), ``cspace``
(the default) and, with OMPL installed, ``ompl-rrtstar`` and ``ompl-rrtconnect``; ``BUILTIN.create(name, context)``."""


def make_planner(
    model: Model,
    scene: Any,
    options: PlannerOptions | None = None,
    steer_options: SteerOptions | None = None,
    *,
    max_obstacles: int | None = None,
    rate_limits: RateLimits | None = None,
) -> Planner:
    """The planner `options.algorithm` names (``[planner] algorithm``), from `BUILTIN` (a `PlanningContext`
    of `model` among `scene` with these options and rate limits; `BUILTIN.create` takes a context)."""
    o = PlannerOptions() if options is None else options
    return BUILTIN.build(
        o.algorithm, model, scene, o, steer_options, max_obstacles=max_obstacles, rate_limits=rate_limits
    )
