"""The closed loop's checks against the obstacles of the current step: dense verification of a motion,
the sampled clearance it records, and whether the reference path ahead is clear. Units: mm, s."""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._run_record import REPORT_POINTS
from crtraj.model.kinematics import Model
from crtraj.planning.validity import Kernels, MotionValidator, held_clearance


class SceneChecks:
    """Checks against one obstacle snapshot (`use` switches it); the CasADi functions are shared by every
    snapshot's validator (built once).

    model: the robot's `Model`. scene: the `crtraj.world.scene.Scene` checked first. loop_options: the
    verification's samples (check_points, check_resolution).
    """

    def __init__(self, model: Model, scene: Any, loop_options: LoopOptions) -> None:
        self.model = model
        self.loop_options = loop_options
        self.kernels = Kernels()  # CasADi functions and compiled kernels shared by every step's validator
        self.validator = self._validator(scene)
        self.scene_now = scene

    def _validator(self, scene: Any) -> MotionValidator:
        lo = self.loop_options
        return MotionValidator(
            self.model, scene, check_points=lo.check_points, resolution=lo.check_resolution, kernels=self.kernels
        )

    def compiled_build(self) -> tuple[Any, np.ndarray] | None:
        """What a compiled step simulation is built with: (the kernels' build cache, the configuration metric
        matrix), or None when the checks run interpreted (no C compiler, tip mode)."""
        if not self.validator.runs_compiled():
            return None
        return self.kernels.build_cache, self.validator.metric_matrix

    def motion_bound(self, dx: np.ndarray) -> np.ndarray:
        """Body-motion bound (mm) of configuration changes dx (..., nx)."""
        return self.validator.motion_bound(dx)

    def metric(self, x: np.ndarray) -> np.ndarray:
        """The body metric's coordinates y = M x (mm) of configurations x (..., nx)."""
        return self.validator.metric(x)

    def use(self, scene: Any) -> None:
        """Make `scene` the obstacles every check of this step uses."""
        if scene is not self.scene_now:
            self.scene_now = scene
            self.validator = self._validator(scene)

    def verify(self, T: np.ndarray, X: np.ndarray, after: tuple[float, float] | None) -> float:
        """Conservative body clearance (mm, minus D_sf) of the sampled motion X at times T.

        after: a time window (s) over which the last configuration, held
        still, must also be clear (so the robot can always stop safely).

        Between two samples every actuator moves monotonically (first-order
        servos), and the bending part moves along a straight line, so each
        configuration in between is within half the body-motion bound of the
        two samples from one of them; each sample therefore must clear, over
        the time window from its previous to its next sample, the obstacles
        by that half bound on top of the validator's chord/sagitta bounds.
        """
        return held_clearance(self.validator, X, T, after)

    def measure(self, T: np.ndarray, X: np.ndarray) -> float:
        """Sampled (not conservative) body clearance (mm, minus D_sf) along the motion, many points."""
        P = self.model.points(X, REPORT_POINTS)
        return float(np.min(self.scene_now.clearance_points(P, T, inflate=self.model.robot.body_radius)))

    def hold_clearance(self, x: np.ndarray, t: float, dt: float) -> float:
        """Conservative clearance (mm, minus D_sf) of holding x from t for dt s."""
        return float(self.validator.clearance(x[None], t, t + dt)[0])

    def path_clear(self, X: np.ndarray, tt: np.ndarray, dt: float) -> bool:
        """Configurations X (n, nx), each reached at tt (n,) s, are clear within dt s of their times."""
        return bool(np.all(self.validator.clearance(X, tt - dt, tt + dt) >= 0.0))
