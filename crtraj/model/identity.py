"""Robot identity: whether two robot definitions describe the same machine.

A result is bound to the robot it was made for. Viewing it with another robot's
model draws a wrong body; streaming it to another robot's actuators drives a
motion nobody verified. Both compare the geometry that decides the body's shape
and the actuation: segment lengths and bend limits, cable radius and phases,
base stroke, coupling and body radius. Names, descriptions and the
``[robot.actuators]`` table are not part of it (a lab may rename a robot file or
retune its servos without changing the robot).
"""

from __future__ import annotations

import math

from crtraj.model.robot import Robot

_RTOL = 1e-12


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=_RTOL, abs_tol=_RTOL)


def robot_mismatch(mine: Robot, other: Robot) -> tuple[str, str, str] | None:
    """None when `other` is the same robot as `mine`; else the first difference as (field, other's value,
    mine's value), each value as text ("segments", "3", "2")."""
    if mine.n_segments != other.n_segments:
        return "segments", str(other.n_segments), str(mine.n_segments)
    for k, (a, b) in enumerate(zip(mine.segments, other.segments, strict=True)):
        for name in ("length", "theta_max", "cable_phase"):
            if not _close(getattr(a, name), getattr(b, name)):
                return f"segment[{k}].{name}", f"{getattr(b, name):g}", f"{getattr(a, name):g}"
        if (a.cable_stroke is None) != (b.cable_stroke is None) or (
            a.cable_stroke is not None and not _close(a.cable_stroke, b.cable_stroke)
        ):
            return f"segment[{k}].cable_stroke", str(b.cable_stroke), str(a.cable_stroke)
    for name in ("cable_radius", "coupling", "body_radius"):
        if not _close(getattr(mine, name), getattr(other, name)):
            return name, f"{getattr(other, name):g}", f"{getattr(mine, name):g}"
    if not all(_close(a, b) for a, b in zip(mine.z_range, other.z_range, strict=True)):
        return "z_range", str(list(other.z_range)), str(list(mine.z_range))
    return None
