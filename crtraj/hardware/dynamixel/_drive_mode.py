"""Drive Mode (register 10) at connect: set what the robot file declares, refuse what it does not.

The ROBOTIS X-series e-manual defines two bits crtraj cares about:

- bit 0, direction of rotation: normal (0) counts counter-clockwise (seen from the front) as positive, reverse
  (1) clockwise. Goal Position, Present Position and Present Velocity all follow it, so a reversed servo is
  transparent to crtraj's values once the robot file's ``sign`` describes the values the servo reports;
- bit 2, profile configuration: velocity-based (0) or time-based (1), where Profile Velocity and Profile
  Acceleration become times in ms. crtraj does not support it
  (`crtraj.hardware.dynamixel._servo_bus.TIME_PROFILE_UNSUPPORTED`);
- bit 3, torque on by goal update: a goal written with the torque off turns it on and moves the servo, so a servo
  that shut down (or stopped with ``torque = "off"``) would not stay stopped. crtraj refuses it
  (`crtraj.hardware.dynamixel._servo_bus.TORQUE_ON_GOAL_UNSUPPORTED`).

`DriveModeCheck.refusal` reads every servo's register and names the first that carries a bit the robot file
does not declare (before anything is written); `apply` then sets the declared reverse bits (torque off:
register 10 is EEPROM) and clears the homed marker (LED, `crtraj.hardware.dynamixel._homing_state`) of every servo whose
bit it changed, since its reading flips with the bit: a spool is then unwrapped again and a multi-turn
actuator must be homed again before it streams.
"""

from __future__ import annotations

import logging

from crtraj.hardware.dynamixel._homing_state import ServoIO
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._servo_bus import TIME_PROFILE_UNSUPPORTED, TORQUE_ON_GOAL_UNSUPPORTED, ServoBus

log = logging.getLogger(__name__)


def _table(bus: ServoBus, k: int) -> str:
    """The robot-file table of actuator k."""
    name = bus.names[k]
    return "[robot.actuators.z]" if k == len(bus.ids) - 1 else f"[robot.actuators.servo.{name}]"


class DriveModeCheck:
    """Drive Mode of every servo of `bus` through `io` against the declarations (see the module doc)."""

    def __init__(self, io: ServoIO, bus: ServoBus) -> None:
        self.io, self.bus = io, bus
        self.modes = [io.read(i, X.DRIVE_MODE, 1) for i in bus.ids]
        self.changed: list[str] = []  # actuator names whose reverse bit `apply` set

    def refusal(self) -> str | None:
        """One line naming the first servo whose register carries a bit the robot file does not declare."""
        for k, dxl_id in enumerate(self.bus.ids):
            mode, who = self.modes[k], f"servo {self.bus.name_of(dxl_id)}"
            if mode & X.DRIVE_TIME_PROFILE:
                return (
                    f"{who}: Drive Mode 0x{mode:02x} has the time-based profile bit set; {TIME_PROFILE_UNSUPPORTED}: "
                    "clear bit 2 of register 10 (e.g. with Dynamixel Wizard)"
                )
            if mode & X.DRIVE_TORQUE_ON_GOAL:
                return (
                    f"{who}: Drive Mode 0x{mode:02x} has bit 3 (torque on by goal update) set; "
                    f"{TORQUE_ON_GOAL_UNSUPPORTED}: clear bit 3 of register 10 (e.g. with Dynamixel Wizard)"
                )
            if mode & X.DRIVE_REVERSE and not self.bus.drive_mode(k).reverse:
                return (
                    f"{who}: Drive Mode 0x{mode:02x} has the reverse bit set, which the robot file does not declare: "
                    f"add drive_mode = {{ reverse = true }} to {_table(self.bus, k)} (sign then describes the values "
                    "the reversed servo reports) or clear bit 0 of register 10"
                )
        return None

    def apply(self) -> None:
        """Set each declared reverse bit that is not set (torque must be off) and clear that servo's homed marker."""
        for k, dxl_id in enumerate(self.bus.ids):
            mode = self.modes[k]
            if self.bus.drive_mode(k).reverse and not mode & X.DRIVE_REVERSE:
                self.io.write(dxl_id, X.DRIVE_MODE, mode | X.DRIVE_REVERSE, 1, "drive mode (reverse bit)")
                self.io.write(dxl_id, X.LED, 0, 1, "homed marker (LED) cleared: the reading flipped")
                self.modes[k] = mode | X.DRIVE_REVERSE
                self.changed.append(self.bus.names[k])
                log.info("servo %s: Drive Mode reverse bit set (declared)", self.bus.name_of(dxl_id))
