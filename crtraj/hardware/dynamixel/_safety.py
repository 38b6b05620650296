"""What keeps Dynamixel servos safe when things go wrong: tendon force caps, the trips of a stream, and the Bus
Watchdog.

Cap. The ROBOTIS X-series e-manual: Current Limit (38) acts only in current control and current-based position
control (Operating Mode 5); in extended position control (mode 4) only PWM Limit (36) caps the output, so a
jammed spool pulls at up to the stall torque. A Dynamixel stream therefore runs every servo with a declared cap
in mode 5, its Goal Current (102, 2.69 mA units, at most Current Limit) at::

    I = F r / k_t        F: max_tension (N), r: spool radius (m; lead / 2 pi for the stage),
                         k_t: torque constant (N*m/A, output shaft)

rounded down, so the servo never pulls harder than the declared tension (to within the current loop's
accuracy). ``k_t`` is the robot file's ``torque_constant`` or the model's stall torque over stall current at
12 V from the e-manual (`TORQUE_CONSTANTS`). A cable servo without ``max_tension`` is refused: crtraj does not
guess a tendon's strength. A stage without ``max_force`` keeps extended position mode (its PWM Limit caps it).

Connect (`ForceCaps.apply`, torque off) also sets, each written only when it differs and read back: Shutdown (63)
to overload, electrical shock, overheating and input voltage (the factory default leaves out input voltage);
PWM Limit (36) to 100 % (a lower value another tool left would slow the servo below its plan, and in mode 5 the
current, not the PWM, is the cap; in mode 4 it is the only cap, at the full stall torque); and a capped servo's
Current Limit (38) to its cap, so that no Goal Current written later (homing, another tool) exceeds it. It
reads back the Temperature Limit (31) and the voltage limits (32, 34) the trips compare with.

Trips (`ForceCaps.trip`, on every sync read of the stream; times are the stream's periods): a reading beyond a
bound latches the stream's verified stop (braking within the limits, then holding; in mode 5 the hold keeps the
tension at most the cap), and the report names the servo, the reading and the status:

- ``over-tension``: |Present Current| at least `AT_CAP` of the Goal Current (the servo is at its cap: a jammed
  spool, or a plan the tendons cannot follow);
- ``slack``: |Present Current| below ``min_tension``'s current while the torque is on (a cut or slipped tendon);
- ``over-temperature``: Present Temperature within `TEMPERATURE_MARGIN` deg C of Temperature Limit (the servo
  shuts itself down at the limit);
- ``under-voltage`` / ``over-voltage``: Present Input Voltage within `VOLTAGE_MARGIN` V of Min / Max Voltage Limit.

Bus Watchdog (`BusWatchdog`): set at connect for the whole session; a servo it stopped last time.

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
from dataclasses import dataclass
from types import MappingProxyType
from typing import Protocol

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._homing_state import ServoIO
from crtraj.hardware.dynamixel._protocol import HW_INPUT_VOLTAGE, HW_OVERHEATING, HW_OVERLOAD, HW_SHOCK, X
from crtraj.hardware.dynamixel._servo_bus import ServoBus
from crtraj.hardware.transport import TransportError

# N*m/A at the output: stall torque / stall current at 12 V (ROBOTIS e-manual, each model's specifications)
TORQUE_CONSTANTS = MappingProxyType(
    {
        1020: 4.1 / 2.3,  # XM430-W350
        1030: 3.0 / 2.3,  # XM430-W210
        1120: 10.6 / 4.4,  # XM540-W270
        1130: 7.3 / 4.4,  # XM540-W150
    }
)
SHUTDOWN = HW_OVERLOAD | HW_SHOCK | HW_OVERHEATING | HW_INPUT_VOLTAGE  # 0x35: the factory 0x34 plus input voltage
PWM_LIMIT = X.PWM_LIMIT_DEFAULT  # 885 = 100 %: in mode 5 the current is the cap, a lower PWM only slows the servo
AT_CAP = 0.95  # |Present Current| / Goal Current that counts as pulling at the cap
TEMPERATURE_MARGIN = 5  # deg C below Temperature Limit
VOLTAGE_MARGIN = 0.5  # V inside the voltage limits


class RegisterIO(Protocol):
    """Register access of one bus (`crtraj.hardware.dynamixel._homing_state.ServoIO`)."""

    def read(self, dxl_id: int, addr: int, size: int) -> int: ...

    def write(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None: ...


@dataclass(frozen=True)
class Reading:
    """One servo's sync-read fields: Present Current (2.69 mA units, signed), Input Voltage (0.1 V),
    Temperature (deg C)."""

    current: int
    voltage: int
    temperature: int


class ForceCaps:
    """The Goal Current of each servo of `acts.bus` from its declared force, and the trips (see the module doc).

    goal: (n,) Goal Current units, 0 for a servo without a cap (extended position mode); floor: (n,) the least
    |Present Current| (units) of a taut tendon, 0: no slack check. radius: (n,) m from force to torque.
    """

    def __init__(self, acts: Actuators) -> None:
        bus = acts.bus
        self.bus = bus
        n = len(bus.ids)
        self.radius = np.array([r / 1000.0 for r in acts.spool_radius] + [bus.per_rev[-1] / (2 * math.pi) / 1000.0])
        self.kt = np.array([self._kt(k) or math.nan for k in range(n)])
        forces = [bus.max_force[k] if bus.max_force else None for k in range(n)]
        self.force = np.array([math.nan if f is None else float(f) for f in forces])
        amps = self.force * self.radius / self.kt
        self.goal = np.where(np.isfinite(amps), np.floor(amps * 1000.0 / X.CURRENT_UNIT), 0).astype(int)
        lows = np.array([bus.min_force[k] if bus.min_force else 0.0 for k in range(n)])
        self.floor = np.where(np.isfinite(self.kt), np.ceil(lows * self.radius / self.kt * 1000 / X.CURRENT_UNIT), 0)
        self.floor = self.floor.astype(int)
        self.limits: dict[int, tuple[int, int, int]] = {}  # id: (temperature limit, min, max voltage) read back

    def _kt(self, k: int) -> float | None:
        declared = self.bus.torque_constant[k] if self.bus.torque_constant else None
        return declared if declared is not None else TORQUE_CONSTANTS.get(self.bus.models[k])

    def refusal(self) -> str | None:
        """Why these servos cannot stream with capped force (one line naming the field), or None."""
        bus = self.bus
        for k, name in enumerate(bus.names):
            stage = k == len(bus.ids) - 1
            where = "robot.actuators.z" if stage else f"robot.actuators.servo.{name}"
            if stage and math.isnan(self.force[k]):
                continue
            if math.isnan(self.force[k]):
                return (
                    f"{where}.max_tension: missing: the largest tension (N) servo {bus.name_of(bus.ids[k])} may pull "
                    "its tendon with (the Goal Current of current-based position mode); set it once in "
                    "[robot.actuators] or per servo"
                )
            if math.isnan(self.kt[k]):
                return (
                    f"{where}.torque_constant: missing: model {bus.models[k]} is not one crtraj knows "
                    f"({', '.join(map(str, TORQUE_CONSTANTS))}); give its output torque per ampere (N*m/A)"
                )
            if self.goal[k] < 1:
                key = "max_force" if stage else "max_tension"
                return f"{where}.{key}: {self.force[k]:g} N is below one unit (2.69 mA) of the servo's current"
        return None

    def tension(self, k: int, units: float) -> float:
        """The force (N) of servo k at `units` of current (2.69 mA)."""
        return float(units) * X.CURRENT_UNIT / 1000.0 * self.kt[k] / self.radius[k]

    # ------------------------------------------------------------- connect
    def apply(self, io: RegisterIO) -> None:
        """With the torque off, on every servo: Shutdown (63), PWM Limit (36) and, for a capped servo, Current
        Limit (38) = Goal Current (102) = its cap in current-based position mode (others: extended position mode),
        each written only when it differs (EEPROM wears) and read back; then the Temperature and voltage limits
        (31, 32, 34) the trips compare with. `TransportError` (one line) for a cap the servo refuses (above its
        model's largest Current Limit) or a register that does not read back what was written."""
        bus = self.bus
        for k, i in enumerate(bus.ids):
            ensure(io, bus, i, X.SHUTDOWN, SHUTDOWN, 1, "shutdown conditions")
            ensure(io, bus, i, X.PWM_LIMIT, PWM_LIMIT, 2, "PWM limit")
            self.limits[i] = (
                io.read(i, X.TEMPERATURE_LIMIT, 1),
                io.read(i, X.MIN_VOLTAGE, 2),
                io.read(i, X.MAX_VOLTAGE, 2),
            )
            if not self.goal[k]:
                io.write(i, X.OPERATING_MODE, X.EXTENDED_POSITION, 1, "extended position mode")
                continue
            try:
                ensure(io, bus, i, X.CURRENT_LIMIT, int(self.goal[k]), 2, "current limit")
            except TransportError:
                raise TransportError(
                    f"servo {bus.name_of(i)}: max tension {self.force[k]:g} N needs {self.goal[k] * X.CURRENT_UNIT:.0f}"
                    " mA, above the largest Current Limit its model takes: lower it in the robot file"
                ) from None
            io.write(i, X.OPERATING_MODE, X.CURRENT_POSITION, 1, "current-based position mode")
            io.write(i, X.GOAL_CURRENT, int(self.goal[k]), 2, "goal current")

    # --------------------------------------------------------------- trips
    def trip(self, k: int, r: Reading) -> tuple[str, str] | None:
        """(status, one line) when servo k's reading `r` is beyond a bound (see the module doc), else None."""
        bus, i = self.bus, self.bus.ids[k]
        who = f"servo {bus.name_of(i)}"
        goal = int(self.goal[k])
        if goal and abs(r.current) >= AT_CAP * goal:
            return "over-tension", (
                f"{who}: pulls {self.tension(k, abs(r.current)):.1f} N ({abs(r.current) * X.CURRENT_UNIT:.0f} mA), "
                f"at its cap of {self.force[k]:g} N: a jammed spool or a plan the tendons cannot follow; stopped"
            )
        if self.floor[k] and abs(r.current) < self.floor[k]:
            return "slack", (
                f"{who}: its tendon pulls {self.tension(k, abs(r.current)):.1f} N, below min_tension "
                f"{bus.min_force[k]:g} N: a cut or slipped tendon; stopped"
            )
        t_lim, v_lo, v_hi = self.limits.get(i, (255, 0, 0xFFFF))
        if r.temperature >= t_lim - TEMPERATURE_MARGIN:
            return "over-temperature", (
                f"{who}: {r.temperature} deg C, within {TEMPERATURE_MARGIN} of its Temperature Limit {t_lim} deg C; "
                "stopped: let it cool"
            )
        margin = VOLTAGE_MARGIN * 10
        if r.voltage <= v_lo + margin or r.voltage >= v_hi - margin:
            what = "under-voltage" if r.voltage <= v_lo + margin else "over-voltage"
            return what, (
                f"{who}: input {r.voltage / 10:.1f} V, within {VOLTAGE_MARGIN:g} V of its limits "
                f"[{v_lo / 10:.1f}, {v_hi / 10:.1f}] V; stopped: check the power supply"
            )
        return None


class TripWatch:
    """The first trip of a stream (`ForceCaps.trip`) and each servo's last reading, fed by every sync read."""

    def __init__(self, caps: ForceCaps) -> None:
        self.caps = caps
        self.first: tuple[str, str] | None = None  # (status, one line) of the first reading beyond a bound
        self.readings: list[Reading | None] = [None] * len(caps.bus.ids)

    def see(self, k: int, current: int, voltage: int, temperature: int) -> None:
        """Servo k's raw fields (Present Current as the unsigned 16 bits read); keeps the first trip."""
        r = Reading(current - (1 << 16) if current >= 1 << 15 else current, voltage, temperature)
        self.readings[k] = r
        if self.first is None:
            self.first = self.caps.trip(k, r)


def ensure(io: RegisterIO, bus: ServoBus, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
    """Register `addr` of servo `dxl_id` = `value`: written only when it reads otherwise (an EEPROM register wears
    with every write), then read back; `TransportError` naming `what` when the servo keeps another value."""
    mask = (1 << (8 * size)) - 1
    if io.read(dxl_id, addr, size) & mask == value & mask:
        return
    io.write(dxl_id, addr, value, size, what)
    got = io.read(dxl_id, addr, size) & mask
    if got != value & mask:
        raise TransportError(f"servo {bus.name_of(dxl_id)}: {what} reads {got} after writing {value}")


# ------------------------------------------------------------------ the Bus Watchdog
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
