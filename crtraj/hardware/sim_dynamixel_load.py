"""What a simulated Dynamixel's shaft carries: its tendon, a jam, and the current its motor draws for them.

The current model of `crtraj.hardware.sim_dynamixel.ServoChain`, from the ROBOTIS X-series e-manual:

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

import numpy as np

from crtraj.hardware.dynamixel_protocol import X

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
