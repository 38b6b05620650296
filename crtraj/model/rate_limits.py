"""Actuator speed and acceleration limits as linear limits on configuration motion.

Every actuator value is affine in the configuration (paper eq. 4 and the spool/stage conversion):
``v = c + J x`` with ``J`` (nq, nx) in actuator units per configuration unit (rad/rad or rad/mm for a
cable servo, mm/mm for the z stage). A timed motion x(t) therefore keeps every actuator within its
limits exactly when ``|J x'(t)| <= vmax`` and ``|J x''(t)| <= amax`` elementwise. The planning and
control layers time and constrain motion with these; the robot description's actuator limits build
them (`crtraj.model.actuator_limits.ActuatorLimits.rate_limits`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from crtraj.core.errors import InputError


@dataclass(frozen=True)
class RateLimits:
    """|J dx/dt| <= vmax and |J d2x/dt2| <= amax per actuator (units: the actuator's per s and per s^2).

    jacobian: (m, nx) d actuator value / d configuration. vmax, amax: (m,) > 0. names: the actuators.
    """

    jacobian: np.ndarray
    vmax: np.ndarray
    amax: np.ndarray
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        J = np.array(self.jacobian, dtype=float)
        v = np.array(self.vmax, dtype=float).reshape(-1)
        a = np.array(self.amax, dtype=float).reshape(-1)
        if J.ndim != 2 or v.shape != (J.shape[0],) or a.shape != v.shape or len(self.names) != v.size:
            raise InputError(
                f"rate limits: shapes J {J.shape}, vmax {v.shape}, amax {a.shape}, {len(self.names)} names"
            )
        if not (np.all(np.isfinite(J)) and np.all(v > 0) and np.all(a > 0) and np.all(np.isfinite(v + a))):
            raise InputError("rate limits: vmax and amax must be finite and > 0, J finite")
        for name, arr in (("jacobian", J), ("vmax", v), ("amax", a)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def scaled(self, fraction: float) -> RateLimits:
        """The same limits with only `fraction` (0, 1] of each speed and acceleration usable (a reserve)."""
        if not (0.0 < fraction <= 1.0):
            raise InputError(f"limit fraction: must be in (0, 1], got {fraction}")
        return replace(self, vmax=self.vmax * fraction, amax=self.amax * fraction)

    def velocity_fraction(self, dx: np.ndarray) -> np.ndarray:
        """max over actuators of |J dx| / vmax for configuration velocities dx (..., nx)."""
        return np.max(np.abs(np.asarray(dx, dtype=float) @ self.jacobian.T) / self.vmax, axis=-1)
