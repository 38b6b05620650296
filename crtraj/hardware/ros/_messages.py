"""What the ROS 2 bridge reads and writes, as plain checks and conversions (no rclpy needed to test them).

Every incoming message is hostile: `joint_state_values` and `marker_obstacles` bound its sizes before
touching its arrays, refuse NaN, infinities and absurd magnitudes, unknown or missing names, and raise
`RejectedError` (kind, one-line reason), which the node counts and records instead of crashing.
The message classes (trajectory_msgs, visualization_msgs, geometry_msgs) are imported inside the
builders because they are an optional extra. Units: ROS messages carry metres and seconds, crtraj mm.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

MAX_JOINTS = 256  # names in one JointState (a robot may publish other joints besides the actuators)
MAX_MARKERS = 256  # markers in one MarkerArray
MAX_VALUE = 1.0e6  # |actuator value| (rad, mm) and |coordinate| (mm) accepted
MAX_STAMP = 1.0e10  # s
MAX_NAME = 128
SPHERE, ADD = 2, 0  # visualization_msgs/Marker type and action codes
LINE_STRIP, DELETEALL = 4, 3


class RejectedError(Exception):
    """An incoming message that was not used: kind (invalid, unknown_name, oversize, frame, type) and why."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def si_scale(units: tuple[str, ...]) -> np.ndarray:
    """ROS value per crtraj value of each actuator: 1 for rad, 1e-3 for mm (ROS joints are in rad and m)."""
    return np.array([1e-3 if u == "mm" else 1.0 for u in units])


def stamp_seconds(stamp: Any) -> float:
    """builtin_interfaces/Time as s; `RejectedError` when out of range."""
    s = float(stamp.sec) + 1e-9 * float(stamp.nanosec)
    if not (math.isfinite(s) and abs(s) <= MAX_STAMP):
        raise RejectedError("invalid", f"header.stamp: {s!r} s out of range")
    return s


def joint_state_values(msg: Any, names: tuple[str, ...]) -> tuple[np.ndarray, float]:
    """(actuator values in `names` order, stamp s) of a sensor_msgs/JointState.

    Extra joints are ignored; a missing or repeated actuator, a length mismatch, a non-finite
    or huge position is refused."""
    n = len(msg.name)
    if n > MAX_JOINTS:
        raise RejectedError("oversize", f"joint_state: {n} names (at most {MAX_JOINTS})")
    if len(msg.position) != n:
        raise RejectedError("invalid", f"joint_state: {n} names but {len(msg.position)} positions")
    index: dict[str, int] = {}
    for i, name in enumerate(msg.name):
        if name in index:
            raise RejectedError("invalid", f"joint_state.name: {str(name)[:40]!r} repeated")
        index[name] = i
    missing = [a for a in names if a not in index]
    if missing:
        expected = ", ".join(names)
        raise RejectedError("unknown_name", f"joint_state.name: no {', '.join(missing)} (expected {expected})")
    pos = np.asarray(msg.position, dtype=float)
    values = pos[[index[a] for a in names]]
    bad = np.flatnonzero(~(np.abs(values) <= MAX_VALUE))
    if bad.size:
        k = int(bad[0])
        raise RejectedError("invalid", f"joint_state.position[{names[k]}]: {values[k]!r} not a finite value")
    return values, stamp_seconds(msg.header.stamp)


def marker_obstacles(msg: Any, frame_id: str) -> tuple[list[dict[str, Any]], list[RejectedError]]:
    """The obstacle messages (the UDP feed's schema: id, center mm, radius mm, timestamp s) of a
    visualization_msgs/MarkerArray, and the markers that were refused.

    An ADD SPHERE marker in `frame_id` is one obstacle: ``ns`` names it (the scene's obstacle
    name), its pose position (m) is the centre and half its largest scale (m, a diameter) the
    radius, so an ellipsoid is covered. Other types, actions or frames are refused one by one;
    an array longer than `MAX_MARKERS` is refused whole."""
    n = len(msg.markers)
    if n > MAX_MARKERS:
        raise RejectedError("oversize", f"markers: {n} markers (at most {MAX_MARKERS})")
    out: list[dict[str, Any]] = []
    refused: list[RejectedError] = []
    for k, m in enumerate(msg.markers):
        try:
            out.append(_sphere(m, k, frame_id))
        except RejectedError as exc:
            refused.append(exc)
    return out, refused


def _sphere(m: Any, k: int, frame_id: str) -> dict[str, Any]:
    where = f"markers[{k}]"
    if m.action != ADD:
        raise RejectedError("type", f"{where}.action: {m.action} is not ADD (0)")
    if m.type != SPHERE:
        raise RejectedError("type", f"{where}.type: {m.type} is not SPHERE (2)")
    if m.header.frame_id != frame_id:
        raise RejectedError("frame", f"{where}.header.frame_id: {m.header.frame_id[:40]!r}, expected {frame_id!r}")
    if not 0 < len(m.ns) <= MAX_NAME:
        raise RejectedError("invalid", f"{where}.ns: the obstacle's name, 1..{MAX_NAME} characters")
    p = m.pose.position
    c = [1000.0 * float(p.x), 1000.0 * float(p.y), 1000.0 * float(p.z)]
    r = 500.0 * max(float(m.scale.x), float(m.scale.y), float(m.scale.z))
    if not all(abs(v) <= MAX_VALUE for v in (*c, r)) or not r >= 0.0:
        raise RejectedError("invalid", f"{where}: position or scale not finite or out of range")
    return {"id": m.ns, "center": c, "radius": r, "timestamp": stamp_seconds(m.header.stamp)}


def _time(seconds: float) -> Any:
    """builtin_interfaces/Time of `seconds` (>= 0)."""
    from builtin_interfaces.msg import Time

    ns = round(max(seconds, 0.0) * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _duration(seconds: float) -> Any:
    from builtin_interfaces.msg import Duration

    ns = round(max(seconds, 0.0) * 1e9)
    return Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def trajectory(
    names: tuple[str, ...], stamp: float, offsets: np.ndarray, positions: np.ndarray, velocities: np.ndarray
) -> Any:
    """A trajectory_msgs/JointTrajectory starting at `stamp` (s): one point per offset (s after it),
    with actuator positions and velocities (N, n) in rad, mm, rad/s, mm/s."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    msg = JointTrajectory()
    msg.header.stamp = _time(stamp)
    msg.joint_names = list(names)
    msg.points = [
        JointTrajectoryPoint(
            positions=[float(v) for v in p], velocities=[float(v) for v in v_], time_from_start=_duration(float(dt))
        )
        for dt, p, v_ in zip(offsets, positions, velocities, strict=True)
    ]
    return msg


def scene_markers(
    frame_id: str, stamp: float, backbone: np.ndarray, body_radius: float, centers: np.ndarray, radii: np.ndarray
) -> Any:
    """A visualization_msgs/MarkerArray for RViz: the backbone (P, 3) mm as a line strip as thick as the
    body, and each obstacle (centres (m, 3), radii (m,) mm) as a sphere; everything in metres."""
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker, MarkerArray

    t = _time(stamp)
    clear = Marker(action=DELETEALL)
    clear.header.frame_id, clear.header.stamp = frame_id, t
    body = Marker(ns="crtraj/backbone", id=0, type=LINE_STRIP, action=ADD)
    body.header.frame_id, body.header.stamp = frame_id, t
    body.scale.x = max(2e-3 * body_radius, 1e-4)
    body.color.r, body.color.g, body.color.b, body.color.a = 0.1, 0.4, 0.9, 1.0
    body.pose.orientation.w = 1.0
    body.points = [Point(x=1e-3 * float(p[0]), y=1e-3 * float(p[1]), z=1e-3 * float(p[2])) for p in backbone]
    out = [clear, body]
    for i, (c, r) in enumerate(zip(np.reshape(centers, (-1, 3)), np.reshape(radii, -1), strict=True)):
        s = Marker(ns="crtraj/obstacles", id=i, type=SPHERE, action=ADD)
        s.header.frame_id, s.header.stamp = frame_id, t
        s.pose.position.x, s.pose.position.y, s.pose.position.z = (1e-3 * float(v) for v in c)
        s.pose.orientation.w = 1.0
        s.scale.x = s.scale.y = s.scale.z = 2e-3 * float(r)
        s.color.r, s.color.g, s.color.b, s.color.a = 0.9, 0.3, 0.2, 0.5
        out.append(s)
    return MarkerArray(markers=out)


def tip_path(frame_id: str, stamp: float, tips: np.ndarray) -> Any:
    """A nav_msgs/Path of tip positions (M, 3) mm, every pose stamped `stamp` (s), in metres."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path

    t = _time(stamp)
    msg = Path()
    msg.header.frame_id, msg.header.stamp = frame_id, t
    for p in np.reshape(tips, (-1, 3)):
        pose = PoseStamped()
        pose.header.frame_id, pose.header.stamp = frame_id, t
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (1e-3 * float(v) for v in p)
        pose.pose.orientation.w = 1.0
        msg.poses.append(pose)
    return msg


# rcl_interfaces/ParameterValue type codes and the field each is read from
_PARAMETER_FIELDS = {
    1: "bool_value",
    2: "integer_value",
    3: "double_value",
    4: "string_value",
    5: "byte_array_value",
    6: "bool_array_value",
    7: "integer_array_value",
    8: "double_array_value",
    9: "string_array_value",
}


def parameter_value(value: Any) -> Any:
    """The Python value of an rcl_interfaces/ParameterValue (None when the parameter is not set)."""
    field = _PARAMETER_FIELDS.get(int(value.type))
    if field is None:
        return None
    v = getattr(value, field)
    return v if isinstance(v, (bool, int, float, str)) else list(v)
