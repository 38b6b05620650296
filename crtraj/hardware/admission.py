"""Admission: which motions may drive a device. The one place that refuses, for every caller.

`admit` takes what is known about a result (`MotionRecord`: plain typed data;
`crtraj.io.results.Result.motion_record` builds it from a result file) and the
device's actuators, and either refuses with a one-line `AdmissionError` or
returns an `AdmittedMotion`: the set-point path to send, sealed so that only
`admit` can make one. `crtraj.hardware.stream.Streamer.run_path` streams
nothing else, so a Python user cannot bypass the refusals that the command
line applies.

Refused, before anything is sent:
- a result that failed (``success`` false), whatever its status;
- a run made without the collision-free terms (``crtraj replan --no-safety``);
- a result with collision steps, or steps closer than the safety distance D_sf;
- a result without its scene (nothing could be re-checked against it);
- a result made for another robot than the device's (`crtraj.model.identity`);
- a slowed replay (time scale != 1) among moving or breathing obstacles: the
  slowed timing was never checked against them (re-verification is issue 13's
  later work; until then it is refused).

The live loop (``crtraj replan --feed --stream``) streams one verified step at
a time through `Streamer.send_values`; `check_stream_safety` is its refusal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crtraj.core.errors import AdmissionError, InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath, check_time_scale
from crtraj.model.identity import robot_difference
from crtraj.model.robot import Robot
from crtraj.world.scene import Scene

# Only `admit` holds this object, so only `admit` can construct an `AdmittedMotion`.
_SEAL = object()


@dataclass(frozen=True)
class MotionRecord:
    """What admission needs to know about a result (mm, s).

    source: where it came from, for messages ("" for data built in memory).
    kind: "plan" or "replan". status, success: the result's own verdict.
    safety: False for a run made without the collision-free terms.
    collisions: steps (or waypoints) whose body touched an obstacle.
    safety_violations: steps closer than the scene's safety distance D_sf.
    robot: the robot the result was made for. scene: its scene, None when the
    result has none. t (N,) s and q (N, nq) mm: the waypoints' times and
    actuation; q is None when the result records none.
    """

    source: str
    kind: str
    status: str
    success: bool
    safety: bool
    collisions: int
    safety_violations: int
    robot: Robot
    scene: Scene | None
    t: np.ndarray
    q: np.ndarray | None


@dataclass(frozen=True)
class AdmittedMotion:
    """A motion `admit` let through: `path` (actuator set-points, already time-scaled) for `actuators`.

    Only `admit` can construct it; `Streamer.run_path` streams nothing else.
    """

    path: SetpointPath
    robot: Robot
    actuators: Actuators
    source: str = ""
    time_scale: float = 1.0
    _seal: object = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self._seal is not _SEAL:
            raise TypeError("AdmittedMotion: made only by crtraj.hardware.admission.admit")

    def admitted_for(self, actuators: Actuators) -> bool:
        """True when `actuators` are the ones this motion was admitted for (same conversion and limits)."""
        return same_actuators(self.actuators, actuators)


def same_actuators(a: Actuators, b: Actuators) -> bool:
    """Same count, conversion (spools, signs, offsets, rest lengths) and limits."""
    if a is b:
        return True
    if a.n_segments != b.n_segments or (a.rest is None) != (b.rest is None):
        return False
    names = ("spool_radius", "sign", "zero_offset", "lower", "upper", "vmax", "amax", "rest")
    return all(getattr(a, k) is None or np.array_equal(getattr(a, k), getattr(b, k)) for k in names)


def check_replay_time_scale(scene: Scene | None, time_scale: float) -> None:
    """Refuse to slow down a motion among moving or breathing obstacles: its slowed timing was never checked.

    time_scale: the replay's slow-down factor (1 = as planned).
    """
    if time_scale == 1.0 or scene is None:
        return
    if any(ob.amplitude != 0.0 or ob.to is not None for ob in scene.obstacles):
        raise AdmissionError(
            f"--time-scale: {time_scale:g} refused: the run's obstacles move or change size, and a slowed replay "
            "was never checked against them (plan again with lower speed limits instead)"
        )


def check_stream_safety(safety: bool) -> None:
    """Refuse to drive a device with a run that has no collision-free terms (``--no-safety``)."""
    if not safety:
        raise AdmissionError(
            "--stream: refused with --no-safety (a run without the collision-free terms never drives a device)"
        )


def _refusal(record: MotionRecord, device_robot: Robot) -> str | None:
    """Why `record` may not drive `device_robot`'s actuators ("FIELD: reason"), or None."""
    if not record.success:
        return f"success: false (status {record.status}): a failed result never drives a device"
    if not record.safety:
        return "safety: false: made without the collision-free terms (--no-safety); it never drives a device"
    if record.collisions > 0:
        return f"summary.collisions: {record.collisions} steps touch an obstacle; a colliding result is never sent"
    if record.safety_violations > 0:
        return (
            f"summary.safety_violations: {record.safety_violations} steps closer than the safety distance; "
            "such a result is never sent"
        )
    if record.scene is None:
        return "scene: missing: a result without its scene cannot be checked and is never sent"
    diff = robot_difference(device_robot, record.robot)
    if diff is not None:
        return (
            f"robot: made for robot '{record.robot.name}', the device is '{device_robot.name}' ({diff}); "
            "a result for another robot is never sent"
        )
    return None


def admit(
    record: MotionRecord, actuators: Actuators, *, robot: Robot | None = None, time_scale: float = 1.0
) -> AdmittedMotion:
    """Admit a result's motion for a device, or refuse it with a one-line `AdmissionError`.

    actuators: the device's actuators (bound to its robot, or unbound: then
    bound to the result's robot). robot: the device's robot definition
    (default: the result's own, when the actuators come from the result's
    robot file). time_scale: play the motion this many times slower
    (0.001..1000). Raises `InputError` for unreadable data (no actuation, a bad
    time scale), `AdmissionError` for a refusal.
    """
    check_time_scale(time_scale)
    where = f"{record.source}: " if record.source else ""
    why = _refusal(record, record.robot if robot is None else robot)
    if why is not None:
        raise AdmissionError(where + why)
    check_replay_time_scale(record.scene, time_scale)
    if record.q is None:
        raise InputError(f"{where}waypoints[0].q: missing (the actuation, mm, that a device is sent)")
    bound = actuators.for_robot(record.robot)
    if actuators.rest is not None and not same_actuators(bound, actuators):
        raise AdmissionError(f"{where}robot: the actuators are bound to another robot's cable lengths")
    path = SetpointPath.from_actuation(record.t, record.q, bound, where)
    if time_scale != 1.0:
        path = path.scaled(time_scale)
    return AdmittedMotion(path, record.robot, bound, record.source, float(time_scale), _SEAL)
