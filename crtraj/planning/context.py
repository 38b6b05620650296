"""The planning context: everything a planner is built from, in one typed object.

A `PlanningContext` holds the robot's `Model`, the default scene, the planner options, the state and
motion validity of that scene, the actuators' rate limits and the compiled kernels (`Kernels`, with
the build cache). Every planner of the registry, OMPL's included, is built from one::

    context = PlanningContext.build(model, scene, options)   # rate limits from the robot file
    planner = BUILTIN.create("cspace", context)

Validators of other scenes (`motion_validity`) share the context's kernels, so a planner that
answers queries among many scenes compiles and builds its functions once.
"""

from __future__ import annotations

from typing import Any

from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.planning.options import PlannerOptions
from crtraj.planning.validity import Kernels, MotionValidator, PaperValidator, StateValidityChecker
from crtraj.world.scene import Scene


class PlanningContext:
    """Model, scene, options, validity, rate limits and kernels of one planner (module docstring).

    model: the robot's `Model`. scene: the default `Scene` (a query may pass another). options:
    `PlannerOptions`. rate_limits: the actuators' full speed and acceleration limits (None: motions
    are timed by `options.max_speed` only); `options.limit_fraction` of them is used. kernels: the
    compiled kernels and CasADi functions (None: new ones; a test injects a `Kernels` with its own
    build cache here).
    """

    def __init__(
        self,
        model: Model,
        scene: Any = None,
        options: PlannerOptions | None = None,
        rate_limits: RateLimits | None = None,
        kernels: Kernels | None = None,
    ) -> None:
        self.model = model
        self.scene = Scene() if scene is None else scene
        self.options = PlannerOptions() if options is None else options
        self.rate_limits = rate_limits
        self.kernels = Kernels() if kernels is None else kernels
        self.validator = self.motion_validity(self.scene)

    @classmethod
    def build(
        cls, model: Model, scene: Any = None, options: PlannerOptions | None = None, *, kernels: Kernels | None = None
    ) -> PlanningContext:
        """The context of `model` among `scene`, with the rate limits of the robot's ``[robot.actuators]``
        (none when the robot file has no actuators)."""
        return cls(model, scene, options, model.robot.rate_limits(), kernels)

    @property
    def robot(self) -> Any:
        """The robot description (`crtraj.model.robot.Robot`)."""
        return self.model.robot

    @property
    def state(self) -> StateValidityChecker:
        """State validity of the default scene."""
        return self.validator.state

    @property
    def usable_limits(self) -> RateLimits | None:
        """The part of the rate limits a plan may use (`options.limit_fraction` of them), or None."""
        if self.rate_limits is None:
            return None
        return self.rate_limits.scaled(self.options.limit_fraction)

    def motion_validity(self, scene: Any) -> MotionValidator:
        """The motion validator the options describe for `scene` (``[planner.check] mode``: "strict", the
        continuous body over continuous time, or "paper"), sharing this context's kernels."""
        o, check = self.options, self.options.check
        common: dict[str, Any] = {
            "resolution": check.resolution,
            "max_speed": o.max_speed,
            "kernels": self.kernels,
            "rate_limits": self.usable_limits,
        }
        if check.mode == "paper":
            points = self.model.robot.collision_points
            return PaperValidator(self.model, scene, step=check.step, check_points=points, **common)
        return MotionValidator(
            self.model,
            scene,
            check_points=check.points,
            compiled=check.compiled,
            broad_phase=check.broad_phase,
            early_exit=check.early_exit,
            **common,
        )

    def validity_for(self, scene: Any) -> MotionValidator:
        """The default scene's validator when `scene` is None or the default scene, else a new one."""
        if scene is None or scene is self.scene:
            return self.validator
        return self.motion_validity(scene)

    def with_options(self, options: PlannerOptions) -> PlanningContext:
        """The same model, scene, rate limits and kernels with other options."""
        return PlanningContext(self.model, self.scene, options, self.rate_limits, self.kernels)

    def without_rate_limits(self) -> PlanningContext:
        """The same context with motions timed by the options' max_speed only (task-space planners)."""
        if self.rate_limits is None:
            return self
        return PlanningContext(self.model, self.scene, self.options, None, self.kernels)
