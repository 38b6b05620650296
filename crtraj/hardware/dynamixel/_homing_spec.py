"""The robot file's ``[robot.homing]`` and ``[robot.stop]`` sections, read and checked.

``[robot.homing.<actuator>]`` (an actuator name: ``z``, ``s1c1``, ...) says how
that actuator finds its absolute position after a power-up:

- ``method = "hard_stop"``: a current-limited move (current-based position
  mode) toward ``direction`` (-1 or +1) at ``speed`` (rad/s or mm/s) until the
  shaft stalls against the mechanical stop: the present current reaches
  ``current`` (mA) while the position moves less than ``stall_travel``
  (rad or mm) for ``stall_time`` s. A servo that has not stalled after
  ``travel`` (default: the width of its position limits plus 10 %) stops and
  is reported; nothing is written.
- ``method = "index"``: a known absolute reference, e.g. a mark the operator
  moves the actuator to by hand (torque off) and confirms.

``reference`` is the actuator's value (rad or mm, as in ``[robot.actuators]``)
at the stop or mark; it must lie within the actuator's position limits.

``[robot.stop]`` says what happens after a stop (e-stop, hold or the end of
a stream): ``torque = "keep"`` (default: the servos hold the braked pose, the
cables stay taut, a lead-screw stage cannot back-drive) or ``"off"``; and
``bus_watchdog`` (s, default 0.1, 0.02..2.54 in 20 ms steps): a servo that hears
no instruction for longer stops on its own with its profile (its Bus Watchdog,
register 98), so a host that dies mid-motion leaves no servo running.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.hardware.actuators import Actuators

METHODS = ("hard_stop", "index")
MAX_CURRENT = 10_000.0  # mA: above any X-series servo's limit


@dataclass(frozen=True)
class HomingSpec:
    """How one actuator is homed. Units: the actuator's (rad for a spool, mm for the stage), s, mA."""

    name: str
    method: str
    reference: float
    direction: int = -1
    speed: float = 0.0
    current: float = 200.0
    travel: float = 0.0
    stall_time: float = 0.2
    stall_travel: float = 0.0


@dataclass(frozen=True)
class StopSpec:
    """torque: "keep" (hold the braked pose) or "off" after a stop. bus_watchdog: s without an instruction
    after which each servo stops on its own (its Bus Watchdog, 20 ms steps, 0.02..2.54 s)."""

    torque: str = "keep"
    bus_watchdog: float = 0.1


def read_homing(robot: Any, actuators: Actuators) -> MappingProxyType[str, HomingSpec]:
    """The ``[robot.homing]`` specs by actuator name (empty without the section); one-line `InputError`
    naming the field otherwise."""
    if getattr(robot, "homing", None) is None:
        return MappingProxyType({})
    top = Table(robot.homing, "robot.homing")
    out: dict[str, HomingSpec] = {}
    for name in top.keys():
        if name not in actuators.names:
            raise top.error(name, f"not an actuator (one of {', '.join(actuators.names)})")
        out[name] = _read_one(top.table(name), name, actuators)
    top.finish()
    return MappingProxyType(out)


def _read_one(t: Table, name: str, acts: Actuators) -> HomingSpec:
    """One ``[robot.homing.<name>]`` table, checked against the actuator's limits."""
    i = acts.index(name)
    lo, hi, unit = float(acts.lower[i]), float(acts.upper[i]), acts.units[i]
    method = t.str("method", choices=METHODS)
    ref = t.float("reference", limit=MAX_LENGTH)
    if not lo <= ref <= hi:
        raise t.error("reference", f"{ref:g} {unit} is outside the position limits [{lo:g}, {hi:g}] {unit}")
    width = hi - lo
    spec = HomingSpec(
        name=name,
        method=method,
        reference=ref,
        direction=t.int("direction", -1, ge=-1, le=1),
        speed=t.float("speed", 0.1 * float(acts.vmax[i]), gt=0.0, le=float(acts.vmax[i])),
        current=t.float("current", 200.0, gt=0.0, le=MAX_CURRENT),
        travel=t.float("travel", 1.1 * width, gt=0.0, limit=MAX_LENGTH),
        stall_time=t.float("stall_time", 0.2, gt=0.0, le=10.0),
        stall_travel=t.float("stall_travel", 0.002 * max(width, 1.0), gt=0.0, limit=MAX_LENGTH),
    )
    if spec.direction == 0:
        raise t.error("direction", "must be -1 or +1 (the side of the stop)")
    t.finish()
    return spec


def read_stop(robot: Any) -> StopSpec:
    """The ``[robot.stop]`` section (defaults without it); one-line `InputError` naming the field otherwise."""
    if getattr(robot, "stop", None) is None:
        return StopSpec()
    t = Table(robot.stop, "robot.stop")
    torque = t.str("torque", "keep", choices=("keep", "off"))
    watchdog = t.float("bus_watchdog", 0.1, ge=0.02, le=2.54)
    t.finish()
    return StopSpec(torque=torque, bus_watchdog=watchdog)
