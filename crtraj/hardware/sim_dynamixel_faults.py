"""Faults a test injects into a simulated Dynamixel chain (`crtraj.hardware.sim_dynamixel.ServoChain` mixes
them in): a hardware error bit, a torque switched off behind the host's back, a jammed spool, a cut tendon, a hot
servo and a sagging supply, each as the ROBOTIS X-series e-manual describes the servo's reaction. Times are the
chain's device time (s); currents in 2.69 mA units.
"""

from __future__ import annotations

import struct
from typing import Any

from crtraj.hardware import dynamixel_protocol as dxl
from crtraj.hardware.dynamixel_protocol import X


class ChainFaults:
    """The fault injections of a `ServoChain` (its ids, control tables, positions, loads, `advance` and
    `_torque`, which the chain defines)."""

    ids: tuple[int, ...]
    loads: Any  # crtraj.hardware.sim_dynamixel_load.ShaftLoads
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
        rises with the position loop's error up to its mode's cap (`crtraj.hardware.sim_dynamixel_load`)."""
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
