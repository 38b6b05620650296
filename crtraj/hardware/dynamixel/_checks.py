"""Connect-time checks of a Dynamixel link (`crtraj.hardware.dynamixel._link`): without the bus, the USB-serial latency
timer, the bus rate and the actuators' position limits against the extended position range; on it (`ServoCheck`),
every id answering with its model number and no hardware error, and why none answers; then each servo's Drive Mode
against the robot file (`DriveModeCheck`).

Drive Mode (register 10) at connect: set what the robot file declares, refuse what it does not. The ROBOTIS
X-series e-manual defines three bits crtraj cares about:

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
register 10 is EEPROM) and clears the homed marker (LED, `crtraj.hardware.dynamixel._homing_state`) of every servo
whose bit it changed, since its reading flips with the bit: a spool is then unwrapped again and a multi-turn
actuator must be homed again before it streams.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._homing_state import ServoIO
from crtraj.hardware.dynamixel._protocol import BAUD_CODES, X, hardware_error_text
from crtraj.hardware.dynamixel._servo_bus import TIME_PROFILE_UNSUPPORTED, TORQUE_ON_GOAL_UNSUPPORTED, ServoBus
from crtraj.hardware.transport import TransportError

log = logging.getLogger(__name__)

SYSFS_USB_SERIAL = Path("/sys/bus/usb-serial/devices")
# the rates tried, in this order, when no servo answers at the requested one
PROBE_BAUDS = (1_000_000, 57_600, 115_200, 2_000_000, 3_000_000, 4_000_000, 9_600)


def latency_warning(device: str, sysfs: Path = SYSFS_USB_SERIAL) -> str | None:
    """The warning for a USB-serial latency timer above 1 ms (Linux), else None."""
    tty = os.path.basename(os.path.realpath(device))
    path = sysfs / tty / "latency_timer"
    try:
        ms = int(path.read_text().strip())
    except (OSError, ValueError):
        return None  # not a USB-serial adapter (or not Linux): nothing to say
    if ms <= 1:
        return None
    return (
        f"warning: {device}: the USB-serial latency timer is {ms} ms, which caps the set-point rate (every bus "
        f"read waits up to {ms} ms); lower it with: echo 1 | sudo tee {path}"
    )


def check_baud(baud: int) -> int:
    """`baud` when it is a Dynamixel bus rate; one-line `InputError` otherwise."""
    if baud not in BAUD_CODES.values():
        rates = ", ".join(str(b) for b in BAUD_CODES.values())
        raise InputError(f"--baud: {baud} is not a Dynamixel bus rate ({rates})")
    return baud


def check_ranges(actuators: Actuators, bus: ServoBus) -> None:
    """Every actuator's position limits must map into the extended position range (ticks)."""
    for i, name in enumerate(actuators.names):
        lim = np.abs(bus.ticks(np.array([actuators.lower, actuators.upper]))[:, i])
        if lim.max() > X.EXTENDED_LIMIT:
            u = actuators.units[i]
            raise InputError(
                f"robot.actuators ({name}): position limits [{actuators.lower[i]:g}, {actuators.upper[i]:g}] {u} "
                f"are up to {lim.max()} ticks, beyond the extended position range +-{X.EXTENDED_LIMIT}"
            )


def hardware_error_line(bus: ServoBus, dxl_id: int, bits: int) -> str:
    """One line for servo `dxl_id`'s hardware error status `bits`, and what to do."""
    return (
        f"servo {bus.name_of(dxl_id)}: hardware error: {hardware_error_text(bits)} (status 0x{bits:02x}); "
        "its torque is off: remove the cause, then reboot or power-cycle it"
    )


class ServoCheck:
    """The servos answering on a `crtraj.hardware.dynamixel._link.DynamixelTransport` being connected (`link`, through
    its SDK transactions: each tried a few times, serial errors mapped)."""

    def __init__(self, link: Any) -> None:
        self.link = link

    def run(self) -> None:
        """Every id answers with the robot file's model number and no hardware error; `TransportError` (one
        line) naming the first that does not."""
        link = self.link
        bus, ph = link.bus, link._ph
        models: dict[int, int] = {}
        for i in bus.ids:
            model, result, _ = link._ask(ph.ping, i)
            if result == link._sdk.COMM_SUCCESS:
                models[i] = model
        if not models:
            raise TransportError(self.no_answer())
        silent = [i for i in bus.ids if i not in models]
        if silent:
            answering = ", ".join(str(i) for i in models)
            raise TransportError(
                f"servo {bus.name_of(silent[0])} does not answer on {link.device} at {link.baud} baud (ids "
                f"{answering} do): check its id, its power and the daisy chain up to it"
            )
        for k, i in enumerate(bus.ids):
            if models[i] != bus.models[k]:
                raise TransportError(
                    f"servo {bus.name_of(i)} is model {models[i]}, the robot file says {bus.models[k]} "
                    f"(robot.actuators model): another servo than the robot file describes"
                )
        for i in bus.ids:
            bits, result, _ = link._ask(ph.read1ByteTxRx, i, X.HARDWARE_ERROR)
            if result != link._sdk.COMM_SUCCESS:
                raise TransportError(f"servo {bus.name_of(i)}: cannot read its hardware error status")
            if bits:
                raise TransportError(hardware_error_line(bus, i, bits))

    def no_answer(self) -> str:
        """Why no servo answered: another baud rate (tried and named), or no servo on the line at all."""
        link = self.link
        first = link.bus.ids[0]
        for b in PROBE_BAUDS:
            if b == link.baud:
                continue
            link._bus(link._set_baud, link._port, b)
            _, result, _ = link._ask(link._ph.ping, first)
            if result == link._sdk.COMM_SUCCESS:
                link._bus(link._set_baud, link._port, link.baud)
                return (
                    f"no servo answers on {link.device} at {link.baud} baud, but id {first} answers at {b} baud: "
                    f"pass --baud {b} (or set the servos' baud rate)"
                )
        link._bus(link._set_baud, link._port, link.baud)
        return (
            f"no servo answers on {link.device} (tried {link.baud} baud and the other common rates): check the "
            "servos' power supply and the data cable"
        )


# ------------------------------------------------------------------------------------------- drive mode
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
