"""A simulated motion-capture tip marker: the `crtraj.control.ports.TipSensor` of a robot whose real
parameters differ from the model the loop plans with.

The loop's actuation q (mm, in the loop's robot file) becomes servo values through that file's
actuators (what a device would be sent); the true robot's parameters (its robot file: lengths, coupling,
cable radius, zero offsets) turn those values into the tip the capture system sees, plus Gaussian noise
per axis. The capture frame is taken as calibrated (the reading is in the robot frame). Units: mm, rad, s.
"""

from __future__ import annotations

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.model.calibration import CalibrateOptions, CalibrationModel, Hardware, Layout, MarkerSite
from crtraj.model.robot import Robot


class SimulatedMocap:
    """Tip readings of `true_robot` driven with the servo values `commanded` computes from the loop's q.

    noise: standard deviation per axis (mm; the paper's capture: 0.3). seed: the noise's seed.
    """

    def __init__(self, true_robot: Robot, commanded: Actuators, *, noise: float = 0.3, seed: int = 0) -> None:
        if not 0.0 <= noise <= 100.0:
            raise InputError(f"mocap noise: must be in [0, 100] mm, got {noise}")
        if true_robot.actuators is None:
            raise InputError(f"--true-robot: robot {true_robot.name!r} has no [robot.actuators] (its zero offsets)")
        true_act = Actuators.from_robot(true_robot)
        if true_act.n != commanded.n:
            raise InputError(f"--true-robot: {true_act.n} actuators, the loop's robot has {commanded.n}")
        layout = Layout.build(true_robot, true_act.zero_offset, np.zeros(6), CalibrateOptions())
        site = (MarkerSite("tip", true_robot.n_segments - 1),)
        self._cm = CalibrationModel(true_robot, Hardware(true_act.spool_radius, true_act.sign), site, layout)
        self._theta = layout.prior
        self._commanded = commanded
        self._noise = float(noise)
        self._rng = np.random.default_rng(seed)

    def true_tip(self, q: np.ndarray) -> np.ndarray:
        """The true robot's tip (3,) mm, without noise, for the loop's actuation q (mm)."""
        values = self._commanded.command(np.asarray(q, dtype=float))
        return np.asarray(self._cm.markers(self._theta, values)).reshape(3)

    def tip(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """A noisy reading of the true tip (3,) mm."""
        return self.true_tip(q) + self._rng.normal(0.0, self._noise, 3)
