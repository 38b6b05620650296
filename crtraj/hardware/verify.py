"""Verified as sent: the set-points that will leave, turned back into configurations and checked.

A planner verifies its own motion (straight lines in configuration space, its
own timing); the device is sent something else: actuator values interpolated
at the stream rate (`crtraj.hardware.setpoints.SetpointPath.sample`, the
streamer's own sampling), an approach move, a live follower's output. So the
library checks the frames themselves, before the first one leaves:

1. Limits: position, velocity and acceleration of every actuator, frame by
   frame, from the state before the first frame (`LimitsGate.check_path`, the
   same gate every frame passes when it is sent).
2. Cables: the actuator values are converted back to actuation q
   (`Actuators.actuation`) and to configurations (the robot's cable ->
   configuration map, `Robot.config`). The cables of a segment are coupled
   (three cables, two bending angles): frames whose cables do not fit one
   configuration within `VerifyOptions.cable_tolerance` would stretch or
   slacken a cable, and are refused.
3. Configuration limits: bending, cable strokes and z stroke of every frame
   (`Robot.limit_violation`).
4. The body, densely, at the frames' times: between two frames the device
   moves along the straight line in actuator space, which is a straight line
   in configuration space (the maps are affine), during the frame period.
   Every such motion is checked with the planning layer's motion validity
   (`crtraj.planning.validity.MotionValidator.edge_clearance`): `check_points`
   backbone points per configuration (chords with their sagitta bound),
   samples at most `resolution` mm of body motion apart, each sample against
   the sphere enclosing everything the obstacle sweeps in its time window,
   with the body radius and the scene's safety distance D_sf. A motion that
   passes keeps D_sf from every obstacle with its continuous body.

The check is conservative by at most `FrameVerifier.slack` mm: whatever it
refuses comes closer than D_sf + slack to an obstacle (or breaks a limit).

Not covered: the device's own lag behind its set-points (the streamer's
following-error check bounds it at run time), and the time before the first
and after the last frame, when the device rests where it is.
Units: mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.limits import LimitsGate
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.validity import Kernels, MotionValidator

# Slack of the configuration-limit comparison (rad or mm): the round trip x -> q -> values -> q -> x.
_LIMIT_TOL = 1e-9


@dataclass(frozen=True)
class VerifyOptions:
    """How densely the frames are checked.

    check_points: backbone points per configuration (>= 2). resolution:
    largest body motion (mm) between checked samples of one frame-to-frame
    motion. cable_tolerance: largest distance (mm) of a frame's cable lengths
    from those of the configuration they map to.
    """

    check_points: int = 40
    resolution: float = 0.5
    cable_tolerance: float = 0.05

    def __post_init__(self) -> None:
        if not (isinstance(self.check_points, int) and 2 <= self.check_points <= 1000):
            raise InputError(f"verify.check_points: must be an integer in 2..1000, got {self.check_points!r}")
        for name in ("resolution", "cable_tolerance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise InputError(f"verify.{name}: must be > 0, got {v!r}")


class FrameVerifier:
    """Checks frame sequences (stamps (M,) s, actuator values (M, n)) against a scene and the limits.

    robot: the robot the frames drive; actuators: its actuators (bound to it);
    scene: the obstacles, in the frames' clock; dt: the stream period (s).
    model: a `Model` of `robot` to reuse (building one compiles CasADi
    functions); kernels: the compiled kernels and CasADi functions to share between verifiers.
    """

    def __init__(
        self,
        robot: Robot,
        actuators: Actuators,
        scene: Any,
        dt: float,
        options: VerifyOptions | None = None,
        *,
        model: Model | None = None,
        kernels: Kernels | None = None,
    ) -> None:
        self.robot = robot
        self.actuators = actuators
        self.scene = scene
        self.dt = float(dt)
        self.options = VerifyOptions() if options is None else options
        self.model = Model(robot) if model is None else model
        self._kernels = Kernels() if kernels is None else kernels
        o = self.options
        self.validator = MotionValidator(
            self.model, scene, check_points=o.check_points, resolution=o.resolution, kernels=self._kernels
        )
        self.gate = LimitsGate(actuators, self.dt)
        self._A, self._q0 = robot.cable_matrix()

    def with_scene(self, scene: Any) -> FrameVerifier:
        """The same checks against another scene (a live snapshot), sharing the model and functions."""
        return FrameVerifier(
            self.robot, self.actuators, scene, self.dt, self.options, model=self.model, kernels=self._kernels
        )

    @property
    def slack(self) -> float:
        """How much the body check may exaggerate (mm): a refused motion comes closer than D_sf + slack.

        Twice the sagitta (the arc strays that far either side of a chord), half
        a sample spacing, and how far an obstacle can move or grow in one frame
        period (its swept sphere stands for a whole window).
        """
        speeds, rates = self.scene.speed_bounds()
        move = float(np.max(speeds + rates)) * self.dt if self.scene.n_obstacles else 0.0
        return 2.0 * self.validator.sagitta + 0.5 * self.options.resolution + move

    def configurations(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(configurations (M, nx), cable mismatch (M,) mm) of actuator values (M, n)."""
        q = self.actuators.actuation(np.atleast_2d(np.asarray(values, dtype=float)))
        X = self.robot.config(q)
        fit = X @ self._A.T + self._q0
        return X, np.max(np.abs(q - fit), axis=1)

    # Over 60 lines only by its checks written out in the module docstring's order.
    def failure(
        self,
        stamps: np.ndarray,
        values: np.ndarray,
        *,
        start: np.ndarray | None = None,
        start_velocity: np.ndarray | None = None,
    ) -> str | None:
        """The first reason the frames may not be sent ("REASON at t=T s"), or None when they may.

        start / start_velocity: the actuator values and velocity before the
        first frame (the device's, or the last frame sent); by default the
        first frame at rest (a motion checked on its own). With `start`, the
        move from it to the first frame, during the period before it, is
        checked too.
        """
        stamps = np.asarray(stamps, dtype=float)
        values = np.atleast_2d(np.asarray(values, dtype=float))
        if stamps.ndim != 1 or values.shape != (stamps.size, self.actuators.n) or stamps.size == 0:
            raise InputError(f"frames: expected stamps (M,) and values (M, {self.actuators.n}), got {values.shape}")
        v = self.gate.check_path(values, stamps, start, start_velocity)
        if v is not None:
            return v.message()
        if start is not None:
            stamps = np.concatenate([[stamps[0] - self.dt], stamps])
            values = np.vstack([np.asarray(start, dtype=float)[None], values])
        X, mismatch = self.configurations(values)
        bad = np.flatnonzero(mismatch > self.options.cable_tolerance)
        if bad.size:
            k = int(bad[0])
            return (
                f"cable lengths fit no configuration (off by {mismatch[k]:.3g} mm > "
                f"{self.options.cable_tolerance:g} mm) at t={stamps[k]:.3f} s"
            )
        over = self.robot.limit_violation(X)
        bad = np.flatnonzero(over > _LIMIT_TOL)
        if bad.size:
            k = int(bad[0])
            return (
                f"configuration outside the robot's limits (bending or stroke, by {over[k]:.3g}) at t={stamps[k]:.3f} s"
            )
        return self._body_failure(stamps, X)

    def _body_failure(self, stamps: np.ndarray, X: np.ndarray) -> str | None:
        """The first frame-to-frame motion whose continuous body comes closer than D_sf, or None."""
        if self.scene.n_obstacles == 0:
            return None
        if len(X) == 1:
            c = self.validator.clearance(X, stamps[0], stamps[0])
            e, t_lo = np.zeros(1, dtype=int), stamps[:1]
        else:
            _, c, e = self.validator.edge_clearance(X[:-1], X[1:], stamps[:-1], stamps[1:])
            t_lo = stamps[:-1][e]
        bad = np.flatnonzero(c < 0.0)
        if not bad.size:
            return None
        j = int(bad[0])
        k = int(e[j]) + (0 if len(X) == 1 else 1)
        return (
            f"body closer than the safety distance D_sf={self.scene.safety_distance:g} mm to an obstacle "
            f"(clearance bound {float(c[j]):.3g} mm) between t={float(t_lo[j]):.3f} s and t={stamps[k]:.3f} s"
        )

    def slowest_scale(self, path: Any, rate: float) -> float | None:
        """The smallest time scale (in steps of 5 %) at which `path`'s sampled set-points pass every
        actuator limit (the velocity and acceleration of a motion fall as 1/s and 1/s^2), or None."""
        _, values = path.sample(rate)
        V = np.diff(values, axis=0) / self.dt
        A = np.diff(V, axis=0) / self.dt
        guess = max(
            1.0,
            float(np.max(np.abs(V) / self.actuators.vmax, initial=0.0)),
            float(np.sqrt(np.max(np.abs(A) / self.actuators.amax, initial=0.0))),
        )
        scale = np.ceil(guess * 20) / 20
        for _ in range(60):
            if scale > 1000.0:
                return None
            st, va = path.scaled(float(scale)).sample(rate)
            if self.gate.check_path(va, st) is None:
                return float(scale)
            scale = np.ceil(scale * 1.05 * 20) / 20
        return None
