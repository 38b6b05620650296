"""The closed loop's tip sensing: reads the tip sensor every step and, with tip feedback, corrects the
model's tip error by moving the goal the reference planner aims the model's tip at. Units: mm, s."""

from __future__ import annotations

import numpy as np

from crtraj.control.loop._reference_manager import ReferenceManager
from crtraj.control.ports import TipSensor
from crtraj.core.errors import InputError
from crtraj.model.kinematics import Model


class TipSensing:
    """The tip sensor's readings of one run (`start` begins a run) and the tip-feedback correction.

    sensor: the `TipSensor`, or None (nothing is read). feedback: correct the goal with a low-pass
    estimate (gain per step `gain`) of measured minus model tip (output-disturbance correction).
    goal (3,) mm: the task's tip goal. tolerance: the goal tolerance (mm); the corrected goal is passed on
    when it moved by more than half of it.
    """

    def __init__(
        self, model: Model, sensor: TipSensor | None, feedback: bool, gain: float, goal: np.ndarray, tolerance: float
    ) -> None:
        if not 0.0 < gain <= 1.0:
            raise InputError(f"tip_gain: must be in (0, 1], got {gain}")
        self.model, self.sensor, self.feedback, self.gain = model, sensor, bool(feedback), float(gain)
        self.goal, self.tolerance = goal, tolerance
        self.start()

    def start(self) -> None:
        """Forget the previous run's readings and estimate."""
        self.target = self.goal.copy()  # the tip goal the reference aims the model's tip at (mm)
        self.bias = np.zeros(3)  # estimated measured minus model tip (mm)
        self.measured: list[np.ndarray] = []  # the tip sensor's readings (mm)

    def sense(self, t: float, q: np.ndarray, x: np.ndarray, references: ReferenceManager) -> None:
        """Read the tip sensor (if any) at t (s) with actuation q; with tip feedback, update the model-error
        estimate and retarget the references when the corrected goal moved by more than half the goal
        tolerance."""
        if self.sensor is None:
            return
        m = self.sensor.tip(t, q)
        self.measured.append(np.full(3, np.nan) if m is None else np.asarray(m, dtype=float))
        if m is None or not self.feedback:
            return
        bias = np.asarray(m, dtype=float) - self.model.tip_position(x)
        self.bias = self.bias + self.gain * (bias - self.bias)
        target = self.goal - self.bias
        if np.linalg.norm(target - self.target) > 0.5 * self.tolerance:
            self.target = target
            references.retarget(target)

    def readings(self) -> np.ndarray | None:
        """The readings at every recorded time (K+1, 3) mm, NaN when not seen; None without a sensor."""
        return np.array(self.measured) if self.sensor is not None else None
