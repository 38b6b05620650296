"""Obstacle shapes with poses, rigid motion over time, and one signed-distance interface (mm, s).

Shapes: `Sphere`, `Box`, `Capsule`, `Cylinder`, `HalfSpace`, each placed by a `Pose`. Motion: `Fixed`,
`Keyframes` (linear or natural-cubic position, slerp rotation), `StraightLine` (the sphere obstacles'
profiles), and `Breathing` (a uniform scale). `MovingShape` implements `DistanceField`: signed distance
and gradient at a time, and a conservative lower bound over an interval. `casadi_distance` gives the
smooth primitives' distances as CasADi expressions. docs/concepts/shapes.md describes them.
"""

from crtraj.world.geometry._distance import DistanceField, MovingShape
from crtraj.world.geometry._motion import INTERPOLATIONS, Breathing, Fixed, Keyframes, Motion, StraightLine
from crtraj.world.geometry._rotation import QUAT_TOL
from crtraj.world.geometry._shapes import SHAPES, Box, Capsule, Cylinder, HalfSpace, Pose, Shape, Sphere
from crtraj.world.geometry._symbolic import BOX_SMOOTH_ERROR, casadi_distance

__all__ = [
    "BOX_SMOOTH_ERROR",
    "INTERPOLATIONS",
    "QUAT_TOL",
    "SHAPES",
    "Box",
    "Breathing",
    "Capsule",
    "Cylinder",
    "DistanceField",
    "Fixed",
    "HalfSpace",
    "Keyframes",
    "Motion",
    "MovingShape",
    "Pose",
    "Shape",
    "Sphere",
    "StraightLine",
    "casadi_distance",
]
