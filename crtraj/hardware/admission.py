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
- a motion whose set-points, as they will be sent, fail `crtraj.hardware.verify`:
  the frames sampled at the stream rate by the streamer's own sampling
  (`SetpointPath.sample`), slowed by the time scale if any, are turned back
  into configurations and checked against the scene at their times (dense
  body check with D_sf, cable consistency, configuration and actuator
  limits). A slowed replay among moving obstacles is checked the same way: it
  is admitted when it stays safe at its new times.

The `AdmittedMotion` carries the verified frames; `Streamer.run_path` sends
exactly those (with a verified approach before them, if asked).

The live loop (``crtraj replan --feed --stream``) streams one step at a time
(`crtraj.hardware.link.DeviceLink`, each step's frames verified by the same
`FrameVerifier` against the loop's scene snapshot); `check_stream_safety` is its refusal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from crtraj.core.errors import AdmissionError, InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath, check_time_scale
from crtraj.hardware.verify import FrameVerifier, VerifyOptions
from crtraj.model.identity import robot_mismatch
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
    actuation; q is None when the result records none. period: s between
    samples when t, q are a run's executed actuation, one sample per control
    period (streamed as its B-spline, `SetpointPath.from_executed`); None for
    waypoints (streamed through them, `SetpointPath.from_actuation`).
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
    period: float | None = None


@dataclass(frozen=True)
class AdmittedMotion:
    """A motion `admit` let through: `path` (actuator set-points, already time-scaled) for `actuators`.

    stamps (M,) s and values (M, n): the frames `path` gives at `rate` Hz, as
    verified (read-only); `Streamer.run_path` sends exactly these. scene: the
    obstacles they were checked against; verifier: the `FrameVerifier` that
    checked them (it checks an approach too). Only `admit` can construct it;
    `Streamer.run_path` streams nothing else.
    """

    path: SetpointPath
    robot: Robot
    actuators: Actuators
    source: str = ""
    time_scale: float = 1.0
    rate: float = 100.0
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    values: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    scene: Scene | None = field(default=None, repr=False)
    verifier: FrameVerifier | None = field(default=None, repr=False, compare=False)
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
    diff = robot_mismatch(device_robot, record.robot)
    if diff is not None:
        field, theirs, ours = diff
        return (
            f"robot: made for robot '{record.robot.name}' ({field} {theirs}), the device is robot "
            f"'{device_robot.name}' ({field} {ours}); a result for another robot is never sent: plan it again with "
            "the device's robot file"
        )
    return None


def admit(
    record: MotionRecord,
    actuators: Actuators,
    *,
    robot: Robot | None = None,
    time_scale: float = 1.0,
    rate: float = 100.0,
    verify: VerifyOptions | None = None,
) -> AdmittedMotion:
    """Admit a result's motion for a device, or refuse it with a one-line `AdmissionError`.

    actuators: the device's actuators (bound to its robot, or unbound: then
    bound to the result's robot). robot: the device's robot definition
    (default: the result's own, when the actuators come from the result's
    robot file). time_scale: play the motion this many times slower
    (0.001..1000). rate: the stream rate (Hz) the frames are verified at (the
    streamer's `StreamOptions.rate`). verify: how densely (`VerifyOptions`).
    Raises `InputError` for unreadable data (no actuation, a bad time scale),
    `AdmissionError` for a refusal.
    """
    check_time_scale(time_scale)
    where = f"{record.source}: " if record.source else ""
    why = _refusal(record, record.robot if robot is None else robot)
    if why is not None:
        raise AdmissionError(where + why)
    if record.q is None:
        raise InputError(f"{where}waypoints[0].q: missing (the actuation, mm, that a device is sent)")
    bound = actuators.for_robot(record.robot)
    if actuators.rest is not None and not same_actuators(bound, actuators):
        raise AdmissionError(f"{where}robot: the actuators are bound to another robot's cable lengths")
    if record.period is not None:
        base = SetpointPath.from_executed(float(record.t[0]), record.period, record.q, bound, where)
    else:
        base = SetpointPath.from_actuation(record.t, record.q, bound, where)
    path = base.scaled(time_scale) if time_scale != 1.0 else base
    stamps, values = path.sample(rate)
    scene = record.scene if record.scene is not None else Scene()  # (_refusal refused a scene-less result)
    verifier = FrameVerifier(record.robot, bound, scene, 1.0 / rate, verify)
    why = verifier.failure(stamps, values)
    if why is not None:
        slowed = f" slowed {time_scale:g} times" if time_scale != 1.0 else ""
        hint = ""
        if " velocity " in why or " acceleration " in why:
            scale = verifier.slowest_scale(base, rate)
            hint = f"; the motion is too fast for the actuators: try --time-scale {scale:.2f}" if scale else ""
        raise AdmissionError(f"{where}set-points{slowed} at {rate:g} Hz refused: {why}{hint}")
    for a in (stamps, values):
        a.setflags(write=False)
    return AdmittedMotion(
        path, record.robot, bound, record.source, float(time_scale), float(rate), stamps, values, scene, verifier, _SEAL
    )
