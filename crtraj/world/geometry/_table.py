"""``[[scene.shape]]`` tables of a problem file: one shape with its pose, motion and breathing (mm, rad, s).

    [[scene.shape]]
    name = "table"
    kind = "box"                         # box, capsule, cylinder, halfspace, sphere, mesh, points
    half_extents = [150.0, 100.0, 10.0]  # box (mm); capsule, cylinder: radius, length; sphere: radius;
                                         # halfspace: normal, offset; mesh: file, spacing; points: file, radius
    position = [0.0, 0.0, -10.0]         # mm (default the origin)
    rotation = [1.0, 0.0, 0.0, 0.0]      # unit quaternion (w, x, y, z) (default none)
    motion = { to = [0.0, 50.0, -10.0], duration = 4.0, profile = "cos" }   # as an obstacle's motion
    # or keyframes = { times = [..], positions = [[..]], rotations = [[..]], interpolation = "linear" }
    breathing = { amplitude = 0.1, omega = 2.0, phase = 0.0 }               # scale 1 + a sin(w t + phase)

`motion.to` is where `position` goes (a straight line, the obstacles' profiles). With `keyframes` the
positions and rotations are the moving frame's pose and `position`, `rotation` place the shape in that
frame (a box on a turning arm: keyframes turning about the axis, `position` the arm's length).
File names are relative to the problem file (`crtraj.io.problem` makes them absolute).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, Table
from crtraj.world.geometry._distance import MovingShape
from crtraj.world.geometry._files import load_points, load_triangles
from crtraj.world.geometry._motion import INTERPOLATIONS, Breathing, Fixed, Keyframes, StraightLine
from crtraj.world.geometry._points import Mesh, PointCloud
from crtraj.world.geometry._shapes import Box, Capsule, Cylinder, HalfSpace, Pose, Sphere
from crtraj.world.obstacle import MAX_COORDINATE, MAX_OMEGA, MIN_DURATION, PROFILES

KINDS = ("box", "capsule", "cylinder", "halfspace", "sphere", "mesh", "points")


def _geometry(t: Table, kind: str, pose: Pose, name: str) -> Any:
    """The shape of `kind` from its own keys (module docstring)."""
    if kind == "box":
        return Box(t.vec("half_extents", 3, limit=MAX_LENGTH), pose, name)
    if kind in ("capsule", "cylinder"):
        cls = Capsule if kind == "capsule" else Cylinder
        return cls(t.float("radius", limit=MAX_LENGTH), t.float("length", limit=MAX_LENGTH), pose, name)
    if kind == "sphere":
        return Sphere(t.float("radius", limit=MAX_LENGTH), pose, name)
    if kind == "halfspace":
        return HalfSpace(t.vec("normal", 3), t.float("offset", 0.0, limit=MAX_LENGTH), pose, name)
    file = t.str("file", max_len=4096)
    field = f"{t.path}.file"
    if kind == "mesh":
        spacing = t.float("spacing", 4.0, gt=0.0, limit=MAX_LENGTH)
        return Mesh(load_triangles(file, field), spacing, pose, name, source=file)
    return PointCloud(load_points(file, field), t.float("radius", gt=0.0, limit=MAX_LENGTH), pose, name, file)


def _motion(t: Table, position: tuple[float, ...]) -> Any:
    if t.has("motion") and t.has("keyframes"):
        raise t.error("keyframes", "give either motion or keyframes, not both")
    if t.has("motion"):
        mt = t.table("motion")
        to = mt.vec("to", 3, limit=MAX_COORDINATE)
        profile = mt.str("profile", "linear", choices=PROFILES)
        duration = mt.float("duration", ge=MIN_DURATION, limit=MAX_TIME)
        mt.finish()
        return StraightLine((0.0, 0.0, 0.0), tuple(b - a for a, b in zip(position, to, strict=True)), duration, profile)
    if t.has("keyframes"):
        kt = t.table("keyframes")
        times = kt.vec("times", None, limit=MAX_TIME)
        positions = kt.raw("positions")
        rotations = kt.raw("rotations", None)
        interp = kt.str("interpolation", "linear", choices=INTERPOLATIONS)
        kt.finish()
        try:
            return Keyframes(times, positions, rotations, interp)
        except InputError as exc:  # name the table: "scene.shape[2].keyframes.times: ..."
            raise InputError(f"{t.path}.{exc}") from None
    return Fixed()


def _breathing(t: Table) -> Breathing | None:
    if not t.has("breathing"):
        return None
    bt = t.table("breathing")
    amp = bt.float("amplitude", limit=1.0)
    if not abs(amp) < 1.0:
        raise bt.error("amplitude", f"must be in (-1, 1) so the scale stays > 0, got {amp:g}")
    b = Breathing(amp, bt.float("omega", 0.0, limit=MAX_OMEGA), bt.float("phase", 0.0, limit=1e3))
    bt.finish()
    return b


def shape_from_table(t: Table) -> MovingShape:
    """One ``[[scene.shape]]`` table as a `MovingShape` (schema in the module docstring)."""
    name = t.str("name", "", max_len=100)
    kind = t.str("kind", choices=KINDS)
    position = t.vec("position", 3, (0.0, 0.0, 0.0), limit=MAX_COORDINATE)
    rotation = t.vec("rotation", 4, (1.0, 0.0, 0.0, 0.0))
    try:
        pose = Pose(position, rotation)
        shape = _geometry(t, kind, pose, name)
    except InputError as exc:
        msg = str(exc)
        raise InputError(msg if msg.startswith(t.path) else f"{t.path}.{msg}") from None
    motion = _motion(t, position)
    breathing = _breathing(t)
    t.finish()
    return MovingShape(shape, motion, breathing)


def _geometry_dict(shape: Any) -> dict[str, Any]:
    if isinstance(shape, Box):
        return {"half_extents": list(shape.half_extents)}
    if isinstance(shape, (Capsule, Cylinder)):
        return {"radius": shape.radius, "length": shape.length}
    if isinstance(shape, Sphere):
        return {"radius": shape.radius}
    if isinstance(shape, HalfSpace):
        return {"normal": list(shape.normal), "offset": shape.offset}
    if isinstance(shape, Mesh):
        return {"file": shape.source, "spacing": shape.spacing}
    return {"file": shape.source, "radius": shape.radius}


def shape_to_dict(ms: MovingShape) -> dict[str, Any]:
    """Plain data in the ``[[scene.shape]]`` schema (round-trips through `shape_from_table` when a mesh or
    cloud came from a file)."""
    s = ms.shape
    d: dict[str, Any] = {"name": s.name} if s.name else {}
    d["kind"] = s.kind
    d.update(_geometry_dict(s))
    d["position"] = list(s.pose.position)
    d["rotation"] = list(s.pose.rotation)
    m = ms.motion
    if isinstance(m, StraightLine):
        to = np.asarray(s.pose.position) + np.asarray(m.to) - np.asarray(m.start)
        d["motion"] = {"to": to.tolist(), "duration": m.duration, "profile": m.profile}
    elif isinstance(m, Keyframes):
        d["keyframes"] = {
            "times": list(m.times),
            "positions": [list(p) for p in m.positions],
            "rotations": [list(q) for q in m.rotations],
            "interpolation": m.interpolation,
        }
    if ms.breathing is not None:
        b = ms.breathing
        d["breathing"] = {"amplitude": b.amplitude, "omega": b.omega, "phase": b.phase}
    return d
