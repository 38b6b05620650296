"""Homing: find each multi-turn actuator's absolute position and make its servo report it.

`Homer.run` first checks, with no motion, that every multi-turn actuator (see
`crtraj.hardware.dynamixel._homing_state.multi_turn`) has a ``[robot.homing.<name>]``
spec, then homes each spec'd actuator in bus order:

- ``hard_stop``: torque off, current-based position mode (operating mode 5)
  with the Goal Current of the spec, profile velocity at the spec's speed;
  the goal is ``travel`` past the present position toward ``direction``. The
  servo stalls at the mechanical stop: stalled = |Present Current| at least
  80 % of the Goal Current while the position moved less than
  ``stall_travel`` within ``stall_time`` (both read every `poll` s on the
  injected clock). No stall by the time the full travel should have been
  covered (twice its time at the spec speed, plus a second): torque off,
  `HomingError` naming the servo.
- ``index``: torque off; the operator moves the actuator to its mark by hand
  and confirms (`confirm`); no confirmation: `HomingError`.

At the reference the Homing Offset (register 20, EEPROM, torque off) becomes
``offset + (ticks(reference) - present)``, so the servo now reports the
reference; the reading is verified (within a tick of the reference and inside
the limits), the mode goes back to extended position (4) and the homed marker
(LED = 1) is set. Spools without a spec are unwrapped into their limits
(`PowerUpCheck`'s rule). `run` returns the `HomedServo` entries; the caller
writes the state file only when every servo succeeded.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np

from crtraj.core.clock import Clock
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._homing_spec import HomingSpec
from crtraj.hardware.dynamixel._homing_state import (
    HomedServo,
    HomingState,
    PowerUpCheck,
    ServoIO,
    identity,
    multi_turn,
    now_text,
)
from crtraj.hardware.dynamixel._protocol import X

log = logging.getLogger(__name__)

STALL_CURRENT = 0.8  # fraction of the Goal Current that counts as pressing the stop


class HomingError(InputError):
    """Homing failed (one line naming the servo); the state file is not written."""


class Homer:
    """Homes the servos of `acts.bus` through `io` (see the module doc). clock: paces the polling (s);
    confirm: asks the operator to confirm an index mark (the text to show) and returns whether they did."""

    def __init__(
        self,
        io: ServoIO,
        acts: Actuators,
        specs: dict[str, HomingSpec],
        clock: Clock,
        confirm: Callable[[str], bool],
        poll: float = 0.01,
    ) -> None:
        self.io, self.acts, self.specs, self.clock, self.confirm, self.poll = io, acts, specs, clock, confirm, poll
        self.bus = acts.bus

    def check(self) -> None:
        """Every multi-turn actuator has a homing spec (before anything moves)."""
        for k, name in enumerate(self.bus.names):
            if multi_turn(self.acts)[k] and name not in self.specs:
                raise HomingError(
                    f"robot.homing.{name}: missing: servo {self.bus.name_of(self.bus.ids[k])} spans a turn or more "
                    "and needs a homing method (hard_stop or index)"
                )

    def run(self) -> list[HomedServo]:
        """Home every spec'd servo and unwrap the others; the entries for the state file."""
        self.check()
        for i in self.bus.ids:
            self.io.write(i, X.TORQUE_ENABLE, 0, 1, "torque off")
        out = []
        for k, name in enumerate(self.bus.names):
            spec = self.specs.get(name)
            if spec is None:
                continue
            out.append(self._home(k, spec))
        # the spools without a spec: unwrapped into their limits (and marked), as at every connect
        PowerUpCheck(self.io, self.acts, HomingState(tuple(out))).run()
        return out

    def _home(self, k: int, spec: HomingSpec) -> HomedServo:
        """Home servo k to its reference; the state entry."""
        dxl_id = self.bus.ids[k]
        if spec.method == "hard_stop":
            self._press_stop(k, spec)
        elif not self.confirm(
            f"move {spec.name} (servo {self.bus.name_of(dxl_id)}) by hand to its mark at {spec.reference:g} "
            f"{self.acts.units[k]}, then confirm"
        ):
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: its index mark was never confirmed (robot.homing.{spec.name}); "
                "nothing written"
            )
        offset = self._set_offset(k, spec)
        self.io.write(dxl_id, X.OPERATING_MODE, X.EXTENDED_POSITION, 1, "extended position mode")
        self.io.write(dxl_id, X.LED, 1, 1, "homed marker (LED)")
        log.info("homed %s: homing offset %d ticks", self.bus.name_of(dxl_id), offset)
        model, info, firmware = identity(self.io, dxl_id)
        last = self.io.read(dxl_id, X.PRESENT_POSITION, 4)  # where it is let go (`PowerUpCheck` checks it)
        return HomedServo(dxl_id, spec.name, model, offset, spec.method, now_text(), info, firmware, last)

    def _set_offset(self, k: int, spec: HomingSpec) -> int:
        """Write the Homing Offset that makes servo k read its reference, and verify the reading."""
        dxl_id, res = self.bus.ids[k], float(self.bus.resolution[k])
        want = int(np.rint(spec.reference / res))
        present = self.io.read(dxl_id, X.PRESENT_POSITION, 4)
        offset = self.io.read(dxl_id, X.HOMING_OFFSET, 4) + (want - present)
        if abs(offset) > X.HOMING_OFFSET_LIMIT:
            raise HomingError(f"servo {self.bus.name_of(dxl_id)}: homing offset {offset} ticks is out of range")
        self.io.write(dxl_id, X.HOMING_OFFSET, offset & 0xFFFFFFFF, 4, "homing offset")
        got = self.io.read(dxl_id, X.PRESENT_POSITION, 4) * res
        lo, hi, unit = float(self.acts.lower[k]), float(self.acts.upper[k]), self.acts.units[k]
        if abs(got - spec.reference) > 1.5 * res or not lo - res <= got <= hi + res:
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: reads {got:.4g} {unit} after homing, not its reference "
                f"{spec.reference:g} {unit} within [{lo:g}, {hi:g}] {unit}; nothing written"
            )
        return offset

    def _press_stop(self, k: int, spec: HomingSpec) -> None:
        """Current-limited move toward the stop until it stalls; torque off after it (or on failure)."""
        io, dxl_id = self.io, self.bus.ids[k]
        rev, res = float(self.bus.per_rev[k]), float(self.bus.resolution[k])
        goal_current = max(1, round(spec.current / X.CURRENT_UNIT))
        io.write(dxl_id, X.OPERATING_MODE, X.CURRENT_POSITION, 1, "current-based position mode")
        io.write(dxl_id, X.GOAL_CURRENT, goal_current, 2, "goal current")
        io.write(dxl_id, X.PROFILE_VELOCITY, max(1, math.floor(spec.speed / rev * 60.0 / X.VELOCITY_UNIT)), 4, "speed")
        acc = math.ceil(float(self.acts.amax[k]) / rev * 3600.0 / X.ACCELERATION_UNIT)
        io.write(dxl_id, X.PROFILE_ACCELERATION, acc, 4, "profile acceleration")
        start = io.read(dxl_id, X.PRESENT_POSITION, 4)
        goal = start + spec.direction * int(np.rint(spec.travel / res))
        io.write(dxl_id, X.TORQUE_ENABLE, 1, 1, "torque on")
        io.write(dxl_id, X.GOAL_POSITION, goal & 0xFFFFFFFF, 4, "goal position")
        try:
            self._wait_stall(k, spec, goal_current)
        finally:
            io.write(dxl_id, X.TORQUE_ENABLE, 0, 1, "torque off")

    def _wait_stall(self, k: int, spec: HomingSpec, goal_current: int) -> None:
        """Poll until stalled at the stop; `HomingError` when the travel's time passes without a stall."""
        io, dxl_id, res = self.io, self.bus.ids[k], float(self.bus.resolution[k])
        t0 = self.clock.now()
        deadline = t0 + 2.0 * spec.travel / spec.speed + 1.0
        window: list[tuple[float, int]] = []
        while self.clock.now() < deadline:
            self.clock.sleep(self.poll)
            now, pos = self.clock.now(), io.read(dxl_id, X.PRESENT_POSITION, 4)
            current = io.read(dxl_id, X.PRESENT_CURRENT, 2)
            window.append((now, pos))
            while len(window) > 1 and now - window[1][0] >= spec.stall_time:
                window.pop(0)  # keep the readings of the last stall_time s, and one just before
            held = now - window[0][0] >= spec.stall_time
            still = max(p for _, p in window) - min(p for _, p in window) <= spec.stall_travel / res
            if spec.direction * current >= STALL_CURRENT * goal_current and held and still:
                return
        unit = self.acts.units[k]
        raise HomingError(
            f"servo {self.bus.name_of(dxl_id)}: no stall within {spec.travel:g} {unit} of travel toward "
            f"direction {spec.direction:+d} (robot.homing.{spec.name}): no mechanical stop found; nothing written"
        )
