"""The safety margin: how far the robot's body is kept from an obstacle (mm).

"Safety" in crtraj means one thing: the continuous body keeps the distance
D_sf (``scene.safety_distance``) from every obstacle surface. The body is a
tube of radius ``body_radius`` (the discs) around a backbone that solvers see
as sampled points, so a backbone point must keep

    inflation = D_sf + body_radius + sagitta + margin            (mm)

from an obstacle surface: ``sagitta`` bounds how far the arc between two
sampled points strays from their chord, ``margin`` is extra room a solver
keeps (servo lag, solver tolerance). Equivalently the point stays outside the
keep-out sphere of radius ``R + inflation`` around an obstacle of radius R,
and its clearance is ``|p - c| - R - inflation`` (>= 0: safe).

The three functions below fix the order of the sums, because plans depend
on the last bit: `inflation` as written above; `keep_out_radius` as
``R + D_sf + (body_radius + margin)`` (the steer NLP and the RRT's sampling
radius); `clearance` as ``distance - body_radius - D_sf``. They are equal up
to rounding. They take floats or CasADi symbols alike.
"""

from __future__ import annotations

from typing import Any

# D_sf (mm) when a scene does not give one: the paper's safety distance.
DEFAULT_SAFETY_DISTANCE = 5.0


def inflation(safety_distance: Any, body_radius: Any, sagitta: Any = 0.0, margin: Any = 0.0) -> Any:
    """Distance (mm) a sampled backbone point keeps from an obstacle surface: D_sf + body + sagitta + margin."""
    return safety_distance + body_radius + sagitta + margin


def keep_out_radius(radius: Any, safety_distance: Any, body_radius: Any, margin: Any = 0.0) -> Any:
    """Radius (mm) of the sphere a backbone point stays outside: R + D_sf + (body_radius + margin)."""
    return radius + safety_distance + (body_radius + margin)


def clearance(surface_distance: Any, safety_distance: Any, body_radius: Any) -> Any:
    """Clearance (mm) of a backbone point `surface_distance` mm from an obstacle surface: d - body - D_sf."""
    return surface_distance - body_radius - safety_distance
