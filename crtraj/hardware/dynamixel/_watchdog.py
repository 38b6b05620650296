"""The servos' Bus Watchdog (register 98) at connect: set for the whole session, and a servo it stopped last time.

ROBOTIS e-manual, Bus Watchdog: with the torque on, a servo that hears no instruction packet for longer than
the register's value (1..127, 20 ms units) stops, and the register reads -1 until 0 is written; meanwhile its
goal values are read-only. crtraj sets it on every servo right after the connect checks, so homing and
streaming are both guarded: a host that dies (SIGKILL, a crash, a frozen machine) leaves no servo running.
A servo found stopped by it was left mid-motion by a host that died: its error is cleared and its homed
marker too, so a multi-turn actuator must be homed again before it streams (`refuse_tripped`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from crtraj.core.errors import InputError
from crtraj.hardware.dynamixel._homing_state import ServoIO
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._servo_bus import ServoBus


def watchdog_units(seconds: float) -> int:
    """Bus Watchdog register units (20 ms) of `seconds`; one-line `InputError` outside 0.02..2.54 s."""
    units = round(float(seconds) / X.WATCHDOG_UNIT) if math.isfinite(float(seconds)) else 0
    if not 1 <= units <= 127:
        raise InputError(f"robot.stop.bus_watchdog: must be 0.02..2.54 s (20 ms steps), got {seconds}")
    return units


class BusWatchdog:
    """Sets the Bus Watchdog of the servos of `bus` through `io` to `units` (20 ms each)."""

    def __init__(self, io: ServoIO, bus: ServoBus, units: int) -> None:
        self.io, self.bus, self.units = io, bus, int(units)

    def start(self) -> list[int]:
        """Set every servo's watchdog; the ids it had stopped (it read -1), their error (0 first, as the
        e-manual asks) and homed marker cleared: a servo that stopped on its own is not trusted where it
        stopped until it is homed again."""
        tripped = []
        for i in self.bus.ids:
            if self.io.read(i, X.BUS_WATCHDOG, 1) & 0xFF == X.WATCHDOG_TRIPPED:
                tripped.append(i)
                self.io.write(i, X.BUS_WATCHDOG, 0, 1, "bus watchdog (clearing its error)")
                self.io.write(i, X.LED, 0, 1, "homed marker (LED)")
            self.io.write(i, X.BUS_WATCHDOG, self.units, 1, "bus watchdog")
        return tripped

    def refuse_tripped(self, tripped: Sequence[int], multi_turn: Sequence[bool], command: str) -> None:
        """One line for the first multi-turn servo (`multi_turn[k]`) its watchdog had stopped; a spool is
        unwrapped by the power-up check as after a power-up."""
        for i in tripped:
            if multi_turn[self.bus.ids.index(i)]:
                raise InputError(
                    f"servo {self.bus.name_of(i)}: its bus watchdog stopped it (the last session's host went "
                    f"silent mid-motion), so its position is not proven; run {command}"
                )
