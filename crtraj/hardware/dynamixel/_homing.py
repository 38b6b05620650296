"""Homing: find each multi-turn actuator's absolute position and make its servo report it.

`Homer.run` first checks, with no motion, that every multi-turn actuator (see
`crtraj.hardware.dynamixel._homing_state.multi_turn`) has a ``[robot.homing.<name>]``
spec, then homes each spec'd actuator in bus order:

- ``hard_stop``: torque off, current-based position mode (operating mode 5)
  with the Goal Current of the spec (at most the servo's force cap, `crtraj.hardware.dynamixel._safety`: the
  stop is never pressed harder than the robot file allows), profile velocity at the spec's speed;
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
``offset + (ticks(reference) - present)``, ``present`` read while the servo still presses the stop (after
torque-off the shaft springs back by an amount friction decides; under the homing current the stop is where it
was last time). A jam is told from the stop by the turn's phase: a mechanical stop sits at the same place
within a turn every time, so when the state file has this servo's last ``hard_stop`` homing, the new offset must
equal the old one modulo one turn within ``stall_travel`` (a jam elsewhere: `HomingError`, nothing written).
The reading after the offset is verified (the offset's change exactly, near the reference and inside
the limits), the mode goes back to extended position (4) and the homed marker (LED = 1) is set. Spools without
a spec are unwrapped into their limits (`PowerUpCheck`'s rule). `run` returns the `HomedServo` entries; the caller
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
from crtraj.hardware.dynamixel._safety import ForceCaps

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
        previous: HomingState | None = None,
    ) -> None:
        self.io, self.acts, self.specs, self.clock, self.confirm, self.poll = io, acts, specs, clock, confirm, poll
        self.bus = acts.bus
        self.previous = previous or HomingState()  # the last homing of each servo (the state file), for the phase
        self.caps = ForceCaps(acts)

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
        pressed = None
        if spec.method == "hard_stop":
            pressed = self._press_stop(k, spec)
        elif not self.confirm(
            f"move {spec.name} (servo {self.bus.name_of(dxl_id)}) by hand to its mark at {spec.reference:g} "
            f"{self.acts.units[k]}, then confirm"
        ):
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: its index mark was never confirmed (robot.homing.{spec.name}); "
                "nothing written"
            )
        offset = self._set_offset(k, spec, pressed)
        self.io.write(dxl_id, X.OPERATING_MODE, X.EXTENDED_POSITION, 1, "extended position mode")
        self.io.write(dxl_id, X.LED, 1, 1, "homed marker (LED)")
        log.info("homed %s: homing offset %d ticks", self.bus.name_of(dxl_id), offset)
        model, info, firmware = identity(self.io, dxl_id)
        last = self.io.read(dxl_id, X.PRESENT_POSITION, 4)  # where it is let go (`PowerUpCheck` checks it)
        return HomedServo(dxl_id, spec.name, model, offset, spec.method, now_text(), info, firmware, last)

    def _set_offset(self, k: int, spec: HomingSpec, pressed: int | None) -> int:
        """Write the Homing Offset that makes servo k read its reference where it read `pressed` (ticks, at the
        stop under the homing current; None: where it is now), and verify the reading."""
        dxl_id, res = self.bus.ids[k], float(self.bus.resolution[k])
        want = int(np.rint(spec.reference / res))
        before = self.io.read(dxl_id, X.PRESENT_POSITION, 4)
        old = self.io.read(dxl_id, X.HOMING_OFFSET, 4)
        offset = old + (want - (before if pressed is None else pressed))
        if abs(offset) > X.HOMING_OFFSET_LIMIT:
            raise HomingError(f"servo {self.bus.name_of(dxl_id)}: homing offset {offset} ticks is out of range")
        if pressed is not None:
            self._check_phase(k, spec, offset)
        self.io.write(dxl_id, X.HOMING_OFFSET, offset & 0xFFFFFFFF, 4, "homing offset")
        raw = self.io.read(dxl_id, X.PRESENT_POSITION, 4)
        got = raw * res
        lo, hi, unit = float(self.acts.lower[k]), float(self.acts.upper[k]), self.acts.units[k]
        slack = 1.5 * res + (spec.stall_travel if pressed is not None else 0.0)  # spring-back off the stop
        moved = abs(raw - (before + offset - old)) > 1  # the offset did not shift the reading by its change
        if moved or abs(got - spec.reference) > slack or not lo - slack <= got <= hi + slack:
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: reads {got:.4g} {unit} after homing, not its reference "
                f"{spec.reference:g} {unit} within [{lo:g}, {hi:g}] {unit}; nothing written"
            )
        return offset

    def _check_phase(self, k: int, spec: HomingSpec, offset: int) -> None:
        """A jam is not the stop: with a last ``hard_stop`` homing of servo k in the state file, `offset` must equal
        its offset modulo one turn within ``stall_travel``; `HomingError` naming the servo otherwise."""
        dxl_id, tpr = self.bus.ids[k], int(self.bus.ticks_per_rev[k])
        last = next((s for s in self.previous.servos if s.id == dxl_id and s.method == "hard_stop"), None)
        if last is None:
            return
        d = (offset - last.offset + tpr // 2) % tpr - tpr // 2
        if abs(d) * float(self.bus.resolution[k]) > spec.stall_travel:
            unit = self.acts.units[k]
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: stalled {d * float(self.bus.resolution[k]):+.3g} {unit} "
                f"(modulo one turn) from where its stop was at the last homing: a jam, not the stop? clear it and "
                f"home again (robot.homing.{spec.name}.stall_travel is the tolerance); nothing written"
            )

    def _refuse_tripped(self, k: int) -> None:
        """`HomingError` when servo k stands still because its Bus Watchdog stopped it: the host was silent longer
        than the watchdog (a loaded machine), so the move ended short of the stop; without this the wait would go on
        to its deadline and blame a missing stop."""
        dxl_id = self.bus.ids[k]
        if self.io.read(dxl_id, X.BUS_WATCHDOG, 1) & 0xFF == X.WATCHDOG_TRIPPED:
            raise HomingError(
                f"servo {self.bus.name_of(dxl_id)}: its bus watchdog stopped it while homing (the host sent no "
                "instruction in time): check the host's load, then home again; nothing written"
            )

    def _goal_current(self, k: int, spec: HomingSpec) -> int:
        """Goal Current units of servo k's stall: the spec's, refused above the servo's force cap."""
        goal = max(1, round(spec.current / X.CURRENT_UNIT))
        cap = int(self.caps.goal[k])
        if cap and goal > cap:
            key = "max_force" if k == len(self.bus.ids) - 1 else "max_tension"
            raise HomingError(
                f"robot.homing.{spec.name}.current: {spec.current:g} mA presses with "
                f"{self.caps.tension(k, goal):.1f} N, above its {key} {self.caps.force[k]:g} N "
                f"({cap * X.CURRENT_UNIT:.0f} mA): lower it"
            )
        return goal

    def _press_stop(self, k: int, spec: HomingSpec) -> int:
        """Current-limited move toward the stop until it stalls; the reading (ticks) while it still presses the
        stop; torque off after it (or on failure)."""
        io, dxl_id = self.io, self.bus.ids[k]
        rev, res = float(self.bus.per_rev[k]), float(self.bus.resolution[k])
        goal_current = self._goal_current(k, spec)
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
            return io.read(dxl_id, X.PRESENT_POSITION, 4)  # still pressing: no spring-back in it
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
            if held and still:
                self._refuse_tripped(k)
        unit = self.acts.units[k]
        raise HomingError(
            f"servo {self.bus.name_of(dxl_id)}: no stall within {spec.travel:g} {unit} of travel toward "
            f"direction {spec.direction:+d} (robot.homing.{spec.name}): no mechanical stop found; nothing written"
        )
