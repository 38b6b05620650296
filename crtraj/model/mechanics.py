"""Mechanical parameters of a tendon-driven robot: the ``[robot.mechanics]`` section of a robot file.

The PCC model (`crtraj.model.kinematics`) needs only lengths and the cable radius; the Cosserat-rod
model (`crtraj.model.cosserat._statics`) also needs the backbone's material and section, the mass it carries
and gravity. They live here, declared once with their units and bounds (`crtraj.core.options`).

Units: lengths mm, moduli N/mm^2 (= MPa), density kg/m^3, disc mass g, gravity m/s^2, force N.
Derived stiffnesses are in N (EA, GA) and N mm^2 (EI, GJ), the distributed weight in N/mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.core.options import Options, option
from crtraj.model.robot import Robot, plain

# Largest modulus accepted (N/mm^2): 1e7 MPa is 50 times diamond; anything above is a unit slip.
MAX_MODULUS = 1e7
# Most integration steps per segment: the symbolic shooting function grows linearly with them.
MAX_STEPS = 400
# Largest |gravity component| (m/s^2): 100 g covers any centrifuge test; above it is a unit slip.
MAX_GRAVITY = 1000.0
# How the servos drive the tendons: they set each tendon's length (position-controlled, crtraj's Dynamixel
# path) or its tension (force-controlled). The rod takes a different shape under each (docs/concepts/pcc-vs-rod.md).
ACTUATION_MODES = ("cable_length", "tension")
# kg/m^3 * mm^2 -> kg/mm; g -> kg
_KG_PER_M3_TO_KG_PER_MM3 = 1e-9
_KG_PER_G = 1e-3


@dataclass(frozen=True)
class Mechanics(Options):
    """Backbone, discs and gravity of a tendon-driven robot (``[robot.mechanics]``).

    youngs_modulus: E of the backbone (N/mm^2 = MPa). shear_modulus: G (N/mm^2).
    backbone_radius: radius of the solid round backbone (mm). backbone_density: kg/m^3.
    disc_mass: mass of one spacer disc (g). disc_spacing: distance between discs (mm); the discs'
    mass is smeared along the backbone as disc_mass / disc_spacing. gravity: acceleration vector in
    the robot's base frame (m/s^2; the base axis is +z, so a robot pointing up has (0, 0, -9.81)).
    tendon_stiffness: EA of one tendon (N): its stretch under tension tau is tau / EA per unit length.
    actuation: how the actuators drive the tendons, which decides the rod's shape for a configuration:
    "cable_length" (position-controlled servos set each tendon's commanded length, `crtraj.model.cosserat._drive`;
    the rod then finds its tensions, tendon stretch and gravity included) or "tension" (force-controlled
    actuators hold the tensions that keep the PCC bending on a weightless rod, whatever the weight does).
    steps: RK4 steps per segment of the shooting integrator. tolerance: largest shooting residual
    (N for forces, N mm / total length for moments) of a converged solve. max_iter: Newton iterations.
    """

    SECTION = "robot.mechanics"

    youngs_modulus: float = option(60_000.0, gt=0.0, le=MAX_MODULUS)
    shear_modulus: float = option(22_500.0, gt=0.0, le=MAX_MODULUS)
    backbone_radius: float = option(0.6, gt=0.0, le=MAX_LENGTH)
    backbone_density: float = option(6450.0, ge=0.0, le=1e5)
    disc_mass: float = option(0.0, ge=0.0, le=1e6)
    disc_spacing: float = option(10.0, gt=0.0, le=MAX_LENGTH)
    gravity: tuple[float, float, float] = option((0.0, 0.0, -9.81), read=False)
    tendon_stiffness: float = option(10_000.0, gt=0.0, le=1e9)
    actuation: str = option("cable_length", choices=ACTUATION_MODES)
    steps: int = option(20, ge=1, le=MAX_STEPS)
    tolerance: float = option(1e-9, gt=0.0, le=1.0)
    max_iter: int = option(50, ge=1, le=1000)

    def _check(self) -> None:
        g = tuple(float(v) for v in self.gravity)
        if len(g) != 3 or not all(math.isfinite(v) and abs(v) <= MAX_GRAVITY for v in g):
            raise InputError(f"{self.SECTION}.gravity: expected 3 finite numbers within +-{MAX_GRAVITY:g} m/s^2")
        object.__setattr__(self, "gravity", g)

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        return {"gravity": t.vec("gravity", 3, (0.0, 0.0, -9.81), limit=MAX_GRAVITY)}

    @classmethod
    def from_robot(cls, robot: Robot) -> Mechanics:
        """The robot's ``[robot.mechanics]`` section; `InputError` when the robot file has none."""
        if robot.mechanics is None:
            raise InputError(f"robot.mechanics: missing; robot {robot.name!r} needs a [robot.mechanics] table")
        return cls.from_table(Table(plain(robot.mechanics), cls.SECTION))

    # ------------------------------------------------------------ derived values
    @property
    def area(self) -> float:
        """Backbone cross-section A (mm^2)."""
        return math.pi * self.backbone_radius**2

    @property
    def second_moment(self) -> float:
        """Area moment I of the round backbone (mm^4); the polar moment is 2 I."""
        return math.pi * self.backbone_radius**4 / 4.0

    @property
    def bending_stiffness(self) -> float:
        """EI (N mm^2)."""
        return self.youngs_modulus * self.second_moment

    def shear_extension(self) -> np.ndarray:
        """K_se = diag(GA, GA, EA) (N), body frame."""
        return np.diag(
            [self.shear_modulus * self.area, self.shear_modulus * self.area, self.youngs_modulus * self.area]
        )

    def bending_torsion(self) -> np.ndarray:
        """K_bt = diag(EI, EI, GJ) (N mm^2), body frame, J = 2 I."""
        ei = self.bending_stiffness
        return np.diag([ei, ei, self.shear_modulus * 2.0 * self.second_moment])

    @property
    def mass_per_length(self) -> float:
        """Backbone plus smeared discs (kg/mm)."""
        rod = self.backbone_density * _KG_PER_M3_TO_KG_PER_MM3 * self.area
        return rod + self.disc_mass * _KG_PER_G / self.disc_spacing

    def weight_per_length(self) -> np.ndarray:
        """Distributed gravity force (N/mm) in the base frame: mass per length (kg/mm) x g (m/s^2)."""
        return self.mass_per_length * np.asarray(self.gravity)
