"""Obstacle shapes with poses, rigid motion over time, and one signed-distance interface (mm, s).

Shapes: `Sphere`, `Box`, `Capsule`, `Cylinder`, `HalfSpace`, each placed by a `Pose`. Motion: `Fixed`,
`Keyframes` (linear or natural-cubic position, slerp rotation), `StraightLine` (the sphere obstacles'
profiles), and `Breathing` (a uniform scale). `MovingShape` implements `DistanceField`: signed distance
and gradient at a time, and a conservative lower bound over an interval. `casadi_distance` gives the
smooth primitives' distances as CasADi expressions. `PointCloud` and `Mesh` are obstacles given as data
(files read by `load_points`, `load_triangles`), with a conservative distance to their points.
`nearest_surface_points` gives the true distance and the nearest surface point of any shape (the view's
closest-approach line). `GridDistance` is a point set's conservative trilinear distance grid (the NLPs'
interpolant and the checker's lookup). `shape_from_table` reads a problem file's ``[[scene.shape]]``;
`shape_clearance` and `chord_clearance` are what the scene and the checker ask. docs/concepts/shapes.md describes them.
"""

from crtraj.world.geometry._clearance import chord_clearance, shape_clearance
from crtraj.world.geometry._distance import ALL_SHAPES, DistanceField, MovingShape
from crtraj.world.geometry._exact import exact_clearances, exact_distance, exact_min_clearance, point_triangle_distance
from crtraj.world.geometry._files import load_points, load_triangles
from crtraj.world.geometry._grid import GridDistance
from crtraj.world.geometry._motion import INTERPOLATIONS, Breathing, Fixed, Keyframes, Motion, StraightLine
from crtraj.world.geometry._nearest import nearest_surface_points
from crtraj.world.geometry._nlp import ShapeTerms
from crtraj.world.geometry._points import MAX_POINTS, POINT_SETS, Mesh, PointCloud
from crtraj.world.geometry._rotation import QUAT_TOL
from crtraj.world.geometry._shapes import SHAPES, Box, Capsule, Cylinder, HalfSpace, Pose, Shape, Sphere
from crtraj.world.geometry._symbolic import BOX_SMOOTH_ERROR, casadi_distance
from crtraj.world.geometry._table import KINDS, shape_from_table, shape_to_dict

__all__ = [
    "ALL_SHAPES",
    "BOX_SMOOTH_ERROR",
    "INTERPOLATIONS",
    "KINDS",
    "MAX_POINTS",
    "POINT_SETS",
    "QUAT_TOL",
    "SHAPES",
    "Box",
    "Breathing",
    "Capsule",
    "Cylinder",
    "DistanceField",
    "Fixed",
    "GridDistance",
    "HalfSpace",
    "Keyframes",
    "Mesh",
    "Motion",
    "MovingShape",
    "PointCloud",
    "Pose",
    "Shape",
    "ShapeTerms",
    "Sphere",
    "StraightLine",
    "casadi_distance",
    "chord_clearance",
    "exact_clearances",
    "exact_distance",
    "exact_min_clearance",
    "load_points",
    "load_triangles",
    "nearest_surface_points",
    "point_triangle_distance",
    "shape_clearance",
    "shape_from_table",
    "shape_to_dict",
]
