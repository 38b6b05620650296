"""What a simulated Dynamixel's shaft carries (its tendon, a jam, a yielding stop), the current its motor draws
for them, and the faults a test injects into a simulated chain (`crtraj.hardware.dynamixel.ServoChain` mixes
`ChainFaults` in).

The current model of `crtraj.hardware.dynamixel.ServoChain`, from the ROBOTIS X-series e-manual:

- the output is capped by the operating mode: in current-based position control (mode 5) by Goal Current (102),
  itself at most Current Limit (38); in position and extended position control (modes 3, 4) only by PWM Limit
  (36), i.e. at up to the stall current scaled by PWM Limit / 885 (`STALL_CURRENT`: 2.3 A, the XM430's at 12 V);
- a shaft that follows its reference draws its tendon's current (`load`, signed 2.69 mA units; friction and
  inertia are not modelled); a shaft that cannot follow (pressing a mechanical stop, or jammed) draws its load
  plus the position loop's output K_P (reference - position), K_P = Position P Gain (84) / 128 units per tick,
  saturated at the mode's cap.

A mechanical stop is stiff but not rigid (`compliance`, ticks per current unit, default 0): pressed with the torque
on, the shaft goes past the stop's surface by compliance x the mode's cap (a stall is at the cap), and springs
back to the surface when the torque goes off.

Faults: `jam` holds a shaft where it is (a spool jammed: position stalls, current rises to the cap); `cut`
drops a tendon's load to 0 (the current collapses).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._protocol import X

STALL_CURRENT = 855  # 2.69 mA units: 2.3 A, the XM430 stall current at 12 V (e-manual)
P_GAIN_DEFAULT = 800  # Position P Gain (84), XM430 factory value


def mode_cap(t: bytearray) -> int:
    """The most current (units) the servo with control table `t` can draw in its operating mode."""
    if t[X.OPERATING_MODE] in (X.CURRENT_POSITION, 0):
        goal, limit = struct.unpack_from("<H", t, X.GOAL_CURRENT)[0], struct.unpack_from("<H", t, X.CURRENT_LIMIT)[0]
        return min(goal, limit)
    (pwm,) = struct.unpack_from("<H", t, X.PWM_LIMIT)
    return int(STALL_CURRENT * min(pwm, X.PWM_LIMIT_DEFAULT) / X.PWM_LIMIT_DEFAULT)


class ShaftLoads:
    """The tendons and jams of n shafts (see the module doc). Positions in the servos' reported ticks."""

    def __init__(self, n: int) -> None:
        self.load = np.zeros(n)  # signed 2.69 mA units drawn to hold each tendon
        self.jammed = np.full(n, np.nan)  # reported ticks a jammed shaft is held at (nan: free)
        self.compliance = np.zeros(n)  # ticks per current unit a pressed stop yields

    def give(self, tables: list[bytearray]) -> np.ndarray:
        """(n,) ticks each shaft may pass its stops by: compliance x its mode's cap while the torque is on."""
        if not self.compliance.any():
            return np.zeros(len(tables))
        return np.array(
            [c * mode_cap(t) if t[X.TORQUE_ENABLE] else 0.0 for c, t in zip(self.compliance, tables, strict=True)]
        )

    def jam(self, k: int, at: float) -> None:
        """Shaft k jams at reported position `at` (ticks): it moves no more either way."""
        self.jammed[k] = at

    def cut(self, k: int) -> None:
        """Shaft k's tendon is cut: it carries no load."""
        self.load[k] = 0.0

    def hold(self, x: np.ndarray) -> np.ndarray:
        """Positions `x` with the jammed shafts held where they jammed."""
        return np.where(np.isnan(self.jammed), x, self.jammed)

    def current(self, t: bytearray, k: int, reference: float, x: float, blocked: bool) -> int:
        """Present Current (units) of servo k with control table `t` at position `x` following `reference`
        (ticks); `blocked`: the shaft cannot follow (a stop or a jam)."""
        if not t[X.TORQUE_ENABLE]:
            return 0
        demand = self.load[k]
        if blocked or not np.isnan(self.jammed[k]):
            gain = struct.unpack_from("<H", t, X.POSITION_P_GAIN)[0] / 128.0
            demand += gain * (reference - x)
        cap = mode_cap(t)
        return int(np.clip(np.rint(demand), -cap, cap))


class ChainFaults:
    """The fault injections of a `ServoChain` (its ids, control tables, positions, loads, `advance` and
    `_torque`, which the chain defines)."""

    ids: tuple[int, ...]
    loads: ShaftLoads
    _table: list[bytearray]
    _x: Any  # numpy array of reported positions (ticks)

    def set_hardware_error(self, dxl_id: int, bits: int, now: float = 0.0) -> None:
        """Error-bit fault: set hardware error status bits; the servo turns its torque off (shutdown)."""
        k = self.ids.index(dxl_id)
        self.advance(now)
        self._table[k][X.HARDWARE_ERROR] = bits & 0xFF
        if bits:
            self._torque(k, False, now)

    def jam(self, dxl_id: int, now: float = 0.0) -> None:
        """Jammed-spool fault: the shaft of `dxl_id` stops where it is at `now` and moves no more; its current
        rises with the position loop's error up to its mode's cap (`crtraj.hardware.dynamixel._sim_shaft`)."""
        self.advance(now)
        k = self.ids.index(dxl_id)
        self.loads.jam(k, float(self._x[k]))

    def set_load(self, dxl_id: int, units: float) -> None:
        """The current (signed 2.69 mA units) that holding `dxl_id`'s tendon takes (its pretension)."""
        self.loads.load[self.ids.index(dxl_id)] = float(units)

    def cut(self, dxl_id: int, now: float = 0.0) -> None:
        """Cut-tendon fault: `dxl_id` carries no load from `now` on; its current collapses."""
        self.advance(now)
        self.loads.cut(self.ids.index(dxl_id))

    def heat(self, dxl_id: int, celsius: int, now: float = 0.0) -> None:
        """Temperature fault: Present Temperature (146) of `dxl_id` reads `celsius`; at its Temperature Limit (31)
        the overheating bit is set and, as Shutdown (63) says, the torque goes off."""
        self.advance(now)
        k = self.ids.index(dxl_id)
        self._table[k][X.PRESENT_TEMPERATURE] = int(celsius)
        if celsius > self._table[k][X.TEMPERATURE_LIMIT]:
            self._hardware_fault(k, dxl.HW_OVERHEATING, now)

    def supply(self, volts: float, now: float = 0.0) -> None:
        """Power supply fault: every servo's Present Input Voltage (144) reads `volts`; outside its voltage limits
        (32, 34) the input voltage bit is set and, as Shutdown (63) says, the torque goes off."""
        self.advance(now)
        for k, t in enumerate(self._table):
            struct.pack_into("<H", t, X.PRESENT_VOLTAGE, round(volts * 10))
            hi, lo = struct.unpack_from("<HH", t, X.MAX_VOLTAGE)
            if not lo <= volts * 10 <= hi:
                self._hardware_fault(k, dxl.HW_INPUT_VOLTAGE, now)

    def _hardware_fault(self, k: int, bit: int, now: float) -> None:
        """Set hardware error `bit` of servo k; the torque goes off when Shutdown (63) has the bit."""
        t = self._table[k]
        t[X.HARDWARE_ERROR] |= bit
        if t[X.SHUTDOWN] & bit:
            self._torque(k, False, now)

    def current(self, dxl_id: int, now: float) -> int:
        """Present Current (signed 2.69 mA units) of `dxl_id` at `now`, as the servo would report it."""
        self.advance(now)
        return self._current(self.ids.index(dxl_id))

    def torque_off(self, dxl_id: int, now: float = 0.0) -> None:
        """Torque-off fault: another program (or a person at a servo tool) switches the servo's torque off."""
        self.advance(now)
        self._torque(self.ids.index(dxl_id), False, now)
