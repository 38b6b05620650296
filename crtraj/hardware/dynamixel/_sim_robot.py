"""A robot file's servos as simulated hardware: the mechanism around a `ServoChain`, and its homing.

The chain keeps each shaft's physical position in normal counting (`ServoChain.shaft`). A robot file describes
its actuators by the values the servos *report*: with ``drive_mode = { reverse = true }`` the servo counts
clockwise as positive (ROBOTIS e-manual, Drive Mode bit 0), so the mechanism sees the reported value backwards.
`mounts` is that relation (+1 normal, -1 reversed), and everything physical is placed through it:

- `stops`: each ``hard_stop`` of ``[robot.homing]`` is a mechanical stop where the servo, homed, reports the
  reference, on the side the spec's ``direction`` approaches in reported counting (physically the other side
  for a reversed servo);
- `robot_chain`: the shafts where the servos report the given actuator values (Homing Offset 0), with the
  declared Drive Mode bits already in their EEPROM (a robot set up once keeps them across power-ups).

`home_in_place` then powers the servos up (each reading falls within one turn plus its Homing Offset), runs
crtraj's own homing (`crtraj.hardware.dynamixel.Homer`) through the chain's protocol on a virtual clock, and moves
every servo back to where its shaft stood: afterwards the servos present what a real robot presents after
``crtraj home`` and a move (homed markers lit, Homing Offsets computed by the homing), and it returns the
homing state entries that ``crtraj home`` would have written. Ticks are the servos' encoder ticks; times s.
"""

from __future__ import annotations

import struct
from dataclasses import replace
from typing import Any

import numpy as np

from crtraj.core.clock import VirtualClock
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._homing import Homer
from crtraj.hardware.dynamixel._homing_spec import HomingSpec, read_homing
from crtraj.hardware.dynamixel._homing_state import HomedServo, multi_turn
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.hardware.transport import TransportError

SETTLE_POLL = 0.05  # s of device time between checks that the servos arrived
SETTLE_LIMIT = 3600.0  # s of device time after which a move back counts as stuck


class ChainIO:
    """Register access (`crtraj.hardware.dynamixel._homing_state.ServoIO`) to a `ServoChain` by its own READ and WRITE
    packets at `clock`'s time (s): what the homing needs, without a port or the SDK."""

    def __init__(self, chain: ServoChain, clock: VirtualClock) -> None:
        self.chain, self.clock = chain, clock

    def _status(self, dxl_id: int, instruction: int, params: bytes, what: str) -> bytes:
        """The one status packet's params after its error byte; `TransportError` naming `what` otherwise."""
        replies = self.chain.handle(dxl.Packet(dxl_id, instruction, params), self.clock.now())
        packets = dxl.PacketReader().feed(b"".join(replies))
        error = packets[0].params[0] & ~dxl.ERR_ALERT if len(packets) == 1 and packets[0].params else -1
        if error:
            raise TransportError(f"sim-dynamixel: servo id {dxl_id}: {what} failed (status error {error})")
        return packets[0].params[1:]

    def read(self, dxl_id: int, addr: int, size: int) -> int:
        data = self._status(dxl_id, dxl.READ, struct.pack("<HH", addr, size), f"reading register {addr}")
        return int.from_bytes(data[:size], "little", signed=size > 1)

    def write(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
        data = (int(value) % (1 << (8 * size))).to_bytes(size, "little")
        self._status(dxl_id, dxl.WRITE, struct.pack("<H", addr) + data, f"setting {what}")


def mounts(acts: Actuators) -> np.ndarray:
    """(n,) how the mechanism sees each servo's reported counting: +1 normal, -1 reversed (Drive Mode bit 0)."""
    return np.array([-1.0 if acts.bus.drive_mode(k).reverse else 1.0 for k in range(len(acts.bus.ids))])


def stops(robot: Any, acts: Actuators) -> list[tuple[float, float]]:
    """Mechanical stops (physical ticks, normal counting, Homing Offset 0) of the servos: one where each
    ``hard_stop`` spec's servo reports its reference, blocking the spec's approach ``direction``; none for the
    others. A reversed servo's reported direction is the shaft's opposite one."""
    specs, mount = read_homing(robot, acts), mounts(acts)
    out = []
    for k, name in enumerate(acts.names):
        s = specs.get(name)
        if s is None or s.method != "hard_stop":
            out.append((-np.inf, np.inf))
            continue
        at = mount[k] * float(acts.bus.ticks(np.where(np.arange(acts.n) == k, s.reference, 0.0))[k])
        out.append((at, np.inf) if mount[k] * s.direction < 0 else (-np.inf, at))
    return out


def robot_chain(
    robot: Any, acts: Actuators, values: np.ndarray | None = None, *, preset: bool = True, **kw: Any
) -> ServoChain:
    """The servos of `acts.bus` with their shafts where they report actuator `values` (rad, mm; default 0) once
    their declared Drive Mode reverse bits are set, and the robot's mechanical `stops`. preset: the bits are
    already set (a robot set up before); False: still clear (crtraj sets them at connect, the readings then flip
    to `values`). kw: `ServoChain`'s options."""
    bus, mount = acts.bus, mounts(acts)
    ticks = np.zeros(len(bus.ids)) if values is None else bus.ticks(values).astype(float)
    chain = ServoChain(bus.ids, bus.models, initial=mount * ticks, stops=stops(robot, acts), **kw)
    io = ChainIO(chain, VirtualClock())
    for k, dxl_id in enumerate(bus.ids):
        if preset and mount[k] < 0:  # EEPROM, torque off: the reading flips about the Homing Offset (0) to `ticks`
            io.write(dxl_id, X.DRIVE_MODE, X.DRIVE_REVERSE, 1, "drive mode (reverse bit)")
    return chain


def _index_specs(robot: Any, acts: Actuators, values: np.ndarray) -> dict[str, HomingSpec]:
    """The robot's homing specs, and for each multi-turn actuator without one an index mark where it stands."""
    specs = dict(read_homing(robot, acts))
    for k, name in enumerate(acts.names):
        if multi_turn(acts)[k] and name not in specs:
            specs[name] = HomingSpec(name=name, method="index", reference=float(values[k]))
    return specs


def home_in_place(robot: Any, acts: Actuators, chain: ServoChain, values: np.ndarray) -> tuple[list[HomedServo], float]:
    """Power the servos of a fresh `chain` (device time 0, from `robot_chain`) up, home them with crtraj's `Homer`
    and move them back to actuator `values` (rad, mm, where their shafts stood); the homing state entries and
    the device time (s) reached. A multi-turn actuator without a homing spec is homed as at an index mark where
    it stands (the operator's confirmation given)."""
    clock = VirtualClock()
    chain.power_cycle(clock.now())
    io = ChainIO(chain, clock)
    homed = Homer(io, acts, _index_specs(robot, acts, values), clock, lambda text: True).run()
    bus = acts.bus
    goals = bus.ticks(values)
    moving = [k for k, dxl_id in enumerate(bus.ids) if io.read(dxl_id, X.PRESENT_POSITION, 4) != goals[k]]
    for k in moving:
        io.write(bus.ids[k], X.OPERATING_MODE, X.EXTENDED_POSITION, 1, "extended position mode")
        io.write(bus.ids[k], X.TORQUE_ENABLE, 1, 1, "torque on")
        io.write(bus.ids[k], X.GOAL_POSITION, int(goals[k]), 4, "goal position")
    while any(io.read(bus.ids[k], X.PRESENT_POSITION, 4) != goals[k] for k in moving):
        if clock.now() > SETTLE_LIMIT:
            raise InputError(f"sim-dynamixel: the servos did not reach the start within {SETTLE_LIMIT:g} s")
        clock.sleep(SETTLE_POLL)
    for k in moving:
        io.write(bus.ids[k], X.TORQUE_ENABLE, 0, 1, "torque off")
    return [replace(h, last=io.read(h.id, X.PRESENT_POSITION, 4)) for h in homed], clock.now()
