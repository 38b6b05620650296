"""The actuators' simulation: a first-order lag per actuator, discretised exactly (units mm, s)."""

from __future__ import annotations

import numpy as np

from crtraj.core.fields import check_float
from crtraj.model.robot import Robot

# Periods whose constants are kept (a caller that varies dt should not grow memory).
MAX_PERIODS = 8


class ServoModel:
    """Actuator simulation: a first-order lag per actuator, discretised exactly.

    ``tau dq/dt = q_cmd - q`` with the command held over each period, so
    ``q(t) = q_cmd + (q0 - q_cmd) exp(-t/tau)``. q is the actuators' actual
    position (nq, mm); ``config(q)`` gives the robot's actual configuration.
    """

    def __init__(self, robot: Robot, tau_cable: float, tau_z: float) -> None:
        check_float(tau_cable, "tau_cable", gt=0.0)
        check_float(tau_z, "tau_z", gt=0.0)
        self.robot = robot
        self.tau = np.append(np.full(3 * robot.n_segments, float(tau_cable)), float(tau_z))
        _, self._q0 = robot.cable_matrix()
        self._Binv = robot.cable_inverse()
        # decay per period dt (s): a control loop advances by the same few periods over and over
        self._decays: dict[float, np.ndarray] = {}

    def decay(self, dt: float) -> np.ndarray:
        """exp(-dt/tau) per actuator: the share of the old position left after dt (s)."""
        return np.exp(-dt / self.tau)

    def advance(self, q: np.ndarray, q_command: np.ndarray, dt: float) -> np.ndarray:
        """Actuator positions (mm) after holding `q_command` for dt (s)."""
        d = self._decays.get(dt)
        if d is None:
            if len(self._decays) >= MAX_PERIODS:
                self._decays.clear()
            d = self.decay(dt)
            d.setflags(write=False)
            self._decays[dt] = d
        return q_command + d * (np.asarray(q, dtype=float) - q_command)

    def trajectory(self, q: np.ndarray, q_command: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Actuator positions (len(times), nq) at times (s) within one held command (dense checks)."""
        t = np.asarray(times, dtype=float).reshape(-1, 1)
        return q_command + np.exp(-t / self.tau) * (np.asarray(q, dtype=float) - q_command)

    def config(self, q: np.ndarray) -> np.ndarray:
        """Configuration(s) x from actuator positions q (mm)."""
        return (np.asarray(q, dtype=float) - self._q0) @ self._Binv.T
